"""Surface regularisers of DSS: repulsion and projection on a weighted PCA.

Paper section "Surface regularization" and Appendix "Parameter discussion".

Notation (all per point ``i`` and neighbour ``k``):

* Neighbourhood: the ``k`` nearest other points of ``p_i`` (default 16, from
  :mod:`dss.knn`), restricted to ``||p_k - p_i|| <= D`` (the rest are masked out).
* Weights (paper Eq. psi, theta, phi)::

      psi_ik   = exp(-||p_i - p_k||^2 / D^2)
      theta_ik = exp(-(1 - n_k.n_i)^2 / max(1e-5, 1 - cos(Theta)))
      phi_ik   = 1 / (o_k + 1)
      w_ik     = psi_ik theta_ik phi_ik / sum_k' psi_ik' theta_ik' phi_ik'

  with ``o_k`` the occlusion count of point ``k`` over the current views (given by the
  caller; ``None`` means 0 for every point) and unit normals ``n`` (``None`` means theta = 1).
* Weighted PCA: weighted mean ``c_i = sum_k w_ik p_k``. The paper takes the SVD of the
  weighted vectors ``w_ik (p_k - c_i)``; its right singular vectors are the eigenvectors of
  ``C_i = sum_k w_ik^2 (p_k - c_i)(p_k - c_i)^T``, which we form directly and decompose (a
  3x3 ``eigh`` per point is much cheaper than an SVD of a K x 3 matrix per point): on the CPU
  with the C++ kernel ``dss/csrc/frames_cpu.cpp`` (the weights, centroid, covariance and a 3x3
  Jacobi in one pass per point), elsewhere with torch ops and batched :func:`torch.linalg.eigh`,
  its twin (``pca_backend``). ``covariance_weight="linear"`` uses the textbook
  ``sum_k w_ik (...)(...)^T`` instead. The two eigenvectors with the largest eigenvalues span
  the tangent plane (``V~``), the smallest one is the normal direction (``V_n``).
* Repulsion (paper)::

      L_r = 1/N sum_i sum_k psi_ik / (d_ik^2 + 1e-4),   d_ik = ||V~ V~^T (p_i - p_k)||

* Projection (paper Eq. projLoss)::

      L_p = 1/N sum_i sum_k w_ik d_ik^2,   d_ik = V_n^T (p_i - p_k)

  Because ``sum_k w_ik = 1`` and ``c_i`` is the ``w``-weighted mean, this splits exactly into
  ``((p_i - c_i).V_n)^2 + sum_k w_ik ((p_k - c_i).V_n)^2``: the squared distance of ``p_i``
  to its local weighted plane plus the weighted spread of the neighbourhood across that plane.
  Minimising it pulls ``p_i`` onto the plane *and* flattens its neighbourhood. We implement the
  paper's formula as written (``mode="paper"``, the default); ``mode="point_to_plane"`` keeps
  only the first part, ``((p_i - c_i).V_n)^2`` with ``c_i`` differentiable.

What is constant for autograd (and why):

* The neighbour sets (integer indices from a kNN).
* The PCA frame (``V~``, ``V_n``, ``c_i`` inside the covariance). Differentiating through a
  per-point eigen-decomposition is unstable: the gradient of ``eigh`` divides by eigenvalue
  gaps, which vanish on planar or isotropic neighbourhoods (exactly the configurations the
  regularisers produce) and give inf/NaN. The frame changes slowly between steps, so treating
  it as fixed for one step is a sound linearisation; the official DSS code detaches it too.
* The weights ``psi``, ``theta``, ``phi``, ``w`` and the normals. Differentiating ``psi``
  in the projection term would let a point lower its loss by running away from neighbours
  (shrinking their weight) instead of moving onto the plane, and in the repulsion term it
  would push points apart along the normal, off the surface. The official code detaches the
  weights as well.

Gradients therefore flow only through the gathered positions ``p_i - p_k`` (both ``p_i`` and
``p_k`` receive them): repulsion forces are purely tangential, projection forces purely normal.

Bandwidth: ``D = 4 sqrt(diag / N)`` (paper; ``diag`` = bounding-box diagonal of the *initial*
shape, ``N`` its number of points; note the paper's formula is not dimensionally a length, we
use it as written), ``Theta = pi/3``; for large deformations the projection term may use the
larger ``D = 0.1 sqrt(diag)`` (``bandwidth_rule="large"``) which pulls outliers to the nearest
surface. The modules fix ``D`` from the first point cloud they see unless it is given.

Neighbours are found with :func:`dss.knn.knn` on every call, or passed in by the caller
(``neighbors=``) to reuse one search for both terms or across steps (see
:func:`find_neighbors`).

Scale: both losses are sums over neighbours averaged over points, so the gradient on one point
is O(1/N). ``eps = 1e-4`` is an absolute squared length (the paper's constant), so ``L_r``
depends on the scene scale; the paper's shapes are normalised to a unit-size bounding box.
"""

