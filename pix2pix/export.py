"""Export the trained generator to ONNX, with self-describing metadata.

The exported graph takes ``noisy`` (B, 3, H, W) float32 renders in their natural range (about
[0, 1]) and returns ``denoised`` of the same shape; B, H and W are dynamic (H, W multiples of 4).
The input normalisation is inside the graph. The file's ``metadata_props`` (all strings, JSON
where structured) let the denoising pipeline configure itself from the model:

=============================  ==============================================================
``dss.kind``                   ``"dss-pix2pix-denoiser"`` (how :mod:`pix2pix.runtime` tells our
                               files from other ONNX models)
``dss.metadata_version``       ``"1"``
``dss.noise_level``            noise std as a fraction of the bbox diagonal (e.g. ``"0.01"``)
``dss.train_image_size``       JSON ``[H, W]`` of the crops the model was trained on
``dss.render_image_size``      JSON ``[H, W]`` of the training renders (render at this size)
``dss.render_settings``        JSON render block of the training data (from its manifest)
``dss.input_normalization``    JSON: mean/std applied in-graph, layout, dtype, value range
``dss.size_multiple``          ``"4"``
``dss.channels``               ``"3"``
``dss.generator``              JSON generator config (to rebuild it in PyTorch)
``dss.name``, ``dss.epoch``,   preset name, training progress, package version
``dss.global_step``,
``dss.package_version``
=============================  ==============================================================
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from ._io import atomic_path
from .networks import SIZE_MULTIPLE

log = logging.getLogger(__name__)

__all__ = [
    "DENOISER_KIND",
    "METADATA_VERSION",
    "build_metadata",
    "export_onnx",
    "export_checkpoint",
    "read_metadata",
    "onnx_parity",
]

DENOISER_KIND = "dss-pix2pix-denoiser"
METADATA_VERSION = "1"
INPUT_NAME, OUTPUT_NAME = "noisy", "denoised"
#: the second output of a generator that predicts its uncertainty (PlanesGenerator(uncertainty=True)):
#: (B, 1, H, W) log of the Laplace scale of each pixel's inverse depth
UNCERTAINTY_NAME = "log_scale"


class _WithUncertainty(nn.Module):
    """The generator's planes and its log-scale map as two graph outputs."""

    def __init__(self, generator: nn.Module):
        super().__init__()
        self.generator = generator

    def forward(self, x: torch.Tensor):
        return self.generator.forward_with_uncertainty(x)
DEFAULT_OPSET = 17
#: metadata keys whose values are JSON (parsed by :func:`read_metadata`)
JSON_KEYS = ("dss.train_image_size", "dss.render_image_size", "dss.render_settings",
             "dss.input_normalization", "dss.generator", "dss.noise_level", "dss.size_multiple",
             "dss.channels", "dss.epoch", "dss.global_step")


def _package_version() -> str:
    try:
        from importlib.metadata import version

        return version("dss-splatting")
    except Exception:  # not installed (source checkout)
        return "0.1.0"


def build_metadata(info: dict[str, Any]) -> dict[str, str]:
    """ONNX ``metadata_props`` from a checkpoint's ``dss_pix2pix`` info (see module docstring)."""
    gen = info.get("generator") or {}
    data = info.get("data") or {}
    crop = info.get("train_crop_size") or data.get("crop_size")
    render_size = data.get("image_size")
    train_size = [int(crop), int(crop)] if crop else render_size
    norm = {
        "mean": gen.get("input_mean", 0.5),
        "std": gen.get("input_std", 0.5),
        "applied_in_graph": True,
        "note": "feed raw renders; the graph computes (x - mean) / std and inverts it on the output",
        "layout": "NCHW",
        "dtype": "float32",
        "input_range": "render values, about [0, 1] (unbounded)",
        "output_range": "unbounded (no tanh), same range as the input",
    }
    if str((data.get("render") or {}).get("shading", "")).lower() == "planes":
        norm["input_range"] = ("planes: per pixel the camera-space plane a of 1/z = a . (x, y, 1) "
                               "(dss.shading.plane_coefficients), 0 on the background")

    def js(v: Any) -> str:
        return json.dumps(v, sort_keys=True)

    return {
        "dss.kind": DENOISER_KIND,
        "dss.metadata_version": METADATA_VERSION,
        "dss.package_version": _package_version(),
        "dss.name": str(info.get("name", "custom")),
        "dss.noise_level": js(data.get("noise_level")),
        "dss.train_image_size": js(train_size),
        "dss.render_image_size": js(render_size),
        "dss.render_settings": js(data.get("render", {})),
        "dss.input_normalization": js(norm),
        "dss.size_multiple": js(SIZE_MULTIPLE),
        "dss.channels": js(int(gen.get("in_channels", 3))),
        "dss.generator": js(gen),
        "dss.epoch": js(info.get("epoch")),
        "dss.global_step": js(info.get("global_step")),
    }


