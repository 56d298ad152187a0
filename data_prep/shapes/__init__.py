"""Procedural shape families: seeded generators of watertight triangle meshes.

Every family is a function ``(rng, grid) -> field`` building a level-set field (negative inside)
on the grid; :func:`make_shape` meshes it with marching cubes, keeps the largest component and
normalises it to a unit bounding-box diagonal centred at the origin. All parameters come from
``rng``, which is seeded from ``(family, seed)``: the same pair always gives the same mesh.

>>> from data_prep.shapes import make_shape, FAMILIES
>>> mesh = make_shape("teapot", seed=3, resolution=96)   # Mesh(vertices (V,3), faces (F,3))
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Callable

import numpy as np

from . import csg, displaced, figures, quadrics, revolution, teapot
from .meshing import Mesh, MeshError, check_mesh, mesh_from_field, normalize_mesh, to_open3d
from .sdf import grid

log = logging.getLogger(__name__)

__all__ = [
    "FAMILIES",
    "Mesh",
    "MeshError",
    "UnknownFamilyError",
    "family_names",
    "resolve_families",
    "make_shape",
    "check_mesh",
    "to_open3d",
]

FieldFn = Callable[[np.random.Generator, object], np.ndarray]

#: name -> (generator, one-line description). Order is the registry order used by "all".
FAMILIES: dict[str, tuple[FieldFn, str]] = {
    "superquadric": (quadrics.superquadric, "superquadrics with taper, twist and engraved grooves"),
    "torus": (quadrics.torus, "tori with superelliptic, twisted sections and knurls"),
    "torus_knot": (quadrics.torus_knot, "(p, q) torus-knot tubes with beads and ring grooves"),
    "displaced_sphere": (displaced.displaced_sphere, "ellipsoids displaced by multi-scale noise, ridges, engravings"),
    "relief": (displaced.relief, "slabs with relief heightfields: bumps, terraces, carved strokes"),
    "revolution": (revolution.revolution, "vases, goblets, bottles and bowls with flutes and rings"),
    "furniture": (csg.furniture, "CSG furniture: tables, chairs, stools, shelves"),
    "mechanical": (csg.mechanical, "CSG mechanical parts: gears, flanges, threaded bolts, brackets"),
    "figure": (figures.figure, "articulated capsule figures: bipeds and quadrupeds"),
    "teapot": (teapot.teapot, "the Utah teapot from its Bezier patches, closed, with varied proportions"),
}

#: Families whose generation may retry with a derived seed if a mesh fails the checks.
MAX_ATTEMPTS = 4


class UnknownFamilyError(ValueError):
    pass


def family_names() -> list[str]:
    return list(FAMILIES)


def resolve_families(names) -> list[str]:
    """Validate a list of family names (``"all"`` expands to every family, in registry order)."""
    if isinstance(names, str):
        names = [names]
    names = list(names)
    if not names:
        raise UnknownFamilyError("the family list is empty")
    out: list[str] = []
    for n in names:
        if n == "all":
            out += [f for f in FAMILIES if f not in out]
        elif n not in FAMILIES:
            raise UnknownFamilyError(f"unknown shape family {n!r}; known: {', '.join(FAMILIES)} (or 'all')")
        elif n not in out:
            out.append(n)
    return out


def family_rng(family: str, seed: int, attempt: int = 0) -> np.random.Generator:
    """The generator every parameter of shape ``(family, seed)`` is drawn from."""
    return np.random.default_rng(np.random.SeedSequence([zlib.crc32(family.encode()), int(seed), attempt]))


def make_shape(family: str, seed: int, resolution: int = 96, normalize: bool = True) -> Mesh:
    """A watertight mesh of ``family`` drawn from ``seed``, meshed on a ``resolution``^3 grid.

    Returns a :class:`Mesh` (vertices (V, 3) float64, faces (F, 3) int64, outward winding),
    normalised to a unit bounding-box diagonal centred at the origin when ``normalize``.
    If a draw yields an unusable mesh (rare: e.g. everything but a sliver vanished at a low
    resolution), the draw is repeated with a derived seed, deterministically.

    Raises:
        UnknownFamilyError: ``family`` is not registered.
        MeshError: no valid mesh after :data:`MAX_ATTEMPTS` draws.
    """
    if family not in FAMILIES:
        raise UnknownFamilyError(f"unknown shape family {family!r}; known: {', '.join(FAMILIES)}")
    fn = FAMILIES[family][0]
    g = grid(int(resolution))
    last = None
    for attempt in range(MAX_ATTEMPTS):
        try:
            field = fn(family_rng(family, seed, attempt), g)
            mesh = mesh_from_field(field, g)
            rep = check_mesh(mesh, min_faces=100)
            if rep["ok"]:
                return normalize_mesh(mesh) if normalize else mesh
            last = f"mesh check failed: {rep}"
        except MeshError as e:
            last = str(e)
        log.info("%s seed %d attempt %d rejected (%s); redrawing", family, seed, attempt, last)
    raise MeshError(f"{family} seed {seed}: no valid mesh after {MAX_ATTEMPTS} draws ({last})")