from __future__ import annotations

import logging
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from dss import reference
from dss._ext import build_error, load_cpu
from dss.autograd import NeighbourDiff
from dss.knn import Neighbors, gather_neighbors, knn
from dss.pointcloud import all_finite, bbox_diagonal  # bbox_diagonal: re-exported

logger = logging.getLogger(__name__)

__all__ = [
    "RegularizerConfig",
    "LocalFrames",
    "RepulsionLoss",
    "ProjectionLoss",
    "bbox_diagonal",
    "default_bandwidth",
    "large_deformation_bandwidth",
    "bandwidth_for",
    "project_to_neighbour_planes",
    "find_neighbors",
    "local_frames",
    "repulsion_loss",
    "projection_loss",
]

DEFAULT_K = 16
DEFAULT_SHARPNESS = math.pi / 3
REPULSION_EPS = 1e-4


# ----------------------------------------------------------------------------- bandwidths


def default_bandwidth(diag: float, n: int) -> float:
    """Paper default ``D = 4 sqrt(diag / N)``."""
    if n < 1:
        raise ValueError(f"number of points must be >= 1, got {n}")
    return 4.0 * math.sqrt(max(diag, 0.0) / n)


def large_deformation_bandwidth(diag: float) -> float:
    """Paper's larger projection bandwidth for large deformation, ``D = 0.1 sqrt(diag)``."""
    return 0.1 * math.sqrt(max(diag, 0.0))


def bandwidth_for(points: torch.Tensor, rule: str = "default") -> float:
    """Bandwidth from an (initial) point cloud: ``rule`` is ``"default"`` or ``"large"``."""
    diag = bbox_diagonal(points)
    if rule == "default":
        d = default_bandwidth(diag, points.shape[0])
    elif rule == "large":
        d = large_deformation_bandwidth(diag)
    else:
        raise ValueError(f"unknown bandwidth rule {rule!r}; expected 'default' or 'large'")
    if not d > 0:
        raise ValueError(
            f"bandwidth rule {rule!r} gives D={d} for a cloud of {points.shape[0]} points with "
            f"bounding-box diagonal {diag}; give the bandwidth explicitly"
        )
    return d


# ----------------------------------------------------------------------------- config


@dataclass
class RegularizerConfig:
    """Settings of one regulariser term.

    Attributes:
        k: neighbours per point (paper: 16 in our default; the official code used 32).
        bandwidth: ``D`` in the scene's units; ``None`` = derive it from the first (initial)
            cloud with ``bandwidth_rule``.
        bandwidth_rule: ``"default"`` (4 sqrt(diag/N)) or ``"large"`` (0.1 sqrt(diag)).
        sharpness_angle: ``Theta`` in radians (pi/3).
        eps: repulsion's ``1e-4`` in ``psi / (d^2 + eps)``.
        projection_mode: ``"paper"`` or ``"point_to_plane"`` (see module docstring).
        covariance_weight: ``"squared"`` (paper: SVD of w-weighted vectors) or ``"linear"``.
        knn_backend: ``"auto"``, ``"cpp"``, ``"scipy"`` or ``"torch"`` (see :mod:`dss.knn`).
        pca_backend: ``"auto"``, ``"cpp"`` or ``"torch"``: the weighted PCA's implementation
            (see :func:`local_frames`).
        cutoff: neighbourhood radius as a multiple of ``D`` (paper: 1, neighbours within ``D``;
            ``inf``: all ``k`` nearest, weighted by psi). With 1, a point farther than ``D``
            from all its neighbours (a noise tail point, an outlier) has no neighbourhood and
            is never moved by the term.
        min_neighbors: the nearest ``min_neighbors`` neighbours count whatever their distance
            (0: the paper's cutoff alone). With a few, noise-tail points and outliers farther
            than the cutoff get a neighbourhood (weighted by psi like any other) and are moved.
    """

    k: int = DEFAULT_K
    bandwidth: float | None = None
    bandwidth_rule: str = "default"
    sharpness_angle: float = DEFAULT_SHARPNESS
    eps: float = REPULSION_EPS
    projection_mode: str = "paper"
    covariance_weight: str = "squared"
    knn_backend: str = "auto"
    pca_backend: str = "auto"
    cutoff: float = 1.0
    min_neighbors: int = 0

    def __post_init__(self):
        if int(self.min_neighbors) != self.min_neighbors or self.min_neighbors < 0:
            raise ValueError(f"min_neighbors must be a non-negative integer, got {self.min_neighbors}")
        if not self.cutoff > 0:
            raise ValueError(f"cutoff must be positive (a multiple of the bandwidth), got {self.cutoff}")
        if int(self.k) != self.k or self.k < 1:
            raise ValueError(f"k must be a positive integer, got {self.k}")
        if self.bandwidth is not None and not (
            self.bandwidth > 0 and math.isfinite(self.bandwidth)
        ):
            raise ValueError(f"bandwidth must be positive and finite, got {self.bandwidth}")
        if self.bandwidth_rule not in ("default", "large"):
            raise ValueError(
                f"bandwidth_rule must be 'default' or 'large', got {self.bandwidth_rule!r}"
            )
        if not self.eps > 0:
            raise ValueError(f"eps must be positive, got {self.eps}")
        if self.projection_mode not in ("paper", "point_to_plane"):
            raise ValueError(
                f"projection_mode must be 'paper' or 'point_to_plane', got {self.projection_mode!r}"
            )
        if self.covariance_weight not in ("squared", "linear"):
            raise ValueError(
                f"covariance_weight must be 'squared' or 'linear', got {self.covariance_weight!r}"
            )
        if self.pca_backend not in PCA_BACKENDS:
            raise ValueError(f"pca_backend must be one of {PCA_BACKENDS}, got {self.pca_backend!r}")


