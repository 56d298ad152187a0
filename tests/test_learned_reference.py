"""What a learned planes reference needs to be trained and used for the plane fusion: the
on-the-fly stream's noise range, multi-view batches and cascade inputs (experiments.onthefly,
experiments.denoising.cascade), the cross-view agreement terms (pix2pix.multiview), the uncertainty head
(PlanesGenerator(uncertainty=True)) through training, ONNX export and the reference generator."""

from __future__ import annotations

import math

import pytest
import torch

from data_prep.clouds import generate_clouds
from data_prep.render_spec import load_render_spec, spec_path
from data_prep.shards import PrepConfig
from experiments.onthefly import OnTheFlyDataModule
from pix2pix.multiview import agreement_terms, has_multiview, probe_observations
from pix2pix.networks import PlanesGenerator

torch.set_num_threads(1)


def _config():
    pc = PrepConfig(families=("superquadric", "displaced_sphere"), shapes_per_family=3, resolution=32,
                    num_points=3000, normals_k=12, val_fraction=0.2, test_fraction=0.2, views_per_shape=2,
                    noise_range=(0.0025, 0.015))
    return pc, load_render_spec(spec_path("planes"), image_size=[64, 64])


@pytest.fixture(scope="module")
def clouds(tmp_path_factory):
    pc, spec = _config()
    root = tmp_path_factory.mktemp("clouds") / "ds"
    generate_clouds(pc, spec, root, progress=False)
    return root


def _dm(root, **kw):
    args = dict(noise_level="range", views_per_shape=4, batch_size=4, crop_size=32, max_val_pairs=4,
                num_workers=0, seed=3, device="cpu", pool=2, probes=256)
    dm = OnTheFlyDataModule(root, **{**args, **kw})
    dm.setup("fit")
    return dm


def test_noise_range_draws_a_level_per_shape_and_epoch(clouds):
    dm = _dm(clouds)
    assert dm.noise_range == [0.0025, 0.015] and dm.noise_level == pytest.approx(math.sqrt(0.0025 * 0.015), abs=1e-6)
    ds = dm.train_set
    stds = [float(ds.render_shape(i, e)["noise_std"][0]) for i in range(2) for e in range(3)]
    assert all(0.0025 <= s <= 0.015 for s in stds) and len(set(stds)) == len(stds)


def test_multiview_batches_share_one_cloud_and_its_cameras_fit_the_renders(clouds):
    """Each batch is one cloud's views; with the clean crops as the output every probe the
    views see has offset ~0 and the views agree; a shifted view makes them disagree."""
    dm = _dm(clouds, multiview=True)
    loader = dm.train_dataloader()
    batch = next(iter(loader))
    assert has_multiview(batch) and batch["noisy"].shape == (4, 3, 32, 32)
    assert torch.equal(batch["probe_points"][0], batch["probe_points"][3])  # one cloud, shared probes
    off, w, z = probe_observations(batch["clean"], batch["clean"], batch["noisy"], batch, tau=0.003)
    t = agreement_terms(off, w, min_views=2, depth=z)
    assert t["valid"].sum() > 20, int(t["valid"].sum())  # the anchor's neighbourhood is seen by several views
    v = t["valid"]
    assert t["mean"][v].abs().median() < 1e-3 and t["spread"][v].median() < 1e-3
    shifted = batch["clean"].clone()
    shifted[0] = shifted[0] * 1.02  # view 0's surface 2% nearer in inverse depth (farther in depth)
    off2, w2, _ = probe_observations(shifted, batch["clean"], batch["noisy"], batch, tau=0.003)
    t2 = agreement_terms(off2, w2, min_views=2)
    both = v & t2["valid"] & (w2[0] > 0)
    assert both.sum() > 5 and (t2["spread"][both] / t["spread"][both]).median() > 3
    # and the loss has a gradient with respect to the planes
    planes = batch["clean"].clone().requires_grad_(True)
    off3, w3, _ = probe_observations(planes * 1.01, batch["clean"], batch["noisy"], batch)
    agreement_terms(off3, w3, 2)["mean"].abs().sum().backward()
    assert planes.grad is not None and planes.grad.abs().sum() > 0


def test_multiview_validation_uses_full_renders(clouds):
    dm = _dm(clouds, multiview=True)
    b = next(iter(dm.val_dataloader()))
    assert b["noisy"].shape[-2:] == (64, 64) and has_multiview(b)
    assert torch.allclose(b["cam_principal"][0], torch.tensor([32.0, 32.0]))


