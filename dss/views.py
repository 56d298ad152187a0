"""View sampling for multi-view optimisation (paper section "Error-aware view sampling").

- :class:`SphereViewSampler`: farthest-point sampling of directions on a sphere around the
  object, randomly jittered, resampled whenever asked (every cycle in the optimiser).
- :func:`error_aware_cameras`: downsample the residual, take the largest-error pixel, focus on
  the mean of the K points projecting nearest to it, and place cameras on a small sphere
  around that focus.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .cameras import Cameras, fit_distance, focal_from_fov, fps_sphere_cameras, look_at

__all__ = ["SphereViewSampler", "error_aware_cameras", "largest_error_pixel"]


@dataclass
class SphereViewSampler:
    """Cameras on a sphere of radius ``distance`` around ``center`` looking at it.

    Attributes:
        center: (3,) look-at point; radius: the object's bounding-sphere radius (sets the
        distance so the object fills the field of view unless ``distance`` is given).
    """

    center: tuple[float, float, float]
    radius: float
    views: int = 12
    image_size: int = 256
    fov_deg: float = 30.0
    jitter: float = 0.1
    distance: float | None = None
    seed: int = 0

    def __post_init__(self):
        if self.views <= 0:
            raise ValueError(f"views per step must be positive, got {self.views}")
        self._gen = torch.Generator().manual_seed(int(self.seed))

    @property
    def focal(self) -> float:
        return focal_from_fov(self.fov_deg, self.image_size)

    def sample(self) -> Cameras:
        d = self.distance or fit_distance(self.radius, self.fov_deg)
        return fps_sphere_cameras(self.views, self.center, d, self.focal, (self.image_size, self.image_size),
                                  jitter=self.jitter, generator=self._gen)


def largest_error_pixel(residual: torch.Tensor, factor: int = 8) -> tuple[int, float, float]:
    """(view, u, v) of the largest error after ``factor`` x ``factor`` average pooling.

    Args:
        residual: (V, H, W) per-pixel error.
    Returns:
        view index and the pixel coordinates (u, v) of the pooled cell's centre.
    """
    V, H, W = residual.shape
    f = max(1, min(factor, H, W))
    pooled = F.avg_pool2d(residual[:, None], f, f)[:, 0]
    flat = int(torch.argmax(pooled))
    v, rem = divmod(flat, pooled.shape[1] * pooled.shape[2])
    i, j = divmod(rem, pooled.shape[2])
    return v, (j + 0.5) * f, (i + 0.5) * f


def error_aware_cameras(points: torch.Tensor, cameras: Cameras, residual: torch.Tensor, views: int,
                        k: int = 20, distance: float = 0.5, factor: int = 8,
                        generator: torch.Generator | None = None, jitter: float = 0.1) -> tuple[Cameras, torch.Tensor]:
    """Cameras around the region of largest image error.

    Args:
        points: (N, 3) current points; cameras: the views that produced ``residual`` (V, H, W).
        views: number of new cameras; k: points averaged into the focus; distance: radius of the
        small camera sphere (world units); factor: residual downsampling.
    Returns:
        (new cameras looking at the focus, focus (3,)).
    """
    v, u, vv = largest_error_pixel(residual, factor)
    uv, z = cameras[v].project(points.detach())
    d2 = (uv[0, :, 0] - u) ** 2 + (uv[0, :, 1] - vv) ** 2
    d2 = torch.where(z[0] > 0, d2, torch.full_like(d2, float("inf")))
    near = torch.topk(d2, min(k, len(d2)), largest=False).indices
    focus = points.detach()[near].mean(0)
    H, W = cameras.image_size
    fov = 2 * torch.atan(torch.tensor(W / 2.0) / cameras.focal[v]).item() * 180 / torch.pi
    cams = fps_sphere_cameras(views, focus.tolist(), distance, focal_from_fov(fov, W), (H, W), jitter=jitter, generator=generator)
    # Keep the cameras on the side of the view that saw the error (mirror the others through the
    # focus), so they do not look at the focus from inside the object.
    seen_from = cameras.centers[v] - focus
    eyes = cams.centers - focus
    flip = (eyes @ seen_from) < 0
    eyes = torch.where(flip[:, None], -eyes, eyes) + focus
    cams = look_at(eyes, focus, (0.0, 1.0, 0.0), cams.focal, (H, W))
    return cams, focus
