"""The apps under bad input and faults: scale, claimed outputs, errors for people (fast)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from scenes import sphere_points

from dss.pointcloud import PointCloud, save_ply

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
torch.set_num_threads(1)


def compose_cfg(name: str, overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(name, overrides=overrides)


def render_cfg(cloud: Path, out: Path, *extra: str):
    return compose_cfg("render_cloud", [f"input={cloud}", "views=2", "image_size=32", f"+out_dir={out}", *extra])


@pytest.fixture(scope="module")
def sphere_ply(tmp_path_factory) -> Path:
    p, n = sphere_points(800, 0.4)
    path = tmp_path_factory.mktemp("cloud") / "sphere.ply"
    save_ply(path, PointCloud(p, n))
    return path


# ------------------------------------------------------------------------------- scale
def test_render_of_a_tiny_cloud_in_its_own_units_matches_the_unit_scale_one(sphere_ply, tmp_path):
    """A cloud 1e-6 across with normalize=false renders as the unit-scale one (not all white)."""
    import matplotlib.image

    from dss.pointcloud import load_ply
    from experiments.apps.render import run

    c = load_ply(sphere_ply)
    small = tmp_path / "small.ply"
    save_ply(small, PointCloud(c.points * 1e-6, c.normals))
    m1 = run(render_cfg(sphere_ply, tmp_path / "unit"))
    ms = run(render_cfg(small, tmp_path / "small", "normalize=false"))
    assert m1["coverage"] > 0.05
    assert ms["coverage"] == pytest.approx(m1["coverage"], abs=1e-3)
    a = matplotlib.image.imread(tmp_path / "unit" / "sun.png")
    b = matplotlib.image.imread(tmp_path / "small" / "sun.png")
    assert np.abs(a - b).max() < 0.02
    assert ms["camera_distance"] == pytest.approx(m1["camera_distance"] * float(np.linalg.norm(
        (c.points.max(0).values - c.points.min(0).values).numpy())) * 1e-6, rel=1e-3)


# ------------------------------------------------------------------------------- blow-up
def test_deform_blowup_fails_without_writing_a_result(sphere_ply, tmp_path):
    """dss-deform with lr_points 1e6: steps that fling points away are undone; when halving the
    rates cannot recover (here: at most 2 halvings) the run fails and writes no final.ply or
    metrics.json."""
    from dss.optimize import OptimizationDiverged
    from experiments.apps.deform import run

    out = tmp_path / "deform"
    cfg = compose_cfg("deform", [f"target.path={sphere_ply}", "start.points=300", "image_size=32",
                                 "optimizer.cycles=1", "optimizer.point_steps=4", "optimizer.normal_steps=1",
                                 "snapshot_steps=[0]", "chamfer_every=0", "progress=false", "optimizer.lr_points=1e6",
                                 "+optimizer.max_lr_halvings=2", f"+out_dir={out}"])
    with pytest.raises(OptimizationDiverged, match="grew the cloud.*lower the learning rates"):
        run(cfg)
    assert not (out / "final.ply").exists() and not (out / "metrics.json").exists()


# ------------------------------------------------------------------------------- claimed outputs
REPO = Path(__file__).resolve().parents[1]


def _env() -> dict:
    import os

    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "DSS_DEBUG")}
    env.setdefault("OMP_NUM_THREADS", "1")
    return env


def _cli(module: str, *args: str, env: dict | None = None):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True,
                          env=env or _env(), timeout=300, cwd=REPO)


def _holder(path: Path):
    """A second process that claims ``path`` (a run directory) and holds it until its stdin closes."""
    import subprocess
    import sys

    code = ("import sys; from pathlib import Path; from experiments.common import claim_run_dir; "
            f"claim_run_dir(Path({str(path)!r}), ()); print('held', flush=True); sys.stdin.read()")
    p = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                         cwd=REPO, env=_env())
    assert p.stdout.readline().strip() == "held"
    return p


def test_a_second_run_into_a_claimed_directory_fails_at_once(sphere_ply, tmp_path):
    from experiments.apps.render import run
    from experiments.common import OutputInUseError, release_claims

    out = tmp_path / "busy"
    holder = _holder(out)
    try:
        with pytest.raises(OutputInUseError, match=r"busy is being written by another running process"):
            run(render_cfg(sphere_ply, out))
        assert sorted(p.name for p in out.iterdir()) == [".dss-run.lock"]  # nothing written
    finally:
        holder.stdin.close()
        holder.wait(30)
        release_claims()
    m = run(render_cfg(sphere_ply, out))  # free again once the other process ended
    assert m["views"] == 2


def test_refused_cli_run_leaves_the_earlier_runs_files_as_they_were(sphere_ply, tmp_path):
    """`dss-render hydra.run.dir=D` twice: the second is refused in one line (exit 2) before Hydra
    writes its .hydra/*.yaml, so the first run's stay byte for byte."""
    d = tmp_path / "run"
    first = _cli("experiments.apps.render", str(sphere_ply), "views=2", "image_size=32", f"hydra.run.dir={d}")
    assert first.returncode == 0, first.stderr[-2000:]
    before = {p.name: p.read_bytes() for p in (d / ".hydra").glob("*.yaml")}
    assert set(before) == {"config.yaml", "hydra.yaml", "overrides.yaml"}
    second = _cli("experiments.apps.render", str(sphere_ply), "views=3", "image_size=32", f"hydra.run.dir={d}")
    assert second.returncode == 2
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1 and "holds an earlier run's results" in lines[0] and "overwrite=true" in lines[0], lines
    assert {p.name: p.read_bytes() for p in (d / ".hydra").glob("*.yaml")} == before
    # overwrite=true replaces the earlier run: no older view PNG stays beside the new ones
    assert (d / "views" / "sun_001.png").is_file()
    third = _cli("experiments.apps.render", str(sphere_ply), "views=1", "image_size=32", "overwrite=true",
                 f"hydra.run.dir={d}")
    assert third.returncode == 0, third.stderr[-2000:]
    assert sorted(p.name for p in (d / "views").glob("*.png")) == ["depth_000.png", "normals_000.png", "sun_000.png"]


def _denoise_overrides(cloud: Path, out: Path, *extra: str) -> list[str]:
    return [f"input={cloud}", f"out_dir={out}", "reference=l0", "image_size=32", "optimizer.cycles=1",
            "optimizer.normal_steps=1", "figures.views=1", "figures.image_size=32", "progress=false",
            "metrics.floor=false", "optimizer.final_projection_k=8", *extra]


@pytest.fixture(scope="module")
def noisy_with_outliers(tmp_path_factory) -> Path:
    from data_prep.sampling import noisy_copy
    from dss.ply import write_ply

    p, _ = sphere_points(1500, 0.4)
    noisy = noisy_copy(p.numpy(), 0.01, seed=1)
    gas = np.random.default_rng(2).uniform(noisy.min(0), noisy.max(0), size=(40, 3)).astype(np.float32)
    path = tmp_path_factory.mktemp("outl") / "noisy.ply"
    write_ply(path, np.concatenate([noisy, gas]))
    return path


def test_denoise_refuses_a_used_run_dir_and_overwrite_leaves_no_stale_file(noisy_with_outliers, tmp_path):
    from experiments.apps.denoise import run
    from experiments.common import OutputExistsError

    out = tmp_path / "run"
    m = run(compose_cfg("denoise", _denoise_overrides(noisy_with_outliers, out)))
    assert m["outliers"]["removed"] > 0 and (out / "outliers.ply").is_file()
    before = (out / "metrics.json").read_bytes()
    with pytest.raises(OutputExistsError, match=r"holds an earlier run's results"):
        run(compose_cfg("denoise", _denoise_overrides(noisy_with_outliers, out, "outliers.remove=false")))
    assert (out / "metrics.json").read_bytes() == before
    m2 = run(compose_cfg("denoise", _denoise_overrides(noisy_with_outliers, out, "outliers.remove=false",
                                                       "overwrite=true")))
    assert m2["outliers"]["removed"] == 0
    assert not (out / "outliers.ply").exists()  # the earlier run's outliers do not sit beside new metrics


def test_an_output_that_appears_meanwhile_is_not_replaced(tmp_path):
    """Exclusive publishing: a file created at the target while a run wrote its result keeps its
    bytes, and the run's result goes beside it (nothing lost)."""
    from dss.io_utils import atomic_path

    target = tmp_path / "denoised.ply"
    writer = atomic_path(target, exclusive=True)
    with writer as tmp:
        tmp.write_bytes(b"ours")
        target.write_bytes(b"theirs")  # another writer got there first
    assert target.read_bytes() == b"theirs"
    assert writer.path == tmp_path / "denoised-1.ply" and writer.path.read_bytes() == b"ours"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["denoised-1.ply", "denoised.ply"]


# ------------------------------------------------------------------------------- fail first
def test_denoise_checks_outputs_points_and_model_before_any_work(noisy_with_outliers, sphere_ply, tmp_path,
                                                                 monkeypatch):
    """An unwritable output, too few points and a foreign ONNX model are refused before the
    optimisation starts and before any file is written (outliers.ply included)."""
    import onnx
    from onnx import TensorProto, helper

    from dss.optimize import MultiViewOptimizer
    from experiments.apps.denoise import run
    from pix2pix.runtime import DenoiserFormatError

    steps = []
    monkeypatch.setattr(MultiViewOptimizer, "run", lambda self, **kw: steps.append(1))

    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    out = tmp_path / "unwritable"
    with pytest.raises(PermissionError, match=r"output .*a_file/denoised\.ply: cannot write into"):
        run(compose_cfg("denoise", _denoise_overrides(noisy_with_outliers, out, f"output={blocker / 'denoised.ply'}")))
    assert not steps and not [p for p in out.iterdir() if not p.name.endswith(".lock")]

    from dss.pointcloud import load_ply

    few = tmp_path / "few.ply"
    c = load_ply(sphere_ply)
    save_ply(few, PointCloud(c.points[::16][:50], c.normals[::16][:50]))
    out = tmp_path / "few"
    with pytest.raises(ValueError, match=r"few\.ply has 50 points, too few for this optimisation"):
        run(compose_cfg("denoise", _denoise_overrides(few, out, "optimizer.final_projection_k=96",
                                                      "outliers.remove=false")))
    assert not steps and not [p for p in out.iterdir() if not p.name.endswith(".lock")]

    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 4, 4])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3, 4, 4])
    relu = tmp_path / "relu.onnx"
    onnx.save(helper.make_model(helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "g", [x], [y]),
                                opset_imports=[helper.make_opsetid("", 17)]), str(relu))
    out = tmp_path / "model"
    with pytest.raises(DenoiserFormatError, match=r"relu\.onnx"):
        run(compose_cfg("denoise", _denoise_overrides(noisy_with_outliers, out, "reference=onnx",
                                                      f"reference.model={relu}")))
    assert not steps and not [p for p in out.iterdir() if not p.name.endswith(".lock")]  # no outliers.ply


# ------------------------------------------------------------------------------- errors for people
def test_expected_failures_print_one_line_and_exit_2(sphere_ply, tmp_path):
    cut = tmp_path / "cut.ply"
    data = sphere_ply.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    cases = [
        (("experiments.apps.render", str(sphere_ply), "inptu=x", f"hydra.run.dir={tmp_path / 'a'}"),
         r"unknown key 'inptu' \(did you mean 'input'\?\)"),
        (("experiments.apps.denoise", "reference=onxx", f"hydra.run.dir={tmp_path / 'b'}"),
         r"no config 'onxx' in 'reference' \(did you mean 'onnx'\?\)"),
        (("experiments.apps.denoise", "reference.model=my.onnx", f"hydra.run.dir={tmp_path / 'g'}"),
         r"unknown key 'reference.model': .*needs reference=onnx reference.model="),
        (("experiments.apps.render", str(cut), f"hydra.run.dir={tmp_path / 'c'}"), r"cut\.ply: truncated"),
        (("experiments.apps.render", f"hydra.run.dir={tmp_path / 'd'}"), r"missing value: input=\.\.\. is required"),
        (("experiments.apps.train", f"data.root={tmp_path / 'nodata'}", "logger=none", f"hydra.run.dir={tmp_path / 'e'}"),
         r"nodata does not exist: make it with `dss-prep`"),
    ]
    for args, pattern in cases:
        proc = _cli(*args)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2, (args, proc.stderr[-2000:])
        assert len(lines) == 1 and "Traceback" not in proc.stderr, (args, proc.stderr[-2000:])
        assert lines[0].split(": error: ")[0].endswith(".py")
        import re

        assert re.search(pattern, lines[0]), (args, lines[0])
    # the traceback is one switch away
    proc = _cli("experiments.apps.render", str(cut), f"hydra.run.dir={tmp_path / 'f'}", env={**_env(), "DSS_DEBUG": "1"})
    assert proc.returncode != 0 and "Traceback" in proc.stderr and "truncated" in proc.stderr


# ------------------------------------------------------------------------------- scale-out
@pytest.mark.slow  # two app processes in parallel (about 25 s on 2 cores): pytest -m slow
def test_joblib_launcher_runs_a_multirun_in_parallel_jobs(sphere_ply, tmp_path):
    """`-m hydra/launcher=joblib` (the launcher conf/prep.yaml names for parallel jobs): two jobs in
    worker processes, each with its own run directory and results."""
    import json

    import yaml

    sweep = tmp_path / "sweep"
    proc = _cli("experiments.apps.render", "-m", f"input={sphere_ply}", "views=1,2", "image_size=32",
                "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    views = sorted(json.loads((sweep / str(j) / "metrics.json").read_text())["views"] for j in (0, 1))
    assert views == [1, 2]
    launcher = yaml.safe_load((sweep / "multirun.yaml").read_text())["hydra"]["launcher"]["_target_"]
    assert "JoblibLauncher" in launcher
