"""Background snap of the denoiser's output (pix2pix.postprocess), in the ONNX runtime and in
experiments.evaluation.evaluate_denoiser (fast)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pix2pix.export import build_metadata, export_onnx
from pix2pix.networks import ResNetGenerator
from pix2pix.postprocess import SNAP_FRACTION, background_snap_threshold, snap_background
from pix2pix.runtime import OnnxDenoiser
from pix2pix.testing import make_synthetic_pair_dataset

torch.set_num_threads(1)

RENDER = {"shading": "point_light", "renderer": {"background": 0.0},
          "light": {"type": "point", "position": [0.0, 0.0, 0.0], "space": "camera", "ambient": 0.1}}


def test_threshold_comes_from_the_render_settings():
    assert background_snap_threshold(RENDER) == pytest.approx(SNAP_FRACTION * 0.1)
    assert background_snap_threshold(None) is None
    assert background_snap_threshold({"light": {"position": [0, 0, 0]}}) is None  # no ambient known
    grey = {**RENDER, "renderer": {"background": 0.5}}
    assert background_snap_threshold(grey) is None  # background is not black: nothing to snap to


def test_snap_zeroes_dark_pixels_only_numpy_and_torch():
    rng = np.random.default_rng(0)
    x = rng.normal(0.2, 0.3, (2, 3, 8, 8)).astype(np.float32)
    y = snap_background(x, 0.05, channel_dim=1)
    dark = x.max(axis=1) < 0.05
    assert dark.any() and (~dark).any()
    assert np.all(y.transpose(0, 2, 3, 1)[dark] == 0)
    np.testing.assert_array_equal(y.transpose(0, 2, 3, 1)[~dark], x.transpose(0, 2, 3, 1)[~dark])
    t = snap_background(torch.from_numpy(x.transpose(0, 2, 3, 1)), 0.05, channel_dim=-1)
    np.testing.assert_array_equal(t.numpy(), y.transpose(0, 2, 3, 1))
    assert snap_background(x, None, channel_dim=1) is x


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    torch.manual_seed(0)
    g = ResNetGenerator(ngf=8, n_blocks=1, residual=True, zero_init_head=False).eval()
    info = {"name": "unit", "generator": g.config(), "train_crop_size": 32,
            "data": {"noise_level": 0.01, "image_size": [32, 32], "render": RENDER}}
    path = tmp_path_factory.mktemp("snap") / "g.onnx"
    export_onnx(g, path, build_metadata(info))
    return g, path


def test_runtime_snaps_by_default_and_can_return_the_raw_output(model):
    g, path = model
    x = np.random.default_rng(1).random((2, 3, 16, 16), dtype=np.float32) * 0.2
    with torch.no_grad():
        ref = g(torch.from_numpy(x)).numpy()
    raw = OnnxDenoiser(path, intra_op_num_threads=1, snap_background=False)(x)
    np.testing.assert_allclose(raw, ref, atol=1e-4)
    den = OnnxDenoiser(path, intra_op_num_threads=1)
    assert den.background_threshold == pytest.approx(0.05)
    out = den(x)
    dark = raw.max(axis=1) < 0.05
    assert dark.any() and (~dark).any()  # the test input exercises both sides
    np.testing.assert_array_equal(out, snap_background(raw, 0.05, channel_dim=1))


def test_evaluate_denoiser_reports_raw_and_snapped(model, tmp_path):
    from experiments.evaluation.evaluate_denoiser import evaluate, markdown

    _, path = model
    root = make_synthetic_pair_dataset(tmp_path / "ds", n_train=4, n_val=8, size=32, noise_level=0.01,
                                       shard_size=4, seed=0, render=RENDER)
    r = evaluate(path, root, "val", max_pairs=6, batch=4)
    assert r["pairs"] == 6 and r["background_threshold"] == pytest.approx(0.05)
    m = r["metrics"]
    for k in ("noisy", "raw", "snapped"):
        assert m[k]["smape"] == pytest.approx(m[k]["smape_clean_fg"] + m[k]["smape_halo"], rel=1e-6)
    # on the halo the target is 0: a snapped pixel scores 0 there, never more than the raw one
    assert m["snapped"]["smape_halo"] <= m["raw"]["smape_halo"] + 1e-9
    assert m["raw"]["smape_reduction"] == pytest.approx(1 - m["raw"]["smape"] / m["noisy"]["smape"])
    assert "background snap" in markdown(r)
