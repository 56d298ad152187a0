"""reference=auto (conf/reference/auto.yaml, experiments.denoising.reference_generators.AutoReference):
the reference chosen per noise level from a table, with the fusion settings an entry brings."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from experiments.denoising.reference_generators import (
    AutoReference,
    IdentityReference,
    OnnxReference,
)

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "experiments" / "assets" / "example"


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """A tiny planes model (untrained: the blurred input), exported as the job would load it."""
    from data_prep.render_spec import load_render_spec, spec_path
    from pix2pix.export import build_metadata, export_onnx
    from pix2pix.networks import PlanesGenerator

    gen = PlanesGenerator(ngf=4, n_blocks=1, uncertainty=True)
    render = load_render_spec(spec_path("planes"), image_size=[64, 64]).to_dict()
    meta = build_metadata({"generator": gen.config(), "data": {"render": render, "image_size": [64, 64],
                                                               "noise_level": 0.006}})
    return export_onnx(gen, tmp_path_factory.mktemp("m") / "m.onnx", meta, example_size=(32, 32))


def test_auto_picks_the_tables_entry_nearest_in_log_noise(model):
    auto = AutoReference({0.003: "identity", 0.01: {"reference": str(model),
                                                    "fusion": {"reference_cloud": "refined", "uncertainty": "trust"}}})
    for noise, kind in ((0.001, IdentityReference), (0.005, IdentityReference), (0.0056, OnnxReference),
                        (0.02, OnnxReference)):
        gen, note, fusion = auto.resolve_for_noise(noise)
        assert isinstance(gen, kind), (noise, gen)
        assert bool(fusion) == (kind is OnnxReference) and "reference=auto" in note
    assert auto.resolve_for_noise(0.02)[2] == {"reference_cloud": "refined", "uncertainty": "trust"}
    with pytest.raises(ValueError, match="neither a reference name"):
        AutoReference({0.01: "teapot"})
    with pytest.raises(ValueError, match="positive fraction"):
        AutoReference({-1: "identity"})
    with pytest.raises(ValueError, match="needs reference.table"):
        AutoReference({})
    from experiments.denoising.reference_generators import ModelNotFoundError

    with pytest.raises(ModelNotFoundError, match="does not exist"):
        AutoReference({0.01: "no/such/model.onnx"}).resolve_for_noise(0.01)


def _cfg(*overrides):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose("denoise", overrides=list(overrides))


def test_the_job_resolves_auto_and_takes_the_entrys_fusion_settings(model):
    from experiments.denoising.references import make_reference

    cfg = _cfg("reference=auto")
    cfg.reference.table = OmegaConf.create({0.005: "identity", 0.01: {"reference": str(model),
                                                                      "fusion": {"reference_cloud": "refined"}}})
    gen, note = make_reference(cfg, 0.004)
    assert gen.name == "identity" and "fusion" not in note and cfg.fusion.reference_cloud == "input"
    gen, note = make_reference(cfg, 0.012)
    assert gen.name == "onnx" and cfg.fusion.reference_cloud == "refined"
    from experiments.denoising.settings import fusion_config

    assert fusion_config(cfg.fusion, "planes").reference_cloud == "refined"


def test_default_auto_table_is_identity_and_the_job_matches_identity(tmp_path):
    """With the shipped table (identity at every level) ``reference=auto`` is the identity job: no
    worse than identity, exactly, on a small fixed case (5K points of a held-out-like cloud)."""
    from dss.pointcloud import PointCloud, load_ply, save_ply
    from experiments.apps.denoise import run

    noisy = load_ply(EXAMPLE / "noisy_1pct.ply", compute_normals=False)
    i = np.random.default_rng(0).choice(len(noisy), 4000, replace=False)
    save_ply(tmp_path / "noisy.ply", PointCloud(noisy.points[i]))
    out = {}
    for ref in ("auto", "identity"):
        cfg = _cfg(f"input={tmp_path / 'noisy.ply'}", f"clean={EXAMPLE / 'clean.ply'}", f"reference={ref}",
                   "noise=0.01", "optimizer.cycles=1", "optimizer.normal_steps=2", "fusion.passes=1",
                   "fusion.batches=1", "fusion.views=4", "image_size=64", "figures.enabled=false",
                   "metrics.protocols=[paper]", "progress=false", "threads=1", f"out_dir={tmp_path / ref}")
        out[ref] = run(cfg)
    assert "reference=auto: identity" in out["auto"]["reference"]["selection"]
    a, b = (load_ply(tmp_path / r / "denoised.ply", compute_normals=False).points for r in ("auto", "identity"))
    assert torch.equal(torch.as_tensor(a), torch.as_tensor(b))
    assert out["auto"]["summary"]["output"]["paper"]["chamfer"] == out["identity"]["summary"]["output"]["paper"]["chamfer"]
