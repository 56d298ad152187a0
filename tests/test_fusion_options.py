"""The plane fusion's options for learned references (dss.fusion, dss.pipeline): a predicted
per-pixel uncertainty (``FusionConfig.uncertainty``) and the cascade (``reference_cloud:
refined``). Default settings keep the fusion as it was (tests/test_fusion.py)."""

from __future__ import annotations

import math

import pytest
import torch

from dss.cameras import look_at
from dss.fusion import FusionConfig, FusionSums, PlaneObservations, fuse_planes, observe_planes
from dss.render import RenderSettings, render


def _plane(n_side: int = 40):
    u, v = torch.meshgrid(torch.linspace(-0.35, 0.35, n_side), torch.linspace(-0.35, 0.35, n_side), indexing="ij")
    pts = torch.stack([u.reshape(-1), v.reshape(-1), torch.zeros(n_side * n_side)], 1)
    return pts.float(), torch.tensor([0.0, 0.0, 1.0]).expand(len(pts), 3).clone()


def _cams(n: int = 4, size: int = 96):
    eyes = torch.tensor([[0.0, 0.3, 1.8], [0.5, -0.2, 1.7], [-0.6, 0.1, 1.6], [0.1, 0.7, 1.5]])[:n]
    return look_at(eyes, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 110.0, (size, size))


def _obs(offsets, sigma, footprint=1.0):
    """Observations of one point by len(offsets) views."""
    v = len(offsets)
    return PlaneObservations(offset=torch.tensor(offsets, dtype=torch.float64)[:, None],
                             ok=torch.ones(v, 1, dtype=torch.bool), weight=torch.ones(v, 1, dtype=torch.float64),
                             footprint=torch.full((v, 1), footprint, dtype=torch.float64),
                             normal=torch.zeros(v, 1, 3), sigma=None if sigma is None else
                             torch.tensor(sigma, dtype=torch.float64)[:, None])


def test_uncertainty_modes_change_trust_and_weights():
    agree, unsure = [1.0, 1.0, 1.0, 1.0], [10.0, 10.0, 10.0, 10.0]
    est = {}
    for mode in ("off", "trust", "both"):
        s = FusionSums(1, uncertainty=mode)
        s.add(_obs(agree, unsure if mode != "off" else None), consistency_px=1.0)
        est[mode] = s.estimate(min_views=3)
    # the views agree exactly: the spread trusts them, a large predicted sigma does not
    assert est["off"]["consistency"][0] == pytest.approx(1.0)
    assert est["trust"]["consistency"][0] == pytest.approx(1 / (1 + 100.0))
    assert est["both"]["consistency"][0] == pytest.approx(1 / (1 + 100.0))
    # views that disagree, two of them sure: "weight" follows the sure ones
    offsets, sigma = [0.0, 0.0, 5.0, -3.0], [0.1, 0.1, 10.0, 10.0]
    s_off, s_w = FusionSums(1), FusionSums(1, uncertainty="weight")
    s_off.add(_obs(offsets, None), 1.0)
    s_w.add(_obs(offsets, sigma), 1.0)
    assert s_off.estimate(3)["offset"][0] == pytest.approx(0.5)
    assert abs(float(s_w.estimate(3)["offset"][0])) < 1e-3
    assert s_w.estimate(3)["consistency"][0] > 0.99 > 0.2 > s_off.estimate(3)["consistency"][0]


def test_uncertainty_needs_a_reference_that_predicts_it():
    with pytest.raises(ValueError, match="fusion.uncertainty"):
        FusionConfig(uncertainty="maybe")
    with pytest.raises(ValueError, match="reference_cloud"):
        FusionConfig(reference_cloud="clean")
    s = FusionSums(1, uncertainty="trust")
    with pytest.raises(ValueError, match="predicts its uncertainty"):
        s.add(_obs([1.0, 1.0, 1.0], None), 1.0)


