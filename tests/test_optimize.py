"""Multi-view optimisation: convergence, regularisers in the loop, schedules, bad configs."""

import math

import pytest
import torch
from scenes import front_view_run, sphere_points

from dss.cameras import look_at
from dss.metrics import evaluate
from dss.optimize import (
    MultiViewOptimizer,
    OptimizationDiverged,
    OptimizerConfig,
    occlusion_counts,
    window_for_cycle,
)
from dss.render import RenderSettings, render
from dss.shading import SunLights

SUN = SunLights(ambient=0.3)


def _sphere_run(schedule="alternating", **kw):
    tp, tn = sphere_points(2000, 0.4)
    tp = tp + torch.tensor([0.05, -0.03, 0.0])
    sp, sn = sphere_points(800, 0.3)
    st = RenderSettings()

    def ref(cams):
        return render(tp, tn, cams, st, shading=SUN).images

    base = dict(cycles=2, normal_steps=2, point_steps=18, lr_points=1.0, lr_normals=200.0, momentum=0.0, lr_scale=1.0,
                schedule=schedule, projection_weight=0.0, repulsion_weight=0.0)
    base.update(kw)
    opt = MultiViewOptimizer(sp, sn, ref, OptimizerConfig(**base), st, center=(0, 0, 0), radius=0.5,
                             image_size=64, shading=SUN)
    return sp, tp, opt.run()


@pytest.mark.parametrize("schedule", ["alternating", "joint"])
def test_shifted_scaled_sphere_converges(schedule, cpp_backend):
    sp, tp, res = _sphere_run(schedule)
    before = evaluate(sp, tp).chamfer
    after = evaluate(res.points, tp).chamfer
    assert after < before / 10, (before, after)
    kinds = set(res.history["kind"])
    assert kinds == ({"normals", "points"} if schedule == "alternating" else {"joint"})
    assert torch.allclose(res.normals.norm(dim=1), torch.ones(len(res.normals)), atol=1e-5)


def _grid_run(repulsion_weight, shading="mask", **kw):
    """A 24x24 grid facing a fixed camera is pulled into a smaller disk (2D silhouette)."""
    g = (torch.arange(24, dtype=torch.float32) + 0.5) / 24 - 0.5
    u, v = torch.meshgrid(g, g, indexing="ij")
    sp = torch.stack([u.flatten(), v.flatten(), torch.zeros(576)], -1) * 0.7
    r = torch.sqrt(torch.rand(6000, generator=torch.Generator().manual_seed(0))) * 0.25
    a = torch.rand(6000, generator=torch.Generator().manual_seed(1)) * 2 * math.pi
    tp = torch.stack([r * torch.cos(a), r * torch.sin(a), torch.zeros(6000)], -1)
    res = front_view_run(sp, tp, shading, cycles=3, normal_steps=0, point_steps=20, lr_points=2.0,
                         repulsion_weight=repulsion_weight, window_start=8, window_end=4, **kw)
    p = res.points[:, :2]
    d = torch.cdist(p, p) + torch.eye(len(p)) * 10
    nn_dist = d.min(1).values
    return {"cv": float(nn_dist.std() / nn_dist.mean()), "radius": float(p.norm(dim=1).mean()),
            "in_disk": float((p.norm(dim=1) < 0.27).float().mean())}


def test_repulsion_keeps_a_2d_grid_spread(cpp_backend):
    without = _grid_run(0.0)
    with_rep = _grid_run(0.05)  # the default; the paper warns that gamma_r > 0.1 repels points off
    # At the start 47% of the grid lies inside the target disk. With repulsion the points fill
    # it evenly; without, they bunch up: nearest-neighbour spacing is less uniform.
    assert with_rep["in_disk"] > 0.7, with_rep
    assert with_rep["cv"] < without["cv"], (with_rep, without)


class _FixedView:
    """A view sampler that always returns the same cameras."""

    def __init__(self, cams):
        self.cams = cams

    def sample(self):
        return self.cams


