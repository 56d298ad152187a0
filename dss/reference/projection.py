"""Stage 1 of rendering in torch: oriented points -> screen-space EWA splats (paper Eqs. rk, filter).

The twin of the kernels' ``project_splats_forward`` (its autograd gives ``project_splats_backward``)
and ``tangent_planes_forward``; ``render()`` runs it on the ``reference`` backend and wherever the
splat sizes or the cameras take a gradient.

For a point ``p_k`` with normal ``n_k`` and a camera, the Jacobian ``J_k`` of the projection
restricted to the tangent plane maps the isotropic object-space Gaussian ``V_k = sigma_k^2 I`` to
the screen-space covariance ``J_k V_k J_k^T``; the low-pass filter adds ``I`` (one pixel^2):

    Sigma_k = sigma_k^2 J_k J_k^T + I,
    rho_bar_k(x) = |det J_k| / (2 pi sqrt(det Sigma_k)) * exp(-1/2 (x - x_k)^T Sigma_k^-1 (x - x_k)).

We never build a tangent basis: with ``M`` the (2, 3) derivative of the pinhole projection in
camera space and ``P = I - n n^T`` the projector onto the tangent plane, ``J J^T = M P M^T`` and
``|det J| = |(m1 x m2) . n| = f^2 |n . p_cam| / Z^3`` for any orthonormal tangent basis. This is smooth in ``n`` (the
normal gradients of Eq. gradN flow through it) and stays finite for edge-on splats, whose weight
simply goes to zero.

Everything here is plain differentiable torch; the rasterisers consume the packed result
(:class:`dss.splats.Splats`).
"""

from __future__ import annotations

import math

import torch

from ..cameras import Cameras
from ..splats import Splats

__all__ = ["project_splats", "tangent_planes"]


def project_splats(points: torch.Tensor, normals: torch.Tensor, cameras: Cameras, sigma: torch.Tensor | float,
                   cutoff: float = 1.0, backface_culling: bool = True, znear: float = 1e-3,
                   filter_variance: float = 1.0) -> Splats:
    """Screen-space EWA splats.

    Args:
        points: (N, 3) world positions.
        normals: (N, 3) normals (need not be unit length; zero normals give zero weight).
        cameras: V cameras.
        sigma: object-space standard deviation sigma_k, a scalar or (N,) (world units).
        cutoff: C; the splat covers pixels with 1/2 d^T Sigma^-1 d <= C.
        backface_culling: drop splats whose normal points away from the camera.
        znear: drop splats closer than this depth (camera units).
        filter_variance: variance (pixels^2) of the screen-space low-pass filter (paper: 1, i.e. I).
            Must be > 0: it keeps edge-on splats finite.

    Returns:
        :class:`Splats` with a packed (V, N, 10) tensor, differentiable in points and normals.
    """
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points and normals must both be (N, 3); got {tuple(points.shape)} and {tuple(normals.shape)}")
    pc = cameras.world_to_camera(points)  # (V,N,3)
    X, Y, Z = pc.unbind(-1)
    Zs = torch.where(Z > znear, Z, torch.full_like(Z, 1.0))  # keep culled splats finite
    f = cameras.focal[:, None]
    cx = cameras.principal[:, None, 0]
    cy = cameras.principal[:, None, 1]
    u = f * X / Zs + cx
    v = f * Y / Zs + cy

    n_cam = torch.einsum("vij,nj->vni", cameras.R, normals)
    n_len2 = (n_cam * n_cam).sum(-1, keepdim=True)
    n_hat = n_cam / torch.sqrt(n_len2 + 1e-20)
    # Rows of M (projection derivative, camera space): m1 = f (1/Z, 0, -X/Z^2), m2 = f (0, 1/Z, -Y/Z^2).
    zero = torch.zeros_like(Zs)
    m1 = torch.stack([f / Zs, zero, -f * X / Zs**2], -1)
    m2 = torch.stack([zero, f / Zs, -f * Y / Zs**2], -1)
    # M P M^T with P = I - n n^T: entries m_i.m_j - (m_i.n)(m_j.n)
    m1n = (m1 * n_hat).sum(-1)
    m2n = (m2 * n_hat).sum(-1)
    A11 = (m1 * m1).sum(-1) - m1n * m1n
    A12 = (m1 * m2).sum(-1) - m1n * m2n
    A22 = (m2 * m2).sum(-1) - m2n * m2n
    # |det J| = |(m1 x m2) . n| = f^2 |n . p_cam| / Z^3 (foreshortening): exact, no cancellation
    # (A11 A22 - A12^2 loses all its digits in float32 for near edge-on splats).
    det_J = f * f * (n_hat * torch.stack([X, Y, Zs], -1)).sum(-1).abs() / (Zs * Zs * Zs)
    det_A = det_J * det_J

    if filter_variance <= 0:
        raise ValueError(f"filter_variance must be > 0, got {filter_variance}")
    s2 = torch.as_tensor(sigma, dtype=points.dtype, device=points.device)
    s2 = (s2 * s2).expand(points.shape[0])[None]
    S11 = s2 * A11 + filter_variance
    S12 = s2 * A12
    S22 = s2 * A22 + filter_variance
    # det(s2 A + f I) = s2^2 det A + s2 f tr A + f^2: a sum of non-negative terms, free of the
    # cancellation that S11 S22 - S12^2 suffers in float32 for splats close to the camera.
    det_S = s2 * s2 * det_A + s2 * filter_variance * (A11 + A22) + filter_variance * filter_variance
    conic_a = S22 / det_S
    conic_b2 = -2.0 * S12 / det_S
    conic_c = S11 / det_S
    norm = det_J / (2 * math.pi * torch.sqrt(det_S))
    rx = torch.sqrt(2.0 * cutoff * S11)
    ry = torch.sqrt(2.0 * cutoff * S22)

    valid = Z > znear
    if backface_culling:
        valid = valid & ((n_cam * pc).sum(-1) < 0)
    packed = torch.stack([u, v, conic_a, conic_b2, conic_c, norm, Z, rx, ry, valid.to(points.dtype)], -1)
    return Splats(packed)


