"""dss-deform's outputs: snapshots during the run (renders at chosen steps, Chamfer against time),
``final.ply``, ``snapshots.png``, the curves, ``metrics.json``."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import torch

from dss.io_utils import atomic_savefig, atomic_write_json
from dss.metrics import evaluate, normal_error_to_points, spacing_stats
from dss.pointcloud import PointCloud, save_ply
from dss.render import render
from dss.topology import openings
from dss.viz import image_grid, save_png, to_uint8

__all__ = ["Recorder", "snapshot", "plot_curves", "plot_points_2d", "write_outputs", "final_metrics"]


class Recorder:
    """The optimiser's callback: a snapshot at each of ``steps`` (renders through ``cams``) and
    Chamfer / Hausdorff to the target ``tp`` every ``chamfer_every`` steps, against the run's
    time without these evaluations."""

    def __init__(self, steps, chamfer_every: int, cams, settings, shading, backend, tp):
        self.steps, self.chamfer_every = set(int(s) for s in steps), chamfer_every
        self.cams, self.settings, self.shading, self.backend, self.tp = cams, settings, shading, backend, tp
        self.snaps: dict[int, np.ndarray] = {}
        self.chamfer_log: list[dict] = []
        self.t_start = time.perf_counter()
        self.eval_time = 0.0

    def __call__(self, step, points, normals):
        t0 = time.perf_counter()
        if step in self.steps:
            self.snaps[step] = snapshot(points, normals, self.cams, self.settings, self.shading, self.backend)
        if self.chamfer_every and (step % int(self.chamfer_every) == 0):
            m = evaluate(points.cpu(), self.tp.cpu(), protocol="paper")
            self.chamfer_log.append({"step": step, "time_s": t0 - self.t_start - self.eval_time, "chamfer": m.chamfer,
                                     "hausdorff": m.hausdorff})
        self.eval_time += time.perf_counter() - t0

    def finish(self, result):
        """The last column: the output, after the final projection and normal re-fit."""
        final_step = result.history["steps"]
        if final_step not in self.snaps:
            self.steps.add(final_step)
            if not any(c["step"] == final_step for c in self.chamfer_log):
                self(final_step, result.points, result.normals)
        self.snaps[final_step] = snapshot(result.points, result.normals, self.cams, self.settings, self.shading,
                                          self.backend)


def snapshot(points, normals, cams, settings, shading, backend) -> np.ndarray:
    with torch.no_grad():
        imgs = render(points, normals, cams, settings, shading=shading, backend=backend).images
    return image_grid([to_uint8(i) for i in imgs], ncols=1)


def plot_curves(out: Path, history: dict, chamfer_log: list[dict], image_loss: str = "l1"):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(history["step"], history["image_loss"], lw=1)
    ax.set_xlabel("step")
    ax.set_ylabel(f"image loss ({image_loss.upper()}, mean over elements)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    atomic_savefig(fig, out / "loss_curve.png")
    plt.close(fig)
    if chamfer_log:
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.plot([c["time_s"] for c in chamfer_log], [c["chamfer"] for c in chamfer_log], "o-", ms=3)
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel("Chamfer to target (paper protocol, x1e4)")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        atomic_savefig(fig, out / "chamfer_vs_time.png")
        plt.close(fig)


def plot_points_2d(out: Path, points: torch.Tensor, spacing: dict):
    """The 2D grid experiments' figure (paper Fig. 2Dlocalminima): the final points on the image
    plane, where piling up (no repulsion) is visible and splat renders hide it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = points.detach().cpu().numpy()
    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    ax.scatter(p[:, 0], p[:, 1], s=2, c="k", linewidths=0)
    ax.set_aspect("equal")
    ax.set_title(f"points piled up: {100 * spacing['clustered_fraction']:.1f}% (nn < 1/4 mean)", fontsize=9)
    atomic_savefig(fig, out / "points_xy.png")
    plt.close(fig)


