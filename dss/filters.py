"""Image filters used as reference generators for DSS shape editing (paper: "Application:
shape editing via image filter").

Each filter maps rendered images ``(V, H, W, C)`` float32 tensors (values ~[0, 1], dss
convention) to tensors of the same shape, dtype and device. An optional ``mask`` ``(V, H, W)``
bool marks the foreground; where given, background pixels are returned unchanged so the
silhouette is kept (as the paper does).

* :func:`l0_smooth` -- L0 gradient minimisation (Xu, Lu, Xu, Jia: "Image Smoothing via L0
  Gradient Minimization", SIGGRAPH Asia 2011), half-quadratic splitting with circular-boundary
  FFT solves, vectorised over views and channels with ``torch.fft``.
* :func:`slic_filter` -- SLIC superpixels (Achanta et al. 2012, scikit-image), each superpixel
  filled with its mean colour.
* :func:`identity` -- returns the images (a copy).

:data:`FILTERS` maps names to callables; :func:`get_filter` builds one with keyword arguments.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np
import torch

__all__ = ["l0_smooth", "slic_filter", "identity", "FILTERS", "get_filter", "gradient_sparsity"]


def _check_images(images: torch.Tensor, mask: torch.Tensor | None, name: str) -> None:
    if not isinstance(images, torch.Tensor):
        raise TypeError(
            f"{name}: images must be a torch.Tensor (V,H,W,C), got {type(images).__name__}"
        )
    if images.ndim != 4:
        raise ValueError(f"{name}: images must have shape (V,H,W,C), got {tuple(images.shape)}")
    if not images.is_floating_point():
        raise TypeError(f"{name}: images must be floating point, got {images.dtype}")
    if mask is not None and tuple(mask.shape) != tuple(images.shape[:3]):
        raise ValueError(
            f"{name}: mask must have shape (V,H,W) = {tuple(images.shape[:3])}, got {tuple(mask.shape)}"
        )


def _keep_background(
    out: torch.Tensor, images: torch.Tensor, mask: torch.Tensor | None
) -> torch.Tensor:
    if mask is None:
        return out
    m = mask.to(device=images.device, dtype=torch.bool)[..., None]
    return torch.where(m, out, images)


def identity(images: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """The reference is the render itself (a copy); useful as a no-op baseline."""
    _check_images(images, mask, "identity")
    return images.clone()


def l0_smooth(
    images: torch.Tensor,
    lam: float = 2e-2,
    kappa: float = 2.0,
    beta_max: float = 1e5,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """L0 gradient smoothing (Xu et al. 2011) of images (V,H,W,C) -> (V,H,W,C).

    Minimises ``|S - I|^2 + lam * #{pixels with non-zero gradient}`` by alternating
    (i) the gradient sub-problem, a hard threshold: ``(h, v) = grad S`` where
    ``sum_channels(h^2 + v^2) >= lam / beta`` else 0, and (ii) the image sub-problem
    ``S = F^-1[(F(I) + beta (F(dx)^* F(h) + F(dy)^* F(v))) / (1 + beta (|F(dx)|^2 + |F(dy)|^2))]``
    with circular forward differences, starting at ``beta = 2 lam`` and multiplying by
    ``kappa`` until ``beta_max``. Larger ``lam`` gives fewer, flatter regions.

    Computed in float32 (float64 if the input is float64) on the input's device; output has
    the input's dtype. Pixels outside ``mask`` (V,H,W) bool, if given, keep their input value.
    """
    _check_images(images, mask, "l0_smooth")
    if lam <= 0 or kappa <= 1 or beta_max <= 0:
        raise ValueError(
            f"l0_smooth: need lam > 0, kappa > 1, beta_max > 0 (got {lam}, {kappa}, {beta_max})"
        )
    V, H, W, C = images.shape
    work = torch.float64 if images.dtype == torch.float64 else torch.float32
    img = images.to(work).permute(0, 3, 1, 2)  # (V,C,H,W): FFT over the last two dims
    # Eigenvalues of the circular forward-difference operators: |1 - exp(-2 pi i k / n)|^2.
    ky = torch.arange(H, device=img.device, dtype=work)
    kx = torch.arange(W // 2 + 1, device=img.device, dtype=work)
    dy2 = 2.0 - 2.0 * torch.cos(2.0 * math.pi * ky / H)
    dx2 = 2.0 - 2.0 * torch.cos(2.0 * math.pi * kx / W)
    denom_grad = dy2[:, None] + dx2[None, :]  # (H, W//2+1)
    f_img = torch.fft.rfft2(img)
    s = img
    beta = 2.0 * lam
    while beta < beta_max:
        # gradient sub-problem: hard threshold on the per-pixel gradient energy (all channels)
        h = torch.roll(s, shifts=-1, dims=3) - s
        v = torch.roll(s, shifts=-1, dims=2) - s
        energy = (h * h + v * v).sum(dim=1, keepdim=True)
        keep = energy >= lam / beta
        h = h * keep
        v = v * keep
        # image sub-problem: D^T applied to (h, v) is the negative backward difference
        div = (torch.roll(h, 1, dims=3) - h) + (torch.roll(v, 1, dims=2) - v)
        s = torch.fft.irfft2(
            (f_img + beta * torch.fft.rfft2(div)) / (1.0 + beta * denom_grad), s=(H, W)
        )
        beta *= kappa
    out = s.permute(0, 2, 3, 1).to(images.dtype).contiguous()
    return _keep_background(out, images, mask)


def slic_filter(
    images: torch.Tensor,
    n_segments: int = 150,
    compactness: float = 20.0,
    mask: torch.Tensor | None = None,
    enforce_connectivity: bool = False,
    max_num_iter: int = 10,
    return_labels: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, np.ndarray]:
    """SLIC superpixels of each view, every superpixel filled with its mean colour.

    ``images`` (V,H,W,C) -> (V,H,W,C). Defaults (150 segments, compactness 20, no connectivity
    enforcement) follow the DSS authors' filter. With ``mask`` (V,H,W) bool, segmentation and
    the means use foreground pixels only and the background is returned unchanged; a view with
    an empty mask is returned unchanged. 3-channel images are segmented in CIELAB (scikit-image
    default), others on their raw values. ``return_labels`` also returns the (V,H,W) int labels
    (0 = background when masked, superpixels numbered from 1).
    """
    from skimage.segmentation import slic

    _check_images(images, mask, "slic_filter")
    if n_segments < 1:
        raise ValueError(f"slic_filter: n_segments must be >= 1, got {n_segments}")
    V, H, W, C = images.shape
    x = images.detach().to("cpu", torch.float64).numpy()
    m = None if mask is None else mask.detach().to("cpu", torch.bool).numpy()
    out = x.copy()
    labels = np.zeros((V, H, W), dtype=np.int64)
    for i in range(V):
        mi = None if m is None else m[i]
        if mi is not None and not mi.any():
            continue
        img = x[i] if C > 1 else x[i, ..., 0]
        lab = slic(
            img,
            n_segments=n_segments,
            compactness=compactness,
            mask=mi,
            start_label=1,
            enforce_connectivity=enforce_connectivity,
            max_num_iter=max_num_iter,
            channel_axis=-1 if C > 1 else None,
            convert2lab=(C == 3),
        )
        labels[i] = lab
        flat = lab.reshape(-1)
        fg = flat > 0
        n = int(flat.max()) + 1
        counts = np.bincount(flat[fg], minlength=n).astype(np.float64)
        pix = x[i].reshape(-1, C)
        means = (
            np.stack(
                [np.bincount(flat[fg], weights=pix[fg, c], minlength=n) for c in range(C)], axis=1
            )
            / np.maximum(counts, 1.0)[:, None]
        )
        o = out[i].reshape(-1, C)
        o[fg] = means[flat[fg]]
    result = torch.from_numpy(out).to(device=images.device, dtype=images.dtype)
    if return_labels:
        return result, labels
    return result


def gradient_sparsity(images: torch.Tensor, tol: float = 1e-3) -> float:
    """Fraction of pixels (V,H,W) whose forward-difference gradient (max over channels) is
    below ``tol``: a measure of how piecewise constant an image is (1 = constant)."""
    h = (images[:, :, 1:, :] - images[:, :, :-1, :]).abs().amax(dim=-1)
    v = (images[:, 1:, :, :] - images[:, :-1, :, :]).abs().amax(dim=-1)
    g = torch.maximum(h[:, :-1, :], v[:, :, :-1])
    return float((g < tol).float().mean())


FILTERS: dict[str, Callable[..., torch.Tensor]] = {
    "l0": l0_smooth,
    "slic": slic_filter,
    "identity": identity,
}


def get_filter(name: str, **kwargs) -> Callable[..., torch.Tensor]:
    """The filter ``name`` ("l0", "slic", "identity") with ``kwargs`` bound."""
    if name not in FILTERS:
        raise ValueError(f"unknown image filter {name!r}; available: {sorted(FILTERS)}")
    return functools.partial(FILTERS[name], **kwargs)
