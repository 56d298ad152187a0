"""Cross-view agreement of planes-channel outputs, measured the way the plane fusion reads them.

The plane fusion (:mod:`dss.fusion`) moves a point along its normal by the mean of the offsets
the views show for it, weighted by the *consistency* ``s0^2 / (s0^2 + spread^2)``: a reference
earns trust only where its views agree on the surface to a fraction of a pixel. A loss on each
view's depth alone does not ask for that. Here a training batch holds several views of one
cloud (``experiments.onthefly`` with ``multiview``: crops around one anchor point, with the
cameras and *probe* points of the clean cloud near the anchor), and for every probe and view:

- the probe is projected into the view's crop; its pixel's output plane gives the depth
  ``z_ref`` of the surface on the probe's ray (the fusion's :func:`dss.fusion.observe_planes`,
  nearest pixel, the plane evaluated on the probe's own ray);
- the observation counts when the clean render shows the probe there (within ``tau`` along the
  ray: the probe is not hidden) with a normal within 45 degrees of the probe's, and both renders
  cover the pixel; weight ``cos^2`` of the ray to the normal;
- its offset along the probe's normal is ``(z_ref / z - 1) (p . n)``; the probes lie on the
  clean surface, so the right offset is 0.

Per probe: the weighted mean offset (what the fusion would move a point there by) and the
weighted spread across views (what its consistency reads). :func:`agreement_terms` returns both;
:class:`pix2pix.module.Pix2PixModule` trains on them (``lambda_agree``, ``lambda_fused``).

Tensors only (no ``dss`` import): the cameras come in the batch as ``cam_R`` (B, 3, 3)
world-to-camera rotations, ``cam_t`` (B, 3), ``cam_focal`` (B,) in pixels and ``cam_principal``
(B, 2) in the crop's pixel coordinates (the full render's principal point less the crop origin).
"""

from __future__ import annotations

import math

import torch

__all__ = ["MULTIVIEW_KEYS", "probe_observations", "agreement_terms", "has_multiview"]

#: the batch keys a multi-view batch carries
MULTIVIEW_KEYS = ("cam_R", "cam_t", "cam_focal", "cam_principal", "probe_points", "probe_normals")


def has_multiview(batch: dict) -> bool:
    return all(k in batch for k in MULTIVIEW_KEYS)


def probe_observations(planes: torch.Tensor, clean: torch.Tensor, noisy: torch.Tensor, batch: dict,
                       tau: float = 0.003, max_angle_deg: float = 45.0,
                       min_cos: float = 0.2) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Offsets (B, P) of the probes along their normals to the surface ``planes`` (B, 3, h, w)
    shows on their rays, their weights (B, P) (0 where the observation does not count) and their
    depths (B, P).

    ``clean`` / ``noisy`` (B, 3, h, w): the crops of the clean and the input render (visibility
    and coverage); ``tau``: how far (bbox diagonals, along the ray) the clean render's surface may
    be from a probe for the probe to count as seen. Differentiable with respect to ``planes``."""
    B, _, h, w = planes.shape
    R, t = batch["cam_R"].to(planes), batch["cam_t"].to(planes)
    f, pp = batch["cam_focal"].to(planes), batch["cam_principal"].to(planes)
    pts, nrm = batch["probe_points"].to(planes), batch["probe_normals"].to(planes)
    pc = torch.einsum("bij,bpj->bpi", R, pts) + t[:, None]
    z = pc[..., 2]
    zs = z.clamp_min(1e-6)
    x, y = pc[..., 0] / zs, pc[..., 1] / zs
    u, v = x * f[:, None] + pp[:, None, 0], y * f[:, None] + pp[:, None, 1]
    iu, iv = u.floor().long(), v.floor().long()
    inside = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h) & (z > 1e-6)
    idx = (iv.clamp(0, h - 1) * w + iu.clamp(0, w - 1))  # (B, P)

    def at(img):  # (B, 3, h, w) -> (B, P, 3) at the probes' pixels
        flat = img.reshape(B, 3, h * w)
        return torch.gather(flat, 2, idx[:, None, :].expand(-1, 3, -1)).transpose(1, 2)

    a, ac, an = at(planes), at(clean.to(planes)), at(noisy.to(planes))
    covered = inside & (ac.abs().amax(-1) > 0) & (an.abs().amax(-1) > 0)
    inv = a[..., 0] * x + a[..., 1] * y + a[..., 2]
    inv_c = ac[..., 0] * x + ac[..., 1] * y + ac[..., 2]
    seen = covered & (inv_c > 1e-6) & ((1.0 / inv_c.clamp_min(1e-6) - z).abs() < tau)
    n_cam = torch.einsum("bij,bpj->bpi", R, nrm)
    ray = torch.nn.functional.normalize(pc, dim=-1)
    cos = (ray * n_cam).sum(-1)
    n_ref = -torch.nn.functional.normalize(ac, dim=-1)
    n_pt = torch.where((cos < 0)[..., None], n_cam, -n_cam)
    agree = (n_ref * n_pt).sum(-1) >= math.cos(math.radians(max_angle_deg))
    ok = seen & agree & (cos.abs() >= min_cos) & (inv > 1e-6)
    z_ref = 1.0 / inv.clamp_min(1e-6)
    offset = (z_ref / zs - 1.0) * (pc * n_cam).sum(-1)
    zero = torch.zeros_like(offset)
    return torch.where(ok, offset, zero), torch.where(ok, (cos * cos).detach(), zero), z.detach()


def agreement_terms(offset: torch.Tensor, weight: torch.Tensor, min_views: int = 3,
                    eps: float = 1e-10, depth: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Per probe over the batch's views (dim 0; the batch is one cloud's views): ``mean`` (P,)
    the weighted mean offset, ``spread`` (P,) the weighted std across views (Bessel-corrected by
    the observation count, as the fusion's), ``valid`` (P,) bool, probes seen in ``min_views``
    views or more, ``count`` (P,) their views, and with ``depth`` (B, P) its weighted mean
    ``depth`` (P,)."""
    n = (weight > 0).sum(0).to(offset)
    W = weight.sum(0)
    Wc = W.clamp_min(1e-12)
    m = (weight * offset).sum(0) / Wc
    var = (weight * (offset - m[None]) ** 2).sum(0) / Wc * n / (n - 1).clamp_min(1)
    out = {"mean": m, "spread": (var + eps).sqrt(), "valid": (n >= min_views) & (W > 0), "count": n}
    if depth is not None:
        out["depth"] = (weight * depth).sum(0) / Wc
    return out
