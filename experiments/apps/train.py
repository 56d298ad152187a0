"""``dss-train``: train the Pix2Pix denoiser (Hydra app over :func:`run`).

    dss-train experiment=noise_1pct data.root=<dataset dir>
    dss-train ckpt_path=<run>/checkpoints/last.ckpt ...      # resume exactly
    dss-train -m hparams_search=optuna ...                   # Optuna sweep

Configs: ``conf/train.yaml`` and its groups (model, data, trainer, logger, callbacks,
experiment, hparams_search). The run directory (``output_dir``) receives ``config.yaml`` (the
resolved config), ``checkpoints/`` (best and last), ``val_grids/``, logger output,
``denoiser.onnx`` (export of the best checkpoint) and ``metrics.json``.

A directory that holds an earlier run's results is refused before any work, unless
``ckpt_path`` resumes that run (a checkpoint inside it) or ``overwrite=true`` (which removes
them first). A resume into another directory carries the run's best checkpoint (copied) and
its score (:class:`pix2pix.checkpoint.BestCheckpoint`), so the export is the run's best.
"""

from __future__ import annotations

import logging
import time
import warnings
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from experiments.common import claim_run_dir, guarded, release_claims

log = logging.getLogger(__name__)

# pix2pix.datamodule.PairStream splits its batch-aligned plan across workers itself, so its
# __len__ is exact with any number of workers; Lightning warns about the general case.
warnings.filterwarnings("ignore", message=".*IterableDataset.*has `__len__` defined")

__all__ = ["run", "main", "instantiate_all", "ARTEFACTS", "claim_run"]

#: what a run writes into its output directory (an earlier run's are refused, or removed with
#: overwrite=true: experiments.common.claim_run_dir)
ARTEFACTS = ("denoiser.onnx", "denoiser.onnx.md", "metrics.json", "config.yaml", "checkpoints/*.ckpt",
             "val_grids/*.png", "csv/metrics.csv", "csv/hparams.yaml", "tensorboard/events.out.tfevents.*")
#: what an interrupted run removes (its checkpoints stay: ckpt_path=<run>/checkpoints/last.ckpt resumes)
UNFINISHED = ("denoiser.onnx", "denoiser.onnx.md", "metrics.json")


def _spawned_rank() -> int:
    """This process's rank when Lightning's DDP launcher started it (``LOCAL_RANK``/``NODE_RANK``,
    which it sets for the processes it spawns); 0 for the process a user starts."""
    import os

    return int(os.environ.get("LOCAL_RANK", 0) or 0) + int(os.environ.get("NODE_RANK", 0) or 0)


def claim_run(cfg: DictConfig, out: Path, clear_records: bool = False) -> Path:
    """Claim the output directory ``out`` (experiments.common.claim_run_dir): an earlier run's
    results there are refused unless ``overwrite``, except when ``ckpt_path`` is a checkpoint of
    that very run (a resume continues it in place). The processes Lightning's DDP launcher starts
    for the other ranks share rank 0's claim."""
    if _spawned_rank() != 0:
        return Path(out)
    ckpt = cfg.get("ckpt_path")
    if ckpt and Path(str(ckpt)).resolve().is_relative_to(Path(out).resolve()):
        return claim_run_dir(out, ())  # resuming this run: its files stay
    return claim_run_dir(out, ARTEFACTS, bool(cfg.get("overwrite", False)), clear_records=clear_records)


def _instantiate(node, group: str):
    """``hydra.utils.instantiate(node)``; a constructor's ValueError names the key, with the group
    (``data.batch_size='abc' is not an integer``)."""
    import re

    from hydra.errors import InstantiationException

    try:
        return hydra.utils.instantiate(node)
    except InstantiationException as e:
        cause = e.__cause__
        if isinstance(cause, ValueError):
            msg = str(cause).splitlines()[0] if str(cause) else type(cause).__name__
            raise ValueError(f"{group}.{msg}" if re.match(r"\w+=", msg) else f"{group}: {msg}") from cause
        raise


def _atomic_json(path: Path, obj: Any) -> None:
    from dss.io_utils import atomic_write_json

    atomic_write_json(path, obj)


def _atomic_text(path: Path, text: str) -> None:
    from dss.io_utils import atomic_write_text

    atomic_write_text(path, text)


def instantiate_all(cfg: DictConfig | None) -> list:
    """Every ``_target_`` entry of a group node of named entries (``callbacks``, ``logger``), in order."""
    if not cfg:
        return []
    return [hydra.utils.instantiate(c) for _, c in cfg.items() if isinstance(c, DictConfig) and "_target_" in c]


def _float_metrics(metrics: dict[str, Any]) -> dict[str, float]:
    out = {}
    for k, v in metrics.items():
        try:
            out[k] = float(v)
        except (TypeError, ValueError):
            continue
    return out


def _check_data(node) -> None:
    """Refuse a missing dataset before anything is built, saying how to make one."""
    root = node.get("root") if node is not None else None
    if root is None:
        return
    root = Path(str(root))
    if not (root / "manifest.json").is_file():
        what = "does not exist" if not root.exists() else "holds no finished dss-pairs dataset (no manifest.json)"
        raise FileNotFoundError(f"training data {root} {what}: make it with `dss-prep` (it writes data/pairs), "
                                "or point data.root=<dir> at a dss-prep output")


