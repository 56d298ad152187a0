"""Stage 2 of rendering in torch: the twin of the kernels' ``rasterize_forward``.

:func:`rasterize` gives the per-pixel top-K cache, :func:`blend_cached` the image and mask that
``rasterize_forward`` returns with attributes (Eq. sumI over the cache's weights).

For every valid splat we enumerate the pixels of its cutoff bounding box, keep those with
1/2 q <= C (q = d^T Sigma^-1 d), and per pixel keep the K entries with the smallest
(depth, point index). Memory grows with the number of covered pixels, so use it for small
scenes; the fast kernels give the same result.
"""

from __future__ import annotations

import math

import torch

from ..fragments import Fragments
from ..splats import Splats

__all__ = ["rasterize", "blend_cached", "bbox", "splat_weight"]


def bbox(packed: torch.Tensor, H: int, W: int):
    """Inclusive pixel ranges (j0, j1, i0, i1) of each splat's cutoff box, one pixel of margin.

    Both backends compute the same box from the same float32 inputs; the box only bounds the
    search, the per-pixel test decides membership.
    """
    u, v, rx, ry = packed[..., 0], packed[..., 1], packed[..., 7], packed[..., 8]
    j0 = torch.floor(u - rx - 0.5).clamp(-1, W) - 1
    j1 = torch.ceil(u + rx - 0.5).clamp(-1, W) + 1
    i0 = torch.floor(v - ry - 0.5).clamp(-1, H) - 1
    i1 = torch.ceil(v + ry - 0.5).clamp(-1, H) + 1
    return (j0.clamp(0, W - 1).long(), j1.clamp(0, W - 1).long(), i0.clamp(0, H - 1).long(), i1.clamp(0, H - 1).long())


def splat_weight(packed_k: torch.Tensor, px: torch.Tensor, py: torch.Tensor):
    """q and rho_bar of splats (M, F) at pixel centres (px, py) (M,), in the kernels' op order."""
    dx = px - packed_k[:, 0]
    dy = py - packed_k[:, 1]
    q = packed_k[:, 2] * dx * dx + packed_k[:, 3] * dx * dy + packed_k[:, 4] * dy * dy
    return q, packed_k[:, 5] * torch.exp(-0.5 * q)


def rasterize(splats: Splats, image_size: tuple[int, int], K: int = 5, cutoff: float = 1.0,
              merge_threshold: float = 0.0) -> Fragments:
    """Top-K fragments per pixel (see :class:`Fragments`)."""
    packed = splats.packed.detach()
    V, N, _ = packed.shape
    H, W = image_size
    dev = packed.device
    idx_out = torch.full((V, H * W, K), -1, dtype=torch.int32, device=dev)
    depth_out = torch.full((V, H * W, K), math.inf, dtype=torch.float32, device=dev)
    rho_out = torch.zeros((V, H * W, K), dtype=torch.float32, device=dev)
    j0, j1, i0, i1 = bbox(packed, H, W)
    for vi in range(V):
        ok = (packed[vi, :, 9] > 0) & (j1[vi] >= j0[vi]) & (i1[vi] >= i0[vi])
        # Splats fully outside the image: their clamped box is a border column/row, so require the
        # unclamped centre box to intersect the image.
        pts = torch.nonzero(ok).flatten()
        if len(pts) == 0:
            continue
        bw = (j1[vi, pts] - j0[vi, pts] + 1)
        bh = (i1[vi, pts] - i0[vi, pts] + 1)
        frag_pix, frag_pt, frag_depth, frag_rho = [], [], [], []
        # Bucket splats by box side (powers of two) so each bucket is one dense tensor op.
        side = torch.maximum(bw, bh)
        bucket = torch.ceil(torch.log2(side.float())).long()
        for b in torch.unique(bucket).tolist():
            sel = pts[bucket == b]
            S = 1 << b
            off = torch.arange(S, device=dev)
            jj = j0[vi, sel][:, None, None] + off[None, None, :]
            ii = i0[vi, sel][:, None, None] + off[None, :, None]
            inside = (jj <= j1[vi, sel][:, None, None]) & (ii <= i1[vi, sel][:, None, None])
            pk = sel[:, None, None].expand_as(inside)[inside]
            jj, ii = jj.expand_as(inside)[inside], ii.expand_as(inside)[inside]
            q, rho = splat_weight(packed[vi, pk], jj.float() + 0.5, ii.float() + 0.5)
            keep = (0.5 * q) <= cutoff
            frag_pix.append((ii * W + jj)[keep])
            frag_pt.append(pk[keep])
            frag_depth.append(packed[vi, pk[keep], 6])
            frag_rho.append(rho[keep])
        pix = torch.cat(frag_pix)
        pt = torch.cat(frag_pt)
        dep = torch.cat(frag_depth)
        rho = torch.cat(frag_rho)
        # Lexicographic order (pixel, depth, point index) by successive stable sorts.
        order = torch.argsort(pt, stable=True)
        order = order[torch.argsort(dep[order], stable=True)]
        order = order[torch.argsort(pix[order], stable=True)]
        pix, pt, dep, rho = pix[order], pt[order], dep[order], rho[order]
        # Rank of each fragment within its pixel's run.
        first = torch.ones_like(pix, dtype=torch.bool)
        first[1:] = pix[1:] != pix[:-1]
        run_start = torch.cummax(torch.where(first, torch.arange(len(pix), device=dev), torch.zeros_like(pix)), 0).values
        rank = torch.arange(len(pix), device=dev) - run_start
        k = rank < K
        idx_out[vi, pix[k], rank[k]] = pt[k].int()
        depth_out[vi, pix[k], rank[k]] = dep[k].float()
        rho_out[vi, pix[k], rank[k]] = rho[k].float()
    shape = (V, H, W, K)
    return Fragments(idx_out.view(shape), depth_out.view(shape), rho_out.view(shape), float(merge_threshold))


def blend_cached(frags: Fragments, attributes: torch.Tensor, background) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised weighted sum (Eq. sumI) over the visible entries of the cache, with the cache's
    weights (no gradient to the splats: :func:`dss.reference.blend` recomputes them).

    Args:
        attributes: (V, N, C) per-view point attributes w_k.
        background: scalar or (C,) value where no splat is visible.

    Returns:
        images (V, H, W, C) and mask (V, H, W) bool.
    """
    vis = frags.visible
    w = torch.where(vis, frags.rho, torch.zeros_like(frags.rho))
    V, H, W, K = frags.idx.shape
    C = attributes.shape[-1]
    safe = frags.idx.clamp_min(0).long().view(V, -1)
    attr = torch.gather(attributes, 1, safe[..., None].expand(V, safe.shape[1], C)).view(V, H, W, K, C)
    num = (w[..., None] * attr).sum(-2)
    den = w.sum(-1, keepdim=True)
    mask = den[..., 0] > 0
    bg = torch.as_tensor(background, dtype=attributes.dtype, device=attributes.device).expand(C)
    img = torch.where(mask[..., None], num / torch.where(den > 0, den, torch.ones_like(den)), bg)
    return img, mask
