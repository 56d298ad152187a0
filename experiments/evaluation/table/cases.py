"""The denoising table's cases: which shapes (``cases``, pymeshlab's samples, the generated
test split), and each case's files made once and cached: ``points`` Poisson-disk samples of the
mesh (the clean cloud, ground truth with the mesh) plus seeded Gaussian noise (the noisy input)
in ``<case dir>/{noisy,clean,mesh}.ply`` with ``case.json``. Used by ``dss-denoise-table``,
``dss-sweep``, ``dss-real-bench`` and the outlier study."""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

__all__ = ["REPO_ROOT", "resolve_repo_path", "safe_name", "plain", "test_split_shapes", "MESHLAB_SAMPLES",
           "meshlab_sample_cases", "case_list", "noise_as_diag_fraction", "make_case_arrays", "prepare_case",
           "load_case"]

REPO_ROOT = Path(__file__).resolve().parents[3]


def resolve_repo_path(p: str | os.PathLike) -> Path:
    """An absolute path as is; a relative one against the repository root."""
    p = Path(os.path.expanduser(str(p)))
    return p if p.is_absolute() else (REPO_ROOT / p).resolve()


def safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", str(name))


def plain(node) -> list | dict:
    """A config node (or None / a plain container) as a plain, resolved container."""
    if node is None:
        return []
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node


def _prep_config(preset: str):
    """The dss-prep :class:`~data_prep.shards.PrepConfig` of ``conf/prep_preset/<preset>.yaml``."""
    from data_prep.shards import PrepConfig

    conf = REPO_ROOT / "conf"
    path = conf / "prep_preset" / f"{preset}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise FileNotFoundError(f"generated.preset: {path} not found (known presets: {known})")
    base = OmegaConf.load(conf / "prep.yaml")
    for k in ("defaults", "hydra"):
        base.pop(k, None)
    return PrepConfig.from_config(OmegaConf.merge(base, OmegaConf.load(path)))


def test_split_shapes(count: int, preset: str = "cpu") -> list[dict]:
    """The first ``count`` shapes of ``preset``'s test split in the dss-prep plan's order
    (families interleave there, so up to 10 shapes are of different families; the first of the
    ``cpu`` preset is the shipped example's ``superquadric-0026``): case dicts."""
    if count <= 0:
        return []
    from data_prep.render_spec import load_render_spec
    from data_prep.shards import build_plan

    pc = _prep_config(preset)
    test = [s for s in build_plan(pc, load_render_spec()).shapes if s.split == "test"]
    if count > len(test):
        raise ValueError(f"generated.count={count}: the {preset} preset's test split has {len(test)} shapes")
    return [{"name": s.shape_id, "family": s.family, "index": s.index, "data_seed": pc.seed,
             "resolution": pc.resolution, "noise_levels": list(pc.noise_levels)} for s in test[:count]]


#: pymeshlab's sample meshes (its tests/sample_meshes folder): the issue's extra benchmark set
MESHLAB_SAMPLES = {"bunny": "bunny.obj", "cow": "cow.obj", "airplane": "airplane.obj", "bone": "bone.ply",
                   "face": "rangemaps/face000.ply"}


def meshlab_sample_cases() -> list[dict]:
    """``{name, mesh, held_out}`` cases for pymeshlab's sample meshes (the optional ``baselines``
    extra; never used for tuning, so held out); a clear error when pymeshlab or its sample folder
    is missing."""
    try:
        import pymeshlab
    except ImportError as e:
        raise RuntimeError("meshlab_samples=true needs pymeshlab (pip install -e '.[baselines]')") from e
    root = Path(pymeshlab.__file__).parent / "tests" / "sample_meshes"
    missing = [f for f in MESHLAB_SAMPLES.values() if not (root / f).is_file()]
    if missing:
        raise FileNotFoundError(f"meshlab_samples=true: {root} lacks {missing} (this pymeshlab build ships no samples)")
    return [{"name": name, "mesh": str(root / f), "held_out": True} for name, f in MESHLAB_SAMPLES.items()]


