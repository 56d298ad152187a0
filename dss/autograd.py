"""Every custom autograd Function of dss: the compiled kernels in both directions.

The kernels are plain functions of tensors (dss/csrc, :mod:`dss.backends`); the Functions here
give them to autograd: each saves what its kernel's backward reads and calls it. Their torch
twins (:mod:`dss.reference`) get the same gradients from autograd, and the tests hold the two
together.

- :class:`KernelProject`: stage 1, ``project_splats_forward`` / ``_backward``.
- :class:`KernelSunShade`: the sun lights, ``sun_shade_forward`` / ``_backward``.
- :class:`KernelBlend`: Eq. sumI, the image the rasteriser blended; backward ``blend_backward``
  (smooth terms) and ``visibility_backward`` (the visibility term for the points).
- :class:`VisibilityGradient`: the visibility term on the ``reference`` backend, whose smooth
  terms come from autograd through :func:`dss.reference.blend`.
- :class:`PermuteRows`: the spatial sort's permutation with a scatter backward.
- :class:`NeighbourDiff`: the regularisers' ``neighbor_diff_forward`` / ``_backward``.
- :class:`FusedSmape`: the SMAPE loss's ``smape_sum``.
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from . import _ext, reference
from .backends import kernels
from .cameras import Cameras
from .fragments import Fragments

__all__ = ["KernelProject", "KernelSunShade", "KernelBlend", "VisibilityGradient", "PermuteRows", "NeighbourDiff",
           "FusedSmape", "visibility_grad"]


class PermuteRows(torch.autograd.Function):
    """``x[order]`` for a permutation ``order`` (N,); the backward scatters each row back once.

    Autograd's own backward of ``x[order]`` is an index_put with accumulation, which on a GPU
    sorts the indices first (two radix sorts and a dozen launches per tensor per step); a
    permutation hits every row exactly once, so a plain scatter gives the same values.
    """

    @staticmethod
    def forward(ctx, x, order):
        ctx.save_for_backward(order)
        # index_select, not x[order]: the same rows, ~3x faster on the CPU (26 against 82 us for
        # 20K x 3 on 2 threads: advanced indexing's general kernel)
        return x.index_select(0, order)

    @staticmethod
    def backward(ctx, grad):
        (order,) = ctx.saved_tensors
        return torch.empty_like(grad).index_copy_(0, order, grad), None


def visibility_grad(o: dict, packed, attrs, idx, depth, rho, images, grad, R, t, focal, principal, background):
    """Visibility term of dL/dp (N, 3) with the chosen backend."""
    if o["backend"] in ("cpp", "cuda"):
        return kernels(o["backend"]).visibility_backward(
            packed, attrs, idx, depth, rho, images, grad, R, focal, principal, background, o["planes"],
            o["window"], o["stride"], o["cutoff"], o["merge"], o["eps"], 0 if o["mode"] == "dss" else 1)
    frags = Fragments(idx, depth, rho, o["merge"])
    cams = Cameras(R, t, focal, principal, o["image_size"])
    return reference.visibility_backward(packed, attrs, frags, images, grad, cams, background,
                                         o["window"], o["stride"], o["cutoff"], o["eps"], o["mode"], planes=o["planes"])


class VisibilityGradient(torch.autograd.Function):
    """Identity on the images; in backward adds the visibility term of Eq. gradP to the points.

    Used with the reference backend, whose smooth terms come from torch autograd.
    """

    @staticmethod
    def forward(ctx, images, points, packed, attrs, frags_t, cam_t, background, opts):
        ctx.save_for_backward(packed, attrs, *frags_t, *cam_t, background, images.detach())
        ctx.opts = opts
        return images.view_as(images)

    @staticmethod
    def backward(ctx, grad):
        packed, attrs, idx, depth, rho, R, t, focal, principal, background, images = ctx.saved_tensors
        grad_points = None
        if ctx.needs_input_grad[1]:
            grad_points = visibility_grad(ctx.opts, packed, attrs, idx, depth, rho, images, grad.contiguous(),
                                          R, t, focal, principal, background).to(grad.dtype)
        return grad, grad_points, None, None, None, None, None, None


class KernelBlend(torch.autograd.Function):
    """Eq. sumI with the C++ or CUDA kernels in both directions (``opts["backend"]``).

    forward: the image the rasteriser already blended. backward: the smooth terms (through
    rho_bar into the packed splat parameters, and through w_k into the attributes) from
    ``blend_backward``, plus the visibility term for the points from ``visibility_backward``
    (when ``opts["mode"]`` is not "none"). Autograd then carries dL/dpacked and dL/dattrs back
    through :func:`dss.reference.project_splats` and the shader in torch.
    """

    @staticmethod
    def forward(ctx, packed, attrs, points, images, mask, frags_t, cam_t, background, opts):
        ctx.save_for_backward(packed.detach(), attrs.detach(), *frags_t, *cam_t, background, images, mask)
        ctx.opts = opts
        # A view, not a copy (a 9 MB copy per step at 12 views of 256x256, ~0.8 ms on 2 cores):
        # the backward reads the saved images, so an in-place edit of the output would change
        # what it reads; autograd refuses that edit (the view shares the saved tensor's version
        # counter), so a caller that wants to edit the image clones it first.
        return images.view_as(images)

    @staticmethod
    def backward(ctx, grad):
        packed, attrs, idx, depth, rho, R, t, focal, principal, background, images, mask = ctx.saved_tensors
        o = ctx.opts
        grad = grad.contiguous().float()
        g_packed = g_attrs = g_points = None
        if ctx.needs_input_grad[0] or ctx.needs_input_grad[1]:
            # the C++ kernel visits only the mask's pixels (9% of them at 20K points, 12 views of
            # 256x256) instead of reading every pixel's cache row; the CUDA one runs per point
            mask_arg = (mask,) if o["backend"] == "cpp" else ()
            g_packed, g_attrs = kernels(o["backend"]).blend_backward(packed, attrs, idx, depth, rho, images, grad,
                                                                     o["merge"], *mask_arg)
        if ctx.needs_input_grad[2] and o["mode"] != "none":
            g_points = visibility_grad(o, packed, attrs, idx, depth, rho, images, grad, R, t, focal, principal, background)
        return g_packed, g_attrs, g_points, None, None, None, None, None, None


class KernelProject(torch.autograd.Function):
    """:func:`dss.reference.project_splats` with the C++ or CUDA kernels in both directions.

    forward: ``project_splats_forward``; backward: ``project_splats_backward`` gives dL/dpoints and
    dL/dnormals from dL/dpacked (sigma and cameras fixed; render() uses the torch version when
    they require grad). One pass over (view, point) each way instead of ~60 torch operators on
    (V, N) tensors and their autograd graph (20K points, 12 views, 2 threads: 30 -> ~8 ms per step;
    on a GPU, ~200 kernel launches fewer per step). Both kernels compile dss/csrc/splat_math.h.
    """

    @staticmethod
    def forward(ctx, points, normals, R, t, focal, principal, sigma, settings, backend):
        mod = kernels(backend)
        packed = mod.project_splats_forward(
            points.detach(), normals.detach(), R, t, focal, principal, sigma, float(settings.cutoff),
            bool(settings.backface_culling), float(settings.znear), float(settings.filter_variance))
        ctx.save_for_backward(points.detach(), normals.detach(), R, t, focal, principal, sigma, packed)
        ctx.settings, ctx.backend = settings, backend
        return packed

    @staticmethod
    def backward(ctx, grad):
        points, normals, R, t, focal, principal, sigma, packed = ctx.saved_tensors
        s = ctx.settings
        gp, gn = kernels(ctx.backend).project_splats_backward(points, normals, R, t, focal, principal, sigma, packed,
                                                              grad.contiguous().float(), float(s.cutoff),
                                                              float(s.filter_variance))
        return (gp.to(points.dtype) if ctx.needs_input_grad[0] else None,
                gn.to(normals.dtype) if ctx.needs_input_grad[1] else None, None, None, None, None, None, None, None)


class KernelSunShade(torch.autograd.Function):
    """:class:`dss.shading.SunLights` (one light per channel) with the C++ or CUDA kernels both ways.

    forward: ``sun_shade_forward`` writes the (V, N, 3) attributes the other kernels read,
    contiguous; backward: ``sun_shade_backward`` gives dL/dnormals and dL/dalbedo. Replaces the
    torch version's product, clamp, permute and copy and their autograd graph (at 20K points, 12
    views, 2 threads, ~5 ms per step forward + backward in torch, ~0.6 ms in the kernels).
    """

    @staticmethod
    def forward(ctx, normals, albedo, dirs, ambient, backend):
        alb = albedo.detach() if albedo is not None else normals.new_empty(0)
        out = kernels(backend).sun_shade_forward(normals.detach(), alb, dirs, float(ambient))
        ctx.save_for_backward(normals.detach(), alb, dirs)
        ctx.ambient, ctx.backend = float(ambient), backend
        return out

    @staticmethod
    def backward(ctx, grad):
        normals, alb, dirs = ctx.saved_tensors
        need_n, need_a = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if not (need_n or need_a):
            return None, None, None, None, None
        gn, ga = kernels(ctx.backend).sun_shade_backward(normals, alb, dirs, ctx.ambient, grad.contiguous().float(),
                                                         bool(need_a))
        return (gn.to(normals.dtype) if need_n else None, ga.to(alb.dtype) if need_a else None, None, None, None)


class NeighbourDiff(torch.autograd.Function):
    """(N, 3) points -> (N, K, 3) ``(p_i - p_k) * valid`` with the C++ forward and backward (the
    backward is a scatter of the (N, K, 3) gradient onto both ends of each pair)."""

    @staticmethod
    def forward(ctx, points, idx, valid):
        ctx.save_for_backward(idx, valid)
        return _ext.load_cpu().neighbor_diff_forward(points.detach(), idx, valid)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        idx, valid = ctx.saved_tensors
        return _ext.load_cpu().neighbor_diff_backward(grad, idx, valid), None, None


class FusedSmape(torch.autograd.Function):
    """mean SMAPE through the C++ ``smape_sum`` (one pass for the value and its derivative).

    The torch expression in :func:`dss.losses.smape_loss` is the reference; this gives the same
    value and gradient to float rounding (tests/test_losses.py) in one pass over the images instead of
    ~12 elementwise operators and their autograd graph (12 views at 256x256, 2 threads: 21 -> ~4 ms).
    """

    @staticmethod
    def forward(ctx, pred, target, eps, scale):
        # the derivative comes back already times the mean's scale: no extra pass over it when
        # the loss is backpropagated alone (go == 1)
        total, grad = _ext.loaded_cpu().smape_sum(pred.detach(), target.detach(), float(eps), float(scale),
                                                  pred.requires_grad)
        ctx.save_for_backward(grad)
        return (total * scale).to(pred.dtype)

    @staticmethod
    def backward(ctx, go):
        (grad,) = ctx.saved_tensors
        if go.numel() == 1 and float(go) == 1.0:
            return grad, None, None, None
        return grad * go, None, None, None
