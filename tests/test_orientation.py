"""Normal orientation toward the views that see each point (dss.orientation) and its use in
the optimiser's per-cycle PCA re-fit (normal_orientation="views")."""

import torch
from scenes import sphere_points

from dss.cameras import fps_sphere_cameras, look_at
from dss.optimize import MultiViewOptimizer, OptimizerConfig
from dss.orientation import orient_to_views, view_orientation_vote, views_seeing
from dss.render import RenderSettings, render


def _random_signs(n, seed=0):
    return torch.where(torch.rand(n, generator=torch.Generator().manual_seed(seed)) < 0.5, -1.0, 1.0)[:, None]


def _cams(views=12, size=64):
    return fps_sphere_cameras(views, (0.0, 0.0, 0.0), 2.5, 80.0, (size, size), jitter=0.1,
                              generator=torch.Generator().manual_seed(0))


def test_views_seeing_finds_the_front_half_even_when_its_normals_face_away():
    """One camera on +z sees the sphere's front cap, whatever the normals' sign (no culling);
    the back half is hidden behind it."""
    p, n = sphere_points(1500, 0.4)
    cam = look_at([(0.0, 0.0, 2.5)], focal=80.0, image_size=(64, 64))
    seen = views_seeing(p, -n, cam, RenderSettings())[0]
    assert seen[p[:, 2] > 0.2].float().mean() > 0.9
    assert seen[p[:, 2] < -0.1].float().mean() < 0.02


def test_orient_to_views_turns_randomly_signed_sphere_normals_outward():
    p, n = sphere_points(1500, 0.4)
    signs = _random_signs(len(p))
    cams = _cams()
    out, unseen = orient_to_views(p, n * signs, cams, RenderSettings())
    assert unseen.float().mean() < 0.02
    outward = (out * n).sum(1) > 0
    assert outward.float().mean() > 0.98, outward.float().mean()
    # the vote's sign is what decides: outward normals vote positive where seen
    seen = views_seeing(p, n, cams, RenderSettings())
    assert (view_orientation_vote(p, n, cams, seen)[seen.any(0)] > 0).all()


def test_unseen_points_keep_the_fallback_sign():
    """A small sphere inside a large one: no view sees it, so its normals keep the sign of the
    fallback normals (here: inward), while the outer sphere's are turned outward."""
    po, no = sphere_points(1500, 0.4)
    pi, ni = sphere_points(200, 0.1)
    p, n = torch.cat([po, pi]), torch.cat([no, ni])
    fallback = torch.cat([no, -ni])
    out, unseen = orient_to_views(p, n * _random_signs(len(p), 1), _cams(), RenderSettings(), fallback=fallback)
    assert unseen[1500:].all() and unseen[:1500].float().mean() < 0.02
    assert ((out[1500:] * ni).sum(1) < 0).all()
    assert ((out[:1500] * no).sum(1) > 0).float().mean() > 0.98


def test_refit_signs_normals_by_the_views_not_by_the_normals_they_replace():
    """A sphere whose normals are tangent-ish and randomly signed (as after a large move): the
    "current" re-fit keeps the coin-flip signs, the "views" re-fit turns them outward."""
    p, n = sphere_points(1200, 0.35)
    t = torch.nn.functional.normalize(torch.cross(n, torch.tensor([[0.3, 1.0, 0.2]]).expand_as(n), dim=1), dim=1)
    start = torch.nn.functional.normalize(t + 0.05 * n * _random_signs(len(p), 2), dim=1)
    st = RenderSettings()

    def ref(cams):
        return render(p, n, cams, st, shading="mask").images

    def outward_after_refit(orientation):
        cfg = OptimizerConfig(cycles=1, normal_steps=1, point_steps=0, normal_refresh="pca",
                              normal_orientation=orientation, projection_weight=0.0, repulsion_weight=0.0)
        opt = MultiViewOptimizer(p, start, ref, cfg, st, center=(0, 0, 0), radius=0.4, image_size=48)
        opt._refresh_neighbourhoods(opt.sampler.sample())
        return float(((opt.normals.detach() * n).sum(1) > 0).float().mean())

    assert outward_after_refit("views") > 0.97
    assert 0.3 < outward_after_refit("current") < 0.7


def test_unknown_orientation_is_refused():
    import pytest

    with pytest.raises(ValueError, match="normal_orientation"):
        OptimizerConfig(normal_orientation="outward")


def test_final_normal_refresh_fits_the_output_normals_to_the_final_points():
    """After the last point steps the output's normals are the PCA normals of the final points,
    signed outward by the last cycle's views; without the option they are the normal steps'."""
    from dss.pointcloud import estimate_normals

    tp, tn = sphere_points(1500, 0.35)
    sp, sn = sphere_points(600, 0.25)
    st = RenderSettings()

    def run(final):
        cfg = OptimizerConfig(cycles=1, normal_steps=1, point_steps=4, lr_scale=1.0, lr_points=1.0, momentum=0.0,
                              normal_refresh="pca", normal_orientation="views", final_normal_refresh_k=final,
                              projection_weight=0.0, repulsion_weight=0.0)
        opt = MultiViewOptimizer(sp, sn, lambda c: render(tp, tn, c, st).images, cfg, st, center=(0, 0, 0),
                                 radius=0.4, image_size=48)
        return opt.run()

    res = run(16)
    pca = estimate_normals(res.points, k=16, orient="none")
    assert torch.allclose((res.normals * pca).sum(1).abs(), torch.ones(len(sp)), atol=1e-4)
    assert ((res.normals * torch.nn.functional.normalize(res.points, dim=1)).sum(1) > 0).float().mean() > 0.97
    plain = run(0)
    assert not torch.allclose((plain.normals * estimate_normals(plain.points, k=16, orient="none")).sum(1).abs(),
                              torch.ones(len(sp)), atol=1e-4)
