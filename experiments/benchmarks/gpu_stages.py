"""The whole-job stages of ``experiments/benchmarks/gpu_check.sh``: ``job``, ``deform``, ``train``.

    python -m experiments.benchmarks.gpu_stages job --out /tmp/g/job            # dss-denoise, 20K and 100K, on cuda
    python -m experiments.benchmarks.gpu_stages deform --out /tmp/g/deform      # dss-deform, the three scenes, on cuda
    python -m experiments.benchmarks.gpu_stages train --out /tmp/g/train --clouds <dss-clouds dir>
    python -m experiments.benchmarks.gpu_stages job --toy --device cpu --out /tmp/t   # the test's toy size

``job``: ``dss-denoise device=<device>`` on the shipped example (20K points, 1% noise) and on
``--points`` samples of the example's mesh (100K: uniform on the surface, seed 0, Gaussian noise
of ``--noise`` = 0.003 of the bounding-box diagonal; the noise-free samples are the clean cloud),
each a process of its own. ``job.json``: per input the whole process's wall seconds (start-up,
imports and kernel loading included), and from its ``metrics.json`` ``time_s``, the per-stage
``profile_s`` / ``profile_cpu_s`` and the Chamfer distances.

``deform``: ``python -m experiments.evaluation.deform_presets --presets default`` on
``--device`` (``presets.json``: Chamfer, Hausdorff, openings, wall and CPU seconds per scene).
The targets are read from ``$DSS_DATA`` (default ``../shared/data``).

``train``: ``dss-train experiment=planes_1pct data=onthefly`` (pairs rendered on the fly, on
the GPU when the device is one) of ``model=--model`` for ``--seconds`` of training
(``trainer.max_time``), then its validation and ONNX export; ``train.json`` (its metrics.json
and the wall seconds), ``denoiser.onnx`` and ``metrics.json`` beside it. The clouds:
``--clouds`` (a ``dss-prep output=clouds`` dataset), else made here with ``dss-prep`` (needs
open3d, which the GPU machines lack: make them on a CPU machine, see docs/development.md).

Every stage stops starting work when less than its share of ``--deadline`` seconds is left and
always writes its JSON. Exit status: the number of parts that failed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "experiments" / "assets" / "example"

__all__ = ["main", "sample_mesh", "make_noisy_input"]


def _write_json(path: Path, obj) -> None:
    from dss.io_utils import atomic_write_json

    atomic_write_json(path, obj)


def _needs(*modules: str) -> str | None:
    """None when every module imports, else one line naming the missing ones."""
    import importlib.util

    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if not missing:
        return None
    return (f"missing Python packages {', '.join(missing)} (on a GPU machine carry their wheels: "
            "docs/development.md \"GPU check\")")


class Clock:
    """The stage's deadline: ``left()`` seconds, ``enough(s)`` when ``s`` of them are left."""

    def __init__(self, deadline: float):
        self.t0, self.deadline = time.perf_counter(), float(deadline)

    def left(self) -> float:
        return self.deadline - (time.perf_counter() - self.t0) if self.deadline > 0 else float("inf")

    def enough(self, seconds: float) -> bool:
        return self.left() >= seconds


def _run(argv: list[str], log: Path, timeout: float, env: dict | None = None) -> tuple[int, float, str]:
    """(exit status, wall seconds, why) of one process, its output in ``log``."""
    t0 = time.perf_counter()
    try:
        with open(log, "w") as f:
            rc = subprocess.run(argv, stdout=f, stderr=subprocess.STDOUT, cwd=REPO, timeout=max(1.0, timeout),
                                env={**os.environ, **(env or {})}).returncode
        why = "ok" if rc == 0 else f"exit {rc}: " + " | ".join(log.read_text(errors="replace").strip().splitlines()[-2:])
    except subprocess.TimeoutExpired:
        rc, why = -1, f"stopped at its {timeout:.0f} s share of the deadline"
    return rc, time.perf_counter() - t0, why


# ------------------------------------------------------------------------------ job
def sample_mesh(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform on a triangle mesh's surface (area-weighted triangles, uniform
    barycentric coordinates) and their triangles' unit normals, float32 (n, 3) each."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    area = np.linalg.norm(cross, axis=1)
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    pts = (1 - r1)[:, None] * a[tri] + (r1 * (1 - r2))[:, None] * b[tri] + (r1 * r2)[:, None] * c[tri]
    nrm = cross[tri] / np.maximum(area[tri], 1e-30)[:, None]
    return pts.astype(np.float32), nrm.astype(np.float32)


