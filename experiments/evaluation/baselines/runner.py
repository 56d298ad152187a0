"""Run a baseline denoiser on a point cloud in a subprocess with a time limit.

A crash (exception or signal, e.g. a segfault inside a C++ library), a hang, NaN output or an
output worse than the input becomes a *failure record*; the calling process is never killed
and carries on with the next method. Every record names the method, its parameters (defaults
filled in, plus the absolute values the method derived from them), the library versions,
timings and, when the clean cloud is given, the input's and output's Chamfer distance.

Usage::

    from experiments.evaluation.baselines.runner import run_method, list_methods
    res = run_method("cgal_jet", noisy_points, params={"k": 32}, time_limit=300, clean=clean)
    res.record.status   # "ok" | "crash" | "timeout" | "nan" | "worse_than_input" |
                        # "invalid_output" | "unavailable"
    res.points          # (N',3) float64, or None on failure

``python -m experiments.evaluation.baselines.runner`` prints which methods are available here.

Statuses: ``ok`` (a valid output; ``judged`` says whether it was compared with the clean cloud),
``crash`` (the method raised, or the worker died; ``signal`` names a fatal signal),
``timeout`` (killed after ``time_limit`` seconds), ``nan`` (non-finite coordinates),
``invalid_output`` (not an (M,3) array with M > 0), ``worse_than_input`` (output Chamfer to the
clean cloud above the input's, ``paper`` protocol), ``unavailable`` (package not installed).
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from experiments.evaluation.baselines.methods import METHODS, PIP_NAMES

log = logging.getLogger(__name__)

FAILURES = ("crash", "timeout", "nan", "invalid_output", "worse_than_input", "unavailable")


@dataclass
class RunRecord:
    """JSON-ready description of one method run (see module docstring for ``status``)."""

    method: str
    params: dict
    status: str
    failed: bool
    message: str = ""
    wall_s: float | None = None  # the method call inside the worker
    cpu_s: float | None = None  # ... its process CPU seconds (all threads)
    total_s: float | None = None  # including process start-up and data transfer
    time_limit_s: float | None = None
    exit_code: int | None = None
    signal: str | None = None
    n_in: int = 0
    n_out: int | None = None
    versions: dict = field(default_factory=dict)
    resolved: dict = field(default_factory=dict)
    judged: bool = False
    protocol: str | None = None
    chamfer_input: float | None = None  # x1e4 in `protocol`
    chamfer_output: float | None = None
    stderr_tail: str = ""

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class RunResult:
    record: RunRecord
    points: np.ndarray | None = None
    normals: np.ndarray | None = None


def availability(method: str) -> tuple[bool, str]:
    """(available, reason) for a registered method or a ``module:function`` spec, without
    importing the package (a broken package cannot take this process down)."""
    if method in METHODS:
        missing = [m for m in METHODS[method].requires if importlib.util.find_spec(m) is None]
        if missing:
            pips = " ".join(PIP_NAMES.get(m, m) for m in missing)
            return (
                False,
                f"not installed: {', '.join(missing)} (pip install {pips}; or the 'baselines' extra)",
            )
        return True, ""
    if ":" in method:
        mod = method.rsplit(":", 1)[0]
        if mod.endswith(".py"):
            return (os.path.isfile(mod), "" if os.path.isfile(mod) else f"{mod}: file not found")
        try:
            ok = importlib.util.find_spec(mod) is not None
        except (ImportError, ValueError):
            ok = False
        return ok, "" if ok else f"module {mod} not found"
    return False, f"unknown method {method!r}; registered: {sorted(METHODS)}"


def list_methods() -> list[dict]:
    """Every registered method with its availability, defaults and description."""
    out = []
    for name, m in METHODS.items():
        ok, why = availability(name)
        out.append(
            {
                "method": name,
                "available": ok,
                "reason": why,
                "defaults": dict(m.defaults),
                "description": m.description,
            }
        )
    return out


def _resolve_params(method: str, params: dict | None) -> dict:
    params = dict(params or {})
    if method in METHODS:
        defaults = METHODS[method].defaults
        unknown = sorted(set(params) - set(defaults))
        if unknown:
            raise ValueError(
                f"{method}: unknown parameter(s) {unknown}; accepted: {sorted(defaults)}"
            )
        return {**defaults, **params}
    return params


def _as_array(x: Any, name: str) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or len(a) == 0:
        raise ValueError(f"{name}: expected a non-empty (N, 3) array, got shape {a.shape}")
    return a


def _signal_name(code: int | None) -> str | None:
    if code is None or code >= 0:
        return None
    try:
        return signal.Signals(-code).name
    except ValueError:
        return f"signal {-code}"


def wait_or_kill(proc: subprocess.Popen, time_limit: float) -> int | None:
    """The exit code of ``proc``, or None after killing its whole process group (it must have
    been started with ``start_new_session=True``) when it outlives ``time_limit`` seconds."""
    try:
        return proc.wait(timeout=time_limit)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()
        return None


def tail_text(path: str | os.PathLike, n: int = 2000) -> str:
    """The last ``n`` bytes of a log file as text ("" when unreadable)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - n))
            return f.read().decode("utf-8", "replace")
    except OSError:
        return ""


