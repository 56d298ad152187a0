"""CSG-like unions of primitives: furniture and mechanical parts (gears, flanges, bolts, brackets).

Parts are signed-distance primitives combined with (smooth) union and subtraction, so the result
is a single closed level set; thin features may vanish at low grid resolution but the mesh stays
watertight. Parts are laid out in model units; :class:`~data_prep.shapes.sdf.Fit` scales the
whole assembly into the grid.
"""

from __future__ import annotations

import numpy as np

from . import sdf
from .sdf import Grid


class _Assembly:
    """Collects (bounding box, field function, operation) and evaluates them in a fitted frame."""

    def __init__(self):
        self.parts = []  # (lo, hi, fn, op, k)

    def add(self, lo, hi, fn, k: float = 0.0):
        self.parts.append((np.asarray(lo, float), np.asarray(hi, float), fn, "union", k))

    def cut(self, fn, k: float = 0.0):
        self.parts.append((None, None, fn, "cut", k))

    def box(self, center, half, radius=0.0, k=0.0):
        c, h = np.asarray(center, float), np.asarray(half, float)
        radius = min(radius, 0.95 * float(h.min()))
        self.add(c - h, c + h, lambda x, y, z: sdf.box(x, y, z, c, h, radius), k)

    def capsule(self, a, b, r, k=0.0):
        a, b = np.asarray(a, float), np.asarray(b, float)
        self.add(np.minimum(a, b) - r, np.maximum(a, b) + r, lambda x, y, z: sdf.capsule(x, y, z, a, b, r), k)

    def cylinder(self, center, r, half_h, k=0.0):
        c = np.asarray(center, float)
        self.add(c - [r, r, half_h], c + [r, r, half_h], lambda x, y, z: sdf.cylinder_z(x, y, z, c, r, half_h), k)

    def evaluate(self, g: Grid, rot: np.ndarray | None = None, margin: float = 0.88) -> np.ndarray:
        """The assembly's field on ``g``, rotated by ``rot`` (3, 3) and fitted into the grid."""
        lo = np.min([p[0] for p in self.parts if p[3] == "union"], axis=0)
        hi = np.max([p[1] for p in self.parts if p[3] == "union"], axis=0)
        if rot is not None:  # the rotated box's corners bound the rotated shape
            corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
            rc = corners @ rot.T
            fit = sdf.Fit(g, rc.min(0), rc.max(0), margin)
            x, y, z = sdf.rotate(fit.x, fit.y, fit.z, rot)
        else:
            fit = sdf.Fit(g, lo, hi, margin)
            x, y, z = fit.x, fit.y, fit.z
        f = None
        for _, _, fn, op, k in self.parts:
            v = fn(x, y, z).astype(np.float32)
            if f is None:
                f = v
            elif op == "union":
                f = sdf.smin(f, v, k)
            else:
                f = sdf.smax(f, -v, k)
        return fit.to_grid(f)


# ----------------------------------------------------------------------------- furniture

def _table(rng, A: _Assembly):
    L, W = rng.uniform(0.8, 1.6), rng.uniform(0.5, 1.0)
    H = rng.uniform(0.6, 1.0)
    t = rng.uniform(0.04, 0.08)
    leg = rng.uniform(0.04, 0.08)
    A.box([0, 0, H - t / 2], [L / 2, W / 2, t / 2], radius=rng.uniform(0.005, 0.03))
    inset = rng.uniform(0.05, 0.15)
    round_legs = rng.random() < 0.5
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (L / 2 - inset), sy * (W / 2 - inset)
            if round_legs:
                A.capsule([cx, cy, leg], [cx * rng.uniform(0.95, 1.05), cy, H - t], leg, k=0.03)
            else:
                A.box([cx, cy, (H - t) / 2], [leg, leg, (H - t) / 2], radius=0.01, k=0.02)
    if rng.random() < 0.6:  # stretchers
        zs = rng.uniform(0.15, 0.4) * H
        A.box([0, W / 2 - inset, zs], [L / 2 - inset, leg * 0.6, leg * 0.6], radius=0.01, k=0.02)
        A.box([0, -(W / 2 - inset), zs], [L / 2 - inset, leg * 0.6, leg * 0.6], radius=0.01, k=0.02)
    if rng.random() < 0.4:  # a shelf
        A.box([0, 0, rng.uniform(0.15, 0.3) * H], [L / 2 - inset, W / 2 - inset, t / 3], radius=0.005, k=0.02)


