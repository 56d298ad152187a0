"""``dss-deform``: shape-from-rendering, a start shape deformed to match a target's renders.

Writes into the run directory: ``config.yaml``, ``final.ply``, ``snapshots/step_XXXX.png`` and
``snapshots.png`` (renders at the chosen steps, a column each, like the paper's teaser),
``loss_curve.png`` + ``loss.json``, ``chamfer_vs_time.png`` (Chamfer to the target against wall
time) and ``metrics.json`` (Chamfer and Hausdorff to the target under the paper protocol, wall
time, steps, learning-rate halvings, point spacing, normal error against the target's normals,
and ``topology``: silhouette holes of the result and the target from a fixed set of views,
:mod:`dss.topology`); the 2D grid experiments
(``front_view_only``) also ``points_xy.png``, the final points on the image plane.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from dss.cameras import fibonacci_sphere, fit_distance, focal_from_fov, look_at, ring_cameras
from dss.io_utils import atomic_savefig, atomic_write_json
from dss.metrics import evaluate, normal_error_to_points, spacing_stats
from dss.optimize import MultiViewOptimizer, OptimizerConfig
from dss.pointcloud import (
    PointCloud,
    PointCloudError,
    centred_cloud,
    load_ply,
    normalize_unit_diagonal,
    save_ply,
)
from dss.render import render, resolve_backend
from dss.topology import openings
from dss.viz import image_grid, save_png, to_uint8
from experiments.common import (
    claim_run_dir,
    guarded,
    prepare_kernels,
    release_claims,
    renderer_settings,
    run_dir,
    save_config,
    save_metrics,
)

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ inputs
def load_target(path: str, n_mesh_samples: int, seed: int = 0) -> PointCloud:
    """A target cloud with normals: a point cloud file as is, or samples of a mesh."""
    import open3d as o3d

    p = Path(path)
    if not p.exists():
        raise PointCloudError(f"{p}: no such file (target.path)")
    mesh = o3d.io.read_triangle_mesh(str(p)) if p.suffix.lower() in (".ply", ".obj", ".off", ".stl") else None
    if mesh is not None and len(mesh.triangles) > 0:
        mesh.compute_triangle_normals()
        o3d.utility.random.seed(int(seed))
        pcd = mesh.sample_points_poisson_disk(int(n_mesh_samples), use_triangle_normal=True)
        # float64 samples: a mesh far from the origin is centred before they become float32
        return centred_cloud(np.asarray(pcd.points, np.float64), np.asarray(pcd.normals, np.float32), source=str(p))
    return load_ply(p)


def start_shape(cfg: DictConfig, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Start points/normals centred at the origin (target units: bbox diagonal 1)."""
    n = int(cfg.start.points)
    if n <= 0:
        raise ValueError(f"start.points must be positive, got {n}")
    s = float(cfg.start.scale)
    kind = cfg.start.shape
    if kind == "sphere":
        d = fibonacci_sphere(n)
        return d * (s / 2), d.clone()
    if kind == "cube":
        per_face = max(1, n // 6)
        m = int(math.ceil(math.sqrt(per_face)))
        g = (torch.arange(m, dtype=torch.float32) + 0.5) / m - 0.5
        u, v = torch.meshgrid(g, g, indexing="ij")
        u, v = u.flatten()[:per_face], v.flatten()[:per_face]
        pts, nrm = [], []
        for axis in range(3):
            for sign in (-1.0, 1.0):
                q = torch.zeros(len(u), 3)
                q[:, axis] = 0.5 * sign
                q[:, (axis + 1) % 3] = u
                q[:, (axis + 2) % 3] = v
                nn = torch.zeros(len(u), 3)
                nn[:, axis] = sign
                pts.append(q)
                nrm.append(nn)
        return torch.cat(pts) * s, torch.cat(nrm)
    if kind == "grid":
        m = int(round(math.sqrt(n)))
        g = (torch.arange(m, dtype=torch.float32) + 0.5) / m - 0.5
        u, v = torch.meshgrid(g, g, indexing="ij")
        pts = torch.stack([u.flatten(), v.flatten(), torch.zeros(m * m)], -1) * s
        return pts, torch.tensor([0.0, 0.0, 1.0]).expand(m * m, 3).clone()
    if kind == "ply":
        if not cfg.start.path:
            raise ValueError("start.shape=ply needs start.path")
        c = load_ply(cfg.start.path)
        p, _, _ = normalize_unit_diagonal(c.points)
        return p * s, c.normals
    raise ValueError(f"unknown start.shape {kind!r}: sphere | cube | grid | ply")


class FrontViewSampler:
    """One fixed camera on the +z axis (for the 2D-grid experiments)."""

    def __init__(self, distance: float, focal: float, size: int):
        self.cams = look_at(torch.tensor([[0.0, 0.0, distance]]), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), focal, (size, size))

    def sample(self):
        return self.cams


