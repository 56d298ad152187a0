"""Background snap: the one physical constraint the denoiser's output must satisfy.

The training renders (``data_prep``) shade every covered pixel with ``(intensity * max(0, n.l) +
ambient) * albedo`` (white albedo) over a black background, so a covered pixel is never darker
than the ambient term, and an uncovered one is exactly 0. The generator's output is unbounded
(no tanh, as the paper's network): around the silhouette it leaves a faint halo where the noisy
input covered pixels that the clean surface does not. Measured on the validation split of the
shipped data (``python -m experiments.evaluation.evaluate_denoiser
experiments/assets/denoiser_noise_1pct.onnx --data data/pairs``, tracked in
results/denoise/denoiser_eval_1pct.json), two thirds of the noisy input's masked SMAPE lies on
such pixels (0.545 of 0.829; SMAPE is 1 per channel for any non-zero value over a zero target),
and the network's raw output keeps nearly all of it (0.545; 0.354 after the snap).

The snap sets a pixel to 0 when its brightest channel is below ``SNAP_FRACTION`` x the darkest
covered value (ambient x white albedo): the decision boundary halfway between background (0) and
the darkest lit surface. It is fixed by the render settings of the training data, never fitted to
validation numbers. Covered pixels keep their (unbounded) values.

Only for the lit channel: renders in the ``planes`` channel (``shading: planes``) hold plane
coefficients, not intensities (their first two components are signed and about 0 on a surface
facing the camera), so they are never snapped, whatever ``light`` block their render settings
carry.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["SNAP_FRACTION", "background_snap_threshold", "snap_background"]

#: the threshold as a fraction of the darkest covered value (halfway between 0 and it)
SNAP_FRACTION = 0.5


def background_snap_threshold(render: dict[str, Any] | None) -> float | None:
    """The snap threshold for renders made with ``render`` (a data manifest's render block, or
    an ONNX file's ``dss.render_settings``); None when it cannot be derived (no point light with
    ambient, or a non-black background), in which case nothing is snapped.

    Returns a render intensity (same units as the images, about [0, 1]).
    """
    if not render:
        return None
    if str(render.get("shading", "")).lower() == "planes":  # plane coefficients, not intensities
        return None
    light = render.get("light") or {}
    background = float((render.get("renderer") or {}).get("background", 0.0))
    ambient = light.get("ambient")
    if ambient is None or background != 0.0 or float(ambient) <= 0.0:
        return None
    return SNAP_FRACTION * float(ambient)


def snap_background(images, threshold: float | None, channel_dim: int):
    """Zero every pixel whose brightest channel is below ``threshold``.

    Args:
        images: (B, C, H, W) (``channel_dim=1``) or (V, H, W, C) (``channel_dim=-1``), a numpy
            array or a torch tensor.
        threshold: from :func:`background_snap_threshold`; None returns ``images`` unchanged.

    Returns:
        The same type and shape; covered pixels unchanged.
    """
    if threshold is None:
        return images
    if isinstance(images, np.ndarray):
        keep = images.max(axis=channel_dim, keepdims=True) >= threshold
        return images * keep
    keep = images.amax(dim=channel_dim, keepdim=True) >= threshold
    return images * keep
