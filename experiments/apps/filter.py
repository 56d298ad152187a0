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

from experiments.apps.denoise import (
    EXAMPLE_DIR,
    check_figures,
    load_ground_truth,
    load_input,
    make_reference,
    optimizer_config,
    resolve_output,
    run_refinement,
    score,
    short_metrics,
    write_figures,
)
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


def run(cfg: DictConfig) -> dict:
    """Filter ``cfg.input`` (see the module docstring); returns the metrics dict."""
    from data_prep.render_spec import load_render_spec
    from dss.metrics import evaluate
    from dss.pointcloud import PointCloud, add_gaussian_noise, estimate_normals, save_ply

    t_start = time.perf_counter()
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    out = run_dir(cfg)
    is_example = not cfg.get("input")
    input_path = str(cfg.input) if cfg.get("input") else str(EXAMPLE_DIR / "clean.ply")
    clean_path, mesh_path = cfg.get("clean"), cfg.get("mesh")
    if is_example:
        clean_path = clean_path or str(EXAMPLE_DIR / "clean.ply")
        mesh_path = mesh_path or str(EXAMPLE_DIR / "mesh.ply")
    check_wandb(cfg.get("wandb"))
    check_figures(cfg.get("figures"))  # drawn after the work: refused before it
    resolve_device(cfg.get("device"))
    claim_run_dir(out, ARTEFACTS, bool(cfg.get("overwrite", False)))
    output = resolve_output(cfg, out, "filtered.ply")
    cloud, input_report = load_input(input_path, cfg.get("nan_policy", "drop"), int(cfg.normals.k),
                                     bool(cfg.normals.recompute))
    try:
        noise = float(cfg.get("noise") or 0.0)
    except (TypeError, ValueError):
        raise ValueError(f"noise={cfg.get('noise')!r} is not a number (the std of the noise to add, as a "
                         "fraction of the bbox diagonal)") from None
    if noise < 0:
        raise ValueError(f"noise must be >= 0 (std as a fraction of the bbox diagonal), got {noise}")
    points, normals = cloud.points, cloud.normals
    if noise > 0:
        points = add_gaussian_noise(points, noise, seed=int(cfg.seed))
        normals = estimate_normals(points, k=int(cfg.normals.k))
        input_report["added_noise"] = noise
        input_report["normals"] = f"estimated after adding noise (PCA, k={int(cfg.normals.k)})"
    if "model" in cfg.reference:
        raise ValueError("dss-filter takes an image filter (reference=l0|slic|identity); "
                         "use dss-denoise for the denoising network")
    generator, _ = make_reference(cfg, None)
    spec = load_render_spec(image_size=[int(cfg.image_size)] * 2) if cfg.get("image_size") else load_render_spec()
    shading = _shading(str(cfg.shading), spec)
    clean, mesh, gt_note = load_ground_truth(clean_path, mesh_path, len(points), int(cfg.seed), cloud.offset)
    optimizer_config(cfg.optimizer, cfg.views, cfg.seed).check_points(len(points), f"input {input_path}")
    kernel_build = prepare_kernels(resolve_device(cfg.get("device")))
    save_config(cfg, out)
    log.info("filtering %s (%d points%s) with %s at %s px, %s shading", input_path, len(points),
             f", +{noise:g} noise" if noise else "", generator.describe(), list(spec.image_size), cfg.shading)

    t0 = time.perf_counter()
    pts, nrm, history, ref, norm, ocfg = run_refinement(cfg, points, normals, generator, spec,
                                                        f"dss-filter ({generator.name})", shading=shading)
    t_opt = time.perf_counter() - t0
    # in the input's frame (a cloud centred on load gets its offset back, as doubles)
    output = save_ply(output, PointCloud(pts, nrm, offset=cloud.offset, stored_as=cloud.stored_as), exclusive=not cfg.get("overwrite", False))

    # How far the geometry moved (input as the reference, paper protocol units).
    moved = evaluate(pts.numpy(), points.numpy(), None, "paper").to_dict()
    protocols = list(cfg.metrics.protocols)
    m_in = score(points.numpy(), clean, mesh, protocols)
    m_out = score(pts.numpy(), clean, mesh, protocols)
    angle = torch.rad2deg(torch.acos((torch.nn.functional.normalize(nrm, dim=1) *
                                      torch.nn.functional.normalize(normals, dim=1)).sum(1).clamp(-1, 1)))
    from dss.filters import gradient_sparsity

    sparsity = None
    if ref.last is not None:
        _, imgs, mask, refs = ref.last
        sparsity = {"input_renders": gradient_sparsity(imgs), "references": gradient_sparsity(refs)}

    labels = [f"input (+{noise:g} noise)" if noise else "input", f"filtered ({generator.name})"]
    figures = write_figures(out, cfg, spec, [(points, normals), (pts, nrm)], labels, ref, history, ocfg,
                            f"dss-filter {Path(input_path).name}, {generator.name}", norm, shading=shading)
    metrics = {
        "input": input_report,
        "example": is_example,
        "output": str(output),
        "reference": generator.describe(),
        "shading": str(cfg.shading),
        "render": {"image_size": list(spec.image_size), "spec": spec.to_dict()},
        **optimization_report(history, t_start, t_opt, kernel_build),
        "change": {"chamfer_to_input_paper_x1e4": moved["chamfer"],
                   "hausdorff_to_input_paper_x1e3": moved["hausdorff"],
                   "normal_change_deg": {"mean": float(angle.mean()), "median": float(angle.median())}},
        "gradient_sparsity": sparsity,
        "ground_truth": {"clean": clean_path, "mesh": mesh_path, "note": gt_note},
        "metrics_input": m_in,
        "metrics_output": m_out,
        "summary": {"input": short_metrics(m_in), "output": short_metrics(m_out)},
        "figures": figures,
    }
    save_metrics(metrics, out)
    log_run(cfg, out, metrics, history, figures, job_type="filter")
    log.info("moved: Chamfer to the input %.3f x1e4 (paper protocol), normals %.1f deg (mean); %.1f s",
             moved["chamfer"], float(angle.mean()), metrics["time_s"]["total"])
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

