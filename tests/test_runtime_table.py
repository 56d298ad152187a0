"""``dss-runtime-table --quick``: the paper's runtime table, structure and sanity of the numbers."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from experiments.benchmarks import runtime_table as rt


@pytest.fixture(scope="module")
def quick(tmp_path_factory, cpp_backend):
    out = tmp_path_factory.mktemp("rt") / "runtime_table"
    result = rt.run(["--quick", "--out", str(out), "--no-progress"])
    return out, result


def _measured(col: dict) -> bool:
    return col.get("status") == "measured"


def test_writes_json_and_markdown(quick):
    out, result = quick
    js = out.with_name(out.name + ".json")
    md = out.with_name(out.name + ".md")
    assert js.is_file() and md.is_file()
    on_disk = json.loads(js.read_text())
    assert [w["key"] for w in on_disk["workloads"]] == ["deformation", "filtering", "denoising"]
    assert on_disk["settings"]["quick"] is True
    assert "estimated" in on_disk["total_note"] and "not a full run" in on_disk["total_note"]
    text = md.read_text()
    assert "paper 1080Ti" in text and "estimated" in text
    for w in on_disk["workloads"]:
        assert w["application"] in text


def test_paper_columns_present(quick):
    _, result = quick
    assert "1080Ti" in result["columns"]["paper_1080ti"]
    paper = {w.key: w for w in rt.WORKLOADS}
    for row in result["workloads"]:
        p = row["paper_1080ti"]
        w = paper[row["key"]]
        assert (p["forward_ms"], p["backward_ms"], p["total_s"]) == (w.paper_forward_ms, w.paper_backward_ms, w.paper_total_s)
        assert p["forward_ms"] > 0 and p["backward_ms"] > p["forward_ms"]  # the paper's backward is the slower pass
        assert (row["position_steps"], row["normal_steps"]) == (w.position_steps, w.normal_steps)


def test_measured_times_positive_and_finite(quick):
    _, result = quick
    rows = result["workloads"]
    assert all(_measured(r["cpp"]) for r in rows), [r["cpp"].get("status") for r in rows]
    # the reference runs on the small quick sizes only
    assert _measured(rows[0]["reference"])
    assert rows[-1]["reference"]["status"].startswith("skipped")
    for r in rows:
        for b in rt.BACKENDS:
            col = r[b]
            if not _measured(col):
                continue
            for key in ("forward_ms", "backward_ms", "total_s_estimated", "peak_memory_mb"):
                assert math.isfinite(col[key]) and col[key] >= 0, (r["key"], b, key, col[key])
            assert col["forward_ms"] > 0 and col["backward_ms"] > 0
            for kind in rt.KINDS:
                pk = col["per_kind"][kind]
                assert len(pk["forward_ms_runs"]) == pk["measured"] >= 1
                assert all(math.isfinite(t) and t > 0 for t in pk["forward_ms_runs"] + pk["backward_ms_runs"])
            # the total is the step-weighted per-kind sum
            est = sum((col["per_kind"][k]["forward_ms"] + col["per_kind"][k]["backward_ms"])
                      * (r["position_steps"] if k == "position" else r["normal_steps"]) for k in rt.KINDS) / 1e3
            assert col["total_s_estimated"] == pytest.approx(est)


def test_cuda_column_without_gpu(quick):
    _, result = quick
    if torch.cuda.is_available():
        pytest.skip("a GPU is present: the CUDA column is measured or names the device")
    assert result["columns"]["cuda"] == rt.NOT_MEASURED_NO_GPU
    for r in result["workloads"]:
        assert r["cuda"]["status"] == "not measured (no GPU)"


def test_benchmark_clouds_can_be_cached(tmp_path, monkeypatch):
    """DSS_BENCH_CLOUDS: the first call samples and writes the cloud, the next reads it back
    (a machine without open3d or ../shared then times the same cloud)."""
    from experiments.benchmarks.bench_render import benchmark_cloud

    monkeypatch.setenv("DSS_BENCH_CLOUDS", str(tmp_path / "clouds"))
    p, n, src = benchmark_cloud(300, seed=3)
    f = tmp_path / "clouds" / "cloud_300_3.npz"
    assert f.is_file() and "read from" not in src
    assert not list((tmp_path / "clouds").glob("*.tmp*"))
    p2, n2, src2 = benchmark_cloud(300, seed=3)
    assert torch.equal(p, p2) and torch.equal(n, n2)
    assert src2.startswith(src) and str(f) in src2
    monkeypatch.delenv("DSS_BENCH_CLOUDS")
    assert torch.equal(benchmark_cloud(300, seed=3)[0], p)  # the cache holds what sampling gives


def test_bad_points_count_is_rejected():
    with pytest.raises(SystemExit):
        rt.parse_args(["--workloads", "deformation", "filtering", "--points", "100"])


def test_floor_comparison_and_targets(tmp_path, cpp_backend):
    """With a perf_counts JSON for the workload, the ratios and the issue's targets are derived."""
    counts = {"machine": {"torch_threads": 1}, "rates": {"flops_per_s": 1e10, "bytes_per_s": 1e10},
              "workloads": [{"points": 20000, "views": 2, "image_size": 32, "flops": 2e6, "bytes": 4e6,
                             "floor_ms": 0.4, "step_floor_ms": {"position": 1.5, "normal": 0.9},
                             "backward": {"position": {"flops": 1e7, "bytes": 8e6},
                                          "normal": {"flops": 1e6, "bytes": 6e6}}}]}
    cpath = tmp_path / "counts.json"
    cpath.write_text(json.dumps(counts))
    result = rt.run(["--quick", "--workloads", "filtering", "--points", "20000",
                     "--counts", str(cpath), "--out", str(tmp_path / "rt"), "--no-progress"])
    fl = result["floor"]
    (w,) = fl["workloads"]
    cpp = result["workloads"][0]["cpp"]["per_kind"]
    step_floor = {"position": 1.5, "normal": 0.9}
    for kind in rt.KINDS:
        m = w["measured"]["cpp"][kind]
        step = cpp[kind]["forward_ms"] + cpp[kind]["backward_ms"]
        assert m["ratio_step_to_floor"] == pytest.approx(step / step_floor[kind])
        assert m["ratio_forward_to_floor"] == pytest.approx(cpp[kind]["forward_ms"] / 0.4)
    ms = lambda f, b: 1e3 * max(f / rt.H100_PUBLISHED["flops_per_s"], b / rt.H100_PUBLISHED["bytes_per_s"])  # noqa: E731
    assert w["h100_published_floor_ms"] == pytest.approx(ms(2e6, 4e6))
    assert w["h100_published_step_floor_ms"]["position"] == pytest.approx(ms(2e6, 4e6) + ms(1e7, 8e6))
    cpu_targets = [t for t in fl["targets"] if t["target"].startswith("2 CPU cores")]
    assert len(cpu_targets) == len(rt.KINDS)
    for t in cpu_targets:
        kind = "position" if "position step" in t["target"] else "normal"
        assert t["floor_ms"] == step_floor[kind]
        assert t["met"] == (t["measured_ms"] <= 250 and t["measured_ms"] <= 4 * step_floor[kind])
    (gpu,) = [t for t in fl["targets"] if "H100" in t["target"]]
    if not torch.cuda.is_available():
        assert gpu["met"] is None and gpu["status"] == "not measured (no GPU)"
    assert "Targets (issue 5)" in (tmp_path / "rt.md").read_text()


