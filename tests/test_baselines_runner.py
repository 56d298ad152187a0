"""The baseline runner survives crashing / hanging methods; the aggregator on a fake sweep."""

import importlib.util
import json
import os
import textwrap
import time

import numpy as np
import pytest

from experiments.evaluation.baselines import aggregate as agg
from experiments.evaluation.baselines.methods import METHODS, PRESETS, preset_params
from experiments.evaluation.baselines.runner import list_methods, run_method, run_methods

FAKES = textwrap.dedent(
    """
    import os, signal, time
    import numpy as np

    def crash(points, normals=None):
        raise RuntimeError("boom from fake method")

    def segfault(points, normals=None):
        os.kill(os.getpid(), signal.SIGSEGV)

    def hang(points, normals=None, seconds=60):
        time.sleep(seconds)
        return points

    def nan(points, normals=None):
        out = points.copy()
        out[0, 0] = np.nan
        return out

    def worse(points, normals=None, sigma=0.3):
        return points + np.random.default_rng(0).normal(scale=sigma, size=points.shape)

    def shrink(points, normals=None, factor=0.5):
        c = points.mean(0)
        return c + factor * (points - c), None, {"resolved": {"factor_used": factor}}

    def wrong_shape(points, normals=None):
        return points[:, :2]
    """
)


@pytest.fixture(scope="module")
def fakes(tmp_path_factory):
    path = tmp_path_factory.mktemp("fakes") / "fake_methods.py"
    path.write_text(FAKES)
    return str(path)


@pytest.fixture(scope="module")
def cloud():
    rng = np.random.default_rng(0)
    clean = rng.normal(size=(300, 3))
    clean /= np.linalg.norm(clean, axis=1, keepdims=True)
    noisy = clean + rng.normal(scale=0.02, size=clean.shape)
    return clean, noisy


def test_crash_hang_and_friends_are_recorded_and_runner_carries_on(fakes, cloud):
    clean, noisy = cloud
    t0 = time.perf_counter()
    results = run_methods(
        {
            f"{fakes}:crash": None,
            f"{fakes}:hang": {"seconds": 60},
            f"{fakes}:segfault": None,
            f"{fakes}:nan": None,
            f"{fakes}:worse": {"sigma": 0.3},
            f"{fakes}:wrong_shape": None,
            f"{fakes}:shrink": {"factor": 1.0},  # identity: equal to the input, not worse
        },
        noisy,
        time_limit=8.0,
        clean=clean,
    )
    elapsed = time.perf_counter() - t0
    st = [r.record.status for r in results]
    assert st == ["crash", "timeout", "crash", "nan", "worse_than_input", "invalid_output", "ok"]
    crash, hang, seg, nan, worse, wrong, ok = (r.record for r in results)
    assert "boom from fake method" in crash.message and crash.failed
    assert "RuntimeError" in crash.stderr_tail
    assert hang.failed and hang.total_s < 30 and "time limit" in hang.message
    assert seg.signal == "SIGSEGV" and "SIGSEGV" in seg.message
    assert results[0].points is None and results[1].points is None
    assert worse.judged and worse.chamfer_output > worse.chamfer_input
    assert ok.judged and not ok.failed and results[-1].points.shape == noisy.shape
    assert ok.params == {"factor": 1.0} and ok.resolved == {"factor_used": 1.0}
    assert ok.wall_s is not None and ok.wall_s <= ok.total_s
    json.dumps([r.record.to_dict() for r in results])  # records are JSON-ready
    assert elapsed < 60  # the hang was cut at the time limit, not waited out


def test_unknown_and_unavailable_methods(cloud, fakes):
    _, noisy = cloud
    r = run_method("no_such_method", noisy)
    assert r.record.status == "unavailable" and "unknown method" in r.record.message
    r = run_method("some_missing_pkg_xyz.module:func", noisy)
    assert r.record.status == "unavailable"
    with pytest.raises(ValueError, match="unknown parameter"):
        run_method("cgal_jet", noisy, params={"not_a_param": 1})
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        run_method(f"{fakes}:nan", noisy[:, :2])


def test_registry_defaults_presets_and_listing():
    listed = {m["method"]: m for m in list_methods()}
    assert set(listed) == set(METHODS)
    for m in listed.values():
        assert isinstance(m["available"], bool)
        if not m["available"]:
            assert "not installed" in m["reason"]
    for name, table in PRESETS.items():
        for params in table.values():
            assert set(params) <= set(METHODS[name].defaults)
    assert preset_params("cgal_jet", 0.009) == PRESETS["cgal_jet"][0.01]
    assert preset_params("cgal_jet", 0.002) == PRESETS["cgal_jet"][0.003]
    assert METHODS["cgal_wlop"].defaults["select_percentage"] == 100.0


