"""Plane fusion: move each point onto the surface that the reference images show (not in the paper).

The DSS optimiser fits the renders of the cloud to the references through the splats' blended
colours and the visibility gradient. A point hidden inside the noise shell, behind its
neighbours' splats, never receives that gradient, and the blended image of a noisy cloud is the
cloud's *front envelope*, so the image loss's minimum is not the surface. With references in the
``planes`` channel (:func:`dss.shading.plane_coefficients`: every pixel holds the plane of the
surface it shows) the surface can be read directly, for every point and not only for the
visible ones:

1. for each view and point, the point's pixel (nearest) gives the reference plane; the camera
   ray through the point meets it at depth ``z_ref``; the signed distance along the point's
   normal from the point to that surface point is one *observation* of where the surface is;
2. an observation counts when the point is on the layer the view shows (``|z_ref - z| < tau``,
   the point's normal and the pixel's plane within ``max_angle_deg``, the ray not grazing:
   ``|cos| >= min_cos``), weighted by ``cos^2`` (a depth error of ``e`` along a ray at angle
   ``theta`` to the normal is ``e cos(theta)`` along the normal);
3. over all views: the weighted mean offset ``m`` and its spread ``s`` (weighted standard
   deviation across views). References of one surface agree across views up to a fraction of a
   pixel; renders of a noisy cloud do not (each view blends other points);
4. each point moves ``c m`` along its normal, with the *consistency* ``c = s0^2 / (s0^2 + s^2)``
   (0 with fewer than ``min_views`` observations): ``s0 = consistency_px`` pixel footprints at
   the point, the disagreement that pixels alone cause, but at most ``consistency_noise`` noise
   levels (images too coarse to resolve the noise cannot tell a surface from a blur of it).
   References that disagree across views move nothing;
5. a point the references do not pin down (consistency below 1/2: unobserved, behind other
   parts, beyond the depth window) moves ``1 - c`` of the way onto the plane of its trusted
   neighbours (``fill_k`` nearest, weighted by their consistency, when those weights sum to at
   least ``fill_min_weight``): the paper's visibility-weighted projection (phi = 1/(o + 1) pulls
   occluded points onto the planes of visible ones), with consistency in place of visibility.
   With references that nobody trusts it moves nothing.

Measured on the shipped example (20K points, 1% noise, Chamfer x1e4, paper protocol), after the
DSS cycles (0.336): references rendered from the clean cloud take it to 0.234, the input's own
renders leave it at 0.327 (consistency 0.04 on average); without the consistency weight the
input's renders pulled the points to their front envelope (Chamfer above 1). Per-stage numbers:
``python -m experiments.evaluation.image_study``; docs/denoising.md.

The displacement is the closed-form minimiser, per point, of the squared depth residuals
against the references along the point's normal: a Gauss-Newton step of a point-wise image
loss, where the paper's image loss acts on blended pixels.

Two options serve learned references (off by default, the behaviour above unchanged):

- ``uncertainty``: a reference may return, with its planes, a per-pixel predicted scale of its
  inverse depth's error (a network trained with a Laplace negative log-likelihood,
  :class:`pix2pix.networks.PlanesGenerator` with ``uncertainty``). Each observation then gets
  the predicted std of its offset along the normal, ``sigma``; ``weight``: the views are
  weighted by ``1 / sigma^2`` instead of ``cos^2``; ``trust``: the consistency uses the
  predicted variance in place of the spread, ``c = s0^2 / (s0^2 + mean sigma^2)``; ``both``:
  the ``1 / sigma^2`` weights and the product of the spread's and the prediction's consistency.
- ``reference_cloud: refined`` (the cascade, read by :func:`dss.pipeline.refine_with_reference`):
  the fusion's references are made from renders of the cloud after the DSS cycles and the
  outlier projection (with :func:`cascade_normals`), not of the input.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import torch

from .cameras import Cameras

log = logging.getLogger(__name__)

__all__ = ["FusionConfig", "PlaneObservations", "FusionSums", "FusionResult", "observe_planes", "fill_from_trusted",
           "fuse_planes", "cascade_normals", "UNCERTAINTY_MODES", "REFERENCE_CLOUDS"]

#: ``cameras -> (planes (V, H, W, 3), coverage mask (V, H, W) bool)``: the reference in the planes
#: channel; it may return a third tensor (V, H, W), the predicted Laplace scale of each pixel's
#: inverse depth (1 / bbox diagonals), read with ``FusionConfig.uncertainty``
PlaneReference = Callable[[Cameras], tuple]

#: FusionConfig.uncertainty: how a reference's predicted per-pixel uncertainty is used
UNCERTAINTY_MODES = ("off", "weight", "trust", "both")
#: FusionConfig.reference_cloud: what the fusion's references are rendered from
REFERENCE_CLOUDS = ("input", "refined")
#: the smallest predicted offset std, in pixel footprints (a network's scale can collapse to 0)
SIGMA_MIN_PX = 0.02


@dataclass
class FusionConfig:
    """Settings of :func:`fuse_planes` (lengths in units of the bounding-box diagonal).

    Attributes:
        passes: fusion passes; each re-fits the normals to the moved points and observes anew.
        batches, views: camera batches per pass, views per batch (fresh cameras for each).
        tau: depth window, a multiple of the noise level (``tau_min`` at least): a point takes a
            view's surface when it is within this distance of it along the ray.
        max_angle_deg: largest angle between the point's normal and the pixel's plane.
        min_cos: smallest |cos| between the camera ray and the point's normal.
        min_views: observations a point needs to move.
        consistency_px: ``s0`` of the consistency weight, in pixel footprints at the point ...
        consistency_noise: ... and at most this many noise levels.
        normal_k: neighbours of the PCA normals the points move along.
        image_normals: also return each point's normal as the references show it (the weighted
            mean of its views' plane normals, where it moved with consistency >= 0.5).
        fill_k, fill_min_weight: step 5 of the module docstring (``fill_k = 0``: off).
        uncertainty: ``off`` | ``weight`` | ``trust`` | ``both``: how a reference's predicted
            per-pixel uncertainty is used (module docstring); not ``off`` needs a reference that
            returns it.
        reference_cloud: ``input`` (the references are made from the input's renders, as in the
            DSS cycles) | ``refined`` (the cascade: from renders of the cloud the cycles and the
            outlier projection left; :func:`dss.pipeline.refine_with_reference`).
    """

    passes: int = 4
    batches: int = 2
    views: int = 12
    tau: float = 2.0
    tau_min: float = 0.005
    max_angle_deg: float = 45.0
    min_cos: float = 0.2
    min_views: int = 3
    consistency_px: float = 0.15
    consistency_noise: float = 0.2
    normal_k: int = 16
    image_normals: bool = True
    fill_k: int = 16
    fill_min_weight: float = 2.0
    # how much of its move each point makes (its consistency times this), and of the fill step:
    # 1 the full fusion, 0 none (the stage is skipped); weight_by_noise ({noise level: weight},
    # interpolated in log noise, dss.schedule) sets it from the cloud's noise when given
    weight: float = 1.0
    weight_by_noise: dict | None = None
    uncertainty: str = "off"
    reference_cloud: str = "input"

    def __post_init__(self):
        if self.uncertainty not in UNCERTAINTY_MODES:
            raise ValueError(f"fusion.uncertainty must be one of {list(UNCERTAINTY_MODES)}, got {self.uncertainty!r}")
        if self.reference_cloud not in REFERENCE_CLOUDS:
            raise ValueError(f"fusion.reference_cloud must be one of {list(REFERENCE_CLOUDS)}, "
                             f"got {self.reference_cloud!r}")
        if self.fill_k < 0 or self.fill_min_weight <= 0:
            raise ValueError(f"fusion.fill_k must be >= 0 and fill_min_weight > 0, got {self.fill_k}, "
                             f"{self.fill_min_weight}")
        for name in ("passes", "batches", "views", "min_views", "normal_k"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"fusion.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("tau", "tau_min", "consistency_px", "consistency_noise"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"fusion.{name} must be > 0, got {getattr(self, name)}")
        table = self.weight_by_noise or {}
        if not 0 <= float(self.weight) <= 1 or any(not (float(k) > 0 and 0 <= float(v) <= 1) for k, v in table.items()):
            raise ValueError(f"fusion.weight and the weights of weight_by_noise must be in [0, 1] (noise levels > 0), "
                             f"got {self.weight}, {self.weight_by_noise}")
        if not 0 < self.max_angle_deg <= 90:
            raise ValueError(f"fusion.max_angle_deg must be in (0, 90], got {self.max_angle_deg}")
        if not 0 <= self.min_cos < 1:
            raise ValueError(f"fusion.min_cos must be in [0, 1), got {self.min_cos}")

    def weight_at(self, noise: float) -> float:
        """The fusion's weight for a cloud of this noise level (``weight_by_noise`` or ``weight``)."""
        if self.weight_by_noise:
            from .schedule import interpolate_by_noise

            return interpolate_by_noise(self.weight_by_noise, float(noise))
        return float(self.weight)

    def depth_window(self, noise: float) -> float:
        """``tau`` in bounding-box diagonals for a noise level (std, same units)."""
        return max(self.tau_min, self.tau * float(noise))


