"""Rendering training pairs: noisy and clean clouds through the same cameras and light.

A *renderer* here is any callable ``(points (N,3) f32, normals (N,3) f32, views, spec) ->
(images (V,H,W,3) float32, mask (V,H,W) bool)``. :func:`dss_renderer` is the real one (DSS
splatting under the spec's point light); tests may inject a cheap stand-in.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from .render_spec import RenderSpec, View

__all__ = ["Renderer", "dss_renderer", "render_views", "render_pairs"]

Renderer = Callable[[np.ndarray, np.ndarray, Sequence[View], RenderSpec], tuple[np.ndarray, np.ndarray]]


def dss_renderer(points: np.ndarray, normals: np.ndarray, views: Sequence[View], spec: RenderSpec):
    """Render with :func:`dss.render.render` in the spec's channel (its point light, or planes).

    All views are rendered in one batch when they share the light position (the usual case),
    otherwise one view at a time with its own light.
    """
    import torch

    from dss.render import render

    pts = torch.from_numpy(np.ascontiguousarray(points, np.float32))
    nrm = torch.from_numpy(np.ascontiguousarray(normals, np.float32))
    settings = spec.render_settings()
    groups: dict[tuple, list[int]] = {}
    for i, v in enumerate(views):
        groups.setdefault(tuple(v.light), []).append(i)
    H, W = spec.image_size
    images = np.zeros((len(views), H, W, 3), np.float32)
    mask = np.zeros((len(views), H, W), bool)
    with torch.no_grad():
        for light, idx in groups.items():
            cams = spec.cameras([views[i] for i in idx])
            out = render(pts, nrm, cams, settings, shading=spec.shader(light), backend=spec.backend)
            images[idx] = out.images.numpy()
            mask[idx] = out.mask.numpy()
    return images, mask


def render_views(points, normals, views: Sequence[View], spec: RenderSpec, renderer: Renderer | None = None):
    """Images (V, H, W, 3) float32 and mask (V, H, W) of one cloud from ``views``."""
    renderer = renderer or dss_renderer
    images, mask = renderer(points, normals, views, spec)
    H, W = spec.image_size
    images = np.asarray(images, np.float32)
    mask = np.asarray(mask, bool)
    if images.shape != (len(views), H, W, 3) or mask.shape != (len(views), H, W):
        raise ValueError(f"renderer returned images {images.shape} / mask {mask.shape}, "
                         f"expected ({len(views)}, {H}, {W}, 3) / ({len(views)}, {H}, {W})")
    return images, mask


def render_pairs(clean_points, clean_normals, noisy_points, noisy_normals, views: Sequence[View], spec: RenderSpec,
                 renderer: Renderer | None = None, clean_render=None) -> dict[str, np.ndarray]:
    """Noisy and clean renders of the same ``views`` (identical cameras and light).

    ``clean_render`` = (images, mask) reuses a clean render of these views (it does not depend on
    the noise level). Returns ``noisy``, ``clean`` (V, H, W, 3) float32 and ``mask`` (V, H, W):
    pixels covered in either render.
    """
    if clean_render is None:
        clean_render = render_views(clean_points, clean_normals, views, spec, renderer)
    clean, clean_mask = clean_render
    noisy, noisy_mask = render_views(noisy_points, noisy_normals, views, spec, renderer)
    return {"noisy": noisy, "clean": clean, "mask": clean_mask | noisy_mask}
