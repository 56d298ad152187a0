"""Screen-space EWA splats: the packed (V, N, 10) layout every rasteriser backend reads, and
the object-space splat size.

The projection that makes them is :func:`dss.reference.project_splats` (torch) and the kernels'
``project_splats_forward`` (:mod:`dss.autograd`); the paper's equations are written out there.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["Splats", "auto_sigma", "SPLAT_FIELDS"]

# Column layout of the packed (V, N, F) splat tensor shared by every rasteriser backend.
SPLAT_FIELDS = ("u", "v", "conic_a", "conic_b2", "conic_c", "norm", "depth", "rx", "ry", "valid")


@dataclass
class Splats:
    """Screen-space splats of N points in V views; every field is (V, N) (``packed``: (V, N, 10)).

    ``u, v``: centre in pixels; ``conic_*``: Sigma^-1 = [[a, b], [b, c]] stored as (a, 2b, c) so that
    ``q = a dx^2 + 2b dx dy + c dy^2``; ``norm``: |det J| / (2 pi sqrt(det Sigma)), the peak weight;
    ``depth``: camera-space z; ``rx, ry``: half extents (pixels) of the cutoff ellipse's bounding box;
    ``valid``: 1 for splats that are rendered (in front of the near plane, front-facing when
    culling), else 0.
    """

    packed: torch.Tensor

    def field(self, name: str) -> torch.Tensor:
        return self.packed[..., SPLAT_FIELDS.index(name)]

    @property
    def valid(self) -> torch.Tensor:
        return self.packed[..., 9] > 0

    def detach(self) -> Splats:
        return Splats(self.packed.detach())


def auto_sigma(points: torch.Tensor, k: int = 8, scale: float = 1.0, max_ratio: float = 3.0) -> torch.Tensor:
    """Per-point object-space splat std from the local point spacing.

    ``sigma_k = scale * mean distance of p_k to its k nearest neighbours`` (N,), capped at
    ``max_ratio`` x the median over points. The cutoff ellipse reaches sqrt(2 C) standard
    deviations, so with the defaults (C = 1, scale = 1) a splat covers its neighbours and a
    uniformly sampled surface renders without holes. The cap keeps isolated points (outliers, or
    points an optimisation step threw off the surface) from becoming discs that cover a large
    part of the image (measured: they wreck sphere -> teapot at larger learning rates).
    """
    from .knn import knn

    N = points.shape[0]
    if N < 2:
        return points.new_full((N,), 1e-2)
    nb = knn(points.detach(), min(k, N - 1), exclude_self=True)
    dist = torch.where(nb.idx >= 0, nb.dist, torch.zeros_like(nb.dist))
    mean = dist.sum(1) / (nb.idx >= 0).sum(1).clamp_min(1)
    if max_ratio is not None and max_ratio > 0:
        mean = torch.minimum(mean, max_ratio * mean.median())
    return (mean * scale).clamp_min(1e-8).to(points.dtype)