def write_outputs(out: Path, result, target, own_frame: bool, rec: Recorder, tp, tn, image_loss: str) -> None:
    """``final.ply`` (in the target's own frame when ``own_frame``: a target centred on load gets
    its offset back), the snapshots and ``snapshots.png`` (a column per step, the target's
    last), ``loss.json`` and the curves."""
    rp, rn = result.points.cpu(), result.normals.cpu()
    save_ply(out / "final.ply", PointCloud(rp, rn, offset=target.offset if own_frame else None,
                                           stored_as=target.stored_as if own_frame else "float"))
    (out / "snapshots").mkdir(exist_ok=True)
    for step, img in sorted(rec.snaps.items()):
        save_png(out / "snapshots" / f"step_{step:04d}.png", img)
    tgt_col = snapshot(tp, tn, rec.cams, rec.settings, rec.shading, rec.backend)
    cols = [rec.snaps[s] for s in sorted(rec.snaps)] + [tgt_col]
    save_png(out / "snapshots.png", np.concatenate([np.pad(c, ((0, 0), (0, 4), (0, 0)), constant_values=255) for c in cols], 1))
    atomic_write_json(out / "loss.json", {k: result.history[k] for k in ("step", "loss", "image_loss", "time", "kind")})
    plot_curves(out, result.history, rec.chamfer_log, image_loss)


def final_metrics(result, start_points, tp, tn, front_view_only: bool, rec: Recorder, run: dict) -> dict:
    """metrics.json: the result against the target (paper protocol; the start shape's too), its
    steps, point spread, normals and silhouette openings; ``run``: the budget note, the stages,
    the kernel build seconds, the target path, backend and device."""
    rp, rn, tp_cpu, tn_cpu = (t.cpu() for t in (result.points, result.normals, tp, tn))
    final = evaluate(rp, tp_cpu, protocol="paper")
    initial = evaluate(start_points.cpu(), tp_cpu, protocol="paper")
    h = result.history
    return {
        "protocol": "paper (Chamfer x1e4, Hausdorff x1e3; target = ground truth)",
        "chamfer": final.chamfer,
        "hausdorff": final.hausdorff,
        "initial_chamfer": initial.chamfer,
        "initial_hausdorff": initial.hausdorff,
        "budget": run["budget"],
        "stages": run["stages"],
        "wall_time_s": h["wall_time"],
        "kernel_build_s": run["kernel_build_s"],
        "steps": h["steps"],
        "point_steps": sum(k in ("points", "joint") for k in h["kind"]),
        "normal_steps": sum(k in ("normals", "joint") for k in h["kind"]),
        "lr_halvings": h["lr_halvings"],
        "points": len(rp),
        "target": run["target"],
        "backend": run["backend"],
        "device": run["device"],
        "torch_threads": torch.get_num_threads(),
        # the optimisation's parts (host-side wall time; on a GPU, launches) and the same in
        # process CPU seconds (with threads=1: what they take on an idle core)
        "profile_s": h.get("profile_s", {}),
        "profile_cpu_s": h.get("profile_cpu_s", {}),
        # point spread (the repulsion term's job): on the image plane for the 2D grid experiments
        "spacing": spacing_stats(rp * torch.tensor([1.0, 1.0, 0.0]) if front_view_only else rp),
        # clean surfaces: the normals against the target's (nearest target point), unoriented
        # mean and the fraction pointing the wrong way (specks under back-face culling)
        "normal_error_deg": normal_error_to_points(rp, rn, tp_cpu, tn_cpu),
        # openings: holes in silhouettes from a fixed hemisphere of views, result vs target
        # (dss.topology; the 2D grid experiments have no 3D shape to count)
        "topology": None if front_view_only else openings(rp, tp_cpu),
        "chamfer_vs_time": rec.chamfer_log,
        "snapshot_steps": sorted(rec.snaps),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
