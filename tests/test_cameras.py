import math

import pytest
import torch

from dss.cameras import fps_sphere_cameras, look_at, ring_cameras


def test_look_at_projects_target_to_principal_point():
    cams = look_at(torch.tensor([[0.0, 0, 3], [2.0, 1.0, -1.0]]), (0.0, 0.0, 0.0), focal=100.0, image_size=(64, 80))
    uv, z = cams.project(torch.zeros(1, 3))
    assert torch.allclose(uv[:, 0], torch.tensor([[40.0, 32.0], [40.0, 32.0]]), atol=1e-4)
    assert torch.allclose(z[:, 0], torch.tensor([3.0, math.sqrt(6.0)]), atol=1e-5)
    R = cams.R
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3).expand(2, 3, 3), atol=1e-6)
    assert torch.allclose(torch.linalg.det(R), torch.ones(2), atol=1e-6)
    assert torch.allclose(cams.centers, torch.tensor([[0.0, 0, 3], [2.0, 1.0, -1.0]]), atol=1e-5)


def test_image_y_points_down_and_x_right():
    cams = look_at(torch.tensor([[0.0, 0, 5]]), (0, 0, 0), up=(0, 1, 0), focal=100.0, image_size=(64, 64))
    uv, _ = cams.project(torch.tensor([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]))
    assert uv[0, 0, 1] < 32  # world up is image up (smaller row)
    assert uv[0, 1, 0] < 32  # looking down -z from +z with y up, world +x is right, -x left


def test_backproject_inverts_project():
    cams = ring_cameras(5, distance=4.0, focal=120.0, image_size=(50, 70))
    pts = torch.randn(30, 3) * 0.5
    uv, z = cams.project(pts)
    back = cams.backproject(uv, z)
    assert torch.allclose(back, pts.expand(5, 30, 3), atol=1e-4)


def test_up_parallel_to_view_is_handled():
    cams = look_at(torch.tensor([[0.0, 5.0, 0.0]]), (0, 0, 0), up=(0, 1, 0))
    assert torch.isfinite(cams.R).all()
    assert torch.allclose(torch.linalg.det(cams.R), torch.ones(1), atol=1e-5)


def test_fps_cameras_spread_and_seeded():
    g = torch.Generator().manual_seed(1)
    a = fps_sphere_cameras(12, distance=3.0, generator=g, jitter=0.05)
    b = fps_sphere_cameras(12, distance=3.0, generator=torch.Generator().manual_seed(1), jitter=0.05)
    assert torch.equal(a.R, b.R)
    c = a.centers
    assert torch.allclose(c.norm(dim=1), torch.full((12,), 3.0), atol=1e-4)
    d = torch.cdist(c, c) + torch.eye(12) * 10
    # 12 FPS directions on a sphere of radius 3 are far apart (icosahedron vertices: 3.15)
    assert d.min() > 1.5


def test_ring_rejects_zero_views():
    with pytest.raises(ValueError, match="positive"):
        ring_cameras(0)
