"""Fixtures and helpers shared by the pix2pix / dss-train / ONNX tests (imported by them).

- ``pairs_root``: a tiny synthetic ``dss-pairs/1`` dataset (32 px, two noise levels).
- ``compose_train`` / ``tiny_overrides``: the Hydra compose API over ``conf/``.
- ``trained_run``: one short dss-train run of the ``tiny`` preset (checkpoints, ONNX).
- ``KillAt``: a callback that raises mid-training (to simulate a killed run).
"""

from __future__ import annotations

import os
from pathlib import Path

import lightning as L
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from pix2pix.testing import make_synthetic_pair_dataset

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def compose_train(overrides: list[str], config_name: str = "train",
                  return_hydra_config: bool = False) -> DictConfig:
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name, overrides=overrides, return_hydra_config=return_hydra_config)


def tiny_overrides(root: Path, out: Path, *extra: str) -> list[str]:
    """A fast, deterministic dss-train config on the synthetic dataset (1 CPU thread)."""
    return [
        "model=tiny",
        "logger=none",
        f"data.root={root}",
        "data.noise_level=0.01",
        "data.batch_size=4",
        "data.val_batch_size=4",
        "data.num_workers=0",
        "data.persistent_workers=false",
        f"output_dir={out}",
        "trainer.max_epochs=1",
        "trainer.num_sanity_val_steps=0",
        "trainer.log_every_n_steps=1",
        "callbacks.progress_bar=null",
        "+trainer.enable_progress_bar=false",
        "trainer.enable_model_summary=false",
        "torch_threads=1",
        *extra,
    ]


@pytest.fixture(scope="session")
def pairs_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("pairs") / "ds"
    return make_synthetic_pair_dataset(root, n_train=16, n_val=4, size=32,
                                       noise_level=[0.003, 0.01], shard_size=4, seed=0)


@pytest.fixture(scope="session")
def trained_run(pairs_root, tmp_path_factory) -> dict:
    """dss-train run() of the tiny preset for 2 epochs; returns its result dict."""
    from experiments.train import run

    out = tmp_path_factory.mktemp("trained") / "run"
    cfg = compose_train(tiny_overrides(pairs_root, out, "trainer.max_epochs=2"))
    result = run(cfg)
    result["output_dir"] = str(out)
    return result


@pytest.fixture()
def wandb_offline_env(tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_DIR", str(tmp_path / "wandb_dir"))
    monkeypatch.setenv("WANDB_CACHE_DIR", str(tmp_path / "wandb_cache"))
    monkeypatch.setenv("WANDB_CONFIG_DIR", str(tmp_path / "wandb_config"))
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_DISABLE_GIT", "true")
    # any attempt to reach a server would need these; make sure none is set
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.setenv("WANDB_BASE_URL", "http://127.0.0.1:9")  # unroutable if ever contacted
    return tmp_path


class KillAt(L.Callback):
    """Raise RuntimeError at (epoch, batch): a run killed mid-epoch, after a checkpoint."""

    def __init__(self, epoch: int, batch: int):
        self.epoch, self.batch = epoch, batch

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.current_epoch == self.epoch and batch_idx == self.batch:
            raise RuntimeError("simulated kill")


def subprocess_env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")
    env["HYDRA_FULL_ERROR"] = "1"
    return env


class RankDump(L.Callback):
    """Write each rank's final weights and step to ``<dirpath>/rank<r>.pt`` (DDP agreement checks)."""

    def __init__(self, dirpath: str):
        self.dirpath = dirpath

    def on_train_end(self, trainer, pl_module):
        import torch

        Path(self.dirpath).mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().cpu().clone() for k, v in pl_module.state_dict().items()}
        torch.save({"rank": trainer.global_rank, "world_size": trainer.world_size, "global_step": trainer.global_step,
                    "state_dict": state}, Path(self.dirpath) / f"rank{trainer.global_rank}.pt")