def _noisy_plane(seed: int, focal: float = 100.0):
    """1500 points on z = 0 with 0.01 normal noise, +z normals, one camera above, and a
    reference that is the current render (the image term asks for nothing, so the regulariser
    acts alone). At focal 100 the plane fills the 32 px view; at 40 its silhouette is inside."""
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(1500, 2, generator=g) - 0.5) * 0.8
    pts = torch.cat([xy, 0.01 * torch.randn(1500, 1, generator=g)], 1)
    nrm = torch.tensor([0.0, 0.0, 1.0]).expand(1500, 3).clone()
    st = RenderSettings()
    cams = look_at(torch.tensor([[0.0, 0.0, 2.0]]), (0, 0, 0), (0, 1, 0), focal, (32, 32))

    def ref(c):
        return render(pts, nrm, c, st, shading=SUN).images

    return pts, nrm, st, _FixedView(cams), ref


def test_silhouette_term_pulls_the_outline_where_the_colours_barely_do(cpp_backend):
    """Dim shading (channels <= 0.04): the colour loss hardly moves the grid onto the disk; the
    coverage term (silhouette_weight) does, as a mask-shaded run would."""
    dim = SunLights(colors=0.02 * torch.eye(3), ambient=0.02)
    colour_only = _grid_run(0.0, shading=dim)
    with_sil = _grid_run(0.0, shading=dim, silhouette_weight=1.0)
    assert with_sil["in_disk"] > colour_only["in_disk"] + 0.3, (colour_only, with_sil)
    assert with_sil["radius"] < 0.8 * colour_only["radius"], (colour_only, with_sil)
    with pytest.raises(ValueError, match="silhouette_weight must be >= 0"):
        OptimizerConfig(silhouette_weight=-1.0)


def test_projection_flattens_a_noisy_plane_during_normal_steps():
    pts, nrm, st, sampler, ref = _noisy_plane(0)
    res = {}
    for w in (0.0, 300.0):  # absolute weights: L_p is tiny in these units (see regularizers)
        cfg = OptimizerConfig(cycles=1, normal_steps=10, point_steps=0, lr_normals=0.0, momentum=0.0, views=1,
                              projection_weight=w, repulsion_weight=0.0, regularizer_weighting="absolute",
                              lr_points=2.0, lr_scale=1.0, clip_point_grad=None)
        opt = MultiViewOptimizer(pts, nrm, ref, cfg, st, sampler=sampler, shading=SUN, image_size=32)
        res[w] = opt.run().points[:, 2].abs().mean().item()
    assert res[0.0] == pytest.approx(pts[:, 2].abs().mean().item())  # nothing moves without it
    assert res[300.0] < 0.5 * res[0.0]



def test_max_displacement_bounds_every_points_move():
    """OptimizerConfig.max_displacement: no point ends farther than the bound from its start (the
    final projection included), and the projection still flattens the plane within it."""
    from dss.optimize import bound_displacement

    pts, nrm, st, sampler, ref = _noisy_plane(0)
    pts = pts.clone()
    pts[0, 2] = 0.2  # a tail point the final projection would move 0.2
    moves = {}
    for bound in (0.0, 0.01):
        cfg = OptimizerConfig(cycles=1, normal_steps=10, point_steps=0, lr_normals=0.0, momentum=0.0, views=1,
                              projection_weight=300.0, repulsion_weight=0.0, regularizer_weighting="absolute",
                              lr_points=2.0, lr_scale=1.0, clip_point_grad=None, final_projection_k=32,
                              max_displacement=bound)
        out = MultiViewOptimizer(pts, nrm, ref, cfg, st, sampler=sampler, shading=SUN, image_size=32).run().points
        moves[bound] = (out - pts).norm(dim=1)
        if bound:
            assert float(moves[bound].max()) <= bound * (1 + 1e-5)
            assert out[1:, 2].abs().mean() < 0.8 * pts[1:, 2].abs().mean()
    assert float(moves[0.0].max()) > 0.1  # unbounded, the tail point goes all the way
    p = torch.tensor([[0.0, 0.0, 3.0], [0.1, 0.0, 0.0]])
    assert torch.allclose(bound_displacement(p, torch.zeros(2, 3), 1.0), torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="max_displacement"):
        OptimizerConfig(max_displacement=-1.0)


