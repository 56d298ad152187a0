"""DSS's refinement of a cloud against reference images: the cycles, the outlier projection and
the plane fusion (:func:`dss.pipeline.refine_with_reference` runs all three), in the input's
units, and the normals written with the result."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

__all__ = ["Refined", "refine", "output_normals", "normals_mode", "progress_bar"]


@dataclass
class Refined:
    """What :func:`refine` gives back.

    Attributes:
        points, normals: (N, 3) the result, points in input units, normals DSS's own.
        history: the optimiser's history (loss per step, timings, ``"fusion"``, ``"device"``).
        ref: the reference renderer (its ``last`` batch: cameras, input renders, mask, references).
        norm: (centre (3,), scale, normalised input points (N, 3)): the optimiser's frame.
        optimizer: the :class:`dss.optimize.OptimizerConfig` it ran with.
    """

    points: torch.Tensor
    normals: torch.Tensor
    history: dict
    ref: Any
    norm: tuple
    optimizer: Any


def progress_bar(total: int, desc: str, enabled: bool):
    from tqdm.auto import tqdm

    bar = tqdm(total=total, desc=desc, unit="step", disable=not enabled, dynamic_ncols=True)

    def update(step: int, loss: float):
        bar.update(1)
        bar.set_postfix(loss=f"{loss:.4f}")

    return bar, update


def _bind_oracle(generator, clean, mesh, center, scale, pn, normals, settings, shading, backend) -> None:
    """Give the oracle the clean cloud (and the mesh's normals) in the optimiser's frame."""
    from experiments.denoising.reference_generators import oracle_normals

    if clean is None:
        raise ValueError("reference=oracle renders the ground truth: give clean= or mesh=")
    cp = ((torch.as_tensor(np.asarray(clean), dtype=center.dtype) - center) / scale).float()
    m = None
    if mesh is not None:
        v, f = mesh
        m = ((np.asarray(v, np.float64) - center.double().numpy()) / scale, f)
    generator.bind(cp, oracle_normals(cp, pn, normals, mesh=m), settings, shading, backend)


def refine(points: torch.Tensor, normals: torch.Tensor, generator, spec, optimizer, *, shading=None,
           fusion=None, noise: float | None = None, device=None, progress: bool = True, desc: str = "dss",
           clean: np.ndarray | None = None, mesh=None, callback=None, fusion_callback=None) -> Refined:
    """Normalise, refine with ``generator`` under ``spec`` (cameras, renderer settings; shading:
    the spec's channel unless given) and ``optimizer`` (an OptimizerConfig: views, seed,
    schedule), then the plane fusion (``fusion``: a FusionConfig, needs ``noise``), de-normalise.
    ``clean`` (M, 3), input units: the ground truth an oracle generator renders (with the
    normals of ``mesh`` (vertices, faces), input units, when given). ``callback`` and
    ``fusion_callback``: the optimiser's and the fusion's per-step / per-pass hooks (in the
    normalised frame; :mod:`experiments.evaluation.image_study` records its numbers with them).
    ``device``: where the optimisation runs (a torch.device; None: the CPU)."""
    from dss.pipeline import refine_with_reference
    from dss.pointcloud import normalize_unit_diagonal
    from experiments.common import describe_device
    from experiments.denoising.reference_generators import SpecViewSampler

    pn, center, scale = normalize_unit_diagonal(points)
    dev = torch.device("cpu") if device is None else device
    sampler = SpecViewSampler(spec, views=optimizer.views, seed=int(optimizer.seed), jitter=optimizer.view_jitter)
    shading = spec.shader() if shading is None else shading
    settings = spec.render_settings()
    if hasattr(generator, "bind"):  # the oracle: the clean cloud in the optimiser's frame
        _bind_oracle(generator, clean, mesh, center, scale, pn, normals, settings, shading, spec.backend)
    fusion_cams = None
    if fusion is not None:
        if noise is None:
            raise ValueError("the plane fusion needs the noise level")
        # its own camera stream (seeded apart from the optimiser's), fusion.views per batch
        fusion_cams = SpecViewSampler(spec, views=fusion.views, seed=int(optimizer.seed) + 7919,
                                      jitter=optimizer.view_jitter).sample
    total = (optimizer.cycles + optimizer.error_aware_cycles) * (optimizer.normal_steps + optimizer.point_steps)
    bar, update = progress_bar(total, desc, progress)
    try:
        # on a GPU the optimisation (renders, regularisers, kNN) runs there and the results come
        # back to the CPU; the reference network gets CPU arrays and its images go to the GPU
        result, ref = refine_with_reference(pn, normals, generator, config=optimizer, settings=settings,
                                            shading=shading, sampler=sampler, backend=spec.backend, progress=update,
                                            device=dev, keep_background=getattr(generator, "keep_background", True),
                                            fusion=fusion, fusion_cameras=fusion_cams, noise=noise,
                                            callback=callback, fusion_callback=fusion_callback)
    finally:
        bar.close()
    result.history["device"] = describe_device(dev)
    _refuse_divergence(result)
    return Refined(result.points * scale + center, result.normals, result.history, ref, (center, scale, pn), optimizer)


def _refuse_divergence(result) -> None:
    """The optimiser undoes blow-ups as they happen; a result that is still far larger than the
    input (or not finite) is not one, and is never written out."""
    from dss.optimize import OptimizationDiverged
    from dss.pointcloud import all_finite, bbox_diagonal

    if not all_finite(result.points, result.normals) or bbox_diagonal(result.points) > 2.0:
        raise OptimizationDiverged(f"the optimisation diverged: the result is not finite or spans "
                                   f"{bbox_diagonal(result.points):.3g}x the input's bounding box; lower the learning rates")


def normals_mode(setting: str, history: dict) -> str:
    """The written normals' kind for ``normals.output``: ``auto`` is the plane fusion's normals
    (the references' where they agree: ``optimized``) where it ran, else ``pca``."""
    setting = str(setting)
    if setting == "auto":
        return "optimized" if "fusion" in history else "pca"
    return setting


def output_normals(points: torch.Tensor, optimized: torch.Tensor, mode: str, k: int = 16) -> torch.Tensor:
    """Normals written with the denoised cloud: ``"optimized"`` (DSS's own normals) or ``"pca"``
    (a PCA fit on the denoised points, each flipped to agree with its optimised normal).

    On the shipped example with the shipped model (mean angle to the ground-truth mesh,
    docs/denoising.md "Written normals"): noisy input PCA 36.6 deg, optimised 12.8, PCA of the
    denoised points 11.9. DSS's normals keep part of the per-view noise of the references.
    """
    if mode == "optimized":
        return optimized
    if mode != "pca":
        raise ValueError(f"normals.output must be 'auto', 'pca' or 'optimized', got {mode!r}")
    from dss.pointcloud import estimate_normals

    # each sign comes from the optimised normal: a consistent orientation would be thrown away
    n = estimate_normals(points, k=k, orient="none")
    flip = (n * optimized).sum(dim=1, keepdim=True) < 0
    return torch.where(flip, -n, n)
