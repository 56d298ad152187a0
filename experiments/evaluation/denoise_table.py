"""``dss-denoise-table``: the paper's point cloud denoising comparison, in one resumable command.

    dss-denoise-table                                 # 20K points, 1% noise, every method
    dss-denoise-table noise=0.003                     # the 0.3% table
    dss-denoise-table out_dir=outputs/dss-denoise-table/<date>   # resume that run
    dss-denoise-table publish=true                    # + copy the summary to results/denoise/table_0.01_20000
    dss-denoise-table methods=[cgal_jet,dss_l0] 'dss_overrides=["optimizer.cycles=4"]'

Cases (``cases`` + ``meshlab_samples`` + ``generated``): the Kangaroo mesh (``../shared/data``,
skipped with the reason when absent), pymeshlab's sample meshes (bunny, cow, airplane, bone, face;
``meshlab_samples=true``, where the ``baselines`` extra is installed) and the first ``generated.count`` shapes of the ``cpu`` dss-prep preset's *test*
split in the plan's order, made exactly as dss-prep and ``experiments/apps/make_example.py`` make them
(the first is the shipped example: at 20K points and 1% noise its files are the shipped ones).
Each case: ``points`` Poisson-disk samples of the mesh (the clean cloud, ground truth with the
mesh) plus Gaussian noise of std ``noise`` x bbox diagonal (the noisy input), seeded, cached in
``out_dir/cases/<case>/{noisy,clean,mesh}.ply`` (+ ``case.json``).

Methods: the input itself (no method) and the Chamfer floor (a second clean sampling), every
baseline of :mod:`experiments.evaluation.baselines` (``preset_params(method, noise)``, run by
:func:`~experiments.evaluation.baselines.runner.run_method` in a subprocess with a time limit), and DSS
(``dss_pix2pix``: dss-denoise with the shipped model for ``noise``; ``dss_l0``: with the L0
image filter), each a ``python -m experiments.apps.denoise`` subprocess with a time limit. A crash,
hang or NaN output is a failure record; the table carries on.

Metrics: :func:`dss.metrics.evaluate` under ``protocol``: ``paper`` (clean cloud's bbox diagonal
= 1; ``noise`` is a fraction of the bbox diagonal, the DSS paper's levels 0.3%, 1%, 2%) or ``score``
(ScoreDenoise / IterativePFN: farthest clean point at distance 1 from the bbox centre; ``noise`` is a
fraction of that bounding-sphere radius, their levels 1%, 2%, 3%; each case's noise is converted to
the bbox-diagonal fraction that the baselines' presets and dss-denoise's model choice expect, and
recorded). CD x1e4, HD x1e3, P2M x1e4 (two-sided, PyTorch3D's definition), plus the method's wall time
(baselines: the method call in its worker; DSS: the outlier removal and the optimisation, i.e. rendering, reference
generation and updates, without start-up, file input and normal estimation).

Outputs in ``out_dir`` (a fresh ``outputs/dss-denoise-table/<date>`` unless given; atomic writes): ``records/<case>/<method>.json`` (one per run; an
existing one is reused unless ``overwrite=true``, so an interrupted run resumes), ``table.json``
(every record + per-method summary), ``table.md`` (rows = methods, columns = CD/HD/P2M per case,
means over cases, mean time; best per column in bold), ``accuracy_vs_time.png`` (mean CD and mean
P2M against mean time, Pareto front marked), ``README.md`` (the command), ``outputs/`` (each
method's cloud) and ``runs/`` (DSS run directories with their logs). ``publish=true`` copies
``table.md``, ``table.json``, the chart, ``README.md`` and ``config.yaml`` to ``published_dir``
(under ``results/``, tracked), replacing what was there.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from experiments.evaluation.baselines.methods import METHODS, preset_params
from experiments.evaluation.baselines.runner import run_method, tail_text, wait_or_kill

log = logging.getLogger(__name__)

__all__ = ["run", "main", "REPO_ROOT", "resolve_repo_path", "test_split_shapes", "prepare_case",
           "render_markdown", "summarize"]

REPO_ROOT = Path(__file__).resolve().parents[2]
PROTOCOL = "paper"  # the default protocol; ``protocol=score`` switches metrics and noise unit
#: the unit of ``noise`` under each protocol
NOISE_UNIT = {"paper": "diag", "score": "radius"}
METRIC_KEYS = ("chamfer", "hausdorff", "p2m")
METRIC_NAMES = {"chamfer": "CD", "hausdorff": "HD", "p2m": "P2M"}
# the two one-sided halves of CD: accuracy (output -> clean) and coverage (clean -> output)
HALF_KEYS = ("chamfer_pred_to_gt", "chamfer_gt_to_pred")
#: statuses whose record still carries metrics (the output exists and is finite)
SCORED = ("ok", "worse_than_input", "reference")
#: fixed arguments of every DSS run: its own metrics and floor are not needed (scored here)
DSS_BASE = ["progress=false", "metrics.protocols=[paper]", "metrics.floor=false", "figures.enabled=false",
            "overwrite=true"]


def resolve_repo_path(p: str | os.PathLike) -> Path:
    """An absolute path as is; a relative one against the repository root."""
    p = Path(os.path.expanduser(str(p)))
    return p if p.is_absolute() else (REPO_ROOT / p).resolve()


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", str(name))


def _versions() -> dict:
    import platform
    from importlib import metadata

    out = {"python": platform.python_version()}
    for pkg in ("dss-splatting", "numpy", "torch", "open3d", "onnxruntime", "cgal", "pymeshlab"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    return out


# ------------------------------------------------------------------------------ cases
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
    cases = [dict(c) for c in _plain(cfg.get("cases"))]
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


def _make_case_arrays(case: dict, points: int, noise: float, seed: int, outliers: float = 0.0,
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
        mesh, clean, noisy, src = _make_case_arrays(case, int(points), float(noise), int(seed), float(outliers), unit)
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


# ------------------------------------------------------------------------------ scoring
def _score(pred: np.ndarray, gt: dict) -> dict:
    """Metrics of ``pred`` (N, 3) against the case's clean cloud and mesh under ``gt["protocol"]``."""
    from dss.metrics import evaluate

    d = evaluate(pred, gt["clean"], gt["mesh"], gt["protocol"]).to_dict()
    d.pop("normalization", None)
    return d


