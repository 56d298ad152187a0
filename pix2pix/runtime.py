"""Run an exported DSS denoiser with onnxruntime (no PyTorch needed).

>>> den = OnnxDenoiser("denoiser_1pct.onnx", intra_op_num_threads=2)
>>> den.noise_level, den.render_image_size
>>> clean = den(noisy)                   # (B, 3, H, W) float32, H and W multiples of 4
>>> clean_views = den.denoise_views(v)   # (V, H, W, 3), the dss image layout

Errors are explicit: a missing file (FileNotFoundError), a file that is not ONNX or is an ONNX
model but not one of our denoisers (:class:`DenoiserFormatError`, a ValueError, naming the
file), a graph whose declared input and output shapes are not images of one size and channel
count (checked at load; :meth:`OnnxDenoiser.check_render` checks them against the renders it
will get, running one blank image), a wrong channel count or a size that is not a multiple of
4 (ValueError naming the shape; ``pad=True`` pads by reflection and crops back instead).

Outputs are background-snapped (:mod:`pix2pix.postprocess`: pixels darker than half the training
renders' ambient term become 0) unless ``snap_background=False``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from .postprocess import background_snap_threshold
from .postprocess import snap_background as _snap

__all__ = ["OnnxDenoiser", "DenoiserFormatError", "DENOISER_KIND"]

DENOISER_KIND = "dss-pix2pix-denoiser"  # same as pix2pix.export.DENOISER_KIND (kept torch-free)
_JSON_KEYS = ("dss.train_image_size", "dss.render_image_size", "dss.render_settings",
              "dss.input_normalization", "dss.generator", "dss.noise_level", "dss.size_multiple",
              "dss.channels", "dss.epoch", "dss.global_step")


class DenoiserFormatError(ValueError):
    """The file is not an ONNX model, or not a DSS pix2pix denoiser."""


class OnnxDenoiser:
    """onnxruntime session over an exported denoiser.

    Args:
        path: the ``.onnx`` file written by ``dss-export``.
        intra_op_num_threads: threads inside an operator (None: onnxruntime's default, all cores).
        inter_op_num_threads: threads across operators (1: sequential execution).
        max_batch: views per ``session.run`` call (bounds peak memory).
        providers: onnxruntime execution providers (default CPU).
        snap_background: zero output pixels darker than half the ambient term of the training
            renders (:mod:`pix2pix.postprocess`); the raw network output with False.

    Attributes:
        metadata: the file's ``dss.*`` metadata, JSON values parsed.
        channels, size_multiple, noise_level, train_image_size, render_image_size,
        render_settings: convenience views of ``metadata``.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        intra_op_num_threads: int | None = None,
        inter_op_num_threads: int | None = 1,
        max_batch: int = 8,
        providers: list[str] | None = None,
        snap_background: bool = True,
    ):
        import onnxruntime as ort

        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"denoiser model {self.path} does not exist")
        if max_batch < 1:
            raise ValueError(f"max_batch must be >= 1, got {max_batch}")
        self.max_batch = int(max_batch)
        opts = ort.SessionOptions()
        if intra_op_num_threads:
            opts.intra_op_num_threads = int(intra_op_num_threads)
        if inter_op_num_threads:
            opts.inter_op_num_threads = int(inter_op_num_threads)
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(
                str(self.path), sess_options=opts, providers=providers or ["CPUExecutionProvider"]
            )
        except Exception as e:  # InvalidProtobuf, Fail, ... (onnxruntime's own classes)
            raise DenoiserFormatError(f"{self.path}: not a loadable ONNX model ({e})") from e
        raw = dict(self.session.get_modelmeta().custom_metadata_map)
        kind = raw.get("dss.kind")
        if kind != DENOISER_KIND:
            raise DenoiserFormatError(
                f"{self.path}: an ONNX model, but not a DSS pix2pix denoiser (metadata dss.kind = "
                f"{kind!r}, expected {DENOISER_KIND!r}); export one from a dss-train checkpoint "
                "with dss-export"
            )
        self.metadata: dict[str, Any] = {
            k: (json.loads(v) if k in _JSON_KEYS else v) for k, v in raw.items()
        }
        inputs = self.session.get_inputs()
        if len(inputs) != 1 or len(inputs[0].shape) != 4:
            raise DenoiserFormatError(
                f"{self.path}: expected one (B, C, H, W) input, got "
                f"{[(i.name, i.shape) for i in inputs]}"
            )
        self.input_name = inputs[0].name
        self.channels = int(self.metadata.get("dss.channels", 3))
        self.size_multiple = int(self.metadata.get("dss.size_multiple", 4))
        self._check_graph(list(inputs[0].shape), self.session.get_outputs())
        #: the graph's second output "log_scale" (PlanesGenerator(uncertainty=True)); the latest
        #: call's map is kept in ``last_log_scale``
        self.predicts_uncertainty = [o.name for o in self.session.get_outputs()[1:2]] == ["log_scale"]
        self.last_log_scale = None
        #: output pixels below this intensity are set to 0 (None: no snap)
        self.background_threshold = (background_snap_threshold(self.render_settings)
                                     if snap_background else None)

    def _check_graph(self, shape_in: list, outputs) -> None:
        """The graph's declared shapes: (B, C, H, W) in, one (B, C, H, W) image out with the same
        channels and size (dims given as names are checked by :meth:`check_render`)."""
        c_in = shape_in[1]
        if isinstance(c_in, int) and c_in != self.channels:
            raise DenoiserFormatError(f"{self.path}: the graph takes {c_in}-channel images, its metadata says "
                                      f"dss.channels = {self.channels}")
        if not outputs or len(outputs[0].shape) != 4:
            raise DenoiserFormatError(f"{self.path}: expected a (B, C, H, W) image output, got "
                                      f"{[(o.name, o.shape) for o in outputs]}")
        shape_out = list(outputs[0].shape)
        for axis, what in ((1, "channels"), (2, "rows"), (3, "columns")):
            a, b = shape_in[axis], shape_out[axis]
            if isinstance(a, int) and isinstance(b, int) and a != b:
                raise DenoiserFormatError(f"{self.path}: the graph maps {shape_in} to {shape_out} ({a} input {what}, "
                                          f"{b} output {what}); a denoiser returns images of its input's shape")
        if isinstance(shape_out[1], int) and shape_out[1] != self.channels:
            raise DenoiserFormatError(f"{self.path}: the graph returns {shape_out[1]}-channel images for "
                                      f"{self.channels}-channel input; a denoiser returns images of its input's shape")

    def check_render(self, image_size, channels: int = 3) -> None:
        """Refuse (DenoiserFormatError, one line) a model that cannot denoise renders of
        ``channels`` x ``image_size`` (H, W): a channel count or fixed size its graph does not
        take, or an output of another shape. Runs one blank image of that size through the
        model (padded to the size multiple), since a graph's dims given as names say nothing."""
        h, w = (int(image_size[0]), int(image_size[1]))
        if channels != self.channels:
            raise DenoiserFormatError(f"{self.path}: the model takes {self.channels}-channel images, the renders have "
                                      f"{channels}")
        shape_in = self.session.get_inputs()[0].shape
        m = self.size_multiple
        ph, pw = h + (-h) % m, w + (-w) % m
        for axis, size in ((2, ph), (3, pw)):
            if isinstance(shape_in[axis], int) and shape_in[axis] != size:
                raise DenoiserFormatError(f"{self.path}: the graph takes images of fixed size {shape_in[2:]}, the "
                                          f"renders are {h}x{w}")
        x = np.zeros((1, self.channels, ph, pw), np.float32)
        try:
            y = self.session.run(None, {self.input_name: x})[0]
        except Exception as e:  # onnxruntime's own classes: one line
            raise DenoiserFormatError(f"{self.path}: the model fails on a {h}x{w} render "
                                      f"({str(e).strip().splitlines()[0][:200]})") from None
        if tuple(y.shape) != x.shape:
            raise DenoiserFormatError(f"{self.path}: the model maps {self.channels}x{ph}x{pw} renders to shape "
                                      f"{tuple(y.shape[1:])}; a denoiser returns images of its input's shape")

    # ---- metadata views ------------------------------------------------------------------------
    @property
    def noise_level(self) -> float | None:
        return self.metadata.get("dss.noise_level")

    @property
    def train_image_size(self) -> list[int] | None:
        return self.metadata.get("dss.train_image_size")

    @property
    def render_image_size(self) -> list[int] | None:
        return self.metadata.get("dss.render_image_size")

    @property
    def render_settings(self) -> dict[str, Any]:
        return self.metadata.get("dss.render_settings") or {}

    def __repr__(self) -> str:
        return (f"OnnxDenoiser({str(self.path)!r}, noise_level={self.noise_level}, "
                f"render_image_size={self.render_image_size}, "
                f"background_threshold={self.background_threshold})")

    # ---- inference -----------------------------------------------------------------------------
    def _check(self, x: np.ndarray, pad: bool) -> None:
        if x.ndim != 4:
            raise ValueError(f"{self.path.name}: expected (B, C, H, W) images, got shape {x.shape}")
        if x.shape[1] != self.channels:
            hint = (" (this looks channels-last: use denoise_views for (V, H, W, C))"
                    if x.shape[-1] == self.channels else "")
            raise ValueError(
                f"{self.path.name}: expected {self.channels} channels in dim 1 of (B, C, H, W), "
                f"got shape {x.shape}{hint}"
            )
        h, w = x.shape[2:]
        m = self.size_multiple
        if not pad and (h % m or w % m):
            raise ValueError(
                f"{self.path.name}: height and width must be multiples of {m}, got {h}x{w} "
                f"(render at a multiple of {m}, or pass pad=True to pad and crop back)"
            )
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{self.path.name}: input images contain NaN or inf")

    def __call__(self, images: Any, pad: bool = False) -> np.ndarray:
        """Denoise (B, C, H, W) float images -> (B, C, H, W) float32, in batches of max_batch.

        ``pad=True`` reflect-pads H and W up to a multiple of 4 and crops the result back.
        """
        x = np.asarray(images, dtype=np.float32)
        self._check(x, pad)
        h, w = x.shape[2:]
        m = self.size_multiple
        ph, pw = (-h) % m, (-w) % m
        if ph or pw:
            x = np.pad(x, ((0, 0), (0, 0), (0, ph), (0, pw)), mode="reflect")
        runs = [
            self.session.run(None, {self.input_name: np.ascontiguousarray(x[i:i + self.max_batch])})
            for i in range(0, x.shape[0], self.max_batch)
        ]
        outs = [r[0] for r in runs]
        y = np.concatenate(outs, axis=0) if outs else np.zeros_like(x)
        # a model that predicts its uncertainty: (B, 1, H, W) log Laplace scale of the inverse depth
        self.last_log_scale = (np.ascontiguousarray(np.concatenate([r[1] for r in runs])[:, :, :h, :w], np.float32)
                               if self.predicts_uncertainty and runs else None)
        y = _snap(y[:, :, :h, :w], self.background_threshold, channel_dim=1)
        return np.ascontiguousarray(y, dtype=np.float32)

    def denoise_views(self, views: Any, pad: bool = False) -> np.ndarray:
        """Denoise (V, H, W, C) images (the ``dss`` layout) -> (V, H, W, C) float32."""
        v = np.asarray(views, dtype=np.float32)
        if v.ndim != 4:
            raise ValueError(f"{self.path.name}: expected (V, H, W, C) views, got shape {v.shape}")
        if v.shape[-1] != self.channels:
            raise ValueError(
                f"{self.path.name}: expected {self.channels} channels in the last dim of "
                f"(V, H, W, C), got shape {v.shape}"
            )
        return self(v.transpose(0, 3, 1, 2), pad=pad).transpose(0, 2, 3, 1).copy()