# ----------------------------------------------------------------------------- core


@dataclass
class LocalFrames:
    """Weighted-PCA frames of every point's neighbourhood.

    Attributes:
        idx: (N, K) int64 neighbour indices (-1 = none).
        valid: (N, K) bool, neighbour exists and lies within the bandwidth.
        diff: (N, K, 3) ``p_i - p_k`` (differentiable w.r.t. the points; zero where invalid).
        psi: (N, K) spatial weights (detached; 0 where invalid).
        weights: (N, K) normalised ``w_ik`` (detached; rows sum to 1, or 0 without neighbours).
        centroid: (N, 3) weighted mean ``c_i`` (detached).
        tangent: (N, 3, 2) the first two principal directions (detached).
        normal: (N, 3) the last principal direction (detached, unit, sign arbitrary).
        eigenvalues: (N, 3) ascending eigenvalues of the weighted covariance.
        bandwidth: the ``D`` used.
    """

    idx: torch.Tensor
    valid: torch.Tensor
    diff: torch.Tensor
    psi: torch.Tensor
    weights: torch.Tensor
    centroid: torch.Tensor
    tangent: torch.Tensor
    normal: torch.Tensor
    eigenvalues: torch.Tensor
    bandwidth: float


def find_neighbors(points: torch.Tensor, k: int = DEFAULT_K, *, backend: str = "auto",
                   dilation: int = 1) -> Neighbors:
    """The k nearest *other* points of every point (self excluded), for caching by the caller.

    ``dilation`` d > 1 keeps every d-th of the ``k * d`` nearest (the 1st, (d+1)-th, ...): a
    neighbourhood d times larger in point count (sqrt(d) in radius) at the cost of k neighbours
    per step; only the search itself sees ``k * d`` points.

    The result can be passed as ``neighbors=`` to :func:`repulsion_loss`,
    :func:`projection_loss`, :func:`local_frames` or the modules, e.g. once per optimisation
    cycle; the bandwidth mask is re-evaluated from the current positions on every call.
    """
    dilation = int(dilation)
    if dilation < 1:
        raise ValueError(f"dilation must be a positive integer, got {dilation}")
    nb = knn(points, k * dilation, exclude_self=True, backend=backend)
    if dilation == 1:
        return nb
    return Neighbors(idx=nb.idx[:, ::dilation].contiguous(), dist=nb.dist[:, ::dilation].contiguous())


# torch.linalg.eigh runs a batch of small matrices one after another on one thread (20K 3x3
# float64 matrices: 21 ms with 1 or 2 torch threads), and local_frames calls it every step:
# splitting the batch over torch's intra-op threads takes it to 12 ms on 2 cores, with the same
# bits (each matrix is decomposed on its own either way).
_EIGH_MIN_CHUNK = 4096
_eigh_pool: ThreadPoolExecutor | None = None
_eigh_pool_key = (0, 0)  # (process id, workers): a forked child gets the pool object without its threads
_eigh_pool_lock = threading.Lock()


