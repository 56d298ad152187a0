"""How a run of the apps starts and ends: options checked before the work, Ctrl-C, refused and
killed runs, lock files, logs, inputs with nothing to remove (fast)."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from scenes import sphere_points

from dss.pointcloud import PointCloud, save_ply

REPO = Path(__file__).resolve().parents[1]
CONF_DIR = REPO / "conf"
torch.set_num_threads(1)


def _cfg(name: str, overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(name, overrides=overrides)


@pytest.fixture(scope="module")
def noisy_ply(tmp_path_factory) -> Path:
    from data_prep.sampling import noisy_copy

    p, _ = sphere_points(1500, 0.4)
    path = tmp_path_factory.mktemp("cloud") / "noisy.ply"
    save_ply(path, PointCloud(torch.from_numpy(noisy_copy(p.numpy(), 0.01, seed=1))))
    return path


def _denoise(cloud: Path, out: Path, *extra: str) -> list[str]:
    return [f"input={cloud}", f"out_dir={out}", "reference=l0", "image_size=32", "optimizer.cycles=1",
            "optimizer.normal_steps=1", "figures.views=1", "figures.image_size=32", "progress=false",
            "metrics.floor=false", "optimizer.final_projection_k=8", *extra]


@pytest.fixture()
def no_optimisation(monkeypatch):
    """Record optimisation runs instead of doing them (what must not happen before a refusal)."""
    from dss.optimize import MultiViewOptimizer

    steps = []
    monkeypatch.setattr(MultiViewOptimizer, "run", lambda self, **kw: steps.append(1))
    return steps


# ------------------------------------------------------------------------------ checked first
@pytest.mark.parametrize("bad,pattern", [
    ("figures.views=abc", r"figures\.views='abc': must be a positive integer"),
    ("figures.image_size=0", r"figures\.image_size=0: must be a positive integer"),
    ("+figures.dpi=300", r"figures: unknown keys \['dpi'\]"),
    ("figures.enabled=maybe", r"figures\.enabled='maybe': must be true or false"),
])
def test_figures_options_are_refused_before_any_work(bad, pattern, noisy_ply, tmp_path, no_optimisation):
    from experiments.apps.denoise import run
    from experiments.common import release_claims

    out = tmp_path / "run"
    with pytest.raises(ValueError, match=pattern):
        run(_cfg("denoise", _denoise(noisy_ply, out, bad)))
    release_claims()
    assert not no_optimisation
    assert not (out / "denoised.ply").exists() and not (out / "metrics.json").exists()


def test_a_noise_hint_that_is_not_a_number_names_the_key(noisy_ply, tmp_path, no_optimisation):
    from experiments.apps.denoise import run
    from experiments.common import release_claims

    with pytest.raises(ValueError, match=r"^noise='abc' is not a number"):
        run(_cfg("denoise", _denoise(noisy_ply, tmp_path / "run", "noise=abc")))
    release_claims()
    assert not no_optimisation


def test_a_noise_free_input_is_said_to_be_one(tmp_path, caplog):
    """A clean surface: the job says its noise is below what it can improve (log and metrics)."""
    from experiments.apps.denoise import run

    p, n = sphere_points(3000, 0.4)
    save_ply(tmp_path / "clean.ply", PointCloud(p, n))
    with caplog.at_level(logging.WARNING):
        m = run(_cfg("denoise", _denoise(tmp_path / "clean.ply", tmp_path / "run", "figures.enabled=false")))
    assert m["noise"]["estimated"] < 0.001
    assert "below what the job can improve" in m["noise"]["note"]
    assert "clean.ply: the estimated noise" in caplog.text and "looks noise-free" in caplog.text


# ------------------------------------------------------------------------------ Ctrl-C
def _interrupt(*args, **kwargs):
    raise KeyboardInterrupt


def test_ctrl_c_on_denoise_leaves_no_result_looking_complete(noisy_ply, tmp_path, monkeypatch, capsys):
    """Ctrl-C after the denoised cloud was written (while it is scored): one line, exit 130, the
    run's results removed, no lock file beside the output; a rerun into the directory is not
    refused (only the run's config and log remain)."""
    import experiments.apps.denoise as dn
    from experiments.denoising import job

    out = tmp_path / "run"
    output = tmp_path / "elsewhere" / "mine.ply"
    monkeypatch.setattr(job, "score", _interrupt)
    with pytest.raises(SystemExit) as exit_info:
        dn._main(_cfg("denoise", _denoise(noisy_ply, out, f"output={output}")))
    assert exit_info.value.code == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "interrupted" in err[0] and "Traceback" not in err[0], err
    assert not output.exists() and not (out / "metrics.json").exists()
    assert sorted(p.name for p in output.parent.iterdir()) == []  # no .mine.ply.lock either
    monkeypatch.undo()
    m = dn.run(_cfg("denoise", _denoise(noisy_ply, out, f"output={output}")))
    assert Path(m["output"]) == output and output.is_file()


def test_ctrl_c_on_deform_leaves_no_result_looking_complete(noisy_ply, tmp_path, monkeypatch, capsys):
    import experiments.apps.deform as df
    from experiments.deformation import outputs

    out = tmp_path / "deform"
    monkeypatch.setattr(outputs, "plot_curves", _interrupt)  # after final.ply and the snapshots
    cfg = _cfg("deform", [f"target.path={noisy_ply}", "start.points=200", "image_size=32", "optimizer.cycles=1",
                          "optimizer.point_steps=1", "optimizer.normal_steps=1", "snapshot_steps=[0]",
                          "chamfer_every=0", "progress=false", f"+out_dir={out}"])
    with pytest.raises(SystemExit) as exit_info:
        df._main(cfg)
    assert exit_info.value.code == 130
    assert "interrupted" in capsys.readouterr().err
    assert not (out / "final.ply").exists() and not list(out.glob("snapshots/*.png"))


# ------------------------------------------------------------------------------ refused runs
def test_a_refused_run_leaves_no_lock_file_beside_its_output(tmp_path, capsys):
    """Too few points (refused after the output was claimed): exit 2 and no .x.ply.lock left."""
    import experiments.apps.denoise as dn

    p, n = sphere_points(40, 0.4)
    save_ply(tmp_path / "few.ply", PointCloud(p, n))
    output = tmp_path / "out" / "x.ply"
    with pytest.raises(SystemExit) as exit_info:
        dn._main(_cfg("denoise", _denoise(tmp_path / "few.ply", tmp_path / "run", f"output={output}",
                                          "optimizer.final_projection_k=96", "outliers.remove=false")))
    assert exit_info.value.code == 2
    assert "too few" in capsys.readouterr().err
    assert not (output.parent / ".x.ply.lock").exists()


def _cli(*args: str):
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "DSS_DEBUG")}
    env.setdefault("OMP_NUM_THREADS", "1")
    return subprocess.run([sys.executable, "-m", "experiments.apps.denoise", *args], capture_output=True, text=True,
                          env=env, timeout=300, cwd=REPO)