@pytest.mark.skipif(importlib.util.find_spec("CGAL") is None, reason="cgal not installed")
def test_cgal_jet_really_denoises(cloud):
    clean, noisy = cloud
    r = run_method("cgal_jet", noisy, time_limit=60, clean=clean)
    assert r.record.status == "ok", r.record.message
    assert r.record.chamfer_output < r.record.chamfer_input
    assert r.record.versions.get("cgal")


# ------------------------------------------------------------------------------------------
# aggregator
# ------------------------------------------------------------------------------------------
def _write(path, obj):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump(obj, f)


def test_pareto_front():
    x = [1, 2, 3, 4, 2, float("nan")]
    y = [5, 3, 4, 1, 3, 0]
    assert agg.pareto_front(x, y).tolist() == [True, True, False, True, True, False]


def test_aggregator_on_fake_sweep(tmp_path):
    root = tmp_path / "sweep"
    # Hydra-like multirun: <job>/metrics.json + .hydra/overrides.yaml
    jobs = [
        (
            "0",
            {"lr": "0.1"},
            {"wall_s": 10.0, "paper": {"chamfer": 1.0}, "score": {"chamfer": 3.0, "p2m": 2.0}},
        ),
        (
            "1",
            {"lr": "0.01"},
            {"wall_s": 20.0, "paper": {"chamfer": 0.5}, "score": {"chamfer": 2.0, "p2m": 3.0}},
        ),
        (
            "2",
            {"lr": "0.001"},
            {"wall_s": 30.0, "paper": {"chamfer": 0.8}, "score": {"chamfer": 2.5, "p2m": 1.0}},
        ),
        ("3", {"lr": "1.0"}, {"wall_s": 1.0, "status": "nan", "paper": {"chamfer": float("nan")}}),
    ]
    for name, ov, m in jobs:
        _write(str(root / name / "metrics.json"), m)
        (root / name / ".hydra").mkdir(parents=True, exist_ok=True)
        (root / name / ".hydra" / "overrides.yaml").write_text(
            "".join(f"- {k}={v}\n" for k, v in ov.items())
        )
    (root / "junk").mkdir()
    (root / "junk" / "metrics.json").write_text("{not json")
    out = tmp_path / "out"
    s = agg.run({"root": str(root), "out_dir": str(out)})
    assert s["x"] == "wall_s" and s["y"] == ["paper.chamfer", "score.p2m"]
    assert s["n_runs"] == 4 and s["n_failed"] == 1
    assert sorted(s["pareto"]["paper.chamfer"]) == ["lr=0.01", "lr=0.1"]
    assert sorted(s["pareto"]["score.p2m"]) == ["lr=0.001", "lr=0.1"]
    for f in ("summary.md", "summary.json", "accuracy_vs_time.png"):
        assert (out / f).stat().st_size > 0
    md = (out / "summary.md").read_text()
    assert "lr=0.01" in md and "| nan |" in md
    assert json.loads((out / "summary.json").read_text())["rows"][0]["label"] == "lr=0.01"


def test_aggregator_groups_seeds_with_failure_rate(tmp_path):
    root = tmp_path / "results"
    for method, times, cds in [
        ("a", [1, 1.2, 1.1], [2.0, 2.2, None]),
        ("b", [5, 6, 7], [1.0, 1.1, 0.9]),
    ]:
        for seed, (t, cd) in enumerate(zip(times, cds)):
            rec = {
                "method": method,
                "seed": seed,
                "total_s": t,
                "status": "ok" if cd is not None else "timeout",
                "metrics": {"paper": {"chamfer": cd}},
            }
            _write(str(root / method / f"seed{seed}" / "metrics.json"), rec)
    s = agg.aggregate(root, group_by=["method"])
    rows = {r["label"]: r for r in s["rows"]}
    assert rows["a"]["n_runs"] == 3 and rows["a"]["failure_rate"] == pytest.approx(1 / 3)
    assert rows["a"]["metrics.paper.chamfer"] == pytest.approx(2.1)
    assert rows["b"]["metrics.paper.chamfer"] == pytest.approx(1.0)
    assert rows["a"]["statuses"] == {"ok": 2, "timeout": 1}
    assert sorted(s["pareto"]["metrics.paper.chamfer"]) == ["a", "b"]
    assert (root / "accuracy_vs_time.png").exists()


def test_aggregator_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a directory"):
        agg.aggregate(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no metrics.json"):
        agg.aggregate(tmp_path / "empty")
    assert agg.main([str(tmp_path / "empty")]) == 2
