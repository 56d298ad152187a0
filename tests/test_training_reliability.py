"""dss-train / dss-export under bad data and reruns: corrupt shards, non-finite losses and
weights, an existing run directory, the best checkpoint across a resume (fast)."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch

from experiments.apps.train import run

try:
    from tests.pix2pix_fixtures import compose_train, pairs_root, tiny_overrides, trained_run  # noqa: F401
except ImportError:
    from pix2pix_fixtures import compose_train, pairs_root, tiny_overrides, trained_run  # noqa: F401

torch.set_num_threads(1)


def _copy(root: Path, dest: Path) -> Path:
    shutil.copytree(root, dest)
    return dest


def _first_train_shard(root: Path) -> tuple[Path, dict, dict]:
    manifest = json.loads((root / "manifest.json").read_text())
    entry = next(s for s in manifest["shards"] if s["split"] == "train" and s["noise_level"] == 0.01)
    return root / entry["path"], entry, manifest


# ------------------------------------------------------------------------------ corrupt data
def test_a_shard_that_differs_from_its_manifest_hash_is_refused_before_training(pairs_root, tmp_path):
    """A flipped byte inside a shard's pixels (the memory maps skip the zip CRC): refused by name
    when the split is set up, before any step, and dss-train writes no checkpoint."""
    from pix2pix.datamodule import Pix2PixDataModule
    from pix2pix.shards import DatasetFormatError

    root = _copy(pairs_root, tmp_path / "ds")
    shard, _, _ = _first_train_shard(root)
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(bytes(data))
    dm = Pix2PixDataModule(root, noise_level=0.01, batch_size=4)
    with pytest.raises(DatasetFormatError, match=rf"{shard.name}: its sha256 does not match the manifest's"):
        dm.setup("fit")
    out = tmp_path / "run"
    with pytest.raises(DatasetFormatError, match="sha256 does not match"):
        run(compose_train(tiny_overrides(root, out)))
    assert not list(out.rglob("*.ckpt")) and not (out / "metrics.json").exists()


def test_a_corrupt_shard_header_gives_a_short_error(pairs_root, tmp_path):
    """A shard whose .npy header is garbage: one short line naming the file (numpy quotes the
    whole header), also when it comes back from a DataLoader worker as a traceback text."""
    from experiments.common import describe_error
    from pix2pix.shards import DatasetFormatError, open_shard

    root = _copy(pairs_root, tmp_path / "ds")
    shard, entry, _ = _first_train_shard(root)
    data = bytearray(shard.read_bytes())
    at = data.index(b"{'descr'")
    data[at:at + 600] = (b"{'descr': " + b"x" * 590)[:600]
    shard.write_bytes(bytes(data))
    with pytest.raises(DatasetFormatError) as info:
        open_shard(shard, (32, 32), 3, entry["num_pairs"])
    msg = str(info.value)
    assert shard.name in msg and "\n" not in msg and len(msg) < 400, msg
    worker = DatasetFormatError("Caught DatasetFormatError in DataLoader worker process 0.\nOriginal Traceback (most "
                                "recent call last):\n  File \"x.py\", line 1, in f\n    g()\n" + "  ...\n" * 40
                                + f"pix2pix.shards.DatasetFormatError: {msg}\n")
    line = describe_error(worker)
    assert line == msg


def _nan_dataset(pairs_root: Path, dest: Path) -> Path:
    """The synthetic dataset with NaN pixels in one training shard (its manifest hash updated:
    the bytes are as written, the values are bad)."""
    import io

    root = _copy(pairs_root, dest)
    shard, entry, manifest = _first_train_shard(root)
    with np.load(shard) as z:
        arrays = {k: z[k].copy() for k in z.files}
    arrays["noisy"][0, 5:9, 5:9] = np.nan
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    shard.write_bytes(buf.getvalue())
    entry["sha256"] = hashlib.sha256(buf.getvalue()).hexdigest()
    (root / "manifest.json").write_text(json.dumps(manifest))
    return root


def test_a_non_finite_loss_stops_training_with_one_clear_error(pairs_root, tmp_path):
    root = _nan_dataset(pairs_root, tmp_path / "ds")
    out = tmp_path / "run"
    # a ValueError (pix2pix.module.NonFiniteLossError): the apps report it in one line
    with pytest.raises(ValueError, match=r"train/loss_\w = nan at epoch 0.*noisy images hold NaN/inf pixels"):
        run(compose_train(tiny_overrides(root, out, "trainer.max_epochs=2")))
    assert not (out / "metrics.json").exists() and not (out / "denoiser.onnx").exists()


def test_export_refuses_non_finite_weights_and_parity(trained_run, tmp_path, monkeypatch):
    from experiments.apps.export import run as export_run

    ckpt = torch.load(trained_run["best_ckpt"], map_location="cpu", weights_only=False)
    name = next(k for k in ckpt["state_dict"] if k.startswith("generator.") and k.endswith("weight"))
    ckpt["state_dict"][name][...] = float("nan")
    bad = tmp_path / "nan.ckpt"
    torch.save(ckpt, bad)
    out = tmp_path / "export"
    cfg = compose_train([f"ckpt_path={bad}", f"output_dir={out}", f"output={out / 'm.onnx'}"], config_name="export")
    with pytest.raises(ValueError, match=r"nan\.ckpt: the generator holds non-finite weights \(1 tensors"):
        export_run(cfg)
    assert not (out / "m.onnx").exists()
    # a parity that is NaN fails the check (NaN > tol is False)
    import pix2pix.export

    monkeypatch.setattr(pix2pix.export, "onnx_parity", lambda *a, **k: float("nan"))
    cfg = compose_train([f"ckpt_path={trained_run['best_ckpt']}", f"output_dir={out}", f"output={out / 'p.onnx'}"],
                        config_name="export")
    with pytest.raises(ValueError, match=r"ONNX parity nan exceeds"):  # experiments.apps.export.ParityError
        export_run(cfg)
    assert not (out / "p.onnx").exists()


def test_data_settings_of_the_wrong_type_name_the_key(pairs_root, tmp_path):
    with pytest.raises(ValueError, match=r"^data\.batch_size='abc' is not an integer$"):
        run(compose_train(tiny_overrides(pairs_root, tmp_path / "run", "data.batch_size=abc")))


# ------------------------------------------------------------------------------ run directories
def test_train_into_an_earlier_runs_directory_is_refused_unless_resuming_it_or_overwrite(pairs_root, tmp_path):
    from experiments.common import OutputExistsError

    out = tmp_path / "run"
    first = run(compose_train(tiny_overrides(pairs_root, out, "export_onnx=false")))
    files = {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and not p.name.startswith(".")}
    with pytest.raises(OutputExistsError, match=r"run holds an earlier run's results .*overwrite=true"):
        run(compose_train(tiny_overrides(pairs_root, out, "export_onnx=false", "seed=7")))
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and not p.name.startswith(".")} == files
    # resuming that run continues it in place
    resumed = run(compose_train(tiny_overrides(pairs_root, out, "export_onnx=false", "trainer.max_epochs=2",
                                               f"ckpt_path={first['last_ckpt']}")))
    assert resumed["global_step"] == 2 * first["global_step"]
    # overwrite=true replaces the earlier run: none of its checkpoints stays beside the new ones
    fresh = run(compose_train(tiny_overrides(pairs_root, out, "export_onnx=false", "overwrite=true")))
    assert fresh["global_step"] == first["global_step"]
    assert sorted(p.name for p in (out / "checkpoints").glob("*.ckpt")) == ["best-epoch000.ckpt", "last.ckpt"]


class Scramble(L.Callback):
    """Wreck the generator at the start of the given epoch: its validation is then worse than
    any before it."""

    def __init__(self, epoch: int):
        self.epoch = epoch

    def on_train_epoch_start(self, trainer, pl_module):
        if trainer.current_epoch == self.epoch:
            g = torch.Generator().manual_seed(0)
            with torch.no_grad():
                for p in pl_module.generator.parameters():
                    p.add_(torch.randn(p.shape, generator=g) * 3.0)


def test_a_resume_into_another_directory_keeps_and_exports_the_runs_best(pairs_root, tmp_path):
    """Run a: 2 epochs. Run b resumes a's last.ckpt into a new directory and its third epoch is
    worse: b's best stays a's (copied into b, same validation), and b exports it."""
    a = run(compose_train(tiny_overrides(pairs_root, tmp_path / "a", "trainer.max_epochs=2", "export_onnx=false")))
    best_a = Path(a["best_ckpt"])
    before = best_a.read_bytes()
    b = run(compose_train(tiny_overrides(pairs_root, tmp_path / "b", "trainer.max_epochs=3", f"ckpt_path={a['last_ckpt']}",
                                         f"+callbacks.scramble._target_={__name__}.Scramble",
                                         "+callbacks.scramble.epoch=2")))
    assert b["epoch"] == 3
    best_b = Path(b["best_ckpt"])
    assert best_b.parent == tmp_path / "b" / "checkpoints" and best_b.name == best_a.name
    assert b["best_val"]["val/smape"] == pytest.approx(a["best_val"]["val/smape"], rel=1e-6)
    assert best_b.read_bytes() == before and best_a.read_bytes() == before  # a's file is left as it was
    assert Path(b["onnx"]).is_file()