def _judge(rec: dict, pred: np.ndarray | None, gt: dict) -> dict:
    """Fill ``rec["metrics"]`` from ``pred`` and settle ``nan`` / ``worse_than_input`` / ``ok``."""
    if pred is None:
        return rec
    if pred.ndim != 2 or pred.shape[1:] != (3,) or len(pred) == 0:
        rec.update(status="invalid_output", failed=True, message=f"output has shape {pred.shape}, expected (M>0, 3)")
        return rec
    if not np.isfinite(pred).all():
        rec.update(status="nan", failed=True,
                   message=f"{int((~np.isfinite(pred)).any(1).sum())} of {len(pred)} output points are NaN/Inf")
        return rec
    rec["metrics"] = _score(pred, gt)
    cd, cd_in = rec["metrics"]["chamfer"], gt["input_chamfer"]
    if cd > cd_in:
        rec.update(status="worse_than_input", message=f"Chamfer x1e4 {cd:.4g} > input {cd_in:.4g}")
    elif rec["status"] in ("ok", "worse_than_input"):
        rec.update(status="ok", message="")
    rec["failed"] = rec["status"] != "ok"
    return rec


def _save_output(out: Path | None, pts: np.ndarray | None) -> str | None:
    if out is None or pts is None or not np.isfinite(pts).all():
        return None
    from dss.ply import write_ply

    out.parent.mkdir(parents=True, exist_ok=True)
    write_ply(out, pts)
    return str(out)


# ------------------------------------------------------------------------------ methods
def method_list(cfg: DictConfig) -> list[str]:
    """The method labels to run, validated (unknown names are refused before any work)."""
    dss, custom = dict(cfg.dss_methods or {}), dict(cfg.custom_methods or {})
    names = cfg.methods
    if isinstance(names, str):
        if names != "all":
            raise ValueError(f"methods must be 'all' or a list, got {names!r}")
        return [*METHODS, *dss, *custom]
    names = [str(m) for m in names]
    known = [*METHODS, *dss, *custom]
    bad = [m for m in names if m not in known]
    if bad:
        raise ValueError(f"methods: unknown {bad}; known: {known} (custom ones go in custom_methods)")
    if len(set(names)) != len(names):
        raise ValueError(f"methods: duplicates in {names}")
    return names


def _prefilter_outliers(noisy: np.ndarray) -> tuple[np.ndarray, dict]:
    """``noisy`` (N, 3) without the points dss-denoise's outlier removal drops (the same
    :func:`dss.pointcloud.find_outliers` parameters, conf/denoise.yaml ``outliers``), and a report."""
    import torch

    from dss.pointcloud import find_outliers
    from experiments.denoising.inputs import outlier_params

    params = outlier_params(OmegaConf.load(REPO_ROOT / "conf" / "denoise.yaml").outliers)
    t0 = time.perf_counter()
    bad = find_outliers(torch.from_numpy(np.ascontiguousarray(noisy, np.float32)), **params).numpy()
    return noisy[~bad], {"removed": int(bad.sum()), "seconds": time.perf_counter() - t0, **params}


def _run_baseline(spec: str, gt: dict, params: dict, limit: float,
                  threads: int | None, out_ply: Path | None, prefilter: bool = False) -> dict:
    """One baseline on one case through the subprocess runner; a JSON-ready record.
    ``prefilter``: the baseline gets the noisy cloud after dss-denoise's outlier removal (its time
    is added to the method's; the record's ``prefilter`` says how many points went)."""
    noisy, pre = gt["noisy"], None
    if prefilter:
        if "prefiltered" not in gt:  # once per case: every baseline gets the same filtered cloud
            gt["prefiltered"] = _prefilter_outliers(noisy)
        noisy, pre = gt["prefiltered"]
    res = run_method(spec, noisy, params=params, time_limit=limit, clean=gt["clean"], protocol=gt["protocol"],
                     threads=threads)
    r = res.record
    rec = {"kind": "baseline", "spec": spec, "params": r.params, "resolved": r.resolved, "status": r.status,
           "failed": r.failed, "message": r.message, "time_s": r.wall_s, "cpu_s": r.cpu_s,
           "total_s": r.total_s,
           "time_limit_s": limit, "n_out": r.n_out, "versions": r.versions, "signal": r.signal,
           "stderr_tail": r.stderr_tail[-1500:] if r.failed and r.status != "worse_than_input" else ""}
    if pre is not None:
        rec["prefilter"] = dict(pre)
        if rec["time_s"] is not None:
            rec["time_s"] += pre["seconds"]
    pts = res.points
    rec = _judge(rec, pts, gt)
    rec["output"] = _save_output(out_ply, pts) if rec.get("metrics") else None
    return rec


