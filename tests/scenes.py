"""Small scenes and data helpers shared by the tests (import as `from scenes import ...`)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def sphere_points(n: int = 2000, radius: float = 1.0, center=(0.0, 0.0, 0.0)):
    """Fibonacci-sphere points (n,3) and outward unit normals."""
    from dss.cameras import fibonacci_sphere

    d = fibonacci_sphere(n)
    return d * radius + torch.tensor(center), d.clone()


def shared_file(name: str) -> Path:
    p = SHARED_DATA / name
    if not p.exists():
        pytest.skip(f"{p} is not present (../shared/data is optional for tests)")
    return p




def axis_camera(H: int = 128, W: int = 128, focal: float = 100.0):
    """One camera at the origin looking down +z (R = I, t = 0), principal point at the centre."""
    from dss.cameras import Cameras

    return Cameras(torch.eye(3)[None], torch.zeros(1, 3), torch.tensor([focal]), torch.tensor([[W / 2.0, H / 2.0]]), (H, W))


def random_scene(seed: int, n: int = 300, views: int = 3, size=(40, 56)):
    """Random points in front of a few cameras, normals roughly facing the cameras."""
    from dss.cameras import ring_cameras

    g = torch.Generator().manual_seed(seed)
    pts = (torch.rand(n, 3, generator=g) - 0.5) * 1.2
    nrm = torch.randn(n, 3, generator=g)
    nrm = nrm / nrm.norm(dim=1, keepdim=True)
    cams = ring_cameras(views, distance=3.0, elevation_deg=15.0, focal=60.0, image_size=size)
    sigma = 0.02 + 0.05 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return pts, nrm, cams, sigma, colors
