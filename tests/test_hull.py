"""Visual-hull pull (dss.hull): nearest silhouette pixels, the displacement, and a membrane that
only the pull removes."""

import math

import torch
from scenes import front_view_run

from dss.cameras import look_at
from dss.hull import fill_displacement, hull_displacement, nearest_covered


def _front_camera(size=32, focal=40.0):
    return look_at(torch.tensor([[0.0, 0.0, 2.0]]), (0, 0, 0), (0, 1, 0), focal, (size, size))


def test_nearest_covered_pixel_centres():
    mask = torch.zeros(2, 5, 6, dtype=torch.bool)
    mask[0, 2, 4] = True
    near = nearest_covered(mask)
    assert near.shape == (2, 5, 6, 2)
    assert torch.equal(near[0, 0, 0], torch.tensor([4.5, 2.5]))  # (u, v) of pixel (i=2, j=4)
    assert torch.equal(near[0, 2, 4], torch.tensor([4.5, 2.5]))
    assert torch.isnan(near[1]).all()  # an empty view pulls nothing


def test_displacement_moves_outside_points_onto_the_silhouette_only():
    cams = _front_camera()
    H, W = cams.image_size
    ii, jj = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    mask = (((ii + 0.5 - 16) ** 2 + (jj + 0.5 - 16) ** 2) < 8.0**2)[None]  # a disk of radius 8 px
    near = nearest_covered(mask)
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.1, 0.0], [-0.4, -0.45, 0.2], [0.05, 0.05, 0.3], [2.0, 0.0, 0.0]])
    d, count = hull_displacement(pts, cams, mask, near)
    uv0, _ = cams.project(pts)
    assert uv0[0, 4, 0] > 32  # off the image: this view cannot judge it
    assert count[4] == 0 and torch.all(d[4] == 0)
    pts, d, count, uv0 = pts[:4], d[:4], count[:4], uv0[:, :4]
    inside0 = ((uv0[0] - 16).norm(dim=1) < 8)
    assert count.tolist() == [0 if b else 1 for b in inside0.tolist()]
    assert torch.all(d[inside0] == 0)
    uv1, z1 = cams.project(pts + d)
    r1 = (uv1[0] - 16).norm(dim=1)
    assert torch.all(r1[~inside0] < 8.0 + 0.75), r1  # onto a covered pixel centre
    z0 = cams.project(pts)[1]
    assert torch.allclose(z1, z0, atol=1e-5)  # a move parallel to the image plane


def test_fill_pulls_the_nearest_point_to_each_empty_reference_pixel():
    cams = _front_camera()
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.15, 0.0, -5.0]])  # the last is behind the camera
    target = torch.zeros(1, 32, 32, dtype=torch.bool)
    target[0, 16, 26] = True  # one reference pixel right of both points
    rendered = torch.zeros_like(target)
    d, count = fill_displacement(pts, cams, target, rendered)
    assert count.tolist() == [0, 1, 0]  # only the nearest point in front of the camera is pulled
    uv, z = cams.project(pts + d)
    assert torch.allclose(uv[0, 1], torch.tensor([26.5, 16.5]), atol=1e-4)  # onto the pixel centre
    assert torch.allclose(z, cams.project(pts)[1])
    assert torch.all(d[[0, 2]] == 0)
    d2, count2 = fill_displacement(pts, cams, target, target)  # a covered pixel pulls nothing
    assert count2.sum() == 0 and torch.all(d2 == 0)


def _annulus_run(hull_step):
    """A full disk of points facing one camera; the reference is a ring (a hole in the middle)."""
    g = (torch.arange(30, dtype=torch.float32) + 0.5) / 30 - 0.5
    u, v = torch.meshgrid(g, g, indexing="ij")
    sp = torch.stack([u.flatten(), v.flatten(), torch.zeros(900)], -1) * 0.6
    sp = sp[sp.norm(dim=1) < 0.3]
    gen = torch.Generator().manual_seed(0)
    r = torch.sqrt(0.15**2 + torch.rand(6000, generator=gen) * (0.3**2 - 0.15**2))
    a = torch.rand(6000, generator=gen) * 2 * math.pi
    tp = torch.stack([r * torch.cos(a), r * torch.sin(a), torch.zeros(6000)], -1)
    res = front_view_run(sp, tp, cycles=2, normal_steps=0, point_steps=15, lr_points=2.0, window_start=8, window_end=4,
                         hull_step=hull_step)
    return float((res.points[:, :2].norm(dim=1) < 0.12).float().mean())


def test_hull_pull_tears_a_membrane_the_image_gradient_keeps(cpp_backend):
    in_hole_before = 0.156  # the start disk's points over the hole (r < 0.12)
    without = _annulus_run(0.0)
    with_pull = _annulus_run(0.3)
    assert without > 0.9 * in_hole_before, without  # the visibility gradient leaves the membrane
    assert with_pull < 0.1 * without, (without, with_pull)


def _front_view_outliers(hull_views):
    """A sphere seen by one fixed camera on +z, plus points in front of it along the camera's
    axis: inside that view's silhouette, outside most others'. Only the hull pull moves points
    (no point rate, no regularisers). Returns the outliers' final distance from the centre."""
    from scenes import sphere_points

    from dss.cameras import look_at
    from dss.optimize import MultiViewOptimizer, OptimizerConfig
    from dss.render import RenderSettings, render

    tp, tn = sphere_points(1500, 0.3)
    out_p = torch.tensor([[0.0, 0.0, 0.55], [0.02, -0.01, 0.5], [-0.02, 0.02, 0.6]])
    sp = torch.cat([sphere_points(500, 0.3)[0], out_p])
    sn = torch.nn.functional.normalize(sp, dim=1)
    st = RenderSettings()
    cams = look_at(torch.tensor([[0.0, 0.0, 2.5]]), (0, 0, 0), (0, 1, 0), 60.0, (48, 48))

    class Fixed:
        def sample(self):
            return cams

    cfg = OptimizerConfig(views=1, cycles=2, normal_steps=0, point_steps=10, lr_points=0.0, projection_weight=0.0,
                          repulsion_weight=0.0, hull_step=0.3, hull_views=hull_views)
    opt = MultiViewOptimizer(sp, sn, lambda c: render(tp, tn, c, st).images, cfg, st, sampler=Fixed(),
                             center=(0, 0, 0), radius=0.7, image_size=48)
    return opt.run().points[-3:].norm(dim=1)


def test_extra_hull_views_pull_in_points_the_step_views_cannot_see_outside(cpp_backend):
    without = _front_view_outliers(0)
    with_views = _front_view_outliers(8)
    assert (without > 0.49).all(), without  # inside the one view's silhouette: no pull
    assert (with_views < 0.36).all(), with_views  # the side views' silhouettes pull them in
