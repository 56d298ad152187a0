"""Training throughput (images/s) of each denoiser preset on this machine's CPU.

    python -m experiments.benchmarks.bench_train                       # all presets, 1 and 2 threads
    python -m experiments.benchmarks.bench_train --presets tiny cpu_small --threads 1 --batches 4

Each measurement composes ``conf/train.yaml`` with ``model=<preset>``, builds the real
LightningModule (G + D, manual optimisation, the same training step as dss-train) and runs
``--warmup`` + ``--batches`` training steps through a Lightning Trainer on a synthetic
dss-pairs dataset at the preset's crop size (loader without worker processes, so the thread
count is what is measured). images/s = batch_size * timed batches / their wall time.
Validation is off. Writes JSON (and prints a table).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

DEFAULT_OUT = Path("results") / "bench" / "bench_train.json"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _compose(overrides: list[str]):
    from hydra import compose, initialize_config_dir

    conf = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        return compose("train", overrides=overrides)


def measure(preset: str, threads: int, batch_size: int, warmup: int, batches: int,
            data_root: Path, crop: int) -> dict:
    """One (preset, threads) measurement; returns a JSON-able dict."""
    import hydra
    import lightning as L
    import torch

    from pix2pix.datamodule import Pix2PixDataModule

    torch.set_num_threads(threads)
    # the paper preset's linear-decay schedule needs an epoch count; a schedule does not change
    # the cost of a step, so every preset is timed with a constant learning rate
    cfg = _compose([f"model={preset}", "output_dir=.", "logger=none", "model.lr_schedule=constant"])
    L.seed_everything(0, verbose=False)
    model = hydra.utils.instantiate(cfg.model)
    dm = Pix2PixDataModule(data_root, batch_size=batch_size, crop_size=crop)
    times: list[float] = []

    class Timer(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            self.t0 = time.perf_counter()

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            times.append(time.perf_counter() - self.t0)

    with tempfile.TemporaryDirectory() as tmp:
        trainer = L.Trainer(max_steps=2 * (warmup + batches), limit_val_batches=0, logger=False,
                            enable_checkpointing=False, enable_progress_bar=False,
                            enable_model_summary=False, default_root_dir=tmp,
                            accelerator="cpu", callbacks=[Timer()])
        trainer.fit(model, datamodule=dm)
    timed = times[warmup:warmup + batches]
    secs = sum(timed)
    n_g = sum(p.numel() for p in model.generator.parameters())
    n_d = sum(p.numel() for p in model.discriminator.parameters()) if model.discriminator else 0
    return {
        "preset": preset,
        "threads": threads,
        "load_average_1min": os.getloadavg()[0],
        "crop": crop,
        "batch_size": batch_size,
        "timed_batches": len(timed),
        "seconds_per_batch": secs / max(1, len(timed)),
        "images_per_s": batch_size * len(timed) / secs if secs > 0 else None,
        "generator_params": n_g,
        "discriminator_params": n_d,
    }


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--presets", nargs="+", default=["tiny", "cpu_small", "cpu_medium", "paper"])
    p.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--paper-batch-size", type=int, default=1,
                   help="batch size for the paper preset (pix2pix default 1; 256 px is slow on a CPU)")
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--batches", type=int, default=4)
    from experiments import outputs

    outputs.add_arguments(p, published=str(DEFAULT_OUT), what="output JSON file")
    args = p.parse_args(argv)
    args.out = Path(outputs.folder(args, "bench_train", name="bench_train.json"))

    import torch

    from experiments.figures import command_line
    from pix2pix.testing import make_synthetic_pair_dataset

    results = []
    with tempfile.TemporaryDirectory() as tmp:
        roots: dict[int, Path] = {}
        for preset in args.presets:
            crop = int(_compose([f"model={preset}", "output_dir=."]).model.train_crop_size)
            bs = args.paper_batch_size if preset == "paper" else args.batch_size
            if crop not in roots:
                n = max(bs, 8) * (args.warmup + args.batches + 1)
                roots[crop] = make_synthetic_pair_dataset(Path(tmp) / f"d{crop}", n_train=n, n_val=1,
                                                          size=crop, noise_level=0.01, shard_size=64)
            for th in args.threads:
                r = measure(preset, th, bs, args.warmup, args.batches, roots[crop], crop)
                results.append(r)
                print(f"{preset:11s} threads={th} crop={crop:4d} batch={bs:2d} "
                      f"{r['images_per_s']:8.2f} images/s  ({r['seconds_per_batch']:.3f} s/batch)",
                      flush=True)
    report = {
        "what": "Pix2Pix training throughput: one G step + one D step per batch (images/s)",
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "note": "synthetic dss-pairs data, loader in-process; on a shared machine compare "
                "load_average_1min with cpu_count: a load above it slows (most) the 2-thread runs",
        "results": results,
        "command": command_line("python -m experiments.benchmarks.bench_train", argv),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp_out = args.out.with_suffix(".tmp")
    tmp_out.write_text(json.dumps(report, indent=2) + "\n")
    os.replace(tmp_out, args.out)
    print(f"wrote {args.out}")
    return report


if __name__ == "__main__":
    main()
