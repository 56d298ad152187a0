"""Sun-light shading in torch: the twin of the kernels' ``sun_shade_forward`` / ``sun_shade_backward``."""

from __future__ import annotations

import torch

__all__ = ["sun_shade"]


def sun_shade(normals: torch.Tensor, albedo: torch.Tensor | None, directions: torch.Tensor,
              ambient: float) -> torch.Tensor:
    """Three directional lights, light l colouring channel l only (:class:`dss.shading.SunLights`
    with its default colours): ``(max(0, n . d_vl) + ambient) * albedo``.

    Args:
        normals: (N, 3) normals (any length: the diffuse term scales with it).
        albedo: (N, 3) per-point albedo, or None (white).
        directions: (V, 3, 3) per view, the world-space unit vectors towards the three lights.
        ambient: added to every channel before the albedo.

    Returns:
        (V, N, 3) attributes, differentiable in ``normals`` and ``albedo``.
    """
    V = directions.shape[0]
    # one (N, 3) x (3, 3 V) product
    lam = (normals @ directions.reshape(V * 3, 3).T).clamp_min(0).view(-1, V, 3)  # (N, V, 3) diffuse terms
    rgb = (lam + ambient).permute(1, 0, 2)  # (V, N, 3)
    if albedo is not None:
        rgb = rgb * albedo[None]
    return rgb