def case_list(cfg: DictConfig) -> list[dict]:
    """The configured cases (``cases``, pymeshlab's samples when ``meshlab_samples``, then the
    generated ones: ``generated.count`` tuning shapes and the next ``generated.held_out`` of the
    test split, held out), validated, as plain dicts. A case with ``held_out: true`` is scored in
    the table's held-out columns and means, apart from the tuning cases."""
    cases = [dict(c) for c in plain(cfg.get("cases"))]
    if cfg.get("meshlab_samples", False):
        cases += meshlab_sample_cases()
    gen = cfg.get("generated") or {}
    count, held = int(gen.get("count", 0) or 0), int(gen.get("held_out", 0) or 0)
    if count < 0 or held < 0:
        raise ValueError(f"generated.count and generated.held_out must be >= 0, got {count}, {held}")
    shapes = test_split_shapes(count + held, str(gen.get("preset", "cpu")))
    cases += shapes[:count] + [{**c, "held_out": True} for c in shapes[count:]]
    seen = set()
    for c in cases:
        if "name" not in c or not (("mesh" in c) ^ ("family" in c)):
            raise ValueError(f"cases: each entry needs a name and either mesh or family, got {c}")
        if c["name"] in seen:
            raise ValueError(f"cases: duplicate case name {c['name']!r}")
        seen.add(c["name"])
    return cases


def _level_index(noise: float, levels, unit: str = "diag") -> int:
    """dss-prep's noise-seed index of ``noise`` (its position among the preset's levels, so the
    shipped example is reproduced); an unlisted level (or any level in ``radius`` units) gets an
    index of its own."""
    if unit == "diag":
        for i, lv in enumerate(levels):
            if abs(float(lv) - noise) <= 1e-9 * max(1.0, noise):
                return i
    return (1000 if unit == "diag" else 2000) + int(round(noise * 1e6))


def noise_as_diag_fraction(points: np.ndarray, noise: float, unit: str) -> float:
    """``noise`` (a fraction of the bbox diagonal, ``unit="diag"``, or of the bounding-sphere
    radius of the score protocol, ``unit="radius"``: the farthest point's distance from the bbox
    centre) of the cloud ``points`` (N, 3), as a fraction of the bbox diagonal."""
    if unit == "diag":
        return float(noise)
    if unit != "radius":
        raise ValueError(f"noise unit must be 'diag' or 'radius', got {unit!r}")
    from dss.metrics import compute_normalization

    # each protocol's scale is 1 / its extent: radius / diagonal = paper scale / score scale
    return float(noise) * compute_normalization(points, "paper").scale / compute_normalization(points, "score").scale


def make_case_arrays(case: dict, points: int, noise: float, seed: int, outliers: float = 0.0,
                      unit: str = "diag"):
    """(mesh, clean Cloud (points, mesh normals), noisy (N, 3) float32, provenance dict).

    Generated shapes use dss-prep's seeds at ``seed`` 0 (the shipped example is reproduced); any
    other ``seed`` gives another sampling and noise draw of the same shape. ``outliers``: a
    fraction of ``points`` added to the noisy cloud, uniform in the clean cloud's bounding box.
    ``unit``: ``noise`` is a fraction of the clean cloud's bbox diagonal (``diag``) or of its
    bounding-sphere radius (``radius``, :func:`noise_as_diag_fraction`); provenance records the
    diagonal fraction used (``noise_diag``)."""
    from data_prep.sampling import measured_noise_std, noisy_copy, poisson_disk
    from data_prep.shapes import make_shape
    from data_prep.shapes.meshing import Mesh
    from data_prep.shards import noise_seed, shape_seed

    levels = case.get("noise_levels", [0.003, 0.01])
    if "family" in case:
        s = shape_seed(int(case.get("data_seed", 0)), case["family"], int(case.get("index", 0)))
        mesh = make_shape(case["family"], s, int(case.get("resolution", 96)))
        src = {"family": case["family"], "index": int(case.get("index", 0)), "shape_seed": s,
               "resolution": int(case.get("resolution", 96))}
        if int(seed):
            s = _seed_mix(s, int(seed))
            src["sample_seed"] = s
    else:
        from dss.metrics import load_mesh

        v, f = load_mesh(resolve_repo_path(case["mesh"]))
        mesh, s = Mesh(np.asarray(v, np.float64), np.asarray(f, np.int64)), int(seed)
        src = {"mesh": str(resolve_repo_path(case["mesh"])), "seed": s}
    clean = poisson_disk(mesh, points, s)
    ns = noise_seed(s, _level_index(noise, levels, unit))
    noise_diag = noise_as_diag_fraction(clean.points, noise, unit)
    noisy = noisy_copy(clean.points, noise_diag, ns)
    src.update(noise_seed=ns, noise_diag=round(noise_diag, 8), vertices=len(mesh.vertices), faces=len(mesh.faces),
               measured_noise=round(measured_noise_std(clean.points, noisy), 6))
    if outliers > 0:
        n_out = int(round(outliers * points))
        rng = np.random.default_rng(_seed_mix(ns, 2))
        lo, hi = clean.points.min(0), clean.points.max(0)
        extra = rng.uniform(lo, hi, size=(n_out, 3)).astype(noisy.dtype)
        noisy = np.concatenate([noisy, extra])[rng.permutation(len(noisy) + n_out)]
        src.update(outliers=n_out, outlier_fraction=float(outliers))
    return mesh, clean, noisy, src


