"""``render``: the one functional entry point of the DSS renderer.

Stages (each usable on its own):
1. projection: points + normals -> screen-space EWA splats (:func:`dss.reference.project_splats`
   in torch; on ``cpp`` and ``cuda`` its kernel twin in both directions,
   :class:`dss.autograd.KernelProject`).
2. rasterisation (:func:`dss.rasterizer.rasterize`): splats -> per-pixel top-K cache
   (:class:`dss.fragments.Fragments`), and the image when no gradient is needed (``reference``:
   pure torch; ``cpp``: C++/OpenMP kernel; ``cuda``: tile-binned CUDA kernels, the same formulas).
3. shading (:func:`dss.shading.shade`): per-view point attributes w_k (torch; the sun lights run
   as a kernel on ``cpp`` and ``cuda``, :class:`dss.autograd.KernelSunShade`).
4. blending (Eq. sumI). With gradients enabled, ``reference`` recomputes the weights of the
   visible cached fragments with differentiable torch ops (:func:`dss.reference.blend`), so
   autograd supplies the smooth terms of Eqs. gradN and gradP (through w_k and rho_bar); ``cpp``
   and ``cuda`` compute those terms with the kernels' blend backward
   (:class:`dss.autograd.KernelBlend`). The visibility term of Eq. gradP for positions is added by
   a custom autograd function on every backend (:func:`dss.reference.visibility_backward` and its
   kernels).

The torch twins of the kernels are in :mod:`dss.reference`, the autograd Functions that run the
kernels in :mod:`dss.autograd`, the choice of backend in :mod:`dss.backends`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from . import reference
from .autograd import KernelBlend, KernelProject, KernelSunShade, PermuteRows, VisibilityGradient
from .backends import BACKENDS, kernels, resolve_backend
from .cameras import Cameras
from .fragments import Fragments
from .ordering import SORT_MIN_POINTS, spatial_order
from .pointcloud import all_finite, bbox_diagonal
from .rasterizer import rasterize
from .shading import SunLights, shade
from .splats import Splats, auto_sigma

log = logging.getLogger(__name__)

__all__ = ["RenderSettings", "RenderOutput", "render", "resolve_backend", "BACKENDS"]


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
            "center", its centre depth at every pixel (see :func:`dss.reference.tangent_planes`).
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

    def seen(self, in_render_order: bool = False) -> torch.Tensor:
        """(V, N) bool: point k is among the visible entries (within the merge threshold of the
        front) of at least one pixel of view v. In the caller's point order, or with
        ``in_render_order`` in ``point_order``'s (for per-point reductions that permute back once)."""
        frags, splats, _ = self._sorted
        V, N = splats.packed.shape[:2]
        flat = frags.idx.long() + (torch.arange(V, device=frags.idx.device) * N)[:, None, None, None]
        seen = torch.zeros(V * N, dtype=torch.bool, device=flat.device)
        seen[flat[frags.visible]] = True
        seen = seen.view(V, N)
        if in_render_order or self.point_order is None:
            return seen
        caller = torch.empty_like(seen)
        caller[:, self.point_order] = seen  # sorted position j holds caller point point_order[j]
        return caller

    @property
    def fragments(self) -> Fragments:
        return self._in_caller_order()[0]

    @property
    def splats(self) -> Splats:
        return self._in_caller_order()[1]

    @property
    def attributes(self) -> torch.Tensor:
        return self._in_caller_order()[2]


def _shade(shading, points, normals, cameras: Cameras, colors, backend: str) -> torch.Tensor:
    """:func:`dss.shading.shade`, with the fused sun shader kernel on the ``cpp`` and ``cuda`` backends."""
    sun = SunLights() if isinstance(shading, str) and shading == "sun" else shading
    # the kernel takes no gradient to the cameras and one albedo value per point and channel
    if (backend not in ("cpp", "cuda") or not isinstance(sun, SunLights) or not sun.one_light_per_channel()
            or cameras.R.requires_grad or (colors is not None and colors.shape != (points.shape[0], 3))):
        return shade(shading, points, normals, cameras, colors)
    return KernelSunShade.apply(normals, colors, sun.world_directions(cameras, normals).float(), sun.ambient,
                                 backend)


def _tangent_planes(points, normals, cameras: Cameras, mode: str, backend: str) -> torch.Tensor:
    """:func:`dss.reference.tangent_planes` (V, N, 3) float32; on the ``cpp`` backend its C++ kernel
    (the same expressions, one pass: 3.2-4.0 -> 1.0-1.2 ms per 20K position step, 12 views, 2
    threads)."""
    if backend == "cpp" and mode in ("plane", "center"):
        return kernels(backend).tangent_planes_forward(points.detach(), normals.detach(), cameras.R.detach(),
                                                        cameras.t.detach(), cameras.focal.detach(),
                                                        cameras.principal.detach(), mode == "center")
    return reference.tangent_planes(points, normals, cameras, mode).float()


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
        points, normals = PermuteRows.apply(points, order), PermuteRows.apply(normals, order)
        colors = None if colors is None else PermuteRows.apply(colors, order)
        if sigma_t.ndim == 1 and sigma_t.numel() == order.numel():
            sigma_t = sigma_t.index_select(0, order)
    camera_grad = any(x.requires_grad for x in (cameras.R, cameras.t, cameras.focal, cameras.principal))
    if backend in ("cpp", "cuda") and not sigma_t.requires_grad and not camera_grad:
        # the fused projection kernel (same formulas as project_splats) and its hand-written backward
        splats = Splats(KernelProject.apply(points, normals, cameras.R, cameras.t, cameras.focal, cameras.principal,
                                             sigma_t.detach().reshape(-1), settings, backend))
    else:
        splats = reference.project_splats(points, normals, cameras, sigma_t, settings.cutoff, settings.backface_culling,
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
            images = KernelBlend.apply(splats.packed, attrs, vis_points, images.float(), mask, frags_t, cam_t, bg,
                                        opts)
        else:
            images, mask = reference.blend(frags, splats, attrs, bg)
            if vis_points.requires_grad:
                images = VisibilityGradient.apply(images, vis_points, splats.packed.detach().contiguous(),
                                                   attrs.detach().contiguous(), frags_t, cam_t, bg, opts)
    if order is not None:
        sigma_t = sigma_caller
    return RenderOutput(images, mask, frags, splats, attrs, sigma_t, point_order=order)
