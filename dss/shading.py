"""Per-point, per-view attributes ``w_k`` that the splats carry (the paper's Phi).

Every shader maps points (N,3), unit normals (N,3) and cameras to a (V, N, C) tensor; the
renderer blends these with the splat weights (Eq. sumI). All are differentiable in torch.

- :class:`SunLights`: diffuse shading under three orthogonal RGB sun lights fixed to the camera
  (the paper's default: the colour encodes the normal and does not depend on position).
- :class:`PointLight`: diffuse shading under a point light placed in camera space (the paper's
  training data for the denoiser); depends on position too.
- ``albedo``, ``normals`` (world-space unit normals, in [-1, 1]), ``depth`` (inverse camera
  depth 1/z), ``mask`` (ones: the blended image is coverage).
- ``planes``: the splat's tangent plane in camera space, as the coefficients ``a = n / (n . p)``
  of ``1/z = a . (x, y, 1)`` at normalised image coordinates ``(x, y)`` (not in the paper). A
  pixel's blended value is then a plane whose inverse depth is exact at the pixel for a flat
  surface, wherever the blended splats' centres lie, and whose direction is the surface normal:
  :func:`planes_inverse_depth` and :func:`planes_normals` read both back. A point's centre depth
  (``depth``) is not: at a tilted surface the cache's K front-most splats are those whose centres
  lie toward the camera, and their mean centre depth is in front of the surface (measured on the
  shipped example's clean cloud at 128 px: 0.9% of the bbox diagonal in front, against 0.1% for
  ``planes``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import torch

from . import reference
from .cameras import Cameras

__all__ = ["SunLights", "PointLight", "shade", "SHADING_CHANNELS", "plane_coefficients", "planes_inverse_depth",
           "planes_normals"]

SHADING_CHANNELS = {"sun": 3, "point": 3, "albedo": 3, "normals": 3, "depth": 1, "mask": 1, "planes": 3}


def _three_orthogonal_dirs() -> torch.Tensor:
    """Rows: three orthonormal directions (camera space) towards the lights.

    They are the rotated coordinate axes whose common diagonal (1,1,1)/sqrt(3) points at the
    viewer (-z in camera space), so every light shines on the visible hemisphere partly.
    A fresh copy of one computation (``render`` builds a ``SunLights`` per call; the dozen small
    torch operations below took ~0.3 ms of every optimisation step).
    """
    return _three_orthogonal_dirs_once().clone()


@functools.lru_cache(maxsize=1)
def _three_orthogonal_dirs_once() -> torch.Tensor:
    a = torch.tensor([1.0, 1.0, 1.0]) / math.sqrt(3.0)
    b = torch.tensor([0.0, 0.0, -1.0])
    v = torch.cross(a, b, dim=0)
    s, c = v.norm(), torch.dot(a, b)
    vx = torch.tensor([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    rot = torch.eye(3) + vx + vx @ vx * ((1 - c) / (s * s))
    return (rot @ torch.eye(3)).T.contiguous()


@dataclass
class SunLights:
    """Three orthogonal directional lights, red/green/blue, fixed relative to the camera.

    Attributes:
        directions: (3, 3) rows are camera-space unit vectors pointing *towards* each light.
        colors: (3, 3) rows are the RGB colour of each light.
        ambient: added to every channel (times albedo). 0.3 as in the official implementation: it
            keeps rendered channels away from 0, where SMAPE is discontinuous (|I - 0| / (|I| + eps)
            jumps from 0 to 1 while its gradient vanishes).
    """

    directions: torch.Tensor = field(default_factory=_three_orthogonal_dirs)
    colors: torch.Tensor = field(default_factory=lambda: torch.eye(3))
    ambient: float = 0.3

    def world_directions(self, cameras: Cameras, like: torch.Tensor) -> torch.Tensor:
        """(V, L, 3): the directions towards the lights in world space for each camera.

        (R_v n) . d_l = n . (R_v^T d_l), so shading needs the lights turned into world space
        instead of every normal rotated into every camera.
        """
        return torch.einsum("vij,li->vlj", cameras.R.to(like), self.directions.to(like))

    def one_light_per_channel(self) -> bool:
        """Whether light l colours channel l only (the default identity ``colors``)."""
        return self.colors.shape == (3, 3) and torch.equal(self.colors.cpu(), torch.eye(3, dtype=self.colors.dtype))

    def __call__(self, points, normals, cameras: Cameras, albedo=None) -> torch.Tensor:
        d_world = self.world_directions(cameras, normals)  # (V,L,3)
        V, L = d_world.shape[:2]
        if L == 3 and self.one_light_per_channel():  # red, green, blue lights (the default): no mixing
            return reference.sun_shade(normals, albedo, d_world, self.ambient)
        # one (N, 3) x (3, V L) product
        lam = (normals @ d_world.reshape(V * L, 3).T).clamp_min(0).view(-1, V, L)  # (N, V, L) diffuse terms
        # a K=L matmul is slow in BLAS for such thin matrices; broadcast instead
        rgb = (lam[..., :, None] * self.colors.to(normals)).sum(-2) + self.ambient
        rgb = rgb.permute(1, 0, 2)  # (V, N, 3)
        if albedo is not None:
            rgb = rgb * albedo[None]
        return rgb


@dataclass
class PointLight:
    """Diffuse shading under a point light at ``position`` in camera space.

    ``intensity * max(0, n . l) + ambient`` times the albedo (white by default), with ``l`` the
    unit vector from the point to the light. No distance falloff: the denoiser's training renders
    must not depend on the object's distance to the camera.
    """

    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    intensity: float = 1.0
    ambient: float = 0.1
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __call__(self, points, normals, cameras: Cameras, albedo=None) -> torch.Tensor:
        # world_to_camera's einsum gives (V, N, 3) with the xyz axis strided by N: reductions over
        # it (the norm below) ran ~25x slower than over contiguous rows (2.6 vs 0.1 ms at 2 x 20K)
        pc = cameras.world_to_camera(points).contiguous()  # (V,N,3)
        n_cam = torch.einsum("vij,nj->vni", cameras.R, normals).contiguous()
        light = torch.as_tensor(self.position, dtype=points.dtype, device=points.device)
        l_dir = light - pc
        l_dir = l_dir / l_dir.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        lam = (n_cam * l_dir).sum(-1, keepdim=True).clamp_min(0)
        col = torch.as_tensor(self.color, dtype=points.dtype, device=points.device)
        rgb = (self.intensity * lam + self.ambient) * col
        if albedo is not None:
            rgb = rgb * albedo[None]
        return rgb


def plane_coefficients(points: torch.Tensor, normals: torch.Tensor, cameras: Cameras,
                       min_cos: float = 0.05) -> torch.Tensor:
    """Per view, per point: the tangent plane's coefficients ``a = n_c / (n_c . p_c)`` (V, N, 3).

    ``n_c``, ``p_c``: the normal and the position in camera space. A point ``z (x, y, 1)`` of the
    camera ray through normalised image coordinates ``(x, y) = ((u - c_x) / f, (v - c_y) / f)``
    lies on the plane where ``1 / z = a . (x, y, 1)``. ``|n_c . p_c|`` is kept at least
    ``min_cos * |p_c|`` (with its sign): near edge-on splats would otherwise blend huge values
    into a pixel (their screen footprint stays a pixel wide through the low-pass filter).
    Units: 1 / world length. Differentiable in points and normals.
    """
    pc = cameras.world_to_camera(points)
    nc = torch.einsum("vij,nj->vni", cameras.R.to(normals), normals)
    nc = torch.nn.functional.normalize(nc, dim=-1)
    d = (nc * pc).sum(-1, keepdim=True)
    lim = min_cos * pc.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    d = torch.where(d < 0, torch.minimum(d, -lim), torch.maximum(d, lim))
    return nc / d


def _normalised_pixel_coords(cameras: Cameras, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    """(x (V, 1, W), y (V, H, 1)): normalised image coordinates of the pixel centres."""
    H, W = cameras.image_size
    j = torch.arange(W, dtype=dtype, device=device) + 0.5
    i = torch.arange(H, dtype=dtype, device=device) + 0.5
    f = cameras.focal.to(dtype).reshape(-1, 1, 1)
    c = cameras.principal.to(dtype)
    return (j[None, None, :] - c[:, 0, None, None]) / f, (i[None, :, None] - c[:, 1, None, None]) / f


def planes_inverse_depth(planes: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """Inverse camera depth 1/z (V, H, W) at the pixel centres of a ``planes`` render (V, H, W, 3);
    0 on the background (a plane of zeros)."""
    x, y = _normalised_pixel_coords(cameras, planes.dtype, planes.device)
    return planes[..., 0] * x + planes[..., 1] * y + planes[..., 2]


def planes_normals(planes: torch.Tensor, cameras: Cameras | None = None) -> torch.Tensor:
    """Unit normals (V, H, W, 3) of a ``planes`` render, facing the camera: in camera space, or
    in world space when ``cameras`` are given. Zero on the background."""
    n = torch.nn.functional.normalize(planes, dim=-1)
    n = -n  # a = n / (n . p) with n . p < 0 for a surface facing the camera: -a points at it
    if cameras is not None:
        n = torch.einsum("vji,vhwj->vhwi", cameras.R.to(n), n)
    return n


def shade(shading, points: torch.Tensor, normals: torch.Tensor, cameras: Cameras,
          colors: torch.Tensor | None = None) -> torch.Tensor:
    """Per-view point attributes (V, N, C) for ``shading``.

    Args:
        shading: ``"sun"``, ``"albedo"``, ``"normals"``, ``"depth"``, ``"planes"``, ``"mask"``, or a callable
            ``(points, normals, cameras, albedo) -> (V, N, C)`` such as :class:`PointLight`.
        colors: optional (N, 3) per-point albedo in [0, 1].
    """
    V, N = len(cameras), points.shape[0]
    if callable(shading):
        return shading(points, normals, cameras, colors)
    if shading == "sun":
        return SunLights()(points, normals, cameras, colors)
    if shading == "point":
        return PointLight()(points, normals, cameras, colors)
    if shading == "albedo":
        if colors is None:
            raise ValueError("shading='albedo' needs per-point colors")
        return colors[None].expand(V, N, colors.shape[1])
    if shading == "normals":
        return normals[None].expand(V, N, 3)
    if shading == "depth":
        _, z = cameras.project(points)
        return (1.0 / z.clamp_min(1e-6))[..., None]
    if shading == "planes":
        return plane_coefficients(points, normals, cameras)
    if shading == "mask":
        return points.new_ones(V, N, 1)
    raise ValueError(f"unknown shading {shading!r}; use one of {sorted(SHADING_CHANNELS)} or a callable")