def _seed_mix(a: int, b: int) -> int:
    """A 32-bit seed from two (stable across runs and platforms, unlike ``hash``)."""
    return int(np.random.SeedSequence([int(a), int(b)]).generate_state(1)[0])


def prepare_case(case: dict, root: Path, points: int, noise: float, seed: int, overwrite: bool = False,
                 outliers: float = 0.0, unit: str = "diag") -> dict:
    """Make (or reuse) ``root/{noisy,clean,mesh}.ply`` and ``root/case.json``; returns case.json,
    whose ``noise_diag`` is the case's noise as a bbox-diagonal fraction (``unit``: of ``noise``).

    A missing mesh file returns ``{"status": "skipped", "reason": ...}`` (nothing written). An
    existing case made with other settings is refused unless ``overwrite`` (then it is remade
    and its records are stale: the caller deletes them; ``case.json["remade"]`` says so).
    """
    import torch

    from dss.io_utils import atomic_write_json
    from dss.ply import write_ply

    # the case's identity (what its files depend on): not its name, not whether it is held out
    key = {"case": {k: v for k, v in case.items() if k not in ("name", "held_out")}, "points": int(points),
           "noise": float(noise), "seed": int(seed)}
    if outliers:  # only when used, so the cases of tables made before the option stay valid
        key["outliers"] = float(outliers)
    if unit != "diag":  # likewise
        key["noise_unit"] = unit
    if "mesh" in case:
        path = resolve_repo_path(case["mesh"])
        if not path.is_file():
            return {"name": case["name"], "status": "skipped", "key": key,
                    "reason": f"mesh file {path} not found (configured as {case['mesh']!r})"}
    meta_path = root / "case.json"
    files = [root / f for f in ("noisy.ply", "clean.ply", "mesh.ply")]
    if meta_path.is_file() and all(f.is_file() for f in files):
        meta = json.loads(meta_path.read_text())
        if meta.get("key") == key:
            return meta
        if not overwrite:
            raise ValueError(f"{root}: case {case['name']!r} was made with other settings ({meta.get('key')} vs "
                             f"{key}); use another out_dir or overwrite=true")
    t0 = time.perf_counter()
    prev = torch.get_num_threads()
    torch.set_num_threads(1)  # open3d's sample elimination and the noise are then reproducible
    try:
        mesh, clean, noisy, src = make_case_arrays(case, int(points), float(noise), int(seed), float(outliers), unit)
    finally:
        torch.set_num_threads(prev)
    root.mkdir(parents=True, exist_ok=True)
    write_ply(root / "mesh.ply", mesh.vertices, faces=mesh.faces)
    write_ply(root / "clean.ply", clean.points, normals=clean.normals)
    write_ply(root / "noisy.ply", noisy)
    meta = {"name": case["name"], "status": "ready", "key": key, "source": src, "points": int(points),
            "noise": float(noise), "noise_unit": unit, "noise_diag": src["noise_diag"],
            "seconds": round(time.perf_counter() - t0, 2),
            "remade": meta_path.is_file()}
    atomic_write_json(meta_path, meta)
    return meta


def load_case(case_dir: Path) -> dict:
    from dss.metrics import load_mesh, load_points

    return {"noisy": load_points(case_dir / "noisy.ply"), "clean": load_points(case_dir / "clean.ply"),
            "mesh": load_mesh(case_dir / "mesh.ply")}
