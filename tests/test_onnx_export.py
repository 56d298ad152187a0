"""ONNX export of the denoiser, its metadata, the onnxruntime wrapper and dss-export (fast)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from onnx import TensorProto, helper

from pix2pix.export import (
    DENOISER_KIND,
    build_metadata,
    export_checkpoint,
    export_onnx,
    onnx_parity,
    read_metadata,
)
from pix2pix.module import load_generator
from pix2pix.networks import ResNetGenerator
from pix2pix.runtime import DenoiserFormatError, OnnxDenoiser
from pix2pix.shards import open_shard, read_manifest, select_shards

try:
    from tests.pix2pix_fixtures import compose_train, pairs_root, trained_run  # noqa: F401
except ImportError:
    from pix2pix_fixtures import compose_train, pairs_root, trained_run  # noqa: F401

torch.set_num_threads(1)


def _perturbed_generator(residual: bool, seed: int = 0) -> ResNetGenerator:
    """A generator whose weights are far from the (near-identity) init, so parity is meaningful."""
    torch.manual_seed(seed)
    g = ResNetGenerator(ngf=8, n_blocks=2, residual=residual)
    with torch.no_grad():
        for p in g.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return g.eval()


def _info(g: ResNetGenerator) -> dict:
    return {"name": "unit", "generator": g.config(), "train_crop_size": 32,
            "data": {"noise_level": 0.003, "image_size": [48, 48],
                     "render": {"shading": "point_light", "light": {"position": [0, 0, 0]}}},
            "epoch": 3, "global_step": 42}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    g = _perturbed_generator(residual=False)
    path = tmp_path_factory.mktemp("onnx") / "g.onnx"
    export_onnx(g, path, build_metadata(_info(g)))
    return g, path


@pytest.mark.parametrize("shape", [(1, 3, 32, 32), (3, 3, 48, 64), (2, 3, 8, 12), (1, 3, 100, 36)])
def test_parity_dynamic_batch_height_width(exported, shape):
    g, path = exported
    x = np.random.default_rng(1).random(shape, dtype=np.float32) * 1.5 - 0.2
    with torch.no_grad():
        ref = g(torch.from_numpy(x)).numpy()
    assert np.abs(ref).max() > 0.1  # a non-trivial output
    assert onnx_parity(g, path, x) <= 1e-4


def test_parity_on_real_dss_renders(exported):
    """Parity on what the pipeline feeds the network: point-light DSS renders of a noisy cloud
    (mostly black background, a lit object), in (B, C, H, W), at the model's render size."""
    from data_prep.render_spec import load_render_spec
    from data_prep.sampling import noisy_copy, poisson_disk
    from data_prep.shapes import make_shape
    from dss.pointcloud import estimate_normals, normalize_unit_diagonal
    from dss.render import render
    from experiments.denoising.reference_generators import SpecViewSampler

    g, path = exported
    mesh = make_shape("superquadric", seed=4, resolution=32)
    pts, _, _ = normalize_unit_diagonal(torch.from_numpy(noisy_copy(poisson_disk(mesh, 3000, seed=4).points, 0.01, seed=5)))
    spec = load_render_spec(image_size=[48, 48])
    cams = SpecViewSampler(spec, views=3, seed=0).sample()
    with torch.no_grad():
        imgs = render(pts, estimate_normals(pts, k=12), cams, spec.render_settings(), shading=spec.point_light()).images
    x = imgs.permute(0, 3, 1, 2).contiguous().numpy()
    assert (x > 0).mean() > 0.05 and (x == 0).mean() > 0.3  # an object on a black background
    assert onnx_parity(g, path, x) <= 1e-4


def test_onnx_checker_and_dynamic_axes(exported):
    _, path = exported
    model = onnx.load(str(path))
    onnx.checker.check_model(model, full_check=True)
    dims = [d.dim_param or d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim]
    assert dims == ["batch", 3, "height", "width"]
    assert model.graph.input[0].name == "noisy" and model.graph.output[0].name == "denoised"
    assert path.stat().st_mode & 0o044 == 0o044  # readable by others (not mkstemp's 0600)


def test_metadata_round_trip(exported):
    g, path = exported
    meta = read_metadata(path)
    assert meta["dss.kind"] == DENOISER_KIND
    assert meta["dss.noise_level"] == 0.003
    assert meta["dss.train_image_size"] == [32, 32]
    assert meta["dss.render_image_size"] == [48, 48]
    assert meta["dss.render_settings"] == _info(g)["data"]["render"]
    norm = meta["dss.input_normalization"]
    assert (norm["mean"], norm["std"], norm["applied_in_graph"]) == (0.5, 0.5, True)
    assert meta["dss.generator"] == json.loads(json.dumps(g.config()))
    assert (meta["dss.epoch"], meta["dss.global_step"], meta["dss.size_multiple"]) == (3, 42, 4)
    den = OnnxDenoiser(path, intra_op_num_threads=1)
    assert den.metadata == meta
    assert den.noise_level == 0.003 and den.render_image_size == [48, 48]
    assert den.render_settings["shading"] == "point_light"
    # a generator rebuilt from the file's own metadata has the same architecture
    rebuilt = ResNetGenerator.from_config(meta["dss.generator"])
    rebuilt.load_state_dict(g.state_dict())


