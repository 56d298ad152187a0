"""Openings of a point cloud counted as holes in its silhouettes (a topology check for
shape-from-rendering).

A shape with an opening (a torus, a handle, the gap between a limb and the body) shows it as a
hole in its silhouette from the views that look through it; a membrane spanning the opening
fills that hole. :func:`silhouette_holes` counts such holes in orthographic silhouettes from a
fixed set of directions, and :func:`openings` compares a result with its target view by view, so
that a filled opening is a number.

Robust to speckle by construction: each point is drawn as a disk of ``point_radius`` (the
silhouette of a ball; normals play no part, so noisy normals change nothing), the gaps a sparse
or uneven sampling leaves between such disks are far narrower than an opening, and a hole counts
only when it holds a disk of ``min_hole_radius`` (its largest inscribed radius, from a distance
transform), so slits and pinholes do not count.

Sparse clouds: the disks grow with the sampling, to ``spacing_factor`` x the clouds' mean
nearest-neighbour distance where that exceeds ``point_radius`` (an 800-point sphere is no sieve),
so openings narrower than about twice that stay unresolved.

Units: the points are taken as given, in units where the object's bounding-box diagonal is 1 (the
apps normalise); lengths (``pixel``, ``point_radius``, ``min_hole_radius``) are in those units.
Opposite directions give mirrored orthographic silhouettes, so the view set is a hemisphere.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["view_directions", "silhouette_masks", "silhouette_holes", "mean_spacing", "openings"]


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


def silhouette_masks(points: Any, directions: np.ndarray, pixel: float = 0.004,
                     point_radius: float = 0.008, extent: float | None = None) -> np.ndarray:
    """Orthographic silhouettes of the union of disks of ``point_radius`` around the points.

    Args:
        points: (N, 3); directions: (V, 3) view directions.
        pixel: pixel size; extent: half width of the square image (default: the points' farthest
            distance from their bounding-box centre, plus two radii).
    Returns:
        (V, S, S) bool masks (S = 2 * extent / pixel, rounded up).
    """
    from scipy.ndimage import binary_dilation

    p = np.asarray(points.detach().cpu() if hasattr(points, "detach") else points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"points must be a non-empty (N, 3) array, got shape {p.shape}")
    c = (p.max(0) + p.min(0)) / 2
    p = p - c
    if extent is None:
        extent = float(np.linalg.norm(p, axis=1).max()) + 2 * point_radius
    size = int(math.ceil(2 * extent / pixel))
    r_px = point_radius / pixel
    ri = int(math.ceil(r_px))
    yy, xx = np.mgrid[-ri:ri + 1, -ri:ri + 1]
    disk = (xx ** 2 + yy ** 2) <= r_px ** 2 + 1e-9
    masks = np.zeros((len(directions), size, size), dtype=bool)
    for v, d in enumerate(np.asarray(directions, dtype=np.float64)):
        d = d / np.linalg.norm(d)
        u, w = _basis(d)
        j = np.floor((p @ u + extent) / pixel).astype(np.int64)
        i = np.floor((p @ w + extent) / pixel).astype(np.int64)
        ok = (i >= 0) & (i < size) & (j >= 0) & (j < size)
        masks[v, i[ok], j[ok]] = True
        masks[v] = binary_dilation(masks[v], structure=disk)
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
                     extent: float | None = None) -> np.ndarray:
    """Number of holes in each silhouette of the points (see the module docstring). (V,) int"""
    dirs = view_directions() if directions is None else np.asarray(directions, dtype=np.float64)
    masks = silhouette_masks(points, dirs, pixel, point_radius, extent)
    return np.array([_count_holes(m, min_hole_radius / pixel) for m in masks], dtype=np.int64)


def mean_spacing(points: Any) -> float:
    """Mean distance from each point to its nearest neighbour."""
    from scipy.spatial import cKDTree

    p = np.asarray(points.detach().cpu() if hasattr(points, "detach") else points, dtype=np.float64)
    if len(p) < 2:
        return 0.0
    d, _ = cKDTree(p).query(p, k=2)
    return float(d[:, 1].mean())


def openings(result: Any, target: Any, directions: np.ndarray | None = None, pixel: float = 0.004,
             point_radius: float = 0.008, min_hole_radius: float = 0.012, spacing_factor: float = 1.5) -> dict:
    """Silhouette holes of ``result`` against ``target`` through the same views.

    Returns ``openings`` / ``openings_target``: the most holes any one view shows (a torus: 1, a
    sphere: 0; a figure whose two openings face the same way: 2); ``views_missing_holes``: views
    where the result shows fewer holes than the target (an opening filled, seen from there);
    ``views_extra_holes``: views with more (the result torn where the target is closed);
    ``holes`` / ``holes_target``: the per-view counts; and the settings used.
    Both clouds are framed alike: the same image extent, each centred on its own bounding box, and
    drawn with the same disks: ``point_radius``, or ``spacing_factor`` x the sparser cloud's mean
    nearest-neighbour distance where that is larger (``settings`` records the radius used).
    """
    dirs = view_directions() if directions is None else np.asarray(directions, dtype=np.float64)

    def arr(x):
        return np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64)

    r, t = arr(result), arr(target)
    # one disk size for both (the sparser cloud's), so that sampling density alone opens nothing
    point_radius = max(point_radius, spacing_factor * max(mean_spacing(r), mean_spacing(t)))
    ext = max(float(np.linalg.norm(q - (q.max(0) + q.min(0)) / 2, axis=1).max()) for q in (r, t)) + 2 * point_radius
    hr = silhouette_holes(r, dirs, pixel, point_radius, min_hole_radius, ext)
    ht = silhouette_holes(t, dirs, pixel, point_radius, min_hole_radius, ext)
    return {
        "openings": int(hr.max()),
        "openings_target": int(ht.max()),
        "views_missing_holes": int((hr < ht).sum()),
        "views_extra_holes": int((hr > ht).sum()),
        "views": len(dirs),
        "holes": hr.tolist(),
        "holes_target": ht.tolist(),
        "settings": {"pixel": pixel, "point_radius": point_radius, "min_hole_radius": min_hole_radius,
                     "spacing_factor": spacing_factor,
                     "projection": "orthographic, hemisphere of Fibonacci directions"},
    }
