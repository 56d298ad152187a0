"""Stage 2 of rendering: per pixel, the K front-most splats (the top-K cache of the paper).

One contract, three implementations: the C++/OpenMP kernel (``cpp``), the tile-binned CUDA
kernels (``cuda``), both ``rasterize_forward`` (dss/csrc/rasterize_*.c*), and their torch twin
(``reference``, :func:`dss.reference.rasterize` and :func:`dss.reference.blend_cached`). All
read the packed splats of :func:`dss.reference.project_splats` (or its kernel) and return a
:class:`dss.fragments.Fragments` cache with entries ordered by (depth, point index), so every
backend gives the same cache.
"""

from __future__ import annotations

import torch

from . import reference
from .backends import kernels
from .fragments import Fragments
from .splats import Splats

__all__ = ["rasterize"]


def rasterize(splats: Splats, image_size, K: int, cutoff: float, merge_threshold: float, backend: str,
              attributes: torch.Tensor | None = None, background: torch.Tensor | None = None):
    """The top-K cache, plus the blended image when ``attributes`` is given.

    Args:
        splats: V views of N splats (packed (V, N, 10)); read detached.
        image_size: (H, W).
        backend: "cpp", "cuda" or "reference" (a concrete one: :func:`dss.backends.resolve_backend`).
        attributes: (V, N, C) per-view point attributes, or None.
        background: (C,) value of empty pixels (zeros when None).

    Returns:
        (fragments, images (V, H, W, C) or None when ``attributes`` is None, mask (V, H, W) bool).
    """
    packed = splats.packed.detach()
    H, W = image_size
    if backend in ("cpp", "cuda"):
        mod = kernels(backend)
        dev = packed.device
        attrs = attributes.detach().float() if attributes is not None else torch.empty(0, device=dev)
        bg = background if background is not None else torch.zeros(attrs.shape[-1] if attrs.numel() else 0, device=dev)
        idx, depth, rho, images, mask = mod.rasterize_forward(packed.float(), attrs, H, W, K, float(cutoff), float(merge_threshold), bg.float())
        frags = Fragments(idx, depth, rho, float(merge_threshold))
        return frags, (images if attributes is not None else None), mask
    frags = reference.rasterize(splats, image_size, K, cutoff, merge_threshold)
    if attributes is None:
        return frags, None, frags.visible.any(-1) & (torch.where(frags.visible, frags.rho, 0).sum(-1) > 0)
    images, mask = reference.blend_cached(frags, attributes.detach(), background)
    return frags, images, mask
