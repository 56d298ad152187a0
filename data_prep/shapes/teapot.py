"""The Utah teapot (Martin Newell, 1975) from its bicubic Bezier patches, closed into a solid.

Data: the classic 32-patch set (with Frank Crow's bottom) is public domain. Its 28 rotational
patches (rim, body, lid, bottom) are quarter-circle sweeps of a profile: each patch row is
``(r, 0, z), (r, -0.56 r, z), (0.56 r, -r, z), (0, -r, z)`` and its three rotated copies, so they
are stored here as the (r, z) profile control points only. The handle and spout are stored as
their y <= 0 half patches (16 control points each); the y >= 0 halves are their mirror images.

Why it needs closing: the classic teapot is not watertight. The lid (outer radius 1.3) does not
meet the rim (inner radius 1.4), the spout is an open tube, and the handle and spout merely
pierce the body, so the patches form a self-intersecting surface with holes. We close it as
follows:

- body, rim, lid and bottom: the profile Bezier curves are joined into one closed (r, z)
  outline, bridging the lid gap with a short horizontal segment (a groove remains where the lid
  sits on the rim), and revolved: a solid of revolution with an exact 2D signed distance.
- handle and spout: the patches are tessellated into tubes whose two end loops are capped with
  triangle fans (the spout tip becomes a flat, closed end); their signed distance comes from
  open3d's raycasting scene (distance to the triangles, sign by ray parity).
- the three solids are joined by a smooth union and meshed by marching cubes like every other
  family, which yields a single watertight manifold (the SDF remeshing route).

Each seed varies the proportions: body width and height, the body curve's bulge, the knob
height, and the size and tilt of spout and handle.
"""

from __future__ import annotations

import numpy as np

from . import sdf
from .sdf import Grid

# (r, z) control points of the rotational patches, each a cubic Bezier curve along the profile.
RIM = [(1.4, 2.4), (1.3375, 2.53125), (1.4375, 2.53125), (1.5, 2.4)]
BODY_UPPER = [(1.5, 2.4), (1.75, 1.875), (2.0, 1.35), (2.0, 0.9)]
BODY_LOWER = [(2.0, 0.9), (2.0, 0.45), (1.5, 0.225), (1.5, 0.15)]
LID_KNOB = [(0.0, 3.15), (0.8, 3.15), (0.0, 2.85), (0.2, 2.7)]
LID_BASE = [(0.2, 2.7), (0.4, 2.55), (1.3, 2.55), (1.3, 2.4)]
BOTTOM = [(0.0, 0.0), (1.425, 0.0), (1.5, 0.075), (1.5, 0.15)]

# Half patches (y <= 0) of handle and spout: 4 rows (along the tube) x 4 control points (around).
HANDLE = [
    [[(-1.6, 0, 2.025), (-1.6, -0.3, 2.025), (-1.5, -0.3, 2.25), (-1.5, 0, 2.25)],
     [(-2.3, 0, 2.025), (-2.3, -0.3, 2.025), (-2.5, -0.3, 2.25), (-2.5, 0, 2.25)],
     [(-2.7, 0, 2.025), (-2.7, -0.3, 2.025), (-3.0, -0.3, 2.25), (-3.0, 0, 2.25)],
     [(-2.7, 0, 1.8), (-2.7, -0.3, 1.8), (-3.0, -0.3, 1.8), (-3.0, 0, 1.8)]],
    [[(-2.7, 0, 1.8), (-2.7, -0.3, 1.8), (-3.0, -0.3, 1.8), (-3.0, 0, 1.8)],
     [(-2.7, 0, 1.575), (-2.7, -0.3, 1.575), (-3.0, -0.3, 1.35), (-3.0, 0, 1.35)],
     [(-2.5, 0, 1.125), (-2.5, -0.3, 1.125), (-2.65, -0.3, 0.9375), (-2.65, 0, 0.9375)],
     [(-2.0, 0, 0.9), (-2.0, -0.3, 0.9), (-1.9, -0.3, 0.6), (-1.9, 0, 0.6)]],
]
SPOUT = [
    [[(1.7, 0, 1.425), (1.7, -0.66, 1.425), (1.7, -0.66, 0.6), (1.7, 0, 0.6)],
     [(2.6, 0, 1.425), (2.6, -0.66, 1.425), (3.1, -0.66, 0.825), (3.1, 0, 0.825)],
     [(2.3, 0, 2.1), (2.3, -0.25, 2.1), (2.4, -0.25, 2.025), (2.4, 0, 2.025)],
     [(2.7, 0, 2.4), (2.7, -0.25, 2.4), (3.3, -0.25, 2.4), (3.3, 0, 2.4)]],
    [[(2.7, 0, 2.4), (2.7, -0.25, 2.4), (3.3, -0.25, 2.4), (3.3, 0, 2.4)],
     [(2.8, 0, 2.475), (2.8, -0.25, 2.475), (3.525, -0.25, 2.49375), (3.525, 0, 2.49375)],
     [(2.9, 0, 2.475), (2.9, -0.15, 2.475), (3.45, -0.15, 2.5125), (3.45, 0, 2.5125)],
     [(2.8, 0, 2.4), (2.8, -0.15, 2.4), (3.2, -0.15, 2.4), (3.2, 0, 2.4)]],
]


