"""Small signed-distance toolkit on a regular grid (numpy, float32).

Every family builds a scalar field ``f`` on the grid returned by :func:`grid`, negative inside
the solid and positive outside, and :func:`data_prep.shapes.meshing.mesh_from_field` turns its
zero level set into a triangle mesh with marching cubes. The fields need not be exact distances
(a level-set function is enough for marching cubes), but they should be roughly 1-Lipschitz near
the surface so that the linear interpolation along grid edges places vertices well.

Coordinates: the grid spans the cube [-1, 1]^3; shapes are built to fit in [-0.9, 0.9]^3 so a
layer of outside cells always surrounds them (the level set is closed inside the grid, hence the
mesh is watertight by construction).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "Grid",
    "grid",
    "smin",
    "smax",
    "sphere",
    "ellipsoid",
    "box",
    "capsule",
    "cylinder_z",
    "torus_z",
    "polygon_sdf_2d",
    "polygon_field_2d",
    "sample_2d_field",
    "rotation_matrix",
    "random_rotation",
    "rotate",
    "Fit",
]

EXTENT = 1.0  # the grid spans [-EXTENT, EXTENT]^3


@dataclass
class Grid:
    """A regular grid of ``res``^3 nodes over [-1, 1]^3. ``x, y, z``: (res, res, res) float32."""

    res: int
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray

    @property
    def spacing(self) -> float:
        return 2.0 * EXTENT / (self.res - 1)

    @property
    def origin(self) -> float:
        return -EXTENT


def grid(res: int) -> Grid:
    """The (res, res, res) node grid over [-1, 1]^3 (``indexing='ij'``: axis 0 is x)."""
    if res < 16:
        raise ValueError(f"grid resolution must be >= 16, got {res}")
    c = np.linspace(-EXTENT, EXTENT, res, dtype=np.float32)
    x, y, z = np.meshgrid(c, c, c, indexing="ij")
    return Grid(res, x, y, z)


def smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth union (Quilez); ``k`` is the blend width in world units (0: plain min)."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.clip(k - np.abs(a - b), 0.0, None) / k
    return np.minimum(a, b) - h * h * k * 0.25


def smax(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Smooth intersection / subtraction helper: ``smax(a, b) = -smin(-a, -b)``."""
    return -smin(-a, -b, k)