@dataclass
class PlaneObservations:
    """What one batch of views says about every point (V views, N points).

    Attributes:
        offset: (V, N) signed distance along the point's normal from the point to the surface
            the view shows on its ray (0 where not ``ok``).
        ok: (V, N) bool, the observation counts (see the module docstring).
        weight: (V, N) ``cos^2`` of the ray to the normal (0 where not ``ok``).
        footprint: (V, N) world size of one pixel at the point's depth.
        normal: (V, N, 3) the pixel's plane normal in world space, signed like the point's normal.
        sigma: (V, N) the predicted std of ``offset`` (bbox diagonals) where the reference gave
            an uncertainty map, else None.
    """

    offset: torch.Tensor
    ok: torch.Tensor
    weight: torch.Tensor
    footprint: torch.Tensor
    normal: torch.Tensor
    sigma: torch.Tensor | None = None


def observe_planes(points: torch.Tensor, normals: torch.Tensor, cameras: Cameras, planes: torch.Tensor,
                   mask: torch.Tensor, tau: float, max_angle_deg: float = 45.0,
                   min_cos: float = 0.2, uncertainty: torch.Tensor | None = None) -> PlaneObservations:
    """Observations of ``points`` (N, 3) with unit ``normals`` (N, 3) in a ``planes`` render
    (V, H, W, 3) with coverage ``mask`` (V, H, W) from ``cameras``; see :class:`PlaneObservations`.
    ``uncertainty`` (V, H, W): the predicted Laplace scale ``b`` of each pixel's inverse depth
    (1 / bbox diagonals); the offset's std is then ``sqrt(2) b z_ref^2 |p . n| / z`` (the
    offset's derivative with respect to the inverse depth)."""
    V, H, W, _ = planes.shape
    pc = cameras.world_to_camera(points)  # (V, N, 3)
    z = pc[..., 2]
    zs = z.clamp_min(1e-6)
    f = cameras.focal.to(pc).reshape(-1, 1)
    u = pc[..., 0] / zs * f + cameras.principal[:, None, 0]
    v = pc[..., 1] / zs * f + cameras.principal[:, None, 1]
    px, py = u.floor().long(), v.floor().long()
    inside = (px >= 0) & (px < W) & (py >= 0) & (py < H) & (z > 1e-6)
    vi = torch.arange(V, device=points.device)[:, None].expand_as(px)
    pxc, pyc = px.clamp(0, W - 1), py.clamp(0, H - 1)
    a = planes[vi, pyc, pxc]  # (V, N, 3): the pixel's plane
    covered = mask[vi, pyc, pxc] & inside
    # the plane's inverse depth on the point's own ray (exact sub-pixel position)
    inv = (a[..., 0] * pc[..., 0] + a[..., 1] * pc[..., 1]) / zs + a[..., 2]
    z_ref = 1.0 / inv.clamp_min(1e-6)
    n_cam = torch.einsum("vij,nj->vni", cameras.R.to(normals), normals)
    ray = torch.nn.functional.normalize(pc, dim=-1)
    cos = (ray * n_cam).sum(-1)
    # the plane's normal facing the camera, compared with the point's normal turned the same way
    n_ref = -torch.nn.functional.normalize(a, dim=-1)
    n_pt = torch.where((cos < 0)[..., None], n_cam, -n_cam)
    agree = (n_ref * n_pt).sum(-1) >= math.cos(math.radians(max_angle_deg))
    ok = covered & (inv > 1e-6) & ((z_ref - z).abs() < tau) & agree & (cos.abs() >= min_cos)
    # q = the ray's point at depth z_ref; offset = (q - p) . n
    offset = ((z_ref / zs - 1.0) * (pc * n_cam).sum(-1))
    zero = torch.zeros_like(z)
    offset = torch.where(ok, offset, zero)
    weight = torch.where(ok, cos * cos, zero)
    footprint = zs / f
    n_world = torch.einsum("vji,vnj->vni", cameras.R.to(n_ref), n_ref)
    n_world = torch.where((n_world * normals[None]).sum(-1, keepdim=True) < 0, -n_world, n_world)
    sigma = None
    if uncertainty is not None:
        b = uncertainty.to(pc)[vi, pyc, pxc]
        sigma = math.sqrt(2.0) * b * z_ref * z_ref * (pc * n_cam).sum(-1).abs() / zs
        sigma = torch.where(ok, sigma.clamp_min(0) + SIGMA_MIN_PX * footprint, torch.ones_like(sigma))
    return PlaneObservations(offset, ok, weight, footprint, n_world, sigma)


