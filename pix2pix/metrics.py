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

__all__ = ["l1", "smape", "psnr", "image_metrics", "SMAPE_EPS", "DEPTH_ERROR_CAP", "pixel_coords",
           "planes_inverse_depth", "surface_pixels", "planes_errors", "planes_metric_sums"]

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


# ------------------------------------------------------------------------------ planes channel
#: depth errors are capped at this many bounding-box diagonals in the mean (a pixel showing
#: another surface than the clean render, at a silhouette or an occlusion edge, would otherwise
#: dominate it; the plane fusion ignores observations that far off anyway)
DEPTH_ERROR_CAP = 0.05
#: the smallest inverse depth read from an image (a smaller one, e.g. the network's output on a
#: pixel it calls background, counts as depth 1 / PLANES_MIN_INV, i.e. a capped error)
PLANES_MIN_INV = 1e-3


def pixel_coords(full_size, focal: float, window=None, offset=(0, 0)) -> torch.Tensor:
    """Normalised image coordinates (2, h, w) of the pixel centres, ``(x, y) = ((u - c_x) / f,
    (v - c_y) / f)`` with ``u = column + 0.5``, ``v = row + 0.5`` and the principal point at the
    centre of the full render (``full_size`` = (H, W); the cameras of ``dss.cameras.look_at``),
    over the (h, w) ``window`` (default: the full render) whose first pixel is at ``offset`` =
    (row, column) of the full render (a training crop)."""
    H, W = int(full_size[0]), int(full_size[1])
    h, w = (H, W) if window is None else (int(window[0]), int(window[1]))
    y0, x0 = int(offset[0]), int(offset[1])
    x = (torch.arange(w, dtype=torch.float32) + x0 + 0.5 - W / 2.0) / float(focal)
    y = (torch.arange(h, dtype=torch.float32) + y0 + 0.5 - H / 2.0) / float(focal)
    return torch.stack([x[None, :].expand(h, w), y[:, None].expand(h, w)])


def planes_inverse_depth(img: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Inverse depth (B, H, W) that a ``planes`` image (B, 3, H, W) gives at its pixels, with
    ``coords`` (B, 2, H, W) their normalised image coordinates: ``a_0 x + a_1 y + a_2``
    (:func:`dss.shading.planes_inverse_depth` in the pix2pix layout)."""
    return img[:, 0] * coords[:, 0] + img[:, 1] * coords[:, 1] + img[:, 2]


def surface_pixels(noisy: torch.Tensor, clean: torch.Tensor) -> torch.Tensor:
    """(B, H, W) bool: pixels both the clean and the noisy render cover (the surface pixels of
    the planes metrics; outside the input's coverage the pipeline keeps its background)."""
    return (clean.abs().amax(1) > 0) & (noisy.abs().amax(1) > 0)


def planes_errors(img: torch.Tensor, clean: torch.Tensor, coords: torch.Tensor,
                  where: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-pixel geometric errors of a ``planes`` image against the clean render, at ``where``
    (B, H, W) bool (1-D tensors over those pixels):

    - ``depth``: |z - z_clean| in the renders' length unit (bounding-box diagonals), z = 1 /
      the implied inverse depth (at least :data:`PLANES_MIN_INV`);
    - ``depth_signed``: z - z_clean (negative: in front of the clean surface);
    - ``normal_deg``: angle between the planes' directions (their normals), degrees;
    - ``abs``: |img - clean| summed over channels; ``smape``: the paper's SMAPE (channel sum).
    """
    inv = planes_inverse_depth(img, coords)[where]
    inv_c = planes_inverse_depth(clean, coords)[where]
    z = 1.0 / inv.clamp_min(PLANES_MIN_INV)
    z_c = 1.0 / inv_c.clamp_min(PLANES_MIN_INV)
    a = img.permute(0, 2, 3, 1)[where]
    b = clean.permute(0, 2, 3, 1)[where]
    cos = torch.nn.functional.cosine_similarity(a, b, dim=1, eps=1e-12).clamp(-1, 1)
    return {"depth": (z - z_c).abs(), "depth_signed": z - z_c, "normal_deg": torch.rad2deg(torch.acos(cos)),
            "abs": (a - b).abs().sum(1), "smape": ((a - b).abs() / (a.abs() + b.abs() + SMAPE_EPS)).sum(1)}


def planes_metric_sums(img: torch.Tensor, clean: torch.Tensor, coords: torch.Tensor,
                       where: torch.Tensor) -> dict[str, torch.Tensor]:
    """Sums over the ``where`` pixels (divide by their count, ``pixels``) of the planes metrics:
    ``surface_l1`` (mean over channels), ``surface_smape``, ``depth_err`` (capped at
    :data:`DEPTH_ERROR_CAP`), ``depth_bias`` (signed error where |error| < the cap; with
    ``depth_bias_pixels``), ``depth_within_1e-3`` (the count within 0.001 diagonals) and
    ``normal_err_deg``."""
    e = planes_errors(img, clean, coords, where)
    inside = e["depth"] < DEPTH_ERROR_CAP
    d = e["depth"].double()
    return {"surface_l1": e["abs"].double().sum() / 3.0, "surface_smape": e["smape"].double().sum(),
            "depth_err": d.clamp_max(DEPTH_ERROR_CAP).sum(), "depth_bias": e["depth_signed"].double()[inside].sum(),
            "depth_bias_pixels": inside.double().sum(), "depth_within_1e-3": (d < 1e-3).double().sum(),
            "normal_err_deg": e["normal_deg"].double().sum(), "pixels": where.double().sum()}