def sphere(x, y, z, center, r):
    cx, cy, cz = center
    return np.sqrt((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2) - r


def ellipsoid(x, y, z, radii):
    """Approximate ellipsoid distance (Quilez' bound): good near the surface."""
    a, b, c = radii
    k0 = np.sqrt((x / a) ** 2 + (y / b) ** 2 + (z / c) ** 2)
    k1 = np.sqrt((x / a**2) ** 2 + (y / b**2) ** 2 + (z / c**2) ** 2)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


def box(x, y, z, center, half, radius: float = 0.0):
    """Rounded axis-aligned box: ``half`` are half extents (before rounding), ``radius`` rounds edges."""
    qx = np.abs(x - center[0]) - (half[0] - radius)
    qy = np.abs(y - center[1]) - (half[1] - radius)
    qz = np.abs(z - center[2]) - (half[2] - radius)
    outside = np.sqrt(np.maximum(qx, 0) ** 2 + np.maximum(qy, 0) ** 2 + np.maximum(qz, 0) ** 2)
    inside = np.minimum(np.maximum(qx, np.maximum(qy, qz)), 0)
    return outside + inside - radius


def capsule(x, y, z, a, b, r, r_b: float | None = None):
    """Capsule (or cone-capsule when ``r_b`` differs) from point ``a`` to ``b`` of radius ``r``."""
    a = np.asarray(a, np.float32)
    b = np.asarray(b, np.float32)
    ba = b - a
    denom = float(ba @ ba) or 1e-12
    pax, pay, paz = x - a[0], y - a[1], z - a[2]
    h = np.clip((pax * ba[0] + pay * ba[1] + paz * ba[2]) / denom, 0.0, 1.0)
    d = np.sqrt((pax - ba[0] * h) ** 2 + (pay - ba[1] * h) ** 2 + (paz - ba[2] * h) ** 2)
    rr = r if r_b is None else r + (r_b - r) * h
    return d - rr


def cylinder_z(x, y, z, center, r, half_h):
    """Capped cylinder along z."""
    dr = np.sqrt((x - center[0]) ** 2 + (y - center[1]) ** 2) - r
    dz = np.abs(z - center[2]) - half_h
    return np.minimum(np.maximum(dr, dz), 0) + np.sqrt(np.maximum(dr, 0) ** 2 + np.maximum(dz, 0) ** 2)


def torus_z(x, y, z, R, r):
    q = np.sqrt(x**2 + y**2) - R
    return np.sqrt(q**2 + z**2) - r


def polygon_sdf_2d(px: np.ndarray, py: np.ndarray, poly: np.ndarray, step: float = 0.002,
                   max_dist: float | None = None) -> np.ndarray:
    """Signed distance of points (px, py) to the closed polygon ``poly`` (M, 2), negative inside.

    The distance is to the boundary densified to ``step`` (error below ``step / 2``, far below a
    voxel); the sign comes from an even-odd inside test (matplotlib's Path).
    """
    from matplotlib.path import Path
    from scipy.spatial import cKDTree

    poly = np.asarray(poly, np.float64)
    a = poly
    b = np.roll(poly, -1, axis=0)
    seg = np.linalg.norm(b - a, axis=1)
    dense = []
    for (pa, pb, L) in zip(a, b, seg):
        n = max(1, int(np.ceil(L / step)))
        t = np.arange(n)[:, None] / n
        dense.append(pa + (pb - pa) * t)
    dense = np.concatenate(dense)
    q = np.stack([np.ravel(px), np.ravel(py)], 1).astype(np.float64)
    bound = np.inf if max_dist is None else float(max_dist)
    d, _ = cKDTree(dense).query(q, k=1, workers=1, distance_upper_bound=bound)
    d = np.minimum(d, bound)
    inside = Path(poly).contains_points(q)
    return np.where(inside, -d, d).reshape(np.shape(px))


def polygon_field_2d(poly: np.ndarray, lo: float = -1.0, hi: float = 1.0, n: int = 256,
                     max_dist: float | None = None) -> np.ndarray:
    """Tabulate :func:`polygon_sdf_2d` on an (n, n) grid over [lo, hi]^2 (axis 0 is u)."""
    c = np.linspace(lo, hi, n)
    u, v = np.meshgrid(c, c, indexing="ij")
    return polygon_sdf_2d(u, v, poly, max_dist=max_dist).astype(np.float32)


def sample_2d_field(field: np.ndarray, lo: tuple[float, float], hi: tuple[float, float],
                    u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinearly sample a 2D field tabulated on a regular grid over [lo, hi] at (u, v).

    Points outside the table are clamped to its border (tables are made large enough that this
    only happens far from the surface).
    """
    from scipy.ndimage import map_coordinates

    n0, n1 = field.shape
    iu = (np.asarray(u, np.float32) - lo[0]) / (hi[0] - lo[0]) * (n0 - 1)
    iv = (np.asarray(v, np.float32) - lo[1]) / (hi[1] - lo[1]) * (n1 - 1)
    coords = np.stack([iu.ravel(), iv.ravel()])
    out = map_coordinates(field.astype(np.float32), coords, order=1, mode="nearest")
    return out.reshape(np.shape(u)).astype(np.float32)


def rotation_matrix(axis, angle: float) -> np.ndarray:
    """(3, 3) rotation about ``axis`` by ``angle`` radians (Rodrigues)."""
    axis = np.asarray(axis, np.float64)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly random (3, 3) rotation (QR of a Gaussian matrix with sign fix)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def rotate(x, y, z, rot: np.ndarray):
    """Coordinates of the grid in a frame rotated by ``rot`` (i.e. apply ``rot.T`` to points).

    Evaluating a field at ``rotate(x, y, z, rot)`` rotates the *shape* by ``rot``.
    """
    r = rot.T.astype(np.float32)
    return (r[0, 0] * x + r[0, 1] * y + r[0, 2] * z,
            r[1, 0] * x + r[1, 1] * y + r[1, 2] * z,
            r[2, 0] * x + r[2, 1] * y + r[2, 2] * z)


class Fit:
    """Model coordinates for the grid so that the model box [lo, hi] fills [-margin, margin]^3.

    Build a field in model units on ``fit.x, fit.y, fit.z`` and return ``fit.to_grid(f)``: the
    shape keeps its proportions, is centred, and its longest side spans ``2 * margin``.
    """

    def __init__(self, g: Grid, lo, hi, margin: float = 0.88):
        lo = np.asarray(lo, np.float64)
        hi = np.asarray(hi, np.float64)
        self.scale = float(2 * margin / np.max(hi - lo))
        c = (lo + hi) / 2
        s = np.float32(1.0 / self.scale)
        self.x = g.x * s + np.float32(c[0])
        self.y = g.y * s + np.float32(c[1])
        self.z = g.z * s + np.float32(c[2])
        self.spacing = g.spacing / self.scale  # grid spacing in model units

    def to_grid(self, f: np.ndarray) -> np.ndarray:
        return (f * np.float32(self.scale)).astype(np.float32)
