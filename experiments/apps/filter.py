"""``dss-filter``: geometry editing through image filters (paper "Application: shape editing via
image filter", Fig. "DSS-based geometry filtering").

    dss-filter                                   # L0 filtering of the shipped example's clean cloud
    dss-filter cloud.ply reference=slic          # superpixels
    dss-filter cloud.ply noise=0.01              # add 1% noise first (the figure's second row)
    dss-filter cloud.ply reference.lam=0.05      # flatter L0 result
    dss-filter cloud.ply shading=point           # the denoiser's point light instead of sun lights

The renders of the input are filtered (L0 smoothing or SLIC superpixels, ``conf/reference``), the
silhouette is kept, and DSS updates normals (and, through the projection and repulsion terms,
points) until the renders match: the paper's local schedule (T_n = 19, T_p = 1, 16 cycles, 12
views). Writes into the run directory: the edited PLY, ``before_after.png`` (input | filtered),
``references.png``, ``loss.png``/``loss.json``, ``metrics.json`` (timing, how far the geometry
moved, and Chamfer/Hausdorff/P2M to a ground truth when one is given).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig

from experiments.common import (
    claim_run_dir,
    guarded,
    optimization_report,
    positional_to_override,
    prepare_kernels,
    release_claims,
    resolve_device,
    run_app,
    run_dir,
    save_config,
    save_metrics,
)
from experiments.denoising.figures import check_figures, write_figures
from experiments.denoising.inputs import (
    EXAMPLE_DIR,
    InputFiles,
    load_ground_truth,
    load_input,
    resolve_output,
)
from experiments.denoising.references import make_reference
from experiments.denoising.refine import refine
from experiments.denoising.scoring import score, short_metrics
from experiments.denoising.settings import optimizer_config
from experiments.wandb_log import check as check_wandb
from experiments.wandb_log import log_run

log = logging.getLogger(__name__)

__all__ = ["run", "main"]


#: what a run writes into its run directory (experiments.common.claim_run_dir)
ARTEFACTS = ("filtered.ply", "before_after.png", "references.png", "loss.png", "loss.json", "metrics.json",
             "config.yaml")


def _shading(name: str, spec):
    if name == "sun":
        return "sun"
    if name == "point":
        return spec.point_light()
    raise ValueError(f"shading must be 'sun' (the paper's three RGB lights) or 'point' (the denoiser's light), got {name!r}")


def _files(cfg: DictConfig) -> InputFiles:
    """The cloud to filter and its optional ground truth; with no input, the shipped example's
    clean cloud and its ground truth."""
    if cfg.get("input"):
        return InputFiles(str(cfg.input), cfg.get("clean"), cfg.get("mesh"), False)
    return InputFiles(str(EXAMPLE_DIR / "clean.ply"), cfg.get("clean") or str(EXAMPLE_DIR / "clean.ply"),
                      cfg.get("mesh") or str(EXAMPLE_DIR / "mesh.ply"), True)


def _with_noise(cfg: DictConfig, cloud, report: dict):
    """(points, normals, noise): the cloud with ``cfg.noise`` white Gaussian noise added (std,
    fraction of the bbox diagonal; 0: as given) and PCA normals of the noisy points."""
    from dss.pointcloud import add_gaussian_noise, estimate_normals

    try:
        noise = float(cfg.get("noise") or 0.0)
    except (TypeError, ValueError):
        raise ValueError(f"noise={cfg.get('noise')!r} is not a number (the std of the noise to add, as a "
                         "fraction of the bbox diagonal)") from None
    if noise < 0:
        raise ValueError(f"noise must be >= 0 (std as a fraction of the bbox diagonal), got {noise}")
    if noise == 0:
        return cloud.points, cloud.normals, noise
    points = add_gaussian_noise(cloud.points, noise, seed=int(cfg.seed))
    report["added_noise"] = noise
    report["normals"] = f"estimated after adding noise (PCA, k={int(cfg.normals.k)})"
    return points, estimate_normals(points, k=int(cfg.normals.k)), noise


def _setup(cfg: DictConfig, n: int, where: str):
    """(generator, render spec, shading, optimiser config): the image filter and its renders."""
    from data_prep.render_spec import load_render_spec

    if "model" in cfg.reference:
        raise ValueError("dss-filter takes an image filter (reference=l0|slic|identity); "
                         "use dss-denoise for the denoising network")
    generator, _ = make_reference(cfg, None)
    spec = load_render_spec(image_size=[int(cfg.image_size)] * 2) if cfg.get("image_size") else load_render_spec()
    ocfg = optimizer_config(cfg.optimizer, cfg.views, cfg.seed)
    ocfg.check_points(n, where)
    return generator, spec, _shading(str(cfg.shading), spec), ocfg


def _change(points, normals, refined) -> dict:
    """How far the geometry moved (the input as the reference, paper protocol units) and the
    normals turned."""
    from dss.metrics import evaluate

    moved = evaluate(refined.points.numpy(), points.numpy(), None, "paper").to_dict()
    angle = torch.rad2deg(torch.acos((torch.nn.functional.normalize(refined.normals, dim=1) *
                                      torch.nn.functional.normalize(normals, dim=1)).sum(1).clamp(-1, 1)))
    return {"chamfer_to_input_paper_x1e4": moved["chamfer"], "hausdorff_to_input_paper_x1e3": moved["hausdorff"],
            "normal_change_deg": {"mean": float(angle.mean()), "median": float(angle.median())}}


def _sparsity(ref) -> dict | None:
    from dss.filters import gradient_sparsity

    if ref.last is None:
        return None
    _, imgs, mask, refs = ref.last
    return {"input_renders": gradient_sparsity(imgs), "references": gradient_sparsity(refs)}


def run(cfg: DictConfig) -> dict:
    """Filter ``cfg.input`` (see the module docstring); returns the metrics dict."""
    from dss.pointcloud import PointCloud, save_ply

    t_start = time.perf_counter()
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    out, files = run_dir(cfg), _files(cfg)
    check_wandb(cfg.get("wandb"))
    check_figures(cfg.get("figures"))  # drawn after the work: refused before it
    dev = resolve_device(cfg.get("device"))
    claim_run_dir(out, ARTEFACTS, bool(cfg.get("overwrite", False)))
    output = resolve_output(cfg, out, "filtered.ply")
    cloud, input_report = load_input(files.input, cfg.get("nan_policy", "drop"), int(cfg.normals.k),
                                     bool(cfg.normals.recompute))
    points, normals, noise = _with_noise(cfg, cloud, input_report)
    generator, spec, shading, ocfg = _setup(cfg, len(points), f"input {files.input}")
    clean, mesh, gt_note = load_ground_truth(files.clean, files.mesh, len(points), int(cfg.seed), cloud.offset)
    kernel_build = prepare_kernels(dev)
    save_config(cfg, out)
    log.info("filtering %s (%d points%s) with %s at %s px, %s shading", files.input, len(points),
             f", +{noise:g} noise" if noise else "", generator.describe(), list(spec.image_size), cfg.shading)
    t0 = time.perf_counter()
    refined = refine(points, normals, generator, spec, ocfg, shading=shading, device=dev,
                     progress=bool(cfg.get("progress", True)), desc=f"dss-filter ({generator.name})")
    t_opt = time.perf_counter() - t0
    # in the input's frame (a cloud centred on load gets its offset back, as doubles)
    output = save_ply(output, PointCloud(refined.points, refined.normals, offset=cloud.offset,
                                         stored_as=cloud.stored_as), exclusive=not cfg.get("overwrite", False))
    protocols = list(cfg.metrics.protocols)
    m_in, m_out = score(points.numpy(), clean, mesh, protocols), score(refined.points.numpy(), clean, mesh, protocols)
    labels = [f"input (+{noise:g} noise)" if noise else "input", f"filtered ({generator.name})"]
    figures = write_figures(out, cfg.get("figures"), int(cfg.seed), spec, [(points, normals),
                            (refined.points, refined.normals)], labels, refined,
                            f"dss-filter {Path(files.input).name}, {generator.name}", shading=shading)
    metrics = {
        "input": input_report,
        "example": files.is_example,
        "output": str(output),
        "reference": generator.describe(),
        "shading": str(cfg.shading),
        "render": {"image_size": list(spec.image_size), "spec": spec.to_dict()},
        **optimization_report(refined.history, t_start, t_opt, kernel_build),
        "change": _change(points, normals, refined),
        "gradient_sparsity": _sparsity(refined.ref),
        "ground_truth": {"clean": files.clean, "mesh": files.mesh, "note": gt_note},
        "metrics_input": m_in,
        "metrics_output": m_out,
        "summary": {"input": short_metrics(m_in), "output": short_metrics(m_out)},
        "figures": figures,
    }
    save_metrics(metrics, out)
    log_run(cfg, out, metrics, refined.history, figures, job_type="filter")
    log.info("moved: Chamfer to the input %.3f x1e4 (paper protocol), normals %.1f deg (mean); %.1f s",
             metrics["change"]["chamfer_to_input_paper_x1e4"], metrics["change"]["normal_change_deg"]["mean"],
             metrics["time_s"]["total"])
    release_claims()
    return metrics


@hydra.main(version_base="1.3", config_path="../../conf", config_name="filter")
@guarded
def _main(cfg: DictConfig) -> None:
    m = run(cfg)
    print(f"filtered cloud: {m['output']} ({m['time_s']['total']:.0f} s); "
          f"Chamfer to the input {m['change']['chamfer_to_input_paper_x1e4']:.3f} x1e4 (paper protocol)")


def main() -> None:
    positional_to_override("input")
    run_app(_main)


if __name__ == "__main__":
    main()