def test_final_projection_pulls_in_a_tail_point_after_the_last_cycle():
    """OptimizerConfig.final_projection_k: with no regulariser the outlier stays where it is;
    the final outlier projection puts it back on the plane and leaves the inliers untouched."""
    pts, nrm, st, sampler, ref = _noisy_plane(0)
    pts = pts.clone()
    pts[0, 2] = 0.2  # 20 noise sigmas above the plane
    out = {}
    for k in (0, 32):
        cfg = OptimizerConfig(cycles=1, normal_steps=2, point_steps=0, lr_normals=0.0, views=1,
                              projection_weight=0.0, repulsion_weight=0.0, final_projection_k=k)
        out[k] = MultiViewOptimizer(pts, nrm, ref, cfg, st, sampler=sampler, shading=SUN, image_size=32).run().points
    assert float(out[0][0, 2]) == pytest.approx(0.2)
    assert abs(float(out[32][0, 2])) < 0.03
    moved = (out[32] - out[0]).norm(dim=-1) > 0
    assert int(moved.sum()) < 0.02 * len(pts)
    # on a dense cloud the regularisers spread their neighbours (reg_dilation); the final projection
    # keeps the plain k nearest, whose plane follows the surface near tips
    from dss.regularizers import project_to_neighbour_planes

    cfg = OptimizerConfig(cycles=1, normal_steps=2, point_steps=0, views=1, final_projection_k=32, reg_dilation=5)
    assert cfg.min_points() == cfg.reg_k * 5 + 1  # the regularisers' list, not 32 x 5
    opt = MultiViewOptimizer(pts, nrm, ref, cfg, st, sampler=sampler, shading=SUN, image_size=32)
    plain = project_to_neighbour_planes(pts, 32, 1, threshold=cfg.final_projection_threshold,
                                        local_ratio=cfg.final_projection_local_ratio,
                                        iterations=cfg.final_projection_iterations)
    assert torch.equal(opt.project_outliers(pts), plain) and abs(float(plain[0, 2])) < 0.03
    with pytest.raises(ValueError, match="final_projection"):
        OptimizerConfig(final_projection_local_ratio=-1.0)
    with pytest.raises(ValueError, match="final_projection_iterations"):
        OptimizerConfig(final_projection_iterations=0)


def test_point_motion_along_normals_stops_tangential_drift():
    """point_motion="normal" moves each point only along its own normal (here +z, fixed); "free"
    also slides points sideways (the projection term pulls a point toward each tilted neighbour
    plane). "pca" moves along the weighted-PCA normal, which on this plane (noise half the point
    spacing) is itself tilted, so it slides too. All three flatten the plane."""
    pts, nrm, st, sampler, ref = _noisy_plane(1)
    xy = pts[:, :2]
    slide, flat = {}, {}
    for motion in ("free", "normal", "pca"):
        cfg = OptimizerConfig(cycles=1, normal_steps=10, point_steps=0, lr_normals=0.0, momentum=0.0, views=1,
                              projection_weight=300.0, repulsion_weight=0.0, regularizer_weighting="absolute",
                              lr_points=2.0, lr_scale=1.0, clip_point_grad=None, point_motion=motion)
        out = MultiViewOptimizer(pts, nrm, ref, cfg, st, sampler=sampler, shading=SUN, image_size=32).run().points
        slide[motion] = (out[:, :2] - xy).norm(dim=1).mean().item()
        flat[motion] = out[:, 2].abs().mean().item()
    assert slide["normal"] == 0.0
    assert slide["free"] > 1e-4 and slide["pca"] > 1e-4
    for motion in slide:
        assert flat[motion] < 0.5 * pts[:, 2].abs().mean().item()
    with pytest.raises(ValueError, match="point_motion"):
        OptimizerConfig(point_motion="sideways")


