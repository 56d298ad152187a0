"""Noise-displaced spheres and relief heightfields on boxes: coarse form plus fine surface detail.

Both use sums of random sinusoids ("random Fourier features") as smooth noise, ridged noise
(``(1 - |sin|)^3``) for sharp crests, and engraved patterns (narrow grooves cut into the surface).
"""

from __future__ import annotations

import numpy as np

from . import sdf
from .sdf import Grid


def _fourier(rng, coords, n_terms: int, freq: tuple[float, float], amp: float):
    """Sum of ``n_terms`` random sinusoids of the given coordinates, total amplitude ~``amp``."""
    out = np.zeros_like(coords[0])
    for _ in range(n_terms):
        w = rng.normal(size=len(coords))
        w *= rng.uniform(*freq) / max(np.linalg.norm(w), 1e-9)
        ph = rng.uniform(0, 2 * np.pi)
        arg = sum(wi * c for wi, c in zip(w, coords))
        out += np.sin(arg + ph).astype(np.float32)
    return out * np.float32(amp / np.sqrt(n_terms))


def _ridged(rng, coords, n_terms: int, freq: tuple[float, float], amp: float):
    out = np.zeros_like(coords[0])
    for _ in range(n_terms):
        w = rng.normal(size=len(coords))
        w *= rng.uniform(*freq) / max(np.linalg.norm(w), 1e-9)
        ph = rng.uniform(0, 2 * np.pi)
        arg = sum(wi * c for wi, c in zip(w, coords))
        out += ((1 - np.abs(np.sin(arg + ph))) ** 3).astype(np.float32)
    return out * np.float32(amp / n_terms)


def _groove(c: np.ndarray, width: float) -> np.ndarray:
    """1 on narrow bands where ``cos`` is near 1 (``c`` = cos of a phase), 0 elsewhere, smooth."""
    t = np.clip((c - (1 - width)) / width, 0, 1)
    return t * t * (3 - 2 * t)


def _sphere_pattern(rng, ux, uy, uz) -> np.ndarray:
    """An engraved pattern on the unit sphere of directions (values in [0, 1])."""
    theta = np.arctan2(uy, ux)
    phi = np.arccos(np.clip(uz, -1, 1))
    kind = rng.choice(["meridians", "latitudes", "spiral", "crosshatch", "dimples"])
    n = int(rng.integers(6, 24))
    m = int(rng.integers(4, 14))
    w = rng.uniform(0.04, 0.12)
    if kind == "meridians":
        return _groove(np.cos(n * theta) * np.sin(phi) ** 0.25, w)
    if kind == "latitudes":
        return _groove(np.cos(2 * m * phi), w)
    if kind == "spiral":
        return _groove(np.cos(n * theta + 2 * m * phi), w)
    if kind == "crosshatch":
        return np.maximum(_groove(np.cos(n * theta + 2 * m * phi), w), _groove(np.cos(n * theta - 2 * m * phi), w))
    # dimples: pits on a lattice
    c = 0.5 * (np.cos(n * theta) * np.sin(phi) + 1) * 0.5 * (np.cos(2 * m * phi) + 1)
    return _groove(2 * c - 1, 3 * w)


def displaced_sphere(rng: np.random.Generator, g: Grid) -> np.ndarray:
    """An ellipsoid displaced along directions by multi-scale noise, ridges and engravings."""
    radii = rng.uniform(0.5, 0.72, size=3)
    x, y, z = sdf.rotate(g.x, g.y, g.z, sdf.random_rotation(rng))
    r = np.sqrt(x * x + y * y + z * z) + np.float32(1e-6)
    ux, uy, uz = x / r, y / r, z / r
    dirs = (ux, uy, uz)
    disp = _fourier(rng, dirs, int(rng.integers(3, 8)), (1.0, 3.0), rng.uniform(0.05, 0.2))  # coarse
    disp += _fourier(rng, dirs, int(rng.integers(4, 10)), (4.0, 9.0), rng.uniform(0.0, 0.05))  # medium
    if rng.random() < 0.6:
        disp += _ridged(rng, dirs, int(rng.integers(2, 6)), (4.0, 12.0), rng.uniform(0.02, 0.08))
    if rng.random() < 0.5:
        disp += _fourier(rng, dirs, 12, (14.0, 30.0), rng.uniform(0.005, 0.015))  # fine bumps
    if rng.random() < 0.6:
        disp -= np.float32(rng.uniform(0.015, 0.04)) * _sphere_pattern(rng, ux, uy, uz)
    q = np.sqrt((x / radii[0]) ** 2 + (y / radii[1]) ** 2 + (z / radii[2]) ** 2)
    f = (q - 1.0 - disp) * np.float32(radii.min())
    return f.astype(np.float32)


