"""Eq. sumI with a gradient to the splats, in torch: the twin of the kernels' ``blend_backward``.

The weights rho_bar of the visible cached fragments are recomputed from the packed splats with
differentiable torch ops (in the kernels' operation order, :func:`splat_weight`), so autograd
supplies the smooth terms of Eqs. gradN and gradP (through the attributes w_k and rho_bar) that
the kernels' ``blend_backward`` writes by hand.
"""

from __future__ import annotations

import torch

from ..fragments import Fragments
from ..splats import Splats
from .rasterization import splat_weight

__all__ = ["blend"]


def blend(frags: Fragments, splats: Splats, attributes: torch.Tensor, background: torch.Tensor):
    """Normalised weighted sum over the visible entries of ``frags``, differentiable in
    ``splats.packed`` (V, N, 10) and ``attributes`` (V, N, C); ``background`` (C,).

    Returns:
        images (V, H, W, C) and mask (V, H, W) bool.
    """
    V, H, W, K = frags.idx.shape
    C = attributes.shape[-1]
    vis = frags.visible
    v_i, i_i, j_i, _ = torch.nonzero(vis, as_tuple=True)
    pts = frags.idx[vis].long()
    pk = splats.packed[v_i, pts]
    _, rho = splat_weight(pk, j_i.float() + 0.5, i_i.float() + 0.5)
    a = attributes[v_i, pts]
    flat = (v_i * H + i_i) * W + j_i
    num = torch.zeros(V * H * W, C, dtype=attributes.dtype, device=attributes.device).index_add(0, flat, rho[:, None] * a)
    den = torch.zeros(V * H * W, dtype=rho.dtype, device=rho.device).index_add(0, flat, rho)
    mask = den > 0
    img = torch.where(mask[:, None], num / torch.where(mask, den, torch.ones_like(den))[:, None], background.expand(C))
    return img.view(V, H, W, C), mask.view(V, H, W)