class FusionSums:
    """Running per-point sums of observations over camera batches (float64)."""

    def __init__(self, n: int, device=None, uncertainty: str = "off"):
        z = lambda *s: torch.zeros(*s, dtype=torch.float64, device=device)  # noqa: E731
        self.count, self.w, self.wx, self.wxx, self.ws0 = z(n), z(n), z(n), z(n), z(n)
        self.wss = z(n)  # weighted predicted offset variance (uncertainty trust / both)
        self.wn = z(n, 3)
        if uncertainty not in UNCERTAINTY_MODES:
            raise ValueError(f"uncertainty must be one of {list(UNCERTAINTY_MODES)}, got {uncertainty!r}")
        self.uncertainty = uncertainty

    def add(self, obs: PlaneObservations, consistency_px: float, s0_max: float = math.inf) -> None:
        """Add a batch; ``s0 = min(consistency_px x footprint, s0_max)`` per observation."""
        w = obs.weight.double()
        if self.uncertainty != "off":
            if obs.sigma is None:
                raise ValueError(f"fusion.uncertainty={self.uncertainty} needs a reference that predicts its "
                                 "uncertainty (a model trained with it); this one returns planes only")
            var = obs.sigma.double() ** 2
            if self.uncertainty in ("weight", "both"):
                # inverse-variance weights, scaled so that an observation of one pixel footprint's
                # std weighs 1 (only ratios within a point matter)
                w = torch.where(obs.ok, (obs.footprint.double() ** 2) / var, torch.zeros_like(var))
            self.wss += (w * torch.where(obs.ok, var, torch.zeros_like(var))).sum(0)
        x = obs.offset.double()
        self.count += obs.ok.sum(0).double()
        self.w += w.sum(0)
        self.wx += (w * x).sum(0)
        self.wxx += (w * x * x).sum(0)
        self.ws0 += (w * (consistency_px * obs.footprint.double()).clamp_max(s0_max) ** 2).sum(0)
        self.wn += (w[..., None] * obs.normal.double()).sum(0)

    def estimate(self, min_views: int) -> dict:
        """Per point (N,): ``offset`` (weighted mean), ``spread`` (weighted std across views,
        Bessel-corrected by the observation count), ``consistency`` in [0, 1], ``count``, and
        ``normal`` (N, 3) the weighted mean plane normal (unit; 0 where unobserved)."""
        w = self.w.clamp_min(1e-300)
        m = self.wx / w
        n = self.count
        var = (self.wxx / w - m * m).clamp_min(0) * n / (n - 1).clamp_min(1)
        s0sq = self.ws0 / w
        enough = (n >= min_views) & (self.w > 0)
        cons = s0sq / (s0sq + var).clamp_min(1e-300)
        if self.uncertainty in ("trust", "both"):
            pred = s0sq / (s0sq + self.wss / w).clamp_min(1e-300)  # the predicted variance as the spread
            cons = pred if self.uncertainty == "trust" else cons * pred
        cons = torch.where(enough, cons, torch.zeros_like(m))
        normal = torch.nn.functional.normalize(self.wn, dim=1)
        return {"offset": torch.where(self.w > 0, m, torch.zeros_like(m)), "spread": var.sqrt(),
                "consistency": cons, "count": n, "normal": normal}


