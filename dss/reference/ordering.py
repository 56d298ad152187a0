"""Z-order (Morton) sorting in torch: the twin of the kernels' ``morton_order``
(dss/csrc/ordering_cpu.cpp: the same codes, a radix sort)."""

from __future__ import annotations

import torch

__all__ = ["morton_order", "morton_codes"]


def _spread3(x: torch.Tensor) -> torch.Tensor:
    """Interleave the low 10 bits of x (int64): bit b moves to bit 3b (magic-number spreading)."""
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    return (x | (x << 2)) & 0x09249249


def morton_codes(points: torch.Tensor) -> torch.Tensor:
    """(N, 3) positions -> (N,) int64 Z-order codes on a 1024^3 grid over the bounding box."""
    p = points.detach()
    lo = p.min(dim=0).values
    ext = (p.max(dim=0).values - lo).clamp_min(1e-30)
    q = ((p - lo) * (1023.0 / ext)).to(torch.int64).clamp_(0, 1023)
    return _spread3(q[:, 0]) | (_spread3(q[:, 1]) << 1) | (_spread3(q[:, 2]) << 2)


def morton_order(points: torch.Tensor) -> torch.Tensor:
    """(N,) int64 permutation that sorts ``points`` (N, 3) by :func:`morton_codes`, stably."""
    return torch.argsort(morton_codes(points), stable=True)
