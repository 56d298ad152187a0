"""The denoiser in the ``planes`` channel: per-channel input normalisation, channel-aware flips
(against renders of mirrored clouds), pixel coordinates through crops and flips, the planes
losses and validation metrics, experiments.evaluation.evaluate_denoiser's geometry, no background snap
(fast)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from pix2pix.augment import apply_flips, resolve_flips, safe_flips
from pix2pix.export import build_metadata, export_onnx
from pix2pix.metrics import (
    DEPTH_ERROR_CAP,
    pixel_coords,
    planes_errors,
    planes_inverse_depth,
    planes_metric_sums,
    surface_pixels,
)
from pix2pix.networks import ResNetGenerator
from pix2pix.postprocess import background_snap_threshold
from pix2pix.runtime import OnnxDenoiser
from pix2pix.testing import make_synthetic_pair_dataset

torch.set_num_threads(1)


def planes_render_block(size: int = 32) -> dict:
    from data_prep.render_spec import load_render_spec, spec_path

    return load_render_spec(spec_path("planes"), image_size=[size, size]).to_dict()


# ---- per-channel normalisation -------------------------------------------------------------
def test_per_channel_normalisation_round_trips_and_starts_at_the_identity(tmp_path):
    g = ResNetGenerator(ngf=8, n_blocks=1, residual=True, input_mean=[0.0, 0.0, 0.5], input_std=[1.0, 1.0, 0.5])
    assert g.config()["input_mean"] == [0.0, 0.0, 0.5] and g.config()["input_std"] == [1.0, 1.0, 0.5]
    assert not any("input" in k for k in g.state_dict())  # constants, not weights
    x = torch.randn(2, 3, 16, 16)
    torch.testing.assert_close(g.eval()(x), x)  # zero head: the identity, whatever the normalisation
    with torch.no_grad():
        g.head[1].weight.normal_(0, 0.1)
    g2 = ResNetGenerator.from_config(json.loads(json.dumps(g.config())))
    g2.load_state_dict(g.state_dict())
    torch.testing.assert_close(g2.eval()(x), g(x))
    # the per-channel std scales each channel's correction: not the same as a scalar 0.5
    scalar = ResNetGenerator.from_config({**g.config(), "input_mean": 0.5, "input_std": 0.5})
    scalar.load_state_dict(g.state_dict())
    assert not torch.allclose(scalar.eval()(x), g(x))
    path = export_onnx(g, tmp_path / "g.onnx", build_metadata({"generator": g.config(), "data": {}}))
    got = OnnxDenoiser(path, intra_op_num_threads=1, snap_background=False)(x.numpy())
    np.testing.assert_allclose(got, g(x).detach().numpy(), atol=1e-4)
    with pytest.raises(ValueError, match="2 values for 3 channels"):
        ResNetGenerator(ngf=8, n_blocks=1, input_mean=[0.0, 0.5])
    with pytest.raises(ValueError, match="input_std must be > 0"):
        ResNetGenerator(ngf=8, n_blocks=1, input_std=[1.0, 0.0, 1.0])


# ---- the planes generator ------------------------------------------------------------------
def _planes_batch(b=2, h=16, w=16, seed=0):
    """Planes of random surfaces facing the camera at depth ~1 (none near edge-on), a background
    corner."""
    g = torch.Generator().manual_seed(seed)
    n = torch.nn.functional.normalize(torch.randn(b, 3, h, w, generator=g).clamp(-2, 2) * 0.2
                                      + torch.tensor([0.0, 0.0, -1.0]).view(1, 3, 1, 1), dim=1)
    z = 1.0 + 0.2 * torch.rand(b, 1, h, w, generator=g)
    from pix2pix.networks import image_coords

    xy = image_coords(torch.zeros(1, 1, h, w), 40.0)
    ray = torch.cat([xy, torch.ones_like(xy[:, :1])], 1)
    a = n / (n * ray * z).sum(1, keepdim=True)  # a = n / (n . p), p = z (x, y, 1)
    a[:, :, :3, :3] = 0
    return a


def test_planes_generator_reads_depth_and_normal_and_writes_planes_back(tmp_path):
    from pix2pix.networks import PlanesGenerator, generator_from_config, image_coords

    a = _planes_batch()
    g = PlanesGenerator(ngf=8, n_blocks=1, base_blur_px=0).eval()
    torch.testing.assert_close(g(a), a, atol=1e-5, rtol=1e-5)  # zero head, no blur: the identity
    inv, m = g.features(a, image_coords(a, 40.0))
    from pix2pix.metrics import planes_inverse_depth as inv_of

    torch.testing.assert_close(inv[:, 0], inv_of(a, image_coords(a, 40.0).expand(2, -1, -1, -1)))
    torch.testing.assert_close(g.planes(inv, m, image_coords(a, 40.0)), a, atol=1e-5, rtol=1e-5)
    # the blurred base keeps a plane a plane (a linear inverse depth, one normal) away from edges
    n = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, -1.0]), dim=0)
    xy = image_coords(torch.zeros(1, 1, 32, 32), 40.0)
    flat = (n / (n @ torch.tensor([0.1, 0.0, 1.2]))).view(1, 3, 1, 1).expand(1, 3, 32, 32).clone()
    flat[:, :, :, :4] = 0  # a background strip
    blur = PlanesGenerator(ngf=8, n_blocks=1, base_blur_px=2.0).eval()
    inner = (..., slice(6, -6), slice(10, -6))  # 3 blur sigmas from the border and the background
    torch.testing.assert_close(blur(flat)[inner], flat[inner], atol=1e-5, rtol=1e-4)
    assert torch.all(blur(flat)[..., :4] == 0)
    noisy = _planes_batch(1, 32, 32, seed=3)
    inv_n = inv_of(noisy, xy)
    inv_b = inv_of(blur(noisy), xy)
    assert float((inv_b[:, :, 1:] - inv_b[:, :, :-1]).abs().mean()) < 0.5 * float((inv_n[:, :, 1:] - inv_n[:, :, :-1]).abs().mean())
    # trained weights: the background stays background; a crop's own coordinates matter
    with torch.no_grad():
        blur.head[1].weight.normal_(0, 0.05)
    out = blur(a)
    assert torch.all(out[:, :, :3, :3] == 0)
    xy_off = image_coords(torch.zeros(1, 1, 32, 32), 40.0)[..., :16, :16]
    assert not torch.allclose(blur(a, xy_off), out)
    g2 = generator_from_config(json.loads(json.dumps(blur.config())))
    g2.load_state_dict(blur.state_dict())
    torch.testing.assert_close(g2.eval()(a), out)
    meta = build_metadata({"generator": blur.config(), "data": {"render": planes_render_block()}})
    path = export_onnx(blur, tmp_path / "pg.onnx", meta)
    den = OnnxDenoiser(path, intra_op_num_threads=1)
    for b, h, w in ((1, 16, 16), (2, 24, 40)):  # dynamic sizes: the coordinates come from the graph
        x = _planes_batch(b, h, w, seed=h)
        np.testing.assert_allclose(den(x.numpy()), blur(x).detach().numpy(), atol=2e-4, rtol=1e-3)
    with pytest.raises(ValueError, match="fov_deg"):
        PlanesGenerator(fov_deg=0.0)


def test_planes_generator_refuses_another_field_of_view(planes_root, tmp_path):
    import lightning as L

    from pix2pix.datamodule import Pix2PixDataModule
    from pix2pix.module import Pix2PixModule
    from pix2pix.networks import PlanesGenerator

    m = Pix2PixModule(PlanesGenerator(ngf=4, n_blocks=1, fov_deg=60.0), None, lambda_gan=0.0, num_grid_images=0)
    dm = Pix2PixDataModule(planes_root, noise_level=0.01, batch_size=2, crop_size=16)
    tr = L.Trainer(max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                   enable_model_summary=False, default_root_dir=tmp_path)
    with pytest.raises(ValueError, match="field of view"):
        tr.fit(m, datamodule=dm)


# ---- flips ---------------------------------------------------------------------------------
def _mirror(points, normals, cams, m):
    """The cloud mirrored by the camera-space linear map ``m`` (3, 3) through camera 0."""
    R, t = cams.R[0], cams.t[0]
    pc = points @ R.T + t
    p = (pc @ m.T - t) @ R
    n = normals @ R.T @ m.T @ R
    return p, n


@pytest.mark.parametrize("flip", ["hflip", "vflip", "transpose"])
def test_planes_flip_is_the_render_of_the_mirrored_cloud(flip):
    """A flipped planes render, with its channel changes, equals the render of the mirrored
    cloud through the same camera: the flipped pairs are renders of real (mirrored) shapes."""
    from data_prep.render_spec import load_render_spec, spec_path
    from dss.render import render

    g = torch.Generator().manual_seed(0)
    u = torch.nn.functional.normalize(torch.randn(4000, 3, generator=g), dim=1)
    radii = torch.tensor([0.32, 0.2, 0.26])
    pts = u * radii
    nrm = torch.nn.functional.normalize(u / radii, dim=1)  # the ellipsoid's normals
    spec = load_render_spec(spec_path("planes"), image_size=[48, 48])
    cams = spec.cameras(spec.sample_views(1, np.random.default_rng(3)))
    m = {"hflip": torch.diag(torch.tensor([-1.0, 1.0, 1.0])), "vflip": torch.diag(torch.tensor([1.0, -1.0, 1.0])),
         "transpose": torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])}[flip]
    mp, mn = _mirror(pts, nrm, cams, m)
    settings = spec.render_settings()
    with torch.no_grad():
        img = render(pts, nrm, cams, settings, shading="planes").images[0].numpy()
        want = render(mp, mn, cams, settings, shading="planes").images[0].numpy()

    class Always:  # every flip applied
        def random(self):
            return 0.0

    got = apply_flips([img], [flip], Always(), planes=True)[0]
    cov = np.abs(want).max(-1) > 0
    assert cov.mean() > 0.2
    assert ((np.abs(got).max(-1) > 0) == cov).mean() > 0.99
    close = np.isclose(got, want, rtol=1e-3, atol=1e-3).all(-1)
    assert close[cov].mean() > 0.98
    # without the channel change the flipped image is not that render
    plain = apply_flips([img], [flip], Always(), planes=False)[0]
    assert np.isclose(plain, want, rtol=1e-3, atol=1e-3).all(-1)[cov].mean() < 0.9


def test_planes_flips_are_safe_and_carry_the_pixel_coordinates():
    block = planes_render_block()
    assert safe_flips(block) == ["hflip", "vflip", "transpose"]
    assert resolve_flips("auto", block) == ["hflip", "vflip", "transpose"]
    rng = np.random.default_rng(0)
    H = W = 32
    c, y0, x0, f = 16, 5, 3, 40.0
    img = rng.normal(size=(c, c, 3)).astype(np.float32)
    coords = pixel_coords((H, W), f, (c, c), (y0, x0)).permute(1, 2, 0).numpy()

    def inv(a, xy):
        return a[..., 0] * xy[..., 0] + a[..., 1] * xy[..., 1] + a[..., 2]

    class Always:
        def random(self):
            return 0.0

    for flip in ("hflip", "vflip", "transpose"):
        a2, xy2 = apply_flips([img, coords], [flip], Always(), planes=True)
        # every pixel keeps its plane's inverse depth: the flipped image shows the mirrored render
        want = {"hflip": inv(img, coords)[:, ::-1], "vflip": inv(img, coords)[::-1],
                "transpose": inv(img, coords).T}[flip]
        np.testing.assert_allclose(inv(a2, xy2), want, atol=1e-5)
    # hflip: the coordinates are those of the mirrored window of the full render
    _, xy = apply_flips([img, coords], ["hflip"], Always(), planes=True)
    np.testing.assert_allclose(xy, pixel_coords((H, W), f, (c, c), (y0, W - x0 - c)).permute(1, 2, 0).numpy(),
                               atol=1e-6)
    with pytest.raises(ValueError, match="planes must be"):
        apply_flips([np.zeros((4, 4))], ["hflip"], Always(), planes=True)


def test_pixel_coords_match_dss_planes_inverse_depth():
    from dss.cameras import look_at
    from dss.shading import planes_inverse_depth as dss_inv

    cams = look_at(torch.tensor([[0.0, 0.0, -2.0]]), focal=30.0, image_size=(12, 16))
    planes = torch.randn(1, 12, 16, 3)
    xy = pixel_coords((12, 16), 30.0)[None]
    torch.testing.assert_close(planes_inverse_depth(planes.permute(0, 3, 1, 2), xy), dss_inv(planes, cams))


# ---- metrics -------------------------------------------------------------------------------
def test_planes_errors_are_the_geometry_of_known_planes():
    z0, d, theta = 1.2, 0.004, math.radians(10.0)
    clean = torch.zeros(1, 3, 8, 8)
    clean[:, 2] = 1.0 / z0  # a fronto-parallel plane at depth z0
    shifted = clean.clone()
    shifted[:, 2] = 1.0 / (z0 + d)  # the same plane, d farther
    xy = pixel_coords((8, 8), 10.0)[None]
    where = surface_pixels(clean, clean)
    e = planes_errors(shifted, clean, xy, where)
    torch.testing.assert_close(e["depth"], torch.full((64,), d), atol=1e-5, rtol=0)
    assert float(e["normal_deg"].max()) < 0.1
    # a plane through the same point at the image centre, turned by theta about y
    n = torch.tensor([math.sin(theta), 0.0, -math.cos(theta)])  # facing the camera
    p = torch.tensor([0.0, 0.0, z0])
    a = n / (n @ p)
    clean9 = torch.zeros(1, 3, 9, 9)
    clean9[:, 2] = 1.0 / z0
    xy9 = pixel_coords((9, 9), 10.0)[None]  # the centre pixel's ray is the optical axis
    e = planes_errors(a.view(1, 3, 1, 1).expand(1, 3, 9, 9), clean9, xy9, surface_pixels(clean9, clean9))
    torch.testing.assert_close(e["normal_deg"], torch.full((81,), 10.0), atol=1e-3, rtol=0)
    assert float(e["depth"][40]) < 1e-6 < float(e["depth"].max())  # exact on the centre's ray only
    s = planes_metric_sums(clean, clean, xy, where)
    assert float(s["depth_err"]) == 0 and float(s["normal_err_deg"]) < 1e-2 and float(s["pixels"]) == 64
    far = clean.clone()
    far[:, 2] = 1e-6  # background-like output on a surface pixel: capped
    s = planes_metric_sums(far, clean, xy, where)
    assert float(s["depth_err"]) / 64 == pytest.approx(DEPTH_ERROR_CAP)


def test_no_background_snap_for_planes(tmp_path):
    assert background_snap_threshold(planes_render_block()) is None
    g = ResNetGenerator(ngf=8, n_blocks=1, residual=True)
    meta = build_metadata({"generator": g.config(), "data": {"noise_level": 0.01, "image_size": [32, 32],
                                                             "render": planes_render_block()}})
    den = OnnxDenoiser(export_onnx(g, tmp_path / "p.onnx", meta), intra_op_num_threads=1)
    assert den.background_threshold is None
    x = np.zeros((1, 3, 8, 8), np.float32)
    x[..., 2] = 0.04  # below the point light's snap threshold (0.05): kept
    np.testing.assert_allclose(den(x), x, atol=1e-6)


# ---- training and evaluation ---------------------------------------------------------------
@pytest.fixture(scope="module")
def planes_root(tmp_path_factory):
    """Synthetic pairs labelled as the planes channel (the values are shading fields; enough for
    shapes, losses and bookkeeping)."""
    return make_synthetic_pair_dataset(tmp_path_factory.mktemp("planes") / "ds", n_train=8, n_val=4, size=32,
                                       noise_level=0.01, shard_size=4, seed=1, render=planes_render_block())


def test_stream_yields_coordinates_of_its_crops(planes_root):
    from pix2pix.datamodule import Pix2PixDataModule

    dm = Pix2PixDataModule(planes_root, noise_level=0.01, batch_size=2, crop_size=16, flips="none")
    dm.setup("fit")
    assert dm.planes and dm.train_set.planes
    f = planes_render_block()["focal"]
    full = pixel_coords((32, 32), f)
    for s in list(dm.train_set)[:4]:
        xy = s["coords"]
        assert xy.shape == (2, 16, 16)
        # a crop of the full render's coordinates: find its offset from the first pixel
        x0 = int(round(float(xy[0, 0, 0]) * f + 16 - 0.5))
        y0 = int(round(float(xy[1, 0, 0]) * f + 16 - 0.5))
        torch.testing.assert_close(xy, full[:, y0:y0 + 16, x0:x0 + 16])
    v = next(iter(dm.val_dataloader()))
    torch.testing.assert_close(v["coords"][0], full)
    flipped = Pix2PixDataModule(planes_root, noise_level=0.01, batch_size=2, crop_size=16)
    flipped.setup("fit")
    assert flipped.train_set.flips == ["hflip", "vflip", "transpose"]


def test_crops_can_be_drawn_on_the_surface(planes_root):
    from pix2pix.datamodule import Pix2PixDataModule

    def coverage(min_cov):
        dm = Pix2PixDataModule(planes_root, noise_level=0.01, batch_size=2, crop_size=12, flips="none",
                               crop_min_coverage=min_cov)
        dm.setup("fit")
        return [float(s["mask"].float().mean()) for _ in range(3) for s in dm.train_set]

    plain, focused = coverage(0.0), coverage(0.9)
    assert np.mean(focused) > np.mean(plain) + 0.1
    assert np.mean(np.asarray(focused) >= 0.9) > 0.8


def test_planes_training_logs_geometry_and_lambda_depth_moves_it(planes_root, tmp_path):
    import lightning as L

    from pix2pix.datamodule import Pix2PixDataModule
    from pix2pix.module import Pix2PixModule

    def fit(lam_d):
        torch.manual_seed(0)
        g = ResNetGenerator(ngf=8, n_blocks=1, residual=True, init_gain=1.0, input_mean=[0.0, 0.0, 0.5],
                            input_std=[1.0, 1.0, 0.5])
        m = Pix2PixModule(g, None, lambda_gan=0.0, lambda_depth=lam_d, lambda_normal=1.0 if lam_d else 0.0,
                          lr=1e-3, num_grid_images=0)
        dm = Pix2PixDataModule(planes_root, noise_level=0.01, batch_size=4, crop_size=16)
        tr = L.Trainer(max_epochs=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                       enable_model_summary=False, num_sanity_val_steps=0, default_root_dir=tmp_path)
        tr.fit(m, datamodule=dm)
        return {k: float(v) for k, v in tr.callback_metrics.items()}

    base, depth = fit(0.0), fit(300.0)
    for k in ("depth_err", "depth_bias", "depth_within_1e-3", "normal_err_deg", "surface_l1", "surface_smape"):
        assert math.isfinite(base[f"val/{k}"]) and math.isfinite(base[f"val/noisy_{k}"])
    assert "val/depth_err_reduction" in base and "val/normal_err_reduction" in base
    assert "train/depth_l1" in depth and "train/depth_l1" not in base
    assert depth["val/depth_err"] != base["val/depth_err"]  # the term changes what is learned


def test_evaluate_denoiser_reports_the_geometry_of_a_planes_model(planes_root, tmp_path):
    from experiments.evaluation.evaluate_denoiser import evaluate, markdown

    g = ResNetGenerator(ngf=8, n_blocks=1, residual=True)  # zero head: the identity
    meta = build_metadata({"generator": g.config(), "data": {"noise_level": 0.01, "image_size": [32, 32],
                                                             "render": planes_render_block()}})
    path = export_onnx(g, tmp_path / "id.onnx", meta)
    r = evaluate(path, planes_root, max_pairs=4)
    assert r["channel"] == "planes" and "snapped" not in r["metrics"]
    gr, gn = r["metrics"]["raw"]["geometry"], r["metrics"]["noisy"]["geometry"]
    assert gn["surface_pixels"] > 0
    for k in ("depth_err", "depth_err_median", "normal_err_deg", "surface_smape"):
        assert gr[k] == pytest.approx(gn[k], rel=1e-4, abs=1e-7)
    assert abs(gr["depth_err_reduction"]) < 1e-3
    table = markdown(r)
    assert "noisy input (identity)" in table and "network output" in table