def test_first_views_match_dss_bench_cameras():
    """The sampler is set up like dss-bench's cameras_for: its first view set is the same."""
    from dss.views import SphereViewSampler
    from experiments.benchmarks.bench_render import cameras_for

    pts = torch.rand(200, 3) - 0.5
    radius = float(pts.norm(dim=1).max())
    ours = SphereViewSampler((0.0, 0.0, 0.0), radius, views=4, image_size=64, fov_deg=rt.FOV_DEG,
                             jitter=rt.JITTER, seed=3).sample()
    bench = cameras_for(pts, 4, 64, seed=3)
    for a, b in ((ours.R, bench.R), (ours.t, bench.t), (ours.focal, bench.focal), (ours.principal, bench.principal)):
        torch.testing.assert_close(a, b)


def test_measured_rates_are_peaks_of_repeated_calls():
    """perf_counts' floor rates: the fastest call of each measurement (a peak, not the mean over
    a noisy second), and the copy bandwidth the faster of the one-thread and all-thread copies."""
    from experiments.benchmarks import perf_counts

    calls = iter([3.0, 1.0, 2.0])  # call durations (s) after the warm-up call
    clock = {"t": 0.0}

    def fn():
        clock["t"] += next(calls, 10.0)

    # warm-up takes 3 s, then calls of 1, 2 and 10 s until the 12 s budget has passed
    assert perf_counts._best_rate(fn, 100.0, seconds=12.0, clock=lambda: clock["t"]) == pytest.approx(100.0)
    r = perf_counts.measure_rates(seconds=0.05)
    assert r["flops_per_s"] > 1e8
    assert r["bytes_per_s"] == max(r["copy_bytes_per_s_1thread"], r["copy_bytes_per_s_all_threads"]) > 1e8


