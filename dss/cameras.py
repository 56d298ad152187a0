"""Batches of look-at pinhole cameras and view samplers.

Conventions (used everywhere in dss):
- world -> camera: ``X_cam = R @ X_world + t``; camera space has x right, y down, z forward,
  so a point in front of the camera has depth ``z > 0``.
- pixels: ``u = f * x / z + cx``, ``v = f * y / z + cy``; the centre of pixel (row i, column j)
  is at ``(u, v) = (j + 0.5, i + 0.5)``. Focal length and principal point are in pixels.
- ``image_size`` is ``(H, W)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = [
    "Cameras",
    "look_at",
    "focal_from_fov",
    "fit_distance",
    "ring_cameras",
    "fps_sphere_cameras",
    "fibonacci_sphere",
    "farthest_point_sampling",
]


@dataclass
class Cameras:
    """V pinhole cameras sharing one image size.

    Attributes:
        R: (V, 3, 3) world-to-camera rotations.
        t: (V, 3) world-to-camera translations.
        focal: (V,) focal lengths in pixels.
        principal: (V, 2) principal points (cx, cy) in pixels.
        image_size: (H, W) in pixels.
    """

    R: torch.Tensor
    t: torch.Tensor
    focal: torch.Tensor
    principal: torch.Tensor
    image_size: tuple[int, int]

    def __post_init__(self):
        V = self.R.shape[0]
        if self.R.shape != (V, 3, 3) or self.t.shape != (V, 3):
            raise ValueError(f"R must be (V,3,3) and t (V,3); got {tuple(self.R.shape)}, {tuple(self.t.shape)}")
        if V == 0:
            raise ValueError("a camera batch needs at least one view")
        self.focal = torch.as_tensor(self.focal, dtype=self.R.dtype, device=self.R.device).expand(V).contiguous()
        self.principal = torch.as_tensor(self.principal, dtype=self.R.dtype, device=self.R.device).expand(V, 2).contiguous()
        H, W = (int(s) for s in self.image_size)
        if H <= 0 or W <= 0:
            raise ValueError(f"image_size must be positive, got {self.image_size}")
        self.image_size = (H, W)

    def __len__(self) -> int:
        return self.R.shape[0]

    @property
    def device(self) -> torch.device:
        return self.R.device

    @property
    def centers(self) -> torch.Tensor:
        """(V, 3) camera centres in world coordinates."""
        return -(self.R.transpose(1, 2) @ self.t[..., None])[..., 0]

    def to(self, device) -> Cameras:
        return Cameras(self.R.to(device), self.t.to(device), self.focal.to(device), self.principal.to(device), self.image_size)

    def __getitem__(self, idx) -> Cameras:
        if isinstance(idx, int):
            idx = slice(idx, idx + 1)
        return Cameras(self.R[idx], self.t[idx], self.focal[idx], self.principal[idx], self.image_size)

    def world_to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) world points -> (V, N, 3) camera-space points."""
        return torch.einsum("vij,nj->vni", self.R, points) + self.t[:, None, :]

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Project (N, 3) world points: returns pixel coordinates (V, N, 2) and depths (V, N)."""
        pc = self.world_to_camera(points)
        z = pc[..., 2]
        zs = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
        uv = pc[..., :2] / zs[..., None] * self.focal[:, None, None] + self.principal[:, None, :]
        return uv, z

    def backproject(self, uv: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Pixel coordinates (V, M, 2) at depths (V, M) -> world points (V, M, 3)."""
        xy = (uv - self.principal[:, None, :]) / self.focal[:, None, None] * depth[..., None]
        pc = torch.cat([xy, depth[..., None]], dim=-1) - self.t[:, None, :]
        return torch.einsum("vji,vmj->vmi", self.R, pc)

    def to_dict(self) -> dict:
        """JSON-friendly description (eye, R, t, focal, principal, image size)."""
        return {
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "eye": self.centers.tolist(),
            "focal": self.focal.tolist(),
            "principal": self.principal.tolist(),
            "image_size": list(self.image_size),
        }


def focal_from_fov(fov_deg: float, width: int) -> float:
    """Focal length in pixels for a horizontal field of view in degrees."""
    return 0.5 * width / math.tan(math.radians(fov_deg) / 2)


def fit_distance(radius: float, fov_deg: float, margin: float = 1.05) -> float:
    """Camera distance at which a sphere of ``radius`` fills the field of view (times ``margin``)."""
    return margin * radius / math.sin(math.radians(fov_deg) / 2)