def _worker_env(threads: int | None) -> dict:
    """The worker's environment: ``threads`` OMP/MKL/OpenBLAS threads, this package importable."""
    env = dict(os.environ)
    if threads is not None:
        for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env[k] = str(int(threads))
    # the worker must import this package even when it is not installed (e.g. a checkout)
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _read_result(job: str, rec: RunRecord, method: str) -> tuple[np.ndarray, np.ndarray | None] | None:
    """The worker's output (points, normals or None) from its ``job`` folder, or None with
    ``rec``'s status and message saying why there is none."""
    res_path = os.path.join(job, "result.json")
    if not os.path.exists(res_path):
        rec.status = "crash"
        rec.message = (
            f"worker died with {rec.signal}"
            if rec.signal
            else f"worker exited with code {rec.exit_code} and no result"
        )
        log.warning("%s: %s", method, rec.message)
        return None
    with open(res_path) as f:
        res = json.load(f)
    rec.versions = res.get("versions", {})
    rec.resolved = res.get("resolved", {})
    rec.wall_s = res.get("wall_s")
    rec.cpu_s = res.get("cpu_s")
    if res.get("status") != "done":
        rec.status = res.get("status", "crash")
        rec.message = res.get("message", "")
        if res.get("traceback"):
            rec.stderr_tail = res["traceback"]
        log.warning("%s: %s: %s", method, rec.status, rec.message)
        return None
    with np.load(os.path.join(job, "output.npz")) as data:
        p = np.array(data["points"])
        n = np.array(data["normals"]) if "normals" in data else None
    return p, n


def _run_worker(method: str, params: dict, pts: np.ndarray, nrm: np.ndarray | None, time_limit: float,
                threads: int | None, rec: RunRecord) -> tuple[np.ndarray, np.ndarray | None] | None:
    """Run the worker subprocess (its own process group, killed at ``time_limit`` s); its
    output, or None with ``rec`` saying why (timeout, crash, the method's own failure)."""
    with tempfile.TemporaryDirectory(prefix="dss_baseline_") as job:
        with open(os.path.join(job, "job.json"), "w") as f:
            json.dump({"method": method, "params": params}, f)
        arrays = {"points": pts} if nrm is None else {"points": pts, "normals": nrm}
        np.savez(os.path.join(job, "input.npz"), **arrays)
        err_path = os.path.join(job, "stderr.txt")
        t0 = time.perf_counter()
        with open(os.path.join(job, "stdout.txt"), "wb") as so, open(err_path, "wb") as se:
            proc = subprocess.Popen(
                [sys.executable, "-m", "experiments.evaluation.baselines.worker", job],
                stdout=so,
                stderr=se,
                env=_worker_env(threads),
                start_new_session=True,
            )
            rec.exit_code = wait_or_kill(proc, time_limit)
            if rec.exit_code is None:
                rec.total_s = time.perf_counter() - t0
                rec.status = "timeout"
                rec.message = f"killed after the time limit of {time_limit:g} s"
                rec.stderr_tail = tail_text(err_path)
                log.warning("%s: %s", method, rec.message)
                return None
        rec.total_s = time.perf_counter() - t0
        rec.signal = _signal_name(rec.exit_code)
        rec.stderr_tail = tail_text(err_path)
        return _read_result(job, rec, method)


