"""Visual-hull pull for shape-from-rendering (an option beyond the paper).

Every point of the true surface projects inside the reference's silhouette in every view. A point
that projects onto reference background in some view is outside the visual hull, whatever its
colour, so it can be moved toward the silhouette directly. This is what the image gradient of
Eq. gradP cannot do for a membrane spanning a hole (the teapot's handle) or the webbing under a
spout: inside such a membrane every pixel is covered by several splats, so moving any one splat
changes no pixel and its visibility gradient is zero. The official DSS code scores points by
their screen distance to the reference silhouette for the same reason (``removeOutlier``).

Units: pixel coordinates follow :meth:`dss.cameras.Cameras.project` (pixel (i, j) has its centre
at u = j + 0.5, v = i + 0.5); displacements are returned in world units.
"""

from __future__ import annotations

import numpy as np
import torch

from .cameras import Cameras

__all__ = ["nearest_covered", "hull_displacement", "fill_displacement"]


def nearest_covered(mask: torch.Tensor) -> torch.Tensor:
    """Centre (u, v) of the nearest covered pixel, for every pixel.

    Args:
        mask: (V, H, W) bool, the reference's coverage.
    Returns:
        (V, H, W, 2) float32 pixel coordinates; a covered pixel maps to its own centre; a view
        with no covered pixel maps to NaN (no pull from it).
    """
    from scipy.ndimage import distance_transform_edt

    m = mask.detach().cpu().numpy().astype(bool)
    out = np.full(m.shape + (2,), np.nan, dtype=np.float32)
    for v in range(m.shape[0]):
        if m[v].any():
            _, (ii, jj) = distance_transform_edt(~m[v], return_indices=True)
            out[v, ..., 0] = jj + 0.5
            out[v, ..., 1] = ii + 0.5
    return torch.from_numpy(out).to(mask.device)


def hull_displacement(points: torch.Tensor, cameras: Cameras, mask: torch.Tensor,
                      nearest: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World displacement that moves each point onto the silhouette in the views it violates.

    For each view where a point (in front of the camera, inside the image) projects onto an
    uncovered pixel, the screen offset to the nearest covered pixel centre is lifted to the
    point's depth (a move parallel to the image plane); the offsets are averaged over those views.

    Args:
        points: (N, 3) world positions.
        cameras: the V cameras of ``mask``.
        mask: (V, H, W) bool reference coverage; nearest: its :func:`nearest_covered`.
    Returns:
        displacement (N, 3) in world units (zero for points inside every silhouette) and the
        (N,) number of views each point violates.
    """
    H, W = cameras.image_size
    uv, z = cameras.project(points.detach())
    j, i = uv[..., 0].floor().long(), uv[..., 1].floor().long()
    # only what a view sees counts: a point off the image (a close-up error-aware view) violates
    # nothing there
    seen = (z > 0) & (i >= 0) & (i < H) & (j >= 0) & (j < W)
    i, j = i.clamp(0, H - 1), j.clamp(0, W - 1)
    vidx = torch.arange(len(cameras), device=points.device)[:, None].expand_as(i)
    target = nearest[vidx, i, j]  # (V, N, 2)
    outside = seen & ~mask[vidx, i, j] & torch.isfinite(target).all(-1)
    d_uv = torch.where(outside[..., None], target - uv, torch.zeros_like(uv))
    scale = (z.clamp_min(1e-9) / cameras.focal[:, None])[..., None]  # pixels -> camera units at depth z
    d_cam = torch.cat([d_uv * scale, torch.zeros_like(z)[..., None]], -1)
    d_world = torch.einsum("vji,vnj->vni", cameras.R, d_cam)  # R^T: camera -> world directions
    count = outside.sum(0)
    return d_world.sum(0) / count.clamp_min(1)[:, None].to(d_world.dtype), count


def fill_displacement(points: torch.Tensor, cameras: Cameras, target_mask: torch.Tensor,
                      rendered_mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World displacement that pulls points toward reference pixels the render leaves empty.

    The counterpart of :func:`hull_displacement` (a one-sided 2D Chamfer from the reference's
    silhouette to the projected points): every pixel covered in the reference but not in the
    render pulls the point (in front of the camera) that projects nearest to it toward its centre,
    parallel to the image plane; a point's pulls are averaged over its pixels and views. Thin
    parts far from the current surface (a handle's ring) are what the visibility gradient's
    window does not reach.

    Args:
        points: (N, 3); cameras: V cameras; target_mask, rendered_mask: (V, H, W) bool.
    Returns:
        displacement (N, 3) in world units and the (N,) number of pixels pulling each point.
    """
    uv, z = cameras.project(points.detach())
    N = points.shape[0]
    total = torch.zeros(N, 3, dtype=points.dtype, device=points.device)
    count = torch.zeros(N, dtype=torch.long, device=points.device)
    for v in range(len(cameras)):
        empty = torch.nonzero(target_mask[v] & ~rendered_mask[v])
        front = torch.nonzero(z[v] > 0).squeeze(1)
        if len(empty) == 0 or len(front) == 0:
            continue
        centres = torch.stack([empty[:, 1], empty[:, 0]], -1).to(uv.dtype) + 0.5  # (M, 2) as (u, v)
        nearest = front[torch.cdist(centres, uv[v, front]).argmin(1)]  # (M,)
        d_uv = centres - uv[v, nearest]
        scale = (z[v, nearest] / cameras.focal[v])[:, None]
        d_cam = torch.cat([d_uv * scale, torch.zeros_like(scale)], -1)
        total.index_add_(0, nearest, d_cam @ cameras.R[v])  # row-vector form of R^T d
        count.index_add_(0, nearest, torch.ones_like(nearest))
    return total / count.clamp_min(1)[:, None].to(total.dtype), count