def tangent_planes(points: torch.Tensor, normals: torch.Tensor, cameras: Cameras, mode: str = "plane") -> torch.Tensor:
    """Inverse-depth planes (V, N, 3) for the backward pass's occlusion test.

    For each point and view, coefficients (A, B, C) with ``1 / z = A px + B py + C`` at pixel
    centre (px, py): the depth the point's splat would have at that pixel, on its tangent plane
    (for a plane, inverse depth is affine in screen space). ``mode="center"`` returns (0, 0, 1/z_k),
    the centre depth at every pixel (the paper's text read literally). Why the plane: on a curved
    surface, a point's centre depth differs from the surface depth a few pixels away by the slope
    times the distance, so with centre depths the visibility gradient treats a point on the same
    surface as occluded (case (b)) and pulls it toward the camera; summed over views, a convex
    shape inflates instead of shrinking to a smaller target (measured in tests/test_optimize.py).
    Planes through the camera centre (n . p = 0) fall back to the centre depth.
    """
    pc = cameras.world_to_camera(points.detach())  # (V,N,3)
    z = pc[..., 2]
    inv_z = torch.where(z > 0, 1.0 / z.clamp_min(1e-12), torch.zeros_like(z))
    zero = torch.zeros_like(z)
    if mode == "center":
        return torch.stack([zero, zero, inv_z], -1).contiguous()
    if mode != "plane":
        raise ValueError(f"occlusion depth mode must be 'plane' or 'center', got {mode!r}")
    n = torch.einsum("vij,nj->vni", cameras.R, normals.detach())
    c0 = (n * pc).sum(-1)  # n . p in the camera frame
    f = cameras.focal[:, None]
    cx, cy = cameras.principal[:, None, 0], cameras.principal[:, None, 1]
    ok = c0.abs() > 1e-12
    c0s = torch.where(ok, c0, torch.ones_like(c0))
    A = n[..., 0] / (f * c0s)
    B = n[..., 1] / (f * c0s)
    C = (n[..., 2] - n[..., 0] * cx / f - n[..., 1] * cy / f) / c0s
    planes = torch.stack([torch.where(ok, A, zero), torch.where(ok, B, zero), torch.where(ok, C, inv_z)], -1)
    return planes.float().contiguous()
