"""The denoise job's stages, in the order ``dss-denoise`` runs them (``experiments/apps/denoise.py``):

1. :func:`check`: every setting that can be refused, before any work;
2. :func:`prepare`: the input (normals, NaN rows), a model file it names, the outliers, the
   noise level;
3. :func:`reference`: the reference generator (:mod:`experiments.denoising.references`);
4. :func:`experiments.denoising.settings.resolve`: the settings for this cloud;
5. :func:`ground_truth`, :func:`refine`: DSS's cycles, the outlier projection and the plane
   fusion (:mod:`experiments.denoising.refine`);
6. :func:`write`, :func:`score`, :func:`floor`, :func:`draw`, :func:`record`: the outputs and
   ``metrics.json``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from dss.pipeline import NOISE_METHODS
from dss.schedule import interpolate_by_noise
from experiments.denoising import inputs, references
from experiments.denoising.figures import check_figures, write_figures
from experiments.denoising.refine import Refined, output_normals
from experiments.denoising.refine import refine as refine_cloud
from experiments.denoising.scoring import chamfer_floor, log_summary, normal_errors, short_metrics
from experiments.denoising.scoring import score as score_points

log = logging.getLogger(__name__)

__all__ = ["Prepared", "GroundTruth", "Scores", "check", "prepare", "reference", "ground_truth", "refine", "write",
           "score", "floor", "draw", "record", "log_start", "log_end"]


@dataclass
class Prepared:
    """What the *prepare* stage gives (:func:`prepare`).

    Attributes:
        files: the job's files.
        cloud_in, input_report: the input as given (scored and drawn as such) and its report.
        cloud: the input without its outliers: what DSS refines.
        outliers, removed: the outlier report (``metrics.json`` ``outliers``) and the removed points.
        noise: the noise level in use.
        given: (generator, note) of a reference that names its model file (made and checked
            before the outlier removal); None for the others.
        kernel_build: seconds of first-use kernel compiling (left out of the run's times).
    """

    files: inputs.InputFiles
    cloud_in: Any
    input_report: dict
    cloud: Any
    outliers: dict
    removed: Any
    noise: inputs.NoiseLevel
    given: tuple | None
    kernel_build: float


@dataclass(frozen=True)
class GroundTruth:
    """The clean cloud ((M, 3) float64 or None) and mesh ((V, F) or None) in the input's frame."""

    clean: np.ndarray | None
    mesh: Any
    note: str


@dataclass
class Scores:
    """Metrics of the input and the output (``{protocol: metrics}``; empty without ground
    truth), the normals' angle to the mesh, the Chamfer floor (None unless asked)."""

    input: dict
    output: dict
    normal_error: dict | None
    floor: dict | None = None


def check(cfg: DictConfig) -> tuple[torch.device, float | None]:
    """(device, noise hint): the settings refused before any work (W&B, device, the noise hint,
    the figures)."""
    from experiments.common import resolve_device
    from experiments.wandb_log import check as check_wandb

    check_wandb(cfg.get("wandb"))
    dev = resolve_device(cfg.get("device"))
    hint = inputs.noise_hint(cfg.get("noise"))
    if str(cfg.get("noise_estimator", "quadric")) not in NOISE_METHODS:
        raise ValueError(f"noise_estimator must be one of {list(NOISE_METHODS)}, got {cfg.noise_estimator!r}")
    check_figures(cfg.get("figures"))
    return dev, hint


def load(cfg: DictConfig, files: inputs.InputFiles):
    """(cloud with normals, report): :func:`experiments.denoising.inputs.load_input` with the
    config's NaN policy and normals settings."""
    return inputs.load_input(files.input, cfg.get("nan_policy", "drop"), int(cfg.normals.k),
                             bool(cfg.normals.recompute))


def drop_outliers(cfg: DictConfig, cloud, report: dict):
    """(inliers, outlier report, removed points or None): ``cfg.outliers``; normals that were
    estimated are estimated again without the outliers."""
    k = None if report["normals"] == "from file" else int(cfg.normals.k)
    return inputs.remove_outliers(cloud, cfg.get("outliers", {}), k)


def prepare(cfg: DictConfig, files: inputs.InputFiles, hint: float | None, device, clock) -> Prepared:
    """Load the input, check a model file it names, build the kernels, remove the outliers and
    settle the noise level (each timed on ``clock``)."""
    from experiments.common import prepare_kernels

    with clock("load"):
        cloud_in, report = load(cfg, files)
    with clock("reference_setup"):
        given = references.given_reference(cfg)
    kernel_build = prepare_kernels(device)
    with clock("outliers"):
        cloud, outliers, removed = drop_outliers(cfg, cloud_in, report)
    with clock("noise_estimate"):
        noise = inputs.noise_level(cloud.points, hint, files.input, str(cfg.get("noise_estimator", "quadric")))
    return Prepared(files, cloud_in, report, cloud, outliers, removed, noise, given, kernel_build)


def reference(cfg: DictConfig, data: Prepared, clock) -> tuple[Any, str | None]:
    """(generator, model selection note): the one :func:`prepare` made, or one for the noise
    level; a warning when a model was trained for a noise level far from it."""
    with clock("reference_setup"):
        generator, note = data.given or references.make_reference(cfg, data.noise.used)
    references.warn_noise_mismatch(generator, data.noise.used, data.noise.hint is not None)
    return generator, note


def ground_truth(cfg: DictConfig, data: Prepared, generator) -> GroundTruth:
    """The ground truth in the input's frame (a mesh alone is sampled with the input's point
    count); the oracle reference refuses to run without one."""
    files = data.files
    clean, mesh, note = inputs.load_ground_truth(files.clean, files.mesh, len(data.cloud_in), int(cfg.seed),
                                                 data.cloud.offset)
    if generator.name == "oracle" and clean is None:
        raise ValueError("reference=oracle renders the ground truth: give clean= or mesh=")
    return GroundTruth(clean, mesh, note)


def log_start(data: Prepared, generator, settings) -> None:
    log.info("denoising %s (%d points, noise %s %.4g) with %s at %s px", data.files.input, len(data.cloud),
             "hint" if data.noise.hint is not None else "estimated", data.noise.used, generator.describe(),
             list(settings.spec.image_size))


def refine(cfg: DictConfig, settings, cloud, generator, truth: GroundTruth, device) -> Refined:
    """DSS on the inliers ``cloud`` with the resolved ``settings``
    (:func:`experiments.denoising.refine.refine`)."""
    return refine_cloud(cloud.points, cloud.normals, generator, settings.spec, settings.optimizer,
                        shading=settings.shading, fusion=settings.fusion, noise=settings.noise, device=device,
                        progress=bool(cfg.get("progress", True)), desc=f"dss-denoise ({generator.name})",
                        clean=truth.clean, mesh=truth.mesh)


def readmit(cfg: DictConfig, refined: Refined, data: Prepared) -> Refined:
    """The removed outliers that lie within ``outliers.readmit`` noise levels (``readmit_by_noise``
    when given: the levels by noise level, interpolated in log noise) of the denoised
    surface (:func:`dss.regularizers.readmit_near_surface`) join the result, projected onto it
    (normals from the local plane, signed like the nearest result point's); ``data.removed`` and
    the outlier report (``readmitted``) follow. At low noise the spacing test also takes the
    sparse last samples of thin tips, whose loss the output's Hausdorff distance shows."""
    node = cfg.get("outliers") or {}
    table = node.get("readmit_by_noise")
    levels = (interpolate_by_noise({float(k): float(v) for k, v in table.items()}, data.noise.used) if table
              else float(node.get("readmit", 0) or 0))
    if data.removed is None or levels <= 0:
        return refined
    from dss.pointcloud import bbox_diagonal
    from dss.regularizers import readmit_near_surface

    pts, nrm = refined.points, refined.normals
    ok, proj, pn = readmit_near_surface(data.removed.points.to(pts), pts, levels * data.noise.used * float(bbox_diagonal(pts)))
    n_ok = int(ok.sum())
    data.outliers["readmitted"] = n_ok
    if n_ok == 0:
        return refined
    from dss.knn import knn

    near = knn(pts, 1, query=proj).idx[:, 0].long()
    pn = torch.where((pn * nrm[near]).sum(1, keepdim=True) < 0, -pn, pn)
    data.removed = data.removed.select(~ok) if n_ok < len(ok) else None
    log.info("readmitted %d of %d removed points: they lie on the denoised surface", n_ok, len(ok))
    return Refined(torch.cat([pts, proj.to(pts.dtype)]), torch.cat([nrm, pn.to(nrm.dtype)]), refined.history,
                   refined.ref, refined.norm, refined.optimizer)


def write(cfg: DictConfig, refined: Refined, mode: str, data: Prepared, output: Path,
          out: Path) -> tuple[torch.Tensor, Path]:
    """(written normals, output path): the denoised cloud with its ``mode`` normals
    (:func:`experiments.denoising.refine.output_normals`) in the input's frame and precision (a
    cloud centred on load gets its offset back, doubles stay doubles), and the removed outliers
    in ``out/outliers.ply`` (``data.outliers["file"]``)."""
    from dss.pointcloud import PointCloud, save_ply

    cloud = data.cloud
    nrm = output_normals(refined.points, refined.normals, mode, int(cfg.normals.k))
    # never replaces a file that appeared meanwhile (overwrite=false): the result then goes beside it
    output = save_ply(output, PointCloud(refined.points, nrm, offset=cloud.offset, stored_as=cloud.stored_as),
                      exclusive=not cfg.get("overwrite", False))
    if data.removed is not None:
        data.outliers["file"] = str(save_ply(out / "outliers.ply", data.removed))
    return nrm, output


def score(cfg: DictConfig, cloud_in, refined: Refined, written: torch.Tensor, truth: GroundTruth) -> Scores:
    """The input (as given) and the output against the ground truth, and the normals' errors."""
    protocols = list(cfg.metrics.protocols)
    pts = refined.points
    return Scores(score_points(cloud_in.points.numpy(), truth.clean, truth.mesh, protocols),
                  score_points(pts.numpy(), truth.clean, truth.mesh, protocols),
                  normal_errors(cloud_in, pts, refined.normals, written, truth.mesh, int(cfg.normals.k)))


def floor(cfg: DictConfig, truth: GroundTruth, n: int, clock) -> dict | None:
    """The Chamfer floor with ``n`` points when asked (``metrics.floor``) and a mesh is given."""
    if truth.mesh is None or not cfg.metrics.get("floor", True):
        return None
    with clock("chamfer_floor"):
        return chamfer_floor(truth.mesh, n, int(cfg.seed), list(cfg.metrics.protocols))


def draw(cfg: DictConfig, out: Path, settings, data: Prepared, refined: Refined, written: torch.Tensor,
         truth: GroundTruth, generator, clock) -> list[str]:
    """The figures (:func:`experiments.denoising.figures.write_figures`): noisy input, denoised
    and, with ground truth, the clean cloud (PCA normals); [] with ``figures.enabled=false``."""
    if not (cfg.get("figures") or {}).get("enabled", True):
        return []
    with clock("figures"):
        rows = [(data.cloud_in.points, data.cloud_in.normals), (refined.points, written)]
        labels = ["noisy input", f"denoised ({generator.name})"]
        if truth.clean is not None:
            from dss.pointcloud import estimate_normals

            cp = torch.from_numpy(np.asarray(truth.clean, np.float32))
            rows.append((cp, estimate_normals(cp, k=int(cfg.normals.k))))
            labels.append("clean (ground truth)")
        title = f"dss-denoise {Path(data.files.input).name}, reference {generator.name}"
        return write_figures(out, cfg.get("figures"), int(cfg.seed), settings.spec, rows, labels, refined, title,
                             shading=settings.shading)


def record(data: Prepared, output: Path, truth: GroundTruth, settings, generator, model_note: str | None,
           refined: Refined, mode: str, scores: Scores, figures: list[str], clock, start: tuple[float, float]) -> dict:
    """``metrics.json``: the input, what was chosen and why, the render setting, the fusion, the
    optimiser's report and times per stage, the metrics (see docs/denoising.md). ``start``: the
    run's (wall, process CPU) clocks at its start."""
    from experiments.common import optimization_report

    history, files = refined.history, data.files
    metrics = {
        "input": data.input_report,
        "example": files.is_example,
        "output": str(output),
        "ground_truth": {"clean": files.clean, "mesh": files.mesh, "note": truth.note},
        "outliers": data.outliers,
        "noise": data.noise.to_dict(),
        **settings.notes,  # cycles, projection_weight, reg_cutoff, reg_dilation: the value used and why
        "budget": settings.budget,
        "reference": {**generator.describe(), "selection": model_note},
        "render": {"source": settings.spec_source, "image_size": list(settings.spec.image_size),
                   "shading": settings.shading_name, "spec": settings.spec.to_dict()},
        "fusion": history.get("fusion"),
        "normals_output": mode,
        **optimization_report(history, start[0], clock.seconds["optimization"], data.kernel_build),
        # seconds per stage of the job; "optimization" split into the loop's parts and the
        # stages after it (host-side wall time)
        "profile_s": {**clock.seconds, "optimization_parts": history.get("profile_s", {})},
        # the same in process CPU seconds: with threads=1 what the stages take on an idle machine
        "profile_cpu_s": {**clock.cpu_seconds, "optimization_parts": history.get("profile_cpu_s", {})},
        "metrics_input": scores.input,
        "metrics_output": scores.output,
        "chamfer_floor": scores.floor,
        "normal_error_deg": scores.normal_error,
        "summary": {"input": short_metrics(scores.input), "output": short_metrics(scores.output)},
        "figures": figures,
    }
    metrics["time_s"]["cpu_total"] = time.process_time() - start[1]  # kernel build included
    return metrics


def log_end(metrics: dict, clock, history: dict) -> None:
    log.info("time per stage: %s", clock.summary(metrics["time_s"]["total"]))
    log.info("optimisation: %s", ", ".join(f"{k} {v:.2f} s" for k, v in history.get("profile_s", {}).items()))
    log_summary(metrics)
