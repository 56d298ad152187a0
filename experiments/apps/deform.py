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
remaining cycles at ``image_size`` (:func:`experiments.deformation.stages.upsample`). The
inputs, budgets, stages and outputs are in :mod:`experiments.deformation`.
"""

from __future__ import annotations

import logging
import time

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from dss.cameras import fit_distance, focal_from_fov, ring_cameras
from dss.optimize import MultiViewOptimizer, OptimizerConfig
from dss.pointcloud import normalize_unit_diagonal
from dss.render import render, resolve_backend
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
from experiments.deformation import outputs
from experiments.deformation.budget import apply_budget, command_line_keys
from experiments.deformation.inputs import FrontViewSampler, load_target, start_shape
from experiments.deformation.stages import merge_histories, stage_configs, upsample

log = logging.getLogger(__name__)

#: what a run writes into its run directory (experiments.common.claim_run_dir)
ARTEFACTS = ("final.ply", "snapshots/*.png", "snapshots.png", "loss_curve.png", "loss.json", "chamfer_vs_time.png",
             "points_xy.png", "metrics.json", "config.yaml")


def _inputs(cfg: DictConfig, gen: torch.Generator):
    """(target cloud, its points and normals in the optimiser's frame, start points, normals)."""
    target = load_target(cfg.target.path, cfg.target.points, cfg.seed)
    tp = target.points
    if cfg.normalize:
        tp, _, _ = normalize_unit_diagonal(tp)
    sp, sn = start_shape(cfg, gen)
    return target, tp, target.normals, sp, sn


def _front_sampler(cfg: DictConfig, radius: float, fov_deg: float, px: int):
    """The 2D grid experiments' fixed camera at ``px`` pixels, None for the others."""
    if not cfg.front_view_only:
        return None
    return FrontViewSampler(fit_distance(radius, fov_deg), focal_from_fov(fov_deg, px), px)


def _recorder(cfg: DictConfig, fov_deg: float, radius: float, settings, backend, tp, dev) -> outputs.Recorder:
    """The snapshots' cameras (the front camera, or a ring) and the run's recorder."""
    size = int(cfg.image_size)
    cams = _front_sampler(cfg, radius, fov_deg, size).sample() if cfg.front_view_only else ring_cameras(
        int(cfg.snapshot_views), (0, 0, 0), fit_distance(radius, fov_deg), 25.0, focal_from_fov(fov_deg, size),
        (size, size))
    return outputs.Recorder(cfg.snapshot_steps, cfg.chamfer_every, cams.to(dev), settings, cfg.shading, backend, tp)


def _stages(cfg: DictConfig, opt_cfg: OptimizerConfig, sp, sn, gen: torch.Generator, dev):
    """([(stage name, optimiser settings, image size)], first stage's start points, normals):
    one stage, or with ``coarse.cycles`` a coarse stage on ``coarse.points`` start points and a
    fine one on all of them."""
    coarse = cfg.get("coarse") or {}
    coarse_cycles = int(coarse.get("cycles", 0) or 0)
    if coarse_cycles <= 0:
        return [("full", opt_cfg, int(cfg.image_size))], sp, sn
    n_coarse = int(coarse.points)
    if not 0 < n_coarse <= len(sp):
        raise ValueError(f"coarse.points must be between 1 and start.points ({len(sp)}), got {n_coarse}")
    cc, fc = stage_configs(opt_cfg, coarse_cycles, sp)
    stages = [("coarse", cc, int(coarse.image_size)), ("fine", fc, int(cfg.image_size))]
    csp, csn = (t.to(dev) for t in start_shape(OmegaConf.merge(cfg, {"start": {"points": n_coarse}}), gen))
    opt_cfg.check_points(len(sp), "start.points")
    return stages, csp, csn


def _progress(cfg: DictConfig, stages):
    """(bar or None, the optimiser's progress callback)."""
    bar = None
    if cfg.progress:
        from tqdm import tqdm

        total = sum((c.cycles + c.error_aware_cycles) * (c.normal_steps + c.point_steps) for _, c, _ in stages)
        bar = tqdm(total=total, desc="dss-deform", unit="step")

    def progress(step, loss):
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{loss:.4f}")

    return bar, progress


def _optimise(cfg: DictConfig, stages, points, normals, n_full: int, reference, settings, backend, radius: float,
              rec: outputs.Recorder, gen: torch.Generator):
    """Run the stages one after the other (the fine stage starts from the coarse result,
    upsampled to ``n_full`` points); (result with one history of all stages, stage notes)."""
    bar, progress = _progress(cfg, stages)
    history, offset, notes = None, 0, []
    for i, (name, stage_cfg, px) in enumerate(stages):
        if name == "fine":
            points, normals = upsample(points, normals, n_full, gen)
        opt = MultiViewOptimizer(points, normals, reference, stage_cfg, settings, center=(0.0, 0.0, 0.0), radius=radius,
                                 shading=cfg.shading, backend=backend,
                                 sampler=_front_sampler(cfg, radius, stage_cfg.fov_deg, px), image_size=px,
                                 callback=lambda step, st, o=offset: rec(step + o, st["points"], st["normals"]))
        if i == 0:
            rec(0, points, normals)
        c0 = time.process_time()
        result = opt.run(progress=progress, final_projection=i == len(stages) - 1)
        notes.append({"stage": name, "points": len(points), "image_size": px, "cycles": stage_cfg.cycles,
                      "steps": result.history["steps"], "wall_time_s": result.history["wall_time"],
                      "cpu_time_s": time.process_time() - c0})
        points, normals = result.points, result.normals
        history = result.history if history is None else merge_histories(history, result.history)
        offset += result.history["steps"]
    result.history = history
    if bar is not None:
        bar.close()
    return result, notes


def _log_result(metrics: dict, budget: str) -> None:
    log.info("Chamfer %.3f -> %.3f (x1e4), Hausdorff %.2f -> %.2f (x1e3) in %.0f s (%.0f CPU s, budget %s)",
             metrics["initial_chamfer"], metrics["chamfer"], metrics["initial_hausdorff"], metrics["hausdorff"],
             metrics["wall_time_s"], metrics["cpu_time_s"], budget)
    topo = metrics["topology"]
    log.info("normal error %.1f deg (%.1f%% flipped), nn spacing CV %.2f%s", metrics["normal_error_deg"]["mean"],
             100 * metrics["normal_error_deg"]["flipped_fraction"], metrics["spacing"]["nn_cv"],
             "" if topo is None else f", openings {topo['openings']} (target {topo['openings_target']}; "
             f"{topo['holes_total']} holes in {topo['views']} views against {topo['holes_total_target']}; "
             f"{topo['views_missing_holes']} views miss a hole, {topo['views_extra_holes']} show an extra one)")


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
    settings = renderer_settings(cfg.renderer)
    # before any clock: a first-use compile is no part of the run's time
    kernel_build = prepare_kernels(dev) if cfg.backend in ("auto", "cpp", "cuda") else 0.0
    backend = resolve_backend(cfg.backend, dev)
    target, tp, tn, sp, sn = _inputs(cfg, gen)
    save_config(cfg, out)  # the inputs are read: the run starts its work (a refused run writes nothing)
    tp, tn, sp, sn = (t.to(dev) for t in (tp, tn, sp, sn))
    radius = float(tp.norm(dim=1).max())

    def reference(cams):
        return render(tp, tn, cams, settings, shading=cfg.shading, backend=backend).images

    rec = _recorder(cfg, opt_cfg.fov_deg, radius, settings, backend, tp, dev)
    stages, first_p, first_n = _stages(cfg, opt_cfg, sp, sn, gen, dev)
    result, stage_notes = _optimise(cfg, stages, first_p, first_n, len(sp), reference, settings, backend, radius,
                                    rec, gen)
    rec.finish(result)
    outputs.write_outputs(out, result, target, not cfg.normalize, rec, tp, tn, str(opt_cfg.image_loss))
    metrics = outputs.final_metrics(result, sp, tp, tn, cfg.front_view_only, rec, {
        "budget": budget_note, "stages": stage_notes, "kernel_build_s": kernel_build, "target": str(cfg.target.path),
        "backend": backend, "device": describe_device(dev)})
    # the whole process's CPU seconds (start-up, imports, kernel loading, target, the run, its
    # outputs and metrics): on one thread what the run takes on an idle core
    metrics["cpu_time_s"] = time.process_time()
    save_metrics(metrics, out)
    if cfg.front_view_only:
        outputs.plot_points_2d(out, result.points.cpu(), metrics["spacing"])
    _log_result(metrics, budget_note["preset"])
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
