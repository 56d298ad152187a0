"""dss-sweep: a tiny study end to end (two table axes, one dss-override axis, a crashing fake
method), shared base points, failure onsets, knees, resume; the denoise table's outlier and seed
options."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import experiments.evaluation.sweep as sw
from dss.metrics import load_points
from experiments.evaluation.table import cases, runners

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
TINY_CASE = {"name": "tiny", "family": "superquadric", "index": 26, "resolution": 32}


def make_cfg(out: Path, fakes: Path, study: str = "stability"):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("sweep", overrides=[f"study={study}", f"out_dir={out}", "progress=false"])
    OmegaConf.set_struct(cfg, False)
    cfg.table = {"points": 600, "noise": 0.01, "generated": {"count": 0}, "cases": [TINY_CASE],
                 "methods": ["open3d_taubin", "fake_crash"], "custom_methods": {"fake_crash": f"{fakes}:crash"},
                 "dss_overrides": ["optimizer.cycles=1", "optimizer.normal_steps=1", "image_size=32",
                                   "figures.views=1", "figures.image_size=32"],
                 "time_limit_s": 120}
    cfg.study.axes = {
        "noise": {"key": "noise", "values": [0.005, 0.01, 0.03], "log": True},
        "outliers": {"key": "outliers", "values": [0.0, 0.1]},
        "views": {"key": "dss.views", "values": [2, 3], "default": 2, "knee": True, "table": {"methods": ["dss_l0"]},
                  "labels": ["two", "three"], "label_name": "n_views"},
    }
    return cfg


@pytest.fixture(scope="module")
def fakes(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("fakes") / "fake_methods.py"
    path.write_text(textwrap.dedent("""
        def crash(points, normals=None):
            raise RuntimeError("boom from a fake method")
    """))
    return path


@pytest.fixture(scope="module")
def sweep(tmp_path_factory, fakes) -> dict:
    out = tmp_path_factory.mktemp("sweep") / "out"
    cfg = make_cfg(out, fakes)
    return {"out": out, "cfg": cfg, "res": sw.run(cfg, command="dss-sweep (test)")}


def _axis(res, name):
    return next(a for a in res["axes"] if a["axis"] == name)


def test_files_points_and_shared_base(sweep):
    out, res = sweep["out"], sweep["res"]
    for f in ("sweep.json", "sweep.md", "README.md", "config.yaml", "noise.png", "outliers.png", "views.png"):
        assert (out / f).is_file(), f
    assert [p["value"] for p in res["points"]] == [0.005, 0.01, 0.03, 0.0, 0.1, 2, 3]
    # the base point (noise 0.01, outliers 0, views default) appears on all three axes: one table
    base = {p["setting"] for p in res["points"] if (p["axis"], p["value"]) in
            {("noise", 0.01), ("outliers", 0.0), ("views", 2)}}
    assert len(base) == 1
    assert len({p["setting"] for p in res["points"]}) == 5
    assert len(list((out / "tables").iterdir())) == 5
    saved = json.loads((out / "sweep.json").read_text())
    assert saved["axes"][0]["values"] == [0.005, 0.01, 0.03]


def test_stats_are_the_tables_records(sweep):
    res = sweep["res"]
    ax = _axis(res, "noise")
    for p, stats in zip([p for p in res["points"] if p["axis"] == "noise"], ax["stats"]):
        rec = json.loads((Path(p["out_dir"]) / "records" / "tiny" / "open3d_taubin.json").read_text())
        inp = json.loads((Path(p["out_dir"]) / "records" / "tiny" / "input.json").read_text())
        s = stats["open3d_taubin"]
        assert s["chamfer"] == pytest.approx(rec["metrics"]["chamfer"])
        assert s["ratio"] == pytest.approx(rec["metrics"]["chamfer"] / inp["metrics"]["chamfer"])
        assert s["failures"] == int(rec["failed"]) and s["n"] == 1
    # more noise, larger input error
    cds = [s["input"]["chamfer"] for s in ax["stats"]]
    assert cds[0] < cds[1] < cds[2]


def test_crash_is_a_failure_at_every_value_and_onset(sweep):
    ax = _axis(sweep["res"], "noise")
    assert all(s["fake_crash"]["failure_rate"] == 1.0 for s in ax["stats"])
    assert ax["onset"]["fake_crash"] == 0.005 and ax["knee"] == {}  # no knee on a non-budget axis
    views = _axis(sweep["res"], "views")
    # labels name the values in the results: the knee, the table header
    assert views["values"] == [2, 3] and views["labels"] == ["two", "three"]
    assert views["knee"]["dss_l0"] in ("two", "three")
    assert "| n_views=two | n_views=three |" in (sweep["out"] / "sweep.md").read_text()
    md = (sweep["out"] / "sweep.md").read_text()
    assert "1/1 failed**: crash" in md


def test_outliers_are_added_to_the_input(sweep):
    pts = [p for p in sweep["res"]["points"] if p["axis"] == "outliers"]
    clean = load_points(Path(pts[1]["out_dir"]) / "cases" / "tiny" / "clean.ply")
    noisy0 = load_points(Path(pts[0]["out_dir"]) / "cases" / "tiny" / "noisy.ply")
    noisy1 = load_points(Path(pts[1]["out_dir"]) / "cases" / "tiny" / "noisy.ply")
    assert len(noisy0) == 600 and len(noisy1) == 660 and len(clean) == 600
    lo, hi = clean.min(0), clean.max(0)
    assert ((noisy1 >= lo - 0.2 * (hi - lo)) & (noisy1 <= hi + 0.2 * (hi - lo))).all()
    ax = _axis(sweep["res"], "outliers")
    assert ax["stats"][1]["input"]["chamfer"] > 1.5 * ax["stats"][0]["input"]["chamfer"]


def test_dss_axis_passes_the_override(sweep):
    pts = [p for p in sweep["res"]["points"] if p["axis"] == "views"]
    reqs = [json.loads((Path(p["out_dir"]) / "records" / "tiny" / "dss_l0.json").read_text())["request"]
            for p in pts]
    assert not any(o.startswith("views=") for o in reqs[0]["overrides"])  # the default: no override
    assert "views=3" in reqs[1]["overrides"]
    stats = _axis(sweep["res"], "views")["stats"]
    assert all(s["dss_l0"]["n"] == 1 for s in stats)


def test_resume_reruns_nothing(sweep, monkeypatch):
    def boom(*a, **k):
        raise AssertionError("a finished record was rerun")

    monkeypatch.setattr(runners, "run_baseline", boom)
    monkeypatch.setattr(runners, "run_dss", boom)
    res = sw.run(sweep["cfg"], command="dss-sweep (resume)")
    assert _axis(res, "noise")["stats"][0]["open3d_taubin"]["chamfer"] == pytest.approx(
        _axis(sweep["res"], "noise")["stats"][0]["open3d_taubin"]["chamfer"])


def test_unknown_axis_and_key_are_refused(tmp_path, fakes):
    cfg = make_cfg(tmp_path / "o", fakes)
    cfg.axes_to_run = ["nope"]
    with pytest.raises(ValueError, match="unknown axis 'nope'"):
        sw.run(cfg)
    cfg = make_cfg(tmp_path / "o2", fakes)
    cfg.study.axes = {"bad": {"key": "views", "values": [1]}}
    with pytest.raises(ValueError, match="not a dss-denoise-table setting"):
        sw.run(cfg)
    cfg.study.axes = {"bad": {"key": "dss.views", "values": [1, 2], "labels": ["one"]}}
    with pytest.raises(ValueError, match="1 labels for 2 values"):
        sw.run(cfg)


def test_declared_dss_defaults_are_never_passed(fakes, tmp_path):
    """A dss axis's declared default is dss-denoise's own: no point, on any axis, passes it, so the
    base point shared by the axes keeps one request (and one set of records)."""
    cfg = make_cfg(tmp_path / "o", fakes)
    cfg.study.axes["cycles"] = {"key": "dss.optimizer.cycles", "values": [1, 2], "default": 1}
    pts = sw.axis_points(cfg.study, list(cfg.study.axes), sw.base_table(cfg.study.table, cfg.table))
    base = [p for p in pts if p["setting"] == next(q["setting"] for q in pts if q["axis"] == "views" and q["value"] == 2)]
    assert {p["axis"] for p in base} == {"noise", "outliers", "views", "cycles"}
    extra = [list(p["table"].dss_overrides)[-2:] for p in base]
    assert all(not any(o.startswith(("views=", "optimizer.cycles=")) for o in e) for e in extra)
    other = next(p for p in pts if p["axis"] == "cycles" and p["value"] == 2)
    assert "optimizer.cycles=2" in other["table"].dss_overrides
    assert not any(o.startswith("views=") for o in other["table"].dss_overrides)


def test_knee_and_onset_helpers():
    st = [{"chamfer": 1.0, "failures": 0}, {"chamfer": 0.5, "failures": 0}, {"chamfer": 0.495, "failures": 1},
          {"chamfer": 0.49, "failures": 0}]
    assert sw.knee([4, 8, 12, 16], st, 0.05) == 8
    assert sw.knee([4, 8, 12, 16], st, 0.01) == 16
    assert sw.first_failure([4, 8, 12, 16], st) == 12
    assert sw.knee([1], [None], 0.1) is None


def test_shipped_studies_compose():
    repo = CONF_DIR.parent
    for study in ("stability", "budget", "width"):
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose("sweep", overrides=[f"study={study}"])
        base = sw.base_table(cfg.study.table, cfg.table)
        pts = sw.axis_points(cfg.study, list(cfg.study.axes), base)
        assert len(pts) == sum(len(a["values"]) for a in cfg.study.axes.values())
        runners.method_list(pts[0]["table"])  # every method name is known
        for p in pts:  # model files named by an axis ship with the repository
            for o in p["table"].dss_overrides:
                if o.startswith("reference.model="):
                    assert (repo / o.split("=", 1)[1]).is_file(), o


def test_seed_gives_another_draw_of_a_generated_shape():
    a = cases.make_case_arrays(TINY_CASE, 300, 0.01, 0)
    b = cases.make_case_arrays(TINY_CASE, 300, 0.01, 1)
    assert a[3]["noise_seed"] != b[3]["noise_seed"]
    assert not np.allclose(a[2], b[2])
    a2 = cases.make_case_arrays(TINY_CASE, 300, 0.01, 0)
    np.testing.assert_array_equal(a[2], a2[2])
