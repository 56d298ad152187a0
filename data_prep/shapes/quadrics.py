"""Superquadrics (with taper/twist and surface grooves), tori and torus knots."""

from __future__ import annotations

import numpy as np

from . import sdf
from .sdf import Grid


def superquadric(rng: np.random.Generator, g: Grid) -> np.ndarray:
    """Barr superquadric with random radii and exponents, optional taper, twist and grooves.

    Exponents e1 (latitude) and e2 (longitude) range from boxy (0.25) over round (1) to pinched
    (2.2); the inside-outside function F is turned into a near-distance ``(F^(e1/2) - 1) * r_min``.
    """
    a, b, c = rng.uniform(0.4, 0.85, size=3)
    e1, e2 = np.exp(rng.uniform(np.log(0.25), np.log(2.2), size=2))
    rot = sdf.random_rotation(rng)
    x, y, z = sdf.rotate(g.x, g.y, g.z, rot)
    x, y, z = x.astype(np.float64), y.astype(np.float64), z.astype(np.float64)
    if rng.random() < 0.4:  # linear taper along z
        t = rng.uniform(-0.5, 0.5)
        s = 1.0 + t * z / c
        s = np.clip(s, 0.3, None)
        x, y = x / s, y / s
    if rng.random() < 0.4:  # twist about z
        k = rng.uniform(-1.5, 1.5)
        ang = k * z
        ca, sa = np.cos(ang), np.sin(ang)
        x, y = ca * x - sa * y, sa * x + ca * y
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        fxy = (np.abs(x / a) ** (2 / e2) + np.abs(y / b) ** (2 / e2)) ** (e2 / e1)
        F = fxy + np.abs(z / c) ** (2 / e1)
        f = (F ** (e1 / 2) - 1.0) * min(a, b, c)
    f = np.nan_to_num(f, nan=1.0, posinf=1.0)
    if rng.random() < 0.6:  # fine detail: engraved parallel grooves or a bumpy pattern
        freq = rng.uniform(8, 20)
        amp = rng.uniform(0.008, 0.02)
        if rng.random() < 0.5:
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            phase = (x * d[0] + y * d[1] + z * d[2]) * freq * 2 * np.pi
            f = f + amp * np.clip(np.cos(phase) * 3 - 2, 0, None)  # narrow grooves
        else:
            f = f - amp * np.sin(freq * 2 * x) * np.sin(freq * 2 * y) * np.sin(freq * 2 * z)
    return f.astype(np.float32)


def torus(rng: np.random.Generator, g: Grid) -> np.ndarray:
    """Torus with a superelliptic, optionally twisted cross-section and knurled surface."""
    R = rng.uniform(0.45, 0.62)
    r = rng.uniform(0.12, min(0.3, 0.85 - R))
    p = rng.choice([2.0, 2.0, 3.0, 4.0, 6.0])  # cross-section exponent: 2 round, >2 squarish
    squash = rng.uniform(0.6, 1.4)
    twist = int(rng.integers(0, 5)) if p > 2 else 0  # quarter turns of the section per loop
    rot = sdf.random_rotation(rng)
    x, y, z = sdf.rotate(g.x, g.y, g.z, rot)
    phi = np.arctan2(y, x)
    q = np.sqrt(x**2 + y**2) - R
    w = z / squash
    if twist:
        ang = twist * phi / 4.0
        ca, sa = np.cos(ang), np.sin(ang)
        q, w = ca * q - sa * w, sa * q + ca * w
    f = (np.abs(q) ** p + np.abs(w) ** p) ** (1.0 / p) - r
    if rng.random() < 0.6:  # knurls / ribs around the ring
        n_rib = int(rng.integers(12, 48))
        amp = rng.uniform(0.008, 0.02)
        theta = np.arctan2(w, q)
        if rng.random() < 0.5:
            f = f - amp * np.cos(n_rib * phi)
        else:
            f = f - amp * np.cos(n_rib * phi) * np.cos(int(rng.integers(3, 10)) * theta)
    return f.astype(np.float32)


_KNOTS = [(2, 3), (2, 5), (3, 2), (3, 4), (3, 5), (2, 7), (3, 7), (4, 3), (5, 2), (5, 3)]


def torus_knot(rng: np.random.Generator, g: Grid) -> np.ndarray:
    """A (p, q) torus-knot tube; distance to the curve via a KD-tree over dense curve samples."""
    from scipy.spatial import cKDTree

    p, q = _KNOTS[int(rng.integers(len(_KNOTS)))]
    R = rng.uniform(0.45, 0.55)
    a = rng.uniform(0.18, 0.3)
    hz = rng.uniform(0.6, 1.4)
    tube = rng.uniform(0.07, 0.12)
    n = 6000
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rr = R + a * np.cos(q * t)
    curve = np.stack([rr * np.cos(p * t), rr * np.sin(p * t), hz * a * np.sin(q * t)], 1)
    curve = curve @ sdf.random_rotation(rng).T
    ext = np.abs(curve).max() + tube * 1.3
    curve *= 0.88 / ext
    tube *= 0.88 / ext
    # tube radius varies along the curve (beads / swellings) for coarse-to-fine detail
    n_beads = int(rng.integers(0, 40))
    amp = rng.uniform(0.0, 0.25) if n_beads else 0.0
    radius = tube * (1.0 + amp * np.cos(n_beads * t))
    tree = cKDTree(curve)
    pts = np.stack([g.x.ravel(), g.y.ravel(), g.z.ravel()], 1)
    band = float(radius.max() + 3 * g.spacing)
    dist, idx = tree.query(pts, k=1, distance_upper_bound=band, workers=1)
    far = ~np.isfinite(dist)
    idx[far] = 0
    f = np.where(far, band, dist - radius[idx])
    if rng.random() < 0.5:  # fine ring grooves around the tube
        freq = rng.uniform(60, 160)
        gamma = np.where(far, 0.0, t[idx])
        f = f + np.where(far, 0.0, 0.006 * np.clip(np.cos(freq * gamma) * 3 - 2, 0, None))
    return f.reshape(g.x.shape).astype(np.float32)

