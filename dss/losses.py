"""Image losses for shape-from-rendering (paper section "Optimization objective").

Images are (V, H, W, C) tensors (views, rows, columns, channels), as everywhere inside ``dss``.

Normalisation (both losses):
    per pixel, the per-channel terms are **summed** over channels (paper Eq. smape sums over c),
    then averaged over pixels; without a mask that is the paper's 1/(HW) sum over pixels,
    averaged over the V views. So SMAPE lies in [0, C].

Masks: an optional ``mask`` of shape (V, H, W), (V, H, W, 1) or anything broadcastable to
(V, H, W) (e.g. (H, W)); bool or float (soft weights). The loss is the weighted mean over all
masked pixels of all views pooled together: sum(mask * per_pixel) / sum(mask). Views therefore
count in proportion to their masked area (as in the official code, which indexes the per-pixel
loss with the mask and takes one mean). An all-zero mask gives 0 (with a gradient of zeros).
"""

from __future__ import annotations

import torch

from .autograd import FusedSmape

__all__ = ["smape_loss", "l1_loss", "SmapeLoss", "L1Loss", "SMAPE_EPS"]

SMAPE_EPS = 1e-5  # paper: "the value of epsilon is typically chosen as 1e-5"


def _fused_smape_ok(pred: torch.Tensor, target: torch.Tensor, mask, reduction: str) -> bool:
    """The fused path covers the optimiser's case: CPU float32, no mask, mean, target constant,
    and the C++ module already built (the loss never starts a compile)."""
    from . import _ext

    return (mask is None and reduction == "mean" and pred.device.type == "cpu" and pred.dtype == torch.float32
            and target.dtype == torch.float32 and not (torch.is_grad_enabled() and target.requires_grad)
            and pred.numel() > 0 and _ext.loaded_cpu() is not None)


def _check_images(pred: torch.Tensor, target: torch.Tensor) -> None:
    if pred.dim() != 4:
        raise ValueError(f"images must have shape (V, H, W, C), got pred {tuple(pred.shape)}")
    if pred.shape != target.shape:
        raise ValueError(
            f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}"
        )


def _reduce(per_pixel: torch.Tensor, mask: torch.Tensor | None, reduction: str) -> torch.Tensor:
    """per_pixel: (V, H, W). Apply the mask and the reduction."""
    if reduction not in ("mean", "none"):
        raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")
    if mask is not None:
        m = mask
        if m.dim() == 4 and m.shape[-1] == 1:
            m = m[..., 0]
        try:
            m = torch.broadcast_to(m.to(per_pixel.dtype), per_pixel.shape)
        except RuntimeError as e:
            raise ValueError(
                f"mask of shape {tuple(mask.shape)} does not broadcast to (V,H,W) "
                f"{tuple(per_pixel.shape)}"
            ) from e
        weighted = per_pixel * m
        if reduction == "none":
            return weighted
        return weighted.sum() / m.sum().clamp_min(1e-12)
    if reduction == "none":
        return per_pixel
    # mean over pixels of each view, then over views (all views have the same H*W)
    return per_pixel.mean()


def _channel_reduce(x: torch.Tensor, channel_reduction: str) -> torch.Tensor:
    if channel_reduction == "sum":
        return x.sum(dim=-1)
    if channel_reduction == "mean":
        return x.mean(dim=-1)
    raise ValueError(f"channel_reduction must be 'sum' or 'mean', got {channel_reduction!r}")


def smape_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    eps: float = SMAPE_EPS,
    reduction: str = "mean",
    channel_reduction: str = "sum",
) -> torch.Tensor:
    """Symmetric mean absolute percentage error (paper Eq. smape).

    ``L = 1/(HW) sum_x sum_c |I - I*| / (|I| + |I*| + eps)``, averaged over the V views.

    Args:
        pred: (V, H, W, C) rendered images.
        target: (V, H, W, C) reference images (normally detached by the caller).
        mask: optional pixel weights, see module docstring.
        eps: the paper's epsilon (1e-5).
        reduction: ``"mean"`` -> scalar; ``"none"`` -> (V, H, W) per-pixel map (mask applied).
        channel_reduction: ``"sum"`` (paper, range [0, C]) or ``"mean"`` (range [0, 1]).

    Returns:
        Scalar (or (V, H, W) map). Each channel term is at most 1 because |a-b| <= |a|+|b|.
    """
    _check_images(pred, target)
    if channel_reduction in ("sum", "mean") and _fused_smape_ok(pred, target, mask, reduction):
        count = pred.numel() // pred.shape[-1] if channel_reduction == "sum" else pred.numel()
        return FusedSmape.apply(pred, target, eps, 1.0 / max(count, 1))
    per = (pred - target).abs() / (pred.abs() + target.abs() + eps)
    return _reduce(_channel_reduce(per, channel_reduction), mask, reduction)


def l1_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    reduction: str = "mean",
    channel_reduction: str = "sum",
) -> torch.Tensor:
    """L1 image loss with the same normalisation as :func:`smape_loss`.

    ``L = 1/(HW) sum_x sum_c |I - I*|``, averaged over views (``channel_reduction="mean"``
    gives the usual element-wise mean, e.g. ``torch.nn.functional.l1_loss``).
    """
    _check_images(pred, target)
    per = (pred - target).abs()
    return _reduce(_channel_reduce(per, channel_reduction), mask, reduction)


class SmapeLoss(torch.nn.Module):
    """Module form of :func:`smape_loss`."""

    def __init__(self, eps: float = SMAPE_EPS, channel_reduction: str = "sum"):
        super().__init__()
        self.eps = eps
        self.channel_reduction = channel_reduction

    def forward(self, pred, target, mask=None):
        return smape_loss(
            pred, target, mask, eps=self.eps, channel_reduction=self.channel_reduction
        )


class L1Loss(torch.nn.Module):
    """Module form of :func:`l1_loss`."""

    def __init__(self, channel_reduction: str = "sum"):
        super().__init__()
        self.channel_reduction = channel_reduction

    def forward(self, pred, target, mask=None):
        return l1_loss(pred, target, mask, channel_reduction=self.channel_reduction)