def _bernstein(t: np.ndarray) -> np.ndarray:
    """(len(t), 4) cubic Bernstein basis."""
    t = np.asarray(t, np.float64)[:, None]
    return np.concatenate([(1 - t) ** 3, 3 * (1 - t) ** 2 * t, 3 * (1 - t) * t**2, t**3], 1)


def bezier_curve(ctrl, n: int = 32) -> np.ndarray:
    """(n + 1, d) points of a cubic Bezier curve with (4, d) control points."""
    return _bernstein(np.linspace(0, 1, n + 1)) @ np.asarray(ctrl, np.float64)


def bezier_patch(ctrl, n: int = 12) -> np.ndarray:
    """(n + 1, n + 1, 3) points of a bicubic patch with (4, 4, 3) control points (rows = u)."""
    B = _bernstein(np.linspace(0, 1, n + 1))
    return np.einsum("ui,vj,ijk->uvk", B, B, np.asarray(ctrl, np.float64))


def profile_polygon(curves, n: int = 32) -> np.ndarray:
    """Closed (r, z) outline of the body + lid, mirrored about the axis (the axis is interior)."""
    pts = [bezier_curve(curves["bottom"], n),
           bezier_curve(curves["body_lower"][::-1], n)[1:],
           bezier_curve(curves["body_upper"][::-1], n)[1:],
           bezier_curve(curves["rim"][::-1], n)[1:],
           # bridge the rim's inner edge (r=1.4) to the lid's outer edge (r=1.3) at z=2.4
           bezier_curve(curves["lid_base"][::-1], n),
           bezier_curve(curves["lid_knob"][::-1], n)[1:]]
    right = np.concatenate(pts)  # from (0, 0) up to (0, 3.15)
    right[:, 0] = np.maximum(right[:, 0], 0.0)
    left = right[::-1].copy()
    left[:, 0] *= -1
    return np.concatenate([right, left[1:-1]])


def _tube_mesh(halves, n: int = 12):
    """Closed triangle mesh of a tube given as half patches; both end loops capped with fans."""
    rows = []
    for k, patch in enumerate(halves):
        P = bezier_patch(patch, n)  # (n+1, n+1, 3); u along the tube, v around (y <= 0 half)
        M = P[:, ::-1].copy()
        M[..., 1] *= -1  # mirror half (y >= 0), reversed so the ring continues
        ring = np.concatenate([P, M[:, 1:-1]], axis=1)  # (n+1, 2n, 3), periodic in v
        rows.append(ring if k == 0 else ring[1:])
    grid_pts = np.concatenate(rows)  # (U, V, 3)
    U, V, _ = grid_pts.shape
    verts = grid_pts.reshape(-1, 3)
    idx = np.arange(U * V).reshape(U, V)
    faces = []
    for i in range(U - 1):
        for j in range(V):
            a, b = idx[i, j], idx[i, (j + 1) % V]
            c, d = idx[i + 1, j], idx[i + 1, (j + 1) % V]
            faces += [(a, b, d), (a, d, c)]
    extra = []
    for i in (0, U - 1):  # caps: fan around the loop's centroid
        c = len(verts) + len(extra)
        extra.append(grid_pts[i].mean(0))
        for j in range(V):
            faces.append((c, idx[i, j], idx[i, (j + 1) % V]))
    verts = np.concatenate([verts, np.array(extra)])
    return verts.astype(np.float32), np.array(faces, np.uint32)