def _chair(rng, A: _Assembly):
    S = rng.uniform(0.4, 0.55)
    H = rng.uniform(0.4, 0.5)
    back = rng.uniform(0.4, 0.7)
    t = rng.uniform(0.04, 0.07)
    leg = rng.uniform(0.025, 0.045)
    A.box([0, 0, H], [S / 2, S / 2, t / 2], radius=0.015)
    for sx in (-1, 1):
        for sy in (-1, 1):
            A.box([sx * (S / 2 - leg), sy * (S / 2 - leg), H / 2], [leg, leg, H / 2], radius=0.008, k=0.02)
    # back posts and slats
    for sx in (-1, 1):
        A.box([sx * (S / 2 - leg), -(S / 2 - leg), H + back / 2], [leg, leg, back / 2], radius=0.008, k=0.02)
    if rng.random() < 0.5:
        A.box([0, -(S / 2 - leg), H + back * 0.8], [S / 2, leg * 0.8, back * 0.15], radius=0.01, k=0.02)
        n_slats = int(rng.integers(2, 6))
        for xs in np.linspace(-S / 2 + 2 * leg, S / 2 - 2 * leg, n_slats):
            A.box([xs, -(S / 2 - leg), H + back * 0.45], [leg * 0.5, leg * 0.5, back * 0.3], radius=0.005, k=0.01)
    else:
        A.box([0, -(S / 2 - leg), H + back * 0.55], [S / 2, leg, back * 0.4], radius=0.02, k=0.02)
    if rng.random() < 0.4:  # arm rests
        for sx in (-1, 1):
            A.box([sx * (S / 2 - leg), 0, H + 0.2], [leg, S / 2, leg], radius=0.01, k=0.02)
            A.box([sx * (S / 2 - leg), S / 2 - leg, H + 0.1], [leg, leg, 0.1], radius=0.008, k=0.02)


def _stool(rng, A: _Assembly):
    R = rng.uniform(0.18, 0.3)
    H = rng.uniform(0.45, 0.8)
    A.cylinder([0, 0, H], R, rng.uniform(0.02, 0.04), k=0.0)
    n = int(rng.integers(3, 5))
    splay = rng.uniform(1.0, 1.4)
    leg = rng.uniform(0.02, 0.035)
    ring_z = rng.uniform(0.2, 0.4) * H
    for i in range(n):
        a = 2 * np.pi * i / n
        top = np.array([np.cos(a), np.sin(a), 0]) * R * 0.7 + [0, 0, H]
        bot = np.array([np.cos(a), np.sin(a), 0]) * R * 0.7 * splay + [0, 0, leg]
        A.capsule(bot, top, leg, k=0.02)
    if rng.random() < 0.7:  # foot ring made of capsules between legs
        for i in range(n):
            a0, a1 = 2 * np.pi * i / n, 2 * np.pi * (i + 1) / n
            rr = R * 0.7 * (splay + (1 - splay) * ring_z / H)
            A.capsule([rr * np.cos(a0), rr * np.sin(a0), ring_z], [rr * np.cos(a1), rr * np.sin(a1), ring_z], leg * 0.7, k=0.02)


def _shelf(rng, A: _Assembly):
    W, D, H = rng.uniform(0.5, 1.0), rng.uniform(0.25, 0.45), rng.uniform(0.7, 1.4)
    t = rng.uniform(0.03, 0.05)
    A.box([0, 0, H / 2], [W / 2, D / 2, H / 2], radius=0.01)
    n = int(rng.integers(2, 5))
    h = (H - (n + 1) * t) / n
    for i in range(n):  # open compartments cut from the front
        zc = t + i * (h + t) + h / 2
        cols = int(rng.integers(1, 3))
        w = (W - (cols + 1) * t) / cols
        for j in range(cols):
            xc = -W / 2 + t + j * (w + t) + w / 2
            c = np.array([xc, -t, zc])  # open towards -y
            hh = np.array([w / 2, D / 2, h / 2])
            A.cut(lambda x, y, z, c=c, hh=hh: sdf.box(x, y, z, c, hh, 0.005))