# ------------------------------------------------------------------------------ outputs
def _snapshot(points, normals, cams, settings, shading, backend) -> np.ndarray:
    with torch.no_grad():
        imgs = render(points, normals, cams, settings, shading=shading, backend=backend).images
    return image_grid([to_uint8(i) for i in imgs], ncols=1)


def _plot_curves(out: Path, history: dict, chamfer_log: list[dict], image_loss: str = "l1"):
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


def _plot_points_2d(out: Path, points: torch.Tensor, spacing: dict):
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


# ------------------------------------------------------------------------------ run
#: what a run writes into its run directory (experiments.common.claim_run_dir)
ARTEFACTS = ("final.ply", "snapshots/*.png", "snapshots.png", "loss_curve.png", "loss.json", "chamfer_vs_time.png",
             "points_xy.png", "metrics.json", "config.yaml")


def run(cfg: DictConfig) -> dict:
    out = run_dir(cfg)
    claim_run_dir(out, ARTEFACTS, bool(cfg.get("overwrite", False)))
    torch.manual_seed(int(cfg.seed))
    gen = torch.Generator().manual_seed(int(cfg.seed))
    opt_cfg = OptimizerConfig(**OmegaConf.to_container(cfg.optimizer, resolve=True))
    settings = renderer_settings(cfg.renderer)
    # before any clock: a first-use compile is no part of the run's time
    kernel_build = prepare_kernels() if cfg.backend in ("auto", "cpp") else 0.0
    backend = resolve_backend(cfg.backend)

    target = load_target(cfg.target.path, cfg.target.points, cfg.seed)
    tp = target.points
    if cfg.normalize:
        tp, _, _ = normalize_unit_diagonal(tp)
    tn = target.normals
    sp, sn = start_shape(cfg, gen)
    save_config(cfg, out)  # the inputs are read: the run starts its work (a refused run writes nothing)
    size = int(cfg.image_size)
    radius = float(tp.norm(dim=1).max())
    sampler = None
    if cfg.front_view_only:
        sampler = FrontViewSampler(fit_distance(radius, opt_cfg.fov_deg), focal_from_fov(opt_cfg.fov_deg, size), size)

    def reference(cams):
        return render(tp, tn, cams, settings, shading=cfg.shading, backend=backend).images

    snap_cams = sampler.sample() if sampler else ring_cameras(int(cfg.snapshot_views), (0, 0, 0), fit_distance(radius, opt_cfg.fov_deg),
                                                              25.0, focal_from_fov(opt_cfg.fov_deg, size), (size, size))
    snap_steps = set(int(s) for s in cfg.snapshot_steps)
    snaps: dict[int, np.ndarray] = {}
    chamfer_log: list[dict] = []
    t_start = time.perf_counter()
    eval_time = 0.0

    def record(step, points, normals):
        nonlocal eval_time
        t0 = time.perf_counter()
        if step in snap_steps:
            snaps[step] = _snapshot(points, normals, snap_cams, settings, cfg.shading, backend)
        if cfg.chamfer_every and (step % int(cfg.chamfer_every) == 0):
            m = evaluate(points, tp, protocol="paper")
            chamfer_log.append({"step": step, "time_s": t0 - t_start - eval_time, "chamfer": m.chamfer, "hausdorff": m.hausdorff})
        eval_time += time.perf_counter() - t0

    opt = MultiViewOptimizer(sp, sn, reference, opt_cfg, settings, center=(0.0, 0.0, 0.0), radius=radius,
                             shading=cfg.shading, backend=backend, sampler=sampler, image_size=size,
                             callback=lambda step, st: record(step, st["points"], st["normals"]))
    record(0, sp, sn)
    bar = None
    if cfg.progress:
        from tqdm import tqdm

        bar = tqdm(total=opt.total_steps, desc="dss-deform", unit="step")

    def progress(step, loss):
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{loss:.4f}")

    result = opt.run(progress=progress)
    if bar is not None:
        bar.close()
    final_step = result.history["steps"]
    if final_step not in snaps:
        snap_steps.add(final_step)
        record(final_step, result.points, result.normals) if not any(c["step"] == final_step for c in chamfer_log) else None
    # the last column is the output: after the final projection and normal re-fit, if configured
    snaps[final_step] = _snapshot(result.points, result.normals, snap_cams, settings, cfg.shading, backend)

    # normalize=false: in the target's own frame (a target centred on load gets its offset back)
    own = not cfg.normalize
    save_ply(out / "final.ply", PointCloud(result.points, result.normals, offset=target.offset if own else None,
                                           stored_as=target.stored_as if own else "float"))
    (out / "snapshots").mkdir(exist_ok=True)
    for step, img in sorted(snaps.items()):
        save_png(out / "snapshots" / f"step_{step:04d}.png", img)
    tgt_col = _snapshot(tp, tn, snap_cams, settings, cfg.shading, backend)
    cols = [snaps[s] for s in sorted(snaps)] + [tgt_col]
    save_png(out / "snapshots.png", np.concatenate([np.pad(c, ((0, 0), (0, 4), (0, 0)), constant_values=255) for c in cols], 1))
    atomic_write_json(out / "loss.json", {k: result.history[k] for k in ("step", "loss", "image_loss", "time", "kind")})
    _plot_curves(out, result.history, chamfer_log, str(opt_cfg.image_loss))

    final = evaluate(result.points, tp, protocol="paper")
    initial = evaluate(sp, tp, protocol="paper")
    metrics = {
        "protocol": "paper (Chamfer x1e4, Hausdorff x1e3; target = ground truth)",
        "chamfer": final.chamfer,
        "hausdorff": final.hausdorff,
        "initial_chamfer": initial.chamfer,
        "initial_hausdorff": initial.hausdorff,
        "wall_time_s": result.history["wall_time"],
        "kernel_build_s": kernel_build,
        "steps": final_step,
        "point_steps": sum(k in ("points", "joint") for k in result.history["kind"]),
        "normal_steps": sum(k in ("normals", "joint") for k in result.history["kind"]),
        "lr_halvings": result.history["lr_halvings"],
        "points": len(sp),
        "target": str(cfg.target.path),
        "backend": backend,
        # point spread (the repulsion term's job): on the image plane for the 2D grid experiments
        "spacing": spacing_stats(result.points * torch.tensor([1.0, 1.0, 0.0]) if cfg.front_view_only else result.points),
        # clean surfaces: the normals against the target's (nearest target point), unoriented
        # mean and the fraction pointing the wrong way (specks under back-face culling)
        "normal_error_deg": normal_error_to_points(result.points, result.normals, tp, tn),
        # openings: holes in silhouettes from a fixed hemisphere of views, result vs target
        # (dss.topology; the 2D grid experiments have no 3D shape to count)
        "topology": None if cfg.front_view_only else openings(result.points, tp),
        "chamfer_vs_time": chamfer_log,
        "snapshot_steps": sorted(snaps),
    }
    save_metrics(metrics, out)
    if cfg.front_view_only:
        _plot_points_2d(out, result.points, metrics["spacing"])
    log.info("Chamfer %.3f -> %.3f (x1e4), Hausdorff %.2f -> %.2f (x1e3) in %.0f s", initial.chamfer, final.chamfer,
             initial.hausdorff, final.hausdorff, result.history["wall_time"])
    topo = metrics["topology"]
    log.info("normal error %.1f deg (%.1f%% flipped), nn spacing CV %.2f%s", metrics["normal_error_deg"]["mean"],
             100 * metrics["normal_error_deg"]["flipped_fraction"], metrics["spacing"]["nn_cv"],
             "" if topo is None else f", openings {topo['openings']} (target {topo['openings_target']}; "
             f"{topo['holes_total']} holes in {topo['views']} views against {topo['holes_total_target']}; "
             f"{topo['views_missing_holes']} views miss a hole, {topo['views_extra_holes']} show an extra one)")
    release_claims()
    return metrics


@hydra.main(version_base="1.3", config_path="../../conf", config_name="deform")
@guarded
def _main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Console entry point: an expected failure prints one line and exits 2 (experiments.common.run_app)."""
    from experiments.common import run_app

    run_app(_main)


if __name__ == "__main__":
    main()