def _hydra_value(s: str) -> str:
    """A path as a Hydra override value (quoted unless plainly safe)."""
    return s if re.fullmatch(r"[A-Za-z0-9_./-]+", s) else "'" + s.replace("\\", "\\\\").replace("'", "\\'") + "'"


def _run_dss(overrides: list[str], case_dir: Path, gt: dict, noise: float, limit: float,
             threads: int | None, run_dir: Path, out_ply: Path | None) -> dict:
    """One dss-denoise subprocess on one case (its own process group, killed at ``limit`` s);
    its run directory (config.yaml, metrics.json, dss.log, figures) is ``run_dir``."""
    run_dir.mkdir(parents=True, exist_ok=True)
    args = [f"input={_hydra_value(str(case_dir / 'noisy.ply'))}", f"clean={_hydra_value(str(case_dir / 'clean.ply'))}",
            f"mesh={_hydra_value(str(case_dir / 'mesh.ply'))}", f"hydra.run.dir={_hydra_value(str(run_dir))}",
            f"noise={noise}", *DSS_BASE, *([f"threads={int(threads)}"] if threads else []), *overrides]
    env = dict(os.environ)
    if threads:
        for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env[k] = str(int(threads))
    env["PYTHONPATH"] = str(REPO_ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    rec = {"kind": "dss", "spec": "experiments.apps.denoise", "params": {"overrides": list(overrides)},
           "command": shlex.join(["python", "-m", "experiments.apps.denoise", *args]), "status": "crash",
           "failed": True, "message": "", "time_s": None, "total_s": None, "time_limit_s": limit,
           "run_dir": str(run_dir)}
    logf = run_dir / "dss.log"
    t0 = time.perf_counter()
    with open(logf, "wb") as lf:
        proc = subprocess.Popen([sys.executable, "-m", "experiments.apps.denoise", *args], stdout=lf,
                                stderr=subprocess.STDOUT, env=env, cwd=str(REPO_ROOT), start_new_session=True)
        code = wait_or_kill(proc, limit)
        if code is None:
            rec.update(status="timeout", message=f"killed after the time limit of {limit:g} s",
                       total_s=time.perf_counter() - t0, stderr_tail=tail_text(logf, 1500))
            return rec
    rec["total_s"], rec["exit_code"] = time.perf_counter() - t0, code
    mpath, ply = run_dir / "metrics.json", run_dir / "denoised.ply"
    if code != 0 or not mpath.is_file() or not ply.is_file():
        sig = f"signal {signal.Signals(-code).name}" if code < 0 else f"exit code {code}"
        rec.update(message=f"dss-denoise failed ({sig}); see {logf}", stderr_tail=tail_text(logf, 1500))
        return rec
    m = json.loads(mpath.read_text())
    t_opt = m.get("time_s", {}).get("optimization")
    # the method's time: the optimisation plus the outlier removal before it
    rec["time_s"] = None if t_opt is None else t_opt + float((m.get("outliers") or {}).get("seconds") or 0.0)
    cpu = m.get("profile_cpu_s") or {}
    # the same stages in process CPU seconds (with one thread: the wall time on an idle machine)
    rec["cpu_s"] = cpu["optimization"] + cpu.get("outliers", 0.0) if "optimization" in cpu else None
    rec["outliers_removed"] = (m.get("outliers") or {}).get("removed")
    rec["reference"] = {k: m.get("reference", {}).get(k) for k in ("name", "model", "noise_level", "selection")}
    rec["versions"] = _versions()
    try:
        pts = _load_raw_points(ply)  # NaN rows kept: a NaN output must be seen, not dropped
    except Exception as e:  # noqa: BLE001 - an unreadable output is this method's failure
        rec.update(status="invalid_output", message=f"{ply}: unreadable ({e})")
        return rec
    rec["status"], rec["n_out"] = "ok", int(len(pts))
    rec = _judge(rec, pts, gt)
    rec["output"] = _save_output(out_ply, pts) if rec.get("metrics") else None
    return rec


def _load_raw_points(path: Path) -> np.ndarray:
    """(N, 3) float64 vertex positions, NaN/inf rows kept."""
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    return np.asarray(pc.points, dtype=np.float64)


def _plain(node) -> list | dict:
    """A config node (or None / a plain container) as a plain, resolved container."""
    if node is None:
        return []
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node


def _request(label: str, cfg: DictConfig, noise: float) -> dict:
    """What determines a (case, method) record besides the case: a stored record is reused only
    when its request is the same."""
    dss = dict(cfg.dss_methods or {})
    if label in dss:
        ovr = [*_plain(dss[label]), *_plain(cfg.get("dss_overrides"))]
        if int(cfg.get("seed", 0)):  # another draw of the cases: DSS's own random views follow it
            ovr.append(f"seed={int(cfg.seed)}")
        # threads=null gives "...=None", which Hydra would read as a string
        req = {"kind": "dss", "overrides": [re.sub(r"=None$", "=null", str(o)) for o in ovr]}
        model = shipped_model_for(req["overrides"], noise)
        if model is not None:  # a retrained shipped model makes its stored records stale
            req["model_sha256"] = file_sha256(model)[:16]
        return req
    spec = str((cfg.custom_methods or {}).get(label, label))
    extra = (_plain(cfg.get("params")) or {}).get(label) or {}
    req = {"kind": "baseline", "spec": spec, "params": {**preset_params(spec, noise), **(extra or {})}}
    if cfg.get("baseline_outlier_removal", False):  # only when on: records made before stay valid
        req["prefilter"] = "outliers"
    return req


def shipped_model_for(overrides: list[str], noise: float) -> Path | None:
    """The shipped ONNX model a dss-denoise run with these overrides uses at ``noise`` (bbox
    diagonal fraction): ``reference=onnx`` without an explicit ``reference.model``; else None."""
    if "reference=onnx" not in overrides:
        return None
    given = [o for o in overrides if o.startswith("reference.model=")]
    if given and given[-1].split("=", 1)[1] not in ("auto", "null"):
        return None
    from experiments.denoising.reference_generators import select_model

    return Path(select_model(noise)[0])


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file's bytes (cached while its size and modification time stay)."""
    st = Path(path).stat()
    return _sha256_cached(str(Path(path).resolve()), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=16)
def _sha256_cached(path: str, size: int, mtime_ns: int) -> str:
    import hashlib

    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _check_params(cfg: DictConfig, methods: list[str], noise: float) -> None:
    """Unknown parameter names of registered baselines are refused before any work."""
    for label in methods:
        req = _request(label, cfg, noise)
        if req["kind"] == "baseline" and req["spec"] in METHODS:
            bad = sorted(set(req["params"]) - set(METHODS[req["spec"]].defaults))
            if bad:
                raise ValueError(f"params.{label}: unknown parameter(s) {bad}; accepted: "
                                 f"{sorted(METHODS[req['spec']].defaults)}")


def _reusable(rec: dict | None, req: dict, limit: float) -> bool:
    if not rec or rec.get("request") != req:
        return False
    # a run killed by a shorter limit than the one asked now is retried
    return not (rec.get("status") == "timeout" and limit > float(rec.get("time_limit_s") or 0))


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _reference_record(kind: str, case: str, pts: np.ndarray, gt: dict, extra: dict | None = None) -> dict:
    """The ``input`` (noisy cloud) or ``floor`` (second clean sampling) row of a case."""
    return {"case": case, "method": kind, "kind": kind, "status": "reference", "failed": False, "message": "",
            "params": extra or {}, "metrics": _score(pts, gt), "time_s": None, "n_out": len(pts)}


# ------------------------------------------------------------------------------ the table
def _mean(vals: list[float]) -> float | None:
    vals = [v for v in vals if v is not None and math.isfinite(v)]
    return float(np.mean(vals)) if vals else None


def summarize(records: list[dict], methods: list[str], cases: list[str], held_out=()) -> list[dict]:
    """Per-method rows: ``{"method", "kind", "cases": {case: {"status", "message", chamfer,
    hausdorff, p2m}}, "mean": {metric: mean over the scored tuning cases}, "n_scored",
    "complete", "time_s" (mean over the scored tuning cases), "pareto": {metric: bool}}``, and,
    when some of ``cases`` are in ``held_out``, the same over those: ``"mean_held_out"``,
    ``"n_scored_held_out"``, ``"complete_held_out"``; ``cases``: the non-skipped case names (the
    table's columns)."""
    held = [c for c in cases if c in set(held_out)]
    tuning = [c for c in cases if c not in set(held_out)]
    from experiments.evaluation.baselines.aggregate import pareto_front

    rows = []
    for label in ["input", "floor", *methods]:
        recs = {r["case"]: r for r in records if r["method"] == label and r["case"] in cases}
        if not recs:
            continue
        cells = {}
        for c in cases:
            r = recs.get(c, {"status": "missing", "message": "no record"})
            m = r.get("metrics") or {}
            cells[c] = {"status": r["status"], "message": r.get("message", ""), "time_s": r.get("time_s"),
                        "cpu_s": r.get("cpu_s"),
                        **{k: m.get(k) for k in METRIC_KEYS + HALF_KEYS}}
        scored = [c for c in tuning if cells[c]["chamfer"] is not None]
        row = {"method": label, "kind": next(iter(recs.values())).get("kind"), "cases": cells,
               "mean": {k: _mean([cells[c][k] for c in scored]) for k in METRIC_KEYS + HALF_KEYS},
               "n_scored": len(scored), "complete": bool(tuning) and len(scored) == len(tuning),
               "time_s": _mean([cells[c]["time_s"] for c in scored]),
               "cpu_s": _mean([cells[c]["cpu_s"] for c in scored]),
               "statuses": sorted({cells[c]["status"] for c in cases})}
        if held:
            scored_h = [c for c in held if cells[c]["chamfer"] is not None]
            row.update({"mean_held_out": {k: _mean([cells[c][k] for c in scored_h]) for k in METRIC_KEYS + HALF_KEYS},
                        "n_scored_held_out": len(scored_h), "complete_held_out": len(scored_h) == len(held)})
        rows.append(row)
    methods_rows = [r for r in rows if r["kind"] not in ("input", "floor") and r["complete"]]
    # the Pareto front and the chart on CPU seconds when every method has them (one thread per
    # method: what an idle machine gives, whatever else ran), else on wall time
    clock = "cpu_s" if methods_rows and all(r.get("cpu_s") is not None for r in methods_rows) else "time_s"
    ranked = [r for r in methods_rows if r[clock] is not None]
    for r in rows:
        r["pareto"], r["clock"] = {}, clock
    for k in ("chamfer", "p2m"):
        front = pareto_front([r[clock] for r in ranked],
                             [np.nan if r["mean"][k] is None else r["mean"][k] for r in ranked])
        for r, f in zip(ranked, front):
            r["pareto"][k] = bool(f)
    return rows


def _fmt(v: float | None) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.4g}"