def furniture(rng: np.random.Generator, g: Grid) -> np.ndarray:
    A = _Assembly()
    kind = str(rng.choice(["table", "chair", "stool", "shelf"]))
    {"table": _table, "chair": _chair, "stool": _stool, "shelf": _shelf}[kind](rng, A)
    return A.evaluate(g)


# ----------------------------------------------------------------------------- mechanical

def _gear_polygon(rng, n_teeth: int, r_root: float, depth: float) -> np.ndarray:
    """A spur-gear outline (trapezoid teeth) as a polygon (M, 2)."""
    top = rng.uniform(0.2, 0.35)  # fraction of the pitch at the tooth tip
    base = top + rng.uniform(0.15, 0.3)  # fraction at the root
    th = np.linspace(0, 2 * np.pi, n_teeth * 32, endpoint=False)
    s = (th * n_teeth / (2 * np.pi)) % 1.0
    d = np.abs(s - 0.5)  # 0 at the tooth centre
    prof = np.clip((base / 2 - d) / ((base - top) / 2), 0, 1)
    r = r_root + depth * prof
    return np.stack([r * np.cos(th), r * np.sin(th)], 1)


def _gear(rng, A: _Assembly, res: int):
    n = int(rng.integers(8, 40))
    R = 0.5
    depth = np.clip(2.2 * np.pi * R / n * rng.uniform(0.35, 0.55), 0.03, 0.12)
    half_t = rng.uniform(0.06, 0.2)
    poly = _gear_polygon(rng, n, R - depth, depth)
    table = sdf.polygon_field_2d(poly, -0.6, 0.6, int(np.clip(4 * res, 128, 512)), max_dist=0.1)
    A.add([-R, -R, -half_t], [R, R, half_t],
          lambda x, y, z: np.maximum(sdf.sample_2d_field(table, (-0.6, -0.6), (0.6, 0.6), x, y), np.abs(z) - half_t))
    hub_r = rng.uniform(0.12, 0.22)
    hub_h = half_t + rng.uniform(0.0, 0.15)
    A.cylinder([0, 0, 0], hub_r, hub_h, k=0.02)
    bore = hub_r * rng.uniform(0.35, 0.6)
    A.cut(lambda x, y, z: sdf.cylinder_z(x, y, z, (0, 0, 0), bore, 1.0))
    if rng.random() < 0.6:  # lightening holes in the web
        k = int(rng.integers(3, 7))
        rr = (hub_r + R - depth) / 2
        hr = min((R - depth - hub_r) * 0.35, np.pi * rr / k * 0.7)
        for i in range(k):
            a = 2 * np.pi * i / k
            c = (rr * np.cos(a), rr * np.sin(a), 0)
            A.cut(lambda x, y, z, c=c: sdf.cylinder_z(x, y, z, c, hr, 1.0), k=0.01)
    if rng.random() < 0.3:  # a keyway
        A.cut(lambda x, y, z: sdf.box(x, y, z, (bore, 0, 0), (bore * 0.4, bore * 0.3, 1.0)))


def _flange(rng, A: _Assembly):
    R = 0.5
    t = rng.uniform(0.05, 0.12)
    A.cylinder([0, 0, 0], R, t, k=0)
    hub_r = rng.uniform(0.18, 0.3)
    hub_h = rng.uniform(0.15, 0.4)
    A.cylinder([0, 0, hub_h / 2], hub_r, hub_h / 2 + t / 2, k=0.04)
    bore = hub_r * rng.uniform(0.4, 0.7)
    A.cut(lambda x, y, z: sdf.cylinder_z(x, y, z, (0, 0, 0), bore, 2.0))
    n = int(rng.integers(3, 9))
    rr = (R + hub_r) / 2 + 0.03
    hr = rng.uniform(0.03, 0.06)
    for i in range(n):
        a = 2 * np.pi * i / n
        c = (rr * np.cos(a), rr * np.sin(a), 0)
        A.cut(lambda x, y, z, c=c: sdf.cylinder_z(x, y, z, c, hr, 1.0), k=0.005)
    if rng.random() < 0.5:  # chamfer-like groove on the rim
        A.cut(lambda x, y, z: sdf.torus_z(x, y, z - t, R, 0.02))


