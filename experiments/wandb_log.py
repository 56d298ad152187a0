"""Weights & Biases logging of one ``dss-denoise`` / ``dss-filter`` run, offline by default.

The apps' ``wandb`` block (``conf/denoise.yaml``)::

    wandb:
      log: auto        # auto: log every job of a Hydra multirun (a sweep), not a single run | true | false
      mode: offline    # offline (no network, no account; `wandb sync <run dir>/wandb/offline-run-*`
                       # uploads later) | online (after `wandb login`) | disabled
      project: dss-denoise

A logged run holds the resolved config, the optimiser's loss per step, every scalar of
``metrics.json`` as the run summary (dotted keys, e.g. ``summary.output.paper.chamfer``) and the
run's PNG figures. The local alternative needs no W&B at all:
``python -m experiments.evaluation.baselines.aggregate <multirun dir>`` turns a sweep's ``metrics.json``
files into one table and an accuracy-vs-time chart.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

log = logging.getLogger(__name__)

MODES = ("offline", "online", "disabled")


def in_multirun() -> bool:
    """True inside a Hydra multirun job (``-m``)."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    except Exception:  # pragma: no cover - hydra not importable or not initialised
        return False


def wanted(node) -> bool:
    """Whether to log, from the ``wandb`` block (``log: auto | true | false``)."""
    if not node:
        return False
    setting = node.get("log", "auto")
    if isinstance(setting, str):
        if setting.lower() != "auto":
            raise ValueError(f"wandb.log must be auto, true or false, got {setting!r}")
        return in_multirun()
    return bool(setting)


def check(node) -> bool:
    """Validate the ``wandb`` block before any work (a typo must not surface after a long run);
    returns :func:`wanted`."""
    if node and str(node.get("mode", "offline")) not in MODES:
        raise ValueError(f"wandb.mode must be one of {MODES}, got {node.get('mode')!r}")
    return wanted(node)


def _scalars(d: dict) -> dict[str, float]:
    """Finite int/float leaves of a nested dict as ``{"a.b": value}`` (bools, strings and lists dropped)."""
    from experiments.common import flatten

    return {k: v for k, v in flatten(d).items()
            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)}


def log_run(cfg, out_dir: str | os.PathLike, metrics: dict, history: dict | None = None,
            figures: list[str] = (), job_type: str = "denoise") -> Path | None:
    """Write one W&B run of an app into ``out_dir/wandb`` and return its run directory (None when
    not wanted).

    Args:
        cfg: the app's config; its ``wandb`` block (see the module docstring) decides, and the
            whole resolved config is logged.
        metrics: the app's ``metrics.json`` content; its numeric leaves become the run summary.
        history: the optimiser's history (``step``, ``loss``, ``image_loss``, ``time``), logged per step.
        figures: PNG file names in ``out_dir``, logged as images under their file stem.
    """
    from omegaconf import OmegaConf

    node = cfg.get("wandb")
    if not check(node):
        return None
    mode = str(node.get("mode", "offline"))
    import wandb

    out_dir = Path(out_dir)
    run = wandb.init(project=str(node.get("project", "dss-denoise")), name=out_dir.name, dir=str(out_dir),
                     mode=mode, config=OmegaConf.to_container(cfg, resolve=True), job_type=job_type,
                     reinit="finish_previous")
    try:
        if history:
            for i, step in enumerate(history.get("step", [])):
                row = {k: history[k][i] for k in ("loss", "image_loss", "time")
                       if k in history and i < len(history[k]) and math.isfinite(history[k][i])}
                if row:
                    run.log(row, step=int(step))
        run.summary.update(_scalars(metrics))
        pngs = [out_dir / f for f in figures if str(f).endswith(".png")]
        images = {f.stem: wandb.Image(str(f)) for f in pngs if f.is_file()}
        if images:
            run.log(images)
        run_path = Path(run.dir).parent  # <out_dir>/wandb/<offline-run-...>/files -> the run directory
    finally:
        run.finish()
    log.info("W&B run (%s) written to %s", mode, run_path)
    return run_path
