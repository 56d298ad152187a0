"""Pairs rendered on the fly from stored clouds: dss-prep output=clouds, the on-the-fly stream
and DataModule, a dss-train run on them (CPU, tiny; fast)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from data_prep.clouds import CLOUDS_FORMAT, generate_clouds, load_cloud, read_clouds_manifest
from data_prep.render_spec import load_render_spec, spec_path
from data_prep.shards import PrepConfig, build_plan
from experiments.onthefly import OnTheFlyDataModule, render_cloud_pairs

torch.set_num_threads(1)


def _config():
    pc = PrepConfig(families=("superquadric", "torus"), shapes_per_family=3, resolution=32, num_points=1500,
                    normals_k=12, val_fraction=0.2, test_fraction=0.2, views_per_shape=2)
    return pc, load_render_spec(spec_path("planes"), image_size=[32, 32])


@pytest.fixture(scope="module")
def clouds(tmp_path_factory):
    pc, spec = _config()
    root = tmp_path_factory.mktemp("clouds") / "ds"
    stats = generate_clouds(pc, spec, root, progress=False)
    return root, stats


def test_cloud_dataset_holds_the_plans_shapes_and_resumes(clouds):
    root, stats = clouds
    pc, spec = _config()
    m = read_clouds_manifest(root)
    assert m["format"] == CLOUDS_FORMAT and m["render"]["shading"] == "planes"
    plan = build_plan(pc, spec)
    assert [(s["shape_id"], s["split"]) for s in m["shapes"]] == [(s.shape_id, s.split) for s in plan.shapes]
    pts, mn = load_cloud(root, m["shapes"][0])
    assert pts.shape == (1500, 3) and pts.dtype == np.float32 and mn.shape == (1500, 3)
    assert np.allclose(np.linalg.norm(mn, axis=1), 1.0, atol=2e-3)
    again = generate_clouds(pc, spec, root, progress=False)
    assert again["shapes_written"] == 0 and again["shapes_skipped"] == len(m["shapes"])
    assert stats["bytes"] < 1500 * 20 * len(m["shapes"])  # ~18 bytes a point (+ headers)


def test_on_the_fly_pairs_are_dss_prep_pairs_of_the_same_noise_and_views(clouds):
    """Same clean cloud, noise seed and views: the pair dss-prep would have rendered."""
    from data_prep.pairs import render_pairs
    from data_prep.sampling import noisy_copy, with_normals

    root, _ = clouds
    _, spec = _config()
    m = read_clouds_manifest(root)
    pts, mn = load_cloud(root, m["shapes"][1])
    views = spec.sample_views(3, np.random.default_rng(5))
    got = render_cloud_pairs(pts, mn, 0.01, 1234, views, spec, normals_k=12)
    clean = with_normals(pts, 12, "mesh", mn)
    noisy = with_normals(noisy_copy(pts, 0.01, 1234), 12, "mesh", mn)
    want = render_pairs(clean.points, clean.normals, noisy.points, noisy.normals, views, spec)
    for k in ("noisy", "clean", "mask"):
        np.testing.assert_array_equal(got[k], want[k])


def _dm(root, **kw):
    dm = OnTheFlyDataModule(root, noise_level=0.01, views_per_shape=2, batch_size=2, crop_size=16,
                            max_val_pairs=4, num_workers=0, seed=3, device="cpu", pool=2, **kw)
    dm.setup("fit")
    return dm


def test_fresh_views_and_noise_every_epoch_fixed_validation(clouds):
    root, _ = clouds
    dm = _dm(root)
    ds = dm.train_set
    n_train = sum(1 for s in dm.manifest["shapes"] if s["split"] == "train")
    assert len(ds) == 2 * n_train
    e0 = list(ds)
    assert len(e0) == len(ds) and e0[0]["coords"].shape == (2, 16, 16) and e0[0]["noisy"].shape == (3, 16, 16)
    e0b = list(ds)
    for a, b in zip(e0, e0b):  # a function of (seed, epoch)
        torch.testing.assert_close(a["noisy"], b["noisy"])
    ds.set_epoch(1)
    e1 = list(ds)
    assert sum(not torch.equal(a["clean"], b["clean"]) for a, b in zip(e0, e1)) >= len(e0) - 1  # fresh views
    v0 = list(dm.val_set)
    dm.set_epoch(2)
    v1 = list(dm.val_set)
    n_val = sum(1 for s in dm.manifest["shapes"] if s["split"] == "val")
    assert len(v0) == len(dm.val_set) == min(4, 2 * n_val) and v0[0]["noisy"].shape == (3, 32, 32)
    for a, b in zip(v0, v1):
        torch.testing.assert_close(a["noisy"], b["noisy"])
    info = dm.info()
    assert info["on_the_fly"] and info["render"]["shading"] == "planes" and info["flips"] == ["hflip", "vflip",
                                                                                                  "transpose"]
    with pytest.raises(ValueError, match="not one of the dataset's"):
        OnTheFlyDataModule(root, noise_level=0.02).setup("fit")


def test_dss_train_on_the_fly_exports_a_planes_model(clouds, tmp_path):
    from hydra import compose, initialize_config_dir

    from experiments.apps.train import run
    from pix2pix.export import read_metadata

    root, _ = clouds
    conf = str(__import__("pathlib").Path(__file__).resolve().parents[1] / "conf")
    with initialize_config_dir(config_dir=conf, version_base="1.3"):
        cfg = compose("train", overrides=[
            "experiment=planes_1pct", "data=onthefly", f"data.root={root}", "data.views_per_shape=2",
            "data.batch_size=2", "data.num_workers=0", "data.max_val_pairs=2", "model.train_crop_size=16",
            "model.generator.ngf=4", "model.generator.n_blocks=1", "logger=none", "callbacks.progress_bar=null",
            "+trainer.enable_progress_bar=false", "trainer.enable_model_summary=false", "trainer.max_epochs=1",
            "trainer.max_time=null", "trainer.num_sanity_val_steps=0", "torch_threads=1", f"output_dir={tmp_path}"])
    res = run(cfg)
    assert res["onnx"] and res["best_val"]["val/noisy_depth_err"] > 0
    meta = read_metadata(res["onnx"])
    assert meta["dss.render_settings"]["shading"] == "planes" and meta["dss.noise_level"] == 0.01