def make_noisy_input(folder: Path, n: int, noise: float, seed: int = 0) -> tuple[Path, Path]:
    """``n`` samples of the shipped example's mesh: ``clean_<n>.ply`` (with the triangles'
    normals) and ``noisy_<n>.ply`` (points only, + Gaussian noise of ``noise`` x the bounding-box
    diagonal) in ``folder``; made once (kept when there)."""
    import torch

    from dss.pointcloud import PointCloud, add_gaussian_noise, read_ply_triangles, save_ply

    folder.mkdir(parents=True, exist_ok=True)
    clean, noisy = folder / f"clean_{n}.ply", folder / f"noisy_{n}.ply"
    if not (clean.is_file() and noisy.is_file()):
        vf = read_ply_triangles(EXAMPLE / "mesh.ply")
        if vf is None:
            raise RuntimeError(f"{EXAMPLE / 'mesh.ply'}: not a binary triangle PLY")
        pts, nrm = sample_mesh(*vf, n, seed)
        p = torch.from_numpy(pts)
        save_ply(clean, PointCloud(p, torch.from_numpy(nrm)))
        save_ply(noisy, PointCloud(add_gaussian_noise(p, noise, seed=seed + 1)))
    return clean, noisy


def stage_job(args) -> int:
    from dss.io_utils import atomic_write_json  # noqa: F401  (fails early without the package)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    clock = Clock(args.deadline)
    missing = _needs("hydra", "omegaconf")
    inputs = ["example", *[str(n) for n in args.points]]
    records, failed = [], 0
    for i, name in enumerate(inputs):
        rec = {"input": name, "device": args.device}
        share = clock.left() / (len(inputs) - i) if args.deadline > 0 else 3600.0
        if missing:
            rec.update(status="failed", why=missing)
        elif not clock.enough(10):
            rec.update(status="skipped", why=f"{clock.left():.0f} s left of --deadline {args.deadline:g}")
        else:
            overrides = [f"device={args.device}", "progress=false", "wandb.log=false", "overwrite=true",
                         f"hydra.run.dir={out / name}", *args.set]
            if name != "example":
                clean, noisy = make_noisy_input(out / "inputs", int(name), args.noise)
                overrides = [f"input={noisy}", f"clean={clean}", f"mesh={EXAMPLE / 'mesh.ply'}", *overrides]
                rec.update(points=int(name), noise=args.noise)
            else:
                rec.update(points=20000, noise=0.01)
            rc, wall, why = _run([sys.executable, "-m", "experiments.apps.denoise", *overrides], out / f"{name}.log",
                                 share)
            rec.update(command="dss-denoise " + " ".join(overrides), process_wall_s=wall,
                       status="ok" if rc == 0 else "failed", why=why)
            m = out / name / "metrics.json"
            if rc == 0 and m.is_file():
                metrics = json.loads(m.read_text())
                rec.update({k: metrics.get(k) for k in ("time_s", "profile_s", "profile_cpu_s", "device",
                                                         "torch_threads", "summary", "budget")})
        failed += rec["status"] != "ok"
        records.append(rec)
        took = "" if "time_s" not in rec else f" job {rec['time_s']['total']:.2f} s (process {rec['process_wall_s']:.1f} s)"
        print(f"job {name}: {rec['status']} {rec.get('why', '')}{took}", flush=True)
    _write_json(out / "job.json", {"stage": "job", "deadline_s": args.deadline, "runs": records})
    return failed


# ------------------------------------------------------------------------------ deform
def stage_deform(args) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    missing = _needs("hydra", "omegaconf")
    data = Path(os.environ.get("DSS_DATA", "../shared/data"))
    if not missing:
        absent = [n for n in ("yoga1_out.ply", "teapot_normal_dense.ply", "bunny-8000.ply")
                  if not (data / n).is_file() and not any("target.path" in s for s in args.set)]
        if absent:
            missing = f"the targets {', '.join(absent)} are not in DSS_DATA={data} (copy ../shared/data there)"
    if missing:
        _write_json(out / "presets.json", {"stage": "deform", "status": "failed", "why": missing})
        print(f"deform: failed: {missing}")
        return 1
    from experiments.evaluation import deform_presets

    argv = ["--presets", "default", "--device", args.device, "--threads", str(args.threads), "--out", str(out)]
    if args.deadline > 0:  # three runs: each gets a third of what is left at the start, less the summary's
        argv += ["--timeout", str(max(10.0, (args.deadline - 10) / 3))]
    if args.set:
        argv += ["--set", *args.set]
    return deform_presets.main(argv)


