"""Image metrics for the denoiser: L1, SMAPE, PSNR on (B, C, H, W) float tensors.

Conventions (state them next to every number):
- ``l1``: mean absolute difference over channels and pixels (the normalisation of pix2pix's L1
  training term, so validation and training L1 are comparable).
- ``smape``: the DSS paper's Eq. (smape): per pixel, |a-b| / (|a|+|b|+eps) **summed** over
  channels, then averaged over pixels; eps = 1e-5; range [0, C]. Same convention as
  ``dss.losses.smape_loss``.
- ``psnr``: 10 log10(data_range^2 / MSE) per image (MSE over channels and pixels), then the mean
  over images; ``data_range`` = 1 (renders are about [0, 1]). Identical images give
  ``max_psnr`` (100 dB) rather than infinity.

Masks: an optional (B, H, W) bool/float ``mask`` restricts every metric to the covered pixels
(the shards' ``mask``: pixels covered in either render). This matters for SMAPE: on background
pixels the clean render is exactly 0, so any output value v != 0 there scores
|v| / (|v| + eps) ~ 1 per channel, and a few 1e-3 of background leakage would dominate the
number. Validation reports the masked metrics as the main ones (and the full-image SMAPE
beside them). l1/smape pool the masked pixels of all images (each pixel counts once); psnr
takes each image's masked MSE.
"""

from __future__ import annotations

import torch

__all__ = ["l1", "smape", "psnr", "image_metrics", "SMAPE_EPS"]

SMAPE_EPS = 1e-5


def _check(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor | None:
    if pred.dim() != 4 or pred.shape != target.shape:
        raise ValueError(
            f"expected two (B, C, H, W) tensors of equal shape, got {tuple(pred.shape)} and "
            f"{tuple(target.shape)}"
        )
    if mask is None:
        return None
    b, _, h, w = pred.shape
    if mask.shape != (b, h, w):
        raise ValueError(f"mask must be (B, H, W) = {(b, h, w)}, got {tuple(mask.shape)}")
    return mask.to(pred.dtype).unsqueeze(1)  # (B, 1, H, W)


def _pixel_mean(per_pixel: torch.Tensor, m: torch.Tensor | None) -> torch.Tensor:
    """per_pixel (B, 1, H, W) -> scalar mean (over masked pixels when m is given)."""
    if m is None:
        return per_pixel.mean()
    return (per_pixel * m).sum() / m.sum().clamp_min(1e-12)


def l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean |pred - target| over channels and (masked) pixels; scalar."""
    m = _check(pred, target, mask)
    return _pixel_mean((pred - target).abs().mean(dim=1, keepdim=True), m)


def smape(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
          eps: float = SMAPE_EPS) -> torch.Tensor:
    """Paper SMAPE (channel sum, mean over (masked) pixels); scalar in [0, C]."""
    m = _check(pred, target, mask)
    per = (pred - target).abs() / (pred.abs() + target.abs() + eps)
    return _pixel_mean(per.sum(dim=1, keepdim=True), m)


def psnr(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
         data_range: float = 1.0, max_psnr: float = 100.0) -> torch.Tensor:
    """Mean over images of the per-image PSNR in dB (MSE over (masked) pixels); scalar."""
    m = _check(pred, target, mask)
    sq = (pred.double() - target.double()).pow(2).mean(dim=1, keepdim=True)  # (B,1,H,W)
    if m is None:
        mse = sq.flatten(1).mean(dim=1)
    else:
        md = m.double()
        mse = (sq * md).flatten(1).sum(dim=1) / md.flatten(1).sum(dim=1).clamp_min(1e-12)
    val = 10.0 * torch.log10(data_range**2 / mse.clamp_min(1e-30))
    return val.clamp(max=max_psnr).mean().to(pred.dtype)


@torch.no_grad()
def image_metrics(pred: torch.Tensor, target: torch.Tensor,
                  mask: torch.Tensor | None = None) -> dict[str, float]:
    """``{"l1", "smape", "psnr"}`` as Python floats."""
    return {
        "l1": float(l1(pred, target, mask)),
        "smape": float(smape(pred, target, mask)),
        "psnr": float(psnr(pred, target, mask)),
    }
