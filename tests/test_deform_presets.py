"""dss-deform's budget presets, the coarse-to-fine schedule and the presets chart command (fast,
toy sizes)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from scenes import sphere_points

from dss.optimize import MultiViewOptimizer, OptimizerConfig, window_for_cycle
from dss.pointcloud import PointCloud, save_ply
from dss.regularizers import bandwidth_for
from dss.render import RenderSettings, render
from experiments.deformation.budget import apply_budget
from experiments.deformation.stages import stage_configs, upsample

CONF = Path(__file__).resolve().parents[1] / "conf"
TOY = ["start.points=1500", "image_size=32", "optimizer.cycles=2", "optimizer.point_steps=2",
       "optimizer.normal_steps=1", "optimizer.hull_views=2", "snapshot_steps=[0]", "chamfer_every=0",
       "progress=false", "threads=1"]

torch.set_num_threads(1)


def _compose(overrides):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("deform", overrides)


def _target(tmp_path) -> Path:
    p, n = sphere_points(800, 0.4)
    path = tmp_path / "sphere.ply"
    save_ply(path, PointCloud(p, n))
    return path


def test_default_preset_changes_nothing_and_every_preset_is_a_valid_config():
    for scene in ("cube_yoga", "sphere_teapot", "sphere_bunny"):
        base = _compose([f"scene={scene}"])
        cfg = base.copy()
        note = apply_budget(cfg)
        assert note == {"preset": "default", "applied": {}, "kept": {}}
        assert OmegaConf.to_container(cfg) == OmegaConf.to_container(base)
        for preset in ("fast", "best"):
            cfg = _compose([f"scene={scene}", f"budget={preset}"])
            note = apply_budget(cfg)
            assert note["preset"] == preset and note["applied"]  # the preset changes something
            for key, value in note["applied"].items():
                assert OmegaConf.select(cfg, key) == value
            OptimizerConfig(**OmegaConf.to_container(cfg.optimizer, resolve=True))


def test_a_given_setting_wins_over_the_preset_and_bad_presets_are_refused():
    cfg = _compose(["scene=cube_yoga", "budget=best", "optimizer.cycles=3"])
    preset_cycles = OmegaConf.select(cfg.budgets.best, "optimizer.cycles")
    assert preset_cycles is not None and preset_cycles != 3
    note = apply_budget(cfg, given={"optimizer.cycles"})
    assert cfg.optimizer.cycles == 3 and note["kept"] == {"optimizer.cycles": 3}
    assert "optimizer.cycles" not in note["applied"]
    with pytest.raises(ValueError, match="no such preset"):
        apply_budget(_compose(["budget=huge"]))
    bad = _compose(["+budgets.odd={optimizer: {cylces: 3}}", "budget=odd"])
    with pytest.raises(ValueError, match="optimizer.cylces is no setting"):
        apply_budget(bad)


def test_upsample_keeps_the_coarse_points_and_adds_points_on_their_tangent_discs():
    p, n = sphere_points(500, 0.5)
    gen = torch.Generator().manual_seed(0)
    up, un = upsample(p, n, 1800, gen)
    assert up.shape == (1800, 3) and un.shape == (1800, 3)
    assert torch.equal(up[:500], p)
    src = torch.arange(1300) % 500
    off = up[500:] - p[src]
    along = (off * n[src]).sum(1)
    assert along.abs().max() < 1e-5  # in the tangent plane
    nn = torch.cdist(p, p).topk(2, largest=False).values[:, 1]
    assert (off.norm(dim=1) <= 0.5 * nn[src] + 1e-6).all()
    assert torch.allclose(un.norm(dim=1), torch.ones(1800), atol=1e-5)
    assert off.norm(dim=1).mean() > 0.2 * nn.mean()  # spread over the disc, not piled on the point
    same, _ = upsample(p, n, 300, gen)
    assert torch.equal(same, p[:300])


def test_the_fine_stage_continues_the_one_stage_schedule():
    c = OptimizerConfig(cycles=8, lr_points=50.0, lr_normals=500.0, lr_decay=0.7, window_start=16, window_end=4,
                        window_decay=0.9, fill_step=0.3, projection_bandwidth="large", normal_refresh="pca",
                        final_normal_refresh_k=32, error_aware_cycles=1)
    full, _ = sphere_points(2000, 0.3)
    coarse, fine = stage_configs(c, 3, full)
    assert coarse.cycles == 3 and coarse.error_aware_cycles == 0 and coarse.final_normal_refresh_k == 0
    assert fine.cycles == 5 and fine.error_aware_cycles == 1 and fine.final_normal_refresh_k == 32
    for k in range(fine.cycles):
        assert window_for_cycle(fine, k) == window_for_cycle(c, 3 + k)
    assert fine.lr_points == pytest.approx(50.0 * 0.7**3) and fine.lr_normals == pytest.approx(500.0 * 0.7**3)
    assert fine.fill_step == pytest.approx(0.3 * 0.7**3)
    assert fine.projection_bandwidth == pytest.approx(bandwidth_for(full, "large"))
    assert fine.repulsion_bandwidth == pytest.approx(bandwidth_for(full, "default"))
    with pytest.raises(ValueError, match="coarse.cycles"):
        stage_configs(c, 8, full)


def test_a_numeric_bandwidth_is_the_regularisers_bandwidth():
    p, n = sphere_points(400, 0.3)
    st = RenderSettings()
    cfg = OptimizerConfig(cycles=1, normal_steps=0, point_steps=1, projection_bandwidth=0.0123,
                          repulsion_bandwidth=0.0456)
    opt = MultiViewOptimizer(p, n, lambda cams: render(p, n, cams, st).images, cfg, st, center=(0, 0, 0),
                             radius=0.5, image_size=32)
    assert opt.proj.bandwidth == pytest.approx(0.0123) and opt.rep.bandwidth == pytest.approx(0.0456)
    rule = MultiViewOptimizer(p, n, lambda cams: render(p, n, cams, st).images,
                              OptimizerConfig(cycles=1, projection_bandwidth="large"), st, center=(0, 0, 0),
                              radius=0.5, image_size=32)
    assert rule.proj.bandwidth == pytest.approx(bandwidth_for(p, "large"))


def test_coarse_to_fine_run_records_its_stages(tmp_path):
    from experiments.apps.deform import run

    out = tmp_path / "run"
    cfg = _compose([f"target.path={_target(tmp_path)}", *TOY, "optimizer.cycles=3", "coarse.cycles=1",
                    "coarse.points=400", "coarse.image_size=24", f"+out_dir={out}"])
    m = run(cfg, given=set())
    assert [s["stage"] for s in m["stages"]] == ["coarse", "fine"]
    coarse, fine = m["stages"]
    assert coarse["image_size"] == 24 and fine["image_size"] == 32 and coarse["points"] < fine["points"]
    assert fine["points"] == m["points"] == 1500 and coarse["points"] == 400
    assert coarse["cycles"] == 1 and fine["cycles"] == 2
    assert m["steps"] == coarse["steps"] + fine["steps"] == 9
    assert m["cpu_time_s"] > 0 and m["budget"]["preset"] == "default"
    assert len(json.loads((out / "loss.json").read_text())["step"]) == 9


FAKE_DEFORM = """#!/usr/bin/env python3
import json, sys
import yaml
from experiments.evaluation.deform_presets import effective_config
args = dict(a.split("=", 1) for a in sys.argv[3:])
overrides = [a for a in sys.argv[3:] if not a.startswith(("hydra.", "overwrite="))]
open(args["hydra.run.dir"] + "/config.yaml", "w").write(yaml.safe_dump(effective_config(overrides)))
metrics = {"chamfer": {"fast": 3.0, "default": 2.0}[args["budget"]], "hausdorff": 60.0, "cpu_time_s": 10.0,
           "wall_time_s": 9.0, "steps": 5, "points": 300, "torch_threads": 1, "budget": {"preset": args["budget"]},
           "topology": {"openings": 1, "openings_target": 2, "holes_total": 3, "holes_total_target": 4,
                        "views_missing_holes": 1},
           "normal_error_deg": {"mean": 10.0, "flipped_fraction": 0.01}, "spacing": {"nn_cv": 0.5}}
