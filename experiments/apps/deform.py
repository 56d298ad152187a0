"""``dss-deform``: shape-from-rendering, a start shape deformed to match a target's renders.

Writes into the run directory: ``config.yaml``, ``final.ply``, ``snapshots/step_XXXX.png`` and
``snapshots.png`` (renders at the chosen steps, a column each, like the paper's teaser),
``loss_curve.png`` + ``loss.json``, ``chamfer_vs_time.png`` (Chamfer to the target against wall
time) and ``metrics.json`` (Chamfer and Hausdorff to the target under the paper protocol, wall
time, steps, learning-rate halvings, point spacing, normal error against the target's normals,
and ``topology``: silhouette holes of the result and the target from a fixed set of views,
:mod:`dss.topology`); the 2D grid experiments
(``front_view_only``) also ``points_xy.png``, the final points on the image plane.

``budget=fast|default|best`` picks a preset of ``budgets`` in ``conf/deform.yaml`` (settings the
preset changes, unless the command line gives them; recorded in ``metrics.json`` under
``budget``). ``coarse.cycles`` > 0 runs the first cycles coarse-to-fine: ``coarse.points`` start
points rendered at ``coarse.image_size``, then the cloud upsampled to ``start.points`` for the
remaining cycles at ``image_size`` (:func:`upsample`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
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
    read_ply_header,
    save_ply,
)
from dss.regularizers import bandwidth_for
from dss.render import render, resolve_backend
from dss.topology import openings
from dss.viz import image_grid, save_png, to_uint8
from experiments.common import (
    claim_run_dir,
    describe_device,
    guarded,
    prepare_kernels,
    release_claims,
    renderer_settings,
    resolve_device,
    run_dir,
    save_config,
    save_metrics,
)

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ inputs
def load_target(path: str, n_mesh_samples: int, seed: int = 0) -> PointCloud:
    """A target cloud with normals: a point cloud file as is, or samples of a mesh."""
    p = Path(path)
    if not p.exists():
        raise PointCloudError(f"{p}: no such file (target.path)")
    suffix = p.suffix.lower()
    if suffix == ".ply":
        # a PLY without faces is a point cloud: read without open3d (not installed everywhere,
        # e.g. on the GPU machines of experiments/benchmarks/gpu_check.sh)
        face = read_ply_header(p).element("face")
        if face is None or face.count == 0:
            return load_ply(p)
    if suffix not in (".ply", ".obj", ".off", ".stl"):
        return load_ply(p)
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(p))
    if len(mesh.triangles) > 0:
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


# ------------------------------------------------------------------------------ budgets
def _leaves(node, prefix: str = "") -> dict:
    """``{"optimizer.cycles": 10, ...}``: the dotted keys of a nested preset's values."""
    out = {}
    for k, v in node.items():
        key = f"{prefix}{k}"
        if isinstance(v, (dict, DictConfig)):
            out.update(_leaves(v, key + "."))
        else:
            out[key] = OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v
    return out


