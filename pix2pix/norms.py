"""Normalisation layers for the Pix2Pix networks, and a plain-data description of them.

The networks take the normalisation as a *callable* ``norm_layer(num_features) -> nn.Module``
(a class or a ``functools.partial``), never as a string: which layer to use is a config-layer
decision (Hydra builds it with ``_target_`` and ``_partial_: true``).

To rebuild a network from a checkpoint or an ONNX file without Hydra, :func:`norm_spec` turns
such a callable into JSON-able data (import path + keyword arguments) and :func:`build_norm`
turns that back into the callable.
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable
from typing import Any

import torch
from torch import nn

__all__ = ["PixelNorm", "Identity", "NormFactory", "norm_spec", "build_norm"]

NormFactory = Callable[[int], nn.Module]


class PixelNorm(nn.Module):
    """Pixel-wise feature vector normalisation (Karras et al. 2018, "Progressive GANs", Sec. 4.2).

    ``b_{x,y} = a_{x,y} / sqrt(mean_c(a_{x,y,c}^2) + eps)``: each pixel's feature vector is scaled to
    unit root-mean-square over channels. It has no parameters and no batch statistics, so it
    behaves the same in training and inference, at any batch size and any image size (which
    batch norm does not), and it keeps signal magnitudes from escalating, which is what the
    DSS paper uses it for against checkerboard artefacts.

    Args:
        num_features: accepted (and ignored) so that it has the same signature as other norms.
        eps: added under the square root (Karras et al. use 1e-8).

    Shapes: (B, C, H, W) -> (B, C, H, W).
    """

    def __init__(self, num_features: int | None = None, eps: float = 1e-8):
        super().__init__()
        self.num_features = num_features
        self.eps = float(eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.rsqrt(x.pow(2).mean(dim=1, keepdim=True) + self.eps)

    def extra_repr(self) -> str:
        return f"eps={self.eps:g}"


class Identity(nn.Identity):
    """No normalisation; takes (and ignores) ``num_features`` like the other norm layers."""

    def __init__(self, num_features: int | None = None):
        super().__init__()


def _qualname(obj: Any) -> str:
    return f"{obj.__module__}.{obj.__qualname__}"


def norm_spec(norm_layer: NormFactory) -> dict[str, Any]:
    """Describe a norm-layer factory as JSON-able data: ``{"target": "pkg.Cls", "kwargs": {...}}``.

    Accepts a class/function or a ``functools.partial`` of one with keyword arguments only
    (which is what Hydra's ``_partial_: true`` produces).
    """
    if isinstance(norm_layer, functools.partial):
        if norm_layer.args:
            raise ValueError(
                f"norm_layer partial {norm_layer!r} has positional arguments; use keywords only"
            )
        inner = norm_spec(norm_layer.func)
        inner["kwargs"] = {**inner["kwargs"], **dict(norm_layer.keywords)}
        return inner
    if not callable(norm_layer):
        raise TypeError(f"norm_layer must be callable(num_features) -> nn.Module, got {norm_layer!r}")
    return {"target": _qualname(norm_layer), "kwargs": {}}


def build_norm(spec: dict[str, Any]) -> NormFactory:
    """Inverse of :func:`norm_spec`: import ``spec["target"]`` and bind ``spec["kwargs"]``."""
    target = spec.get("target")
    if not isinstance(target, str) or "." not in target:
        raise ValueError(f"norm spec needs a dotted 'target', got {spec!r}")
    module_name, _, attr = target.rpartition(".")
    try:
        obj = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"cannot import norm layer {target!r}: {e}") from e
    kwargs = dict(spec.get("kwargs") or {})
    return functools.partial(obj, **kwargs) if kwargs else obj