open(args["hydra.run.dir"] + "/metrics.json", "w").write(json.dumps(metrics))
"""


def test_presets_chart_collects_resumes_and_counts_failures(tmp_path, monkeypatch, capsys):
    """The chart command's plumbing, with a stand-in for dss-deform that writes a metrics.json."""
    from experiments.evaluation import deform_presets

    fake = tmp_path / "fake_python"
    fake.write_text(FAKE_DEFORM)
    fake.chmod(0o755)
    monkeypatch.setattr(deform_presets, "PYTHON", str(fake))
    out = tmp_path / "chart"
    args = ["--scenes", "cube_yoga", "--presets", "default", "fast", "--out", str(out), "--set", "image_size=32"]
    assert deform_presets.main(args) == 0
    doc = json.loads((out / "presets.json").read_text())
    assert [(r["preset"], r["status"], r["chamfer"]) for r in doc["runs"]] == [("default", "ok", 2.0), ("fast", "ok", 3.0)]
    assert "image_size=32" in doc["runs"][0]["command"] and doc["targets"]["cube_yoga"]["chamfer"] == 1.5
    assert (out / "cube_yoga.png").stat().st_size > 0
    assert "| `cube_yoga` | fast | 3.00 | 60.0 | 1 (2) |" in (out / "presets.md").read_text()
    fake.write_text("#!/bin/sh\nexit 3\n")  # resumed: a finished run is not run again
    capsys.readouterr()
    assert deform_presets.main(args) == 0 and capsys.readouterr().out.count("done before") == 2
    assert deform_presets.main([*args[:3], "default", "best", "huge", *args[5:]]) == 2  # failures count
    doc = json.loads((out / "presets.json").read_text())
    assert [r["status"] for r in doc["runs"]] == ["ok", "failed", "failed"]
    assert doc["runs"][1]["why"] == "exit 3" and "no such preset" in doc["runs"][2]["why"]
    saved = out / "runs" / "cube_yoga" / "default" / "config.yaml"  # other settings: run again
    saved.write_text(saved.read_text().replace("image_size: 32", "image_size: 48"))
    assert deform_presets.main(args) == 1
    assert deform_presets.main([*args, "--publish"]) == 2  # a toy (--set) is never published


