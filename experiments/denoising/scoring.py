"""The job's metrics against a ground truth: Chamfer, Hausdorff and point-to-mesh distances in
the requested protocols (:mod:`dss.metrics`), the normals' angle to the mesh, the Chamfer floor."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["score", "short_metrics", "normal_errors", "chamfer_floor", "log_summary"]


def score(pred: np.ndarray, clean: np.ndarray | None, mesh, protocols) -> dict:
    """``{protocol: metrics dict}`` (see :mod:`dss.metrics`), empty without ground truth."""
    from dss.metrics import evaluate_all

    if clean is None:
        return {}
    return evaluate_all(pred, clean, mesh, protocols)


def short_metrics(m: dict) -> dict:
    keys = ("chamfer", "hausdorff", "p2m", "point_to_mesh")
    return {pr: {k: d[k] for k in keys if d.get(k) is not None} for pr, d in m.items()}


def normal_errors(cloud_in, points, optimized, written, mesh, k: int = 16) -> dict | None:
    """Degrees to the closest ground-truth triangle's normal (input frame), None without a mesh:
    the input's PCA normals (``cloud_in``), and on the denoised ``points`` (N, 3) DSS's own
    (``optimized``), a PCA fit of them (``k`` neighbours: what the images' normals must beat) and
    the ``written`` ones."""
    if mesh is None:
        return None
    from dss.metrics import mesh_normals_at, normal_error_deg
    from experiments.denoising.refine import output_normals

    p = points.numpy()
    at_out = mesh_normals_at(p, mesh)  # three normal sets on the same points
    return {"input_pca": normal_error_deg(cloud_in.points.numpy(), cloud_in.normals.numpy(), mesh),
            "optimized": normal_error_deg(p, optimized.numpy(), mesh, at_out),
            "pca": normal_error_deg(p, output_normals(points, optimized, "pca", k).numpy(), mesh, at_out),
            "output": normal_error_deg(p, written.numpy(), mesh, at_out)}


def chamfer_floor(mesh, n: int, seed: int, protocols) -> dict:
    """``{protocol: metrics}`` of a second Poisson-disk sampling of ``mesh`` (``n`` points):
    the Chamfer distance a perfect result would still have."""
    from dss.metrics import chamfer_floors

    floors = chamfer_floors(mesh, n, int(seed), protocols, with_mesh=True)
    return {pr: r.to_dict() for pr, r in floors.items()}


def log_summary(metrics: dict) -> None:
    s = metrics["summary"]
    for pr in s["output"]:
        i, o = s["input"][pr], s["output"][pr]
        log.info("%s protocol: Chamfer x1e4 %.3f -> %.3f, Hausdorff x1e3 %.3f -> %.3f%s", pr, i["chamfer"], o["chamfer"],
                 i["hausdorff"], o["hausdorff"],
                 f", P2M x1e4 {i['p2m']:.3f} -> {o['p2m']:.3f}" if o.get("p2m") is not None else "")
    ne = metrics.get("normal_error_deg")
    if ne:
        log.info("normals, mean angle to the mesh (deg): input (PCA) %.1f, DSS %.1f, written (%s) %.1f",
                 ne["input_pca"]["mean"], ne["optimized"]["mean"], "output", ne["output"]["mean"])
    log.info("wall time %.1f s; outputs in %s", metrics["time_s"]["total"], Path(metrics["output"]).parent)
