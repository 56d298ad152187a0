"""Training data from real shapes (dss-prep shapes.real, noise_range; conf/prep_preset/real_planes):
the real tuning meshes join the generated families, every shape gets its own noise level from a
continuous range, and no held-out or open mesh can ever be rendered for training."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from data_prep.real_meshes import (
    DEFAULT_ROOT,
    RealDataError,
    load_split,
    load_training_mesh,
    resolve_root,
)
from data_prep.render_spec import RenderSpec, load_render_spec
from data_prep.shards import (
    REAL_FAMILY,
    PrepConfig,
    PrepConfigError,
    build_plan,
    fingerprint,
    generate_dataset,
    shape_noise,
)

ROOT = Path(__file__).resolve().parents[1]
SPLIT = load_split()["groups"]
NOT_FOR_TRAINING = set(SPLIT["held_out"]) | set(SPLIT["open"])


def _preset(name: str, *overrides: str):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("prep", overrides=[f"prep_preset={name}", *overrides])
    return PrepConfig.from_config(cfg), RenderSpec.from_config(cfg.render)


def test_real_planes_preset_plan_holds_no_held_out_or_open_mesh():
    pc, spec = _preset("real_planes")
    plan = build_plan(pc, spec)
    real = [s for s in plan.shapes if s.family == REAL_FAMILY]
    meshes = {s.mesh for s in real}
    assert meshes == set(SPLIT["tuning"])                       # every tuning mesh, nothing else
    assert not meshes & NOT_FOR_TRAINING
    assert all(s.shape_id.split("-")[1] not in NOT_FOR_TRAINING for s in plan.shapes)
    # the generated shapes are cpu_planes' (same ids, seeds and splits: its test split stays unseen)
    pc0, spec0 = _preset("cpu_planes")
    gen = {(s.shape_id, s.seed, s.split) for s in plan.shapes if s.family != REAL_FAMILY}
    assert gen == {(s.shape_id, s.seed, s.split) for s in build_plan(pc0, spec0).shapes}
    # a real mesh's samplings share one split, and no real mesh is in test
    by_mesh = {}
    for s in real:
        by_mesh.setdefault(s.mesh, set()).add(s.split)
    assert all(len(v) == 1 for v in by_mesh.values()) and not any("test" in v for v in by_mesh.values())
    assert sum(v == {"val"} for v in by_mesh.values()) == 1
    assert pc.noise_range == (0.0025, 0.015) and spec.shading == "planes" and tuple(spec.image_size) == (256, 256)


@pytest.mark.parametrize("group", ["held_out", "open", "cad"])
def test_other_real_groups_are_refused_for_training(group):
    with pytest.raises(PrepConfigError, match="may not be rendered for training"):
        _preset("real_planes", f"shapes.real.groups=[{group}]")
    for name in SPLIT[group][:2]:
        with pytest.raises(RealDataError, match="only \\['tuning'\\] meshes"):
            load_training_mesh(name)
    with pytest.raises(RealDataError, match="group None"):
        load_training_mesh("not-a-mesh")


def test_noise_range_draws_one_level_per_shape_in_the_range():
    pc, spec = _preset("tiny", "noise_range=[0.0025,0.015]")
    assert pc.noise_levels == (round(float(np.sqrt(0.0025 * 0.015)), 6),)
    plan = build_plan(pc, spec)
    levels = [shape_noise(pc, s, pc.noise_levels[0]) for s in plan.shapes]
    assert all(0.0025 <= x <= 0.015 for x in levels) and len(set(levels)) == len(levels)
    assert levels == [shape_noise(pc, s, pc.noise_levels[0]) for s in build_plan(pc, spec).shapes]
    for bad in ("noise_range=[0.01,0.005]", "noise_range=[0,0.01]", "noise_range=[0.01]"):
        with pytest.raises(PrepConfigError, match="noise_range"):
            _preset("tiny", bad)
    # a config without the new keys keeps its fingerprint's inputs (datasets made before still match)
    plain, _ = _preset("tiny")
    assert fingerprint(plain, spec) == fingerprint(PrepConfig(**{**plain.__dict__, "real_root": "/elsewhere"}), spec)


@pytest.mark.skipif(not (resolve_root(DEFAULT_ROOT) / "manifest.json").is_file(),
                    reason="the real meshes are not installed (dss-data real)")
def test_real_meshes_and_noise_range_in_a_small_dataset(tmp_path):
    """Pairs of a small config with the real tuning meshes: each real shape is a normalised
    sampling of its mesh, each shape's noisy cloud has the std the plan drew for it."""
    import json

    from data_prep.sampling import measured_noise_std

    seen = {}

    def renderer(points, normals, views, spec):  # records the clouds instead of rendering
        seen.setdefault(len(seen), np.asarray(points))
        H, W = spec.image_size
        return np.zeros((len(views), H, W, 3), np.float32), np.zeros((len(views), H, W), bool)

    pc = PrepConfig(seed=3, families=("torus",), shapes_per_family=2, resolution=28, val_fraction=0.1,
                    test_fraction=0.0, num_points=1500, normals_k=10, views_per_shape=1, shapes_per_shard=4,
                    real_groups=("tuning",), real_repeats=1, noise_range=(0.0025, 0.015))
    spec = load_render_spec(image_size=[16, 16], backend="reference")
    stats = generate_dataset(pc, spec, tmp_path, renderer=renderer, progress=False)
    assert stats["complete"]
    man = json.loads((tmp_path / "manifest.json").read_text())
    assert man["noise_range"] == [0.0025, 0.015] and man["config"]["real"]["meshes"] == SPLIT["tuning"]
    assert {s["mesh"] for s in man["shapes"] if s["family"] == REAL_FAMILY} == set(SPLIT["tuning"])
    stds = {p["shape_id"]: p["noise_std"] for p in man["pairs"]}
    assert len(set(stds.values())) == len(stds) == 2 + len(SPLIT["tuning"])
    clouds = list(seen.values())  # clean, noisy per shape (one slot)
    order = [shape for task in build_plan(pc, spec).tasks for shape in task.shapes]  # rendering order
    for k, shape in enumerate(order):
        clean, noisy = clouds[2 * k], clouds[2 * k + 1]
        ext = clean.max(0) - clean.min(0)
        assert abs(np.linalg.norm(ext) - 1.0) < 0.02  # a unit-diagonal frame
        assert measured_noise_std(clean, noisy) == pytest.approx(stds[shape.shape_id], rel=0.05)
