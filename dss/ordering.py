"""Spatial (Morton / Z-order) ordering of points, for memory locality in the kernels.

The CPU kernels walk points in index order and touch, for each point, the pixels around its
splat in every view. When consecutive points are neighbours in space, they are neighbours on
screen in every view, and those pixels stay in cache. Point clouds from files or samplers come in
arbitrary order; :func:`dss.render.render` therefore renders a Morton-sorted copy and returns
everything in the caller's order. Measured on the shipped example (20K points, 12 views,
256 px, one thread, ``python -m experiments.bench_render --order``): forward 1.7x, position
backward 2.2x, normal backward 1.9x faster than in the file's order.
"""

from __future__ import annotations

import torch

__all__ = ["morton_codes", "spatial_order", "SORT_MIN_POINTS"]

#: below this many points the sort costs more than it saves (everything fits in cache)
SORT_MIN_POINTS = 2048


def _spread3(x: torch.Tensor, bits: int) -> torch.Tensor:
    """Interleave: bit b of x goes to bit 3b of the result (int64)."""
    out = torch.zeros_like(x)
    for b in range(bits):
        out |= ((x >> b) & 1) << (3 * b)
    return out


def morton_codes(points: torch.Tensor, bits: int = 10) -> torch.Tensor:
    """(N, 3) positions -> (N,) int64 Z-order codes on a 2^bits grid over the bounding box."""
    p = points.detach().to(torch.float64)
    lo = p.min(dim=0).values
    ext = (p.max(dim=0).values - lo).clamp_min(1e-30)
    q = ((p - lo) / ext * (2**bits - 1)).round().to(torch.int64).clamp(0, 2**bits - 1)
    return _spread3(q[:, 0], bits) | (_spread3(q[:, 1], bits) << 1) | (_spread3(q[:, 2], bits) << 2)


def spatial_order(points: torch.Tensor, bits: int = 10) -> torch.Tensor:
    """(N,) int64 permutation that sorts ``points`` along the Z-order curve (stable)."""
    return torch.argsort(morton_codes(points, bits), stable=True)
