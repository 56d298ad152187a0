"""Table, figure and benchmark commands leave tracked files alone by default: each run writes a
fresh outputs/<command>/<timestamp> folder under the working directory, and results/ changes only
with --publish / publish=true."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from experiments import outputs

ROOT = Path(__file__).resolve().parents[1]
CONF_DIR = ROOT / "conf"
TINY_CASE = {"name": "tiny", "family": "superquadric", "index": 26, "resolution": 32}


def _args(argv, published="results/x"):
    ap = argparse.ArgumentParser()
    outputs.add_arguments(ap, published=published)
    return ap.parse_args(argv)


def test_output_folder_choice(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    a = outputs.folder(_args([]), "cmd")
    b = outputs.folder(_args([]), "cmd")
    assert a.is_dir() and b.is_dir() and a != b  # two runs in one second: two folders
    assert a.parent == Path("outputs") / "cmd"
    assert outputs.folder(_args([]), "cmd", name="t.json").parent.parent == Path("outputs") / "cmd"
    assert outputs.folder(_args(["--publish"]), "cmd") == Path("results/x")
    assert outputs.folder(_args(["--out", "o"]), "cmd") == Path("o")
    with pytest.raises(SystemExit, match="not both"):
        outputs.folder(_args(["--out", "o", "--publish"]), "cmd")
    assert not (tmp_path / "results").exists()


def test_latest_points_at_the_newest_run(tmp_path, monkeypatch):
    """outputs/<command>/latest follows each new run folder, as a relative link (the tree can
    move); a real file or folder named latest is left alone."""
    monkeypatch.chdir(tmp_path)
    latest = Path("outputs") / "cmd" / "latest"
    for _ in range(3):
        run = outputs.fresh_folder("cmd")
        (run / "model.onnx").write_text(run.name)
        assert latest.is_symlink() and os.readlink(latest) == run.name
        assert (latest / "model.onnx").read_text() == run.name  # a pasted path reaches this run's file
    assert not list(latest.parent.glob(".latest.*"))  # no temporary link left behind
    moved = tmp_path / "moved"
    (tmp_path / "outputs").rename(moved)
    assert (moved / "cmd" / "latest" / "model.onnx").read_text() == run.name
    mine = tmp_path / "mine"
    (mine / "latest").mkdir(parents=True)
    assert outputs.link_latest(mine / "run") is None and (mine / "latest").is_dir()


def test_a_hydra_run_links_latest(tmp_path):
    """`dss-render` under Hydra (conf/hydra/default.yaml's JobStart callback): outputs/render/latest
    is the run directory, and a second run moves it; a run directory given elsewhere is not linked."""
    import subprocess
    import sys

    from scenes import sphere_points

    from dss.pointcloud import PointCloud, save_ply

    p, n = sphere_points(300, 0.4)
    save_ply(tmp_path / "s.ply", PointCloud(p, n))
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    seen = []
    for _ in range(2):
        r = subprocess.run([sys.executable, "-m", "experiments.apps.render", str(tmp_path / "s.ply"), "views=1",
                            "image_size=16"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        latest = tmp_path / "outputs" / "render" / "latest"
        assert latest.is_symlink() and (latest / "metrics.json").is_file()
        seen.append(os.readlink(latest))
    assert seen[0] != seen[1] and sorted(seen) == sorted(
        p.name for p in latest.parent.iterdir() if p.is_dir() and not p.is_symlink())
    # a run directory given elsewhere (a table's per-case runs) gets no link beside it
    r = subprocess.run([sys.executable, "-m", "experiments.apps.render", str(tmp_path / "s.ply"), "views=1",
                        "image_size=16", "hydra.run.dir=runs/case/method"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert [p.name for p in (tmp_path / "runs" / "case").iterdir()] == ["method"]
    assert os.readlink(latest) == seen[1]


def test_publish_files_replaces_and_removes_stale(tmp_path):
    src, dest = tmp_path / "run", tmp_path / "pub"
    src.mkdir()
    (src / "a.md").write_text("new")
    dest.mkdir()
    (dest / "a.md").write_text("old")
    (dest / "stale.json").write_text("{}")
    written = outputs.publish_files(src, dest, ["a.md"], stale=["stale.json"])
    assert [p.name for p in written] == ["a.md"] and (dest / "a.md").read_text() == "new"
    assert not (dest / "stale.json").exists() and oct((dest / "a.md").stat().st_mode & 0o777) == "0o644"
    with pytest.raises(FileNotFoundError):
        outputs.publish_files(src, dest, ["missing.md"])


def test_figure_command_writes_a_fresh_folder_by_default(tmp_path, monkeypatch):
    from experiments.figures import two_points

    monkeypatch.chdir(tmp_path)
    assert two_points.main(["--trials", "0", "--steps", "6", "--snapshots", "0", "6"]) == 0
    runs = [p for p in (tmp_path / "outputs" / "dss-fig-twopoints").iterdir() if not p.is_symlink()]
    assert len(runs) == 1 and (runs[0] / "two_points.png").is_file() and (runs[0] / "two_points.json").is_file()
    assert (tmp_path / "outputs" / "dss-fig-twopoints" / "latest").resolve() == runs[0].resolve()
    assert not (tmp_path / "results").exists()


def test_runtime_chart_writes_a_fresh_folder_by_default(tmp_path, monkeypatch):
    from experiments.figures import runtime_chart

    cpu = ROOT / "results" / "bench" / "runtime_table.json"
    cuda = ROOT / "results" / "bench" / "gpu" / "h100" / "runtime_table_cuda_measured_floors.json"
    monkeypatch.chdir(tmp_path)
    runtime_chart.run(["--cpu", str(cpu), "--cuda", str(cuda)])
    runs = [p for p in (tmp_path / "outputs" / "dss-fig-runtime").iterdir() if not p.is_symlink()]
    assert len(runs) == 1 and {p.name for p in runs[0].iterdir()} == {"runtime_chart.png", "runtime_chart.json"}


def test_results_index_writes_the_tracked_readme_only_with_publish(tmp_path, monkeypatch):
    from experiments.evaluation.results_index import build, main

    res = tmp_path / "results"
    (res / "misc").mkdir(parents=True)
    (res / "misc" / "x.json").write_text(json.dumps({"command": "dss-x"}))
    monkeypatch.chdir(tmp_path)
    assert main(["--results", str(res)]) == 0
    assert not (res / "README.md").exists()
    written = [p for p in (tmp_path / "outputs" / "dss-results").glob("*/README.md") if not p.parent.is_symlink()]
    assert len(written) == 1 and written[0].read_text() == build(res)
    assert main(["--results", str(res), "--publish"]) == 0
    assert (res / "README.md").read_text() == build(res)


def test_table_and_sweep_configs_default_to_fresh_folders(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        table = compose("denoise_table")
        sweep = compose("sweep")
    assert table.publish is False and table.published_dir == "results/denoise/table_0.01_20000"
    assert str(table.out_dir).startswith("outputs/dss-denoise-table/")
    assert table.out_dir == table.out_dir  # one path per process, however often it is resolved
    assert sweep.publish is False and sweep.published_dir == "results/stability"
    assert str(sweep.out_dir).startswith("outputs/dss-sweep/")


def test_denoise_table_publishes_only_the_summary_when_asked(tmp_path, monkeypatch):
    import experiments.evaluation.denoise_table as dt

    monkeypatch.chdir(tmp_path)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("denoise_table", overrides=["points=600", "methods=[open3d_taubin]", "floor=false",
                                                  "progress=false", f"published_dir={tmp_path / 'pub'}"])
    OmegaConf.set_struct(cfg, False)
    cfg.cases = [TINY_CASE]
    cfg.generated = {"count": 0, "held_out": 0, "preset": "cpu"}
    res = dt.run(cfg)
    out = Path(res["out_dir"])
    assert out.is_relative_to(tmp_path / "outputs" / "dss-denoise-table") and (out / "table.md").is_file()
    assert res["published"] == [] and not (tmp_path / "pub").exists() and not (tmp_path / "results").exists()
    cfg.out_dir, cfg.publish = str(out), True  # resume the run from its own folder, then publish
    res = dt.run(cfg)
    pub = {p.name for p in (tmp_path / "pub").iterdir()}
    assert pub == set(res["files"].values()) and {"table.md", "table.json", "README.md", "config.yaml"} <= pub
    assert (tmp_path / "pub" / "table.md").read_text() == (out / "table.md").read_text()


def test_results_index_lists_a_real_shape_report_with_its_command(tmp_path):
    """A dss-real-bench report under results/ gets its own section: the command from its README
    and one row per (noise level, group) with the default, the best classical and the oracle."""
    from experiments.evaluation.results_index import build

    folder = tmp_path / "results" / "denoise" / "real_2000"
    folder.mkdir(parents=True)
    (folder / "README.md").write_text("# t\n\nProduced by:\n\n```\ndss-real-bench 'groups=[held_out]'\n```\n")
    m = {k: {"chamfer": c, "hausdorff": h} for k, c, h in
         (("input", 0.5, 20.0), ("best_classical", 0.25, 12.0), ("dss_default", 0.2, 13.0), ("dss_oracle", 0.15, 11.0))}
    (folder / "report.json").write_text(json.dumps({"title": "Real shapes: test", "summary": {
        "dss_methods": ["dss_default", "dss_oracle"], "classical": ["jet"],
        "levels": [{"noise": 0.005, "group": "held_out", "n": 3, "mean": m}]}}))
    text = build(tmp_path / "results")
    assert "## Real shapes (`dss-real-bench`)" in text and "`dss-real-bench 'groups=[held_out]'`" in text
    assert "| 0.5% | held_out | 3 | 0.5 / 20 | 0.25 / 12 | 0.2 / 13 | 0.15 / 11 |" in text