def export_onnx(
    generator: nn.Module,
    path: str | Path,
    metadata: dict[str, str],
    *,
    opset: int = DEFAULT_OPSET,
    example_size: tuple[int, int] = (64, 64),
    overwrite: bool = False,
) -> Path:
    """Export ``generator`` to ONNX at ``path`` (atomically), add ``metadata`` and check it.

    Batch, height and width are dynamic axes. The model is checked with
    ``onnx.checker.check_model(full_check=True)`` before it is moved into place.

    Raises FileExistsError when ``path`` exists and ``overwrite`` is False.
    """
    import onnx

    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    bad = [k for k, v in metadata.items() if not isinstance(k, str) or not isinstance(v, str)]
    if bad:
        raise TypeError(f"ONNX metadata keys and values must be strings: {bad}")
    was_training = generator.training
    generator = generator.eval()
    channels = int(getattr(generator, "in_channels", 3))
    example = torch.rand(1, channels, *example_size)
    module, outputs = generator, [OUTPUT_NAME]
    if getattr(generator, "predicts_uncertainty", False):  # a second output: the log scale map
        module, outputs = _WithUncertainty(generator), [OUTPUT_NAME, UNCERTAINTY_NAME]
    axes = {0: "batch", 2: "height", 3: "width"}
    try:
        with atomic_path(path) as tmp, torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # tracer chatter about shapes; we check the result
            # the TorchScript exporter (dynamo=False) needs no extra package (onnxscript)
            torch.onnx.export(
                module, (example,), str(tmp),
                input_names=[INPUT_NAME], output_names=outputs,
                dynamic_axes={INPUT_NAME: axes, **{o: axes for o in outputs}},
                opset_version=opset, do_constant_folding=True, dynamo=False,
            )
            model = onnx.load(str(tmp))
            del model.metadata_props[:]
            for k, v in sorted(metadata.items()):
                entry = model.metadata_props.add()
                entry.key, entry.value = k, v
            model.doc_string = "DSS Pix2Pix image denoiser: noisy (B,3,H,W) renders -> denoised"
            model.producer_name = "dss-splatting"
            model.producer_version = _package_version()
            onnx.checker.check_model(model, full_check=True)
            onnx.save(model, str(tmp))
    finally:
        generator.train(was_training)
    log.info("exported %s (opset %d)", path, opset)
    return path


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The ``metadata_props`` of an ONNX file, JSON values parsed (no onnxruntime needed)."""
    import onnx

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"ONNX file {path} does not exist")
    try:
        model = onnx.load(str(path), load_external_data=False)
    except Exception as e:
        raise ValueError(f"{path}: not an ONNX model ({e})") from e
    return parse_metadata({p.key: p.value for p in model.metadata_props})


def parse_metadata(raw: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in raw.items():
        if k in JSON_KEYS:
            try:
                out[k] = json.loads(v)
            except json.JSONDecodeError:
                out[k] = v
        else:
            out[k] = v
    return out


def export_checkpoint(
    ckpt_path: str | Path,
    out_path: str | Path,
    *,
    opset: int = DEFAULT_OPSET,
    overwrite: bool = False,
) -> tuple[Path, dict[str, str], nn.Module]:
    """Lightning checkpoint (from ``dss-train``) -> ONNX file. Returns (path, metadata, generator).

    A checkpoint whose generator holds NaN or inf weights (a diverged training) is refused
    (ValueError) before anything is written."""
    from .module import load_generator

    gen, info = load_generator(ckpt_path)
    bad = [k for k, v in gen.state_dict().items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise ValueError(f"{ckpt_path}: the generator holds non-finite weights ({len(bad)} tensors, e.g. "
                         f"{', '.join(bad[:3])}): the training diverged; export an earlier checkpoint")
    meta = build_metadata(info)
    size = info.get("train_crop_size") or 64
    example = (min(int(size), 64) // SIZE_MULTIPLE * SIZE_MULTIPLE,) * 2
    path = export_onnx(gen, out_path, meta, opset=opset, example_size=example, overwrite=overwrite)
    return path, meta, gen


@torch.no_grad()
def onnx_parity(generator: nn.Module, onnx_path: str | Path, inputs: np.ndarray | torch.Tensor) -> float:
    """Max |PyTorch - onnxruntime| over ``inputs`` (B, C, H, W) float32."""
    import onnxruntime as ort

    x = torch.as_tensor(np.asarray(inputs, dtype=np.float32))
    ref = generator.eval()(x).numpy()
    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {sess.get_inputs()[0].name: x.numpy()})[0]
    return float(np.abs(ref - got).max())
