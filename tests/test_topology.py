"""Openings counted as silhouette holes (dss.topology): a torus has one, a sphere none, a membrane
across the torus's hole closes it, and sparse or noisy sampling does not invent or lose any."""

import math

import numpy as np
import pytest

from dss.topology import openings, silhouette_holes, view_directions


def _unit_diagonal(p):
    c = (p.max(0) + p.min(0)) / 2
    return (p - c) / np.linalg.norm(p.max(0) - p.min(0))


def _torus(n, R=1.0, r=0.35, seed=0):
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(0, 2 * math.pi, (2, n))
    return np.stack([(R + r * np.cos(b)) * np.cos(a), (R + r * np.cos(b)) * np.sin(a), r * np.sin(b)], -1)


def _sphere(n, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _disk(n, radius, seed=0):
    rng = np.random.default_rng(seed)
    r, a = radius * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * math.pi, n)
    return np.stack([r * np.cos(a), r * np.sin(a), np.zeros(n)], -1)


def test_view_directions_cover_a_hemisphere():
    d = view_directions(32)
    assert d.shape == (32, 3)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert d[:, 2].min() >= 0 and d[:, 2].max() > 0.95 and d[:, 2].min() < 0.05


def test_torus_has_one_opening_sphere_none():
    torus, sphere = _unit_diagonal(_torus(8000)), _unit_diagonal(_sphere(8000))
    ht = silhouette_holes(torus)
    assert ht.max() == 1
    assert ht[0] == 1  # seen from above (the first direction is near +z), the hole shows
    assert (ht == 0).any()  # edge-on it does not
    assert silhouette_holes(sphere).max() == 0


def test_membrane_across_the_hole_fills_the_opening():
    t = _torus(8000)
    with_membrane = _unit_diagonal(np.concatenate([t, _disk(3000, 1.0)]))
    res = openings(with_membrane, _unit_diagonal(t))
    assert res["openings_target"] == 1 and res["openings"] == 0
    assert res["views_missing_holes"] > 0 and res["views_extra_holes"] == 0
    assert len(res["holes"]) == len(res["holes_target"]) == res["views"]


def test_two_openings_side_by_side():
    two = np.concatenate([_torus(6000), _torus(6000, seed=1) + np.array([2.7, 0.0, 0.0])])
    assert silhouette_holes(_unit_diagonal(two)).max() == 2


@pytest.mark.parametrize("n,noise", [(5000, 0.0), (8000, 0.004)])
def test_sparse_or_noisy_sampling_keeps_the_count(n, noise):
    """Uneven sampling (5K uniformly random points: sparser and about as uneven as a deformation
    result's 8K) or noise of 0.4% of the diagonal makes pinholes and slits between the disks,
    not holes that hold a disk of min_hole_radius."""
    rng = np.random.default_rng(3)
    for shape, want in ((_torus(n), 1), (_sphere(n), 0)):
        p = _unit_diagonal(shape) + rng.normal(0, noise, (n, 3))
        assert silhouette_holes(p).max() == want


def test_a_sparse_patch_is_drawn_closed():
    """A patch of the surface sampled 6x sparser (as optimised surfaces are, here and there)
    renders closed with splats sized to the local spacing; the disks follow it (fixed disks of the
    dense part's size show it as holes)."""
    p = _sphere(20000, seed=4)
    cap = p[:, 2] > 0.5
    keep = ~cap | (np.random.default_rng(5).uniform(size=len(p)) < 1 / 6)
    q = _unit_diagonal(p[keep])
    assert silhouette_holes(q).max() == 0
    assert silhouette_holes(q, spacing_factor=0.0, point_radius=0.004).max() > 0


def test_bad_input_is_refused():
    with pytest.raises(ValueError):
        silhouette_holes(np.zeros((0, 3)))
    with pytest.raises(ValueError):
        view_directions(0)


def test_normal_error_to_points_is_unoriented_and_counts_flips():
    from dss.metrics import normal_error_to_points

    p = _sphere(500)
    flipped = p.copy()
    flipped[:100] *= -1
    res = normal_error_to_points(p, flipped, p, p)
    assert res["mean"] == pytest.approx(0.0, abs=1e-4)
    assert res["flipped_fraction"] == pytest.approx(0.2)
    tilted = normal_error_to_points(p, np.tile([0.0, 0.0, 1.0], (500, 1)), p, p)
    assert 40 < tilted["mean"] < 70  # a constant normal against a sphere's: about 57 deg on average


def test_deform_writes_normal_error_spacing_and_openings(tmp_path):
    """dss-deform's metrics.json carries the clean-surface and topology numbers."""
    import json
    from pathlib import Path

    import torch
    from hydra import compose, initialize_config_dir
    from scenes import sphere_points

    from dss.pointcloud import PointCloud, save_ply
    from experiments.apps.deform import run

    torch.set_num_threads(1)
    p, n = sphere_points(800, 0.4)
    target = tmp_path / "sphere.ply"
    save_ply(target, PointCloud(p, n))
    out = tmp_path / "deform"
    conf = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("deform", [f"target.path={target}", "start.points=300", "image_size=32",
                                 "optimizer.cycles=1", "optimizer.point_steps=2", "optimizer.normal_steps=1",
                                 "snapshot_steps=[0]", "chamfer_every=0", "progress=false", f"+out_dir={out}"])
    run(cfg)
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["normal_error_deg"]) == {"mean", "median", "p90", "flipped_fraction"}
    assert m["spacing"]["nn_cv"] > 0
    topo = m["topology"]
    assert topo["openings_target"] == 0 and topo["openings"] == 0  # sphere to sphere: none
    assert len(topo["holes"]) == topo["views"]
