"""gpu_check.sh's whole-job stages (job, deform, train): the plumbing (fast), the 100K input's
sampling (fast) and the three stages end to end on the CPU at a toy size (slow)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from experiments.benchmarks.gpu_stages import make_noisy_input, sample_mesh

REPO = Path(__file__).resolve().parents[1]
GPU_CHECK = REPO / "experiments" / "benchmarks" / "gpu_check.sh"


def _check(tmp_path, stages, **env):
    e = {**os.environ, "OUT": str(tmp_path / "out"), **{k: str(v) for k, v in env.items()}}
    return subprocess.run(["bash", str(GPU_CHECK), *stages], env=e, capture_output=True, text=True, cwd=REPO,
                          timeout=1200)


def test_stages_call_gpu_stages_with_the_device_out_folder_toy_switch_and_deadline(tmp_path):
    """A stand-in python records each stage's command line and STAGE_DEADLINE_S."""
    fake = tmp_path / "python"
    record = tmp_path / "calls.txt"
    fake.write_text(f'#!/bin/bash\necho "$STAGE_DEADLINE_S $*" >> {record}\n')
    fake.chmod(0o755)
    r = _check(tmp_path, ["job", "deform", "train"], PYTHON=fake, DEVICE="cpu", TOY=1, DEADLINE_S=400)
    assert r.returncode == 0, r.stdout + r.stderr
    calls = record.read_text().splitlines()
    out = tmp_path / "out"
    assert len(calls) == 3
    for line, stage in zip(calls, ("job", "deform", "train")):
        deadline, *argv = line.split()
        assert argv[:3] == ["-m", "experiments.benchmarks.gpu_stages", stage]
        assert "--device cpu" in line and f"--out {out / stage}" in line and argv[-1] == "--toy"
        assert 0 < int(deadline) <= 400 - 15 - 5  # the stage's limit (cut by DEADLINE_S) less 5 s
    r = _check(tmp_path, ["job"], PYTHON=fake)  # without TOY and DEVICE: the GPU, full size
    assert r.returncode == 0
    last = record.read_text().splitlines()[-1]
    assert "--device cuda" in last and "--toy" not in last


def test_the_sampled_input_lies_on_the_mesh_with_the_asked_noise(tmp_path):
    from dss.pointcloud import load_ply, read_ply_triangles

    v, f = read_ply_triangles(REPO / "experiments" / "assets" / "example" / "mesh.ply")
    pts, nrm = sample_mesh(v, f, 4000, seed=0)
    assert pts.shape == (4000, 3) and np.allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-4)
    # every sample on a triangle: its distance to the nearest vertex is at most the longest edge
    from scipy.spatial import cKDTree

    edge = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1).max()
    assert cKDTree(v).query(pts)[0].max() <= edge
    clean, noisy = make_noisy_input(tmp_path, 4000, 0.003)
    c, n = load_ply(clean).points.numpy(), load_ply(noisy, compute_normals=False).points.numpy()
    diag = np.linalg.norm(c.max(0) - c.min(0))
    assert np.std(n - c) / diag == pytest.approx(0.003, rel=0.1)
    stamp = noisy.stat().st_mtime_ns
    make_noisy_input(tmp_path, 4000, 0.003)  # made once
    assert noisy.stat().st_mtime_ns == stamp


@pytest.mark.slow
def test_job_deform_and_train_stages_run_on_the_cpu_at_a_toy_size(tmp_path):
    import torch
    from scenes import sphere_points

    from dss.pointcloud import PointCloud, save_ply

    data = tmp_path / "data"
    data.mkdir()
    p, n = sphere_points(600, 0.4)
    for name in ("yoga1_out.ply", "teapot_normal_dense.ply", "bunny-8000.ply"):
        save_ply(data / name, PointCloud(p * torch.tensor([1.0, 1.3, 0.8]), n))
    import sys

    from torch.utils.cpp_extension import get_default_build_root

    # the kernels this checkout already built (gpu_check.sh's own default is a fresh folder):
    # torch's folder when TORCH_EXTENSIONS_DIR is not set
    ext = os.environ.get("TORCH_EXTENSIONS_DIR") or os.path.join(
        get_default_build_root(), f"py{sys.version_info.major}{sys.version_info.minor}_"
        + (f"cu{torch.version.cuda.replace('.', '')}" if torch.version.cuda else "cpu"))
    r = _check(tmp_path, ["job", "deform", "train"], PYTHON=os.environ.get("PYTHON", "python"), DEVICE="cpu", TOY=1,
               DSS_DATA=data, OMP_NUM_THREADS=1, DEADLINE_S=900, TORCH_EXTENSIONS_DIR=ext)
    out = tmp_path / "out"
    assert r.returncode == 0, r.stdout + "".join((out / f"{s}.txt").read_text() for s in ("job", "deform", "train")
                                                  if (out / f"{s}.txt").is_file())
    job = json.loads((out / "job" / "job.json").read_text())
    assert [x["input"] for x in job["runs"]] == ["example", "1500"]
    for x in job["runs"]:
        assert x["status"] == "ok" and x["time_s"]["total"] > 0 and x["profile_s"] and x["process_wall_s"] > 0
    deform = json.loads((out / "deform" / "presets.json").read_text())
    assert [(x["scene"], x["status"]) for x in deform["runs"]] == [
        ("sphere_teapot", "ok"), ("sphere_bunny", "ok"), ("cube_yoga", "ok")]
    assert all(x["device"] == "cpu" and x["wall_time_s"] > 0 for x in deform["runs"])
    train = json.loads((out / "train" / "train.json").read_text())
    assert train["status"] == "ok", train
    assert (out / "train" / "denoiser.onnx").stat().st_size > 0 and (out / "train" / "metrics.json").is_file()