@dataclass
class FusionResult:
    """Output of :func:`fuse_planes`.

    Attributes:
        points: (N, 3) moved points.
        normals: (N, 3) normals: the references' (``image_normals``) where a point moved with
            consistency >= 0.5, elsewhere a PCA fit to the moved points, signed like the input's.
        consistency: (N,) the last pass's consistency weight.
        image_normal_mask: (N,) bool, where ``normals`` came from the references.
        passes: per pass: fraction of points observed (>= 1 and >= ``min_views`` views), mean
            consistency, mean and max |move| (bbox diagonals), the mean spread, seconds (of
            which rendering and mapping the references: ``reference_seconds``).
    """

    points: torch.Tensor
    normals: torch.Tensor
    consistency: torch.Tensor
    image_normal_mask: torch.Tensor
    passes: list = field(default_factory=list)
    config: dict = field(default_factory=dict)


def _pca_normals(points: torch.Tensor, like: torch.Tensor, k: int) -> torch.Tensor:
    from .pointcloud import estimate_normals

    n = estimate_normals(points, k=k, orient="none").to(points.device, points.dtype)
    return torch.where((n * like).sum(1, keepdim=True) < 0, -n, n)


def cascade_normals(points: torch.Tensor, like: torch.Tensor, k: int = 16) -> torch.Tensor:
    """The normals (N, 3) a refined cloud ``points`` (N, 3) is rendered with for the cascade's
    references (``reference_cloud: refined``): a PCA fit over ``k`` neighbours, signed like
    ``like`` (N, 3). Training data for a cascade model renders its inputs with this function too
    (:mod:`experiments.denoising.cascade`), so that the model sees at training what the job gives it."""
    return _pca_normals(points.float(), like.float(), int(k))