def test_gpu_floors_on_given_rates_match_the_tables_h100_floors(capsys):
    """perf_counts.gpu_floors on the published H100 rates gives the runtime table's H100 floors
    (the same counted work, one formula); --gpu-rates refuses to run without a GPU."""
    from experiments.benchmarks import perf_counts

    counts = json.loads(Path("results/bench/perf_counts.json").read_text())
    rows = perf_counts.gpu_floors(counts, rt.H100_PUBLISHED)
    for w, r in zip(counts["workloads"], rows):
        assert r["points"] == w["points"]
        assert r["forward_floor_ms"] == pytest.approx(rt._published_h100_ms(w))
        for k, b in w["backward"].items():
            assert r["step_floor_ms"][k] == pytest.approx(rt._published_h100_ms(w) + rt._published_h100_ms(b))
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit, match="needs a CUDA GPU"):
            perf_counts.main(["--gpu-rates", "unused.json"])


H100_RUN = Path(__file__).resolve().parents[1] / "results" / "bench" / "gpu" / "h100"


def test_from_json_redoes_the_cuda_floors_on_measured_gpu_rates(tmp_path):
    """--from-json --gpu-rates: the shipped H100 table with floors on that GPU's measured rates;
    the measurements are kept as they were, the floors equal perf_counts' own on those rates."""
    from experiments.benchmarks import perf_counts

    src = H100_RUN / "runtime_table_cuda.json"
    rates_file = H100_RUN / "gpu_rates.json"
    before = json.loads(src.read_text())
    res = rt.run(["--from-json", str(src), "--gpu-rates", str(rates_file), "--out", str(tmp_path / "rt")])
    assert res["workloads"] == before["workloads"] and res["measured_by"] == before["command"]
    rates = json.loads(rates_file.read_text())
    counts = json.loads(Path(rt.parse_args([]).counts).read_text())
    expected = {f["points"]: f for f in perf_counts.gpu_floors(counts, rates["rates"])}
    fl = res["floor"]
    assert fl["gpu_rates"]["source"] == "measured" and "H100" in fl["gpu_rates"]["device"]
    for w in fl["workloads"]:
        e = expected[w["points"]]
        assert w["gpu_floor_ms"] == pytest.approx(e["forward_floor_ms"])
        for k in rt.KINDS:
            assert w["gpu_step_floor_ms"][k] == pytest.approx(e["step_floor_ms"][k])
            m = w["measured"]["cuda"][k]
            assert m["ratio_step_to_floor"] == pytest.approx(m["step_ms"] / e["step_floor_ms"][k])
        # the measured H100 is slower than its datasheet: higher floors than the published ones
        assert w["gpu_floor_ms"] > w["h100_published_floor_ms"]
    gpu_targets = [t for t in fl["targets"] if "H100" in t["target"]]
    assert len(gpu_targets) == 2 and all(t["met"] is True and t["floor_rates"] == "measured" for t in gpu_targets)
    md = (tmp_path / "rt.md").read_text()
    assert "GPU floors from rates measured on the NVIDIA H100" in md and "measurements from `dss-runtime-table" in md


def test_gpu_rates_of_another_device_are_refused(tmp_path):
    """The H200's rates cannot be the floors of the H100's CUDA column."""
    h200_rates = H100_RUN.parent / "h200" / "gpu_rates.json"
    with pytest.raises(SystemExit, match="gpu_rates.json: rates measured on 'NVIDIA H200'.*another device"):
        rt.run(["--from-json", str(H100_RUN / "runtime_table_cuda.json"), "--gpu-rates", str(h200_rates),
                "--out", str(tmp_path / "rt")])
    assert not (tmp_path / "rt.json").exists()


