"""Worker entry point: ``python -m experiments.evaluation.baselines.worker JOB_DIR``.

Reads ``JOB_DIR/job.json`` (``{"method": spec, "params": {...}}``) and ``JOB_DIR/input.npz``
(``points`` (N,3), optional ``normals``), runs the method, and writes ``JOB_DIR/output.npz`` and
``JOB_DIR/result.json`` (each atomically, result last). Exit codes: 0 done, 1 the method raised,
3 the method is unavailable, 2 bad job. A crash (signal) or a hang leaves no ``result.json``;
the parent (:mod:`experiments.evaluation.baselines.runner`) records those.

A method spec is a registered name (:data:`experiments.evaluation.baselines.methods.METHODS`),
``"package.module:function"`` or ``"/path/to/file.py:function"``.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import os
import sys
import time
import traceback

import numpy as np

EXIT_OK, EXIT_ERROR, EXIT_BAD_JOB, EXIT_UNAVAILABLE = 0, 1, 2, 3


def resolve(spec: str):
    """The callable for a method spec (see module docstring)."""
    from experiments.evaluation.baselines.methods import METHODS

    if spec in METHODS:
        return METHODS[spec].func
    if ":" not in spec:
        raise KeyError(f"unknown method {spec!r}; registered: {sorted(METHODS)}")
    mod_name, fn_name = spec.rsplit(":", 1)
    if mod_name.endswith(".py"):
        if not os.path.isfile(mod_name):
            raise FileNotFoundError(f"{mod_name}: method file not found")
        s = importlib.util.spec_from_file_location("_baseline_method", mod_name)
        mod = importlib.util.module_from_spec(s)
        s.loader.exec_module(mod)
    else:
        mod = importlib.import_module(mod_name)
    return getattr(mod, fn_name)


def _write_json(path: str, obj: dict) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(obj, f, default=str)
    os.replace(tmp, path)


def _write_npz(path: str, **arrays) -> None:
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)


def _versions(spec: str) -> dict:
    from importlib import metadata

    from experiments.evaluation.baselines.methods import METHODS, PIP_NAMES

    out = {}
    mods = METHODS[spec].requires if spec in METHODS else ()
    for m in mods:
        try:
            out[PIP_NAMES.get(m, m)] = metadata.version(PIP_NAMES.get(m, m))
        except metadata.PackageNotFoundError:
            out[PIP_NAMES.get(m, m)] = None
    return out


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1 or not os.path.isdir(argv[0]):
        print("usage: python -m experiments.evaluation.baselines.worker JOB_DIR", file=sys.stderr)
        return EXIT_BAD_JOB
    job_dir = argv[0]
    os.environ["DSS_BASELINE_WORKDIR"] = job_dir
    with open(os.path.join(job_dir, "job.json")) as f:
        job = json.load(f)
    data = np.load(os.path.join(job_dir, "input.npz"))
    points = np.asarray(data["points"], dtype=np.float64)
    normals = np.asarray(data["normals"], dtype=np.float64) if "normals" in data else None
    result: dict = {"method": job["method"], "params": job.get("params", {})}

    def finish(code: int) -> int:
        _write_json(os.path.join(job_dir, "result.json"), result)
        return code

    try:
        fn = resolve(job["method"])
        result["versions"] = _versions(job["method"])
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn(points, normals, **job.get("params", {}))
        result["wall_s"] = time.perf_counter() - t0
        result["cpu_s"] = time.process_time() - c0  # every thread of the worker: load-independent
    except Exception as e:  # noqa: BLE001 - every failure of a third-party method is recorded
        from experiments.evaluation.baselines.methods import MethodUnavailable

        result["error_type"] = type(e).__name__
        result["message"] = f"{type(e).__name__}: {e}"
        result["traceback"] = traceback.format_exc(limit=8)
        unavailable = isinstance(e, (MethodUnavailable, ImportError))
        result["status"] = "unavailable" if unavailable else "crash"
        return finish(EXIT_UNAVAILABLE if unavailable else EXIT_ERROR)

    extra: dict = {}
    out_normals = None
    if isinstance(out, tuple):  # (points, normals) or (points, normals, extra-record dict)
        parts = list(out) + [None, None]
        out, out_normals = parts[0], parts[1]
        extra = parts[2] if isinstance(parts[2], dict) else {}
    arrays = {"points": np.asarray(out, dtype=np.float64)}
    if out_normals is not None:
        arrays["normals"] = np.asarray(out_normals, dtype=np.float64)
    _write_npz(os.path.join(job_dir, "output.npz"), **arrays)
    result.update(extra)
    result["status"] = "done"
    return finish(EXIT_OK)


if __name__ == "__main__":
    sys.exit(main())
