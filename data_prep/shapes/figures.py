"""Articulated capsule figures: bipeds and quadrupeds posed by random joint angles.

A skeleton (joint positions) is built from random limb lengths and angles; every bone is a
(cone-)capsule, the head an ellipsoid-ish sphere, and all parts are joined by a smooth union, so
the figure is one closed level set (watertight after marching cubes).
"""

from __future__ import annotations

import numpy as np

from . import sdf
from .sdf import Grid


def _dir(yaw: float, pitch: float) -> np.ndarray:
    """Unit vector from yaw (about z) and pitch (elevation from the xy plane)."""
    return np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])


def _limb(rng, start, base_yaw, base_pitch, lengths, spread):
    """Joint chain from ``start``: each segment deviates from the previous by random angles."""
    pts = [np.asarray(start, float)]
    yaw, pitch = base_yaw, base_pitch
    for L in lengths:
        yaw += rng.uniform(-spread, spread)
        pitch += rng.uniform(-spread, spread)
        pts.append(pts[-1] + L * _dir(yaw, pitch))
    return pts


def _biped(rng):
    bones = []  # (a, b, r_a, r_b)
    u = rng.uniform
    pelvis = np.array([0.0, 0.0, 0.0])
    torso_len = u(0.45, 0.7)
    lean = u(-0.3, 0.3)
    chest = pelvis + torso_len * _dir(u(0, 2 * np.pi), np.pi / 2 - abs(lean))
    bones.append((pelvis, chest, u(0.1, 0.16), u(0.12, 0.2)))
    neck = chest + u(0.08, 0.14) * _dir(0, np.pi / 2 - u(-0.3, 0.3))
    bones.append((chest, neck, 0.05, 0.05))
    head_r = u(0.1, 0.15)
    head = neck + head_r * 0.9 * _dir(u(0, 2 * np.pi), np.pi / 2 - u(0, 0.5))
    sh_w = u(0.14, 0.22)
    hip_w = u(0.08, 0.12)
    arm = [u(0.22, 0.32), u(0.2, 0.3)]
    leg = [u(0.3, 0.42), u(0.28, 0.4)]
    for side in (-1, 1):
        shoulder = chest + np.array([0, side * sh_w, -0.03])
        pts = _limb(rng, shoulder, side * np.pi / 2, u(-1.4, 0.6), arm, 1.0)
        bones += [(pts[0], pts[1], 0.05, 0.04), (pts[1], pts[2], 0.04, 0.035)]
        hip = pelvis + np.array([0, side * hip_w, -0.02])
        pts = _limb(rng, hip, u(-0.4, 0.4) + side * 0.2, -np.pi / 2 + u(-0.6, 0.6), leg, 0.6)
        bones += [(pts[0], pts[1], 0.07, 0.055), (pts[1], pts[2], 0.055, 0.045)]
        foot = pts[2] + np.array([u(0.08, 0.14), 0, 0])
        bones.append((pts[2], foot, 0.045, 0.035))
    return bones, [(head, head_r)]


def _quadruped(rng):
    bones = []
    u = rng.uniform
    body_len = u(0.6, 1.0)
    back = np.array([-body_len / 2, 0, 0])
    front = np.array([body_len / 2, 0, u(-0.05, 0.15)])
    girth = u(0.12, 0.22)
    bones.append((back, front, girth * u(0.8, 1.1), girth))
    neck_end = front + u(0.2, 0.4) * _dir(0, u(0.3, 1.2))
    bones.append((front, neck_end, girth * 0.6, girth * 0.4))
    head_r = u(0.08, 0.13)
    snout = neck_end + u(0.1, 0.2) * _dir(u(-0.5, 0.5), u(-0.6, 0.1))
    bones.append((neck_end, snout, head_r, head_r * 0.5))
    leg = [u(0.22, 0.35), u(0.2, 0.32)]
    for end, x in ((back, -1), (front, 1)):
        for side in (-1, 1):
            hip = end + np.array([0, side * girth * 0.6, -girth * 0.3])
            pts = _limb(rng, hip, u(-0.5, 0.5) + (0 if x > 0 else np.pi), -np.pi / 2 + u(-0.5, 0.5), leg, 0.5)
            bones += [(pts[0], pts[1], 0.06, 0.045), (pts[1], pts[2], 0.045, 0.035)]
    if rng.random() < 0.8:  # tail
        pts = _limb(rng, back, np.pi, u(-0.5, 0.8), [u(0.15, 0.3), u(0.1, 0.25)], 0.7)
        bones += [(pts[0], pts[1], 0.04, 0.03), (pts[1], pts[2], 0.03, 0.015)]
    if rng.random() < 0.5:  # ears or horns
        for side in (-1, 1):
            base = neck_end + np.array([0, side * head_r * 0.6, head_r * 0.6])
            tip = base + u(0.06, 0.15) * _dir(side * u(0.8, 1.6), u(0.4, 1.3))
            bones.append((base, tip, 0.025, 0.01))
    return bones, [(neck_end, head_r)]


def figure(rng: np.random.Generator, g: Grid) -> np.ndarray:
    bones, balls = (_biped if rng.random() < 0.55 else _quadruped)(rng)
    k = rng.uniform(0.02, 0.06)
    pts = np.array([p for b in bones for p in b[:2]] + [c for c, _ in balls])
    rmax = max(max(b[2], b[3]) for b in bones)
    lo, hi = pts.min(0) - rmax, pts.max(0) + rmax
    rot = sdf.random_rotation(rng) if rng.random() < 0.3 else np.eye(3)
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])]) @ rot.T
    fit = sdf.Fit(g, corners.min(0), corners.max(0))
    x, y, z = sdf.rotate(fit.x, fit.y, fit.z, rot)
    f = None
    for a, b, ra, rb in bones:
        v = sdf.capsule(x, y, z, a, b, ra, rb)
        f = v if f is None else sdf.smin(f, v, k)
    for c, r in balls:
        f = sdf.smin(f, sdf.sphere(x, y, z, c, r), k)
    if rng.random() < 0.4:  # fine detail: shallow scales / fur ridges
        freq = rng.uniform(40, 90)
        f = f + np.float32(rng.uniform(0.003, 0.008)) * np.sin(freq * x) * np.sin(freq * y) * np.sin(freq * z)
    return fit.to_grid(f)
