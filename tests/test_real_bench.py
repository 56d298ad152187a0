"""dss-real-bench: the real-shape benchmark (a 2-mesh smoke case where the meshes are installed)."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

CONF = str(Path(__file__).resolve().parents[1] / "conf")
REAL = Path(__file__).resolve().parents[1] / "data" / "real" / "manifest.json"


def _cfg(out: Path, *overrides: str):
    import experiments  # noqa: F401  (resolvers)

    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(config_name="real_bench", overrides=[f"out_dir={out}", "progress=false", *overrides])
    OmegaConf.set_struct(cfg, False)
    return cfg


def _record(case, method, shape, group, cd, hd, status="ok"):
    keys = ("chamfer", "hausdorff", "p2m", "hausdorff_gt_to_pred", "gt_to_pred_p99", "normal_error_all_deg",
            "normal_error_curved_deg")
    m = {k: 1.0 for k in keys}
    m.update(chamfer=cd, hausdorff=hd)
    return {"case": case, "method": method, "shape": shape, "group": group, "points": 20000, "noise": 0.005,
            "seed": 0, "status": status, "metrics": m, "cpu_s": 1.0}


def test_best_classical_is_the_per_case_minimum_of_each_metric_and_missing_cases_are_listed(tmp_path):
    from experiments.evaluation.real_benchmark import render_report, summarize_bench

    cfg = _cfg(tmp_path)
    cfg.classical = {"a": {"method": "cgal_jet", "params": {"k": 16}}, "b": {"method": "cgal_jet", "params": {"k": 32}}}
    cfg.dss_methods = {"dss_default": []}
    recs = [_record("c1", "input", "s1", "held_out", 2.0, 20.0), _record("c1", "a", "s1", "held_out", 0.5, 15.0),
            _record("c1", "b", "s1", "held_out", 0.7, 12.0), _record("c1", "dss_default", "s1", "held_out", 0.4, 21.0),
            _record("c2", "input", "s2", "held_out", 2.0, 20.0), _record("c2", "a", "s2", "held_out", 0.5, 15.0)]
    s = summarize_bench(recs, cfg)
    (lv,) = s["levels"]
    assert lv["n"] == 1 and lv["missing"] == ["c2"]  # c2 has no DSS result: not in the means
    assert lv["mean"]["best_classical"]["chamfer"] == 0.5 and lv["mean"]["best_classical"]["hausdorff"] == 12.0
    assert lv["hd_above_input"]["dss_default"] == 1
    md = render_report(s, "t", [], [{"name": "x", "group": "open", "reason": "not installed"}])
    assert "x (open): not installed" in md and "| 20000 | 0.5% (1%) | held_out | 1 (1 missing) |" in md


@pytest.mark.skipif(not REAL.is_file(), reason="the real meshes are not installed (dss-data real)")
def test_two_real_meshes_run_every_method_and_resume(tmp_path):
    from experiments.evaluation.real_benchmark import run

    cfg = _cfg(tmp_path / "bench", "groups=[tuning,held_out]", "shapes_per_group=1", "points=[2000]",
               "noise=[0.005]", "seeds=[0,1]", "seeds_by_group={tuning:[0],held_out:[1]}", "face_scan=false")
    cfg.classical = {"taubin": {"method": "open3d_taubin", "params": {"iterations": 10}}}  # open3d: no extra needed
    cfg.dss_methods = {"dss_default": []}
    res = run(cfg)
    assert {(r["group"], r["seed"]) for r in res["records"]} == {("tuning", 0), ("held_out", 1)}
    levels = res["summary"]["levels"]
    assert {lv["group"] for lv in levels} == {"tuning", "held_out"} and all(lv["n"] == 1 for lv in levels)
    for lv in levels:
        m = lv["mean"]
        assert m["dss_default"]["chamfer"] < m["input"]["chamfer"]
        assert m["best_classical"]["chamfer"] is not None and lv["cpu_s"]["dss_default"] > 0
    assert (tmp_path / "bench" / "report.md").is_file() and any(Path(tmp_path / "bench").glob("accuracy_vs_time_*.png"))
    again = run(cfg)  # every record is reused
    assert [r.get("metrics") for r in again["records"]] == [r.get("metrics") for r in res["records"]]
    cfg.seeds_by_group = {"open": [0]}  # a group not in the run: refused before any work
    with pytest.raises(ValueError, match="seeds_by_group.open: must name a group"):
        run(cfg)