def test_training_with_uncertainty_and_agreement_logs_the_fusions_measures(clouds, tmp_path):
    import lightning as L

    from pix2pix.module import Pix2PixModule

    dm = _dm(clouds, multiview=True, max_val_pairs=4)
    gen = PlanesGenerator(ngf=4, n_blocks=1, uncertainty=True)
    model = Pix2PixModule(gen, None, lambda_l1=10.0, lambda_gan=0.0, lambda_depth=300.0, lambda_normal=100.0,
                          lambda_nll=1.0, lambda_agree=1000.0, lambda_fused=1000.0, agree_min_views=2)
    trainer = L.Trainer(max_epochs=1, limit_train_batches=2, limit_val_batches=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, default_root_dir=str(tmp_path), num_sanity_val_steps=0,
                        enable_model_summary=False, accelerator="cpu")
    trainer.fit(model, datamodule=dm)
    m = {k: float(v) for k, v in trainer.callback_metrics.items()}
    for k in ("train/nll", "train/probe_spread", "val/nll", "val/probe_spread", "val/probe_noisy_spread",
              "val/probe_trusted", "val/probe_fused_err"):
        assert k in m and math.isfinite(m[k]), (k, sorted(m))


def test_uncertainty_head_exports_a_second_output_the_reference_passes_on(tmp_path):
    from experiments.denoising.reference_generators import OnnxReference
    from pix2pix.export import build_metadata, export_onnx, onnx_parity
    from pix2pix.runtime import OnnxDenoiser

    gen = PlanesGenerator(ngf=4, n_blocks=1, uncertainty=True, uncertainty_init=0.02).eval()
    x = torch.zeros(1, 3, 32, 32)
    x[:, 2, 8:24, 8:24] = -1.0  # a fronto-parallel plane at depth 1 (a = n / (n . p), n facing the camera)
    a, log_b = gen.forward_with_uncertainty(x)
    assert a.shape == x.shape and log_b.shape == (1, 1, 32, 32)
    assert torch.allclose(log_b, torch.full_like(log_b, math.log(0.02)))  # the zero-initialised head
    assert PlanesGenerator.from_config(gen.config()).predicts_uncertainty
    render = load_render_spec(spec_path("planes"), image_size=[32, 32]).to_dict()
    meta = build_metadata({"generator": gen.config(), "data": {"render": render, "image_size": [32, 32],
                                                               "noise_level": 0.006}})
    path = export_onnx(gen, tmp_path / "m.onnx", meta, example_size=(32, 32))
    assert onnx_parity(gen, path, x) < 1e-4
    den = OnnxDenoiser(path)
    assert den.predicts_uncertainty
    ref = OnnxReference(path, threads=1)
    views = x.permute(0, 2, 3, 1).expand(2, -1, -1, -1).contiguous()
    out = ref(views, mask=views.abs().amax(-1) > 0)
    assert out.shape == views.shape and ref.last_uncertainty.shape == (2, 32, 32)
    assert torch.allclose(ref.last_uncertainty, torch.full((2, 32, 32), 0.02), rtol=1e-4)
    # a model without the head keeps one output and no uncertainty
    plain = PlanesGenerator(ngf=4, n_blocks=1).eval()
    p2 = export_onnx(plain, tmp_path / "p.onnx", meta, example_size=(32, 32))
    assert not OnnxDenoiser(p2).predicts_uncertainty and OnnxReference(p2).last_uncertainty is None


def test_cascade_cache_runs_the_jobs_classical_stage_and_resumes(clouds, tmp_path):
    """python -m experiments.denoising.cascade: one item per chosen shape and draw, the refined
    cloud nearer the clean one than the noisy draw, a manifest the on-the-fly data reads, and a
    rerun that remakes nothing; another seed into the same folder is refused."""
    import numpy as np

    from data_prep.cascade_cache import load_cascade_item, read_cascade_manifest
    from data_prep.clouds import load_cloud, read_clouds_manifest
    from data_prep.sampling import noisy_copy
    from dss.metrics import evaluate
    from experiments.denoising.cascade import main

    args = ["--data", str(clouds), "--out", str(tmp_path / "c"), "--per-family", "1", "--val-per-family", "0",
            "--noise", "0.01", "0.01", "optimizer.cycles=2", "image_size=64", "views=4"]
    assert main(args) == 0
    man = read_cascade_manifest(tmp_path / "c")
    assert len(man["items"]) == 2 and {e["split"] for e in man["items"]} == {"train"}
    shapes = {s["shape_id"]: s for s in read_clouds_manifest(clouds)["shapes"]}
    for e in man["items"]:
        pts, nrm = load_cascade_item(tmp_path / "c", e)
        clean, _ = load_cloud(clouds, shapes[e["shape_id"]])
        assert pts.shape == clean.shape and np.isfinite(pts).all() and np.allclose(np.linalg.norm(nrm, axis=1), 1, atol=1e-3)
        noisy = noisy_copy(clean, e["noise_std"], e["noise_seed"])
        assert evaluate(pts, clean).chamfer < evaluate(noisy, clean).chamfer
    stamp = [(tmp_path / "c" / e["file"]).stat().st_mtime_ns for e in man["items"]]
    assert main(args) == 0
    assert [(tmp_path / "c" / e["file"]).stat().st_mtime_ns for e in man["items"]] == stamp
    assert main([*args[:-3], "--seed", "1", *args[-3:]]) == 2