def _normalize(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), focal: float | torch.Tensor = 300.0,
            image_size: tuple[int, int] = (256, 256), principal=None) -> Cameras:
    """Cameras at ``eye`` (V, 3) looking at ``target`` with ``up`` as the image's up direction.

    ``up`` may be (3,) or (V, 3); where it is parallel to the viewing direction another
    world axis is used, so the result is always a proper rotation.
    """
    eye = torch.as_tensor(eye, dtype=torch.float32)
    if eye.ndim == 1:
        eye = eye[None]
    V = eye.shape[0]
    target = torch.as_tensor(target, dtype=torch.float32, device=eye.device).expand(V, 3)
    up = torch.as_tensor(up, dtype=torch.float32, device=eye.device).expand(V, 3)
    f = target - eye
    if (f.norm(dim=-1) < 1e-9).any():
        raise ValueError("look_at: eye and target coincide")
    f = _normalize(f)
    x = torch.cross(f, up, dim=-1)
    bad = x.norm(dim=-1) < 1e-6
    if bad.any():  # up parallel to the view direction: fall back to another axis
        alt = torch.tensor([0.0, 0.0, 1.0], device=eye.device).expand(V, 3)
        alt2 = torch.tensor([1.0, 0.0, 0.0], device=eye.device).expand(V, 3)
        x_alt = torch.cross(f, alt, dim=-1)
        x_alt = torch.where((x_alt.norm(dim=-1) < 1e-6)[:, None], torch.cross(f, alt2, dim=-1), x_alt)
        x = torch.where(bad[:, None], x_alt, x)
    x = _normalize(x)
    y = torch.cross(f, x, dim=-1)  # image y points down
    R = torch.stack([x, y, f], dim=1)
    t = -(R @ eye[..., None])[..., 0]
    H, W = image_size
    if principal is None:
        principal = torch.tensor([W / 2.0, H / 2.0])
    return Cameras(R, t, torch.as_tensor(focal, dtype=torch.float32), torch.as_tensor(principal, dtype=torch.float32), (H, W))


def fibonacci_sphere(n: int) -> torch.Tensor:
    """(n, 3) nearly uniform unit directions (Fibonacci lattice)."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    phi = torch.acos(1 - 2 * i / n)
    theta = math.pi * (1 + 5**0.5) * i
    return torch.stack([torch.cos(theta) * torch.sin(phi), torch.cos(phi), torch.sin(theta) * torch.sin(phi)], -1).float()


def farthest_point_sampling(points: torch.Tensor, n: int, start: int = 0) -> torch.Tensor:
    """Indices (n,) of a greedy farthest-point subset of (M, d) ``points``."""
    M = points.shape[0]
    if n > M:
        raise ValueError(f"cannot pick {n} of {M} points")
    idx = torch.empty(n, dtype=torch.long)
    idx[0] = start
    dist = (points - points[start]).square().sum(-1)
    for i in range(1, n):
        idx[i] = torch.argmax(dist)
        dist = torch.minimum(dist, (points - points[idx[i]]).square().sum(-1))
    return idx


def ring_cameras(n: int, center=(0.0, 0.0, 0.0), distance: float = 3.0, elevation_deg: float = 20.0,
                 focal: float = 300.0, image_size: tuple[int, int] = (256, 256), up=(0.0, 1.0, 0.0)) -> Cameras:
    """``n`` cameras evenly spaced on a horizontal ring (world y is up) looking at ``center``."""
    if n <= 0:
        raise ValueError(f"number of views must be positive, got {n}")
    az = torch.arange(n, dtype=torch.float32) * (2 * math.pi / n)
    el = math.radians(elevation_deg)
    d = torch.stack([torch.sin(az) * math.cos(el), torch.full_like(az, math.sin(el)), torch.cos(az) * math.cos(el)], -1)
    c = torch.as_tensor(center, dtype=torch.float32)
    return look_at(c + distance * d, c, up, focal, image_size)


def fps_sphere_cameras(n: int, center=(0.0, 0.0, 0.0), distance: float = 3.0, focal: float = 300.0,
                       image_size: tuple[int, int] = (256, 256), jitter: float = 0.1,
                       generator: torch.Generator | None = None, candidates: int = 1000,
                       up=(0.0, 1.0, 0.0), roll_deg: float = 0.0) -> Cameras:
    """``n`` cameras on a sphere around ``center`` by farthest-point sampling, with random jitter.

    Candidates are a Fibonacci lattice of ``candidates`` directions; the FPS start is random, each
    chosen direction is perturbed by Gaussian noise of std ``jitter`` (radians, roughly) and
    renormalised. ``roll_deg`` > 0 rotates each camera's up vector by a random angle in
    ``[-roll_deg, roll_deg]`` about the viewing direction (varied up-vectors for training data).
    """
    if n <= 0:
        raise ValueError(f"number of views must be positive, got {n}")
    dirs = fibonacci_sphere(max(candidates, n))
    start = int(torch.randint(len(dirs), (1,), generator=generator))
    d = dirs[farthest_point_sampling(dirs, n, start)]
    if jitter > 0:
        d = _normalize(d + jitter * torch.randn(d.shape, generator=generator))
    c = torch.as_tensor(center, dtype=torch.float32)
    up_v = torch.as_tensor(up, dtype=torch.float32).expand(n, 3).clone()
    if roll_deg > 0:
        ang = (torch.rand(n, generator=generator) * 2 - 1) * math.radians(roll_deg)
        f = -d
        # Rodrigues rotation of up about the viewing axis f
        up_v = (up_v * torch.cos(ang)[:, None] + torch.cross(f, up_v, dim=-1) * torch.sin(ang)[:, None]
                + f * (f * up_v).sum(-1, keepdim=True) * (1 - torch.cos(ang))[:, None])
    return look_at(c + distance * d, c, up_v, focal, image_size)
