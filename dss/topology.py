"""Openings of a point cloud counted as holes in its silhouettes (a topology check for
shape-from-rendering).

A shape with an opening (a torus, a handle, the gap between a limb and the body) shows it as a
hole in its silhouette from the views that look through it; a membrane spanning the opening
fills that hole. :func:`silhouette_holes` counts such holes in orthographic silhouettes from a
fixed set of directions, and :func:`openings` compares a result with its target view by view, so
that a filled opening is a number.

Robust to speckle by construction: each point is drawn as a disk (the silhouette of a ball;
normals play no part, so noisy normals change nothing) whose radius follows the local sampling
as a splat's does: ``spacing_factor`` x the point's mean distance to its 8 nearest neighbours
(capped at 3x the median, like :func:`dss.splats.auto_sigma`), at least ``point_radius``. So the
gaps an uneven sampling leaves (a sparse patch of an optimised surface renders closed, and is
drawn closed) are covered, and a hole counts only when it holds a disk of ``min_hole_radius``
(its largest inscribed radius, from a distance transform), so slits and pinholes do not count.
Measured on the yoga figure (``dss-deform scene=cube_yoga``): with fixed disks the sparse patches
of a result showed up to 4 "openings" against the target's 2; with these disks 1 or 2, as the
renders show.

Units: the points are taken as given, in units where the object's bounding-box diagonal is 1 (the
apps normalise); lengths (``pixel``, ``point_radius``, ``min_hole_radius``) are in those units.
Opposite directions give mirrored orthographic silhouettes, so the view set is a hemisphere.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["view_directions", "silhouette_masks", "silhouette_holes", "local_radii", "openings"]


def view_directions(n: int = 32) -> np.ndarray:
    """``n`` unit directions spread over the upper hemisphere (z >= 0), Fibonacci spiral. (n, 3)"""
    if n <= 0:
        raise ValueError(f"need at least one view direction, got {n}")
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - i / n  # (0, 1]: heights uniform in area on the hemisphere
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def _basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane orthogonal to ``d``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(d, a)
    u /= np.linalg.norm(u)
    return u, np.cross(d, u)


def local_radii(points: Any, point_radius: float = 0.008, spacing_factor: float = 0.9, k: int = 8,
                cap: float = 3.0) -> np.ndarray:
    """Disk radius per point: ``spacing_factor`` x its mean distance to its ``k`` nearest
    neighbours, capped at ``cap`` x the median of that, at least ``point_radius``. (N,)"""
    from scipy.spatial import cKDTree

    p = _array(points)
    if spacing_factor <= 0 or len(p) < 2:
        return np.full(len(p), float(point_radius))
    k = min(k, len(p) - 1)
    d, _ = cKDTree(p).query(p, k=k + 1)
    m = d[:, 1:].mean(1)
    m = np.minimum(m, cap * np.median(m))
    return np.maximum(float(point_radius), spacing_factor * m)


def _array(x: Any) -> np.ndarray:
    return np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64)


def silhouette_masks(points: Any, directions: np.ndarray, pixel: float = 0.004,
                     point_radius: float | np.ndarray = 0.008, extent: float | None = None) -> np.ndarray:
    """Orthographic silhouettes of the union of disks of ``point_radius`` around the points.

    Args:
        points: (N, 3); directions: (V, 3) view directions; point_radius: one radius or (N,)
            radii (drawn to the nearest half pixel).
        pixel: pixel size; extent: half width of the square image (default: the points' farthest
            distance from their bounding-box centre, plus two radii).
    Returns:
        (V, S, S) bool masks (S = 2 * extent / pixel, rounded up).
    """
    from scipy.ndimage import binary_dilation

    p = _array(points)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"points must be a non-empty (N, 3) array, got shape {p.shape}")
    radius = np.broadcast_to(np.asarray(point_radius, dtype=np.float64), (len(p),))
    c = (p.max(0) + p.min(0)) / 2
    p = p - c
    if extent is None:
        extent = float(np.linalg.norm(p, axis=1).max()) + 2 * float(radius.max())
    size = int(math.ceil(2 * extent / pixel))
    r_px = np.round(radius / pixel * 2) / 2  # half-pixel steps: a few dilations per view
    groups = [(r, r_px == r) for r in np.unique(r_px)]
    masks = np.zeros((len(directions), size, size), dtype=bool)
    for v, d in enumerate(np.asarray(directions, dtype=np.float64)):
        d = d / np.linalg.norm(d)
        u, w = _basis(d)
        j = np.floor((p @ u + extent) / pixel).astype(np.int64)
        i = np.floor((p @ w + extent) / pixel).astype(np.int64)
        ok = (i >= 0) & (i < size) & (j >= 0) & (j < size)
        for r, sel in groups:
            centres = np.zeros((size, size), dtype=bool)
            centres[i[ok & sel], j[ok & sel]] = True
            ri = int(math.ceil(r))
            yy, xx = np.mgrid[-ri:ri + 1, -ri:ri + 1]
            masks[v] |= binary_dilation(centres, structure=(xx ** 2 + yy ** 2) <= r ** 2 + 1e-9)
    return masks


def _count_holes(mask: np.ndarray, min_radius_px: float) -> int:
    """Background components that do not touch the image border and hold a disk of
    ``min_radius_px`` (their distance transform's maximum)."""
    from scipy.ndimage import distance_transform_edt, label

    bg = ~mask
    lab, n = label(bg)
    if n == 0:
        return 0
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    dist = distance_transform_edt(np.pad(bg, 1, constant_values=False))[1:-1, 1:-1]
    depth = np.zeros(n + 1)
    np.maximum.at(depth, lab.ravel(), dist.ravel())
    keep = depth >= min_radius_px
    keep[0] = False
    keep[border] = False
    return int(keep.sum())


def silhouette_holes(points: Any, directions: np.ndarray | None = None, pixel: float = 0.004,
                     point_radius: float = 0.008, min_hole_radius: float = 0.012,
                     extent: float | None = None, spacing_factor: float = 0.9) -> np.ndarray:
    """Number of holes in each silhouette of the points (see the module docstring; disks of
    :func:`local_radii`, fixed ones of ``point_radius`` with ``spacing_factor`` 0). (V,) int"""
    dirs = view_directions() if directions is None else np.asarray(directions, dtype=np.float64)
    masks = silhouette_masks(points, dirs, pixel, local_radii(points, point_radius, spacing_factor), extent)
    return np.array([_count_holes(m, min_hole_radius / pixel) for m in masks], dtype=np.int64)


def openings(result: Any, target: Any, directions: np.ndarray | None = None, pixel: float = 0.004,
             point_radius: float = 0.008, min_hole_radius: float = 0.012, spacing_factor: float = 0.9) -> dict:
    """Silhouette holes of ``result`` against ``target`` through the same views.

    Returns ``openings`` / ``openings_target``: the most holes any one view shows (a torus: 1, a
    sphere: 0; a figure whose two openings face the same way: 2); ``views_missing_holes``: views
    where the result shows fewer holes than the target (an opening filled, seen from there);
    ``views_extra_holes``: views with more (the result torn where the target is closed);
    ``holes_total`` / ``holes_total_target``: the holes summed over the views (an opening seen
    from fewer views, e.g. half closed, lowers it); ``holes`` / ``holes_target``: the per-view
    counts; and the settings used.
    Both clouds are framed alike: the same image extent, each centred on its own bounding box,
    each drawn with its own :func:`local_radii`.
    """
    dirs = view_directions() if directions is None else np.asarray(directions, dtype=np.float64)
    r, t = _array(result), _array(target)
    rr, rt = local_radii(r, point_radius, spacing_factor), local_radii(t, point_radius, spacing_factor)
    ext = max(float(np.linalg.norm(q - (q.max(0) + q.min(0)) / 2, axis=1).max()) + 2 * float(rad.max())
              for q, rad in ((r, rr), (t, rt)))
    masks_r = silhouette_masks(r, dirs, pixel, rr, ext)
    masks_t = silhouette_masks(t, dirs, pixel, rt, ext)
    hr = np.array([_count_holes(m, min_hole_radius / pixel) for m in masks_r], dtype=np.int64)
    ht = np.array([_count_holes(m, min_hole_radius / pixel) for m in masks_t], dtype=np.int64)
    return {
        "openings": int(hr.max()),
        "openings_target": int(ht.max()),
        "views_missing_holes": int((hr < ht).sum()),
        "views_extra_holes": int((hr > ht).sum()),
        "holes_total": int(hr.sum()),
        "holes_total_target": int(ht.sum()),
        "views": len(dirs),
        "holes": hr.tolist(),
        "holes_target": ht.tolist(),
        "settings": {"pixel": pixel, "point_radius": point_radius, "min_hole_radius": min_hole_radius,
                     "spacing_factor": spacing_factor, "median_radius": float(np.median(rr)),
                     "median_radius_target": float(np.median(rt)),
                     "projection": "orthographic, hemisphere of Fibonacci directions"},
    }
