"""dss-denoise-table: one tiny table end to end (two cheap baselines, a crashing and a hanging
fake method, L0-DSS with a 3-step schedule, a missing mesh file), resume, config checks."""

from __future__ import annotations

import json
import re
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

import experiments.evaluation.denoise_table as dt
from dss.metrics import evaluate, load_mesh, load_points
from experiments.evaluation.table import cases, report, runners

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
# open3d is a core dependency (cgal and pymeshlab are the optional `baselines` extra)
METHODS = ["open3d_mls", "open3d_taubin", "fake_crash", "fake_hang", "dss_l0"]
FAKES = textwrap.dedent(
    """
    import time

    def crash(points, normals=None):
        raise RuntimeError("boom from a fake method")

    def hang(points, normals=None):
        time.sleep(60)
        return points
    """
)


def make_cfg(out: Path, fakes: Path, methods=METHODS, *extra: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("denoise_table", overrides=[
            f"out_dir={out}", "points=1500", "noise=0.01", "generated.count=0", "generated.held_out=0", "progress=false",
            f"methods=[{','.join(methods)}]", f"+custom_methods.fake_crash={fakes}:crash",
            f"+custom_methods.fake_hang={fakes}:hang", "+time_limits.fake_hang=2", *extra])
    cfg.cases = [{"name": "tiny", "family": "superquadric", "index": 26, "resolution": 32},
                 {"name": "kangaroo", "mesh": str(out.parent / "absent" / "Kangaroo_V10k.ply")}]
    cfg.dss_overrides = ["optimizer.cycles=1", "optimizer.normal_steps=2", "views=2", "image_size=48",
                         "figures.views=1", "figures.image_size=32"]
    return cfg


@pytest.fixture(scope="module")
def fakes(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("fakes") / "fake_methods.py"
    path.write_text(FAKES)
    return path


@pytest.fixture(scope="module")
def table(tmp_path_factory, fakes) -> dict:
    out = tmp_path_factory.mktemp("table") / "out"
    res = dt.run(make_cfg(out, fakes), command="dss-denoise-table (test)")
    return {"out": out, "res": res, "fakes": fakes}


def _recs(res: dict, case: str) -> dict:
    return {r["method"]: r for r in res["records"] if r["case"] == case}


def _md_rows(md: str) -> dict:
    """First table of table.md: {row label: [cells]}."""
    rows = {}
    for line in md.split("## Accuracy and coverage")[0].splitlines():
        if line.startswith("| ") and not line.startswith("| method"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows[cells[0]] = cells[1:]
    return rows


def test_table_files_and_rows(table):
    out = table["out"]
    for f in ("table.md", "table.json", "accuracy_vs_time.png", "README.md", "config.yaml",
              "cases/tiny/noisy.ply", "cases/tiny/clean.ply", "cases/tiny/mesh.ply"):
        assert (out / f).is_file() and (out / f).stat().st_size > 0, f
    md = (out / "table.md").read_text()
    rows = _md_rows(md)
    assert set(rows) == {"input (noisy)", "floor (2nd clean sampling)", *METHODS}
    header = next(line for line in md.splitlines() if line.startswith("| method"))
    assert "tiny CD" in header and "tiny P2M" in header and "mean CD" in header and "kangaroo CD" not in header
    assert "dss-denoise-table (test)" in (out / "README.md").read_text()
    saved = json.loads((out / "table.json").read_text())
    assert {(r["case"], r["method"]) for r in saved["records"]} == {
        (r["case"], r["method"]) for r in table["res"]["records"]}
    assert saved["versions"]["numpy"] and not list(out.rglob(".*.tmp*"))  # atomic writes leave no temp files


def test_metrics_are_paper_protocol_of_the_outputs(table):
    out, recs = table["out"], _recs(table["res"], "tiny")
    noisy, clean = load_points(out / "cases/tiny/noisy.ply"), load_points(out / "cases/tiny/clean.ply")
    mesh = load_mesh(out / "cases/tiny/mesh.ply")
    assert len(clean) == 1500 and len(noisy) == 1500
    ref = evaluate(noisy, clean, mesh, "paper")
    assert recs["input"]["metrics"]["chamfer"] == pytest.approx(ref.chamfer)
    assert recs["input"]["metrics"]["p2m"] == pytest.approx(ref.p2m)
    base = recs["open3d_taubin"]
    assert base["status"] == "ok" and base["params"]["knn"] == 20  # the 1% preset
    got = evaluate(load_points(base["output"]), clean, mesh, "paper")
    assert base["metrics"]["hausdorff"] == pytest.approx(got.hausdorff)
    assert base["metrics"]["chamfer"] < ref.chamfer and base["time_s"] > 0
    # DSS ran as a subprocess after the failures and was scored (ok, or worse than its input)
    d = recs["dss_l0"]
    assert d["kind"] == "dss" and d["status"] in ("ok", "worse_than_input") and d["metrics"]["p2m"] > 0
    assert (Path(d["run_dir"]) / "metrics.json").is_file() and d["time_s"] > 0
    assert "optimizer.cycles=1" in d["command"] and "reference=l0" in d["command"]


def test_failures_are_recorded_and_shown(table):
    recs = _recs(table["res"], "tiny")
    assert recs["fake_crash"]["status"] == "crash" and "boom" in recs["fake_crash"]["message"]
    assert recs["fake_hang"]["status"] == "timeout" and recs["fake_hang"]["time_limit_s"] == 2
    assert recs["fake_crash"].get("metrics") is None
    rows = _md_rows(table["res"]["markdown"])
    assert rows["fake_crash"][:3] == ["crash"] * 3 and rows["fake_hang"][0] == "timeout"
    assert "## Failures" in table["res"]["markdown"]


def test_best_value_in_bold(table):
    rows = _md_rows(table["res"]["markdown"])
    recs = _recs(table["res"], "tiny")
    cds = {m: recs[m]["metrics"]["chamfer"] for m in METHODS if recs[m].get("metrics")}
    best = min(cds, key=cds.get)
    assert rows[best][0].startswith("**")
    assert not any(rows[m][0].startswith("**") for m in cds if cds[m] > cds[best])
    assert not rows["input (noisy)"][0].startswith("**")


def test_missing_mesh_is_a_skipped_case(table):
    recs = _recs(table["res"], "kangaroo")
    assert set(recs) == {"input", *METHODS}
    for r in recs.values():
        assert r["status"] == "skipped" and "Kangaroo_V10k.ply not found" in r["message"]
    assert re.search(r"\| kangaroo \|.*\| skipped: mesh file .*Kangaroo_V10k\.ply not found", table["res"]["markdown"])


def test_resume_skips_completed_records(table, monkeypatch):
    out, fakes = table["out"], table["fakes"]
    before = {p.name: p.read_text() for p in (out / "records/tiny").glob("*.json")}

    def boom(*a, **k):
        raise AssertionError("a completed record was rerun")

    monkeypatch.setattr(runners, "run_dss", boom)
    monkeypatch.setattr(runners, "run_method", boom)
    res = dt.run(make_cfg(out, fakes))
    assert {p.name: p.read_text() for p in (out / "records/tiny").glob("*.json")} == before
    assert res["markdown"].split("## Cases")[0] == table["res"]["markdown"].split("## Cases")[0]

    # a deleted record and a changed parameter are rerun; nothing else is
    calls = []
    from experiments.evaluation.baselines.runner import run_method

    def counting(spec, *a, **k):
        calls.append((spec, k.get("params")))
        return run_method(spec, *a, **k)

    monkeypatch.setattr(runners, "run_method", counting)
    (out / "records/tiny/open3d_taubin.json").unlink()
    res = dt.run(make_cfg(out, fakes, METHODS, "+params.open3d_mls.max_nn=8"))
    assert sorted(c[0] for c in calls) == ["open3d_mls", "open3d_taubin"]
    assert _recs(res, "tiny")["open3d_mls"]["params"]["max_nn"] == 8


def test_config_errors_before_any_work(tmp_path, fakes):
    out = tmp_path / "bad"
    with pytest.raises(ValueError, match=r"methods: unknown \['nope'\]"):
        dt.run(make_cfg(out, fakes, ["open3d_mls", "nope"]))
    with pytest.raises(ValueError, match=r"params.open3d_mls: unknown parameter\(s\) \['kk'\]"):
        dt.run(make_cfg(out, fakes, ["open3d_mls"], "+params.open3d_mls.kk=3"))
    assert not out.exists()


def test_generated_cases_and_paths(tmp_path):
    shapes = cases.test_split_shapes(3, "cpu")
    # the first test shape of the cpu preset is the shipped example (experiments/apps/make_example.py)
    assert (shapes[0]["family"], shapes[0]["index"]) == ("superquadric", 26)
    assert len({s["family"] for s in shapes}) == 3 and all(s["resolution"] == 96 for s in shapes)
    # ... and at 20K points and 1% noise its case files are the shipped example's, bit for bit
    example = cases.REPO_ROOT / "experiments/assets/example"
    if (example / "noisy_1pct.ply").is_file():
        meta = cases.prepare_case(shapes[0], tmp_path / "ex", 20000, 0.01, seed=0)
        assert meta["status"] == "ready" and meta["source"]["shape_seed"] == 787853971
        for ours, shipped in (("noisy.ply", "noisy_1pct.ply"), ("clean.ply", "clean.ply")):
            np.testing.assert_array_equal(load_points(tmp_path / "ex" / ours), load_points(example / shipped))
        again = cases.prepare_case(shapes[0], tmp_path / "ex", 20000, 0.01, seed=0)  # cached: not remade
        assert again == meta
        with pytest.raises(ValueError, match="made with other settings.*overwrite=true"):
            cases.prepare_case(shapes[0], tmp_path / "ex", 20000, 0.003, seed=0)
    # resolved: ../shared may be a link (as in a checkout that links the shared data beside it)
    assert cases.resolve_repo_path("../shared/data/K.ply") == (cases.REPO_ROOT.parent / "shared/data/K.ply").resolve()
    assert cases.resolve_repo_path("/abs/x.ply") == Path("/abs/x.ply")
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("denoise_table")
    assert cfg.published_dir == "results/denoise/table_0.01_20000" and cfg.methods == "all"
    labels = runners.method_list(cfg)
    assert labels[-8:] == ["dss_default", "dss_pix2pix", "dss_l0", "dss_identity", "dss_oracle",
                           "dss_pix2pix_fast", "dss_identity_fast", "dss_default_fast"] and "cgal_jet" in labels
    assert runners.request("dss_default", cfg, 0.01)["overrides"] == []
    assert "budget=fast" in runners.request("dss_identity_fast", cfg, 0.01)["overrides"]
    req = runners.request("dss_pix2pix", cfg, 0.01)
    assert req["overrides"] == ["reference=onnx", "reference.threads=1"]


def test_meshlab_sample_cases(tmp_path, monkeypatch):
    """meshlab_samples=true adds pymeshlab's five sample meshes after the configured cases; without
    pymeshlab it is a clear error, not a silently smaller benchmark."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("denoise_table", ["meshlab_samples=true", "generated.count=1", "generated.held_out=0"])
    try:
        import pymeshlab  # noqa: F401
    except ImportError:
        with pytest.raises(RuntimeError, match="needs pymeshlab"):
            cases.case_list(cfg)
        return
    names = [c["name"] for c in cases.case_list(cfg)]
    assert names == ["kangaroo", "bunny", "cow", "airplane", "bone", "face", "superquadric-0026"]
    bone = next(c for c in cases.case_list(cfg) if c["name"] == "bone")
    meta = cases.prepare_case(bone, tmp_path / "bone", 2000, 0.01, seed=0)  # a real mesh file becomes a case
    assert meta["status"] == "ready" and (tmp_path / "bone" / "noisy.ply").is_file()
    monkeypatch.setitem(sys.modules, "pymeshlab", None)  # as if the extra were not installed
    with pytest.raises(RuntimeError, match="needs pymeshlab"):
        cases.meshlab_sample_cases()


def test_markdown_marks_partial_means_and_worse_than_input():
    def rec(case, method, status, cd=None, t=1.0):
        m = None if cd is None else {"chamfer": cd, "hausdorff": 10 * cd, "p2m": cd / 2}
        return {"case": case, "method": method, "kind": "input" if method == "input" else "baseline",
                "status": status, "metrics": m, "time_s": None if method == "input" else t, "message": ""}

    recs = [rec("a", "input", "reference", 1.0), rec("b", "input", "reference", 2.0),
            rec("a", "good", "ok", 0.5, 2.0), rec("b", "good", "ok", 0.7, 4.0),
            rec("a", "half", "ok", 0.1), rec("b", "half", "crash"),
            rec("a", "bad", "worse_than_input", 1.5), rec("b", "bad", "ok", 1.9)]
    rows = report.summarize(recs, ["good", "half", "bad"], ["a", "b"])
    info = [{"name": c, "status": "ready", "key": {"points": 10, "noise": 0.01, "case": {}},
             "source": {"family": "x", "index": 0}} for c in ("a", "b")]
    md = _md_rows(report.render_markdown(rows, info, "t", []))
    # columns: a CD, a HD, a P2M, b CD, b HD, b P2M, mean CD, mean HD, mean P2M, time
    assert md["half"][0] == "**0.1**" and md["half"][3] == "crash" and md["half"][6] == "0.1 (1/2)"
    assert md["good"][6] == "**0.6**" and md["good"][9] == "3" and md["bad"][9] == "**1**"  # fastest complete
    assert md["bad"][0] == "1.5 †" and not md["bad"][3].startswith("**")
    good = next(r for r in rows if r["method"] == "good")
    assert good["pareto"] == {"chamfer": True, "p2m": True} and np.isclose(good["mean"]["p2m"], 0.3)
    assert "half" not in [r["method"] for r in rows if r["pareto"].get("chamfer")]
    halves = report.render_markdown(rows, info, "t", []).split("## Accuracy and coverage")[1].split("## Cases")[0]
    assert "| good |" in halves and "| half |" not in halves  # complete rows only
    # b held out: its own columns after the tuning cases and its own mean; "mean" is a's alone
    rows = report.summarize(recs, ["good", "half", "bad"], ["a", "b"], held_out={"b"})
    good = next(r for r in rows if r["method"] == "good")
    assert good["mean"]["chamfer"] == 0.5 and good["mean_held_out"]["chamfer"] == 0.7 and good["complete_held_out"]
    half = next(r for r in rows if r["method"] == "half")
    assert half["complete"] and not half["complete_held_out"] and half["n_scored_held_out"] == 0
    info_h = [{**info[0], "held_out": False}, {**info[1], "held_out": True}]
    text = report.render_markdown(rows, info_h, "t", [])
    head = next(line for line in text.splitlines() if line.startswith("| method"))
    assert "| b (held out) CD |" in head and "| held-out mean CD |" in head
    md = _md_rows(text)
    # columns: a CD/HD/P2M, b CD/HD/P2M, mean x3, held-out mean x3, time
    assert md["good"][6] == "0.5" and md["half"][6] == "**0.1**" and md["good"][9] == "**0.7**"
    assert md["half"][9] == "-"


def test_score_protocol_noise_in_radius_units(tmp_path, fakes):
    """protocol=score: noise is a fraction of the clean cloud's bounding-sphere radius (measured on
    the noisy cloud it made), each method gets the bbox-diagonal equivalent, and every metric is
    the score protocol's."""
    out = tmp_path / "score"
    cfg = make_cfg(out, fakes, ["open3d_mls"], "protocol=score", "noise=0.02", "floor=false")
    cfg.cases = cfg.cases[:1]
    res = dt.run(cfg, command="dss-denoise-table protocol=score (test)")
    meta = res["cases"][0]
    clean, noisy = load_points(out / "cases/tiny/clean.ply"), load_points(out / "cases/tiny/noisy.ply")
    lo, hi = clean.min(0), clean.max(0)
    radius = np.sqrt(((clean - (lo + hi) / 2) ** 2).sum(1)).max()
    diag = np.linalg.norm(hi - lo)
    assert meta["noise_unit"] == "radius" and np.isclose(meta["noise_diag"], 0.02 * radius / diag, rtol=1e-5)
    assert 0.25 < meta["noise_diag"] / 0.02 < 0.5  # a radius is at most half the diagonal
    assert np.isclose(np.std(noisy - clean), 0.02 * radius, rtol=0.05)  # per-axis std = 2% of the radius
    rec = json.loads((out / "records/tiny/open3d_mls.json").read_text())
    from experiments.evaluation.baselines.methods import preset_params

    assert rec["request"]["params"] == preset_params("open3d_mls", meta["noise_diag"])
    mesh = load_mesh(out / "cases/tiny/mesh.ply")
    out_pts = load_points(out / "outputs/tiny/open3d_mls.ply")
    ref = evaluate(out_pts, clean, mesh, "score")
    assert np.isclose(rec["metrics"]["chamfer"], ref.chamfer, rtol=1e-6)
    assert not np.isclose(ref.chamfer, evaluate(out_pts, clean, mesh, "paper").chamfer, rtol=0.1)
    table = json.loads((out / "table.json").read_text())
    assert table["protocol"] == "score" and "bounding-sphere radius" in table["title"]
    assert "`score` protocol" in (out / "table.md").read_text()
    with pytest.raises(ValueError, match="protocol must be one of"):
        dt.run(make_cfg(tmp_path / "bad", fakes, ["open3d_mls"], "protocol=pap"))


def test_baseline_outlier_removal_gives_baselines_the_filtered_cloud(tmp_path, fakes):
    """baseline_outlier_removal=true: a baseline gets the noisy cloud minus what dss-denoise's
    outlier removal drops (so an outlier axis compares smoothers); the request records it, so
    records made without it are not reused."""
    out = tmp_path / "pre"
    cfg = make_cfg(out, fakes, ["open3d_mls"], "outliers=0.05", "floor=false", "baseline_outlier_removal=true")
    cfg.cases = cfg.cases[:1]
    dt.run(cfg)
    rec = json.loads((out / "records/tiny/open3d_mls.json").read_text())
    noisy = load_points(out / "cases/tiny/noisy.ply")
    n_out = int(round(0.05 * 1500))
    assert rec["request"]["prefilter"] == "outliers" and n_out // 3 < rec["prefilter"]["removed"] <= n_out + 5
    assert rec["n_out"] == len(noisy) - rec["prefilter"]["removed"]  # MLS keeps its input's count
    assert "after DSS's outlier removal" in (out / "table.md").read_text()
    cfg2 = make_cfg(out, fakes, ["open3d_mls"], "outliers=0.05", "floor=false")
    cfg2.cases = cfg.cases
    dt.run(cfg2)  # without the prefilter: rerun, not the stored record
    rec2 = json.loads((out / "records/tiny/open3d_mls.json").read_text())
    assert "prefilter" not in rec2 and rec2["n_out"] == len(noisy)
    assert rec2["metrics"]["chamfer"] > rec["metrics"]["chamfer"]  # the outliers stay in its output


def test_dss_request_names_the_shipped_model_it_uses():
    """A DSS record is reused only while the shipped model it ran with is unchanged: the request
    holds that file's hash (per case noise), and an explicit model path is left to the overrides."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("denoise_table")
    lo, hi = runners.request("dss_pix2pix", cfg, 0.003), runners.request("dss_pix2pix", cfg, 0.012)
    assert lo["model_sha256"] == runners.file_sha256(cases.REPO_ROOT / "experiments/assets/denoiser_noise_0.3pct.onnx")[:16]
    assert hi["model_sha256"] == runners.file_sha256(cases.REPO_ROOT / "experiments/assets/denoiser_noise_1pct.onnx")[:16]
    assert "model_sha256" not in runners.request("dss_l0", cfg, 0.01)
    assert runners.shipped_model_for(["reference=onnx", "reference.model=/x/m.onnx"], 0.01) is None


def test_pareto_front_and_cpu_column_use_cpu_seconds_when_every_method_has_them():
    """Wall time on a busy machine says little; one-thread CPU seconds do not depend on the load.
    The front is on CPU seconds when every complete method has them, else on wall time."""
    def rec(case, method, cd, wall, cpu):
        return {"case": case, "method": method, "kind": "dss", "status": "ok", "message": "",
                "metrics": {"chamfer": cd, "hausdorff": cd, "p2m": cd}, "time_s": wall, "cpu_s": cpu}

    # fast is slower on the (loaded) wall clock but cheaper in CPU: on the front only by CPU
    recs = [rec("a", "slow_good", 0.3, 10.0, 40.0), rec("a", "fast", 0.5, 20.0, 10.0)]
    rows = report.summarize(recs, ["slow_good", "fast"], ["a"])
    front = {r["method"] for r in rows if r["pareto"]["chamfer"]}
    assert front == {"slow_good", "fast"} and rows[0]["clock"] == "cpu_s"
    info = [{"name": "a", "status": "ready", "key": {"points": 10, "noise": 0.01, "case": {}},
             "source": {"family": "x", "index": 0}}]
    md = _md_rows(report.render_markdown(rows, info, "t", []))
    assert md["fast"][-1] == "**10**" and md["fast"][-2] == "20"  # time (s), CPU (s)
    recs[1]["cpu_s"] = None  # one method without CPU seconds: wall time decides
    rows = report.summarize(recs, ["slow_good", "fast"], ["a"])
    assert {r["method"] for r in rows if r["pareto"]["chamfer"]} == {"slow_good"} and rows[0]["clock"] == "time_s"