def render_markdown(rows: list[dict], case_info: list[dict], title: str, notes: list[str]) -> str:
    """The paper-style table: rows = methods, columns = CD/HD/P2M per case, means, time; the best
    method value per column in bold (input and floor rows excluded; means only of complete rows);
    a failure shows as its status; † marks an output worse than the noisy input (Chamfer).
    Held-out cases (``held_out`` in their case dict) come after the tuning cases, marked in the
    header, with their own means (``held-out mean``)."""
    held = {c["name"] for c in case_info if c.get("held_out")}
    names = [c["name"] for c in case_info if c["status"] != "skipped"]
    cases = [c for c in names if c not in held] + [c for c in names if c in held]
    agg = ["mean"] + (["held-out mean"] if any(c in held for c in cases) else [])
    cols = ([(c, k) for c in cases for k in METRIC_KEYS] + [(a, k) for a in agg for k in METRIC_KEYS]
            + [("time", None), ("cpu", None)])
    aggregate = {"mean": ("mean", "complete"), "held-out mean": ("mean_held_out", "complete_held_out")}

    def value(r, c, k):
        if c in aggregate:
            return (r.get(aggregate[c][0]) or {}).get(k)
        if c in ("time", "cpu"):
            return r.get(f"{c}_s")
        return r["cases"][c][k]

    def complete(r, c):
        return r.get(aggregate[c][1], False) if c in aggregate else (r["complete"] if c in ("time", "cpu") else True)

    best = {}
    for c, k in cols:
        vals = [value(r, c, k) for r in rows if r["kind"] not in ("input", "floor") and complete(r, c)]
        vals = [v for v in vals if v is not None and math.isfinite(v)]
        best[(c, k)] = min(vals) if vals else None

    head = ["method"] + [f"{c}{' (held out)' if c in held else ''} {METRIC_NAMES[k]}" if k
                         else {"time": "time (s)", "cpu": "CPU (s)"}[c] for c, k in cols]
    lines = [f"# {title}", "", *[f"- {n}" for n in notes], "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    labels = {"input": "input (noisy)", "floor": "floor (2nd clean sampling)"}
    for r in rows:
        out = [labels.get(r["method"], r["method"])]
        for c, k in cols:
            v = value(r, c, k)
            if c not in aggregate and c not in ("time", "cpu") and v is None:
                out.append(r["cases"][c]["status"])
                continue
            s = _fmt(v)
            if c in aggregate and v is not None and not complete(r, c):
                n = r["n_scored"] if c == "mean" else r.get("n_scored_held_out", 0)
                s += f" ({n}/{sum((x in held) == (c != 'mean') for x in cases)})"
            elif (v is not None and best[(c, k)] is not None and v == best[(c, k)] and r["kind"] not in ("input", "floor")
                  and complete(r, c)):
                s = f"**{s}**"
            if c not in aggregate and k == "chamfer" and r["cases"][c]["status"] == "worse_than_input":
                s += " †"
            out.append(s)
        lines.append("| " + " | ".join(out) + " |")
    lines += ["", "† worse than the noisy input (Chamfer). Means over cases: `(k/n)` when only k of the n "
              "cases have a result (not ranked). time: mean method wall time over the scored cases; CPU: "
              "the same stages' process CPU seconds (with one thread per method, the wall time an idle "
              "machine would give)."
              + (" mean: over the tuning cases (the settings were chosen on them); held-out mean: over the "
                 "cases marked (held out), which were not looked at while tuning." if len(agg) > 1 else ""), "",
              "## Accuracy and coverage", "",
              "CD = accuracy + coverage: the mean squared distance from each output point to the clean cloud, "
              "and from each clean point to the output (x1e4). A method that moves points sideways into "
              "clumps keeps its accuracy but loses coverage.", "",
              "| method | mean accuracy (output -> clean) | mean coverage (clean -> output) |", "|---|---|---|"]
    for r in rows:
        if r["complete"] or r["kind"] in ("input", "floor"):
            lines.append(f"| {labels.get(r['method'], r['method'])} | {_fmt(r['mean'].get(HALF_KEYS[0]))} | "
                         f"{_fmt(r['mean'].get(HALF_KEYS[1]))} |")
    lines += ["", "## Cases", "", "noise: the configured level (its unit in the title); noise (x diag): the same as a fraction "
              "of the clean bbox diagonal (what the baselines' presets and dss-denoise were given); measured noise: "
              "std of the noisy - clean offsets per axis, x diag.", "",
              "| case | source | points | noise | noise (x diag) | measured noise | status |", "|---|---|---|---|---|---|---|"]
    for c in case_info:
        src = c.get("source") or c.get("key", {}).get("case", {})
        src_s = src.get("mesh") or f"{src.get('family')} #{src.get('index')} (shape seed {src.get('shape_seed')})"
        st = "skipped: " + c["reason"] if c["status"] == "skipped" else "ok"
        lines.append(f"| {c['name']} | {src_s} | {c['key']['points']} | {c['key']['noise']:g} | "
                     f"{_fmt(c.get('noise_diag', c['key']['noise']))} | "
                     f"{_fmt((c.get('source') or {}).get('measured_noise'))} | {st} |")
    fails = [(c, r["method"], r["cases"][c]) for r in rows for c in cases
             if r["cases"][c]["status"] not in SCORED]
    if fails:
        lines += ["", "## Failures", "", "| case | method | status | message |", "|---|---|---|---|"]
        lines += [f"| {c} | {m} | {cell['status']} | {str(cell['message']).replace('|', '/')[:200]} |"
                  for c, m, cell in fails]
    return "\n".join(lines) + "\n"


def _label_points(ax, items: list[tuple[float, float, str]], fontsize: float = 7.0) -> None:
    """Name each point beside it; labels that would overlap an earlier one move down in steps of
    a line, with a leader line back to their point. The DSS variants sit within a few percent of
    each other in both time and error, so plain offsets put their names on top of each other."""
    ax.figure.canvas.draw()  # fixes the limits and scales the display transform needs
    scale = ax.figure.dpi / 72.0  # points -> pixels
    line, placed = fontsize * 1.35 * scale, []
    for x, y, text in sorted(items, key=lambda it: -it[1]):
        px, py = ax.transData.transform((x, y))
        w = len(text) * fontsize * 0.6 * scale
        lx, ly = px + 3 * scale, py + 3 * scale
        if lx + w > ax.bbox.x1:  # near the right edge: name it on the left
            lx = px - 3 * scale - w
        while any(lx < bx + bw and bx < lx + w and abs(ly - by) < line for bx, by, bw in placed):
            ly -= line
        placed.append((lx, ly, w))
        moved = abs(ly - (py + 3 * scale)) > 0.5
        ax.annotate(text, (x, y), fontsize=fontsize, xytext=((lx - px) / scale, (ly - py) / scale),
                    textcoords="offset points",
                    arrowprops={"arrowstyle": "-", "color": "0.35", "lw": 0.6, "shrinkA": 0,
                                "shrinkB": 3} if moved else None)


def plot_accuracy_vs_time(rows: list[dict], path: Path, title: str, protocol: str = PROTOCOL) -> Path | None:
    """Mean CD and mean P2M (x1e4, ``protocol``) against mean CPU seconds per method (wall time
    when some method has none; complete rows), the
    Pareto front (lower time and error) marked, the input and the floor as horizontal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dss.io_utils import atomic_savefig

    clock = next((r["clock"] for r in rows if r.get("clock")), "time_s")
    pts = [r for r in rows if r["kind"] not in ("input", "floor") and r["complete"] and r.get(clock)]
    ref = {r["kind"]: r for r in rows if r["kind"] in ("input", "floor")}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, k in zip(axes, ("chamfer", "p2m")):
        good = [r for r in pts if r["mean"][k] is not None]
        for r in good:
            on = r["pareto"].get(k, False)
            ax.scatter(r[clock], r["mean"][k], s=36, zorder=3, color="C3" if r["kind"] == "dss" else "C0")
            if on:
                ax.scatter(r[clock], r["mean"][k], s=150, facecolors="none", edgecolors="k", lw=1.4, zorder=4)
        front = sorted((r[clock], r["mean"][k]) for r in good if r["pareto"].get(k))
        if front:
            ax.step(*zip(*front), where="post", color="k", ls="--", lw=1, zorder=2, label="Pareto front")
        for kind, style in (("input", ":"), ("floor", "-.")):
            v = ref.get(kind, {}).get("mean", {}).get(k)
            if v is not None:
                ax.axhline(v, color="0.5", ls=style, lw=1, label=f"{kind} ({v:.3g})")
        times = [r[clock] for r in good]
        if times and min(times) > 0 and max(times) / min(times) > 20:
            from matplotlib.ticker import NullFormatter, ScalarFormatter

            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(ScalarFormatter())  # 1, 10, 100, not 10^0 ...
            ax.xaxis.set_minor_formatter(NullFormatter())  # minor labels overlap on short ranges
        _label_points(ax, [(r[clock], r["mean"][k], r["method"]) for r in good])
        ax.set_xlabel("mean CPU seconds per case (one thread)" if clock == "cpu_s" else "mean wall time per case (s)")
        ax.set_ylabel(f"mean {METRIC_NAMES[k]} x1e4 ({protocol} protocol)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title + "  (red: DSS; circled: Pareto front; failed methods not shown)", fontsize=9)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------ the app
def _load_gt(case_dir: Path) -> dict:
    from dss.metrics import load_mesh, load_points

    return {"noisy": load_points(case_dir / "noisy.ply"), "clean": load_points(case_dir / "clean.ply"),
            "mesh": load_mesh(case_dir / "mesh.ply")}


def _reference_rows(name: str, gt: dict, rdir: Path, floor: bool, seed: int, overwrite: bool) -> list:
    from dss.io_utils import atomic_write_json
    from dss.metrics import sample_poisson_disk

    out = []
    for kind in ("input", "floor") if floor else ("input",):
        path = rdir / f"{kind}.json"
        rec = None if overwrite else _read_json(path)
        if rec is None:
            if kind == "input":
                rec = _reference_record("input", name, gt["noisy"], gt)
            else:  # Poisson-disk samples of the mesh with another seed, scored against the clean cloud
                rec = _reference_record("floor", name, sample_poisson_disk(gt["mesh"], len(gt["clean"]), seed + 1),
                                        gt, {"seed": seed + 1})
            atomic_write_json(path, rec)
        out.append(rec)
    return out


def run(cfg: DictConfig, command: str | None = None) -> dict:
    """Build the table (see the module docstring); returns ``{"out_dir", "records", "rows",
    "cases", "files", "time_s"}``. ``command``: the command line recorded in README.md."""
    from tqdm.auto import tqdm

    from dss.io_utils import atomic_write_json, atomic_write_text
    from experiments.common import save_config

    t0 = time.perf_counter()
    noise, points, seed = float(cfg.noise), int(cfg.points), int(cfg.seed)
    outliers = float(cfg.get("outliers", 0.0) or 0.0)
    protocol = str(cfg.get("protocol", PROTOCOL))
    if protocol not in NOISE_UNIT:
        raise ValueError(f"protocol must be one of {sorted(NOISE_UNIT)}, got {protocol!r}")
    unit = NOISE_UNIT[protocol]
    unit_name = {"diag": "bbox diagonal", "radius": "bounding-sphere radius"}[unit]
    if not (noise > 0 and math.isfinite(noise)):
        raise ValueError(f"noise must be a positive fraction of the {unit_name}, got {cfg.noise}")
    if not (0.0 <= outliers <= 1.0):
        raise ValueError(f"outliers must be a fraction of points in [0, 1], got {cfg.outliers}")
    if points < 32:
        raise ValueError(f"points must be >= 32, got {points}")
    methods = method_list(cfg)
    _check_params(cfg, methods, noise)
    cases = case_list(cfg)
    out = Path(os.path.expanduser(str(cfg.out_dir))).absolute()
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out)
    threads = int(cfg.threads) if cfg.get("threads") else None
    overwrite, dss_methods = bool(cfg.get("overwrite", False)), dict(cfg.dss_methods or {})
    records, case_info = [], []
    bar = tqdm(total=len(cases) * len(methods), desc="denoise table", unit="run",
               disable=not cfg.get("progress", True), dynamic_ncols=True)
    for case in cases:
        name = case["name"]
        cdir, rdir = out / "cases" / _safe(name), out / "records" / _safe(name)
        bar.set_description(f"{name}: preparing")
        meta = prepare_case(case, cdir, points, noise, seed, overwrite, outliers, unit)
        case_info.append(meta)
        if meta["status"] == "skipped":
            log.warning("case %s skipped: %s", name, meta["reason"])
            records += [{"case": name, "method": m, "kind": None, "status": "skipped", "failed": True,
                         "message": meta["reason"], "metrics": None} for m in ["input", *methods]]
            bar.update(len(methods))
            continue
        if meta.get("remade"):
            for f in rdir.glob("*.json"):  # made for the old case files
                f.unlink()
        rdir.mkdir(parents=True, exist_ok=True)
        gt = _load_gt(cdir)
        gt["protocol"] = protocol
        case_noise = float(meta.get("noise_diag", noise))  # what presets and dss-denoise expect
        refs = _reference_rows(name, gt, rdir, bool(cfg.get("floor", True)), seed, overwrite)
        records += refs
        gt["input_chamfer"] = refs[0]["metrics"]["chamfer"]
        for label in methods:
            path = rdir / f"{_safe(label)}.json"
            req = _request(label, cfg, case_noise)
            limit = float((cfg.time_limits or {}).get(label, cfg.time_limit_s))
            old = None if overwrite else _read_json(path)
            if _reusable(old, req, limit):
                records.append(old)
                bar.update(1)
                continue
            bar.set_description(f"{name}: {label}")
            out_ply = out / "outputs" / _safe(name) / f"{_safe(label)}.ply" if cfg.get("save_outputs", True) else None
            if label in dss_methods:
                rec = _run_dss(req["overrides"], cdir, gt, case_noise, limit, threads,
                               out / "runs" / _safe(name) / _safe(label), out_ply)
            else:
                rec = _run_baseline(req["spec"], gt, req["params"], limit, threads, out_ply,
                                    prefilter=req.get("prefilter") == "outliers")
            rec = {"case": name, "method": label, **rec, "request": req}
            atomic_write_json(path, rec)
            cd = (rec.get("metrics") or {}).get("chamfer")
            log.info("%s / %s: %s%s (%s s)", name, label, rec["status"], f", CD x1e4 {cd:.4g}" if cd else "",
                     _fmt(rec.get("time_s")))
            records.append(rec)
            bar.update(1)
    bar.close()

    ready = [c["name"] for c in case_info if c["status"] != "skipped"]
    held_out = {c["name"] for c in cases if c.get("held_out")}
    for meta in case_info:  # the table's markdown reads it from the case info
        meta["held_out"] = meta["name"] in held_out
    rows = summarize(records, methods, ready, held_out)
    title = f"Point cloud denoising: {points} points, noise {noise:g} x {unit_name}" + (
        f", {outliers:.3g} x {points} uniform outliers" if outliers else "") + (f", seed {seed}" if seed else "") + (
        ", baselines after DSS's outlier removal" if cfg.get("baseline_outlier_removal", False) else "")
    scale = {"paper": "bbox diagonal 1", "score": "farthest point at distance 1"}[protocol]
    notes = [f"`{protocol}` protocol (dss/metrics.py): clean cloud's bbox centred, {scale}; CD x1e4, HD x1e3 "
             "(symmetric, not squared), P2M x1e4 (two-sided, PyTorch3D's point_mesh_face_distance, exact "
             "triangle distances); lower is better",
             "time: baselines: the method call in its worker process; DSS: the outlier removal and the optimisation (rendering, "
             "reference generation, updates), without start-up, file input and normal estimation",
             f"threads per method: {threads or 'default'}; time limit {cfg.time_limit_s:g} s per run"
             + (f" (per method: {dict(cfg.time_limits)})" if cfg.time_limits else ""),
             f"DSS overrides: {_plain(cfg.get('dss_overrides'))}; baseline parameters: "
             "preset_params(method, case noise as a bbox-diagonal fraction) (+ params), see table.json"]
    md = render_markdown(rows, case_info, title, notes)
    files = {"markdown": "table.md", "json": "table.json", "readme": "README.md", "config": "config.yaml"}
    if rows and plot_accuracy_vs_time(rows, out / "accuracy_vs_time.png", title, protocol):
        files["chart"] = "accuracy_vs_time.png"
    elapsed = time.perf_counter() - t0
    result = {"title": title, "protocol": protocol, "noise_unit": unit, "points": points, "noise": noise, "seed": seed,
              "outliers": outliers,
              "methods": methods, "cases": case_info, "rows": rows, "records": records, "versions": _versions(),
              "config": OmegaConf.to_container(cfg, resolve=True), "time_s": elapsed, "files": files,
              "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}
    atomic_write_json(out / "table.json", result)
    atomic_write_text(out / "table.md", md)
    command = command or "python -c 'experiments.evaluation.denoise_table.run(cfg)' (the config is config.yaml)"
    atomic_write_text(out / "README.md", (
        f"# {title}\n\nProduced by (from the repository root):\n\n```\n{command}\n```\n\n"
        f"Last run: {time.strftime('%Y-%m-%d %H:%M:%S')}, {elapsed:.0f} s (resumed records not rerun), "
        f"{os.cpu_count()} CPU cores, load average {result['load_average']}.\n\n"
        "Files: `table.md` (the table), `table.json` (every record: case, method, parameters, status, "
        "metrics, times, versions), `accuracy_vs_time.png`, `config.yaml`, `cases/` (noisy, clean, mesh "
        "PLYs), `records/` (one JSON per case and method; delete one to rerun it), `outputs/` (each "
        "method's cloud), `runs/` (DSS run directories and logs).\n"))
    published = []
    if cfg.get("publish", False):
        from experiments import outputs

        published = [str(p) for p in outputs.publish_files(out, Path(str(cfg.published_dir)), list(files.values()))]
    return {"out_dir": str(out), "records": records, "rows": rows, "cases": case_info, "files": files,
            "time_s": elapsed, "markdown": md, "published": published}


@hydra.main(version_base="1.3", config_path="../../conf", config_name="denoise_table")
def _main(cfg: DictConfig) -> None:
    res = run(cfg, command=shlex.join(["dss-denoise-table", *sys.argv[1:]]))
    print(res["markdown"])
    print(f"table: {Path(res['out_dir']) / 'table.md'} ({res['time_s']:.0f} s)")
    if res["published"]:
        print(f"published to {cfg.published_dir}: {', '.join(Path(p).name for p in res['published'])}")
    for c in res["cases"]:  # a missing optional case (a mesh outside the repository) must not pass unnoticed
        if c["status"] == "skipped":
            print(f"NOTICE: case {c['name']} was skipped: {c['reason']}", file=sys.stderr)


def main() -> None:
    _main()


if __name__ == "__main__":
    main()