def test_runtime_batches_layouts_and_padding(exported):
    g, path = exported
    x = np.random.default_rng(2).random((5, 3, 16, 20), dtype=np.float32)
    whole = OnnxDenoiser(path, intra_op_num_threads=1, max_batch=8)(x)
    split = OnnxDenoiser(path, intra_op_num_threads=1, max_batch=2)(x)
    np.testing.assert_allclose(whole, split, atol=1e-5)
    with torch.no_grad():
        np.testing.assert_allclose(whole, g(torch.from_numpy(x)).numpy(), atol=1e-4)
    den = OnnxDenoiser(path, intra_op_num_threads=1)
    views = den.denoise_views(x.transpose(0, 2, 3, 1))
    np.testing.assert_allclose(views.transpose(0, 3, 1, 2), whole, atol=1e-6)
    odd = x[:, :, :15, :18]
    out = den(odd, pad=True)
    assert out.shape == odd.shape and out.dtype == np.float32


def test_runtime_clear_errors(exported, tmp_path):
    _, path = exported
    den = OnnxDenoiser(path, intra_op_num_threads=1)
    with pytest.raises(ValueError, match="expected 3 channels.*channels-last"):
        den(np.zeros((1, 16, 16, 3), np.float32))
    with pytest.raises(ValueError, match="expected 3 channels"):
        den(np.zeros((1, 1, 16, 16), np.float32))
    with pytest.raises(ValueError, match="multiples of 4, got 30x32"):
        den(np.zeros((1, 3, 30, 32), np.float32))
    with pytest.raises(ValueError, match="NaN"):
        den(np.full((1, 3, 16, 16), np.nan, np.float32))
    with pytest.raises(ValueError, match=r"\(V, H, W, C\)"):
        den.denoise_views(np.zeros((1, 3, 16, 16), np.float32))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        OnnxDenoiser(tmp_path / "missing.onnx")
    # an ONNX model that is not ours
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 4, 4])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3, 4, 4])
    foreign = helper.make_model(helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "g", [x], [y]),
                                opset_imports=[helper.make_opsetid("", 17)])
    fpath = tmp_path / "foreign.onnx"
    onnx.save(foreign, str(fpath))
    with pytest.raises(DenoiserFormatError, match="not a DSS pix2pix denoiser") as e:
        OnnxDenoiser(fpath)
    assert "foreign.onnx" in str(e.value)
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"\x00\x01 definitely not protobuf" * 10)
    with pytest.raises(DenoiserFormatError, match="garbage.onnx"):
        OnnxDenoiser(garbage)


def test_export_refuses_to_overwrite(exported, tmp_path):
    g, path = exported
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="overwrite"):
        export_onnx(g, path, build_metadata(_info(g)))
    assert path.read_bytes() == before


def test_residual_generator_parity(tmp_path):
    g = _perturbed_generator(residual=True, seed=3)
    path = export_onnx(g, tmp_path / "r.onnx", build_metadata(_info(g)))
    x = np.random.default_rng(3).random((2, 3, 24, 40), dtype=np.float32)
    assert onnx_parity(g, path, x) <= 1e-4


def test_checkpoint_export_parity_on_real_renders(trained_run, pairs_root, tmp_path):
    """A dss-train checkpoint -> ONNX, parity on validation renders of the dataset."""
    path, meta, gen = export_checkpoint(trained_run["best_ckpt"], tmp_path / "ck.onnx")
    g2, info = load_generator(trained_run["best_ckpt"])
    assert info["data"]["noise_level"] == 0.01 and info["train_crop_size"] == 32
    manifest = read_manifest(pairs_root)
    shard = select_shards(pairs_root, manifest, "val", 0.01)[0]
    x = np.asarray(open_shard(shard.path)["noisy"], dtype=np.float32).transpose(0, 3, 1, 2)
    assert onnx_parity(gen, path, x) <= 1e-4
    m = read_metadata(path)
    assert m["dss.noise_level"] == 0.01 and m["dss.render_settings"] == manifest["render"]
    assert m["dss.train_image_size"] == [32, 32] and m["dss.render_image_size"] == [32, 32]
    assert m["dss.global_step"] == torch.load(trained_run["best_ckpt"], weights_only=False)["global_step"]


def test_load_generator_rejects_foreign_checkpoint(tmp_path):
    bad = tmp_path / "x.ckpt"
    torch.save({"state_dict": {}}, bad)
    with pytest.raises(ValueError, match="not a dss pix2pix checkpoint"):
        load_generator(bad)
    bad.write_bytes(b"junk")
    with pytest.raises(ValueError, match="not a readable"):
        load_generator(bad)


def test_dss_export_app(trained_run, pairs_root, tmp_path):
    from experiments.apps.export import run

    out = tmp_path / "app"
    target = tmp_path / "den.onnx"
    cfg = compose_train([f"ckpt_path={trained_run['best_ckpt']}", f"output={target}",
                         f"data_root={pairs_root}", f"output_dir={out}"], config_name="export")
    res = run(cfg)
    assert res["parity_worst"] <= 1e-4 and any(k.startswith("real_") for k in res["parity_max_abs"])
    assert target.is_file() and Path(res["model_card"]).is_file()
    card = Path(res["model_card"]).read_text()
    assert "noise level: 0.01" in card and "| smape |" in card
    assert json.loads((out / "metrics.json").read_text())["onnx"] == str(target)
    OnnxDenoiser(target)  # loads as one of ours
    before = target.read_bytes()
    with pytest.raises(FileExistsError, match="overwrite=true"):
        run(cfg)
    assert target.read_bytes() == before
    cfg.overwrite = True
    assert run(cfg)["parity_worst"] <= 1e-4