def test_runtime_chart_reads_tables_of_older_versions(tmp_path):
    """A CPU table without per-step floors (only the forward's, cpu_floor_ms): ratios on that floor."""
    from experiments.figures import runtime_chart as rc

    table = json.loads((Path(__file__).resolve().parents[1] / "results" / "bench" / "runtime_table.json").read_text())
    for f in table["floor"]["workloads"]:
        for k in ("cpu_step_floor_ms", "step_floor_counts_backward", "h100_published_step_floor_ms"):
            f.pop(k, None)
    old = tmp_path / "old_table.json"
    old.write_text(json.dumps(table))
    data = rc.run(["--cpu", str(old), "--cuda", str(H100_RUN / "runtime_table_cuda.json"), "--out", str(tmp_path / "c")])
    for w, f in zip(data["workloads"], table["floor"]["workloads"]):
        floors = f.get("cpu_step_floor_ms") or {k: f["cpu_floor_ms"] for k in rt.KINDS}
        r = next(r for r in table["workloads"] if r["key"] == w["key"])["cpp"]["per_kind"]
        for k in rt.KINDS:
            assert w["ratio_to_floor"]["cpp"][k] == pytest.approx((r[k]["forward_ms"] + r[k]["backward_ms"]) / floors[k])
    assert (tmp_path / "c.png").is_file()


def test_bad_gpu_rates_and_tables_are_refused_with_their_names(tmp_path):
    bad = tmp_path / "rates.json"
    bad.write_text(json.dumps({"rates": {"device": "X", "flops_per_s": 1e12}}))
    with pytest.raises(SystemExit, match="rates.json: not a perf_counts --gpu-rates JSON"):
        rt.load_gpu_rates(str(bad))
    bad.write_text(json.dumps({"rates": {"device": "X", "flops_per_s": 1e12, "bytes_per_s": 0}}))
    with pytest.raises(SystemExit, match="must be positive"):
        rt.load_gpu_rates(str(bad))
    with pytest.raises(SystemExit, match="missing.json: no such file"):
        rt.run(["--gpu-rates", str(tmp_path / "missing.json"), "--quick", "--out", str(tmp_path / "rt")])
    with pytest.raises(SystemExit, match="rates.json: not a dss-runtime-table JSON"):
        rt.run(["--from-json", str(bad), "--out", str(tmp_path / "rt")])
    assert not (tmp_path / "rt.json").exists()


def test_runtime_chart_plots_the_tables_numbers(tmp_path):
    """dss-fig-runtime on the shipped CPU table and the shipped H100 table: a PNG, and a JSON whose
    numbers are the tables' own (step = forward + backward; ratios over each table's floors)."""
    from experiments.figures import runtime_chart as rc

    cpu_path = Path(__file__).resolve().parents[1] / "results" / "bench" / "runtime_table.json"
    cuda_path = H100_RUN / "runtime_table_cuda_measured_floors.json"
    data = rc.run(["--cpu", str(cpu_path), "--cuda", str(cuda_path), "--out", str(tmp_path / "chart")])
    png = (tmp_path / "chart.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    assert json.loads((tmp_path / "chart.json").read_text()) == json.loads(json.dumps(data))
    cpu, cuda = json.loads(cpu_path.read_text()), json.loads(cuda_path.read_text())
    by_key = {w["key"]: w for w in data["workloads"]}
    assert len(by_key) == 3
    for r, c, f in zip(cpu["workloads"], cuda["workloads"], cuda["floor"]["workloads"]):
        w = by_key[r["key"]]
        assert w["step_ms"]["paper_1080ti"] == r["paper_1080ti"]["forward_ms"] + r["paper_1080ti"]["backward_ms"]
        assert w["step_ms"]["cpp"] == pytest.approx(r["cpp"]["forward_ms"] + r["cpp"]["backward_ms"])
        assert w["step_ms"]["cuda"] == pytest.approx(c["cuda"]["forward_ms"] + c["cuda"]["backward_ms"])
        for k in rt.KINDS:
            assert w["ratio_to_floor"]["cuda"][k] == pytest.approx(f["measured"]["cuda"][k]["ratio_step_to_floor"])
    assert "skipped" in by_key["denoising"]["status"]["reference"]  # the reference does not run at 100K
    assert data["sources"]["cuda"]["floor_rates"].startswith("rates measured on the NVIDIA H100")


def test_runtime_chart_refuses_tables_without_the_column(tmp_path):
    from experiments.figures import runtime_chart as rc

    with pytest.raises(SystemExit, match="nope.json: no such file"):
        rc.load_table(tmp_path / "nope.json", "cpp")
    (tmp_path / "x.json").write_text("[1, 2]")
    with pytest.raises(SystemExit, match="x.json: not a dss-runtime-table JSON"):
        rc.load_table(tmp_path / "x.json", "cpp")
    cpu_path = Path(__file__).resolve().parents[1] / "results" / "bench" / "runtime_table.json"
    with pytest.raises(SystemExit, match="its cuda column was not measured"):
        rc.load_table(cpu_path, "cuda")