def fill_from_trusted(points: torch.Tensor, normals: torch.Tensor, consistency: torch.Tensor, k: int = 16,
                      min_weight: float = 2.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 5 of the module docstring: points (N, 3) with consistency below 1/2 move ``1 - c`` of
    the way onto the plane through their ``k`` nearest neighbours' consistency-weighted centroid,
    normal the neighbours' weighted mean normal (signed like the point's), where the weights sum
    to ``min_weight`` or more. Returns (points, moved (N,) bool)."""
    from .knn import knn

    nb = knn(points, k, exclude_self=True).idx.long()
    ok = nb >= 0
    nb = nb.clamp_min(0)
    w = torch.where(ok, consistency[nb], torch.zeros_like(consistency[nb]))  # (N, k)
    W = w.sum(1)
    centroid = (w[..., None] * points[nb]).sum(1) / W.clamp_min(1e-12)[:, None]
    nn_ = normals[nb]
    nn_ = torch.where((nn_ * normals[:, None]).sum(-1, keepdim=True) < 0, -nn_, nn_)
    nrm = torch.nn.functional.normalize((w[..., None] * nn_).sum(1), dim=1)
    dist = ((points - centroid) * nrm).sum(1)
    moved = (W >= min_weight) & (consistency < 0.5)
    step = torch.where(moved, (1 - consistency) * dist, torch.zeros_like(dist))
    return points - step[:, None] * nrm, moved


def fuse_planes(points: torch.Tensor, normals: torch.Tensor, reference: PlaneReference, sample_cameras: Callable[[], Cameras],
                config: FusionConfig | None = None, noise: float = 0.01,
                callback: Callable[[int, dict], None] | None = None) -> FusionResult:
    """Move ``points`` onto the surface the ``planes`` references show (module docstring).

    Args:
        points: (N, 3) float32 cloud in bounding-box-diagonal units (the apps normalise).
        normals: (N, 3) normals; only their signs are used (the points move along PCA normals
            re-fitted every pass, signed like these).
        reference: ``cameras -> (planes (V, H, W, 3), mask (V, H, W))`` reference images.
        sample_cameras: ``() -> Cameras`` with ``config.views`` fresh views per call.
        noise: the cloud's noise level (std, bbox diagonals): sets the depth window ``tau``.
        callback: ``callback(pass, stats)`` after every pass (the study's per-stage numbers).

    Returns:
        :class:`FusionResult`.
    """
    import time

    cfg = config or FusionConfig()
    tau = cfg.depth_window(noise)
    weight = cfg.weight_at(noise)
    p = points.detach().clone().float()
    signs = normals.detach().float()
    result_normals = None
    est = None
    stats = []
    for k in range(cfg.passes):
        t0 = time.perf_counter()
        n = _pca_normals(p, signs, cfg.normal_k)
        sums = FusionSums(len(p), p.device, cfg.uncertainty)
        t_ref = 0.0
        for _ in range(cfg.batches):
            cams = sample_cameras().to(p.device)
            with torch.no_grad():
                t1 = time.perf_counter()
                planes, mask, *extra = reference(cams)
                t_ref += time.perf_counter() - t1
                unc = extra[0] if extra and extra[0] is not None and cfg.uncertainty != "off" else None
                obs = observe_planes(p, n, cams, planes.to(p), mask.to(p.device), tau, cfg.max_angle_deg,
                                     cfg.min_cos, uncertainty=unc)
            sums.add(obs, cfg.consistency_px, cfg.consistency_noise * float(noise))
        est = sums.estimate(cfg.min_views)
        move = (weight * est["consistency"] * est["offset"]).float()
        p = p + move[:, None] * n
        filled = torch.zeros(len(p), dtype=torch.bool, device=p.device)
        if cfg.fill_k > 0:
            before = p
            p, filled = fill_from_trusted(p, n, est["consistency"].float(), cfg.fill_k, cfg.fill_min_weight)
            p = before + weight * (p - before)
            move = move + ((p - before) * n).sum(1)
        signs = n
        result_normals = n
        seen = est["count"] > 0
        s = {"pass": k, "observed": float(seen.double().mean()),
             "observed_min_views": float((est["count"] >= cfg.min_views).double().mean()),
             "consistency_mean": float(est["consistency"].mean()), "filled": float(filled.float().mean()),
             "move_mean": float(move.abs().mean()), "move_max": float(move.abs().max()),
             "spread_median": float(est["spread"][seen].median()) if bool(seen.any()) else float("nan"),
             "trusted": float((est["consistency"] >= 0.5).double().mean()),
             "tau": tau, "seconds": time.perf_counter() - t0, "reference_seconds": t_ref}
        stats.append(s)
        log.info("plane fusion pass %d: %.0f%% of points observed, consistency %.2f, mean move %.2g (max %.2g)",
                 k, 100 * s["observed"], s["consistency_mean"], s["move_mean"], s["move_max"])
        if callback is not None:
            callback(k, {**s, "points": p, "normals": n, "consistency": est["consistency"],
                         "image_normals": est["normal"].float(), "count": est["count"]})
    out_n = _pca_normals(p, result_normals, cfg.normal_k)
    use_img = torch.zeros(len(p), dtype=torch.bool, device=p.device)
    if cfg.image_normals and est is not None:
        use_img = (est["consistency"] >= 0.5) & (est["normal"].norm(dim=1) > 0.5)
        img_n = est["normal"].float()
        img_n = torch.where((img_n * out_n).sum(1, keepdim=True) < 0, -img_n, img_n)
        out_n = torch.where(use_img[:, None], img_n, out_n)
    cons = est["consistency"].float() if est is not None else torch.zeros(len(p))
    return FusionResult(p, out_n, cons, use_img, stats, asdict(cfg))