def run(cfg: DictConfig, extra_callbacks: list | tuple = ()) -> dict[str, Any]:
    """Train (or resume) per ``cfg``, with the ``callbacks`` group's Lightning callbacks and
    ``extra_callbacks``; returns (and writes to metrics.json) the results.

    Returns a dict with ``metrics`` (last logged values), ``best_val`` (validation of the best
    checkpoint: output vs clean and the noisy baseline), ``best_ckpt``, ``last_ckpt``,
    ``global_step``, ``epoch``, ``fit_seconds``, ``train_images_per_s``, ``onnx`` and
    ``objective`` (``cfg.optimized_metric`` of the best checkpoint, for sweepers).
    """
    _check_data(cfg.get("data"))
    out_dir = Path(cfg.output_dir)
    ckpt_path = cfg.get("ckpt_path")
    if ckpt_path is not None and not Path(ckpt_path).is_file():
        raise FileNotFoundError(f"ckpt_path={ckpt_path}: no such checkpoint file")
    claim_run(cfg, out_dir)
    try:
        return _run(cfg, out_dir, ckpt_path, extra_callbacks)
    finally:
        release_claims()


def _run(cfg: DictConfig, out_dir: Path, ckpt_path, extra_callbacks=()) -> dict[str, Any]:
    import lightning as L
    import torch
    from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint

    if cfg.get("torch_threads"):
        torch.set_num_threads(int(cfg.torch_threads))
    if cfg.get("seed") is not None:
        L.seed_everything(int(cfg.seed), workers=True)

    log.info("data: %s", cfg.data.get("_target_"))
    datamodule = _instantiate(cfg.data, "data")
    model = _instantiate(cfg.model, "model")
    out_dir.mkdir(parents=True, exist_ok=True)
    _atomic_text(out_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
    callbacks = instantiate_all(cfg.get("callbacks")) + list(extra_callbacks)
    loggers = instantiate_all(cfg.get("logger"))
    if not loggers:
        dropped = [c for c in callbacks if isinstance(c, LearningRateMonitor)]
        if dropped:
            log.info("no logger configured: LearningRateMonitor dropped")
        callbacks = [c for c in callbacks if not isinstance(c, LearningRateMonitor)]
    trainer = hydra.utils.instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)
    hparams = OmegaConf.to_container(cfg, resolve=True)
    for lg in loggers:
        lg.log_hyperparams(hparams)

    result: dict[str, Any] = {"task_name": cfg.get("task_name"), "model": cfg.model.get("name"),
                              "noise_level": None, "resumed_from": ckpt_path}
    try:
        t0 = time.perf_counter()
        trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path)
        result["fit_seconds"] = time.perf_counter() - t0
        result["metrics"] = _float_metrics(trainer.callback_metrics)
        result["train_images_per_s"] = result["metrics"].get("train/images_per_s")
        result["global_step"] = int(trainer.global_step)
        result["epoch"] = int(trainer.current_epoch)
        result["noise_level"] = getattr(datamodule, "noise_level", None)
        from pix2pix.checkpoint import LastCheckpoint

        ckpt_cb = next((c for c in callbacks if isinstance(c, ModelCheckpoint) and c.monitor), None)
        last_cb = next((c for c in callbacks if isinstance(c, LastCheckpoint)), None)
        best = ckpt_cb.best_model_path if ckpt_cb is not None else ""
        result["best_ckpt"] = best or None
        last = (last_cb.last_model_path or last_cb.best_model_path) if last_cb is not None else None
        if not last and ckpt_cb is not None:
            last = ckpt_cb.last_model_path
        result["last_ckpt"] = last or None
        result["best_val"] = None
        if best and cfg.get("validate_best", True):
            val = trainer.validate(model, datamodule=datamodule, ckpt_path=best, verbose=False)
            result["best_val"] = _float_metrics(val[0]) if val else None
        source = result["best_val"] or result["metrics"]
        metric = cfg.get("optimized_metric")
        result["objective"] = source.get(metric) if metric else None
        result["onnx"] = None
        if best and cfg.get("export_onnx", True) and trainer.is_global_zero:
            from pix2pix.export import export_checkpoint

            onnx_path, _, _ = export_checkpoint(best, out_dir / "denoiser.onnx", overwrite=True)
            result["onnx"] = str(onnx_path)
        result["torch_threads"] = torch.get_num_threads()
        if trainer.is_global_zero:
            _atomic_json(out_dir / "metrics.json", result)
    finally:
        for lg in loggers:
            if type(lg).__name__ == "WandbLogger":
                import wandb

                wandb.finish()
    return result


@hydra.main(version_base="1.3", config_path="../../conf", config_name="train")
@guarded
def _main(cfg: DictConfig) -> float | None:
    """Console entry point ``dss-train``; returns the optimised metric (for sweepers)."""
    result = run(cfg)
    obj = result.get("objective")
    return None if obj is None else float(obj)


def main() -> float | None:
    """Console entry point: an expected failure prints one line and exits 2 (experiments.common.run_app)."""
    from experiments.common import run_app

    return run_app(_main)


if __name__ == "__main__":
    main()