def _plane_pattern(rng, x, y) -> np.ndarray:
    """Engraved strokes on a plane (values in [0, 1]): lines, rings, a grid or random glyph strokes."""
    kind = rng.choice(["lines", "rings", "grid", "strokes"])
    w = rng.uniform(0.06, 0.15)
    if kind == "lines":
        a = rng.uniform(0, np.pi)
        f = rng.uniform(6, 18)
        return _groove(np.cos(f * 2 * (np.cos(a) * x + np.sin(a) * y)), w)
    if kind == "rings":
        cx, cy = rng.uniform(-0.3, 0.3, 2)
        f = rng.uniform(8, 20)
        return _groove(np.cos(f * 2 * np.sqrt((x - cx) ** 2 + (y - cy) ** 2)), w)
    if kind == "grid":
        f = rng.uniform(6, 14)
        return np.maximum(_groove(np.cos(f * 2 * x), w), _groove(np.cos(f * 2 * y), w))
    # strokes: short random segments, like carved glyphs
    out = np.zeros_like(x)
    width = rng.uniform(0.012, 0.025)
    for _ in range(int(rng.integers(6, 16))):
        a = rng.uniform(-0.6, 0.6, 2)
        b = a + rng.normal(size=2) * 0.15
        ba = b - a
        h = np.clip(((x - a[0]) * ba[0] + (y - a[1]) * ba[1]) / max(float(ba @ ba), 1e-9), 0, 1)
        d = np.sqrt((x - a[0] - ba[0] * h) ** 2 + (y - a[1] - ba[1] * h) ** 2)
        out = np.maximum(out, np.clip(1 - d / width, 0, 1))
    return out


def _heightfield(rng, x, y) -> np.ndarray:
    """A relief: bumps, waves, terraces, ridges and engravings, roughly within [-0.2, 0.2]."""
    h = np.zeros_like(x)
    for _ in range(int(rng.integers(2, 9))):  # coarse Gaussian bumps and dents
        c = rng.uniform(-0.7, 0.7, 2)
        s = rng.uniform(0.08, 0.3)
        h += np.float32(rng.uniform(-0.12, 0.15)) * np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2) / (2 * s * s))
    h += _fourier(rng, (x, y), int(rng.integers(3, 8)), (3.0, 12.0), rng.uniform(0.01, 0.05))
    if rng.random() < 0.4:
        h += _ridged(rng, (x, y), int(rng.integers(2, 5)), (5.0, 15.0), rng.uniform(0.02, 0.06))
    if rng.random() < 0.3:  # terraces (soft steps)
        step = rng.uniform(0.03, 0.06)
        k = h / step
        fl = np.floor(k)
        t = np.clip((k - fl - 0.8) / 0.2, 0, 1)
        h = (fl + t * t * (3 - 2 * t)) * step
    if rng.random() < 0.7:
        h -= np.float32(rng.uniform(0.015, 0.035)) * _plane_pattern(rng, x, y)
    return h.astype(np.float32)


def relief(rng: np.random.Generator, g: Grid) -> np.ndarray:
    """A rounded slab whose top (and sometimes bottom) face carries a relief heightfield."""
    sx, sy = rng.uniform(0.6, 0.88, size=2)
    sz = rng.uniform(0.12, 0.35)
    rad = rng.uniform(0.02, 0.1)
    x, y, z = g.x, g.y, g.z
    # 2D rounded rectangle for the sides
    qx = np.abs(x) - (sx - rad)
    qy = np.abs(y) - (sy - rad)
    side = np.sqrt(np.maximum(qx, 0) ** 2 + np.maximum(qy, 0) ** 2) + np.minimum(np.maximum(qx, qy), 0) - rad
    top = sz + _heightfield(rng, x[:, :, :1], y[:, :, :1])  # (res, res, 1): depends on x, y only
    if rng.random() < 0.35:
        bottom = -sz - _heightfield(rng, x[:, :, :1], y[:, :, :1])
    else:
        bottom = np.full_like(top, -sz)
    bottom = np.minimum(bottom, top - 0.08)  # keep the slab at least 0.08 thick
    f = sdf.smax(sdf.smax(side, z - top, 0.03), bottom - z, 0.03)
    return f.astype(np.float32)
