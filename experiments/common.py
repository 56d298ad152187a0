"""Helpers shared by the Hydra apps: run directory, config echo, metrics, positional inputs."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from dss.io_utils import atomic_write_json, atomic_write_text

log = logging.getLogger(__name__)

__all__ = ["run_dir", "save_config", "save_metrics", "positional_to_override", "renderer_settings", "optimization_report",
           "prepare_kernels"]


def flatten(d, prefix: str = "") -> dict:
    """Nested dicts -> ``{"a.b.c": value}``; lists of scalars are kept as lists."""
    out: dict = {}
    if isinstance(d, dict):
        for k, v in d.items():
            key = f"{prefix}.{k}" if prefix else str(k)
            if isinstance(v, dict):
                out.update(flatten(v, key))
            else:
                out[key] = v
    else:
        out[prefix or "value"] = d
    return out


def run_dir(cfg: DictConfig | None = None) -> Path:
    """The Hydra run directory when running under Hydra, else ``cfg.out_dir`` or the cwd."""
    try:
        from hydra.core.hydra_config import HydraConfig

        if HydraConfig.initialized():
            return Path(HydraConfig.get().runtime.output_dir)
    except Exception:  # pragma: no cover - hydra not initialised
        pass
    if cfg is not None and cfg.get("out_dir"):
        p = Path(cfg.out_dir)
        p.mkdir(parents=True, exist_ok=True)
        return p
    return Path.cwd()


def save_config(cfg: DictConfig, out: Path) -> Path:
    """Echo the resolved config as ``config.yaml`` (atomically)."""
    return atomic_write_text(out / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))


def save_metrics(metrics: dict, out: Path, name: str = "metrics.json") -> Path:
    return atomic_write_json(out / name, metrics)


def positional_to_override(key: str) -> None:
    """Let ``app file.ply`` mean ``app key=file.ply`` (Hydra itself takes only overrides)."""
    args = sys.argv[1:]
    for i, a in enumerate(args):
        if "=" not in a and not a.startswith("-") and (i == 0 or not args[i - 1].startswith("-")):
            sys.argv[1 + i] = f"{key}={a}"
            break


def renderer_settings(node) -> RenderSettings:  # noqa: F821
    """RenderSettings from a config node (unknown keys are an error, named)."""
    from dss.render import RenderSettings

    d = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else dict(node)
    fields = set(RenderSettings.__dataclass_fields__)
    unknown = set(d) - fields
    if unknown:
        raise ValueError(f"unknown renderer settings {sorted(unknown)}; known: {sorted(fields)}")
    if isinstance(d.get("background"), list):
        d["background"] = tuple(d["background"])
    return RenderSettings(**d)


def resolve_device(value) -> torch.device:  # noqa: F821
    """The device an app's DSS optimisation runs on, from its ``device`` setting.

    ``cpu`` (or null), ``cuda`` / ``cuda:N``, or ``auto`` (the first GPU when torch sees one, else
    the CPU). Refuses a GPU that this torch build or machine does not have, saying which.
    """
    import torch

    name = "cpu" if value in (None, "") else str(value).strip().lower()
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name != "cpu" and not name.startswith("cuda"):
        raise ValueError(f"device must be cpu, cuda, cuda:N or auto, got {value!r}")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(f"device={value} but torch sees no GPU (torch {torch.__version__}, CUDA build: "
                             f"{torch.version.cuda or 'none'}); use device=cpu or install a CUDA build of torch")
        dev = torch.device(name)
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device={value} but torch sees {torch.cuda.device_count()} GPU(s)")
        return dev
    return torch.device("cpu")


def describe_device(dev) -> str:
    """``cpu`` or ``cuda:0 (NVIDIA H100 80GB HBM3)``: what metrics.json records."""
    import torch

    if dev.type != "cuda":
        return str(dev)
    index = dev.index if dev.index is not None else torch.cuda.current_device()
    return f"cuda:{index} ({torch.cuda.get_device_name(index)})"


def prepare_kernels(device=None) -> float:
    """Build (or load) the compiled kernels a run will use, before its timed work starts.

    A first-use compile (44 s on an idle 2-core machine, about 200 s on a busy one) happens once
    per machine; it is no part of a run's cost, so the apps report it apart (``time_s.kernel_build``)
    and leave it out of their totals. Returns the seconds this run has spent compiling: since the
    run's start (:class:`JobStart` marks it when Hydra runs the app), so a compile that an earlier
    step of the run (reading the input, estimating its normals) started is counted too; without a
    mark, in this call. 0 when the kernels were cached.
    """
    from dss import _ext

    before = _ext.build_seconds()
    _ext.load_cpu()
    if device is not None and getattr(device, "type", str(device)) == "cuda":
        from dss import _ext_cuda

        _ext_cuda.load_cuda()
    start = _RUN_BUILD_MARK[0]
    return _ext.build_seconds() - (before if start is None else min(start, before))


#: dss._ext.build_seconds() when the current Hydra job started (:class:`JobStart`), or None
_RUN_BUILD_MARK: list[float | None] = [None]


def optimization_report(history: dict, t_start: float, t_opt: float, kernel_build: float = 0.0) -> dict:
    """The metrics.json fields every optimisation app reports (schedule, steps, timings, load).

    ``kernel_build``: seconds of first-use kernel compiling since ``t_start``
    (:func:`prepare_kernels`), left out of ``time_s.total``."""
    import os
    import time

    import torch

    return {
        "optimizer": history["config"],
        "steps": history.get("steps"),
        "lr_halvings": history.get("lr_halvings"),
        "final_loss": history["loss"][-1] if history["loss"] else None,
        "time_s": {"total": time.perf_counter() - t_start - kernel_build, "optimization": t_opt,
                   "kernel_build": kernel_build,
                   "reference_generation": history.get("reference_seconds"),
                   "per_step": t_opt / max(1, history.get("steps") or 1)},
        "device": history.get("device", "cpu"),
        "torch_threads": torch.get_num_threads(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


# ------------------------------------------------------------------------------ claimed outputs
class OutputExistsError(FileExistsError):
    """The output (a file, or a run directory holding an earlier run's results) exists and
    ``overwrite`` is false."""


class OutputInUseError(FileExistsError):
    """Another running process has claimed the output."""


#: locks this process holds: resolved lock path -> open file descriptor (flock is released by
#: the kernel when the process ends, however it ends, so no stale lock outlives a killed run)
_claims: dict[str, int] = {}


_remove_on_release: set[str] = set()  # lock files beside a user's output: not left there

#: files that record a run but are no result of it (the resolved config, Hydra's .hydra/ and
#: the job's log): a directory holding only these is an unfinished run's (refused at input, or
#: killed before it wrote a result), which a new run replaces without overwrite=true
RECORDS = ("config.yaml", ".hydra/*.yaml", "*.log")

#: what this process claimed, with what was there before: run directories (claim_run_dir: each
#: file's identity) and output files (claim_output), so that an interrupted run removes only what
#: it wrote itself
_claimed_dirs: dict[Path, dict[Path, tuple | None]] = {}
_claimed_outputs: dict[Path, tuple | None] = {}


def _lock(lock_path: Path, what: str, remove: bool = False) -> None:
    """Take an exclusive, non-blocking flock on ``lock_path`` (re-entrant within a process)."""
    import fcntl
    import os

    key = str(lock_path.resolve())
    if key in _claims:
        return
    try:
        lock_path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        raise PermissionError(f"{what}: cannot write into {lock_path.parent} ({e.strerror or e})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise OutputInUseError(f"{what} is being written by another running process (lock {lock_path}); "
                               "wait for it or choose another output") from None
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    if not _claims and not _atexit_registered:
        import atexit

        # a failed or interrupted run releases its claims too (no lock file left beside an output)
        atexit.register(release_claims)
        _atexit_registered.append(True)
    _claims[key] = fd
    if remove:
        _remove_on_release.add(key)


_atexit_registered: list[bool] = []


def release_claims() -> None:
    """Release every claim this process holds (the end of a run)."""
    import os

    _claimed_dirs.clear()
    _claimed_outputs.clear()
    _RUN.clear()
    while _claims:
        key, fd = _claims.popitem()
        if key in _remove_on_release:  # unlinked while still held: no other run can take it between
            _remove_on_release.discard(key)
            Path(key).unlink(missing_ok=True)
        os.close(fd)


def _earlier_results(out: Path, artefacts) -> list[Path]:
    found: list[Path] = []
    for pattern in artefacts:
        found += [p for p in out.glob(pattern) if p.is_file()]
    return sorted(set(found))


def claim_run_dir(out: Path, artefacts, overwrite: bool = False, what: str = "run directory",
                  clear_records: bool = False) -> Path:
    """Claim ``out`` for this run before any work: exclusively (a second concurrent run fails at
    once with :class:`OutputInUseError`) and without mixing runs. Files of ``artefacts`` (glob
    patterns relative to ``out``: what the app writes) left by an earlier run make it refuse
    (:class:`OutputExistsError`) unless ``overwrite``, which removes them first, so no earlier
    result stays beside new metrics. Files of :data:`RECORDS` (config echoes, logs) alone are no
    earlier results; ``clear_records`` (before Hydra writes this run's) removes them too."""
    out = Path(out)
    _lock(out / ".dss-run.lock", f"{what} {out}")
    records = set(_earlier_results(out, RECORDS))
    earlier = [p for p in _earlier_results(out, artefacts) if p not in records]
    if earlier and not overwrite:
        names = ", ".join(str(p.relative_to(out)) for p in earlier[:3]) + (" ..." if len(earlier) > 3 else "")
        raise OutputExistsError(f"{what} {out} holds an earlier run's results ({names}); refusing to mix runs "
                                "(choose another directory, or pass overwrite=true to replace them)")
    for p in earlier:
        p.unlink(missing_ok=True)
    if earlier:
        log.warning("overwrite=true: removed %d files of an earlier run from %s", len(earlier), out)
    if clear_records:  # an unfinished or replaced run's config and log: not mixed with this run's
        for p in records:
            p.unlink(missing_ok=True)
    if out.resolve() not in _claimed_dirs:
        _claimed_dirs[out.resolve()] = {p: _identity(p) for p in out.rglob("*") if p.is_file()}
    return out


def claim_output(path: Path, overwrite: bool = False) -> Path:
    """Claim an output file before any work: its folder must be writable, no other running
    process may hold it, and an existing file is refused unless ``overwrite``."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"output {path} is a directory")
    _lock(path.parent / f".{path.name}.lock", f"output {path}", remove=True)
    if path.exists() and not overwrite:
        raise OutputExistsError(f"output {path} already exists; refusing to replace it (pass overwrite=true)")
    _claimed_outputs[path.resolve()] = _identity(path)
    return path


def _identity(path: Path) -> tuple | None:
    """(inode, size, mtime) of a file, None when there is none: whether a run replaced it."""
    try:
        st = path.stat()
    except OSError:
        return None
    return (st.st_ino, st.st_size, st.st_mtime_ns)


class ClaimRunDir(Callback):
    """Hydra callback (conf/hydra/default.yaml): claims ``hydra.run.dir`` before Hydra writes
    ``.hydra/`` into it, so that a refused run leaves an earlier run's files as they were. ``app``:
    the app's config name; its module (:data:`experiments.app_registry.APPS`) lists in
    ``ARTEFACTS`` what the app writes. Apps without ``ARTEFACTS`` claim nothing (the table commands
    resume in their folder; dss-prep and dss-export write to their own places)."""

    def __init__(self, app: str):
        self.app = app

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        import importlib

        from experiments.app_registry import APPS

        artefacts = run_dir_artefacts(self.app)
        if artefacts is None:
            return
        module = importlib.import_module(APPS[self.app].module)
        out = Path(str(config.hydra.run.dir))
        created = _first_missing(out)
        try:
            # an app whose runs can be continued (dss-train's resume) decides itself; the records
            # of an unfinished run (its .hydra/, log) are cleared before Hydra writes this run's
            claim = getattr(module, "claim_run", None)
            if claim is not None:
                claim(config, out, clear_records=True)
            else:
                claim_run_dir(out, artefacts, bool(config.get("overwrite", False)), clear_records=True)
            _RUN.clear()
            _RUN.update(dir=out.resolve(), created=created, artefacts=tuple(artefacts))
        except (OSError, ValueError) as e:
            # Hydra turns a callback's exception into a warning and runs the job anyway: stop here
            if _DEBUG[0]:
                import traceback

                traceback.print_exc()
            _report(e, None)


#: the run directory ClaimRunDir claimed for this process: ``dir``, ``created`` (the topmost
#: folder this run created, or None when the directory existed) and the app's ``artefacts``
_RUN: dict = {}


def _first_missing(path: Path) -> Path | None:
    """The topmost of ``path`` and its parents that does not exist (what claiming creates)."""
    path = path.absolute()
    missing = None
    for p in (path, *path.parents):
        if p.exists():
            break
        missing = p
    return missing


def _log_to_run_files(level: int, message: str) -> None:
    """Write ``message`` into the run's log files only (Hydra's job log): the console gets its
    one line from :func:`_report`."""
    import logging

    record = logging.LogRecord("dss", level, __file__, 0, message, None, None)
    for h in logging.getLogger().handlers:
        if isinstance(h, logging.FileHandler):
            h.handle(record)


def _only_records(folder: Path, run: Path) -> bool:
    """Whether everything under ``folder`` is this run's records (.hydra/, log, lock files) in ``run``."""
    for p in folder.rglob("*"):
        if p.is_dir():
            continue
        rel = p.relative_to(run) if p.is_relative_to(run) else None
        if rel is None or not (rel.parts[0] == ".hydra" or (len(rel.parts) == 1 and (
                p.suffix == ".log" or (p.name.startswith(".") and p.name.endswith(".lock"))))):
            return False
    return True


def _close_log_files(run: Path) -> None:
    import logging

    root = logging.getLogger()
    for h in list(root.handlers):
        if isinstance(h, logging.FileHandler) and Path(h.baseFilename).resolve().is_relative_to(run):
            root.removeHandler(h)
            h.close()


def _end_failed_run(e: BaseException, artefacts, unfinished=None) -> str | None:
    """After an expected failure or an interrupt inside a run: the error (or the interruption)
    goes into the run's log, the results an interrupted run wrote (files of ``unfinished``,
    default ``artefacts``, and its output file) are removed, so none is left looking complete,
    and a run directory that this run created and that holds nothing but its records (a run
    refused at input) is removed. Returns a note for the console line, or None."""
    import shutil

    unfinished = artefacts if unfinished is None else unfinished
    interrupted = isinstance(e, KeyboardInterrupt)
    run = _RUN.get("dir")
    if run is None and _claimed_dirs:  # called with a config (no Hydra): the run() claimed one
        run = next(iter(_claimed_dirs))
    note = None
    removed: list[str] = []
    if interrupted:
        for d, before in _claimed_dirs.items():  # what this run wrote in the folders it claimed
            records = set(_earlier_results(d, RECORDS))
            for p in _earlier_results(d, unfinished):
                if p not in records and _identity(p) != before.get(p):
                    p.unlink(missing_ok=True)
                    removed.append(str(p))
        for path, before in _claimed_outputs.items():
            now = _identity(path)
            if now is not None and now != before:  # written by this run
                path.unlink(missing_ok=True)
                removed.append(str(path))
        note = f"removed this run's unfinished results ({len(removed)} files)" if removed else None
    message = ("interrupted" + (f": {note}: {', '.join(removed)}" if note else "") if interrupted
               else f"error: {describe_error(e)}")
    if run is not None and Path(run).is_dir():
        _log_to_run_files(40, message)
        created = _RUN.get("created")
        refused_at_input = not (Path(run) / "config.yaml").exists() and not _earlier_results(Path(run), artefacts)
        if created is not None and refused_at_input and Path(run).is_relative_to(created) and _only_records(created, Path(run)):
            _close_log_files(Path(run))
            release_claims()
            shutil.rmtree(created, ignore_errors=True)
    release_claims()
    return note


def run_dir_artefacts(app: str) -> list[str] | None:
    """The glob patterns of what app ``app`` (a config name) writes into its run directory, or None
    when it does not claim one (no ``ARTEFACTS`` in its module)."""
    import importlib

    from experiments.app_registry import APPS

    entry = APPS.get(app)
    if entry is None:
        return None
    artefacts = getattr(importlib.import_module(entry.module), "ARTEFACTS", None)
    return None if artefacts is None else list(artefacts)


class JobStart(Callback):
    """Hydra callback (conf/hydra/default.yaml), when a job's run directory exists: marks the
    job's start for :func:`prepare_kernels`, and for a single run in ``outputs/<app>/`` (the
    default place; not a ``hydra.run.dir`` elsewhere, such as a table's per-case runs) points
    ``outputs/<app>/latest`` at it: ``outputs/train/latest/denoiser.onnx`` is the newest
    training's model."""

    def on_job_start(self, config: DictConfig, **kwargs) -> None:
        from hydra.types import RunMode

        from dss import _ext
        from experiments.outputs import OUTPUTS, link_latest

        _RUN_BUILD_MARK[0] = _ext.build_seconds()
        run = Path(str(config.hydra.runtime.output_dir))
        if config.hydra.mode == RunMode.RUN and run.parent.parent.name == OUTPUTS.name:
            link_latest(run)

    def on_job_end(self, config: DictConfig, job_return, **kwargs) -> None:
        _RUN_BUILD_MARK[0] = None


# ------------------------------------------------------------------------------ errors for people
#: set to 1 (or Hydra's HYDRA_FULL_ERROR=1) to see the traceback of an expected failure
DEBUG_ENV = "DSS_DEBUG"


def _expected(e: BaseException) -> bool:
    """Failures a person causes and can act on (bad file, key, value, model, output), as
    opposed to bugs, which keep their traceback."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from dss.optimize import OptimizationDiverged

    return isinstance(e, (ValueError, OSError, HydraException, OmegaConfBaseException, OptimizationDiverged))


def _closest(word: str, candidates, prefix: str = "") -> str:
    import difflib

    best = difflib.get_close_matches(word, [str(c) for c in candidates], n=1, cutoff=0.5)
    return f" (did you mean '{prefix}{best[0]}'?)" if best else ""


def describe_error(e: BaseException) -> str:
    """One line for a person: what is wrong and, for a mistyped key or option, the closest valid
    one (Hydra's "Key 'inptu' is not in struct" becomes "unknown key 'inptu' (did you mean
    'input'?)")."""
    from hydra.errors import InstantiationException, MissingConfigException
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError, MissingMandatoryValue

    cause = e.__cause__
    if isinstance(e, InstantiationException) and isinstance(cause, Exception):
        return describe_error(cause)
    if isinstance(cause, (ConfigKeyError, ConfigAttributeError)) and "not in struct" in str(cause):
        full = str(getattr(cause, "full_key", None) or getattr(cause, "key", "") or "")
        key = full.rsplit(".", 1)[-1]
        parent = getattr(cause, "parent_node", None)
        prefix = full[: len(full) - len(key)]
        keys = list(parent.keys()) if parent is not None and hasattr(parent, "keys") else []
        if full in ("reference.model", "reference.threads") and "model" not in keys:
            # the default reference (identity) has no model: the key belongs to reference=onnx
            return f"unknown key '{full}': the reference in use takes no model; a model file needs reference=onnx {full}=..."
        return f"unknown key '{full}'{_closest(key, keys, prefix)}; add it with +{full}=... only if it is meant to be new"
    if isinstance(e, MissingConfigException) and e.options:
        group = (e.missing_cfg_file or "").rsplit("/", 1)
        name = group[-1]
        where = f" in '{group[0]}'" if len(group) == 2 else ""
        return (f"no config '{name}'{where}{_closest(name, e.options)}; options: {', '.join(sorted(e.options))}")
    if isinstance(e, MissingMandatoryValue) or isinstance(cause, MissingMandatoryValue):
        err = cause if isinstance(cause, MissingMandatoryValue) else e
        key = getattr(err, "full_key", None) or getattr(err, "key", None)
        return f"missing value: {key}=... is required" if key else str(err).splitlines()[0]
    text = str(e)
    if "Traceback (most recent call last)" in text:  # re-raised from a worker (a DataLoader's): its last line
        import re

        last = [ln.strip() for ln in text.splitlines() if ln.strip()][-1]
        head, sep, rest = last.partition(": ")
        text = rest if sep and re.fullmatch(r"[\w.]+", head) else last
    lines = [_clip(ln.strip()) for ln in text.splitlines() if ln.strip() and not ln.strip().startswith(
        ("full_key:", "object_type=", "reference_type="))]
    if isinstance(cause, Exception) and str(cause).strip():
        first = _clip(str(cause).strip().splitlines()[0])
        if first not in lines:
            lines.append(first)
    return "; ".join(lines) or type(e).__name__


def _clip(line: str, limit: int = 400) -> str:
    """A message line of at most ``limit`` characters (a library may quote whole headers)."""
    return line if len(line) <= limit else line[:limit] + " ..."


def _report(e: BaseException, prog: str | None) -> None:
    prog = prog or Path(sys.argv[0]).name
    sys.stderr.write(f"{prog}: error: {describe_error(e)}\n")
    sys.exit(2)


#: the exit status of a run stopped with Ctrl-C (128 + SIGINT, as a shell reports it)
INTERRUPTED = 130


def _interrupted(prog: str | None, note: str | None = None) -> None:
    prog = prog or Path(sys.argv[0]).name
    sys.stderr.write(f"{prog}: interrupted{f'; {note}' if note else ''}\n")
    sys.exit(INTERRUPTED)


def _debug() -> bool:
    import os

    return bool(os.environ.get(DEBUG_ENV)) or bool(os.environ.get("HYDRA_FULL_ERROR"))


def guarded(task):
    """Decorator for an app's task function (under ``@hydra.main``): an expected failure inside
    the run is reported as by :func:`run_app` before Hydra adds its own lines around it."""
    import functools

    @functools.wraps(task)
    def wrapper(cfg):
        import importlib

        module = importlib.import_module(task.__module__)
        artefacts = tuple(getattr(module, "ARTEFACTS", ()))
        # what an interrupted run must not leave behind (dss-train keeps its checkpoints to resume)
        unfinished = tuple(getattr(module, "UNFINISHED", artefacts))
        try:
            return task(cfg)
        except KeyboardInterrupt as e:  # Ctrl-C: one line, exit 130, no result left looking complete
            _interrupted(None, _end_failed_run(e, artefacts, unfinished))
        except Exception as e:
            if not _expected(e):
                raise
            _end_failed_run(e, artefacts)
            if _DEBUG[0]:
                raise
            _report(e, None)

    return wrapper


_DEBUG = [False]  # run_app's reading of DSS_DEBUG / HYDRA_FULL_ERROR before it sets the latter


def run_app(hydra_main, prog: str | None = None):
    """Run a ``@hydra.main`` function for a person: an expected failure (bad file, key, value,
    model, output; :func:`_expected`) prints one line, ``<prog>: error: ...``, to stderr and
    exits with status 2, without a traceback; ``DSS_DEBUG=1`` or ``HYDRA_FULL_ERROR=1`` shows
    it. Other errors (bugs) keep their traceback. Returns what ``hydra_main`` returns."""
    import os

    debug = _DEBUG[0] = _debug()
    saved = os.environ.get("HYDRA_FULL_ERROR")
    # Hydra prints its own shortened report unless HYDRA_FULL_ERROR is set; with it set, the
    # exception comes here and is reported in one line
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        return hydra_main()
    except KeyboardInterrupt:  # before or after the task (composing the config, a callback)
        _interrupted(prog)
    except Exception as e:
        if debug or not _expected(e):
            raise
        _report(e, prog)
    finally:
        if saved is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = saved
