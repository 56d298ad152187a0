"""``dss-render``: render a point cloud from V views (sun shading, normals, inverse depth).

Writes into the run directory: ``config.yaml``, ``views/<kind>_<v>.png``, one grid per kind
(``sun.png``, ``normals.png``, ``depth.png``), ``grid.png`` (all kinds, a row each) and
``metrics.json`` (points, views, render time per kind, backend).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig

from dss.cameras import fit_distance, focal_from_fov, fps_sphere_cameras, ring_cameras
from dss.pointcloud import load_ply, normalize_unit_diagonal
from dss.render import render, resolve_backend
from dss.viz import colorize_depth, colorize_normals, image_grid, save_png, to_uint8
from experiments.common import (
    claim_run_dir,
    guarded,
    positional_to_override,
    prepare_kernels,
    release_claims,
    renderer_settings,
    run_app,
    run_dir,
    save_config,
    save_metrics,
)

log = logging.getLogger(__name__)


def make_cameras(cfg: DictConfig, points: torch.Tensor):
    """Cameras around the cloud's bounding-box centre, far enough to see all of it."""
    center = (points.max(0).values + points.min(0).values) / 2
    radius = float((points - center).norm(dim=1).max())
    dist = fit_distance(radius, cfg.fov_deg)
    size = (int(cfg.image_size), int(cfg.image_size))
    focal = focal_from_fov(cfg.fov_deg, size[1])
    if cfg.views <= 0:
        raise ValueError(f"views must be positive, got {cfg.views}")
    if cfg.sampler == "ring":
        return ring_cameras(cfg.views, center, dist, cfg.elevation_deg, focal, size)
    if cfg.sampler == "fps":
        g = torch.Generator().manual_seed(int(cfg.seed))
        return fps_sphere_cameras(cfg.views, center, dist, focal, size, jitter=cfg.jitter, generator=g)
    raise ValueError(f"unknown sampler {cfg.sampler!r}: use 'fps' or 'ring'")


#: what a run writes into its run directory: an earlier run's files there are refused or, with
#: overwrite=true, removed first (no older view PNGs stay beside new ones)
ARTEFACTS = ("views/*.png", "sun.png", "normals.png", "depth.png", "grid.png", "metrics.json", "config.yaml")


def run(cfg: DictConfig) -> dict:
    out = run_dir(cfg)
    claim_run_dir(out, ARTEFACTS, bool(cfg.get("overwrite", False)))
    cloud = load_ply(cfg.input)
    save_config(cfg, out)
    # Rendered in units of the bounding-box diagonal whatever ``normalize`` says: the renderer's
    # near plane and size floors are absolute lengths, so a cloud 1e-6 across would render
    # empty in its own units. The cameras frame the cloud, so the images do not depend on it.
    points, normals = cloud.points, cloud.normals
    points, _, scale = normalize_unit_diagonal(points)
    settings = renderer_settings(cfg.renderer)
    # a first-use compile (when the C++ backend may be used) is not a render time
    kernel_build = prepare_kernels() if cfg.backend in ("auto", "cpp") else 0.0
    backend = resolve_backend(cfg.backend)
    cams = make_cameras(cfg, points)
    results, timings = {}, {}
    for kind in ("sun", "normals", "depth"):
        t0 = time.perf_counter()
        with torch.no_grad():
            r = render(points, normals, cams, settings, shading=kind, backend=backend)
        timings[kind] = time.perf_counter() - t0
        if kind == "normals":
            imgs = colorize_normals(r.images, r.mask)
        elif kind == "depth":
            imgs = colorize_depth(r.images, r.mask)
            imgs = torch.where(r.mask[..., None], imgs, torch.ones_like(imgs))
        else:
            imgs = r.images
        results[kind] = [to_uint8(i) for i in imgs]
        coverage = r.mask.float().mean().item()
    (out / "views").mkdir(exist_ok=True)
    for kind, imgs in results.items():
        for v, im in enumerate(imgs):
            save_png(out / "views" / f"{kind}_{v:03d}.png", im)
        save_png(out / f"{kind}.png", image_grid(imgs))
    rows = [image_grid(results[k], ncols=len(results[k])) for k in results]
    save_png(out / "grid.png", np.concatenate(rows, 0))
    metrics = {
        "input": str(Path(cfg.input)),
        "points": len(cloud),
        "views": len(cams),
        "image_size": list(cams.image_size),
        # camera distance from the cloud's centre: in the input's units unless normalize
        "camera_distance": float(cams.centers[0].norm()) * (1.0 if cfg.normalize else scale),
        "backend": backend,
        "render_seconds": timings,
        "kernel_build_seconds": kernel_build,
        "coverage": coverage,
        "outputs": ["grid.png", "sun.png", "normals.png", "depth.png", "views/"],
    }
    save_metrics(metrics, out)
    log.info("rendered %d points x %d views into %s", len(cloud), len(cams), out)
    release_claims()
    return metrics


@hydra.main(version_base="1.3", config_path="../conf", config_name="render_cloud")
@guarded
def _main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    positional_to_override("input")
    run_app(_main)


if __name__ == "__main__":
    main()
