"""Multi-view shape-from-rendering (paper sections "Implementation details", "Results").

The optimiser moves points and normals until their renders match reference images from many
views. It is the engine of deformation (``dss-deform``), image-filter editing (``dss-filter``)
and denoising (``dss-denoise``); the caller supplies the reference as a function of the cameras.

Schedule (paper "Alternating normal and point update"): each cycle samples ``views`` cameras
(farthest-point sampling on a sphere with jitter), then makes ``normal_steps`` (T_n) steps on
the normals and ``point_steps`` (T_p) steps on the positions. During normal steps the positions
still move by the regulariser gradients alone. ``schedule="joint"`` updates both together.

Scale conventions. The paper gives learning rates 5 (points) and 5000 (normals) for its own
code's units, which it does not state. Ours: the image loss is averaged over all V x H x W x C
elements (``loss.mean()`` over the batch of renders), positions are in units where the
object's bounding-box diagonal is 1 (the apps normalise), images are about 256 x 256. In these
units the paper's rates overshoot (sphere -> teapot, 4K points, 128 px: with lr_scale 1 Chamfer
grows from 126 to 2026; 0.1 is the largest scale that converges), so the SGD step uses
``lr x lr_scale`` with ``lr_scale = 0.01`` by default (``dss-deform`` sets the point rate 10x
higher and controls it with ``bold_driver`` and ``lr_decay``): the configured
numbers stay the paper's, and their ratio (points : normals = 1 : 1000) is kept. SGD with
Nesterov momentum 0.9; normals are
renormalised to unit length after every step; the gradient of each position coordinate is
clipped to +-``clip_point_grad`` (0.01, the official implementation's default) so that a few
points with huge visibility gradients do not jump across the scene; normal gradients likewise to
+-``clip_normal_grad`` (the EWA weight's derivative is singular for edge-on splats, so pixels
covered only by grazing splats give unbounded normal gradients). Non-finite gradient entries
are zeroed.

Regulariser weights: with ``regularizer_weighting="relative"`` (default) the weights gamma_p
and gamma_r are what the paper's Appendix says they are for: the ratio of the mean per-point
gradient magnitude of L_p (L_r) to that of the image loss. Both magnitudes are measured once, at
the first step of the run, which fixes each term's multiplier; it then stays constant, so a term
shrinks as its residual does (re-measuring every step normalised the regularisers' magnitude:
the image gradient grows as the cloud drifts, a runaway feedback, and a smooth surface's tiny
projection residual was blown up until it scattered the points). This keeps the balance
independent of point count and scene scale (the absolute losses are not: L_r's 1e-4 is an
absolute squared length). ``"absolute"`` adds
gamma x L as in Eq. total_loss.

Large deformations (``dss-deform`` defaults, conf/deform.yaml): ``lr_decay`` multiplies the
learning rates after every cycle, and ``normal_refresh="pca"`` re-fits the normals to the points
(PCA over ``normal_refresh_k`` neighbours, signed to agree with the current normals) at the start
of every cycle. Both are additions to the paper's schedule, measured on sphere -> teapot: without
them the points approach the target but the normals stop matching the geometry and the renders
degrade after about five cycles. Local editing and denoising keep the defaults (off).

Divergence guard: a step that makes the loss or any parameter non-finite, or a finite
blow-up (the cloud's bounding-box diagonal beyond ``blowup_extent`` x its start, or the start's
camera sphere, whichever is larger; optionally the image loss beyond ``blowup_loss`` x the first
loss of its cycle, whose cameras and references it shares) is undone (the step; for the loss, the
cycle so far), the learning rates are halved, and a warning says so (``history["lr_halvings"]``,
``history["rejected"]``). After ``max_lr_halvings`` halvings the run cannot recover:
:class:`OptimizationDiverged` is raised, and no result exists to be written.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import torch

from .cameras import Cameras
from .gc_pause import frozen_gc
from .hull import fill_displacement, hull_displacement, nearest_covered
from .losses import l1_loss, smape_loss
from .orientation import orient_to_views
from .pointcloud import all_finite
from .regularizers import (
    ProjectionLoss,
    RegularizerConfig,
    RepulsionLoss,
    find_neighbors,
    project_to_neighbour_planes,
    pull_rim_strays,
    with_new_differences,
)
from .render import RenderOutput, RenderSettings, render
from .sgd import SGD
from .shading import shade
from .splats import auto_sigma
from .timing import StageClock
from .views import SphereViewSampler, error_aware_cameras

log = logging.getLogger(__name__)

__all__ = ["OptimizerConfig", "MultiViewOptimizer", "OptimizationResult", "OptimizationDiverged", "occlusion_counts",
           "window_for_cycle"]


def bound_displacement(points: torch.Tensor, start: torch.Tensor, radius: float) -> torch.Tensor:
    """``points`` (N, 3) with each displacement from ``start`` (N, 3) scaled back to at most
    ``radius`` (same units); unchanged where it is within."""
    d = points - start
    length = d.norm(dim=1, keepdim=True)
    return start + d * (float(radius) / length.clamp_min(1e-30)).clamp(max=1.0)


class OptimizationDiverged(RuntimeError):
    """The optimisation blew up and halving the learning rates did not recover it."""

Reference = Callable[[Cameras], torch.Tensor]


@dataclass
class OptimizerConfig:
    """Settings of :class:`MultiViewOptimizer` (defaults: the paper's large-deformation setup).

    Local editing / denoising in the paper: ``normal_steps=19, point_steps=1``.
    """

    cycles: int = 16
    normal_steps: int = 15
    point_steps: int = 25
    schedule: str = "alternating"  # "alternating" | "joint"
    lr_points: float = 5.0
    lr_normals: float = 5000.0
    lr_scale: float = 0.01
    lr_decay: float = 1.0  # learning rates x lr_decay after every cycle
    bold_driver: bool = False  # point lr x0.5 when a point step raised the loss, x1.1 (up to the set lr) when not
    momentum: float = 0.9
    nesterov: bool = True
    optimizer: str = "sgd"  # "sgd" (paper: Nesterov momentum) | "adam" (scale-free steps, an option)
    adam_lr_points: float = 2e-3
    adam_lr_normals: float = 2e-2
    clip_point_grad: float | None = 0.01
    clip_normal_grad: float | None = 1e-4
    image_loss: str = "smape"  # "smape" | "l1"
    # > 0: add silhouette_weight x L1 between the rendered coverage (a constant channel blended
    # like the colours: 1 where a splat is visible, the background elsewhere) and the reference's
    # (its pixels that differ from the background). Only the visibility gradient of Eq. gradP
    # acts on that channel: a shape-from-silhouette pull that shading cannot cancel. 0: the paper.
    silhouette_weight: float = 0.0
    # > 0: after every point step, points that project onto the reference's background move this
    # fraction of the way to its silhouette (dss.hull: a visual-hull pull that tears membranes
    # across holes, where the visibility gradient is zero). 0: the paper.
    hull_step: float = 0.0
    # > 0 (with hull_step > 0): the hull pull also tests this many more views per cycle, sampled
    # like the step's (their references are rendered once per cycle for their silhouettes only;
    # no image loss). A point outside the visual hull in a view the cycle does not render is
    # otherwise left there until a later cycle's views happen to include one that shows it.
    hull_views: int = 0
    # > 0: after every point step, each reference pixel the render leaves empty pulls the nearest
    # projected point this fraction of the way to it (dss.hull.fill_displacement), times
    # lr_decay^cycle like the learning rates (thin parts form early, the surface then settles).
    # 0: the paper.
    fill_step: float = 0.0
    projection_weight: float = 0.02
    repulsion_weight: float = 0.05
    regularizer_weighting: str = "relative"  # "relative" | "absolute" | "per_point" (x N; see _regularizer_grads)
    regularizer_calibration: str = "once"  # relative weighting: gamma fixed at the first step | "every_step"
    projection_bandwidth: str | float = "default"  # "default" | "large" | a number
    projection_mode: str = "paper"  # "paper" | "point_to_plane" (dss.regularizers.projection_loss)
    # "free": points move along their full gradient; "normal": only its component along the point's
    # current (optimised) normal; "pca": along the normal of the point's own weighted-PCA plane
    # (the projection term's V_n). Both stop the tangential drift: the projection term pulls a
    # point toward each neighbour's plane, and that pull has a tangential part wherever the
    # neighbour's plane is tilted against the point's own.
    point_motion: str = "free"
    repulsion_bandwidth: str | float = "default"
    reg_k: int = 16
    # every reg_dilation-th of the reg_k * reg_dilation nearest (dss.regularizers.find_neighbors)
    reg_dilation: int = 1
    # neighbourhood radius of both regularisers' weighted PCA, a multiple of their bandwidth D
    # (paper: 1; dss.regularizers.RegularizerConfig.cutoff)
    reg_cutoff: float = 1.0
    # the nearest reg_min_neighbors count whatever the cutoff (RegularizerConfig.min_neighbors)
    reg_min_neighbors: int = 0
    # the regularisers' weighted-PCA frames (weights, planes) are re-fitted every frames_every-th
    # step of a cycle and kept in between (the point differences are always current); the paper
    # re-fits every step (1). The fit is most of a denoising step's regulariser time.
    frames_every: int = 1
    # > 0: after the last cycle, project points onto the plane of their final_projection_k
    # nearest (dss.regularizers.project_to_neighbour_planes; plain neighbours, not reg_dilation's
    # spread ones: on a dense cloud a spread patch is too wide to follow the surface near a tip,
    # so the outliers there go unflagged); 0: the paper (none).
    # final_projection_threshold t > 0 moves only the outliers (plane distance > t robust
    # sigmas and > final_projection_local_ratio x their neighbours' median, onto their nearest
    # inliers' plane), final_projection_iterations times; t = 0: every point
    final_projection_k: int = 0
    final_projection_threshold: float = 3.0
    final_projection_local_ratio: float = 3.0
    final_projection_iterations: int = 2
    # > 0: no point ends a step farther than this (the cloud's units) from where it started the
    # run: its displacement is scaled back onto that ball (dss.pipeline applies the same bound
    # after the fusion and the final projection). Denoising only has to undo the noise: a point
    # moved much farther than the noise is being moved by the smoothing itself (shrinkage of
    # tips, folds filled in). 0: no bound (the paper).
    max_displacement: float = 0.0
    # > 0: after the final projection, points beyond the rim of their rim_k nearest neighbours'
    # patch move back onto it (dss.regularizers.pull_rim_strays: the strays a plane projection
    # leaves past thin and sharply curved parts). 0: off (the paper).
    rim_k: int = 0
    rim_ratio: float = 1.3
    rim_target: float = 1.0
    rim_iterations: int = 2
    views: int = 12
    fov_deg: float = 30.0
    view_jitter: float = 0.1
    resample_every_cycle: bool = True
    window_start: int = 16
    window_end: int = 4
    window_decay: float = 0.9
    window_samples: int = 8
    # > 0: window_start / window_end are in pixels of an image this many pixels across, and a
    # larger (smaller) image scales them up (down) so that the window keeps its reach on the
    # object and against the splats, whose size in pixels grows with the image (0: in pixels
    # whatever the image size)
    window_reference_size: int = 0
    error_aware_cycles: int = 0
    error_aware_distance: float = 0.5
    grad_smoothing: int = 0  # passes of neighbour averaging of the image gradient on the points
    normal_refresh: str = "none"  # "none" | "pca": re-fit normals to the points at each cycle start
    normal_refresh_k: int = 16
    # the sign of a re-fitted normal (normal_refresh): "current", that of the normal it replaces;
    # "views", toward the cycle's cameras that see its point (dss.orientation; a point no view
    # sees keeps the current sign). An addition to the paper, like the re-fit itself.
    normal_orientation: str = "current"
    # > 0 (with normal_refresh): re-fit the normals once more after the last cycle (and the final
    # projection) over this many neighbours, signed as at a cycle start with the last cycle's
    # views. The last cycle's point steps move the points after its normal steps; the output's
    # normals follow them. 0: the output's normals are the last normal steps'.
    final_normal_refresh_k: int = 0
    # divergence guard (module docstring): a step that grows the cloud's extent beyond
    # blowup_extent x its start's, or the image loss beyond blowup_loss x its cycle's first, is
    # undone and the rates halved; 0 turns a test off. After max_lr_halvings: OptimizationDiverged.
    # The loss test is off by default: denoising starts each cycle from renders of the input,
    # whose loss against references made from the input is small, and a healthy run's loss then
    # grows many-fold as the points leave the noise (with 10x, tests/test_denoise.py's tiny-model
    # case had its cycles undone: Chamfer x1e4 3.61 -> 3.56 where it reaches below 2.9). A
    # blown-up cloud trips the extent test. 3x: dss-deform with lr_points 1e6 (300 points, 32
    # px) ended at Chamfer x1e4 7.2e4 with 10x (points flung 4 diagonals away, under 10x), 538
    # with 3x; its default rate tripped neither.
    blowup_extent: float = 3.0
    blowup_loss: float = 0.0
    max_lr_halvings: int = 16
    seed: int = 0

    def __post_init__(self):
        if self.schedule not in ("alternating", "joint"):
            raise ValueError(f"schedule must be 'alternating' or 'joint', got {self.schedule!r}")
        if self.optimizer not in ("sgd", "adam"):
            raise ValueError(f"optimizer must be 'sgd' or 'adam', got {self.optimizer!r}")
        if self.regularizer_weighting not in ("relative", "absolute", "per_point"):
            raise ValueError("regularizer_weighting must be 'relative', 'absolute' or 'per_point', "
                             f"got {self.regularizer_weighting!r}")
        if self.image_loss not in ("smape", "l1"):
            raise ValueError(f"image_loss must be 'smape' or 'l1', got {self.image_loss!r}")
        if self.regularizer_calibration not in ("once", "every_step"):
            raise ValueError(f"regularizer_calibration must be 'once' or 'every_step', got {self.regularizer_calibration!r}")
        if self.point_motion not in ("free", "normal", "pca"):
            raise ValueError(f"point_motion must be 'free', 'normal' or 'pca', got {self.point_motion!r}")
        if self.normal_refresh not in ("none", "pca"):
            raise ValueError(f"normal_refresh must be 'none' or 'pca', got {self.normal_refresh!r}")
        if self.normal_orientation not in ("current", "views"):
            raise ValueError(f"normal_orientation must be 'current' or 'views', got {self.normal_orientation!r}")
        if self.views <= 0:
            raise ValueError(f"views per step must be positive, got {self.views}")
        for name in ("lr_points", "lr_normals", "silhouette_weight", "hull_step", "fill_step"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if int(self.frames_every) != self.frames_every or self.frames_every < 1:
            raise ValueError(f"frames_every must be a positive integer, got {self.frames_every}")
        for name in ("cycles", "normal_steps", "point_steps", "error_aware_cycles", "hull_views",
                     "final_normal_refresh_k"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.cycles + self.error_aware_cycles == 0 or self.normal_steps + self.point_steps == 0:
            raise ValueError("nothing to do: cycles and steps are all zero")
        if min(self.final_projection_k, self.final_projection_threshold, self.final_projection_local_ratio) < 0:
            raise ValueError("final_projection_k, _threshold and _local_ratio must be >= 0, got "
                             f"{self.final_projection_k}, {self.final_projection_threshold}, "
                             f"{self.final_projection_local_ratio}")
        if self.rim_k < 0 or not (self.rim_ratio > 0 and self.rim_target > 0) or self.rim_iterations < 1:
            raise ValueError(f"rim_k must be >= 0, rim_ratio and rim_target > 0, rim_iterations >= 1, got "
                             f"{self.rim_k}, {self.rim_ratio}, {self.rim_target}, {self.rim_iterations}")
        if self.max_displacement < 0:
            raise ValueError(f"max_displacement must be >= 0, got {self.max_displacement}")
        if self.blowup_extent < 0 or self.blowup_loss < 0 or self.max_lr_halvings < 0:
            raise ValueError("blowup_extent, blowup_loss and max_lr_halvings must be >= 0, got "
                             f"{self.blowup_extent}, {self.blowup_loss}, {self.max_lr_halvings}")
        if self.final_projection_iterations < 1:
            raise ValueError(f"final_projection_iterations must be >= 1, got {self.final_projection_iterations}")


    def min_points(self) -> int:
        """The fewest points this configuration can optimise: more than the largest neighbour
        list it asks for (regularisers: reg_k x reg_dilation; final projection:
        final_projection_k; normal refresh: normal_refresh_k)."""
        need = 3
        if self.projection_weight > 0 or self.repulsion_weight > 0:
            need = max(need, self.reg_k * self.reg_dilation + 1)
        if self.final_projection_k > 0:
            need = max(need, self.final_projection_k + 1)
        if self.normal_refresh != "none":
            need = max(need, max(self.normal_refresh_k, self.final_normal_refresh_k) + 1)
        return need

    def check_points(self, n: int, what: str = "the cloud") -> None:
        """Refuse ``n`` points before any work when they are too few (:meth:`min_points`)."""
        if n < self.min_points():
            raise ValueError(f"{what} has {n} points, too few for this optimisation (at least {self.min_points()}: "
                             f"reg_k {self.reg_k} x reg_dilation {self.reg_dilation}, final_projection_k "
                             f"{self.final_projection_k}, normal_refresh_k {self.normal_refresh_k})")


@dataclass
class OptimizationResult:
    points: torch.Tensor
    normals: torch.Tensor
    history: dict = field(default_factory=dict)


def window_for_cycle(cfg: OptimizerConfig, cycle: int, image_size: int | None = None) -> tuple[int, int]:
    """Visibility-gradient window (half size, stride) for a cycle: long range first, then local.

    With ``cfg.window_reference_size`` > 0 and ``image_size`` (the larger side, pixels) given, the
    windows scale by ``image_size / window_reference_size``; the stride keeps ``window_samples``
    samples per half window, so a scaled window costs about what the unscaled one does."""
    scale = image_size / cfg.window_reference_size if cfg.window_reference_size > 0 and image_size else 1.0
    end = max(1, int(round(cfg.window_end * scale)))
    w = max(end, int(round(cfg.window_start * scale * cfg.window_decay**cycle)))
    stride = max(1, math.ceil(w / max(1, cfg.window_samples)))
    return w, stride


def occlusion_counts(out: RenderOutput) -> torch.Tensor:
    """o_k: in how many views point k is rendered (valid splat) but visible at no pixel. (N,)

    Counted in the order the kernels rendered in and permuted back once (an (N,) gather): the
    fragments' (V, H, W, K) indices are never mapped to the caller's order."""
    _, splats, _ = out.in_render_order
    counts = (splats.valid & ~out.seen(in_render_order=True)).sum(0).float()
    if out.point_order is None:
        return counts
    caller = torch.empty_like(counts)
    caller[out.point_order] = counts  # sorted position j holds caller point point_order[j]
    return caller


def _bandwidth(rule, points):
    if isinstance(rule, str):
        return RegularizerConfig(bandwidth_rule=rule)
    return RegularizerConfig(bandwidth=float(rule))


class MultiViewOptimizer:
    """Optimise points and normals against reference images.

    Args:
        points, normals: (N, 3) initial state (copied).
        reference: ``cameras -> (V, H, W, C)`` target images for those cameras (computed once
            per camera set and cached for the cycle).
        config: :class:`OptimizerConfig`.
        settings: renderer settings (``window`` is overridden by the schedule).
        center, radius: the sphere the cameras look at (default: the start cloud's bounds).
        shading: shading used for both the renders and (by the caller) the references.
        callback: called as ``callback(step, state_dict)`` after every step (snapshots, logging).
    """

    def __init__(self, points: torch.Tensor, normals: torch.Tensor, reference: Reference,
                 config: OptimizerConfig | None = None, settings: RenderSettings | None = None,
                 center=None, radius: float | None = None, shading="sun", backend: str = "auto",
                 callback: Callable[[int, dict], None] | None = None, sampler: SphereViewSampler | None = None,
                 image_size: int = 256):
        self.cfg = config or OptimizerConfig()
        self.cfg.check_points(points.shape[0])
        self.settings = settings or RenderSettings()
        self.points = points.detach().clone().float().requires_grad_(True)
        self.normals = torch.nn.functional.normalize(normals.detach().clone().float(), dim=1).requires_grad_(True)
        self.reference = reference
        self.shading = shading
        self.backend = backend
        self.callback = callback
        p = self.points.detach()
        if center is None:
            center = ((p.max(0).values + p.min(0).values) / 2).tolist()
        if radius is None:
            radius = float((p - torch.tensor(center)).norm(dim=1).max())
        self.sampler = sampler or SphereViewSampler(tuple(center), radius, self.cfg.views, image_size,
                                                    self.cfg.fov_deg, self.cfg.view_jitter, seed=self.cfg.seed)
        # the hull pull's extra views (hull_views): their own generator, so the step's views are
        # the same with and without them
        self._hull_sampler = None
        if self.cfg.hull_views > 0 and self.cfg.hull_step > 0:
            self._hull_sampler = SphereViewSampler(tuple(center), radius, self.cfg.hull_views, image_size,
                                                   self.cfg.fov_deg, self.cfg.view_jitter, seed=self.cfg.seed + 7919)
        self._hull_extra: tuple[Cameras, torch.Tensor, torch.Tensor] | None = None
        self._last_cams: Cameras | None = None  # the last cycle's views (final_normal_refresh)
        self.proj = ProjectionLoss(_bandwidth(self.cfg.projection_bandwidth, p), k=self.cfg.reg_k,
                                   projection_mode=self.cfg.projection_mode, cutoff=self.cfg.reg_cutoff,
                                   min_neighbors=self.cfg.reg_min_neighbors)
        self.rep = RepulsionLoss(_bandwidth(self.cfg.repulsion_bandwidth, p), k=self.cfg.reg_k,
                                 cutoff=self.cfg.reg_cutoff, min_neighbors=self.cfg.reg_min_neighbors)
        # the divergence guard's yardstick: the start cloud or the cameras' sphere, the larger
        self._start = self.points.detach().clone()  # max_displacement's centres
        self._extent0 = max(float((p.max(0).values - p.min(0).values).norm()), 2 * float(radius), 1e-12)
        # a rule fixes D from the start cloud; a number given as the bandwidth is D
        for term in (self.proj, self.rep):
            if term.bandwidth is None:
                term.set_initial_shape(p)
        self.lr_scale = 1.0
        self._img_grad_scale: float | None = None
        self._reg_gamma: dict[int, float] = {}
        self._neighbors = None
        self._frames: dict[int, object] = {}  # per term: the last fitted frames (frames_every)
        self._frames_age = 0
        self._pca_normals: torch.Tensor | None = None  # the projection term's PCA normals, last step
        self._sigma = None
        # the reference the coverage was derived from, its coverage (V, H, W) bool and (for the
        # hull pull) its nearest covered pixels: once per reference, i.e. once per cycle
        self._ref_coverage: tuple[torch.Tensor, torch.Tensor, torch.Tensor | None] | None = None
        self._cycle_decay = 1.0  # lr_decay ** cycle
        self.history: dict = {"step": [], "loss": [], "image_loss": [], "time": [], "kind": [], "lr_halvings": 0,
                              "rejected": [], "config": asdict(self.cfg)}
        # host-side wall time per part of the loop (history["profile_s"])
        self.clock = StageClock()
        self._make_optimizers()

    # ------------------------------------------------------------------ internals
    def _make_optimizers(self):
        c = self.cfg
        if c.optimizer == "adam":  # lr in scene units per step: each coordinate moves ~lr
            self.opt_p = torch.optim.Adam([self.points], lr=c.adam_lr_points * self.lr_scale)
            self.opt_n = torch.optim.Adam([self.normals], lr=c.adam_lr_normals * self.lr_scale)
            return
        nest = c.nesterov and c.momentum > 0
        # dss.sgd.SGD computes torch.optim.SGD's update without importing torch._dynamo (~2 s)
        self.opt_p = SGD([self.points], lr=c.lr_points * c.lr_scale * self.lr_scale, momentum=c.momentum, nesterov=nest)
        self.opt_n = SGD([self.normals], lr=c.lr_normals * c.lr_scale * self.lr_scale, momentum=c.momentum, nesterov=nest)

    def _image_loss(self, images, target):
        if self.cfg.image_loss == "smape":
            return smape_loss(images, target, channel_reduction="mean")
        return l1_loss(images, target, channel_reduction="mean")

    def _with_coverage(self, points, normals, cameras: Cameras, colors=None) -> torch.Tensor:
        """The shading's attributes plus a constant 1 channel (blended: the coverage). (V, N, C+1)"""
        a = shade(self.shading, points, normals, cameras, colors)
        return torch.cat([a, a.new_ones(a.shape[:-1] + (1,))], -1)

    def _coverage(self, target: torch.Tensor, nearest: bool = False):
        """Reference coverage (V, H, W) bool: pixels whose value differs from the background; with
        ``nearest``, also its :func:`dss.hull.nearest_covered`. Computed once per reference."""
        cache = self._ref_coverage
        if cache is None or cache[0] is not target:
            bg = torch.as_tensor(self.settings.background, dtype=target.dtype, device=target.device).flatten()
            cache = (target, (target - bg).abs().amax(-1) > 1e-6, None)
        if nearest and cache[2] is None:
            cache = (target, cache[1], nearest_covered(cache[1]))
        self._ref_coverage = cache
        return cache[1:] if nearest else cache[1]

    def _regularizer_grads(self, out: RenderOutput) -> torch.Tensor | None:
        """gamma-weighted regulariser gradients on the points (N, 3), or None. ``out``: this
        step's render, for the occlusion counts of a frames fit."""
        c = self.cfg
        total = None
        occl = None
        for weight, term in ((c.projection_weight, self.proj), (c.repulsion_weight, self.rep)):
            if weight <= 0:
                continue
            p = self.points.detach().requires_grad_(True)
            cached = self._frames.get(id(term))
            if cached is None or self._frames_age >= c.frames_every:
                if occl is None:  # only a fit needs them (its weights)
                    occl = occlusion_counts(out).detach()
                frames = term.frames(p, self.normals.detach(), occl, self._neighbors)
                # kept without its differences' graph (with_new_differences makes new ones)
                self._frames[id(term)] = replace(frames, diff=frames.diff.detach())
            else:
                frames = with_new_differences(cached, p)
            if term is self.proj:
                self._pca_normals = frames.normal.detach()
            (g,) = torch.autograd.grad(term(p, frames=frames), p)
            g = torch.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0)
            if c.regularizer_weighting == "relative":
                # gamma calibrated once, at the first step, so that the term's mean per-point
                # gradient is ``weight`` x the image term's, then kept fixed (paper Appendix:
                # the weights are found by that calibration). Rescaling every step instead
                # normalises the term's magnitude: once the surface is smooth its tiny residual
                # gradient is blown up to the same size and scatters the points (measured:
                # denoising the example, Chamfer 0.93 after 8 cycles, 3.6 after 16).
                # ("every_step" re-normalises at every step instead: the term's mean per-point
                # gradient is always ``weight`` x the first image gradient's, the behaviour
                # dss-deform was tuned with)
                once = c.regularizer_calibration == "once"
                gamma = self._reg_gamma.get(id(term)) if once else None
                if gamma is None:
                    ref, mag = self._img_grad_scale, float(g.double().norm(dim=1).mean())
                    if ref is not None and mag > 0:
                        gamma = weight * ref / mag
                    if once and gamma is not None:
                        self._reg_gamma[id(term)] = gamma
                        name = "projection" if term is self.proj else "repulsion"
                        self.history.setdefault("reg_gamma", {})[name] = gamma
                        log.info("%s term: gamma %.4g (mean per-point gradient: image %.4g, term %.4g)",
                                 name, gamma, ref, mag)
                g = g * gamma if gamma is not None else torch.zeros_like(g)
            elif c.regularizer_weighting == "per_point":
                # the terms are means over the N points: x N gives each point the gradient of its
                # own summand, so a weight means the same for any N and any reference
                g = (weight * self.points.shape[0]) * g
            else:
                g = weight * g
            total = g if total is None else total + g
        self._frames_age = 1 if self._frames_age >= c.frames_every else self._frames_age + 1
        return total

    def _step(self, kind: str, cams: Cameras, target: torch.Tensor, window: int, stride: int):
        s = self.settings
        settings = RenderSettings(**{**asdict(s), "window": window, "window_stride": stride})
        # Point steps move points by the image loss; normal steps need its point gradient only
        # once, to set the scale of the relative regulariser weights.
        image_moves_points = kind in ("points", "joint")
        need_img_scale = (self._img_grad_scale is None and self.cfg.regularizer_weighting == "relative"
                          and (self.cfg.projection_weight > 0 or self.cfg.repulsion_weight > 0))
        move_normals = kind in ("normals", "joint")
        self.opt_p.zero_grad(set_to_none=True)
        self.opt_n.zero_grad(set_to_none=True)
        saved = (self.points.detach().clone(), self.normals.detach().clone())
        pts = self.points if (image_moves_points or need_img_scale) else self.points.detach()
        sil = self.cfg.silhouette_weight > 0
        with self.clock("render"):
            out = render(pts, self.normals if move_normals else self.normals.detach(), cams, settings,
                         shading=self._with_coverage if sil else self.shading, backend=self.backend, sigma=self._sigma)
        if sil:
            img_loss = self._image_loss(out.images[..., :-1], target)
            cover = self._coverage(target).to(out.images.dtype)
            img_loss = img_loss + self.cfg.silhouette_weight * (out.images[..., -1] - cover).abs().mean()
        else:
            img_loss = self._image_loss(out.images, target)
        if not torch.isfinite(img_loss):
            self._diverged("the image loss is not finite", saved)
            return float("nan"), float("nan")
        if img_loss.requires_grad:
            with self.clock("backward"):
                img_loss.backward()
        g_img = self.points.grad
        if g_img is not None:
            # Pixels covered only by near edge-on splats have a tiny total weight, and the
            # gradient of the normalised sum w.r.t. their weights is huge there (the EWA weight's
            # log-derivative is singular at grazing angles): sanitise and clip before use.
            g_img = torch.nan_to_num(g_img.detach(), nan=0.0, posinf=0.0, neginf=0.0)
            if self.cfg.clip_point_grad:
                g_img = g_img.clamp(-self.cfg.clip_point_grad, self.cfg.clip_point_grad)
            if self._img_grad_scale is None:
                # Measured once (first image gradient of the run) and then kept: re-measuring it
                # every step couples the regulariser step to the image gradient, which grows as
                # the cloud drifts from the reference, a runaway feedback.
                self._img_grad_scale = float(g_img.double().norm(dim=1).mean())
            if not image_moves_points:
                g_img = None
            elif self.cfg.grad_smoothing > 0:
                g_img = self._smooth(g_img, self.cfg.grad_smoothing)
        with self.clock("regularizers"):
            g_reg = self._regularizer_grads(out)
        # Points move in every step: by image + regulariser gradients in point steps, by the
        # regulariser alone in normal steps (paper "Alternating normal and point update").
        g = g_img if g_reg is None else (g_reg if g_img is None else g_img + g_reg)
        if g is not None and self.cfg.point_motion != "free":
            n = self._pca_normals if (self.cfg.point_motion == "pca" and self._pca_normals is not None) else self.normals
            n = torch.nn.functional.normalize(n.detach(), dim=1)
            g = (g * n).sum(1, keepdim=True) * n
        self.points.grad = g
        if g is not None:
            if self.cfg.clip_point_grad:
                g.clamp_(-self.cfg.clip_point_grad, self.cfg.clip_point_grad)
            self.opt_p.step()
        if move_normals and self.normals.grad is not None:
            gn = torch.nan_to_num(self.normals.grad, nan=0.0, posinf=0.0, neginf=0.0)
            if self.cfg.clip_normal_grad:
                gn = gn.clamp(-self.cfg.clip_normal_grad, self.cfg.clip_normal_grad)
            self.normals.grad = gn
            self.opt_n.step()
        with torch.no_grad():
            self.normals.copy_(torch.nn.functional.normalize(self.normals, dim=1))
            if self.cfg.max_displacement > 0:
                self.points.copy_(bound_displacement(self.points, self._start, self.cfg.max_displacement))
            if image_moves_points and self.cfg.hull_step > 0:
                d, n_out = hull_displacement(self.points, cams, *self._coverage(target, nearest=True))
                if self._hull_extra is not None:  # averaged over the violated views of both sets
                    d2, n2 = hull_displacement(self.points, *self._hull_extra)
                    d = (d * n_out[:, None] + d2 * n2[:, None]) / (n_out + n2).clamp_min(1)[:, None].to(d.dtype)
                self.points.add_(self.cfg.hull_step * d)
            if image_moves_points and self.cfg.fill_step > 0:
                d, _ = fill_displacement(self.points, cams, self._coverage(target), out.mask)
                self.points.add_(self.cfg.fill_step * self._cycle_decay * d)
        if not all_finite(self.points, self.normals):
            self._diverged("a step produced NaN/inf parameters", saved)
            return float("nan"), float("nan")
        if self.cfg.blowup_extent > 0:
            p = self.points.detach()
            extent = float((p.max(0).values - p.min(0).values).norm())
            if extent > self.cfg.blowup_extent * self._extent0:
                self._diverged(f"a step grew the cloud to {extent / self._extent0:.3g}x its start's extent", saved)
                return float("nan"), float("nan")
        return float(img_loss.detach()), float(img_loss.detach())

    def _diverged(self, why: str, saved):
        """Undo to ``saved`` (points, normals), halve the learning rates, reset their momentum;
        raises :class:`OptimizationDiverged` once ``max_lr_halvings`` did not help."""
        with torch.no_grad():
            self.points.copy_(saved[0])
            self.normals.copy_(saved[1])
        h = self.history
        h["rejected"].append({"step": len(h["step"]) + 1, "why": why})
        if h["lr_halvings"] >= self.cfg.max_lr_halvings:
            raise OptimizationDiverged(
                f"the optimisation diverged and did not recover: {why}, after {h['lr_halvings']} halvings of the "
                f"learning rates (x{self.lr_scale:.3g} of the configured ones); lower the learning rates")
        self.lr_scale *= 0.5
        h["lr_halvings"] += 1
        log.warning("%s: step rejected, learning rates halved (x%.3g of the configured ones)", why, self.lr_scale)
        self._make_optimizers()

    def _refresh_neighbourhoods(self, cams: Cameras | None = None):
        """Once per cycle: kNN lists for the regularisers and the splat sizes (points move little
        within a cycle; the regularisers re-apply their bandwidth masks every step), and the
        normal re-fit (``normal_refresh``; signed by ``cams`` with ``normal_orientation="views"``)."""
        p = self.points.detach()
        s = self.settings
        self._sigma = auto_sigma(p, s.sigma_k, s.sigma_scale) if s.sigma == "auto" else None
        if self.cfg.normal_refresh == "pca":
            self._refit_normals(p, cams)
        self._neighbors = find_neighbors(p, self.cfg.reg_k, dilation=self.cfg.reg_dilation)
        self._frames, self._frames_age = {}, 0  # new neighbour lists: fit anew

    def _hull_views(self) -> tuple[Cameras, torch.Tensor, torch.Tensor]:
        """The cycle's extra silhouette views (``hull_views``): cameras, reference coverage
        (V, H, W) and its nearest covered pixels (:func:`dss.hull.nearest_covered`)."""
        cams = self._hull_sampler.sample().to(self.points.device)
        ref = self.reference(cams).detach()
        bg = torch.as_tensor(self.settings.background, dtype=ref.dtype, device=ref.device).flatten()
        mask = (ref - bg).abs().amax(-1) > 1e-6
        return cams, mask, nearest_covered(mask)

    def _bold_driver(self, worse: bool):
        """Halve the point learning rate after a point step that raised the image loss (and drop
        its momentum); otherwise grow it by 10% up to its scheduled value. Large learning rates
        are what large deformations need early on, and what overshoots on other shapes (measured:
        sphere -> bunny's loss rises by a third in the first cycle at the teapot's rate)."""
        for group in self.opt_p.param_groups:
            cap = group.setdefault("scheduled_lr", group["lr"])
            group["lr"] = group["lr"] * 0.5 if worse else min(cap, group["lr"] * 1.1)
        if worse:
            self.opt_p.state.clear()
        self.history.setdefault("lr_points", []).append(self.opt_p.param_groups[0]["lr"])

    def _smooth(self, g: torch.Tensor, passes: int) -> torch.Tensor:
        """Average a per-point field over each point and its kNN (the cycle's neighbour lists).

        The visibility gradient moves single silhouette points, each toward the pixels it could
        cover; averaging over neighbours moves patches of surface together, a cheap form of the
        smoothed ("Sobolev") gradients of mesh inverse rendering. Measured on sphere -> teapot
        (8K points, 128 px, 320 steps): Chamfer x1e4 24.9 without, 18.8 with two passes.
        """
        nb = self._neighbors
        idx = nb.idx.long()
        ok = (idx >= 0).to(g.dtype)[..., None]
        for _ in range(passes):
            s = (g[idx.clamp_min(0)] * ok).sum(1) + g
            g = s / (ok.sum(1) + 1)
        return g

    def _refit_normals(self, p: torch.Tensor, cams: Cameras | None = None, k: int | None = None):
        """Normals := PCA normals of the current points, signed to agree with the current normals
        (``normal_orientation="current"``) or to face the views in ``cams`` that see their points
        (``"views"``, :func:`dss.orientation.orient_to_views`; unseen points: the current sign).

        Large deformations move points far in a few cycles, and the image gradient of the
        normals (a colour match per pixel) does not keep up: measured on sphere -> teapot, the
        median |cos| between the optimised normals and the PCA normals of the points falls to
        0.58 and the renders turn into noise although the points lie near the target. Re-fitting
        once per cycle keeps the normals tied to the geometry; the normal steps then refine them.
        """
        from .pointcloud import estimate_normals

        n = estimate_normals(p, k=k or self.cfg.normal_refresh_k, orient="none").to(p.device)
        if self.cfg.normal_orientation == "views" and cams is not None:
            n, unseen = orient_to_views(p, n, cams, self.settings, fallback=self.normals.detach(),
                                        backend=self.backend, sigma=self._sigma)
            self.history.setdefault("unseen_fraction", []).append(float(unseen.float().mean()))
        else:
            n = n * torch.where((n * self.normals.detach()).sum(1, keepdim=True) < 0, -1.0, 1.0)
        with torch.no_grad():
            self.normals.copy_(n)
        # momentum of the old normals is meaningless for the new ones
        self.opt_n.state.clear()

    def _cycle_plan(self) -> list[str]:
        c = self.cfg
        if c.schedule == "joint":
            return ["joint"] * (c.normal_steps + c.point_steps)
        return ["normals"] * c.normal_steps + ["points"] * c.point_steps

    # ------------------------------------------------------------------ public
    @property
    def total_steps(self) -> int:
        return (self.cfg.cycles + self.cfg.error_aware_cycles) * len(self._cycle_plan())

    def run(self, progress: Callable[[int, float], None] | None = None,
            final_projection: bool = True) -> OptimizationResult:
        """Run all cycles; ``progress(step, loss)`` is called after each step (progress bars).
        ``final_projection=False`` leaves :meth:`project_outliers` to the caller (a stage that
        runs after the cycles, such as :func:`dss.fusion.fuse_planes`, comes before it)."""
        c = self.cfg
        t0 = time.perf_counter()
        gen = torch.Generator().manual_seed(c.seed + 1)
        with frozen_gc():  # see dss/gc_pause.py: full collections cost ~150 ms each otherwise
            step = self._run_cycles(progress, gen, t0)
        if final_projection:
            with torch.no_grad():
                p = self.project_outliers(self.points.detach())
                if self.cfg.max_displacement > 0:
                    p = bound_displacement(p, self._start, self.cfg.max_displacement)
                self.points.copy_(p)
            self.refit_final_normals()
        self.history["wall_time"] = time.perf_counter() - t0
        self.history["steps"] = step
        # the rest of each step: loss, optimiser updates, clipping, the divergence guard, callbacks
        self.history["profile_s"] = {**self.clock.seconds,
                                     "other": max(0.0, self.history["wall_time"] - sum(self.clock.seconds.values()))}
        self.history["profile_cpu_s"] = dict(self.clock.cpu_seconds)
        if self.history["lr_halvings"]:
            log.warning("the optimisation was unstable: %d steps rejected, learning rates halved %d times "
                        "(x%.3g of the configured ones); lower them", len(self.history["rejected"]),
                        self.history["lr_halvings"], self.lr_scale)
        return OptimizationResult(self.points.detach().clone(), self.normals.detach().clone(), self.history)

    def _run_cycles(self, progress, gen: torch.Generator, t0: float) -> int:
        """The cycles of :meth:`run`; returns the number of steps taken."""
        c = self.cfg
        step = 0
        cams = None
        for cycle in range(c.cycles + c.error_aware_cycles):
            if cams is None or c.resample_every_cycle:
                if cycle >= c.cycles and cams is not None:
                    cams = self._error_aware(cams, gen)
                else:  # on the points' device: the renders and the reference see one device
                    cams = self.sampler.sample().to(self.points.device)
            self._last_cams = cams
            with torch.no_grad(), self.clock("references"):
                target = self.reference(cams).detach()
                if self._hull_sampler is not None:
                    self._hull_extra = self._hull_views()
            self._cycle_decay = c.lr_decay ** cycle
            with self.clock("neighbourhoods"):
                self._refresh_neighbourhoods(cams)
            if cycle > 0 and c.lr_decay != 1.0:
                for opt in (self.opt_p, self.opt_n):
                    for group in opt.param_groups:
                        group["lr"] *= c.lr_decay
                        if "scheduled_lr" in group:
                            group["scheduled_lr"] *= c.lr_decay
            window, stride = window_for_cycle(c, cycle, max(cams.image_size))
            prev_point_loss = None
            # the loss guard's reference: the cycle's first loss and state (same cameras and
            # references for every step of the cycle, so their losses compare)
            first_loss = None
            start = (self.points.detach().clone(), self.normals.detach().clone()) if c.blowup_loss > 0 else None
            for kind in self._cycle_plan():
                loss, img_loss = self._step(kind, cams, target, window, stride)
                if start is not None and math.isfinite(img_loss):
                    if first_loss is None:
                        first_loss = img_loss
                    elif first_loss > 0 and img_loss > c.blowup_loss * first_loss:
                        self._diverged(f"the image loss rose to {img_loss / first_loss:.3g}x its cycle's first",
                                       start)
                        loss = img_loss = float("nan")
                if c.bold_driver and kind in ("points", "joint") and math.isfinite(img_loss):
                    # the loss of step t is measured before its update: it judges step t-1's
                    # update (same cameras and references within a cycle)
                    if prev_point_loss is not None:
                        self._bold_driver(img_loss > prev_point_loss * (1 + 1e-3))
                    prev_point_loss = img_loss
                step += 1
                h = self.history
                h["step"].append(step)
                h["loss"].append(loss)
                h["image_loss"].append(img_loss)
                h["kind"].append(kind)
                h["time"].append(time.perf_counter() - t0)
                if self.callback is not None:
                    self.callback(step, {"points": self.points.detach(), "normals": self.normals.detach(), "cycle": cycle,
                                         "loss": loss, "cameras": cams})
                if progress is not None:
                    progress(step, loss)
        return step

    def refit_final_normals(self) -> None:
        """The configured final normal re-fit (``final_normal_refresh_k`` > 0 with
        ``normal_refresh``): the normals re-fitted to the current points over that many
        neighbours, signed as at a cycle start with the last cycle's views; nothing when it is
        off (a caller that defers the final projection calls this after it)."""
        if self.cfg.final_normal_refresh_k > 0 and self.cfg.normal_refresh != "none":
            p = self.points.detach()
            s = self.settings
            self._sigma = auto_sigma(p, s.sigma_k, s.sigma_scale) if s.sigma == "auto" else None
            self._refit_normals(p, self._last_cams, k=self.cfg.final_normal_refresh_k)

    def project_outliers(self, points: torch.Tensor) -> torch.Tensor:
        """The configured final projection (``final_projection_k`` > 0) of ``points`` (N, 3):
        outliers onto their inliers' planes (:func:`dss.regularizers.project_to_neighbour_planes`),
        then the rim strays back onto their patches (``rim_k`` > 0, :func:`dss.regularizers.pull_rim_strays`);
        ``points`` unchanged when it is off."""
        c = self.cfg
        with torch.no_grad():
            if c.final_projection_k > 0:
                points = project_to_neighbour_planes(points, c.final_projection_k, 1,
                                                     threshold=c.final_projection_threshold,
                                                     local_ratio=c.final_projection_local_ratio,
                                                     iterations=c.final_projection_iterations)
            if c.rim_k > 0:
                points, moved = pull_rim_strays(points, c.rim_k, c.reg_dilation, ratio=c.rim_ratio,
                                                target=c.rim_target, iterations=c.rim_iterations)
                self.history.setdefault("rim_moved", []).append(moved)
            return points

    def _error_aware(self, cams: Cameras, gen: torch.Generator) -> Cameras:
        with torch.no_grad():
            out = render(self.points.detach(), self.normals.detach(), cams, self.settings, shading=self.shading, backend=self.backend)
            target = self.reference(cams)
            residual = (out.images - target).abs().sum(-1)
        # the view choice is a few small CPU computations (and its generator is a CPU one)
        new, focus = error_aware_cameras(self.points.detach().cpu(), cams.to("cpu"), residual.cpu(), self.cfg.views,
                                         distance=self.cfg.error_aware_distance, generator=gen)
        log.info("error-aware views around %s", [round(x, 3) for x in focus.tolist()])
        return new.to(self.points.device)