def test_observed_sigma_is_the_offsets_std_from_the_inverse_depth_scale():
    """A reference whose inverse depth is off by db moves a point's offset by about
    sigma / sqrt(2) * db / b: the predicted std is the derivative times sqrt(2) b."""
    pts, nrm = _plane()
    cams = _cams(2)
    st = RenderSettings(K=8, sigma_scale=0.5, merge_fraction=0.04)
    out = render(pts, nrm, cams, st, shading="planes")
    b = 1e-3
    unc = torch.full(out.mask.shape, b)
    obs = observe_planes(pts, nrm, cams, out.images, out.mask, tau=0.02, uncertainty=unc)
    # the same surface 1e-3 farther in inverse depth: planes scale by (inv + d) / inv
    from dss.shading import planes_inverse_depth

    inv = planes_inverse_depth(out.images, cams)
    d = 1e-3
    shifted = out.images * ((inv + d) / inv.clamp_min(1e-6))[..., None]
    obs2 = observe_planes(pts, nrm, cams, shifted, out.mask, tau=0.02)
    ok = obs.ok & obs2.ok
    assert ok.float().mean() > 0.5
    moved = (obs2.offset - obs.offset).abs()[ok]
    footprint = obs.footprint[ok]
    pred = obs.sigma[ok] - 0.02 * footprint  # less the floor (SIGMA_MIN_PX)
    ratio = moved / (pred / (math.sqrt(2.0) * b) * d)
    assert (ratio - 1).abs().median() < 0.02, ratio.median()


def test_fusion_trusts_a_sure_reference_and_not_an_unsure_one():
    """One reference, two predicted uncertainties: with ``trust`` the fusion moves the points
    when the prediction is sure (scale << the consistency's s0) and leaves them when it is not."""
    pts, nrm = _plane()
    noisy = pts + 0.004 * torch.randn(pts.shape[0], 1, generator=torch.Generator().manual_seed(0)) * nrm
    st = RenderSettings(K=8, sigma_scale=0.5, merge_fraction=0.04)

    def ref(scale):
        def fn(cams):
            out = render(pts, nrm, cams, st, shading="planes")
            return out.images, out.mask, torch.full(out.mask.shape, scale)
        return fn

    cfg = FusionConfig(passes=1, batches=1, views=4, uncertainty="trust", fill_k=0)
    sure = fuse_planes(noisy, nrm, ref(1e-5), lambda: _cams(4), cfg, noise=0.004)
    unsure = fuse_planes(noisy, nrm, ref(1.0), lambda: _cams(4), cfg, noise=0.004)
    err = lambda r: (r.points[:, 2]).abs().median()  # noqa: E731  (the clean plane is z = 0)
    before = noisy[:, 2].abs().median()
    assert err(sure) < 0.3 * before and sure.passes[0]["trusted"] > 0.5
    assert unsure.passes[0]["trusted"] < 0.01 and err(unsure) > 0.95 * before


def test_cascade_renders_the_fusions_references_from_the_refined_cloud():
    """``reference_cloud: refined``: the cycles never call ``image_fn`` (the input's own renders
    are their references); the fusion calls it on renders of the refined cloud, which differ
    from the input's."""
    from scenes import sphere_points

    from data_prep.render_spec import load_render_spec, spec_path
    from dss.optimize import OptimizerConfig
    from dss.pipeline import refine_with_reference
    from experiments.denoising.reference_generators import SpecViewSampler

    pts, nrm = sphere_points(1500, 0.4)
    noisy = pts + 0.01 * torch.randn(pts.shape, generator=torch.Generator().manual_seed(2))
    spec = load_render_spec(spec_path("planes"), image_size=[48, 48])
    seen = []

    def fn(images):
        seen.append(images.clone())
        return images

    ocfg = OptimizerConfig(cycles=2, normal_steps=2, point_steps=1, views=2)
    runs = {}
    for cloud in ("input", "refined"):
        seen.clear()
        fcfg = FusionConfig(passes=1, batches=1, views=3, reference_cloud=cloud)
        res, ref = refine_with_reference(noisy, nrm, fn, config=ocfg, settings=spec.render_settings(),
                                         shading="planes", sampler=SpecViewSampler(spec, 2, seed=0),
                                         fusion=fcfg, fusion_cameras=SpecViewSampler(spec, 3, seed=1).sample,
                                         noise=0.01)
        runs[cloud] = (len(seen), res, ref)
    assert runs["input"][0] == 2 + 1          # two cycles and one fusion batch
    assert runs["refined"][0] == 1            # the fusion batch only
    assert runs["refined"][1].history["reference_calls_cycles"] == 2
    # the renderer handed back is the fusion's, holding the refined cloud (not the input)
    assert not torch.equal(runs["refined"][2].points, noisy.float())
    assert torch.isfinite(runs["refined"][1].points).all()