def test_per_point_weighting_does_not_depend_on_the_reference():
    """With "relative" weighting the projection strength is calibrated against the first image
    gradient, so a different reference changes how far the regulariser moves the points even when
    the images move nothing (here lr_normals 0, no point steps). "per_point" weighting does not.
    For "relative" the plane's silhouette is in view, so the black reference has a real image
    gradient (with the view filled, both image gradients were round-off and so were the
    differences); for "per_point" the view is filled."""
    moved = {}
    for weighting, w, focal in (("relative", 1.0, 40.0), ("per_point", 0.05, 100.0)):
        pts, nrm, st, sampler, ref_same = _noisy_plane(2, focal=focal)

        def ref_black(c, ref_same=ref_same):
            return torch.zeros_like(ref_same(c))

        for name, ref in (("same", ref_same), ("black", ref_black)):
            cfg = OptimizerConfig(cycles=1, normal_steps=5, point_steps=0, lr_normals=0.0, views=1,
                                  projection_weight=w, repulsion_weight=0.0, regularizer_weighting=weighting,
                                  lr_points=2.0, lr_scale=1.0, clip_point_grad=None)
            out = MultiViewOptimizer(pts, nrm, ref, cfg, st, sampler=sampler, shading=SUN, image_size=32).run()
            moved[weighting, name] = out.points
    # per_point: the same move for both references, up to float round-off (1e-8 here, against
    # moves of 5e-2; weight 0.5 scattered the plane and amplified the round-off)
    torch.testing.assert_close(moved["per_point", "same"], moved["per_point", "black"], atol=1e-6, rtol=0)
    assert (moved["per_point", "same"] - pts).abs().max() > 1e-2
    # relative weighting: how far the points move follows the reference's image gradient
    step = {name: float((moved["relative", name] - pts).abs().max()) for name in ("same", "black")}
    assert step["black"] > 10 * step["same"], step


def test_every_step_calibration_keeps_the_regulariser_step_size():
    """regularizer_calibration="every_step" re-normalises the relative regulariser every step
    (dss-deform), "once" fixes gamma at the first step (dss-denoise): as the plane flattens, the
    once-calibrated steps shrink with the residual, the re-normalised ones do not."""
    pts, nrm, st, sampler, _ = _noisy_plane(3)

    def ref_shifted(c):  # a real image gradient on the points (it sets the relative scale)
        return render(pts + torch.tensor([0.1, 0.0, 0.0]), nrm, c, st, shading=SUN).images

    last_step = {}
    for cal in ("once", "every_step"):
        cfg = OptimizerConfig(cycles=1, normal_steps=12, point_steps=0, lr_normals=0.0, momentum=0.0, views=1,
                              projection_weight=1e5, repulsion_weight=0.0, regularizer_calibration=cal,
                              lr_points=2.0, lr_scale=1.0, clip_point_grad=None)
        trail = []
        opt = MultiViewOptimizer(pts, nrm, ref_shifted, cfg, st, sampler=sampler, shading=SUN, image_size=32,
                                 callback=lambda step, state, trail=trail: trail.append(state["points"].clone()))
        opt.run()
        last_step[cal] = (trail[-1] - trail[-2]).norm(dim=1).mean().item()
    assert last_step["every_step"] > 1.5 * last_step["once"] > 0
    with pytest.raises(ValueError, match="regularizer_calibration"):
        OptimizerConfig(regularizer_calibration="sometimes")

def test_window_schedule_shrinks():
    cfg = OptimizerConfig(window_start=32, window_end=4, window_decay=0.5, window_samples=8)
    ws = [window_for_cycle(cfg, c) for c in range(6)]
    assert ws[0] == (32, 4) and ws[-1] == (4, 1)
    assert all(a[0] >= b[0] for a, b in zip(ws, ws[1:]))


def test_window_schedule_scales_with_the_image():
    """window_reference_size: windows given for 128 px double at 256 px, with the same number of
    samples per half window; without it the image size changes nothing."""
    cfg = OptimizerConfig(window_start=16, window_end=4, window_decay=0.9, window_samples=8, window_reference_size=128)
    assert window_for_cycle(cfg, 0, 128) == (16, 2) and window_for_cycle(cfg, 0, 256) == (32, 4)
    assert window_for_cycle(cfg, 30, 256) == (8, 1) and window_for_cycle(cfg, 30, 128) == (4, 1)
    plain = OptimizerConfig(window_start=16, window_end=4)
    assert window_for_cycle(plain, 0, 256) == window_for_cycle(plain, 0) == (16, 2)