def _hexagon(x, y, r):
    """2D regular hexagon (flat sides at distance r)."""
    k = np.array([-0.8660254, 0.5, 0.57735])
    px, py = np.abs(x), np.abs(y)
    dot = np.minimum(k[0] * px + k[1] * py, 0)
    px = px - 2 * dot * k[0]
    py = py - 2 * dot * k[1]
    cx = np.clip(px, -k[2] * r, k[2] * r)
    d = np.sqrt((px - cx) ** 2 + (py - r) ** 2)
    return d * np.sign(py - r)


def _bolt(rng, A: _Assembly):
    head_r = rng.uniform(0.18, 0.28)
    head_h = rng.uniform(0.08, 0.15)
    shank_r = head_r * rng.uniform(0.45, 0.6)
    L = rng.uniform(0.6, 1.2)
    pitch = rng.uniform(0.04, 0.08)
    depth = pitch * 0.35
    A.add([-head_r * 1.2, -head_r * 1.2, L], [head_r * 1.2, head_r * 1.2, L + 2 * head_h],
          lambda x, y, z: np.maximum(_hexagon(x, y, head_r), np.abs(z - L - head_h) - head_h))

    def shank(x, y, z):
        r = np.sqrt(x * x + y * y)
        th = np.arctan2(y, x)
        s = (z / pitch - th / (2 * np.pi)) % 1.0
        thread = depth * (1 - 2 * np.abs(s - 0.5) * 2).clip(0, 1)  # triangular thread
        tip = np.clip((z - 0.0) / (3 * pitch), 0, 1)
        rr = shank_r - depth + thread * tip
        return np.maximum(np.maximum(r - rr, -z), z - L - 0.01)

    A.add([-shank_r, -shank_r, 0], [shank_r, shank_r, L], shank, k=0.01)
    if rng.random() < 0.5:  # a nut on the shank
        zn = rng.uniform(0.2, 0.5) * L
        nut_h = head_h * 0.9
        A.add([-head_r * 1.2, -head_r * 1.2, zn - nut_h], [head_r * 1.2, head_r * 1.2, zn + nut_h],
              lambda x, y, z: np.maximum(_hexagon(x, y, head_r * 0.95), np.abs(z - zn) - nut_h))


def _bracket(rng, A: _Assembly):
    L = rng.uniform(0.6, 1.0)
    W = rng.uniform(0.3, 0.6)
    t = rng.uniform(0.06, 0.12)
    H = rng.uniform(0.4, 0.9)
    A.box([L / 2, 0, t / 2], [L / 2, W / 2, t / 2], radius=0.01)
    A.box([t / 2, 0, H / 2], [t / 2, W / 2, H / 2], radius=0.01, k=0.05)
    if rng.random() < 0.7:  # triangular gusset: intersection of half-spaces
        gt = t * 0.6
        a = min(L, H) * 0.7

        def gusset(x, y, z):
            plane = (x + z - a) / np.sqrt(2)
            return np.maximum(np.maximum(plane, np.maximum(-x, -z)), np.abs(y) - gt / 2)

        A.add([0, -gt / 2, 0], [a, gt / 2, a], gusset, k=0.02)
    hr = rng.uniform(0.03, 0.06)
    for i in range(int(rng.integers(1, 4))):  # holes in the base
        c = (L * (0.45 + 0.5 * i / 3), rng.uniform(-W / 4, W / 4), 0)
        A.cut(lambda x, y, z, c=c: sdf.cylinder_z(x, y, z, c, hr, 1.0))
    for i in range(int(rng.integers(1, 3))):  # slots in the upright (cylinders along x)
        zc = H * (0.55 + 0.3 * i)
        yc = rng.uniform(-W / 4, W / 4)
        A.cut(lambda x, y, z, zc=zc, yc=yc: np.maximum(np.sqrt((y - yc) ** 2 + (z - zc) ** 2) - hr, np.abs(x) - 1.0))


def mechanical(rng: np.random.Generator, g: Grid) -> np.ndarray:
    A = _Assembly()
    kind = str(rng.choice(["gear", "gear", "flange", "bolt", "bracket"]))
    if kind == "gear":
        _gear(rng, A, g.res)
    else:
        {"flange": _flange, "bolt": _bolt, "bracket": _bracket}[kind](rng, A)
    return A.evaluate(g, rot=sdf.random_rotation(rng))
