"""``render``: the one functional entry point of the DSS renderer.

Stages (each usable on its own):
1. :func:`dss.splats.project_splats` — points + normals -> screen-space EWA splats (torch; the
   ``cpp`` and ``cuda`` backends run its kernel twin in both directions, :class:`_KernelProject`).
2. a rasteriser backend — splats -> per-pixel top-K cache (:class:`Fragments`), and the image
   when no gradient is needed (``reference``: pure torch; ``cpp``: C++/OpenMP kernel; ``cuda``:
   tile-binned CUDA kernels, the same formulas).
3. :func:`dss.shading.shade` — per-view point attributes w_k (torch; the sun lights run as a
   kernel on ``cpp`` and ``cuda``, :class:`_KernelSunShade`).
4. blending (Eq. sumI). With gradients enabled, ``reference`` recomputes the weights of the
   visible cached fragments with differentiable torch ops, so autograd supplies the smooth terms
   of Eqs. gradN and gradP (through w_k and rho_bar); ``cpp`` and ``cuda`` compute those terms
   with the kernels' blend backward (:class:`_KernelBlend`). The visibility term of Eq. gradP for
   positions is added by a custom autograd function on every backend (:mod:`dss.visibility`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from . import _ext, _ext_cuda
from .cameras import Cameras
from .ordering import SORT_MIN_POINTS, spatial_order
from .pointcloud import all_finite, bbox_diagonal
from .rasterizer import reference as ref_raster
from .rasterizer.fragments import Fragments
from .shading import SunLights, shade
from .splats import Splats, auto_sigma, project_splats, tangent_planes
from .visibility import visibility_grad_reference

log = logging.getLogger(__name__)

__all__ = ["RenderSettings", "RenderOutput", "render", "resolve_backend", "rasterize", "BACKENDS"]

BACKENDS = ("auto", "cpp", "cuda", "reference")


@dataclass
class RenderSettings:
    """Renderer settings (paper section "Forward pass" and Appendix "Parameter discussion").

    Attributes:
        K: cached splats per pixel (paper: 5; at most 8).
        cutoff: C; a splat covers pixels with 1/2 d^T Sigma^-1 d <= C (radius ~ sqrt(2C) std).
        merge_threshold: T in world units; None -> ``merge_fraction`` x bounding-box diagonal.
        merge_fraction: T relative to the bbox diagonal of the rendered points (paper: 1%).
        sigma: object-space splat std: a number (world units) or "auto" (per point, ``sigma_scale``
            x mean distance to the ``sigma_k`` nearest neighbours).
        filter_variance: variance (pixels^2) of the screen-space low-pass filter (paper: 1). It
            widens every splat, silhouettes included, by about sqrt(2 C filter_variance) pixels.
        backface_culling: drop splats facing away from the camera (paper: on).
        znear: near plane (camera units).
        background: value of empty pixels (scalar or per channel).
        gradient: "dss" (the paper's visibility gradient), "rbf" (smooth Gaussian derivative, for
            comparisons only) or "none" (smooth terms only).
        window: half size (pixels) of the screen window around each point whose pixels feed the
            visibility gradient; ``window_stride`` > 1 samples it sparsely (long range, cheaper).
        epsilon: the paper's epsilon in Eq. gradcase (world units squared).
        occlusion_depth: the depth a point is compared at in the visibility gradient's occlusion
            test, cases (a)/(b): "plane" (default), the depth of its tangent plane at the pixel;
            "center", its centre depth at every pixel (see :func:`dss.splats.tangent_planes`).
        spatial_sort: render a Morton-sorted copy of the points (memory locality in the kernels,
            :mod:`dss.ordering`) and return everything in the caller's order. Results are the same
            up to the order of depth ties and float summation order.
    """

    K: int = 5
    cutoff: float = 1.0
    merge_threshold: float | None = None
    merge_fraction: float = 0.01
    sigma: float | str = "auto"
    sigma_k: int = 8
    sigma_scale: float = 1.0
    filter_variance: float = 1.0
    backface_culling: bool = True
    znear: float = 1e-3
    background: float | tuple = 0.0
    gradient: str = "dss"
    window: int = 4
    window_stride: int = 1
    epsilon: float = 1e-5
    occlusion_depth: str = "plane"
    spatial_sort: bool = True

    def __post_init__(self):
        if not 1 <= self.K <= 8:
            raise ValueError(f"K must be in [1, 8], got {self.K}")
        if self.filter_variance <= 0:
            raise ValueError(f"filter_variance must be > 0, got {self.filter_variance}")
        if self.cutoff <= 0:
            raise ValueError(f"cutoff must be > 0, got {self.cutoff}")
        if self.gradient not in ("dss", "rbf", "none"):
            raise ValueError(f"gradient must be 'dss', 'rbf' or 'none', got {self.gradient!r}")
        if self.occlusion_depth not in ("plane", "center"):
            raise ValueError(f"occlusion_depth must be 'plane' or 'center', got {self.occlusion_depth!r}")
        if self.window < 0 or self.window_stride < 1:
            raise ValueError("window must be >= 0 and window_stride >= 1")
        if isinstance(self.sigma, str) and self.sigma != "auto":
            raise ValueError(f"sigma must be a number or 'auto', got {self.sigma!r}")


class RenderOutput:
    """Result of :func:`render`.

    Attributes:
        images: (V, H, W, C) float32. When it carries a gradient on the ``cpp`` and ``cuda``
            backends, the backward reads it: autograd refuses an in-place edit (clone it first).
        mask: (V, H, W) bool, pixels where a splat is visible.
        fragments: the per-pixel top-K cache (index, weight, depth); indices in the caller's order.
        splats: the screen-space splats (packed (V, N, 10)), in the caller's point order.
        attributes: (V, N, C) per-view point attributes that were blended.
        sigma: (N,) or scalar splat std used.
        point_order: the (N,) permutation the kernels rendered in (``settings.spatial_sort``), or
            None. ``fragments``, ``splats`` and ``attributes`` are mapped back to the caller's
            order on first access (the optimiser's image loss never pays for it).
    """

    def __init__(self, images: torch.Tensor, mask: torch.Tensor, fragments: Fragments, splats: Splats,
                 attributes: torch.Tensor, sigma: torch.Tensor, extras: dict | None = None,
                 point_order: torch.Tensor | None = None):
        self.images, self.mask, self.sigma = images, mask, sigma
        self.extras = {} if extras is None else extras
        self.point_order = point_order
        self._sorted = (fragments, splats, attributes)
        self._caller: tuple | None = None if point_order is not None else self._sorted

    def _in_caller_order(self) -> tuple:
        if self._caller is None:
            frags, splats, attrs = self._sorted
            order = self.point_order
            inv = torch.empty_like(order)
            inv[order] = torch.arange(order.numel(), device=order.device)
            idx = frags.idx
            idx = torch.where(idx >= 0, order.to(idx.dtype)[idx.clamp_min(0).long()], idx)
            self._caller = (Fragments(idx, frags.depth, frags.rho, frags.merge_threshold),
                            Splats(splats.packed[:, inv]), attrs[:, inv])
        return self._caller

    @property
    def in_render_order(self) -> tuple:
        """(fragments, splats, attributes) in the order the kernels rendered in (``point_order``;
        the caller's order when it is None): for per-point reductions that permute back once."""
        return self._sorted

    @property
    def fragments(self) -> Fragments:
        return self._in_caller_order()[0]

    @property
    def splats(self) -> Splats:
        return self._in_caller_order()[1]

    @property
    def attributes(self) -> torch.Tensor:
        return self._in_caller_order()[2]


class _PermuteRows(torch.autograd.Function):
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


def resolve_backend(backend: str, device: torch.device | None = None) -> str:
    """Pick a concrete backend: "auto" -> the fastest available for ``device``."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")
    if device is not None and device.type == "cuda":
        if backend == "cpp":
            raise ValueError("backend 'cpp' runs on CPU tensors only")
        if backend == "auto":
            return "cuda" if _ext_cuda.cuda_available() else "reference"
        if backend == "cuda" and not _ext_cuda.cuda_available():
            raise RuntimeError(f"the CUDA backend is not available: {_ext_cuda.build_error()}")
        return backend
    if backend == "cuda":
        raise ValueError("backend 'cuda' needs CUDA tensors (move points, normals and cameras to the GPU)")
    if device is not None and device.type != "cpu":
        if backend == "cpp":
            raise ValueError("backend 'cpp' runs on CPU tensors only")
        return "reference"
    if backend == "auto":
        return "cpp" if _ext.cpu_available() else "reference"
    if backend == "cpp" and not _ext.cpu_available():
        raise RuntimeError(f"the C++ backend is not available: {_ext.build_error()}")
    return backend


def _kernels(backend: str):
    """The compiled module of a kernel backend ("cpp" or "cuda"); same function names."""
    return _ext.load_cpu() if backend == "cpp" else _ext_cuda.load_cuda()


def rasterize(splats: Splats, image_size, K: int, cutoff: float, merge_threshold: float, backend: str,
              attributes: torch.Tensor | None = None, background: torch.Tensor | None = None):
    """Stage 2: top-K cache, plus the blended image/mask when ``attributes`` is given."""
    packed = splats.packed.detach()
    H, W = image_size
    if backend in ("cpp", "cuda"):
        mod = _kernels(backend)
        dev = packed.device
        attrs = attributes.detach().float() if attributes is not None else torch.empty(0, device=dev)
        bg = background if background is not None else torch.zeros(attrs.shape[-1] if attrs.numel() else 0, device=dev)
        idx, depth, rho, images, mask = mod.rasterize_forward(packed.float(), attrs, H, W, K, float(cutoff), float(merge_threshold), bg.float())
        frags = Fragments(idx, depth, rho, float(merge_threshold))
        return frags, (images if attributes is not None else None), mask
    frags = ref_raster.rasterize(splats, image_size, K, cutoff, merge_threshold)
    if attributes is None:
        return frags, None, frags.visible.any(-1) & (torch.where(frags.visible, frags.rho, 0).sum(-1) > 0)
    images, mask = ref_raster.blend(frags, attributes.detach(), background)
    return frags, images, mask


def _blend_differentiable(frags: Fragments, splats: Splats, attributes: torch.Tensor, background: torch.Tensor):
    """Eq. sumI over the visible cached fragments with rho_bar recomputed in torch (autograd)."""
    V, H, W, K = frags.idx.shape
    C = attributes.shape[-1]
    vis = frags.visible
    v_i, i_i, j_i, _ = torch.nonzero(vis, as_tuple=True)
    pts = frags.idx[vis].long()
    pk = splats.packed[v_i, pts]
    _, rho = ref_raster.splat_weight(pk, j_i.float() + 0.5, i_i.float() + 0.5)
    a = attributes[v_i, pts]
    flat = (v_i * H + i_i) * W + j_i
    num = torch.zeros(V * H * W, C, dtype=attributes.dtype, device=attributes.device).index_add(0, flat, rho[:, None] * a)
    den = torch.zeros(V * H * W, dtype=rho.dtype, device=rho.device).index_add(0, flat, rho)
    mask = den > 0
    img = torch.where(mask[:, None], num / torch.where(mask, den, torch.ones_like(den))[:, None], background.expand(C))
    return img.view(V, H, W, C), mask.view(V, H, W)


def _visibility_grad(o: dict, packed, attrs, idx, depth, rho, images, grad, R, t, focal, principal, background):
    """Visibility term of dL/dp (N, 3) with the chosen backend."""
    if o["backend"] in ("cpp", "cuda"):
        return _kernels(o["backend"]).visibility_backward(
            packed, attrs, idx, depth, rho, images, grad, R, focal, principal, background, o["planes"],
            o["window"], o["stride"], o["cutoff"], o["merge"], o["eps"], 0 if o["mode"] == "dss" else 1)
    frags = Fragments(idx, depth, rho, o["merge"])
    cams = Cameras(R, t, focal, principal, o["image_size"])
    return visibility_grad_reference(packed, attrs, frags, images, grad, cams, background,
                                     o["window"], o["stride"], o["cutoff"], o["eps"], o["mode"], planes=o["planes"])


class _VisibilityGradient(torch.autograd.Function):
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
            grad_points = _visibility_grad(ctx.opts, packed, attrs, idx, depth, rho, images, grad.contiguous(),
                                           R, t, focal, principal, background).to(grad.dtype)
        return grad, grad_points, None, None, None, None, None, None


class _KernelBlend(torch.autograd.Function):
    """Eq. sumI with the C++ or CUDA kernels in both directions (``opts["backend"]``).

    forward: the image the rasteriser already blended. backward: the smooth terms (through
    rho_bar into the packed splat parameters, and through w_k into the attributes) from
    ``blend_backward``, plus the visibility term for the points from ``visibility_backward``
    (when ``opts["mode"]`` is not "none"). Autograd then carries dL/dpacked and dL/dattrs back
    through :func:`project_splats` and the shader in torch.
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
            g_packed, g_attrs = _kernels(o["backend"]).blend_backward(packed, attrs, idx, depth, rho, images, grad,
                                                                       o["merge"], *mask_arg)
        if ctx.needs_input_grad[2] and o["mode"] != "none":
            g_points = _visibility_grad(o, packed, attrs, idx, depth, rho, images, grad, R, t, focal, principal, background)
        return g_packed, g_attrs, g_points, None, None, None, None, None, None


class _KernelProject(torch.autograd.Function):
    """:func:`dss.splats.project_splats` with the C++ or CUDA kernels in both directions.

    forward: ``project_splats_forward``; backward: ``project_splats_backward`` gives dL/dpoints and
    dL/dnormals from dL/dpacked (sigma and cameras fixed; render() uses the torch version when
    they require grad). One pass over (view, point) each way instead of ~60 torch operators on
    (V, N) tensors and their autograd graph (20K points, 12 views, 2 threads: 30 -> ~8 ms per step;
    on a GPU, ~200 kernel launches fewer per step). Both kernels compile dss/csrc/splat_math.h.
    """

    @staticmethod
    def forward(ctx, points, normals, R, t, focal, principal, sigma, settings, backend):
        mod = _kernels(backend)
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
        gp, gn = _kernels(ctx.backend).project_splats_backward(points, normals, R, t, focal, principal, sigma, packed,
                                                               grad.contiguous().float(), float(s.cutoff),
                                                               float(s.filter_variance))
        return (gp.to(points.dtype) if ctx.needs_input_grad[0] else None,
                gn.to(normals.dtype) if ctx.needs_input_grad[1] else None, None, None, None, None, None, None, None)


class _KernelSunShade(torch.autograd.Function):
    """:class:`dss.shading.SunLights` (one light per channel) with the C++ or CUDA kernels both ways.

    forward: ``sun_shade_forward`` writes the (V, N, 3) attributes the other kernels read,
    contiguous; backward: ``sun_shade_backward`` gives dL/dnormals and dL/dalbedo. Replaces the
    torch version's product, clamp, permute and copy and their autograd graph (at 20K points, 12
    views, 2 threads, ~5 ms per step forward + backward in torch, ~0.6 ms in the kernels).
    """

    @staticmethod
    def forward(ctx, normals, albedo, dirs, ambient, backend):
        alb = albedo.detach() if albedo is not None else normals.new_empty(0)
        out = _kernels(backend).sun_shade_forward(normals.detach(), alb, dirs, float(ambient))
        ctx.save_for_backward(normals.detach(), alb, dirs)
        ctx.ambient, ctx.backend = float(ambient), backend
        return out

    @staticmethod
    def backward(ctx, grad):
        normals, alb, dirs = ctx.saved_tensors
        need_n, need_a = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if not (need_n or need_a):
            return None, None, None, None, None
        gn, ga = _kernels(ctx.backend).sun_shade_backward(normals, alb, dirs, ctx.ambient, grad.contiguous().float(),
                                                          bool(need_a))
        return (gn.to(normals.dtype) if need_n else None, ga.to(alb.dtype) if need_a else None, None, None, None)


def _shade(shading, points, normals, cameras: Cameras, colors, backend: str) -> torch.Tensor:
    """:func:`dss.shading.shade`, with the fused sun shader kernel on the ``cpp`` and ``cuda`` backends."""
    sun = SunLights() if isinstance(shading, str) and shading == "sun" else shading
    # the kernel takes no gradient to the cameras and one albedo value per point and channel
    if (backend not in ("cpp", "cuda") or not isinstance(sun, SunLights) or not sun.one_light_per_channel()
            or cameras.R.requires_grad or (colors is not None and colors.shape != (points.shape[0], 3))):
        return shade(shading, points, normals, cameras, colors)
    return _KernelSunShade.apply(normals, colors, sun.world_directions(cameras, normals).float(), sun.ambient,
                                 backend)


def _tangent_planes(points, normals, cameras: Cameras, mode: str, backend: str) -> torch.Tensor:
    """:func:`dss.splats.tangent_planes` (V, N, 3) float32; on the ``cpp`` backend its C++ kernel
    (the same expressions, one pass: 3.2-4.0 -> 1.0-1.2 ms per 20K position step, 12 views, 2
    threads)."""
    if backend == "cpp" and mode in ("plane", "center"):
        return _kernels(backend).tangent_planes_forward(points.detach(), normals.detach(), cameras.R.detach(),
                                                        cameras.t.detach(), cameras.focal.detach(),
                                                        cameras.principal.detach(), mode == "center")
    return tangent_planes(points, normals, cameras, mode).float()


def _check_inputs(points: torch.Tensor, normals: torch.Tensor, cameras: Cameras):
    if not isinstance(points, torch.Tensor) or points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be a (N, 3) tensor, got {getattr(points, 'shape', type(points))}")
    if points.shape[0] == 0:
        raise ValueError("cannot render an empty point cloud")
    if normals is None or normals.shape != points.shape:
        raise ValueError(f"normals must be (N, 3) like points; got {None if normals is None else tuple(normals.shape)}")
    if not isinstance(cameras, Cameras):
        raise TypeError("cameras must be a dss.cameras.Cameras")
    if points.device != normals.device or points.device != cameras.R.device:
        raise ValueError(f"points ({points.device}), normals ({normals.device}) and cameras ({cameras.R.device}) must be "
                         "on one device (cameras.to(points.device))")
    if not all_finite(points, normals):
        raise ValueError("points/normals contain NaN or inf; drop those rows first (dss.pointcloud.finite_rows)")
    if not (points.is_floating_point() and normals.is_floating_point() and cameras.R.is_floating_point()):
        raise ValueError(f"points ({points.dtype}), normals ({normals.dtype}) and cameras ({cameras.R.dtype}) "
                         "must be floating-point tensors")


def render(points: torch.Tensor, normals: torch.Tensor, cameras: Cameras, settings: RenderSettings | None = None,
           shading="sun", colors: torch.Tensor | None = None, backend: str = "auto",
           sigma: torch.Tensor | float | None = None) -> RenderOutput:
    """Render N oriented points from V cameras with differentiable EWA surface splatting.

    Args:
        points: (N, 3) world positions (float32; may require grad).
        normals: (N, 3) normals (may require grad; need not be unit length).
        cameras: V :class:`Cameras`; all images are ``cameras.image_size`` = (H, W).
        settings: :class:`RenderSettings` (defaults follow the paper).
        shading: "sun" (default), "albedo", "normals", "depth", "mask", or a callable such as
            :class:`dss.shading.PointLight` (see :func:`dss.shading.shade`).
        colors: (N, 3) per-point albedo (may require grad).
        backend: "auto", "cpp", "cuda" (CUDA tensors) or "reference".
        sigma: overrides ``settings.sigma`` with a scalar or an (N,) tensor.

    Returns:
        :class:`RenderOutput` with images (V, H, W, C) and mask (V, H, W).
    """
    settings = settings or RenderSettings()
    _check_inputs(points, normals, cameras)
    # one dtype throughout, the cameras' (e.g. float64 points from numpy with float32 cameras);
    # autograd hands the gradients back in the caller's dtype
    points, normals = points.to(cameras.R.dtype), normals.to(cameras.R.dtype)
    backend = resolve_backend(backend, points.device)
    if sigma is None:
        sigma = auto_sigma(points.detach(), settings.sigma_k, settings.sigma_scale) if settings.sigma == "auto" else float(settings.sigma)
    sigma_t = torch.as_tensor(sigma, dtype=points.dtype, device=points.device)
    merge = settings.merge_threshold
    if merge is None:
        merge = settings.merge_fraction * max(bbox_diagonal(points.detach()), 1e-12)
    order = None
    if settings.spatial_sort and points.shape[0] >= SORT_MIN_POINTS:
        order = spatial_order(points)
        sigma_caller = sigma_t
        points, normals = _PermuteRows.apply(points, order), _PermuteRows.apply(normals, order)
        colors = None if colors is None else _PermuteRows.apply(colors, order)
        if sigma_t.ndim == 1 and sigma_t.numel() == order.numel():
            sigma_t = sigma_t.index_select(0, order)
    camera_grad = any(x.requires_grad for x in (cameras.R, cameras.t, cameras.focal, cameras.principal))
    if backend in ("cpp", "cuda") and not sigma_t.requires_grad and not camera_grad:
        # the fused projection kernel (same formulas as project_splats) and its hand-written backward
        splats = Splats(_KernelProject.apply(points, normals, cameras.R, cameras.t, cameras.focal, cameras.principal,
                                             sigma_t.detach().reshape(-1), settings, backend))
    else:
        splats = project_splats(points, normals, cameras, sigma_t, settings.cutoff, settings.backface_culling,
                                settings.znear, settings.filter_variance)
    attrs = _shade(shading, points, normals, cameras, colors, backend)
    if backend in ("cpp", "cuda"):
        # one copy here (a torch shader's attributes can be a permuted or expanded view; the
        # kernels' sun shader's are contiguous already) instead of one in every kernel that reads
        # them (rasteriser, blend and visibility backward)
        attrs = attrs.float().contiguous()
    C = attrs.shape[-1]
    bg = torch.as_tensor(settings.background, dtype=torch.float32, device=points.device).flatten()
    if bg.numel() not in (1, C):
        raise ValueError(f"background has {bg.numel()} values, the shading has {C} channels")
    bg = bg.expand(C).contiguous()

    needs_grad = torch.is_grad_enabled() and (splats.packed.requires_grad or attrs.requires_grad)
    frags, images, mask = rasterize(splats, cameras.image_size, settings.K, settings.cutoff, merge, backend,
                                    attributes=attrs, background=bg)
    if needs_grad:
        opts = dict(backend=backend, window=int(settings.window), stride=int(settings.window_stride),
                    cutoff=float(settings.cutoff), merge=float(merge), eps=float(settings.epsilon),
                    mode=settings.gradient, image_size=cameras.image_size)
        frags_t = (frags.idx, frags.depth, frags.rho)
        cam_t = (cameras.R, cameras.t, cameras.focal, cameras.principal)
        vis_points = points if (settings.gradient != "none" and points.requires_grad) else points.detach()
        opts["planes"] = (_tangent_planes(points, normals, cameras, settings.occlusion_depth, backend)
                          if vis_points.requires_grad else None)
        if backend in ("cpp", "cuda"):
            images = _KernelBlend.apply(splats.packed, attrs, vis_points, images.float(), mask, frags_t, cam_t, bg,
                                        opts)
        else:
            images, mask = _blend_differentiable(frags, splats, attrs, bg)
            if vis_points.requires_grad:
                images = _VisibilityGradient.apply(images, vis_points, splats.packed.detach().contiguous(),
                                                   attrs.detach().contiguous(), frags_t, cam_t, bg, opts)
    if order is not None:
        sigma_t = sigma_caller
    return RenderOutput(images, mask, frags, splats, attrs, sigma_t, point_order=order)