def test_occlusion_counts_count_hidden_points():
    cams = look_at(torch.tensor([[0.0, 0.0, 3.0]]), (0, 0, 0), (0, 1, 0), 60.0, (32, 32))
    pts = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, 0.0]])  # the second hides behind the first
    nrm = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    out = render(pts, nrm, cams, RenderSettings(sigma=0.05, merge_threshold=0.1))
    assert occlusion_counts(out).tolist() == [0.0, 1.0]


def test_bad_configs_fail_clearly():
    with pytest.raises(ValueError, match="views per step must be positive"):
        OptimizerConfig(views=0)
    with pytest.raises(ValueError, match="lr_points must be >= 0"):
        OptimizerConfig(lr_points=-1.0)
    with pytest.raises(ValueError, match="schedule"):
        OptimizerConfig(schedule="sometimes")
    with pytest.raises(ValueError, match="nothing to do"):
        OptimizerConfig(cycles=0)
    with pytest.raises(ValueError, match="blowup_extent"):
        OptimizerConfig(blowup_extent=-1.0)


def test_finite_blowup_is_undone_and_reported(caplog):
    """lr_points=1e6: every point step throws the cloud far away (finite, so the NaN guard does
    not see it). Each such step is undone and the rates halved until they work; the result keeps
    the start's size and the halvings are reported."""
    with caplog.at_level("WARNING", logger="dss.optimize"):
        sp, tp, res = _sphere_run(cycles=1, normal_steps=0, point_steps=6, lr_points=1e6)
    extent = float((res.points.max(0).values - res.points.min(0).values).norm())
    start = float((sp.max(0).values - sp.min(0).values).norm())
    assert extent < 2 * start, (extent, start)
    assert res.history["lr_halvings"] >= 1 and res.history["rejected"]
    assert "grew the cloud" in res.history["rejected"][0]["why"]
    assert "learning rates halved" in caplog.text and "unstable" in caplog.text


def test_unrecoverable_blowup_raises_with_a_clear_message():
    with pytest.raises(OptimizationDiverged, match=r"diverged and did not recover.*2 halvings.*lower the learning rates"):
        _sphere_run(cycles=1, normal_steps=0, point_steps=6, lr_points=1e6, max_lr_halvings=2)


def test_loss_blowup_within_a_cycle_restores_the_cycle_start():
    """A loss far above its cycle's first (same cameras and references) undoes the cycle."""
    tp, tn = sphere_points(600, 0.4)
    st = RenderSettings()
    calls = {"n": 0}

    def ref(cams):
        return render(tp, tn, cams, st, shading=SUN).images

    cfg = OptimizerConfig(cycles=1, normal_steps=0, point_steps=4, lr_points=0.0, lr_normals=0.0,
                          projection_weight=0.0, repulsion_weight=0.0, blowup_loss=3.0)
    opt = MultiViewOptimizer(tp, tn, ref, cfg, st, center=(0, 0, 0), radius=0.5, image_size=32, shading=SUN)
    real = opt._image_loss

    def loss(images, target):  # the third step's loss is 100x the first
        calls["n"] += 1
        return (real(images, target) + 0.01) * (100.0 if calls["n"] == 3 else 1.0)

    opt._image_loss = loss
    res = opt.run()
    assert res.history["lr_halvings"] == 1
    assert "loss rose" in res.history["rejected"][0]["why"]
    assert math.isnan(res.history["loss"][2]) and torch.allclose(res.points, tp)