def _judge_output(rec: RunRecord, out: RunResult, pts: np.ndarray, p: np.ndarray, n, clean, protocol: str) -> None:
    """Settle ``rec``'s status from the output ``p``: invalid, NaN, worse than the input
    (Chamfer against ``clean``, when given) or ok; a usable output goes into ``out``."""
    rec.n_out = int(len(p)) if p.ndim >= 1 else 0
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        rec.status = "invalid_output"
        rec.message = f"output has shape {p.shape}, expected (M, 3) with M > 0"
        return
    if not np.isfinite(p).all():
        bad = int((~np.isfinite(p)).any(axis=1).sum())
        rec.status = "nan"
        rec.message = f"{bad} of {len(p)} output points are NaN/Inf"
        return
    out.points, out.normals = p, n
    if clean is not None:
        from dss.metrics import evaluate

        c = _as_array(clean, "clean")
        rec.judged, rec.protocol = True, protocol
        rec.chamfer_input = evaluate(pts, c, protocol=protocol).chamfer
        rec.chamfer_output = evaluate(p, c, protocol=protocol).chamfer
        if rec.chamfer_output > rec.chamfer_input:
            rec.status = "worse_than_input"
            rec.message = f"Chamfer x1e4 ({protocol}) {rec.chamfer_output:.4g} > input {rec.chamfer_input:.4g}"
            return
    rec.status, rec.failed = "ok", False


def run_method(
    method: str,
    points: Any,
    normals: Any | None = None,
    params: dict | None = None,
    time_limit: float = 600.0,
    clean: Any | None = None,
    protocol: str = "paper",
    threads: int | None = None,
) -> RunResult:
    """Run ``method`` on ``points`` (N,3) [+ ``normals`` (N,3)] in a worker subprocess.

    ``time_limit`` seconds for the whole worker (start-up included); ``clean`` (M,3), if
    given, enables the ``worse_than_input`` check (Chamfer, ``protocol``). ``threads`` sets
    OMP/MKL/OpenBLAS thread counts in the worker. Never raises for a failing method; raises
    ValueError only for bad arguments (wrong shapes, unknown parameters).
    """
    pts = _as_array(points, "points")
    nrm = None if normals is None else _as_array(normals, "normals")
    if nrm is not None and len(nrm) != len(pts):
        raise ValueError(f"normals: {len(nrm)} rows for {len(pts)} points")
    params = _resolve_params(method, params)
    rec = RunRecord(
        method=method,
        params=params,
        status="unavailable",
        failed=True,
        n_in=len(pts),
        time_limit_s=float(time_limit),
    )
    ok, why = availability(method)
    if not ok:
        rec.message = why
        log.warning("%s unavailable: %s", method, why)
        return RunResult(rec)
    out = RunResult(rec)
    result = _run_worker(method, params, pts, nrm, time_limit, threads, rec)
    if result is not None:
        _judge_output(rec, out, pts, *result, clean, protocol)
    return out


def run_methods(methods: dict[str, dict] | list[str], points: Any, **kwargs) -> list[RunResult]:
    """Run several methods (``{name: params}`` or a list of names) one after another; a
    failure of one is recorded and the next one runs."""
    items = methods.items() if isinstance(methods, dict) else [(m, None) for m in methods]
    return [run_method(m, points, params=p, **kwargs) for m, p in items]


def main(argv=None) -> int:
    """Print the registered baselines and whether they are available here."""
    logging.basicConfig(level=logging.INFO)
    for m in list_methods():
        state = "available" if m["available"] else f"unavailable ({m['reason']})"
        print(f"{m['method']:18s} {state}\n    {m['description']}\n    defaults: {m['defaults']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
