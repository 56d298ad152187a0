"""Surfaces of revolution: vases, goblets, bottles and bowls, hollowed where they hold something.

A profile R(z) (monotone cubic through random knots) is revolved about z; the level-set function
``r - R(z, theta)`` capped by the bottom and top planes is the solid; a cavity ``r < R - wall``
above the floor is cut out for open vessels. Flutes, rings and spiral ribs add fine detail.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import PchipInterpolator

from . import sdf
from .sdf import Grid


def _profile(rng, kind: str):
    """Knots (z, R) of the outer profile, z increasing; returns (z_knots, r_knots, hollow_from)."""
    u = rng.uniform
    if kind == "vase":
        z = np.array([-0.85, -0.8, u(-0.5, -0.1), u(0.15, 0.45), u(0.55, 0.7), 0.85])
        r = np.array([u(0.2, 0.4), u(0.22, 0.42), u(0.4, 0.65), u(0.25, 0.55), u(0.1, 0.25), u(0.15, 0.35)])
        return z, r, -0.8 + u(0.05, 0.12)
    if kind == "goblet":
        foot = u(0.3, 0.45)
        stem = u(0.05, 0.09)
        cup_z = u(-0.15, 0.15)
        z = np.array([-0.85, -0.8, -0.7, u(-0.55, -0.35), cup_z - 0.12, cup_z, u(0.45, 0.6), 0.85])
        r = np.array([foot, foot * 0.9, stem * 1.3, stem * u(1.4, 2.2), stem, u(0.25, 0.35), u(0.35, 0.55), u(0.3, 0.55)])
        return z, r, cup_z + 0.06
    if kind == "bottle":
        body = u(0.3, 0.5)
        neck = u(0.08, 0.15)
        shoulder = u(0.0, 0.35)
        z = np.array([-0.85, -0.8, shoulder, shoulder + u(0.15, 0.3), 0.72, 0.78, 0.85])
        r = np.array([body * 0.95, body, body * u(0.9, 1.05), neck, neck, neck * 1.35, neck * 1.2])
        return z, r, None
    # bowl
    z = np.array([-0.4, -0.35, u(-0.1, 0.1), 0.35])
    r = np.array([u(0.2, 0.35), u(0.3, 0.45), u(0.65, 0.8), u(0.75, 0.88)])
    return z, r, -0.35 + u(0.05, 0.1)


def revolution(rng: np.random.Generator, g: Grid) -> np.ndarray:
    kind = str(rng.choice(["vase", "goblet", "bottle", "bowl"]))
    zk, rk, hollow_from = _profile(rng, kind)
    prof = PchipInterpolator(zk, rk, extrapolate=False)
    zmin, zmax = float(zk[0]), float(zk[-1])
    zs = np.clip(g.z[0, 0, :].astype(np.float64), zmin, zmax)  # R depends on z only: tabulate on the z axis
    R = np.clip(prof(zs), 0.02, None).astype(np.float32)[None, None, :]
    x, y, z = g.x, g.y, g.z
    r = np.sqrt(x * x + y * y)
    theta = np.arctan2(y, x)
    mod = np.ones_like(r)
    if rng.random() < 0.45:  # flutes / lobes around the axis
        n = int(rng.integers(5, 28))
        mod = mod + np.float32(rng.uniform(0.015, 0.05)) * np.cos(n * theta)
    if rng.random() < 0.35:  # spiral ribs
        n = int(rng.integers(6, 20))
        pitch = rng.uniform(2, 8)
        mod = mod + np.float32(rng.uniform(0.01, 0.03)) * np.cos(n * theta + pitch * z * np.pi)
    Rz = R * mod
    if rng.random() < 0.5:  # horizontal rings (beads)
        for zc in rng.uniform(zmin + 0.1, zmax - 0.05, size=int(rng.integers(1, 4))):
            Rz = Rz + np.float32(rng.uniform(0.015, 0.04)) * np.exp(-(((z - zc) / rng.uniform(0.01, 0.03)) ** 2))
    outer = np.maximum(np.maximum(r - Rz, zmin - z), z - zmax)
    f = outer
    if hollow_from is not None:
        wall = rng.uniform(0.045, 0.08)
        cavity = np.maximum(r - (Rz - np.float32(wall)), np.float32(hollow_from) - z)
        f = sdf.smax(outer, -cavity, 0.01)
    return f.astype(np.float32)