def test_deform_app_rejects_unknown_target(tmp_path):
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    from dss.pointcloud import PointCloudError
    from experiments.apps import deform

    conf = Path(deform.__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("deform", overrides=[f"target.path={tmp_path / 'missing.ply'}", f"+out_dir={tmp_path}"])
    with pytest.raises(PointCloudError, match="missing.ply: no such file"):
        deform.run(cfg)


def test_large_deformation_options():
    """bold driver halves the point lr after a worse step and regrows it up to the schedule;
    gradient smoothing keeps a constant field and damps noise; regulariser gammas are fixed
    after the first step; bad option values are refused."""
    sp, tp, _ = _sphere_run(cycles=1, normal_steps=0, point_steps=1)
    cfg = OptimizerConfig(cycles=1, normal_steps=1, point_steps=3, lr_scale=1.0, bold_driver=True, grad_smoothing=2,
                          normal_refresh="pca", projection_weight=0.1, repulsion_weight=0.05)
    tp2, tn2 = sphere_points(1000, 0.35)
    st = RenderSettings()
    opt = MultiViewOptimizer(sp, sp / sp.norm(dim=1, keepdim=True), lambda c: render(tp2, tn2, c, st, shading=SUN).images,
                             cfg, st, center=(0, 0, 0), radius=0.5, image_size=48, shading=SUN)
    res = opt.run()
    assert len(opt._reg_gamma) == 2
    gam = dict(opt._reg_gamma)
    lr0 = opt.opt_p.param_groups[0]["lr"]
    opt._bold_driver(True)
    assert opt.opt_p.param_groups[0]["lr"] == pytest.approx(lr0 * 0.5)
    for _ in range(60):  # x1.1 per step from at most a 2^k reduction
        opt._bold_driver(False)
    assert opt.opt_p.param_groups[0]["lr"] == pytest.approx(opt.opt_p.param_groups[0]["scheduled_lr"])
    opt._step("points", opt.sampler.sample(), torch.zeros(cfg.views, 48, 48, 3), 4, 1)
    assert opt._reg_gamma == gam  # calibrated once
    const = torch.ones(len(res.points), 3)
    assert torch.allclose(opt._smooth(const, 2), const)
    noise = torch.randn(len(res.points), 3, generator=torch.Generator().manual_seed(0))
    assert opt._smooth(noise, 2).std() < 0.6 * noise.std()
    assert torch.allclose(res.normals.norm(dim=1), torch.ones(len(res.normals)), atol=1e-5)
    with pytest.raises(ValueError, match="normal_refresh"):
        OptimizerConfig(normal_refresh="mls")


def test_every_deform_scene_composes_into_a_valid_optimizer_config():
    """Each conf/scene/*.yaml composes with conf/deform.yaml and its optimizer block is a valid
    OptimizerConfig (a mistyped key or a bad value fails here, not minutes into a run)."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    conf = Path(__file__).resolve().parents[1] / "conf"
    scenes = sorted(p.stem for p in (conf / "scene").glob("*.yaml"))
    assert {"sphere_teapot", "sphere_bunny", "cube_yoga", "grid_teapot"} <= set(scenes)
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        for scene in scenes:
            cfg = compose("deform", overrides=[f"scene={scene}"])
            opt = OptimizerConfig(**OmegaConf.to_container(cfg.optimizer, resolve=True))
            if scene.startswith("grid_teapot"):
                assert opt.hull_step == 0.0  # the paper's repulsion experiment, image term only
            else:
                assert opt.hull_step > 0
    assert OptimizerConfig().hull_step == 0.0 and OptimizerConfig().fill_step == 0.0  # the paper's optimiser


def test_frozen_gc_freezes_for_the_block_and_leaves_a_callers_freeze_alone():
    """dss.gc_pause.frozen_gc (around MultiViewOptimizer.run's cycles) freezes the objects alive
    at entry and unfreezes them at exit, and does neither when something is frozen already.
    Whether an object is frozen is read from gc.get_objects(), which lists the collected
    generations only. (Not by comparing freeze counts: a frozen object that another thread or a
    finaliser frees meanwhile lowers the count; such comparisons failed in clean-clone CI runs.)"""
    import gc

    from dss.gc_pause import frozen_gc

    def frozen(obj) -> bool:
        return not any(o is obj for o in gc.get_objects())

    assert gc.get_freeze_count() == 0
    ours = [object()]  # tracked by the collector until frozen
    assert not frozen(ours)
    with frozen_gc():
        assert gc.get_freeze_count() > 0 and frozen(ours)
        with frozen_gc():  # nested: no second freeze, no early unfreeze
            assert frozen(ours)
        assert frozen(ours)
    assert gc.get_freeze_count() == 0 and not frozen(ours)
    mine = [object()]
    gc.freeze()
    try:
        assert frozen(mine)
        with frozen_gc():
            pass
        assert gc.get_freeze_count() > 0 and frozen(mine)  # the caller's freeze stays
    finally:
        gc.unfreeze()
    assert gc.get_freeze_count() == 0 and not frozen(mine)


def test_frames_every_refits_the_planes_every_kth_step_and_keeps_the_differences_current():
    """frames_every=k fits the regularisers' weighted-PCA frames at the first step of a cycle and
    every k-th after it (the fit is the costly part); in between the frames' weights and planes
    are kept and only the point differences follow the points. frames_every=1 is the paper's
    every-step fit. Both flatten the plane; with stale planes each step does less (here, 10 steps
    of a strong projection: 30% vs 70% of the noise removed)."""
    from dss.regularizers import ProjectionLoss, RegularizerConfig, with_new_differences

    pts, nrm, st, sampler, ref = _noisy_plane(3)
    flat = {}
    for every, fits_expected in ((1, 10), (4, 3)):
        cfg = OptimizerConfig(cycles=1, normal_steps=10, point_steps=0, lr_normals=0.0, momentum=0.0, views=1,
                              projection_weight=300.0, repulsion_weight=0.0, regularizer_weighting="absolute",
                              lr_points=2.0, lr_scale=1.0, clip_point_grad=None, point_motion="normal",
                              frames_every=every)
        opt = MultiViewOptimizer(pts, nrm, ref, cfg, st, sampler=sampler, shading=SUN, image_size=32)
        fits = []
        fit = opt.proj.frames
        opt.proj.frames = lambda *a, fits=fits, fit=fit, **k: fits.append(1) or fit(*a, **k)
        flat[every] = opt.run().points[:, 2].abs().mean().item()
        assert len(fits) == fits_expected, (every, len(fits))
    start = pts[:, 2].abs().mean().item()
    assert flat[1] < 0.5 * start and flat[4] < 0.8 * start
    with pytest.raises(ValueError, match="frames_every"):
        OptimizerConfig(frames_every=0)
    # kept frames at unmoved points are the fitted ones; at moved points only diff changes
    proj = ProjectionLoss(RegularizerConfig(k=8))
    proj.set_initial_shape(pts)
    frames = proj.frames(pts, nrm)
    same = with_new_differences(frames, pts)
    assert torch.equal(same.diff, frames.diff) and same.weights is frames.weights
    moved = pts + torch.tensor([0.0, 0.0, 0.01]) * torch.arange(len(pts))[:, None] / len(pts)
    kept = with_new_differences(frames, moved)
    assert kept.normal is frames.normal and not torch.equal(kept.diff, frames.diff)


@pytest.mark.parametrize("momentum,nesterov", [(0.0, False), (0.9, False), (0.9, True)])
def test_sgd_matches_torch_optim(momentum, nesterov):
    """dss.sgd.SGD (no torch._dynamo import) makes torch.optim.SGD's steps, through a learning-rate
    change and a momentum reset as the optimiser's bold driver and normal refit make them."""
    from dss.sgd import SGD

    gen = torch.Generator().manual_seed(0)
    start = torch.randn(50, 3, generator=gen)
    grads = [torch.randn(50, 3, generator=gen) for _ in range(6)]
    ours, ref = start.clone().requires_grad_(True), start.clone().requires_grad_(True)
    a = SGD([ours], lr=0.05, momentum=momentum, nesterov=nesterov)
    b = torch.optim.SGD([ref], lr=0.05, momentum=momentum, nesterov=nesterov)
    for i, g in enumerate(grads):
        for opt, p in ((a, ours), (b, ref)):
            opt.zero_grad(set_to_none=True)
            p.grad = g.clone()
            if i == 2:
                opt.param_groups[0]["lr"] *= 0.5
            if i == 4:
                opt.state.clear()
            opt.step()
        assert torch.allclose(ours, ref, atol=1e-6, rtol=0), i
    assert not torch.equal(ours, start)
