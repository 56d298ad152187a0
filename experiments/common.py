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
    _claims[key] = fd
    if remove:
        _remove_on_release.add(key)


def release_claims() -> None:
    """Release every claim this process holds (the end of a run)."""
    import os

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


def claim_run_dir(out: Path, artefacts, overwrite: bool = False, what: str = "run directory") -> Path:
    """Claim ``out`` for this run before any work: exclusively (a second concurrent run fails at
    once with :class:`OutputInUseError`) and without mixing runs. Files of ``artefacts`` (glob
    patterns relative to ``out``: what the app writes) left by an earlier run make it refuse
    (:class:`OutputExistsError`) unless ``overwrite``, which removes them first, so no earlier
    result stays beside new metrics."""
    out = Path(out)
    _lock(out / ".dss-run.lock", f"{what} {out}")
    earlier = _earlier_results(out, artefacts)
    if earlier and not overwrite:
        names = ", ".join(str(p.relative_to(out)) for p in earlier[:3]) + (" ..." if len(earlier) > 3 else "")
        raise OutputExistsError(f"{what} {out} holds an earlier run's results ({names}); refusing to mix runs "
                                "(choose another directory, or pass overwrite=true to replace them)")
    for p in earlier:
        p.unlink(missing_ok=True)
    if earlier:
        log.warning("overwrite=true: removed %d files of an earlier run from %s", len(earlier), out)
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
    return path


class ClaimRunDir(Callback):
    """Hydra callback (conf/hydra/default.yaml): claims ``hydra.run.dir`` before Hydra writes
    ``.hydra/`` into it, so that a refused run leaves an earlier run's files as they were. ``app``:
    the app's config name; its module (:data:`experiments.app_registry.APPS`) lists in
    ``ARTEFACTS`` what the app writes. Apps without ``ARTEFACTS`` claim nothing (the table commands
    resume in their folder; dss-train, dss-prep and dss-export write to fresh or their own places)."""

    def __init__(self, app: str):
        self.app = app

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        artefacts = run_dir_artefacts(self.app)
        if artefacts is None:
            return
        out = Path(str(config.hydra.run.dir))
        try:
            claim_run_dir(out, [*artefacts, ".hydra/*.yaml"], bool(config.get("overwrite", False)))
        except (OSError, ValueError) as e:
            # Hydra turns a callback's exception into a warning and runs the job anyway: stop here
            if _DEBUG[0]:
                import traceback

                traceback.print_exc()
            _report(e, None)


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
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip() and not ln.strip().startswith(
        ("full_key:", "object_type=", "reference_type="))]
    if isinstance(cause, Exception) and str(cause).strip():
        first = str(cause).strip().splitlines()[0]
        if first not in lines:
            lines.append(first)
    return "; ".join(lines) or type(e).__name__


def _report(e: BaseException, prog: str | None) -> None:
    prog = prog or Path(sys.argv[0]).name
    sys.stderr.write(f"{prog}: error: {describe_error(e)}\n")
    sys.exit(2)


def _debug() -> bool:
    import os

    return bool(os.environ.get(DEBUG_ENV)) or bool(os.environ.get("HYDRA_FULL_ERROR"))


def guarded(task):
    """Decorator for an app's task function (under ``@hydra.main``): an expected failure inside
    the run is reported as by :func:`run_app` before Hydra adds its own lines around it."""
    import functools

    @functools.wraps(task)
    def wrapper(cfg):
        try:
            return task(cfg)
        except Exception as e:
            if _DEBUG[0] or not _expected(e):
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
    except Exception as e:
        if debug or not _expected(e):
            raise
        _report(e, prog)
    finally:
        if saved is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = saved
