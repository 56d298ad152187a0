"""The paper's visibility gradient for point positions (Eqs. gradcase and filteredG), in torch.

The twin of the kernels' ``visibility_backward`` (dss/csrc/visibility_backward_*), the same rules
written out readably.

For every rendered point k (valid splat in view v) and every pixel x of a (2w+1)^2 window
around its centre (optionally on a stride), with the pixel's cached top-K list sorted by depth,
front depth d0 and ``I_x`` the rendered value:

- (c) k is visible at x (in the list, within T of the front): remove it. The new front is the
  first remaining entry and the visible set is re-evaluated (this may reveal entries that were
  occluded). ``dI = I_new - I_x``. The point can move *away* from x until x leaves the cutoff
  ellipse (|dx| = r - s) or *through* x until x leaves it on the other side (|dx| = r + s), with s
  the distance from the centre to x and r the ellipse radius in that direction; both moves are
  in the image plane at the point's depth, and both terms are summed (paper Fig. 1D, right).
- (a) k is not visible and nothing covers x in front of it (the pixel is empty, or
  ``z_k <= d0 + T``): add it at x with its peak weight ``rho* = norm_k``, merging with the entries
  within T of ``min(z_k, d0)``; the move is screen space at the point's depth toward the
  back-projected pixel q_x.
- (b) k is not visible because splats cover x in front of it (``z_k > d0 + T``): it must come
  forward to the front depth d0, where it merges with the visible entries; the move
  ``q_x(d0) - p_k`` has a negative depth component.

Each move ``dp`` contributes ``(dL/dI . dI) dp / (|dp|^2 + eps)`` to dL/dp_k, and is dropped
when ``dL/dI . dI >= 0`` (the change could not reduce the loss, Eq. filteredG).

Occlusion test (cases (a)/(b)): z_k above is the depth of k's tangent plane at pixel x (the depth
its splat would have there, ``planes`` from :func:`dss.reference.tangent_planes`, clamped to a slope
of ``MAX_SLOPE``), not its centre depth; (a) moves toward q_x at that depth, (b) comes forward by
``d0 - z_k``. The paper compares centre depths. On a curved surface the centre depth of a point a
few pixels away differs from the surface depth at x by slope x distance, more than T, so a point
of the visible surface counts as occluded there and case (b) pulls it toward the camera; every view
does so, and a sphere that must shrink onto a smaller target inflates instead (measured: a step
along the gradient raises the loss; tests/test_render_backward.py). ``planes=None`` (or
``RenderSettings(occlusion_depth="center")``) gives the paper's literal rule.

Deviation from the paper's text: Eq. gradcase writes the second visible-case term with
``|dp+|`` unsquared; we square it like every other term, which keeps the gradient's units
consistent (the unsquared form is a typo as far as we can tell; the 1D figure is reproduced).

``mode="rbf"`` replaces the linearised visibility step by the derivative of a smooth Gaussian
``h = exp(-q/2)`` of the same splat, ``dPhi/dp = (I_with - I_without) dh/dp``, without the filter:
the RBF-derived gradient the paper compares against.
"""

from __future__ import annotations

import torch

from ..cameras import Cameras
from ..fragments import Fragments

__all__ = ["visibility_backward", "MAX_SLOPE"]

# Grazing tangent planes are clamped to this slope: |z_plane - z| <= MAX_SLOPE * (pixel distance) * z / f.
MAX_SLOPE = 3.0


def _plane_depth(pl, px, py, z, u, v, f):
    """Depth of each point's tangent plane at pixel (px, py) (the C++ kernel's vis_state, dss/csrc/visibility_backward_cpu.h)."""
    iz = pl[:, 0] * px + pl[:, 1] * py + pl[:, 2]
    zp = torch.where(iz > 0, 1.0 / torch.where(iz > 0, iz, torch.ones_like(iz)), z)
    dmax = MAX_SLOPE * torch.sqrt((px - u) ** 2 + (py - v) ** 2) * z / f
    return torch.minimum(torch.maximum(zp, z - dmax), z + dmax)