def _signed_distance(verts, faces, x, y, z, band: float) -> np.ndarray:
    """Signed distance to a closed triangle mesh near it; elsewhere a positive lower bound.

    Only grid points within ``band`` of the mesh's bounding box are queried (raycasting is the
    expensive part); the others get their distance to that box, which is >= ``band`` > 0, so the
    zero level set and the smooth union (blend width < band) are unchanged.
    """
    import open3d as o3d

    lo = verts.min(0) - band
    hi = verts.max(0) + band
    dx = np.maximum(np.maximum(lo[0] - x, x - hi[0]), 0)
    dy = np.maximum(np.maximum(lo[1] - y, y - hi[1]), 0)
    dz = np.maximum(np.maximum(lo[2] - z, z - hi[2]), 0)
    out = (np.sqrt(dx * dx + dy * dy + dz * dz) + band).astype(np.float32)
    near = (dx == 0) & (dy == 0) & (dz == 0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(faces))
    q = np.stack([x[near], y[near], z[near]], -1).astype(np.float32)
    out[near] = scene.compute_signed_distance(o3d.core.Tensor(q), nthreads=1, nsamples=3).numpy()
    return out


def _affine(patches, center, scale: float, tilt: float):
    """Scale patches about ``center`` and rotate them about the y axis by ``tilt`` radians."""
    P = np.asarray(patches, np.float64)
    c = np.asarray(center, np.float64)
    R = sdf.rotation_matrix([0, 1, 0], tilt)
    return (P - c) @ R.T * scale + c


def teapot(rng: np.random.Generator, g: Grid) -> np.ndarray:
    u = rng.uniform
    sr, sz = u(0.85, 1.2), u(0.8, 1.25)  # body width and height
    bulge = u(-0.15, 0.15)
    knob = u(0.7, 1.5)
    curves = {
        "rim": np.array(RIM), "bottom": np.array(BOTTOM), "lid_base": np.array(LID_BASE),
        "body_upper": np.array(BODY_UPPER), "body_lower": np.array(BODY_LOWER),
        "lid_knob": np.array(LID_KNOB),
    }
    curves["body_upper"][1:3, 0] *= 1 + bulge  # inner control points only: joints stay C0
    curves["body_lower"][1:3, 0] *= 1 + bulge
    lk = curves["lid_knob"]
    lk[:, 1] = 2.7 + (lk[:, 1] - 2.7) * knob
    handle = _affine(HANDLE, (-1.55, 0, 1.5), u(0.85, 1.2), u(-0.2, 0.2))
    spout = _affine(SPOUT, (1.7, 0, 1.0), u(0.8, 1.2), u(-0.25, 0.15))
    poly = profile_polygon(curves)
    # scale everything: x, y (r) by sr, z by sz
    poly = poly * [sr, sz]
    handle = handle * [sr, sr, sz]
    spout = spout * [sr, sr, sz]
    hv, hf = _tube_mesh(handle)
    sv, sf = _tube_mesh(spout)
    allpts = np.concatenate([hv, sv, [[poly[:, 0].max(), poly[:, 0].max(), 0]],
                             [[-poly[:, 0].max(), -poly[:, 0].max(), poly[:, 1].max()]]])
    fit = sdf.Fit(g, allpts.min(0), allpts.max(0))
    x, y, z = fit.x, fit.y, fit.z
    rmax = float(np.abs(allpts[:, :2]).max()) * 1.5 + 0.5
    zlo, zhi = float(allpts[:, 2].min()) - 0.5, float(allpts[:, 2].max()) + 0.5
    n_tab = int(np.clip(4 * g.res, 128, 512))  # table cells ~1/3 of a grid cell
    c_r = np.linspace(0.0, rmax, n_tab)
    c_z = np.linspace(zlo, zhi, n_tab)
    rr, zz = np.meshgrid(c_r, c_z, indexing="ij")
    table = sdf.polygon_sdf_2d(rr, zz, poly, step=(zhi - zlo) / n_tab / 4, max_dist=0.5).astype(np.float32)
    r = np.sqrt(x * x + y * y)
    body = sdf.sample_2d_field(table, (0.0, zlo), (rmax, zhi), r, z)
    f = body
    k = 0.06
    band = 2 * k + 3 * fit.spacing
    f = sdf.smin(f, _signed_distance(hv, hf, x, y, z, band), k)
    f = sdf.smin(f, _signed_distance(sv, sf, x, y, z, band), k)
    return fit.to_grid(f)