@pytest.mark.slow
def test_presets_chart_runs_dss_deform_and_resumes(tmp_path, capsys):
    from experiments.evaluation import deform_presets

    target = _target(tmp_path)
    out = tmp_path / "chart"
    toy = ["start.points=1500", "image_size=32", "optimizer.point_steps=1", "optimizer.normal_steps=1",
           "optimizer.hull_views=2", "coarse.points=400", "coarse.image_size=24", "snapshot_steps=[0]",
           "chamfer_every=0"]
    args = ["--scenes", "sphere_bunny", "--presets", "default", "fast", "--out", str(out),
            "--set", f"target.path={target}", *toy]
    assert deform_presets.main(args) == 0
    doc = json.loads((out / "presets.json").read_text())
    assert [(r["scene"], r["preset"], r["status"]) for r in doc["runs"]] == [
        ("sphere_bunny", "default", "ok"), ("sphere_bunny", "fast", "ok")]
    for r in doc["runs"]:
        assert r["cpu_time_s"] > 0 and r["chamfer"] > 0 and r["budget"]["preset"] == r["preset"]
    fast = doc["runs"][1]
    assert [s["stage"] for s in fast["stages"]] == ["coarse", "fine"] and fast["budget"]["applied"]
    log = out / "runs" / "sphere_bunny" / "fast" / "log.txt"
    stamp = log.stat().st_mtime_ns
    capsys.readouterr()
    assert deform_presets.main(args) == 0  # resumed: nothing is run again
    assert "done before" in capsys.readouterr().out and log.stat().st_mtime_ns == stamp