def visibility_backward(packed: torch.Tensor, attrs: torch.Tensor, frags: Fragments, images: torch.Tensor,
                        grad: torch.Tensor, cameras: Cameras, background: torch.Tensor, window: int = 4,
                        stride: int = 1, cutoff: float = 1.0, eps: float = 1e-5, mode: str = "dss",
                        planes: torch.Tensor | None = None) -> torch.Tensor:
    """dL/dp (N, 3) in world coordinates from the visibility term alone.

    Args:
        packed: (V, N, 10) splats; attrs: (V, N, C); frags: the forward cache; images: (V, H, W, C)
        rendered; grad: dL/dimages (V, H, W, C); background: (C,).
        planes: (V, N, 3) inverse-depth planes of :func:`dss.reference.tangent_planes`; None: the
            centre depth at every pixel.
    """
    V, N, _ = packed.shape
    _, H, W, K = frags.idx.shape
    C = attrs.shape[-1]
    merge = frags.merge_threshold
    dev = packed.device
    out = torch.zeros(N, 3, dtype=packed.dtype, device=dev)  # the splats' dtype (float64 renders too)
    off = torch.arange(-window, window + 1, stride, device=dev)
    oy, ox = torch.meshgrid(off, off, indexing="ij")
    oy, ox = oy.flatten(), ox.flatten()
    bg = background.to(dev, torch.float32).expand(C)
    for v in range(V):
        s = packed[v]
        ks = torch.nonzero(s[:, 9] > 0).flatten()
        if len(ks) == 0:
            continue
        sk = s[ks]
        u, vv, nk, z = sk[:, 0], sk[:, 1], sk[:, 5], sk[:, 6]
        f = cameras.focal[v]
        cx, cy = cameras.principal[v, 0], cameras.principal[v, 1]
        X = (u - cx) * z / f
        Y = (vv - cy) * z / f
        ii = torch.floor(vv).long()[:, None] + oy[None]
        jj = torch.floor(u).long()[:, None] + ox[None]
        kk = torch.arange(len(ks), device=dev)[:, None].expand_as(ii)
        inside = (ii >= 0) & (ii < H) & (jj >= 0) & (jj < W)
        ii, jj, kk = ii[inside], jj[inside], kk[inside]
        g = grad[v, ii, jj]
        nz = (g != 0).any(-1)
        ii, jj, kk, g = ii[nz], jj[nz], kk[nz], g[nz]
        if len(kk) == 0:
            continue
        pid = ks[kk]
        pi = frags.idx[v, ii, jj].long()
        pd = frags.depth[v, ii, jj]
        pr = frags.rho[v, ii, jj]
        valid = pi >= 0
        nvalid = valid.sum(-1)
        d0 = pd[:, 0]
        is_k = pi == pid[:, None]
        k_visible = (is_k & valid & (pd <= d0[:, None] + merge)).any(-1)
        rem = valid & ~is_k
        front_c = torch.where(rem, pd, torch.full_like(pd, float("inf"))).min(-1).values
        zc = z[kk]
        zk = zc if planes is None else _plane_depth(planes[v, ks][kk], jj.float() + 0.5, ii.float() + 0.5, zc,
                                                    u[kk], vv[kk], f)
        kase = torch.where(k_visible, 2, torch.where((nvalid == 0) | (zk <= d0 + merge), 0, 1))
        zf = torch.where(kase == 0, torch.minimum(zk, d0), d0)
        lim = torch.where(k_visible, front_c, zf)
        sel = rem & (pd <= lim[:, None] + merge)
        wts = torch.where(sel, pr, torch.zeros_like(pr))
        a_e = attrs[v][pi.clamp_min(0)]  # (M,K,C)
        num = (wts[..., None] * a_e).sum(1)
        den = wts.sum(1)
        add = (~k_visible).float()
        num = num + (add * nk[kk])[:, None] * attrs[v, pid]
        den = den + add * nk[kk]
        inew = torch.where((den > 0)[:, None], num / torch.where(den > 0, den, torch.ones_like(den))[:, None], bg)
        gd = (g * (inew - images[v, ii, jj])).sum(-1)
        px = jj.float() + 0.5
        py = ii.float() + 0.5
        acc = torch.zeros(len(kk), 3, dtype=packed.dtype, device=dev)
        if mode == "dss":
            use = gd < 0
            # (a)/(b): toward the back-projected pixel, at the point's depth or the front depth.
            zt = torch.where(kase == 1, d0, zk)
            m = torch.stack([(px - cx) * zt / f - X[kk], (py - cy) * zt / f - Y[kk], zt - zk], -1)
            coef = gd / ((m * m).sum(-1) + eps)
            inv = use & (kase != 2)
            acc = acc + torch.where(inv[:, None], coef[:, None] * m, torch.zeros_like(m))
            # (c): away to the near boundary and through to the far one, in the image plane.
            ddx, ddy = px - u[kk], py - vv[kk]
            sd = torch.sqrt(ddx * ddx + ddy * ddy)
            vis = use & (kase == 2) & (sd >= 1e-6)
            sds = torch.where(sd >= 1e-6, sd, torch.ones_like(sd))
            ux, uy = ddx / sds, ddy / sds
            sk_kk = sk[kk]
            qu = sk_kk[:, 2] * ux * ux + sk_kk[:, 3] * ux * uy + sk_kk[:, 4] * uy * uy
            r = torch.sqrt(2.0 * cutoff / qu.clamp_min(1e-20))
            for step in (-(r - sd).clamp_min(0), r + sd):
                mx = step * ux * zc / f
                my = step * uy * zc / f
                c2 = gd / (mx * mx + my * my + eps)
                mm = torch.stack([mx, my, torch.zeros_like(mx)], -1)
                acc = acc + torch.where(vis[:, None], c2[:, None] * mm, torch.zeros_like(mm))
        elif mode == "rbf":
            sk_kk = sk[kk]
            ddx, ddy = px - u[kk], py - vv[kk]
            q = sk_kk[:, 2] * ddx * ddx + sk_kk[:, 3] * ddx * ddy + sk_kk[:, 4] * ddy * ddy
            h = torch.exp(-0.5 * q)
            gu = h * (sk_kk[:, 2] * ddx + 0.5 * sk_kk[:, 3] * ddy)
            gv = h * (0.5 * sk_kk[:, 3] * ddx + sk_kk[:, 4] * ddy)
            c = torch.where(kase == 2, -gd, gd)
            Xk, Yk = X[kk], Y[kk]
            acc = torch.stack([c * f / zc * gu, c * f / zc * gv, c * (-f * Xk / (zc * zc) * gu - f * Yk / (zc * zc) * gv)], -1)
        else:
            raise ValueError(f"unknown gradient mode {mode!r}")
        acc_k = torch.zeros(len(ks), 3, dtype=acc.dtype, device=dev).index_add_(0, kk, acc)
        out.index_add_(0, ks, acc_k @ cameras.R[v])  # world = R^T acc  <=>  acc @ R
    return out
