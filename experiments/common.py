"""Helpers shared by the Hydra apps: run directory, config echo, metrics, positional inputs."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

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

    A first-use compile takes 30 s or more and happens once per machine; it is no part of a
    run's cost, so the apps call this before their clocks and report it apart
    (``time_s.kernel_build``). Returns the seconds spent compiling (0 when cached).
    """
    from dss import _ext

    before = _ext.build_seconds()
    _ext.load_cpu()
    if device is not None and getattr(device, "type", str(device)) == "cuda":
        from dss import _ext_cuda

        _ext_cuda.load_cuda()
    return _ext.build_seconds() - before


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