def test_refused_and_killed_runs_leave_nothing_that_blocks_a_rerun(tmp_path):
    """A run refused at input leaves no directory behind; a killed run's .hydra/, config and log
    (no result) do not make a rerun refused, and the rerun's log does not keep the killed run's
    lines; after overwrite=true neither does it; the error of a run in an existing directory
    goes into its log."""
    missing = tmp_path / "missing.ply"
    new = tmp_path / "a" / "b" / "run"
    proc = _cli(str(missing), f"hydra.run.dir={new}")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr[-2000:]
    assert "missing.ply: no such file" in proc.stderr
    assert not (tmp_path / "a").exists()

    killed = tmp_path / "killed"
    (killed / ".hydra").mkdir(parents=True)
    for name in ("config.yaml", "hydra.yaml", "overrides.yaml"):
        (killed / ".hydra" / name).write_text("from the killed run\n")
    (killed / "config.yaml").write_text("from the killed run\n")
    (killed / "denoise.log").write_text("KILLED RUN LINE\n")
    proc = _cli(str(missing), f"hydra.run.dir={killed}")
    assert proc.returncode == 2 and "missing.ply: no such file" in proc.stderr, proc.stderr[-2000:]
    assert "earlier run" not in proc.stderr
    log = (killed / "denoise.log").read_text()
    assert "KILLED RUN LINE" not in log and "missing.ply: no such file" in log

    (killed / "metrics.json").write_text("{}")
    (killed / "denoise.log").write_text("KILLED RUN LINE\n")
    proc = _cli(str(missing), "overwrite=true", f"hydra.run.dir={killed}")
    assert proc.returncode == 2 and "missing.ply: no such file" in proc.stderr, proc.stderr[-2000:]
    assert not (killed / "metrics.json").exists()
    assert "KILLED RUN LINE" not in (killed / "denoise.log").read_text()
    assert np.all([p.read_text() != "from the killed run\n" for p in (killed / ".hydra").glob("*.yaml")])
