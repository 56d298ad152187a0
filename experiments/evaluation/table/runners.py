"""Running one method on one case of the denoising table: a baseline
(:mod:`experiments.evaluation.baselines`, in a worker process) or a ``dss-denoise`` subprocess,
each with a time limit; its JSON-ready record (status, metrics, times), and whether a stored
record can be reused (same request, not cut short by a shorter limit)."""

from __future__ import annotations

import functools
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from experiments.evaluation.baselines.methods import METHODS, preset_params
from experiments.evaluation.baselines.runner import run_method, tail_text, wait_or_kill
from experiments.evaluation.table.cases import REPO_ROOT, plain

__all__ = ["DSS_BASE", "versions", "score", "judge", "save_output", "method_list", "prefilter_outliers",
           "run_baseline", "hydra_value", "run_dss", "load_raw_points", "request", "shipped_model_for", "file_sha256",
           "check_params", "reusable", "read_json", "reference_record", "reference_rows"]

#: fixed arguments of every DSS run: its own metrics and floor are not needed (scored here)
DSS_BASE = ["progress=false", "metrics.protocols=[paper]", "metrics.floor=false", "figures.enabled=false",
            "overwrite=true"]


def versions() -> dict:
    import platform
    from importlib import metadata

    out = {"python": platform.python_version()}
    for pkg in ("dss-splatting", "numpy", "torch", "open3d", "onnxruntime", "cgal", "pymeshlab"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    return out


def score(pred: np.ndarray, gt: dict) -> dict:
    """Metrics of ``pred`` (N, 3) against the case's clean cloud and mesh under ``gt["protocol"]``."""
    from dss.metrics import evaluate

    d = evaluate(pred, gt["clean"], gt["mesh"], gt["protocol"]).to_dict()
    d.pop("normalization", None)
    return d


def judge(rec: dict, pred: np.ndarray | None, gt: dict) -> dict:
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
    rec["metrics"] = score(pred, gt)
    cd, cd_in = rec["metrics"]["chamfer"], gt["input_chamfer"]
    if cd > cd_in:
        rec.update(status="worse_than_input", message=f"Chamfer x1e4 {cd:.4g} > input {cd_in:.4g}")
    elif rec["status"] in ("ok", "worse_than_input"):
        rec.update(status="ok", message="")
    rec["failed"] = rec["status"] != "ok"
    return rec


def save_output(out: Path | None, pts: np.ndarray | None) -> str | None:
    if out is None or pts is None or not np.isfinite(pts).all():
        return None
    from dss.ply import write_ply

    out.parent.mkdir(parents=True, exist_ok=True)
    write_ply(out, pts)
    return str(out)


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


def prefilter_outliers(noisy: np.ndarray) -> tuple[np.ndarray, dict]:
    """``noisy`` (N, 3) without the points dss-denoise's outlier removal drops (the same
    :func:`dss.pointcloud.find_outliers` parameters, conf/denoise.yaml ``outliers``), and a report."""
    import torch

    from dss.pointcloud import find_outliers
    from experiments.denoising.inputs import outlier_params

    params = outlier_params(OmegaConf.load(REPO_ROOT / "conf" / "denoise.yaml").outliers)
    t0 = time.perf_counter()
    bad = find_outliers(torch.from_numpy(np.ascontiguousarray(noisy, np.float32)), **params).numpy()
    return noisy[~bad], {"removed": int(bad.sum()), "seconds": time.perf_counter() - t0, **params}


def run_baseline(spec: str, gt: dict, params: dict, limit: float,
                  threads: int | None, out_ply: Path | None, prefilter: bool = False) -> dict:
    """One baseline on one case through the subprocess runner; a JSON-ready record.
    ``prefilter``: the baseline gets the noisy cloud after dss-denoise's outlier removal (its time
    is added to the method's; the record's ``prefilter`` says how many points went)."""
    noisy, pre = gt["noisy"], None
    if prefilter:
        if "prefiltered" not in gt:  # once per case: every baseline gets the same filtered cloud
            gt["prefiltered"] = prefilter_outliers(noisy)
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
    rec = judge(rec, pts, gt)
    rec["output"] = save_output(out_ply, pts) if rec.get("metrics") else None
    return rec


def hydra_value(s: str) -> str:
    """A path as a Hydra override value (quoted unless plainly safe)."""
    return s if re.fullmatch(r"[A-Za-z0-9_./-]+", s) else "'" + s.replace("\\", "\\\\").replace("'", "\\'") + "'"


def run_dss(overrides: list[str], case_dir: Path, gt: dict, noise: float, limit: float,
             threads: int | None, run_dir: Path, out_ply: Path | None) -> dict:
    """One dss-denoise subprocess on one case (its own process group, killed at ``limit`` s);
    its run directory (config.yaml, metrics.json, dss.log, figures) is ``run_dir``."""
    run_dir.mkdir(parents=True, exist_ok=True)
    args = [f"input={hydra_value(str(case_dir / 'noisy.ply'))}", f"clean={hydra_value(str(case_dir / 'clean.ply'))}",
            f"mesh={hydra_value(str(case_dir / 'mesh.ply'))}", f"hydra.run.dir={hydra_value(str(run_dir))}",
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
    rec["versions"] = versions()
    try:
        pts = load_raw_points(ply)  # NaN rows kept: a NaN output must be seen, not dropped
    except Exception as e:  # noqa: BLE001 - an unreadable output is this method's failure
        rec.update(status="invalid_output", message=f"{ply}: unreadable ({e})")
        return rec
    rec["status"], rec["n_out"] = "ok", int(len(pts))
    rec = judge(rec, pts, gt)
    rec["output"] = save_output(out_ply, pts) if rec.get("metrics") else None
    return rec


def load_raw_points(path: Path) -> np.ndarray:
    """(N, 3) float64 vertex positions, NaN/inf rows kept."""
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    return np.asarray(pc.points, dtype=np.float64)


def request(label: str, cfg: DictConfig, noise: float) -> dict:
    """What determines a (case, method) record besides the case: a stored record is reused only
    when its request is the same."""
    dss = dict(cfg.dss_methods or {})
    if label in dss:
        ovr = [*plain(dss[label]), *plain(cfg.get("dss_overrides"))]
        if int(cfg.get("seed", 0)):  # another draw of the cases: DSS's own random views follow it
            ovr.append(f"seed={int(cfg.seed)}")
        # threads=null gives "...=None", which Hydra would read as a string
        req = {"kind": "dss", "overrides": [re.sub(r"=None$", "=null", str(o)) for o in ovr]}
        model = shipped_model_for(req["overrides"], noise)
        if model is not None:  # a retrained shipped model makes its stored records stale
            req["model_sha256"] = file_sha256(model)[:16]
        return req
    spec = str((cfg.custom_methods or {}).get(label, label))
    extra = (plain(cfg.get("params")) or {}).get(label) or {}
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


def check_params(cfg: DictConfig, methods: list[str], noise: float) -> None:
    """Unknown parameter names of registered baselines are refused before any work."""
    for label in methods:
        req = request(label, cfg, noise)
        if req["kind"] == "baseline" and req["spec"] in METHODS:
            bad = sorted(set(req["params"]) - set(METHODS[req["spec"]].defaults))
            if bad:
                raise ValueError(f"params.{label}: unknown parameter(s) {bad}; accepted: "
                                 f"{sorted(METHODS[req['spec']].defaults)}")


def reusable(rec: dict | None, req: dict, limit: float) -> bool:
    if not rec or rec.get("request") != req:
        return False
    # a run killed by a shorter limit than the one asked now is retried
    return not (rec.get("status") == "timeout" and limit > float(rec.get("time_limit_s") or 0))


def read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def reference_record(kind: str, case: str, pts: np.ndarray, gt: dict, extra: dict | None = None) -> dict:
    """The ``input`` (noisy cloud) or ``floor`` (second clean sampling) row of a case."""
    return {"case": case, "method": kind, "kind": kind, "status": "reference", "failed": False, "message": "",
            "params": extra or {}, "metrics": score(pts, gt), "time_s": None, "n_out": len(pts)}


def reference_rows(name: str, gt: dict, rdir: Path, floor: bool, seed: int, overwrite: bool) -> list:
    from dss.io_utils import atomic_write_json
    from dss.metrics import sample_poisson_disk

    out = []
    for kind in ("input", "floor") if floor else ("input",):
        path = rdir / f"{kind}.json"
        rec = None if overwrite else read_json(path)
        if rec is None:
            if kind == "input":
                rec = reference_record("input", name, gt["noisy"], gt)
            else:  # Poisson-disk samples of the mesh with another seed, scored against the clean cloud
                rec = reference_record("floor", name, sample_poisson_disk(gt["mesh"], len(gt["clean"]), seed + 1),
                                        gt, {"seed": seed + 1})
            atomic_write_json(path, rec)
        out.append(rec)
    return out
