"""Augmentations that keep the lighting of training pairs consistent.

The training renders are lit by a light **fixed to the camera** (a point light given in camera
space, x right, y down, z forward). What the denoiser must learn is how shading encodes local
geometry *under that light*; at test time it always sees the same light. So an augmentation is
safe only if the transformed image is one the same camera+light could have produced:

- **Random crops: safe.** Every pixel keeps the shading it was rendered with; only the framing
  changes. The generator is fully convolutional and cannot use absolute position anyway, and it
  is applied to full renders at test time. (Crops must keep H, W multiples of 4.)
- **Horizontal flip** (x -> -x): shows a mirrored shape lit by a light mirrored to -x. Safe
  **only if the light's x is 0** (light in the camera's vertical symmetry plane). Otherwise a
  bump lit from the left becomes a bump lit from the right, which under the real light reads
  as a dent: the pairs stay consistent with each other but teach the wrong shading->geometry
  relation and waste capacity on a light never seen at test time.
- **Vertical flip** (y -> -y): safe only if the light's y is 0.
- **Transpose** (x <-> y; with the flips it generates the 90-degree rotations): safe only if
  the light's x equals its y.
- The three orthogonal RGB **sun lights** of the paper's default shading are not symmetric
  under any of these: no flips.
- The **planes** channel (``shading: planes``, :func:`dss.shading.plane_coefficients`: a pixel
  holds the plane ``1/z = a . (x, y, 1)`` at normalised image coordinates) is not lit: a flipped
  image is the render of the mirrored shape (a shape as valid as any other) once the plane is
  mirrored too. ``x -> -x`` (hflip) negates ``a_0``, ``y -> -y`` (vflip) negates ``a_1``, and
  the transpose swaps them; the principal point is the image centre, so a flipped pixel's
  normalised coordinates are the original's, mirrored. All three flips are safe with those
  channel changes (:func:`apply_flips` with ``planes=True``).
- **Photometric changes** (brightness, contrast, gamma, colour jitter): unsafe. Intensity is
  the signal (n . l); scaling it changes the implied normals, and DSS later compares the
  network's output with renders in absolute terms.
- **Rescaling**: unsafe-ish: it changes splat footprint and noise amplitude in pixels relative
  to what the renderer produces at the training focal length/distance; data generation
  already varies distance instead.

:func:`safe_flips` applies these rules to a manifest's render block; unknown lighting gives no
flips (the conservative choice).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["FLIPS", "find_camera_light_position", "safe_flips", "apply_flips", "resolve_flips", "is_planes"]

FLIPS = ("hflip", "vflip", "transpose")


def find_camera_light_position(render: dict[str, Any] | None) -> list[float] | None:
    """The point light's camera-space position from a render block, or None when not found.

    Looks for ``light: {position, space}``, ``point_light: {position}``, ``light_position`` and
    ``light_position_camera``. A light declared in world space returns None (not camera-fixed).
    """
    if not isinstance(render, dict):
        return None
    shading = str(render.get("shading", "")).lower()
    # the planes channel is not lit by a light (safe_flips gives its channel-aware flips)
    if shading in ("sun", "suns", "three_suns", "planes"):
        return None
    candidates: list[tuple[Any, Any]] = []
    for key in ("light", "point_light"):
        v = render.get(key)
        if isinstance(v, dict):
            candidates.append((v.get("position"), v.get("space", "camera")))
    candidates.append((render.get("light_position_camera"), "camera"))
    candidates.append((render.get("light_position"), render.get("light_space", "camera")))
    for pos, space in candidates:
        if pos is None:
            continue
        if str(space).lower() != "camera":
            return None
        arr = np.asarray(pos, dtype=float).reshape(-1)
        if arr.shape == (3,) and np.all(np.isfinite(arr)):
            return arr.tolist()
    return None


def is_planes(render: dict[str, Any] | None) -> bool:
    """Whether a render block is the ``planes`` channel (flips change its channels)."""
    return isinstance(render, dict) and str(render.get("shading", "")).lower() == "planes"


def safe_flips(render: dict[str, Any] | None, rtol: float = 1e-6) -> list[str]:
    """Flips that leave the camera-fixed light where it is (see module docstring); all three for
    the ``planes`` channel, whose flips mirror the planes' first two components
    (:func:`apply_flips` with ``planes=True``)."""
    if is_planes(render):
        return list(FLIPS)
    pos = find_camera_light_position(render)
    if pos is None:
        return []
    x, y, z = pos
    tol = rtol * max(1.0, abs(x), abs(y), abs(z))
    out = []
    if abs(x) <= tol:
        out.append("hflip")
    if abs(y) <= tol:
        out.append("vflip")
    if abs(x - y) <= tol:
        out.append("transpose")
    return out


def resolve_flips(flips: str | Sequence[str] | None, render: dict[str, Any] | None) -> list[str]:
    """Turn a config value (``"auto"``, ``"none"``/None, or a list) into a list of flips.

    An explicit list that the light makes unsafe is honoured but logged as a warning.
    """
    if flips is None or flips == "none":
        return []
    if flips == "auto":
        chosen = safe_flips(render)
        log.info("augmentation: flips safe for this dataset's lighting: %s", chosen or "none")
        return chosen
    if isinstance(flips, str):
        flips = [flips]
    flips = list(flips)
    bad = [f for f in flips if f not in FLIPS]
    if bad:
        raise ValueError(f"unknown flips {bad}; choose from {list(FLIPS)}, 'auto' or 'none'")
    unsafe = [f for f in flips if f not in safe_flips(render)]
    if unsafe:
        log.warning("augmentation: %s change the light direction of this dataset's renders", unsafe)
    return flips


def apply_flips(arrays: Sequence[np.ndarray], flips: Sequence[str],
                rng: np.random.Generator, planes: Sequence[bool] | bool = False) -> list[np.ndarray]:
    """Apply each of ``flips`` with probability 1/2 to all ``arrays`` alike ((H, W, ...) each).

    ``planes``: per array (or one value for all), whether it holds planes (H, W, C >= 2) whose
    first two channels are the ``x`` and ``y`` components (the planes channel, or normalised
    image coordinates): hflip negates channel 0, vflip channel 1, transpose swaps them.
    """
    out = list(arrays)
    kinds = [bool(planes)] * len(out) if isinstance(planes, bool) else [bool(p) for p in planes]
    if len(kinds) != len(out):
        raise ValueError(f"planes: {len(kinds)} flags for {len(out)} arrays")
    for f in flips:
        if rng.random() < 0.5:
            if f == "hflip":
                out = [a[:, ::-1] for a in out]
            elif f == "vflip":
                out = [a[::-1] for a in out]
            elif f == "transpose":
                out = [np.swapaxes(a, 0, 1) for a in out]
            out = [_mirror_planes(a, f) if k else a for a, k in zip(out, kinds)]
    return out


def _mirror_planes(a: np.ndarray, flip: str) -> np.ndarray:
    """The channel change of ``flip`` on planes (H, W, C): see :func:`apply_flips`."""
    if a.ndim != 3 or a.shape[-1] < 2:
        raise ValueError(f"planes must be (H, W, C >= 2), got {a.shape}")
    a = np.array(a)  # a copy: the input may be a read-only memory map
    if flip == "hflip":
        a[..., 0] = -a[..., 0]
    elif flip == "vflip":
        a[..., 1] = -a[..., 1]
    elif flip == "transpose":
        a[..., [0, 1]] = a[..., [1, 0]]
    return a