def command_line_keys() -> set[str]:
    """The keys the command line set (Hydra's task overrides; empty outside a Hydra run)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return set()
    keys = set()
    for o in HydraConfig.get().overrides.task:
        key = o.split("=", 1)[0].lstrip("+~")
        keys.add(key)
    return keys


def apply_budget(cfg: DictConfig, given: set[str] | None = None) -> dict:
    """Apply the ``budget`` preset of ``cfg.budgets`` to ``cfg``: each of its settings (nested
    like the config, e.g. ``{optimizer: {cycles: 10}}``) replaces the config's, except the keys in
    ``given`` (the command line's: what a user sets explicitly wins over the preset). Returns
    the note for metrics.json: ``preset``, ``applied`` (key -> value), ``kept`` (key -> the given
    value where the preset had another)."""
    name = str(cfg.get("budget", "default"))
    presets = cfg.get("budgets") or {}
    if name not in presets:
        raise ValueError(f"budget={name!r}: no such preset (have {', '.join(sorted(presets))}; conf/deform.yaml budgets)")
    given = set() if given is None else given
    applied, kept = {}, {}
    for key, value in _leaves(presets[name] or {}).items():
        if OmegaConf.select(cfg, key, default="__missing__") == "__missing__":
            raise ValueError(f"budgets.{name}: {key} is no setting of dss-deform")
        if key in given:
            kept[key] = OmegaConf.select(cfg, key)
            continue
        OmegaConf.update(cfg, key, value, merge=False)
        applied[key] = value
    return {"preset": name, "applied": applied, "kept": kept}


# ------------------------------------------------------------------------------ coarse-to-fine
def upsample(points: torch.Tensor, normals: torch.Tensor, n: int,
             generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` points and normals from the ``m`` of a coarse cloud ((m, 3) each, m <= n): every
    coarse point kept, and ``n - m`` more, the coarse points in turn, each placed uniformly at
    random on the disc in its tangent plane of radius half its nearest-neighbour distance (the
    share of the surface a point stands for), with its normal. The fine cycles' normal re-fit,
    projection and repulsion then settle them on the surface."""
    from scipy.spatial import cKDTree

    m = len(points)
    if n <= m:
        return points[:n].clone(), normals[:n].clone()
    p = points.detach().cpu()
    nrm = torch.nn.functional.normalize(normals.detach().cpu(), dim=1)
    d, _ = cKDTree(p.numpy()).query(p.numpy(), k=2)
    nn = torch.from_numpy(d[:, 1]).float()
    idx = torch.arange(n - m) % m
    nv = nrm[idx]
    helper = torch.where((nv[:, :1].abs() < 0.9), torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
    t1 = torch.nn.functional.normalize(torch.cross(nv, helper, dim=1), dim=1)
    t2 = torch.cross(nv, t1, dim=1)
    angle = 2 * math.pi * torch.rand(n - m, generator=generator)
    radius = 0.5 * nn[idx] * torch.rand(n - m, generator=generator).sqrt()
    new = p[idx] + radius[:, None] * (angle.cos()[:, None] * t1 + angle.sin()[:, None] * t2)
    return (torch.cat([p, new]).to(points.device), torch.cat([nrm, nv]).to(points.device))


def stage_configs(opt_cfg: OptimizerConfig, coarse_cycles: int,
                  fine_start: torch.Tensor) -> tuple[OptimizerConfig, OptimizerConfig]:
    """The coarse and the fine stage's optimiser settings: the coarse stage runs the schedule's
    first ``coarse_cycles`` cycles; the fine stage the rest, where the schedule stands after them
    (learning rates and the fill pull x lr_decay^coarse_cycles, the window x
    window_decay^coarse_cycles), with the regularisers' bandwidths of the full start cloud
    ``fine_start`` (N, 3), as a one-stage run has them, and views of their own seed."""
    c = opt_cfg
    if not 0 < coarse_cycles < c.cycles:
        raise ValueError(f"coarse.cycles must be between 1 and optimizer.cycles - 1 = {c.cycles - 1}, got {coarse_cycles}")
    coarse = dataclasses.replace(c, cycles=coarse_cycles, error_aware_cycles=0, final_normal_refresh_k=0,
                                 final_projection_k=0)
    decay = c.lr_decay ** coarse_cycles

    def bw(rule):
        return bandwidth_for(fine_start, rule) if isinstance(rule, str) else rule

    fine = dataclasses.replace(c, cycles=c.cycles - coarse_cycles, lr_points=c.lr_points * decay,
                               lr_normals=c.lr_normals * decay, fill_step=c.fill_step * decay,
                               window_start=c.window_start * c.window_decay ** coarse_cycles,
                               projection_bandwidth=bw(c.projection_bandwidth),
                               repulsion_bandwidth=bw(c.repulsion_bandwidth), seed=c.seed + 104729)
    return coarse, fine


def _merge_histories(first: dict, second: dict) -> dict:
    """One history of two stages run one after the other (steps and times continued)."""
    steps, t = first["steps"], first["wall_time"]
    h = dict(second)
    for key, shift in (("step", steps), ("time", t)):
        h[key] = list(first[key]) + [x + shift for x in second[key]]
    for key, value in first.items():  # per-step and per-cycle lists: one after the other
        if key not in ("step", "time") and isinstance(value, list) and isinstance(second.get(key), list):
            h[key] = value + second[key]
    h["lr_halvings"] = first["lr_halvings"] + second["lr_halvings"]
    h["steps"] = steps + second["steps"]
    h["wall_time"] = t + second["wall_time"]
    for key in ("profile_s", "profile_cpu_s"):
        a, b = first.get(key, {}), second.get(key, {})
        h[key] = {k: a.get(k, 0.0) + b.get(k, 0.0) for k in {**a, **b}}
    h["config"] = {"coarse": first["config"], "fine": second["config"]}
    return h


# ------------------------------------------------------------------------------ run
#: what a run writes into its run directory (experiments.common.claim_run_dir)
ARTEFACTS = ("final.ply", "snapshots/*.png", "snapshots.png", "loss_curve.png", "loss.json", "chamfer_vs_time.png",
             "points_xy.png", "metrics.json", "config.yaml")


def run(cfg: DictConfig, given: set[str] | None = None) -> dict:
    """One dss-deform run (module docstring); ``given``: the keys set on the command line, which
    the budget preset leaves alone (default: Hydra's task overrides). Returns the metrics."""
    out = run_dir(cfg)
    budget_note = apply_budget(cfg, command_line_keys() if given is None else given)
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    dev = resolve_device(cfg.get("device"))
    claim_run_dir(out, ARTEFACTS, bool(cfg.get("overwrite", False)))
    torch.manual_seed(int(cfg.seed))
    gen = torch.Generator().manual_seed(int(cfg.seed))
    opt_cfg = OptimizerConfig(**OmegaConf.to_container(cfg.optimizer, resolve=True))
    coarse = cfg.get("coarse") or {}
    coarse_cycles = int(coarse.get("cycles", 0) or 0)
    settings = renderer_settings(cfg.renderer)
    # before any clock: a first-use compile is no part of the run's time
    kernel_build = prepare_kernels(dev) if cfg.backend in ("auto", "cpp", "cuda") else 0.0
    backend = resolve_backend(cfg.backend, dev)

    target = load_target(cfg.target.path, cfg.target.points, cfg.seed)
    tp = target.points
    if cfg.normalize:
        tp, _, _ = normalize_unit_diagonal(tp)
    tn = target.normals
    sp, sn = start_shape(cfg, gen)
    save_config(cfg, out)  # the inputs are read: the run starts its work (a refused run writes nothing)
    tp, tn, sp, sn = (t.to(dev) for t in (tp, tn, sp, sn))
    size = int(cfg.image_size)
    radius = float(tp.norm(dim=1).max())

    def front_sampler(px):
        return FrontViewSampler(fit_distance(radius, opt_cfg.fov_deg), focal_from_fov(opt_cfg.fov_deg, px), px) \
            if cfg.front_view_only else None

    def reference(cams):
        return render(tp, tn, cams, settings, shading=cfg.shading, backend=backend).images

    snap_cams = front_sampler(size).sample() if cfg.front_view_only else ring_cameras(
        int(cfg.snapshot_views), (0, 0, 0), fit_distance(radius, opt_cfg.fov_deg), 25.0,
        focal_from_fov(opt_cfg.fov_deg, size), (size, size))
    snap_cams = snap_cams.to(dev)
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
            m = evaluate(points.cpu(), tp.cpu(), protocol="paper")
            chamfer_log.append({"step": step, "time_s": t0 - t_start - eval_time, "chamfer": m.chamfer, "hausdorff": m.hausdorff})
        eval_time += time.perf_counter() - t0

    # (stage name, optimiser settings, image size, start points, start normals)
    stages = [("full", opt_cfg, size)]
    if coarse_cycles > 0:
        n_coarse = int(coarse.points)
        if not 0 < n_coarse <= len(sp):
            raise ValueError(f"coarse.points must be between 1 and start.points ({len(sp)}), got {n_coarse}")
        cc, fc = stage_configs(opt_cfg, coarse_cycles, sp)
        stages = [("coarse", cc, int(coarse.image_size)), ("fine", fc, size)]
        full_start = sp
        sp, sn = (t.to(dev) for t in start_shape(OmegaConf.merge(cfg, {"start": {"points": n_coarse}}), gen))
        opt_cfg.check_points(len(full_start), "start.points")
    bar = None
    if cfg.progress:
        from tqdm import tqdm

        total = sum((c.cycles + c.error_aware_cycles) * (c.normal_steps + c.point_steps) for _, c, _ in stages)
        bar = tqdm(total=total, desc="dss-deform", unit="step")

    def progress(step, loss):
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{loss:.4f}")

    points, normals, history, offset = sp, sn, None, 0
    stage_notes = []
    for i, (name, stage_cfg, px) in enumerate(stages):
        if name == "fine":
            points, normals = upsample(points, normals, len(full_start), gen)
        opt = MultiViewOptimizer(points, normals, reference, stage_cfg, settings, center=(0.0, 0.0, 0.0), radius=radius,
                                 shading=cfg.shading, backend=backend, sampler=front_sampler(px), image_size=px,
                                 callback=lambda step, st, o=offset: record(step + o, st["points"], st["normals"]))
        if i == 0:
            record(0, points, normals)
        c0 = time.process_time()
        result = opt.run(progress=progress, final_projection=i == len(stages) - 1)
        stage_notes.append({"stage": name, "points": len(points), "image_size": px, "cycles": stage_cfg.cycles,
                            "steps": result.history["steps"], "wall_time_s": result.history["wall_time"],
                            "cpu_time_s": time.process_time() - c0})
        points, normals = result.points, result.normals
        history = result.history if history is None else _merge_histories(history, result.history)
        offset += result.history["steps"]
    result.history = history
    if bar is not None:
        bar.close()
    final_step = result.history["steps"]
    if final_step not in snaps:
        snap_steps.add(final_step)
        record(final_step, result.points, result.normals) if not any(c["step"] == final_step for c in chamfer_log) else None
    # the last column is the output: after the final projection and normal re-fit, if configured
    snaps[final_step] = _snapshot(result.points, result.normals, snap_cams, settings, cfg.shading, backend)

    rp, rn, tp_cpu, tn_cpu = (t.cpu() for t in (result.points, result.normals, tp, tn))
    # normalize=false: in the target's own frame (a target centred on load gets its offset back)
    own = not cfg.normalize
    save_ply(out / "final.ply", PointCloud(rp, rn, offset=target.offset if own else None,
                                           stored_as=target.stored_as if own else "float"))
    (out / "snapshots").mkdir(exist_ok=True)
    for step, img in sorted(snaps.items()):
        save_png(out / "snapshots" / f"step_{step:04d}.png", img)
    tgt_col = _snapshot(tp, tn, snap_cams, settings, cfg.shading, backend)
    cols = [snaps[s] for s in sorted(snaps)] + [tgt_col]
    save_png(out / "snapshots.png", np.concatenate([np.pad(c, ((0, 0), (0, 4), (0, 0)), constant_values=255) for c in cols], 1))
    atomic_write_json(out / "loss.json", {k: result.history[k] for k in ("step", "loss", "image_loss", "time", "kind")})
    _plot_curves(out, result.history, chamfer_log, str(opt_cfg.image_loss))

    final = evaluate(rp, tp_cpu, protocol="paper")
    initial = evaluate(sp.cpu() if coarse_cycles == 0 else full_start.cpu(), tp_cpu, protocol="paper")
    metrics = {
        "protocol": "paper (Chamfer x1e4, Hausdorff x1e3; target = ground truth)",
        "chamfer": final.chamfer,
        "hausdorff": final.hausdorff,
        "initial_chamfer": initial.chamfer,
        "initial_hausdorff": initial.hausdorff,
        "budget": budget_note,
        "stages": stage_notes,
        "wall_time_s": result.history["wall_time"],
        "kernel_build_s": kernel_build,
        "steps": final_step,
        "point_steps": sum(k in ("points", "joint") for k in result.history["kind"]),
        "normal_steps": sum(k in ("normals", "joint") for k in result.history["kind"]),
        "lr_halvings": result.history["lr_halvings"],
        "points": len(rp),
        "target": str(cfg.target.path),
        "backend": backend,
        "device": describe_device(dev),
        "torch_threads": torch.get_num_threads(),
        # the optimisation's parts (host-side wall time; on a GPU, launches) and the same in
        # process CPU seconds (with threads=1: what they take on an idle core)
        "profile_s": result.history.get("profile_s", {}),
        "profile_cpu_s": result.history.get("profile_cpu_s", {}),
        # point spread (the repulsion term's job): on the image plane for the 2D grid experiments
        "spacing": spacing_stats(rp * torch.tensor([1.0, 1.0, 0.0]) if cfg.front_view_only else rp),
        # clean surfaces: the normals against the target's (nearest target point), unoriented
        # mean and the fraction pointing the wrong way (specks under back-face culling)
        "normal_error_deg": normal_error_to_points(rp, rn, tp_cpu, tn_cpu),
        # openings: holes in silhouettes from a fixed hemisphere of views, result vs target
        # (dss.topology; the 2D grid experiments have no 3D shape to count)
        "topology": None if cfg.front_view_only else openings(rp, tp_cpu),
        "chamfer_vs_time": chamfer_log,
        "snapshot_steps": sorted(snaps),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
    # the whole process's CPU seconds (start-up, imports, kernel loading, target, the run, its
    # outputs and metrics): on one thread what the run takes on an idle core
    metrics["cpu_time_s"] = time.process_time()
    save_metrics(metrics, out)
    if cfg.front_view_only:
        _plot_points_2d(out, rp, metrics["spacing"])
    log.info("Chamfer %.3f -> %.3f (x1e4), Hausdorff %.2f -> %.2f (x1e3) in %.0f s (%.0f CPU s, budget %s)",
             initial.chamfer, final.chamfer, initial.hausdorff, final.hausdorff, result.history["wall_time"],
             metrics["cpu_time_s"], budget_note["preset"])
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
