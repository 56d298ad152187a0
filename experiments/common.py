"""Helpers shared by the Hydra apps: run directory, config echo, metrics, positional inputs."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from dss.io_utils import atomic_write_json, atomic_write_text

log = logging.getLogger(__name__)

__all__ = ["run_dir", "save_config", "save_metrics", "positional_to_override", "renderer_settings", "optimization_report"]


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


def optimization_report(history: dict, t_start: float, t_opt: float) -> dict:
    """The metrics.json fields every optimisation app reports (schedule, steps, timings, load)."""
    import os
    import time

    import torch

    return {
        "optimizer": history["config"],
        "steps": history.get("steps"),
        "lr_halvings": history.get("lr_halvings"),
        "final_loss": history["loss"][-1] if history["loss"] else None,
        "time_s": {"total": time.perf_counter() - t_start, "optimization": t_opt,
                   "reference_generation": history.get("reference_seconds"),
                   "per_step": t_opt / max(1, history.get("steps") or 1)},
        "torch_threads": torch.get_num_threads(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
