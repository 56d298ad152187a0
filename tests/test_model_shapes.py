"""Denoiser models whose graph does not fit the renders are refused at load, in one line (fast)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest


def _model(path: Path, nodes, inputs, outputs, channels: int = 3, size=(32, 32)) -> Path:
    import onnx
    from onnx import TensorProto, helper

    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info(n, TensorProto.FLOAT, s) for n, s in inputs],
                              [helper.make_tensor_value_info(n, TensorProto.FLOAT, s) for n, s in outputs])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    for k, v in {"dss.kind": "dss-pix2pix-denoiser", "dss.channels": json.dumps(channels),
                 "dss.render_image_size": json.dumps(list(size)), "dss.noise_level": "0.01"}.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v
    onnx.save(model, str(path))
    return path


def _gray(path):  # 3 channels in, their mean out: 1 channel
    from onnx import helper

    return _model(path, [helper.make_node("ReduceMean", ["x"], ["y"], keepdims=1, axes=[1])],
                  [("x", ["b", 3, "h", "w"])], [("y", ["b", 1, "h", "w"])])


def _half(path):  # the output at half the resolution, its size given by names only
    from onnx import helper

    return _model(path, [helper.make_node("AveragePool", ["x"], ["y"], kernel_shape=[2, 2], strides=[2, 2])],
                  [("x", ["b", 3, "h", "w"])], [("y", ["b", 3, "h2", "w2"])])


def _four(path):  # takes 4-channel images (the renders have 3)
    from onnx import helper

    return _model(path, [helper.make_node("Relu", ["x"], ["y"])], [("x", ["b", 4, "h", "w"])],
                  [("y", ["b", 4, "h", "w"])], channels=4)


@pytest.mark.parametrize("make,pattern", [
    (_gray, r"gray\.onnx: the graph maps .* \(3 input channels, 1 output channels\)"),
    (_half, r"half\.onnx: the model maps 3x32x32 renders to shape \(3, 16, 16\)"),
    (_four, r"four\.onnx: the model takes 4-channel images, the renders have 3"),
])
def test_a_model_of_the_wrong_shape_is_refused_at_load(make, pattern, tmp_path):
    from experiments.denoising.reference_generators import OnnxReference
    from pix2pix.runtime import DenoiserFormatError

    path = make(tmp_path / f"{make.__name__.strip('_')}.onnx")
    with pytest.raises(DenoiserFormatError, match=pattern) as info:
        OnnxReference(path)
    assert "\n" not in str(info.value)


def test_the_shipped_models_fit_their_renders():
    from experiments.denoising.reference_generators import OnnxReference, select_model

    for level in (0.003, 0.01):
        ref = OnnxReference(select_model(level)[0])
        x = np.zeros((1, 3, *ref.denoiser.render_image_size), np.float32)
        assert ref.denoiser(x).shape == x.shape


def test_denoise_refuses_a_wrong_model_before_any_work(tmp_path, monkeypatch):
    from hydra import compose, initialize_config_dir
    from scenes import sphere_points

    from dss.optimize import MultiViewOptimizer
    from dss.pointcloud import PointCloud, save_ply
    from experiments.apps.denoise import run
    from experiments.common import release_claims
    from pix2pix.runtime import DenoiserFormatError

    steps = []
    monkeypatch.setattr(MultiViewOptimizer, "run", lambda self, **kw: steps.append(1))
    p, n = sphere_points(500, 0.4)
    save_ply(tmp_path / "c.ply", PointCloud(p, n))
    conf = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("denoise", [f"input={tmp_path / 'c.ply'}", f"out_dir={tmp_path / 'run'}", "reference=onnx",
                                  f"reference.model={_gray(tmp_path / 'gray.onnx')}", "progress=false"])
    with pytest.raises(DenoiserFormatError, match=r"gray\.onnx"):
        run(cfg)
    release_claims()
    assert not steps