def batched_eigh(mats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`torch.linalg.eigh` of a (B, n, n) CPU batch, split over torch's intra-op threads.

    Returns (eigenvalues (B, n) ascending, eigenvectors (B, n, n) as columns), equal to
    ``torch.linalg.eigh(mats)``. Small batches, other devices and tensors that require grad take
    the plain call.
    """
    threads = torch.get_num_threads()
    chunks = min(threads, mats.shape[0] // _EIGH_MIN_CHUNK)
    if chunks < 2 or mats.device.type != "cpu" or (torch.is_grad_enabled() and mats.requires_grad):
        return torch.linalg.eigh(mats)
    global _eigh_pool, _eigh_pool_key
    with _eigh_pool_lock:
        if _eigh_pool is None or _eigh_pool_key[0] != os.getpid() or _eigh_pool_key[1] < chunks:
            if _eigh_pool is not None and _eigh_pool_key[0] == os.getpid():
                _eigh_pool.shutdown(wait=False)  # its threads end once idle
            _eigh_pool = ThreadPoolExecutor(max_workers=chunks, thread_name_prefix="dss-eigh")
            _eigh_pool_key = (os.getpid(), chunks)
        pool = _eigh_pool
    parts = list(pool.map(torch.linalg.eigh, mats.tensor_split(chunks)))
    return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])


def _fit_planes(neighbours: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unweighted least-squares planes of (N, K, 3) neighbourhoods: centroids (N, 3) and unit
    normals (N, 3) (eigenvector of the smallest eigenvalue of the scatter matrix)."""
    centroid = neighbours.mean(1)
    centred = neighbours - centroid.unsqueeze(1)
    _, evecs = batched_eigh(torch.einsum("nki,nkj->nij", centred, centred))
    return centroid, evecs[..., 0]


def readmit_near_surface(candidates: torch.Tensor, surface: torch.Tensor, max_distance: float, k: int = 16,
                         max_spread: float = 4.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Which of ``candidates`` (M, 3) lie on ``surface`` (N, 3) after all: (mask (M,) bool, their
    points projected onto it (K, 3), the planes' unit normals there (K, 3)).

    A candidate lies on the surface when its distance to the plane of its ``k`` nearest surface
    points is at most ``max_distance`` and its offset from their centroid along that plane is at
    most ``max_spread`` x their in-plane spread (the std along the main axis): near the patch,
    a tip's last sample included, not on the plane's extension far away. Points removed as
    outliers before denoising because they are sparser than their neighbours (the tip of a horn
    at low noise) pass; junk off the surface does not.
    """
    if candidates.dim() != 2 or candidates.shape[1] != 3 or surface.dim() != 2 or surface.shape[1] != 3:
        raise ValueError("candidates and surface must be (M, 3) and (N, 3)")
    if len(candidates) == 0 or len(surface) <= k:
        empty = torch.zeros(0, 3, dtype=candidates.dtype)
        return torch.zeros(len(candidates), dtype=torch.bool), empty, empty
    with torch.no_grad():
        s = surface.detach().double()
        c = candidates.detach().double()
        nb = gather_neighbors(s, knn(s, k, query=c).idx)
        centroid = nb.mean(1)
        centred = nb - centroid.unsqueeze(1)
        evals, evecs = batched_eigh(torch.einsum("nki,nkj->nij", centred, centred) / nb.shape[1])
        normal = evecs[..., 0]
        d = c - centroid
        off = (d * normal).sum(-1)
        along = (d - off.unsqueeze(-1) * normal).norm(dim=-1)
        ok = (off.abs() <= float(max_distance)) & (along <= max_spread * evals[..., 2].clamp_min(0).sqrt())
        proj = c - off.unsqueeze(-1) * normal
        return ok, proj[ok].to(candidates.dtype), normal[ok].to(candidates.dtype)


def pull_rim_strays(points: torch.Tensor, k: int = 16, dilation: int = 1, *, ratio: float = 1.3,
                    target: float = 1.0, iterations: int = 2) -> tuple[torch.Tensor, int]:
    """Move points that lie beyond the rim of their own neighbourhood back to it. (N, 3) ->
    ((N, 3), number of points moved in the last iteration).

    A plane projection leaves a point on its neighbours' plane but not *within* their patch: at
    a thin or sharply curved part (an ear, a horn, a fingertip) noise pushes points off the tip,
    and the projection puts them on the plane of the tip, past its end, where no surface is.
    Measured on dss-denoise's outputs of real meshes at 1% noise, the points farthest from the
    clean surface sit within 1-2e-3 of their 16 neighbours' plane but 15-25e-3 from their
    centroid along it, more than the neighbourhood's own spread. For each point: the unweighted
    PCA of its ``k`` (x ``dilation``) nearest other points gives a centroid, a normal and the
    in-plane spread ``s`` (std along the main axis); a point whose in-plane offset from the
    centroid exceeds ``ratio * s`` moves along the plane to ``target * s`` from it (its offset
    along the normal is kept). Inside a sampled surface the offset is a small fraction of ``s``;
    on a true boundary of an open surface (a half disk) it is about 0.85 s, so ``ratio`` above
    1 leaves boundaries alone. ``iterations`` repeats with fresh neighbourhoods.
    """
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {tuple(points.shape)}")
    if points.shape[0] <= k * dilation:
        raise ValueError(f"{points.shape[0]} points are too few for {k} x {dilation} neighbours")
    if not (ratio > 0 and target > 0) or int(iterations) != iterations or iterations < 1:
        raise ValueError(f"ratio and target must be > 0 and iterations a positive integer, got {ratio}, {target}, "
                         f"{iterations}")
    moved = 0
    with torch.no_grad():
        p = points.detach().double().clone()
        for _ in range(int(iterations)):
            idx = find_neighbors(p, k, dilation=dilation).idx
            nb = gather_neighbors(p, idx)
            centroid = nb.mean(1)
            centred = nb - centroid.unsqueeze(1)
            evals, evecs = batched_eigh(torch.einsum("nki,nkj->nij", centred, centred) / nb.shape[1])
            normal = evecs[..., 0]
            spread = evals[..., 2].clamp_min(0).sqrt()
            d = p - centroid
            along = (d * normal).sum(-1, keepdim=True) * normal
            tangential = d - along
            length = tangential.norm(dim=-1)
            far = length > ratio * spread
            moved = int(far.sum())
            if moved == 0:
                break
            scale = torch.where(far, target * spread / length.clamp_min(1e-30), torch.ones_like(length))
            p = centroid + along + tangential * scale.unsqueeze(-1)
        return p.to(points.dtype), moved


def project_to_neighbour_planes(
    points: torch.Tensor,
    k: int = 32,
    dilation: int = 1,
    *,
    threshold: float = 0.0,
    local_ratio: float = 0.0,
    iterations: int = 1,
) -> torch.Tensor:
    """Move points onto the least-squares plane of their ``k`` nearest other points
    (unweighted PCA, no cutoff; ``dilation`` as in :func:`find_neighbors`). (N, 3) -> (N, 3).

    ``threshold`` 0 moves every point. ``threshold`` t > 0 moves only the *outliers*: points
    whose distance r_i to their neighbours' plane exceeds t * sigma, sigma = 1.4826 *
    median(r) (the residuals' robust scale, the std for Gaussian residuals); each outlier goes
    onto the plane of its ``k`` (x ``dilation``) nearest *inliers*, so a small clump of
    off-surface points no longer tilts its own plane. ``local_ratio`` q > 0 also requires
    r_i > q * median of its neighbours' r: near a sharp edge or a thin part every point is far
    from its neighbours' plane (the plane is wrong there, not the point), while a noise-tail
    point stands out from its neighbourhood. ``iterations`` repeats flag-and-project (a
    clump's last points are flagged once the others have moved). Inliers never move, so the
    surface's fine detail is kept.

    A one-shot, non-differentiable finishing step (``OptimizerConfig.final_projection_k``):
    unlike the projection term it reaches isolated noise-tail points, whose nearest neighbours
    lie beyond the bandwidth or are themselves off the surface (conf/denoise.yaml measures it).
    """
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {tuple(points.shape)}")
    if points.shape[0] <= k * dilation:
        raise ValueError(f"{points.shape[0]} points are too few for {k} x {dilation} neighbours")
    if not threshold >= 0:
        raise ValueError(f"threshold must be >= 0 (0: move every point), got {threshold}")
    if not local_ratio >= 0:
        raise ValueError(f"local_ratio must be >= 0 (0: no local test), got {local_ratio}")
    if int(iterations) != iterations or iterations < 1:
        raise ValueError(f"iterations must be a positive integer, got {iterations}")
    with torch.no_grad():
        p = points.detach().double().clone()  # never write into the caller's tensor
        for _ in range(int(iterations)):
            idx = find_neighbors(p, k, dilation=dilation).idx
            centroid, normal = _fit_planes(gather_neighbors(p, idx))
            offset = ((p - centroid) * normal).sum(-1)
            if threshold == 0:
                p = p - offset.unsqueeze(-1) * normal
                continue
            r = offset.abs()
            out = r > threshold * 1.4826 * r.median()
            if local_ratio > 0:
                out &= r > local_ratio * r[idx].median(1).values
            n_out = int(out.sum())
            if n_out == 0 or n_out > p.shape[0] - k * dilation:
                break
            inliers = p[~out]
            nb = knn(inliers, k * dilation, query=p[out]).idx[:, ::dilation]
            centroid, normal = _fit_planes(gather_neighbors(inliers, nb))
            off = ((p[out] - centroid) * normal).sum(-1, keepdim=True)
            p[out] = p[out] - off * normal
        return p.to(points.dtype)


def _check_inputs(points, normals, occlusion):
    if not isinstance(points, torch.Tensor) or points.dim() != 2 or points.shape[1] != 3:
        shape = tuple(points.shape) if isinstance(points, torch.Tensor) else type(points).__name__
        raise ValueError(f"points must be a (N, 3) tensor, got {shape}")
    n = points.shape[0]
    if not all_finite(points):
        raise ValueError("points contain NaN or inf coordinates")
    if normals is not None and tuple(normals.shape) != (n, 3):
        raise ValueError(f"normals must have shape ({n}, 3), got {tuple(normals.shape)}")
    if occlusion is not None:
        if tuple(occlusion.shape) != (n,):
            raise ValueError(
                f"occlusion counts must have shape ({n},), got {tuple(occlusion.shape)}"
            )
        if not bool(torch.isfinite(occlusion.float()).all()) or bool((occlusion < 0).any()):
            raise ValueError("occlusion counts must be finite and >= 0")


def _basis_from_normal(n: torch.Tensor) -> torch.Tensor:
    """(M, 3) unit normals -> (M, 3, 3) frames with columns [t1, t2, n]."""
    helper = torch.zeros_like(n)
    use_x = n[:, 0].abs() < 0.9
    helper[use_x, 0] = 1.0
    helper[~use_x, 1] = 1.0
    t1 = F.normalize(helper - (helper * n).sum(-1, keepdim=True) * n, dim=-1)
    t2 = torch.cross(n, t1, dim=-1)
    return torch.stack([t1, t2, n], dim=-1)


PCA_BACKENDS = ("auto", "cpp", "torch")


def _frames_kernel(points: torch.Tensor, pca_backend: str):
    """The C++ module local_frames should use, or None for the torch twin."""
    if pca_backend not in PCA_BACKENDS:
        raise ValueError(f"pca_backend must be one of {PCA_BACKENDS}, got {pca_backend!r}")
    if pca_backend == "torch":
        return None
    usable = points.device.type == "cpu" and points.dtype in (torch.float32, torch.float64)
    if pca_backend == "cpp" and not usable:
        raise ValueError(f"pca_backend='cpp' needs CPU float32/float64 points, got {points.dtype} on {points.device}")
    mod = load_cpu() if usable else None
    if mod is None and pca_backend == "cpp":
        raise RuntimeError(f"pca_backend='cpp' but the C++ kernel is unavailable: {build_error()}")
    return mod


def local_frames(
    points: torch.Tensor,
    normals: torch.Tensor | None = None,
    occlusion: torch.Tensor | None = None,
    *,
    bandwidth: float,
    k: int = DEFAULT_K,
    sharpness_angle: float = DEFAULT_SHARPNESS,
    covariance_weight: str = "squared",
    neighbors: Neighbors | None = None,
    backend: str = "auto",
    cutoff: float = 1.0,
    min_neighbors: int = 0,
    pca_backend: str = "auto",
) -> LocalFrames:
    """Weighted PCA of every point's neighbourhood (see module docstring).

    Args:
        points: (N, 3) positions (may require grad).
        normals: (N, 3) normals or None; normalised internally, zero normals stay zero.
        occlusion: (N,) occlusion counts ``o_k`` >= 0 or None (= 0).
        bandwidth: ``D``.
        k: neighbours per point (ignored if ``neighbors`` is given).
        sharpness_angle: ``Theta`` in radians.
        covariance_weight: ``"squared"`` (paper) or ``"linear"``.
        neighbors: precomputed :func:`find_neighbors` result (self excluded), or None.
        backend: kNN backend when searching.
        cutoff: neighbours farther than ``cutoff * D`` are masked out (paper: 1).
        min_neighbors: ... except the nearest ``min_neighbors`` (0: none; the neighbour lists
            are sorted by distance, as :func:`find_neighbors` returns them).
        pca_backend: ``"cpp"`` (the C++ kernel, dss/csrc/frames_cpu.cpp: CPU float32/float64
            points), ``"torch"`` (torch ops, its twin) or ``"auto"`` (the kernel where it applies
            and builds). They agree to the points' precision, not bit for bit, and the
            eigenvectors' signs may differ (see ``LocalFrames.normal``).

    Neighbourhoods with fewer than 3 valid neighbours have no well-defined plane; for those the
    frame is built from the given normal ``n_i`` when it is non-zero (else the PCA result, which
    is arbitrary but harmless: such rows carry little or no weight).
    """
    _check_inputs(points, normals, occlusion)
    if not bandwidth > 0:
        raise ValueError(f"bandwidth must be positive, got {bandwidth}")
    n_pts = points.shape[0]
    if neighbors is None:
        neighbors = find_neighbors(points, k, backend=backend)
    idx = neighbors.idx
    if idx.shape[0] != n_pts:
        raise ValueError(
            f"neighbour list has {idx.shape[0]} rows but there are {n_pts} points; recompute it"
        )
    if idx.device != points.device:
        idx = idx.to(points.device)

    if covariance_weight not in ("squared", "linear"):
        raise ValueError(
            f"covariance_weight must be 'squared' or 'linear', got {covariance_weight!r}"
        )
    mod = _frames_kernel(points, pca_backend)
    if mod is not None:
        # dss/csrc/frames_cpu.cpp: the detached weights and frames in one pass per point, the
        # differences with a scatter backward instead of torch's gather + index_put
        idx = idx.long()
        none = points.new_empty(0)
        denom = max(1e-5, 1.0 - math.cos(sharpness_angle))
        valid, psi, w, centroid, evals, evecs = mod.local_frames_forward(
            points.detach(), idx, none if normals is None else normals.detach(),
            none if occlusion is None else occlusion.detach(), (cutoff * bandwidth) ** 2,
            1.0 / (bandwidth * bandwidth), int(min_neighbors), 1.0 / denom, covariance_weight == "squared")
        diff = NeighbourDiff.apply(points, idx, valid)
        nrm = None  # only the few-neighbour fallback below needs the unit normals
    else:
        valid, diff, psi, w, centroid, evals, evecs, nrm = reference.local_frames(
            points, normals, occlusion, idx, bandwidth, sharpness_angle, covariance_weight, cutoff, min_neighbors)
    with torch.no_grad():
        if normals is not None:
            few = valid.sum(1) < 3
            if bool(few.any()):
                if nrm is None:
                    nrm = F.normalize(normals.detach(), dim=-1)
                fb = few & (nrm.norm(dim=-1) > 0.5)
                evecs[fb] = _basis_from_normal(nrm[fb])[..., [2, 0, 1]]
        # contiguous: a (N, 3) column view with stride 9 made every later reduction over xyz
        # (F.normalize of the optimiser's "pca" point motion) ~15x slower
        normal_dir = evecs[..., 0].contiguous()
        tangent = evecs[..., 1:3]
    return LocalFrames(
        idx=idx,
        valid=valid,
        diff=diff,
        psi=psi,
        weights=w,
        centroid=centroid,
        tangent=tangent,
        normal=normal_dir,
        eigenvalues=evals,
        bandwidth=float(bandwidth),
    )


def with_new_differences(frames: LocalFrames, points: torch.Tensor) -> LocalFrames:
    """``frames`` with ``diff`` recomputed from ``points`` (N, 3) (differentiable), its weights,
    centroids and principal directions kept: the regularisers' gradient at moved points under
    frames fitted a few steps before (the weighted PCA is the costly part of a step)."""
    if _frames_kernel(points, "auto") is not None:  # the C++ difference and its scatter backward
        diff = NeighbourDiff.apply(points, frames.idx, frames.valid)
    else:
        diff = reference.neighbor_diff(points, frames.idx, frames.valid)
    return replace(frames, diff=diff)


def repulsion_loss(
    points: torch.Tensor,
    normals: torch.Tensor | None = None,
    occlusion: torch.Tensor | None = None,
    *,
    bandwidth: float,
    k: int = DEFAULT_K,
    sharpness_angle: float = DEFAULT_SHARPNESS,
    eps: float = REPULSION_EPS,
    covariance_weight: str = "squared",
    neighbors: Neighbors | None = None,
    frames: LocalFrames | None = None,
    backend: str = "auto",
) -> torch.Tensor:
    """Repulsion ``L_r = 1/N sum_i sum_k psi_ik / (d_ik^2 + eps)`` (scalar).

    ``d_ik`` is ``p_i - p_k`` projected onto the tangent plane of ``i``'s weighted PCA.
    ``frames`` (from :func:`local_frames` with the same bandwidth) skips the PCA.
    """
    if frames is None:
        frames = local_frames(points, normals, occlusion, bandwidth=bandwidth, k=k, sharpness_angle=sharpness_angle,
                              covariance_weight=covariance_weight, neighbors=neighbors, backend=backend)
    n = points.shape[0]
    if n == 0:
        return points.sum() * 0.0
    t = torch.einsum("nkc,nct->nkt", frames.diff, frames.tangent)  # (N, K, 2)
    d2 = (t * t).sum(-1)
    return (frames.psi / (d2 + eps)).sum() / n


def projection_loss(
    points: torch.Tensor,
    normals: torch.Tensor | None = None,
    occlusion: torch.Tensor | None = None,
    *,
    bandwidth: float,
    k: int = DEFAULT_K,
    sharpness_angle: float = DEFAULT_SHARPNESS,
    mode: str = "paper",
    covariance_weight: str = "squared",
    neighbors: Neighbors | None = None,
    frames: LocalFrames | None = None,
    backend: str = "auto",
) -> torch.Tensor:
    """Projection ``L_p = 1/N sum_i sum_k w_ik (V_n^T (p_i - p_k))^2`` (scalar).

    ``mode="point_to_plane"`` gives ``1/N sum_i (V_n^T (p_i - c_i))^2`` instead (see module
    docstring for how the two relate).
    """
    if mode not in ("paper", "point_to_plane"):
        raise ValueError(f"projection mode must be 'paper' or 'point_to_plane', got {mode!r}")
    if frames is None:
        frames = local_frames(points, normals, occlusion, bandwidth=bandwidth, k=k, sharpness_angle=sharpness_angle,
                              covariance_weight=covariance_weight, neighbors=neighbors, backend=backend)
    n = points.shape[0]
    if n == 0:
        return points.sum() * 0.0
    if mode == "paper":
        dn = (frames.diff * frames.normal.unsqueeze(1)).sum(-1)  # (N, K)
        return (frames.weights * dn * dn).sum() / n
    # sum_k w_ik (p_i - p_k) = p_i - c_i, differentiable w.r.t. p_i and the p_k
    offset = (frames.weights.unsqueeze(-1) * frames.diff).sum(1)
    s = (offset * frames.normal).sum(-1)
    return (s * s).sum() / n


# ----------------------------------------------------------------------------- modules


class _SurfaceRegularizer(torch.nn.Module):
    def __init__(self, config: RegularizerConfig | None = None, **overrides):
        super().__init__()
        cfg = config if config is not None else RegularizerConfig()
        self.config = replace(cfg, **overrides) if overrides else cfg
        self._bandwidth = self.config.bandwidth

    @property
    def bandwidth(self) -> float | None:
        """The bandwidth ``D`` in use (None until fixed)."""
        return self._bandwidth

    def set_initial_shape(self, points: torch.Tensor) -> float:
        """Fix ``D`` from the initial shape with the configured rule; returns it."""
        self._bandwidth = bandwidth_for(points, self.config.bandwidth_rule)
        logger.info(
            "%s: bandwidth D=%.6g (rule %r, N=%d)",
            type(self).__name__,
            self._bandwidth,
            self.config.bandwidth_rule,
            points.shape[0],
        )
        return self._bandwidth

    def _resolve_bandwidth(self, points: torch.Tensor) -> float:
        if self._bandwidth is None:
            self.set_initial_shape(points)
        return self._bandwidth

    def find_neighbors(self, points: torch.Tensor) -> Neighbors:
        """Neighbour search with this term's k and backend (for caching by the caller)."""
        return find_neighbors(points, self.config.k, backend=self.config.knn_backend)

    def frames(self, points, normals=None, occlusion=None, neighbors=None) -> LocalFrames:
        """The weighted-PCA frames this term uses (shareable between terms of equal D)."""
        return local_frames(
            points,
            normals,
            occlusion,
            bandwidth=self._resolve_bandwidth(points),
            k=self.config.k,
            sharpness_angle=self.config.sharpness_angle,
            covariance_weight=self.config.covariance_weight,
            neighbors=neighbors,
            backend=self.config.knn_backend,
            cutoff=self.config.cutoff,
            min_neighbors=self.config.min_neighbors,
            pca_backend=self.config.pca_backend,
        )

    def extra_repr(self) -> str:
        return f"config={self.config}, bandwidth={self._bandwidth}"


class RepulsionLoss(_SurfaceRegularizer):
    """Module form of :func:`repulsion_loss`.

    ``forward(points (N,3), normals (N,3)|None, occlusion (N,)|None, neighbors=None,
    frames=None) -> scalar``. With ``config.bandwidth=None`` the bandwidth is fixed from the
    first cloud passed (the initial shape) or by :meth:`set_initial_shape`.
    """

    def forward(self, points, normals=None, occlusion=None, neighbors=None, frames=None):
        if frames is None:
            frames = self.frames(points, normals, occlusion, neighbors)
        return repulsion_loss(
            points, bandwidth=frames.bandwidth, eps=self.config.eps, frames=frames
        )


class ProjectionLoss(_SurfaceRegularizer):
    """Module form of :func:`projection_loss`.

    For large deformations use ``ProjectionLoss(bandwidth_rule="large")`` (D = 0.1 sqrt(diag)).
    """

    def forward(self, points, normals=None, occlusion=None, neighbors=None, frames=None):
        if frames is None:
            frames = self.frames(points, normals, occlusion, neighbors)
        return projection_loss(
            points, bandwidth=frames.bandwidth, mode=self.config.projection_mode, frames=frames
        )