# ------------------------------------------------------------------------------ train
def stage_train(args) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    clock = Clock(args.deadline)
    rec = {"stage": "train", "device": args.device, "model": args.model, "train_seconds": args.seconds}
    missing = _needs("hydra", "omegaconf", "lightning", "onnx")
    clouds = Path(args.clouds) if args.clouds else out / "clouds"
    if not missing and not (clouds / "manifest.json").is_file():
        if args.clouds:
            missing = f"{clouds}: no dss-clouds dataset (manifest.json) there"
        elif _needs("open3d"):
            missing = ("no --clouds given and no open3d to make them: make a dataset on a CPU machine "
                       "(docs/development.md \"GPU check\") and pass --clouds / DSS_TRAIN_CLOUDS")
        else:
            prep = ["prep_preset=tiny", "render=planes", "output=clouds", f"out_dir={clouds}", "progress=false",
                    f"hydra.run.dir={out / 'prep'}"] + (["shapes.per_family=2", "sampling.num_points=1500"]
                                                        if args.toy else ["render.image_size=[128,128]"])
            rc, wall, why = _run([sys.executable, "-m", "experiments.apps.prep", *prep], out / "prep.log",
                                 clock.left())
            rec["prep"] = {"command": "dss-prep " + " ".join(prep), "wall_s": wall, "status": why}
            if rc != 0:
                missing = f"dss-prep clouds failed: {why}"
    if missing:
        rec.update(status="failed", why=missing)
        _write_json(out / "train.json", rec)
        print(f"train: failed: {missing}")
        return 1
    accelerator = "gpu" if args.device.startswith("cuda") else "cpu"
    run_dir = out / "run"
    overrides = ["experiment=planes_1pct", "data=onthefly", f"data.root={clouds}", f"model={args.model}",
                 f"trainer.accelerator={accelerator}", "trainer.devices=1", "logger=csv",
                 f"trainer.max_time=00:00:00:{int(args.seconds):02d}" if args.seconds < 60 else
                 f"trainer.max_time=00:00:{int(args.seconds) // 60:02d}:{int(args.seconds) % 60:02d}",
                 f"data.device={'cuda' if accelerator == 'gpu' else 'cpu'}", "data.num_workers=0",
                 f"hydra.run.dir={run_dir}", *args.set]
    rc, wall, why = _run([sys.executable, "-m", "experiments.apps.train", *overrides], out / "train.log",
                         max(10.0, clock.left() - 5))
    rec.update(command="dss-train " + " ".join(overrides), process_wall_s=wall, status="ok" if rc == 0 else "failed",
               why=why)
    m = run_dir / "metrics.json"
    if rc == 0 and m.is_file():
        rec["metrics"] = json.loads(m.read_text())
        shutil.copyfile(m, out / "metrics.json")
        onnx = run_dir / "denoiser.onnx"
        if onnx.is_file():
            shutil.copyfile(onnx, out / "denoiser.onnx")
            rec["onnx_bytes"] = onnx.stat().st_size
        else:
            rec.update(status="failed", why="no denoiser.onnx exported")
    _write_json(out / "train.json", rec)
    print(f"train: {rec['status']} ({rec['why']}), process {wall:.1f} s", flush=True)
    return int(rec["status"] != "ok")


# ------------------------------------------------------------------------------ main
# toy sizes: seconds per run on one CPU thread (a sparser start cloud makes the topology metric's
# disks, sized by the spacing, slow: 400 cube points take 44 s there, 1500 take 7 s in all)
TOY = {
    "job": ["optimizer.cycles=1", "figures.enabled=false"],
    "deform": ["start.points=1500", "image_size=32", "optimizer.cycles=1", "optimizer.point_steps=2",
               "optimizer.normal_steps=1", "optimizer.hull_views=2", "snapshot_steps=[0]", "chamfer_every=0"],
    "train": ["model.train_crop_size=32", "data.views_per_shape=1", "data.batch_size=2", "data.max_val_pairs=2",
              "trainer.limit_train_batches=2", "trainer.max_epochs=1", "trainer.limit_val_batches=1"],
}


def parse_args(argv):
    ap = argparse.ArgumentParser(prog="python -m experiments.benchmarks.gpu_stages", description=__doc__.split("\n")[0])
    ap.add_argument("stage", choices=("job", "deform", "train"))
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--device", default="cuda", help="cuda (default), cpu or auto")
    ap.add_argument("--deadline", type=float, default=float(os.environ.get("STAGE_DEADLINE_S", 0) or 0),
                    help="seconds for the whole stage (default: $STAGE_DEADLINE_S, set by gpu_check.sh; 0: none)")
    ap.add_argument("--points", type=int, nargs="*", default=[100000], help="job: sampled inputs besides the example")
    ap.add_argument("--noise", type=float, default=0.003, help="job: noise of the sampled inputs (bbox diagonals)")
    ap.add_argument("--threads", type=int, default=0, help="deform: threads per run (0: torch's default)")
    ap.add_argument("--clouds", default=os.environ.get("DSS_TRAIN_CLOUDS") or None,
                    help="train: a dss-prep output=clouds dataset (default: $DSS_TRAIN_CLOUDS, else made here)")
    ap.add_argument("--model", default="cpu_small", help="train: model preset")
    ap.add_argument("--seconds", type=int, default=60, help="train: training time (trainer.max_time)")
    ap.add_argument("--toy", action="store_true", help="toy sizes (the CPU test): small inputs, a step or two")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="more settings for the app")
    args = ap.parse_args(argv)
    if args.toy:
        if args.stage == "job":
            args.points = [1500]
        args.set = TOY[args.stage] + list(args.set)
        if args.stage == "train":
            args.model = "tiny"
            args.seconds = min(args.seconds, 30)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    return {"job": stage_job, "deform": stage_deform, "train": stage_train}[args.stage](args)


if __name__ == "__main__":
    sys.exit(main())
