"""dss-train: Hydra configs, the data stream, Lightning training, resume, W&B offline (fast)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import hydra
import lightning as L
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from experiments.apps.train import instantiate_all, run
from pix2pix.datamodule import PairStream, Pix2PixDataModule
from pix2pix.module import GRID_MIN_TILE, Pix2PixModule
from pix2pix.networks import PatchDiscriminator, ResNetGenerator

try:
    from tests.pix2pix_fixtures import (  # noqa: F401
        CONF_DIR,
        KillAt,
        RankDump,
        compose_train,
        pairs_root,
        subprocess_env,
        tiny_overrides,
        trained_run,
        wandb_offline_env,
    )
except ImportError:
    from pix2pix_fixtures import (  # noqa: F401
        CONF_DIR,
        KillAt,
        RankDump,
        compose_train,
        pairs_root,
        subprocess_env,
        tiny_overrides,
        trained_run,
        wandb_offline_env,
    )

torch.set_num_threads(1)

MODEL_PRESETS = sorted(p.stem for p in (CONF_DIR / "model").glob("*.yaml"))
GROUPS = {g: sorted(p.stem for p in (CONF_DIR / g).glob("*.yaml"))
          for g in ("data", "trainer", "logger", "callbacks", "experiment", "hparams_search")}


# ---- configs -------------------------------------------------------------------------------------
def test_presets_exist():
    assert {"paper", "cpu_small", "tiny"} <= set(MODEL_PRESETS)
    assert {"cpu", "gpu", "ddp"} <= set(GROUPS["trainer"])
    assert {"none", "csv", "tensorboard", "wandb"} <= set(GROUPS["logger"])
    assert {"noise_0.3pct", "noise_1pct"} <= set(GROUPS["experiment"])
    assert "optuna" in GROUPS["hparams_search"]


@pytest.mark.parametrize("preset", MODEL_PRESETS)
def test_model_presets_instantiate(preset, tmp_path):
    cfg = compose_train([f"model={preset}", f"output_dir={tmp_path}"])
    model = hydra.utils.instantiate(cfg.model)
    assert isinstance(model, Pix2PixModule)
    assert isinstance(model.generator, ResNetGenerator)
    assert isinstance(model.discriminator, PatchDiscriminator)
    assert model.hparams.lambda_l1 == 100.0 and tuple(model.hparams.betas) == (0.5, 0.999)
    if preset == "paper":
        gcfg = model.generator.config()
        assert (gcfg["ngf"], gcfg["n_blocks"], gcfg["residual"]) == (64, 9, False)
        assert gcfg["norm_layer"]["target"] == "pix2pix.norms.PixelNorm"
        assert model.hparams.train_crop_size == 256 and model.hparams.lr == 2e-4
        assert model.discriminator.receptive_field == 70


@pytest.mark.parametrize("group", ["data", "trainer", "logger", "callbacks"])
def test_group_options_instantiate(group, tmp_path, wandb_offline_env):
    for option in GROUPS[group]:
        extra = ["trainer.accelerator=cpu"] if group == "trainer" else []
        cfg = compose_train([f"{group}={option}", f"output_dir={tmp_path}", *extra])
        if group == "data" and option == "onthefly":  # pairs rendered from stored clouds
            from experiments.onthefly import OnTheFlyDataModule

            dm = hydra.utils.instantiate(cfg.data, noise_level=0.01)
            assert isinstance(dm, OnTheFlyDataModule) and dm.crop_size == cfg.model.train_crop_size
        elif group == "data":
            dm = hydra.utils.instantiate(cfg.data)
            assert isinstance(dm, Pix2PixDataModule) and dm.crop_size == cfg.model.train_crop_size
        elif group == "trainer":
            trainer = hydra.utils.instantiate(cfg.trainer, logger=False, callbacks=[])
            assert isinstance(trainer, L.Trainer)
        elif group == "logger":
            loggers = instantiate_all(cfg.get("logger"))
            assert (len(loggers) == 0) == (option == "none")
            if option == "wandb":
                assert loggers[0]._offline is True  # offline unless the user opts in
        else:
            cbs = instantiate_all(cfg.get("callbacks"))
            assert (len(cbs) == 0) == (option == "none")


def test_the_quick_path_stops_on_its_time_budget(tmp_path):
    """experiment=quick (the README's quick path): the tiny model on dss-prep's tiny dataset, and
    trainer.max_time ends the run, not max_epochs (the trainer group's 10 would end it first)."""
    cfg = compose_train(["experiment=quick", f"output_dir={tmp_path}"])
    assert cfg.model.name == "tiny" and cfg.data.root == "data/pairs-tiny" and cfg.data.noise_level == 0.01
    assert cfg.torch_threads == 1 and cfg.trainer.max_time == "00:00:05:00"
    trainer = hydra.utils.instantiate(cfg.trainer, logger=False, callbacks=[])
    # a 32 px tiny dataset runs thousands of epochs in 5 minutes: only the time limit stops it
    assert trainer.max_epochs >= 10_000
    short = compose_train(["experiment=quick", "trainer.max_time=00:00:02:00", f"output_dir={tmp_path}"])
    assert short.trainer.max_time == "00:00:02:00"


@pytest.mark.parametrize("exp,level", [("noise_0.3pct", 0.003), ("noise_1pct", 0.01),
                                       ("noise_0.3pct_coverage", 0.003), ("planes_1pct", 0.01),
                                       ("planes_0.3pct", 0.003)])
def test_experiments_compose(exp, level, tmp_path):
    cfg = compose_train([f"experiment={exp}", f"output_dir={tmp_path}"])
    assert cfg.data.noise_level == level
    if exp.startswith("planes"):  # no GAN term, the planes normalisation and losses
        model = hydra.utils.instantiate(cfg.model)
        assert model.discriminator is None and not model.uses_gan
        assert model.generator.config()["kind"] == "planes" and len(model.generator.config()["input_mean"]) == 4
        assert model.hparams.lambda_depth > 0 and cfg.data.root == "data/pairs-planes"
        assert cfg.callbacks.model_checkpoint.monitor == "val/depth_err"
    assert cfg.trainer.accelerator == "cpu" and cfg.model.name == "cpu_small"
    assert hydra.utils.instantiate(cfg.data).noise_level == level
    if exp.endswith("_coverage"):  # warm start from the shipped 0.3% model (+ a coverage head if it has none)
        model = hydra.utils.instantiate(cfg.model)
        assert model.generator.coverage is not None
        assert set(model.warm_start["kept_init"]) <= {"coverage.1.bias", "coverage.1.weight"}
        assert model.warm_start["loaded"] + len(model.warm_start["kept_init"]) == len(model.generator.state_dict())


def test_hparams_search_composes_with_optuna_sweeper(tmp_path):
    cfg = compose_train(["hparams_search=optuna", f"output_dir={tmp_path}"], return_hydra_config=True)
    assert "OptunaSweeper" in cfg.hydra.sweeper._target_
    assert cfg.hydra.sweeper.direction == "minimize" and cfg.optimized_metric == "val/smape"
    assert "model.lr" in cfg.hydra.sweeper.params


# ---- data stream ---------------------------------------------------------------------------------
def _stream(pairs_root, **kw):
    dm = Pix2PixDataModule(pairs_root, noise_level=0.01, batch_size=4, crop_size=16, **kw)
    dm.setup("fit")
    return dm


def test_datamodule_needs_a_noise_level_when_several(pairs_root):
    dm = Pix2PixDataModule(pairs_root, batch_size=2)
    with pytest.raises(ValueError, match="one model per noise level"):
        dm.setup("fit")


def test_stream_order_depends_on_seed_and_epoch_only(pairs_root):
    ds = _stream(pairs_root).train_set
    assert len(ds) == 16
    ids0 = [int(s["pair_id"]) for s in ds]
    assert sorted(ids0) == sorted(set(ids0)) and len(ids0) == 16
    assert [int(s["pair_id"]) for s in ds] == ids0  # same epoch: same order
    ds.set_epoch(1)
    ids1 = [int(s["pair_id"]) for s in ds]
    assert sorted(ids1) == sorted(ids0) and ids1 != ids0
    # independent of the number of DataLoader workers (batch-aligned plan, round-robin workers)
    loader = torch.utils.data.DataLoader(ds, batch_size=4, num_workers=2)
    ids_w = [int(i) for b in loader for i in b["pair_id"]]
    assert ids_w == ids1
    sample = next(iter(ds))
    assert sample["noisy"].shape == (3, 16, 16) and sample["noisy"].dtype == torch.float32
    assert sample["mask"].shape == (16, 16) and sample["mask"].dtype == torch.bool


def test_stream_splits_ranks_evenly_and_disjointly(pairs_root):
    dm = _stream(pairs_root)
    shards = dm.train_set.shards
    parts = [PairStream(shards, 4, (32, 32), crop_size=16, rank=r, world_size=3) for r in range(3)]
    ids = [[int(s["pair_id"]) for s in p] for p in parts]
    assert len({len(i) for i in ids}) == 1 and len(ids[0]) == 16 // 3
    flat = sum(ids, [])
    assert len(flat) == len(set(flat))


def test_val_stream_is_deterministic_full_images(pairs_root):
    dm = Pix2PixDataModule(pairs_root, noise_level=0.01, batch_size=2, crop_size=16,
                           max_val_pairs=3)
    dm.setup("fit")
    a = [s["noisy"] for s in dm.val_set]
    b = [s["noisy"] for s in dm.val_set]
    assert len(a) == 3 and all(torch.equal(x, y) for x, y in zip(a, b))
    assert a[0].shape == (3, 32, 32)


def test_trainer_reshuffles_each_epoch(pairs_root, tmp_path):
    """Epoch e of a fit reads exactly the plan of epoch e (set_epoch reaches the stream in time)."""
    seen: dict[int, list[int]] = {}

    class Rec(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            seen.setdefault(trainer.current_epoch, []).extend(int(i) for i in batch["pair_id"])

    dm = _stream(pairs_root, num_workers=1, persistent_workers=True)
    model = Pix2PixModule(ResNetGenerator(ngf=4, n_blocks=1, residual=True), None)
    trainer = L.Trainer(max_epochs=3, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False,
                        limit_val_batches=0, default_root_dir=tmp_path, callbacks=[Rec()])
    trainer.fit(model, datamodule=dm)
    plans = {e: [int(np.load(dm.train_set.shards[s].path)["pair_id"][r])
                 for s, r in dm.train_set._rank_plan(e)] for e in range(3)}
    assert seen == plans and seen[0] != seen[1]


# ---- training ------------------------------------------------------------------------------------
@pytest.mark.parametrize("preset", MODEL_PRESETS)
def test_fast_dev_run_each_model_preset(preset, pairs_root, tmp_path):
    cfg = compose_train(tiny_overrides(pairs_root, tmp_path, f"model={preset}",
                                       "model.train_crop_size=32", "data.batch_size=2",
                                       "trainer.fast_dev_run=true"))
    result = run(cfg)
    assert result["global_step"] == 2  # one batch: a D step and a G step
    for k in ("val/smape", "val/noisy_smape", "val/l1", "val/psnr", "train/loss_g", "train/loss_d"):
        assert np.isfinite(result["metrics"][k]), k
    assert (tmp_path / "config.yaml").is_file() and (tmp_path / "metrics.json").is_file()


def test_tiny_model_overfits_tiny_dataset(pairs_root, tmp_path):
    """The tiny preset's generator, predicting the image (paper mode), fits 8 pairs: the
    training L1 drops by at least 50%. (The residual variant starts at the identity, already
    near the L1 floor of a short run, so a 50% drop is not what it can show in seconds.)"""
    from pix2pix.testing import make_synthetic_pair_dataset

    root = make_synthetic_pair_dataset(tmp_path / "ds8", n_train=8, n_val=2, size=32,
                                       noise_level=0.01, shard_size=8)

    def fit(residual: bool, epochs: int) -> list[float]:  # noqa: B023
        losses: list[float] = []

        class Rec(L.Callback):
            def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
                losses.append(float(trainer.callback_metrics["train/l1_step"]))

        cfg = compose_train(["model=tiny", f"output_dir={tmp_path}",
                             f"model.generator.residual={residual}"])
        model = hydra.utils.instantiate(cfg.model)
        dm = Pix2PixDataModule(root, batch_size=8, crop_size=32)
        trainer = L.Trainer(max_epochs=epochs, logger=False, enable_checkpointing=False,
                            enable_progress_bar=False, enable_model_summary=False,
                            limit_val_batches=0, default_root_dir=tmp_path, callbacks=[Rec()])
        L.seed_everything(0)
        trainer.fit(model, datamodule=dm)
        return losses

    direct = fit(False, 120)
    first, last = np.mean(direct[:3]), np.mean(direct[-10:])
    assert last <= 0.5 * first, (first, last)


def _opt_states(trainer) -> list[dict]:
    import copy

    return [copy.deepcopy(o.state_dict()) for o in trainer.optimizers]  # live tensors otherwise


def _assert_same_opt_state(a: dict, b: dict):
    assert a["param_groups"] == b["param_groups"]
    assert a["state"].keys() == b["state"].keys()
    for k in a["state"]:
        for name in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(torch.as_tensor(a["state"][k][name]), torch.as_tensor(b["state"][k][name]))


def test_kill_and_resume_continue_exactly(pairs_root, tmp_path):
    """Uninterrupted 3 epochs == 2 epochs, killed in epoch 3, resumed from last.ckpt."""
    base = ["trainer.max_epochs=3", "trainer.deterministic=true"]
    cfg_a = compose_train(tiny_overrides(pairs_root, tmp_path / "a", *base, "export_onnx=false"))
    res_a = run(cfg_a)
    ck_a = torch.load(res_a["last_ckpt"], map_location="cpu", weights_only=False)

    kill = [f"+callbacks.kill._target_={KillAt.__module__}.KillAt", "+callbacks.kill.epoch=2",
            "+callbacks.kill.batch=1"]
    cfg_b = compose_train(tiny_overrides(pairs_root, tmp_path / "b", *base, *kill))
    with pytest.raises(RuntimeError, match="simulated kill"):
        run(cfg_b)
    last_b = tmp_path / "b" / "checkpoints" / "last.ckpt"
    ck_b = torch.load(last_b, map_location="cpu", weights_only=False)
    assert ck_b["global_step"] == 2 * ck_a["global_step"] // 3  # saved at the end of epoch 2

    restored: dict = {}

    class Probe(L.Callback):
        def on_train_start(self, trainer, pl_module):
            restored["step"] = trainer.global_step
            restored["opt"] = _opt_states(trainer)

    cfg_c = compose_train(tiny_overrides(pairs_root, tmp_path / "c", *base, f"ckpt_path={last_b}"))
    res_c = run(cfg_c, extra_callbacks=[Probe()])
    # the resumed run starts at the saved step with the saved optimizer state ...
    assert restored["step"] == ck_b["global_step"]
    for got, saved in zip(restored["opt"], ck_b["optimizer_states"]):
        _assert_same_opt_state(got, saved)
    # ... and ends where the uninterrupted run ended: same step, weights, optimizer state
    ck_c = torch.load(res_c["last_ckpt"], map_location="cpu", weights_only=False)
    assert res_c["global_step"] == res_a["global_step"] == ck_a["global_step"]
    assert ck_c["epoch"] == ck_a["epoch"]
    for k, v in ck_a["state_dict"].items():
        assert torch.allclose(v, ck_c["state_dict"][k], atol=1e-6, rtol=0), k
    for a, c in zip(ck_a["optimizer_states"], ck_c["optimizer_states"]):
        assert a["state"].keys() == c["state"].keys()
        for p in a["state"]:
            assert torch.allclose(a["state"][p]["exp_avg"], c["state"][p]["exp_avg"], atol=1e-7)


class SigtermAt(L.Callback):
    """Send this process SIGTERM after (epoch, batch), as a scheduler stopping a job would."""

    def __init__(self, epoch: int, batch: int):
        self.epoch, self.batch = epoch, batch

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        import os
        import signal

        if trainer.current_epoch == self.epoch and batch_idx == self.batch:
            os.kill(os.getpid(), signal.SIGTERM)


def test_last_checkpoint_is_written_every_epoch_without_improvement(pairs_root, tmp_path):
    """lr 0: validation never improves after the first epoch; last.ckpt still follows every epoch,
    so a run killed in epoch 3 resumes after epoch 2, not after epoch 1."""
    kill = [f"+callbacks.kill._target_={KillAt.__module__}.KillAt", "+callbacks.kill.epoch=2",
            "+callbacks.kill.batch=1"]
    cfg = compose_train(tiny_overrides(pairs_root, tmp_path / "flat", "trainer.max_epochs=3", "model.lr=0.0", *kill))
    with pytest.raises(RuntimeError, match="simulated kill"):
        run(cfg)
    ckpts = tmp_path / "flat" / "checkpoints"
    best = torch.load(next(ckpts.glob("best-*.ckpt")), map_location="cpu", weights_only=False)
    last = torch.load(ckpts / "last.ckpt", map_location="cpu", weights_only=False)
    assert best["global_step"] > 0 and best["epoch"] == 0  # never improved after epoch 1
    assert last["global_step"] == 2 * best["global_step"]  # saved after epoch 2 all the same


def test_sigterm_saves_the_step_reached_and_resume_continues_there(pairs_root, tmp_path):
    """A run stopped by SIGTERM mid-epoch writes last.ckpt at the step it reached; resuming
    from it starts at that step with the saved optimiser state and ends at the planned step."""
    base = ["trainer.max_epochs=2"]
    stop = [f"+callbacks.stop._target_={__name__}.SigtermAt", "+callbacks.stop.epoch=1", "+callbacks.stop.batch=1"]
    cfg = compose_train(tiny_overrides(pairs_root, tmp_path / "a", *base, *stop, "export_onnx=false"))
    with pytest.raises(SystemExit):  # Lightning's SIGTERMException
        run(cfg)
    last = tmp_path / "a" / "checkpoints" / "last.ckpt"
    ck = torch.load(last, map_location="cpu", weights_only=False)
    steps_per_epoch = 8  # 16 pairs / batch 4, a D and a G step each
    assert ck["global_step"] == steps_per_epoch + 2 * 2  # epoch 1, batches 0 and 1 done

    restored: dict = {}

    class Probe(L.Callback):
        def on_train_start(self, trainer, pl_module):
            restored["step"] = trainer.global_step
            restored["opt"] = _opt_states(trainer)

    res = run(compose_train(tiny_overrides(pairs_root, tmp_path / "b", *base, f"ckpt_path={last}",
                                           "export_onnx=false")), extra_callbacks=[Probe()])
    assert restored["step"] == ck["global_step"]
    for got, saved in zip(restored["opt"], ck["optimizer_states"]):
        _assert_same_opt_state(got, saved)
    assert res["global_step"] == 2 * steps_per_epoch


def test_run_dir_contents_and_export(trained_run):
    out = Path(trained_run["output_dir"])
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["global_step"] == trained_run["global_step"] > 0
    assert metrics["torch_threads"] == 1
    assert Path(metrics["best_ckpt"]).is_file() and Path(metrics["best_ckpt"]).parent == out / "checkpoints"
    assert (out / "checkpoints" / "last.ckpt").is_file()
    assert (out / "denoiser.onnx").is_file()
    assert OmegaConf.load(out / "config.yaml").model.name == "tiny"
    grids = sorted((out / "val_grids").glob("epoch*.png"))
    assert len(grids) == 2  # one per validation epoch
    assert len(list((out / "val_grids").glob("validate-*.png"))) == 1  # the best checkpoint's validation
    assert (out / "denoiser.onnx").stat().st_mode & 0o044 == 0o044 and grids[0].stat().st_mode & 0o044 == 0o044
    import matplotlib.image

    img = matplotlib.image.imread(grids[-1])
    s = -(-GRID_MIN_TILE // 32)  # 32 px renders, enlarged to be seen
    assert img.shape[:2] == (24 + 2 * 32 * s, 3 * 32 * s)  # a header, 2 images, columns noisy | output | clean
    bv = metrics["best_val"]
    for k in ("val/l1", "val/smape", "val/psnr", "val/noisy_l1", "val/noisy_smape",
              "val/noisy_psnr", "val/smape_reduction"):
        assert np.isfinite(bv[k]), k
    assert metrics["objective"] == bv["val/smape"]


def test_wandb_offline_writes_a_run(pairs_root, tmp_path, wandb_offline_env):
    out = tmp_path / "run"
    cfg = compose_train(tiny_overrides(pairs_root, out, "logger=wandb", "export_onnx=false"))
    res = run(cfg)
    assert res["global_step"] > 0
    runs = list((out / "wandb").glob("offline-run-*"))
    assert len(runs) == 1, list(out.rglob("*"))[:20]
    assert list(runs[0].glob("run-*.wandb"))
    assert list(runs[0].rglob("*.png"))  # the validation grid went to W&B as an image


def test_dss_train_cli_end_to_end(pairs_root, tmp_path):
    """`dss-train experiment=noise_1pct data.root=...` through @hydra.main (a subprocess)."""
    out = tmp_path / "cli"
    cmd = [sys.executable, "-m", "experiments.apps.train", "experiment=noise_1pct",
           f"data.root={pairs_root}", "model=tiny", "data.num_workers=0",
           "data.persistent_workers=false", "trainer.max_epochs=1", "trainer.max_time=null",
           "logger=csv", f"hydra.run.dir={out}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=subprocess_env(), timeout=300,
                          cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 0, proc.stderr[-3000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["noise_level"] == 0.01 and metrics["task_name"] == "train_noise_1pct"
    assert (out / "denoiser.onnx").is_file() and (out / "csv" / "metrics.csv").is_file()


@pytest.mark.slow  # an Optuna multirun of two trainings (about 12 s): pytest -m slow
def test_optuna_sweep_runs(pairs_root, tmp_path):
    """hparams_search=optuna with two trials of the tiny model (multirun through Hydra)."""
    out = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "experiments.apps.train", "hparams_search=optuna",
           f"data.root={pairs_root}", "data.noise_level=0.01", "model=tiny",
           "data.num_workers=0", "data.persistent_workers=false", "trainer.max_epochs=1",
           "logger=none", "hydra.sweeper.n_trials=2", "hydra.sweeper.sampler.n_startup_trials=2",
           f"hydra.sweep.dir={out}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=subprocess_env(), timeout=300,
                          cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 0, proc.stderr[-3000:]
    best = OmegaConf.load(out / "optimization_results.yaml")
    assert "model.lr" in best.best_params and np.isfinite(best.best_value)
    assert sorted(p.name for p in out.iterdir() if p.is_dir() and p.name.isdigit()) == ["0", "1"]


@pytest.mark.slow  # times every preset's training step (about 9 s): pytest -m slow
def test_bench_train_times_every_kind_of_preset(tmp_path):
    """`python -m experiments.benchmarks.bench_train`: the paper preset (linear-decay schedule) is timed as
    well as the constant-rate CPU presets, and the JSON holds a positive images/s for each."""
    from experiments.benchmarks.bench_train import main as bench

    out = tmp_path / "bench.json"
    res = bench(["--presets", "tiny", "paper", "--threads", "1", "--warmup", "0", "--batches", "1",
                 "--out", str(out)])
    rows = json.loads(out.read_text())["results"]
    assert [r["preset"] for r in rows] == ["tiny", "paper"] and res["results"] == rows
    assert all(r["images_per_s"] and r["images_per_s"] > 0 and r["timed_batches"] == 1 for r in rows)


# ---- scale-out -----------------------------------------------------------------------------------
def _ddp_cmd(pairs_root, out: Path, dump: Path, *extra: str) -> list[str]:
    """dss-train under conf/trainer/ddp.yaml, on 2 CPU processes (gloo) instead of 4 GPUs."""
    return [sys.executable, "-m", "experiments.apps.train", "trainer=ddp", "trainer.accelerator=cpu",
            "trainer.devices=2", "trainer.sync_batchnorm=false", "model=tiny", "logger=none",
            f"data.root={pairs_root}", "data.noise_level=0.01", "data.batch_size=4", "data.val_batch_size=4",
            "data.num_workers=0", "data.persistent_workers=false", "trainer.num_sanity_val_steps=0",
            "callbacks.progress_bar=null", "+trainer.enable_progress_bar=false", "trainer.enable_model_summary=false",
            "torch_threads=1", "export_onnx=false", "validate_best=false",
            f"+callbacks.dump._target_={RankDump.__module__}.RankDump", f"+callbacks.dump.dirpath={dump}",
            f"hydra.run.dir={out}", *extra]


def _ranks(dump: Path) -> list[dict]:
    return [torch.load(dump / f"rank{r}.pt", map_location="cpu", weights_only=False) for r in (0, 1)]


@pytest.mark.slow  # two training processes, about two minutes on two cores
def test_ddp_on_two_cpu_processes_agrees_and_resumes(pairs_root, tmp_path):
    """Lightning DDP (gloo) with 2 processes: both ranks end with the same weights and step, and
    the checkpoint resumes under DDP to the planned step with the ranks still in agreement."""
    import os

    tests_dir = str(Path(__file__).resolve().parent)
    env = {**subprocess_env(), "MASTER_PORT": str(29500 + (abs(hash(str(tmp_path))) % 2000)),
           "PYTHONPATH": os.pathsep.join(p for p in (tests_dir, os.environ.get("PYTHONPATH")) if p)}
    out, dump = tmp_path / "ddp", tmp_path / "dump1"
    proc = subprocess.run(_ddp_cmd(pairs_root, out, dump, "trainer.max_epochs=1"), capture_output=True, text=True,
                          env=env, timeout=400, cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 0, proc.stderr[-3000:]
    r0, r1 = _ranks(dump)
    assert (r0["world_size"], r1["world_size"]) == (2, 2) and r0["global_step"] == r1["global_step"] > 0
    for k, v in r0["state_dict"].items():
        assert torch.equal(v, r1["state_dict"][k]), k
    steps = r0["global_step"]
    last = out / "checkpoints" / "last.ckpt"
    assert torch.load(last, map_location="cpu", weights_only=False)["global_step"] == steps

    dump2 = tmp_path / "dump2"
    proc = subprocess.run(_ddp_cmd(pairs_root, tmp_path / "ddp2", dump2, "trainer.max_epochs=2", f"ckpt_path={last}"),
                          capture_output=True, text=True, env=env, timeout=400, cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 0, proc.stderr[-3000:]
    r0, r1 = _ranks(dump2)
    assert r0["global_step"] == r1["global_step"] == 2 * steps
    for k, v in r0["state_dict"].items():
        assert torch.equal(v, r1["state_dict"][k]), k
