"""``dss-denoise``: multi-view DSS point cloud denoising (paper "Application: point cloud denoising").

    dss-denoise                                      # the shipped example (1% noise, ground truth)
    dss-denoise noisy.ply                            # model picked from the estimated noise level
    dss-denoise noisy.ply noise=0.003                # ... or from a hint (0.003 | 0.01)
    dss-denoise noisy.ply reference=l0               # L0-DSS (image filter instead of the network)
    dss-denoise noisy.ply reference.model=my.onnx    # any denoiser exported with dss-export
    dss-denoise noisy.ply clean=clean.ply mesh=gt.ply   # ground truth: metrics in both protocols

The noisy cloud (normals estimated when missing; rows with NaN/inf reported and dropped; points
much sparser than the surface removed, ``outliers`` in ``conf/denoise.yaml``, and written to
``outliers.ply``) is normalised to a unit bounding-box diagonal. Every cycle 2 views (the
``budget`` preset; the paper: 12) are sampled around it, the
*input* is rendered with the denoiser's training render setting (the model file's metadata, or
``conf/render/pairs.yaml`` at the budget's 64 px for the filters), the renders are mapped through the reference
generator (``conf/reference``), and DSS optimises normals to match them (the paper's local
schedule, T_n = 19 normal steps per cycle; ``cycles_by_noise`` and ``lr_points_by_noise`` for
``auto``: 4 cycles at 3x the paper's point rate at 1% noise) while the projection term moves the
points onto the planes of the corrected normals. The paper's T_p = 1 image-driven point step
per cycle is ``optimizer.point_steps=1``: with learned references it made the result worse
(measurements in ``conf/denoise.yaml``). Writes into the run directory: ``config.yaml``, the denoised PLY (input units),
``before_after.png`` (rows: noisy | denoised | clean when given), ``references.png`` (last cycle:
input renders | references | final renders), ``loss.png`` + ``loss.json``, ``metrics.json``.
"""

from __future__ import annotations

import logging
import math
import os
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from dss.timing import StageClock
from experiments.common import (
    OutputExistsError,
    claim_output,
    claim_run_dir,
    describe_device,
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

__all__ = ["run", "main", "EXAMPLE_DIR", "ARTEFACTS", "OutputExistsError", "load_input", "resolve_output"]

EXAMPLE_DIR = Path(__file__).resolve().parents[1] / "assets" / "example"
EXAMPLE_FILES = {"input": "noisy_1pct.ply", "clean": "clean.ply", "mesh": "mesh.ply"}


#: what a run writes into its run directory (an earlier run's are refused or, with overwrite,
#: removed first: experiments.common.claim_run_dir)
ARTEFACTS = ("denoised.ply", "outliers.ply", "before_after.png", "references.png", "loss.png", "loss.json",
             "metrics.json", "config.yaml")


# ------------------------------------------------------------------------------ input / output
def resolve_output(cfg: DictConfig, out: Path, default_name: str) -> Path:
    """The output PLY path, claimed for this run (experiments.common.claim_output): its folder
    must be writable, no other running process may hold it, and an existing file is refused
    unless ``cfg.overwrite``."""
    path = Path(cfg.output) if cfg.get("output") else out / default_name
    if path.suffix.lower() != ".ply":
        raise ValueError(f"output {path}: must be a .ply file")
    return claim_output(path, bool(cfg.get("overwrite", False)))


def _raw_row_count(path: Path) -> int | None:
    """The rows the file declares (a PLY header's vertex count; open3d's count otherwise)."""
    from dss.pointcloud import read_ply_header

    try:
        if path.suffix.lower() == ".ply":
            return read_ply_header(path).element("vertex").count
        import open3d as o3d

        return len(o3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False).points)
    except Exception:  # load_ply reports the real problem
        return None


def load_input(path: str | os.PathLike, nan_policy: str = "drop", normals_k: int = 16,
               recompute_normals: bool = False) -> tuple[Any, dict]:
    """Load the input cloud: (PointCloud with normals, report dict).

    NaN/inf rows are counted and dropped (``nan_policy="drop"``) or refused (``"raise"``);
    normals are estimated (PCA, ``normals_k`` neighbours, consistent orientation) when the file
    has none or ``recompute_normals``. A cloud far from the origin comes centred, its float64
    ``offset`` kept for the output (:func:`dss.pointcloud.load_ply`).
    """
    from dss.pointcloud import PointCloudError, estimate_normals, load_ply

    path = Path(path)
    if not path.exists():
        raise PointCloudError(f"input {path}: no such file")
    raw = _raw_row_count(path)
    cloud = load_ply(path, nan_policy=nan_policy, compute_normals=False)
    had_normals = cloud.normals is not None
    if not had_normals or recompute_normals:
        if len(cloud) < max(3, normals_k):
            raise PointCloudError(f"input {path}: {len(cloud)} points are too few (need at least {max(3, normals_k)})")
        cloud = cloud.with_normals(estimate_normals(cloud.points, k=normals_k))
    dropped = (raw - len(cloud)) if raw is not None else 0
    if dropped:
        log.warning("input %s: dropped %d rows with NaN/inf values", path, dropped)
    report = {"path": str(path), "points": len(cloud), "rows_in_file": raw, "nan_rows_dropped": int(dropped),
              "normals": "from file" if had_normals and not recompute_normals else f"estimated (PCA, k={normals_k})",
              # the input's coordinates are points + offset: the job works centred, the output is written back
              "offset": None if cloud.offset is None else cloud.offset.tolist()}
    return cloud, report


OUTLIER_KEYS = ("k", "z_threshold", "ratio_threshold", "iterations")


def outlier_params(node) -> dict:
    """``dss.pointcloud.find_outliers`` keyword arguments from an ``outliers`` config block; keys
    it leaves out take find_outliers' defaults."""
    return {k: node[k] for k in OUTLIER_KEYS if node.get(k) is not None}


def remove_outliers(cloud, node, normals_k: int | None = None) -> tuple[Any, dict, Any]:
    """(inlier cloud, report, removed cloud or None): ``node`` is conf/denoise.yaml's ``outliers``
    block. The caller writes the removed points to ``outliers.ply`` with the run's results
    (nothing the user gave is lost, and nothing is written before the run can succeed).
    ``normals_k``: the normals were estimated (not read), so re-estimate them without the outliers."""
    from dss.pointcloud import PointCloudError, estimate_normals, find_outliers

    params = outlier_params(node)
    if not node.get("remove", True):
        return cloud, {"removed": 0, "enabled": False, **params}, None
    t0 = time.perf_counter()
    bad = find_outliers(cloud.points, **params)
    n_bad = int(bad.sum())
    report = {"enabled": True, "removed": n_bad, "fraction": n_bad / max(1, len(cloud)), **params,
              "seconds": time.perf_counter() - t0, "file": None}
    if n_bad == 0:
        return cloud, report, None
    kept = cloud.select(~bad)
    if len(kept) < 16:
        raise PointCloudError(f"outlier removal would leave {len(kept)} of {len(cloud)} points; "
                              "set outliers.remove=false")
    if normals_k:
        kept = kept.with_normals(estimate_normals(kept.points, k=normals_k))
    log.log(logging.WARNING if report["fraction"] > 0.1 else logging.INFO,
            "removed %d of %d points (%.2f%%) as outliers (sparser than the surface; kept in outliers.ply with the results)%s",
            n_bad, len(cloud), 100 * report["fraction"],
            ": a scan of varying density loses its sparse parts, set outliers.remove=false to keep them"
            if report["fraction"] > 0.1 else "")
    return kept, report, cloud.select(bad)


def _explicit_model(cfg: DictConfig) -> bool:
    """Whether the reference names its model file (checked before any work) rather than ``auto``."""
    node = cfg.reference
    return "model" in node and node.model not in (None, "auto")


def load_ground_truth(clean: str | None, mesh: str | None, n: int, seed: int = 0, offset=None):
    """(clean points (M, 3) float64 or None, mesh (V, F) or None, note), less ``offset`` (the
    input cloud's, float64 (3,); see :func:`load_input`) so that they share the input's frame."""
    from dss.metrics import load_mesh, load_points, sample_poisson_disk

    shift = np.zeros(3) if offset is None else np.asarray(offset, np.float64).reshape(3)
    m = load_mesh(mesh) if mesh else None
    if m is not None and offset is not None:
        m = (m[0] - shift, m[1])
    if clean:
        pts = load_points(clean)
        return (pts if offset is None else pts - shift), m, "clean cloud from file"
    if m is not None:
        return sample_poisson_disk(m, n, seed), m, f"clean cloud: {n} Poisson-disk samples of the mesh (seed {seed})"
    return None, None, "no ground truth"


def score(pred: np.ndarray, clean: np.ndarray | None, mesh, protocols) -> dict:
    """``{protocol: metrics dict}`` (see :mod:`dss.metrics`), empty without ground truth."""
    from dss.metrics import evaluate_all

    if clean is None:
        return {}
    return evaluate_all(pred, clean, mesh, protocols)


def interpolate_by_noise(table: dict, noise: float) -> float:
    """The value of ``table`` ({noise level: value}) at ``noise``: piecewise linear in log(noise)
    between the two levels around it (in log(value) too when every value is positive, so that a
    rate or a count grows by a constant factor per factor of noise), the end values beyond the
    table's range. Continuous in ``noise``: a cloud between two tuned levels gets settings between
    theirs, never the nearest level's."""
    levels = sorted(float(k) for k in table)
    vals = [float(table[k]) for k in sorted(table, key=float)]
    if not levels:
        raise ValueError("an empty table")
    if noise <= levels[0] or len(levels) == 1:
        return vals[0]
    if noise >= levels[-1]:
        return vals[-1]
    i = max(j for j in range(len(levels) - 1) if levels[j] <= noise)
    t = (math.log(noise) - math.log(levels[i])) / (math.log(levels[i + 1]) - math.log(levels[i]))
    a, b = vals[i], vals[i + 1]
    if a > 0 and b > 0:
        return float(math.exp((1 - t) * math.log(a) + t * math.log(b)))
    return float((1 - t) * a + t * b)


def resolve_by_noise(cfg: DictConfig, noise: float, key: str, cast=float) -> dict:
    """Set ``cfg.optimizer.<key>`` when it is ``auto``: ``<key>_by_noise`` interpolated at the noise
    level in use (:func:`interpolate_by_noise`; integers rounded). Returns what was chosen and why
    (for metrics.json; ``exact``: the interpolated value before rounding)."""
    setting = cfg.optimizer[key]
    if str(setting) != "auto":
        return {"setting": cast(setting), "used": cast(setting)}
    name = f"{key}_by_noise"
    table = {float(k): float(v) for k, v in (cfg.get(name) or {}).items()}
    if not table:
        raise ValueError(f"optimizer.{key}=auto needs {name} ({{noise level: value}})")
    exact = interpolate_by_noise(table, float(noise))
    used = max(1, int(round(exact))) if cast is int else float(exact)
    cfg.optimizer[key] = used
    return {"setting": "auto", "used": used, "exact": exact, "noise": noise, name: table}


#: optimiser settings that may be ``auto`` (taken from ``<key>_by_noise`` in conf/denoise.yaml)
BY_NOISE = (("cycles", int), ("lr_points", float), ("projection_weight", float), ("reg_cutoff", float),
            ("final_projection_k", int))


def resolve_all_by_noise(cfg: DictConfig, noise: float, n_points: int | None = None) -> dict:
    """:func:`resolve_by_noise` for every :data:`BY_NOISE` key, then (given the point count)
    :func:`resolve_neighbourhood`; ``{key: note}``."""
    notes = {key: resolve_by_noise(cfg, noise, key, cast) for key, cast in BY_NOISE}
    cyc, lr = notes["cycles"], notes["lr_points"]
    if cyc["setting"] == "auto" and lr["setting"] == "auto" and cyc["exact"] != cyc["used"]:
        # cycles are whole; the point rate takes the rounding so that cycles x rate (how far the
        # regularisers move the points) stays continuous in the noise level
        lr["used"] = cfg.optimizer.lr_points = float(cfg.optimizer.lr_points) * cyc["exact"] / cyc["used"]
        lr["cycles_rounding"] = f"x {cyc['exact']:.3g} / {cyc['used']}"
    if str(cfg.optimizer.get("max_displacement", 0)) == "auto":
        # max_move noise levels (the noise is in bbox diagonals, the optimiser's frame)
        cfg.optimizer.max_displacement = float(cfg.get("max_move", 0) or 0) * float(noise)
        notes["max_displacement"] = {"setting": "auto", "used": float(cfg.optimizer.max_displacement),
                                     "max_move": float(cfg.get("max_move", 0) or 0)}
    if n_points is not None:
        notes["reg_dilation"] = resolve_neighbourhood(cfg, n_points, notes.get("reg_cutoff"))
    return notes


def resolve_neighbourhood(cfg: DictConfig, n_points: int, cutoff_note: dict | None = None) -> dict:
    """Set ``cfg.optimizer.reg_dilation`` when it is ``auto``: the regularisers' neighbourhood
    keeps the same extent on the surface at any density.

    The projection term fits a plane to each point's ``reg_k`` nearest neighbours, a count tuned
    at ``reg_dilation_points`` (20K) points. A denser cloud puts the same count into a smaller
    patch: at 100K points and 1% noise 16 neighbours span less than the noise, and DSS removed
    half as much of it as at 20K. ``auto`` uses every d-th of the ``reg_k * d`` nearest, ``d =
    round(n_points / reg_dilation_points)`` (at least 1, at most ``reg_dilation_max``): the patch
    of the tuned setting, at the per-step cost of ``reg_k`` neighbours. When ``reg_cutoff`` came
    from its table (``auto``), it is raised to at least ``sqrt(d)`` (the patch's radius in D,
    which shrinks as ``1/sqrt(N)``) so that the wider neighbours are not masked out again.
    Measured in conf/denoise.yaml (a noise-scaled rule was tried and rejected there).
    """
    setting = cfg.optimizer.get("reg_dilation", 1)
    if str(setting) != "auto":
        return {"setting": int(setting), "used": int(setting)}
    if n_points < 1:
        raise ValueError(f"reg_dilation=auto needs a positive point count, got {n_points}")
    tuned = int(cfg.get("reg_dilation_points", 20000))
    cap = int(cfg.get("reg_dilation_max", 8))
    d = int(min(cap, max(1, math.floor(n_points / tuned + 0.5))))
    cfg.optimizer.reg_dilation = d
    note = {"setting": "auto", "used": d, "points": int(n_points), "reg_dilation_points": tuned,
            "reg_dilation_max": cap}
    if d > 1 and cutoff_note is not None and cutoff_note.get("setting") == "auto":
        cutoff = max(float(cfg.optimizer.reg_cutoff), math.sqrt(d))
        if cutoff != float(cfg.optimizer.reg_cutoff):
            note["reg_cutoff"] = f"{cfg.optimizer.reg_cutoff:g} -> {cutoff:.3g} (sqrt of the dilation)"
            cfg.optimizer.reg_cutoff = cutoff
            cutoff_note["used"] = cutoff
    return note


def resolve_budget(cfg: DictConfig, n_points: int, cycles_note: dict | None = None,
                   lr_note: dict | None = None) -> dict:
    """Apply the ``budget`` preset (``default`` | ``fast`` | ``auto``: ``fast`` for inputs of more
    than ``budget_fast_above`` points): ``cfg.views`` when it is null, the filters' and the planes
    channel's render sizes (``filter_image_size`` / ``planes_image_size`` in the note) when
    ``cfg.image_size`` is null, ``cfg.fusion.passes`` when it is null, and the preset's
    ``cycles_scale`` on cycles that came from ``cycles_by_noise`` (an explicit
    ``optimizer.cycles`` is kept) and its ``lr_points_scale`` on a point rate that came from
    ``lr_points_by_noise`` (fewer cycles, longer steps: the regularisers move the points about
    as far). Returns what was chosen and why (for metrics.json)."""
    setting = str(cfg.get("budget", "default"))
    presets = cfg.get("budgets") or {}
    if setting == "auto":
        limit = int(cfg.get("budget_fast_above", 0) or 0)
        name = "fast" if limit and n_points > limit else "default"
        reason = f"{n_points} points {'>' if name == 'fast' else '<='} budget_fast_above {limit}"
    else:
        name, reason = setting, "given"
    if name not in presets:
        raise ValueError(f"budget={setting!r}: no preset {name!r} in budgets (have {sorted(presets)})")
    preset = presets[name]
    note = {"setting": setting, "used": name, "reason": reason}
    if cfg.get("views") is None:
        cfg.views = int(preset.views)
        note["views"] = int(preset.views)
    else:
        note["views"] = f"{int(cfg.views)} (given)"
    if cfg.get("image_size") is None and preset.get("filter_image_size"):
        # an image filter renders at any size; a model ignores it (it renders at its training size)
        note["filter_image_size"] = int(preset.filter_image_size)
    if cfg.get("image_size") is None and preset.get("planes_image_size"):
        # identity and the oracle in the planes channel; a model renders at its training size
        note["planes_image_size"] = int(preset.planes_image_size)
    fusion = cfg.get("fusion")
    if fusion is not None and fusion.get("passes") is None:
        fusion.passes = int(preset.get("fusion_passes", 4))
        note["fusion_passes"] = int(fusion.passes)
    scale = float(preset.get("cycles_scale", 1.0))
    if scale != 1.0 and cycles_note is not None and cycles_note.get("setting") == "auto":
        cfg.optimizer.cycles = max(1, int(round(int(cfg.optimizer.cycles) * scale)))
        note["cycles"] = f"{cycles_note['used']} x {scale:g} -> {cfg.optimizer.cycles}"
    lr_scale = float(preset.get("lr_points_scale", 1.0))
    if lr_scale != 1.0 and lr_note is not None and lr_note.get("setting") == "auto":
        used = float(cfg.optimizer.lr_points)
        cfg.optimizer.lr_points = used * lr_scale
        note["lr_points"] = f"{used:g} x {lr_scale:g} -> {cfg.optimizer.lr_points:g}"
    return note


def output_normals(points: torch.Tensor, optimized: torch.Tensor, mode: str, k: int = 16) -> torch.Tensor:
    """Normals written with the denoised cloud: ``"optimized"`` (DSS's own normals) or ``"pca"``
    (a PCA fit on the denoised points, each flipped to agree with its optimised normal).

    Measured on the shipped example (angle to the ground-truth mesh, mean): noisy input PCA 36.6
    deg, optimised 29.9, PCA of the denoised points 13.4. DSS moves the points onto a smooth
    surface, but its normals keep part of the per-view noise of the references; the renders of
    the optimised normals look speckled.
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


def short_metrics(m: dict) -> dict:
    keys = ("chamfer", "hausdorff", "p2m", "point_to_mesh")
    return {pr: {k: d[k] for k in keys if d.get(k) is not None} for pr, d in m.items()}


# ------------------------------------------------------------------------------ figures
def figure_cameras(spec, n: int = 4, seed: int = 0, size: int | None = None):
    """``n`` fixed cameras seeing the whole normalised object with the spec's field of view."""
    from dss.cameras import fit_distance, focal_from_fov, fps_sphere_cameras

    H, W = (size, size) if size else spec.image_size
    dist = fit_distance(0.5, spec.fov_deg)  # a unit-diagonal box fits in a radius-0.5 sphere
    return fps_sphere_cameras(n, (0.0, 0.0, 0.0), dist, focal_from_fov(spec.fov_deg, W), (H, W), jitter=0.0,
                              generator=torch.Generator().manual_seed(seed), up=spec.up)


def render_rows(clouds: list[tuple[torch.Tensor, torch.Tensor]], cams, settings, shading, backend="auto"):
    from dss.render import render

    rows = []
    with torch.no_grad():
        for p, n in clouds:
            rows.append(render(p, n, cams, settings, shading=shading, backend=backend).images.clamp(0, 1))
    return rows


def save_image_rows(path: Path, rows: list[torch.Tensor], labels: list[str]) -> Path:
    """Grid PNG: one row per entry of ``rows`` ((V, H, W, C) each, in [0, 1]), labelled on the left."""
    from dss.viz import labelled_rows, save_png

    return save_png(path, labelled_rows([r.clamp(0, 1) for r in rows], labels))


def save_loss_curve(path: Path, history: dict, steps_per_cycle: int, title: str, image_loss: str = "l1") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dss.io_utils import atomic_savefig

    loss = np.asarray(history["loss"], np.float64)
    fig, ax = plt.subplots(figsize=(6, 3.2))
    ax.plot(np.arange(1, len(loss) + 1), loss, lw=1)
    for c in range(steps_per_cycle, len(loss), steps_per_cycle):
        ax.axvline(c + 0.5, color="0.85", lw=0.5, zorder=0)
    ax.set_xlabel("step (grey lines: new views and references)")
    # the plotted value is the step's whole objective; name the image term the config chose
    ax.set_ylabel(f"loss ({image_loss.upper()} image term + regularisers)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------ pieces
def optimizer_config(node, views: int, seed: int):
    from dss.optimize import OptimizerConfig

    d = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else dict(node or {})
    known = set(OptimizerConfig.__dataclass_fields__)
    bad = set(d) - known
    if bad:
        raise ValueError(f"optimizer: unknown keys {sorted(bad)}; known: {sorted(known)}")
    return OptimizerConfig(**{**d, "views": int(views), "seed": int(seed)})


def make_reference(cfg: DictConfig, noise: float | None):
    """Instantiate ``cfg.reference``; an ``onnx`` generator with ``model: auto`` gets the shipped
    model for ``noise``. Returns (generator, model selection note)."""
    from hydra.utils import instantiate

    from experiments.apps.reference_generators import select_model

    node = cfg.reference
    note = None
    kwargs = {}
    if "model" in node and (node.model in (None, "auto")):
        if noise is None:
            raise ValueError("reference.model=auto needs a noise level (noise=... or the estimate)")
        path, level = select_model(noise)
        kwargs["model"] = str(path)
        note = f"shipped model for noise {level:g} ({path.name}), chosen for noise {noise:.4g}"
    from hydra.errors import InstantiationException

    try:
        generator = instantiate(node, **kwargs)
    except InstantiationException as e:
        # Hydra wraps the generator's own (clear) error; show that one to the user.
        if isinstance(e.__cause__, Exception):
            raise e.__cause__ from None
        raise
    if hasattr(generator, "resolve_for_noise"):  # reference=auto: the table's entry for this noise level
        if noise is None:
            raise ValueError("reference=auto needs a noise level (noise=... or the estimate)")
        generator, note, fusion = generator.resolve_for_noise(noise)
        if fusion:
            with open_dict(cfg):
                for k, v in fusion.items():
                    cfg.fusion[k] = v
    return generator, note


def progress_bar(total: int, desc: str, enabled: bool):
    from tqdm.auto import tqdm

    bar = tqdm(total=total, desc=desc, unit="step", disable=not enabled, dynamic_ncols=True)

    def update(step: int, loss: float):
        bar.update(1)
        bar.set_postfix(loss=f"{loss:.4f}")

    return bar, update


def fusion_config(cfg: DictConfig, shading):
    """The :class:`dss.fusion.FusionConfig` of ``cfg.fusion``, or None when the stage is off
    (``enabled: auto``: on in the planes channel)."""
    from dss.fusion import FusionConfig

    node = cfg.get("fusion") or {}
    enabled = str(node.get("enabled", "auto")).lower()
    if enabled not in ("auto", "true", "false"):
        raise ValueError(f"fusion.enabled must be auto, true or false, got {node.get('enabled')!r}")
    planes = isinstance(shading, str) and shading == "planes"
    if enabled == "false" or (enabled == "auto" and not planes):
        return None
    if not planes:
        raise ValueError("fusion.enabled=true needs the planes channel (channel=planes, or a model trained on it)")
    d = {k: v for k, v in OmegaConf.to_container(node, resolve=True).items() if k != "enabled"}
    if d.get("passes") is None:  # null: the budget preset's (resolve_budget), else FusionConfig's
        d.pop("passes", None)
    known = set(FusionConfig.__dataclass_fields__)
    bad = set(d) - known
    if bad:
        raise ValueError(f"fusion: unknown keys {sorted(bad)}; known: {sorted(known | {'enabled'})}")
    return FusionConfig(**d)


def run_refinement(cfg: DictConfig, points: torch.Tensor, normals: torch.Tensor, generator, spec, desc: str,
                   shading=None, noise: float | None = None, clean: np.ndarray | None = None, mesh=None,
                   callback=None, fusion_callback=None):
    """Normalise, refine with ``generator`` under ``spec`` (cameras, renderer settings; shading:
    the spec's channel unless given), then the plane fusion (``cfg.fusion``), de-normalise.
    ``clean`` (M, 3), input units: the ground truth an oracle generator renders (with the
    normals of ``mesh`` (vertices, faces), input units, when given). ``callback`` and
    ``fusion_callback``: the optimiser's and the fusion's per-step / per-pass hooks (in the
    normalised frame; :mod:`experiments.evaluation.image_study` records its numbers with them).

    Returns (points, normals in input units, history, reference renderer, normalisation
    (centre, scale, normalised input points), optimiser config)."""
    from dss.pipeline import refine_with_reference
    from dss.pointcloud import normalize_unit_diagonal
    from experiments.apps.reference_generators import SpecViewSampler, oracle_normals

    pn, center, scale = normalize_unit_diagonal(points)
    dev = resolve_device(cfg.get("device"))
    ocfg = optimizer_config(cfg.optimizer, cfg.views, cfg.seed)
    sampler = SpecViewSampler(spec, views=ocfg.views, seed=int(cfg.seed), jitter=ocfg.view_jitter)
    shading = spec.shader() if shading is None else shading
    settings = spec.render_settings()
    if hasattr(generator, "bind"):  # the oracle: the clean cloud in the optimiser's frame
        if clean is None:
            raise ValueError("reference=oracle renders the ground truth: give clean= or mesh=")
        cp = ((torch.as_tensor(np.asarray(clean), dtype=center.dtype) - center) / scale).float()
        m = None
        if mesh is not None:
            v, f = mesh
            m = ((np.asarray(v, np.float64) - center.double().numpy()) / scale, f)
        generator.bind(cp, oracle_normals(cp, pn, normals, mesh=m), settings, shading, spec.backend)
    fcfg = fusion_config(cfg, shading)
    fusion_cams = None
    if fcfg is not None:
        if noise is None:
            raise ValueError("the plane fusion needs the noise level")
        # its own camera stream (seeded apart from the optimiser's), fusion.views per batch
        fusion_cams = SpecViewSampler(spec, views=fcfg.views, seed=int(cfg.seed) + 7919, jitter=ocfg.view_jitter).sample
    total = (ocfg.cycles + ocfg.error_aware_cycles) * (ocfg.normal_steps + ocfg.point_steps)
    bar, update = progress_bar(total, desc, bool(cfg.get("progress", True)))
    try:
        # on a GPU the optimisation (renders, regularisers, kNN) runs there and the results come
        # back to the CPU; the reference network gets CPU arrays and its images go to the GPU
        result, ref = refine_with_reference(pn, normals, generator, config=ocfg, settings=settings,
                                            shading=shading, sampler=sampler, backend=spec.backend, progress=update,
                                            device=dev, keep_background=getattr(generator, "keep_background", True),
                                            fusion=fcfg, fusion_cameras=fusion_cams, noise=noise,
                                            callback=callback, fusion_callback=fusion_callback)
    finally:
        bar.close()
    result.history["device"] = describe_device(dev)
    # the optimiser undoes blow-ups as they happen; a result that is still far larger than the
    # input (or not finite) is not one, and is never written out
    from dss.optimize import OptimizationDiverged
    from dss.pointcloud import all_finite, bbox_diagonal

    if not all_finite(result.points, result.normals) or bbox_diagonal(result.points) > 2.0:
        raise OptimizationDiverged(f"the optimisation diverged: the result is not finite or spans "
                                   f"{bbox_diagonal(result.points):.3g}x the input's bounding box; lower the learning rates")
    out_p = result.points * scale + center
    return out_p, result.normals, result.history, ref, (center, scale, pn), ocfg


def write_figures(out: Path, cfg: DictConfig, spec, rows_pts: list, labels: list, ref, history: dict, ocfg,
                  title: str, norm, shading=None) -> list[str]:
    """before_after.png (a row per cloud of ``rows_pts``, in input units), references.png (last
    cycle: input renders | references | result renders), loss.png / loss.json."""
    from dss.io_utils import atomic_write_json

    center, scale, _ = norm
    fig_cfg = cfg.get("figures", {}) or {}
    cams = figure_cameras(spec, int(fig_cfg.get("views", 4)), int(cfg.seed), fig_cfg.get("image_size"))
    settings = spec.render_settings()
    shading = spec.shader() if shading is None else shading
    planes = isinstance(shading, str) and shading == "planes"
    clouds = [((p - center) / scale, n) for p, n in rows_pts]
    # planes are not a picture: the before/after rows use the paper's sun lights in that channel
    rows = render_rows(clouds, cams, settings, "sun" if planes else shading, spec.backend)
    written = [save_image_rows(out / "before_after.png", rows, labels).name]
    if ref.last is not None:
        from dss.render import render
        from dss.shading import planes_normals

        cams_r, imgs, _mask, refs = ref.last
        k = min(4, len(cams_r))
        sub = cams_r[:k]
        p, n = clouds[1]
        with torch.no_grad():
            final = render(p, n, sub, settings, shading=shading, backend=spec.backend).images

        def show(x):  # planes as a normal map (camera-facing normals, world axes -> RGB)
            if not planes:
                return x.clamp(0, 1)
            covered = (x.abs().amax(-1, keepdim=True) > 0)
            return torch.where(covered, 0.5 + 0.5 * planes_normals(x, sub), torch.zeros_like(x))

        written.append(save_image_rows(out / "references.png", [show(imgs[:k]), show(refs[:k]), show(final)],
                                       ["input render", "reference", "result"]).name)
    steps = ocfg.normal_steps + ocfg.point_steps
    written.append(save_loss_curve(out / "loss.png", history, steps, title, str(ocfg.image_loss)).name)
    atomic_write_json(out / "loss.json", {"step": history["step"], "loss": history["loss"], "kind": history["kind"],
                                          "time": history["time"], "steps_per_cycle": steps})
    written.append("loss.json")
    return written


CHANNELS = ("auto", "planes", "sun", "point")


def resolve_channel(cfg: DictConfig, generator, budget_note: dict):
    """(render spec, its source, shading, shading name) for ``generator``.

    A model renders in its training data's channel at its size (its metadata). Filters, identity
    and the oracle take ``cfg.channel``: ``planes`` (``conf/render/planes.yaml`` at its own size,
    or ``image_size``), ``point`` (``conf/render/pairs.yaml``'s light) or ``sun`` (the paper's
    three RGB lights with pairs.yaml's cameras), both at ``image_size`` or the budget's
    ``filter_image_size``; ``auto``: planes for identity and the oracle, sun for image filters.
    """
    from data_prep.render_spec import load_render_spec, spec_path

    channel = str(cfg.get("channel", "auto"))
    if channel not in CHANNELS:
        raise ValueError(f"channel must be one of {list(CHANNELS)}, got {channel!r}")
    if channel == "auto":
        channel = "planes" if generator.name in ("identity", "oracle") else "sun"
    size = cfg.get("image_size")
    if generator.name == "onnx":
        spec, source = generator.render_spec(None)
        if size and list(spec.image_size) != [int(size)] * 2:
            log.warning("image_size=%s ignored: the model fixes the render size to %s", size, list(spec.image_size))
        return spec, source, spec.shader(), spec.describe_shading()
    if channel == "planes":
        size = size or budget_note.get("planes_image_size")
        spec = load_render_spec(spec_path("planes"), **({"image_size": [int(size)] * 2} if size else {}))
        return spec, "config (conf/render/planes.yaml)", "planes", "planes"
    size = size or budget_note.get("filter_image_size")
    spec = load_render_spec(**({"image_size": [int(size)] * 2} if size else {}))
    if channel == "sun":
        return spec, "config", "sun", "sun"
    return spec, "config", spec.point_light(), spec.describe_shading()


# ------------------------------------------------------------------------------ checks
#: the noise estimator reads a clean surface as less than this (dss.pipeline.estimate_noise_level):
#: an input estimated below it holds no noise the job can tell apart from its surface
NOISE_FLOOR = 0.001


def noise_hint(value) -> float | None:
    """``noise=``: None (estimate it) or a positive fraction of the bbox diagonal; anything else is
    refused naming the key."""
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"noise={value!r} is not a number: give the noise std as a fraction of the bbox "
                         "diagonal (0.003, 0.01), or leave noise unset to estimate it") from None
    if not (v > 0 and math.isfinite(v)):
        raise ValueError(f"noise={value}: the noise hint must be a positive fraction of the bbox diagonal "
                         "(0.003, 0.01)")
    return v


FIGURE_KEYS = ("enabled", "views", "image_size")


def check_figures(node) -> None:
    """Refuse a bad ``figures`` block before any work (the figures are drawn after it)."""
    node = node or {}
    unknown = sorted(set(node) - set(FIGURE_KEYS))
    if unknown:
        raise ValueError(f"figures: unknown keys {unknown}; known: {list(FIGURE_KEYS)}")
    enabled = node.get("enabled", True)
    if not isinstance(enabled, bool):
        raise ValueError(f"figures.enabled={enabled!r}: must be true or false")
    for key, default, allow_null in (("views", 4, False), ("image_size", None, True)):
        value = node.get(key, default)
        if value is None and allow_null:
            continue
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"figures.{key}={value!r}: must be a positive integer"
                             + (" (or null: the render size)" if allow_null else ""))


def noise_floor_note(path, estimated: float, hint: float | None) -> str | None:
    """A clear word when the input holds less noise than the job can tell from its surface: the job
    still runs (and smooths what it sees), but there is nothing to remove. None otherwise."""
    if hint is not None or estimated >= NOISE_FLOOR:
        return None
    note = (f"the estimated noise ({100 * estimated:.2g}% of the bbox diagonal) is below what the job can improve "
            f"(a clean surface reads below {100 * NOISE_FLOOR:.2g}%): the input looks noise-free, so the output differs "
            "from it only by the job's smoothing (noise=... sets the level if the estimate is wrong)")
    log.warning("input %s: %s", path, note)
    return note


# ------------------------------------------------------------------------------ the app
def _example_defaults(cfg: DictConfig) -> tuple[str, str | None, str | None, bool]:
    """(input, clean, mesh, is_example): with no input, the shipped example and its ground truth."""
    if cfg.get("input"):
        return str(cfg.input), cfg.get("clean"), cfg.get("mesh"), False
    ex = EXAMPLE_DIR
    missing = [f for f in EXAMPLE_FILES.values() if not (ex / f).is_file()]
    if missing:
        raise FileNotFoundError(f"the shipped example is incomplete: {missing} missing in {ex} "
                                "(regenerate it with python -m experiments.apps.make_example)")
    return (str(ex / EXAMPLE_FILES["input"]), cfg.get("clean") or str(ex / EXAMPLE_FILES["clean"]),
            cfg.get("mesh") or str(ex / EXAMPLE_FILES["mesh"]), True)


def run(cfg: DictConfig) -> dict:
    """Denoise ``cfg.input`` (see the module docstring); returns the metrics dict."""
    from dss.pipeline import estimate_noise_level
    from dss.pointcloud import PointCloud, save_ply

    t_start, c_start = time.perf_counter(), time.process_time()
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    out = run_dir(cfg)
    input_path, clean_path, mesh_path, is_example = _example_defaults(cfg)
    # Everything that can be refused is checked before any work or any output file: settings,
    # the outputs (claimed: writable, not another run's), the input, the model.
    check_wandb(cfg.get("wandb"))
    dev = resolve_device(cfg.get("device"))
    hint = noise_hint(cfg.get("noise"))
    check_figures(cfg.get("figures"))
    claim_run_dir(out, ARTEFACTS, bool(cfg.get("overwrite", False)))
    output = resolve_output(cfg, out, "denoised.ply")
    clock = StageClock()  # where the job's time goes: metrics.json profile_s and the log
    with clock("load"):
        cloud, input_report = load_input(input_path, cfg.get("nan_policy", "drop"), int(cfg.normals.k),
                                         bool(cfg.normals.recompute))
    with clock("reference_setup"):
        generator, model_note = make_reference(cfg, None) if _explicit_model(cfg) else (None, None)
    kernel_build = prepare_kernels(dev)
    cloud_in = cloud  # the input as given: scored and drawn as "noisy input"
    with clock("outliers"):
        cloud, outlier_report, removed = remove_outliers(
            cloud, cfg.get("outliers", {}), None if input_report["normals"] == "from file" else int(cfg.normals.k))
    with clock("noise_estimate"):
        estimated = estimate_noise_level(cloud.points)
    noise = hint if hint is not None else estimated
    noise_note = noise_floor_note(input_path, estimated, hint)
    if generator is None:
        with clock("reference_setup"):
            generator, model_note = make_reference(cfg, noise)
    if generator.noise_level and not 0.5 < noise / generator.noise_level < 2.0:
        log.warning("the denoiser was trained for noise %.3g but this cloud's noise is %s %.3g: results may be poor",
                    generator.noise_level, "given as" if hint is not None else "estimated at", noise)
    by_noise = resolve_all_by_noise(cfg, noise, len(cloud))
    budget_note = resolve_budget(cfg, len(cloud), by_noise["cycles"], by_noise["lr_points"])
    spec, spec_source, shading, shading_name = resolve_channel(cfg, generator, budget_note)
    fusion_config(cfg, shading)  # a bad fusion block is refused before any work
    # settings resolved: the point count they need is known before any optimisation
    optimizer_config(cfg.optimizer, cfg.views, cfg.seed).check_points(len(cloud), f"input {input_path}")
    with clock("ground_truth"):
        clean, mesh, gt_note = load_ground_truth(clean_path, mesh_path, len(cloud_in), int(cfg.seed), cloud.offset)
    if generator.name == "oracle" and clean is None:
        raise ValueError("reference=oracle renders the ground truth: give clean= or mesh=")
    save_config(cfg, out)
    log.info("denoising %s (%d points, noise %s %.4g) with %s at %s px", input_path, len(cloud),
             "hint" if hint is not None else "estimated", noise, generator.describe(), list(spec.image_size))

    t0, c0 = time.perf_counter(), time.process_time()
    pts, nrm, history, ref, norm, ocfg = run_refinement(cfg, cloud.points, cloud.normals, generator, spec,
                                                        f"dss-denoise ({generator.name})", shading=shading,
                                                        noise=noise, clean=clean, mesh=mesh)
    t_opt = time.perf_counter() - t0
    clock.add("optimization", t_opt, time.process_time() - c0)
    nrm_opt = nrm
    mode = str(cfg.normals.get("output", "auto"))
    if mode == "auto":  # the plane fusion's normals (the references' where they agree), else PCA
        mode = "optimized" if "fusion" in history else "pca"
    with clock("write"):
        nrm = output_normals(pts, nrm_opt, mode, int(cfg.normals.k))
        # never replaces a file that appeared meanwhile (overwrite=false): the result then goes beside it
        # in the input's frame and precision: a cloud centred on load gets its offset back, doubles stay doubles
        output = save_ply(output, PointCloud(pts, nrm, offset=cloud.offset, stored_as=cloud.stored_as), exclusive=not cfg.get("overwrite", False))
        if removed is not None:
            outlier_report["file"] = str(save_ply(out / "outliers.ply", removed))

    protocols = list(cfg.metrics.protocols)
    t_metrics, c_metrics = time.perf_counter(), time.process_time()
    m_in = score(cloud_in.points.numpy(), clean, mesh, protocols)
    m_out = score(pts.numpy(), clean, mesh, protocols)
    normal_error = None
    if mesh is not None:  # degrees to the closest ground-truth triangle's normal (input frame)
        from dss.metrics import mesh_normals_at, normal_error_deg

        at_out = mesh_normals_at(pts.numpy(), mesh)  # three normal sets on the same points
        normal_error = {"input_pca": normal_error_deg(cloud_in.points.numpy(), cloud_in.normals.numpy(), mesh),
                        "optimized": normal_error_deg(pts.numpy(), nrm_opt.numpy(), mesh, at_out),
                        # a PCA fit on the same denoised points: what the images' normals must beat
                        "pca": normal_error_deg(pts.numpy(), output_normals(pts, nrm_opt, "pca",
                                                                             int(cfg.normals.k)).numpy(), mesh, at_out),
                        "output": normal_error_deg(pts.numpy(), nrm.numpy(), mesh, at_out)}
    clock.add("metrics", time.perf_counter() - t_metrics, time.process_time() - c_metrics)
    floor = None
    if mesh is not None and cfg.metrics.get("floor", True):
        from dss.metrics import chamfer_floors

        with clock("chamfer_floor"):
            floors = chamfer_floors(mesh, len(cloud_in), int(cfg.seed), protocols, with_mesh=True)
            floor = {pr: r.to_dict() for pr, r in floors.items()}

    figures = []
    if (cfg.get("figures") or {}).get("enabled", True):
        with clock("figures"):
            rows = [(cloud_in.points, cloud_in.normals), (pts, nrm)]
            labels = ["noisy input", f"denoised ({generator.name})"]
            if clean is not None:
                from dss.pointcloud import estimate_normals

                cp = torch.from_numpy(np.asarray(clean, np.float32))
                rows.append((cp, estimate_normals(cp, k=int(cfg.normals.k))))
                labels.append("clean (ground truth)")
            title = f"dss-denoise {Path(input_path).name}, reference {generator.name}"
            figures = write_figures(out, cfg, spec, rows, labels, ref, history, ocfg, title, norm, shading=shading)

    metrics = {
        "input": input_report,
        "example": is_example,
        "output": str(output),
        "ground_truth": {"clean": clean_path, "mesh": mesh_path, "note": gt_note},
        "outliers": outlier_report,
        "noise": {"hint": hint, "estimated": estimated, "used": noise, "note": noise_note},
        **by_noise,  # cycles, projection_weight, reg_cutoff, reg_dilation: the value used and why
        "budget": budget_note,
        "reference": {**generator.describe(), "selection": model_note},
        "render": {"source": spec_source, "image_size": list(spec.image_size), "shading": shading_name,
                   "spec": spec.to_dict()},
        "fusion": history.get("fusion"),
        "normals_output": mode,
        **optimization_report(history, t_start, t_opt, kernel_build),
        # seconds per stage of the job; "optimization" split into the loop's parts and the
        # stages after it (host-side wall time)
        "profile_s": {**clock.seconds, "optimization_parts": history.get("profile_s", {})},
        # the same in process CPU seconds: with threads=1 what the stages take on an idle machine
        "profile_cpu_s": {**clock.cpu_seconds, "optimization_parts": history.get("profile_cpu_s", {})},
        "metrics_input": m_in,
        "metrics_output": m_out,
        "chamfer_floor": floor,
        "normal_error_deg": normal_error,
        "summary": {"input": short_metrics(m_in), "output": short_metrics(m_out)},
        "figures": figures,
    }
    metrics["time_s"]["cpu_total"] = time.process_time() - c_start  # kernel build included
    save_metrics(metrics, out)
    log.info("time per stage: %s", clock.summary(metrics["time_s"]["total"]))
    log.info("optimisation: %s", ", ".join(f"{k} {v:.2f} s" for k, v in history.get("profile_s", {}).items()))
    _log_summary(metrics)
    log_run(cfg, out, metrics, history, figures)
    release_claims()
    return metrics


def _log_summary(metrics: dict) -> None:
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


@hydra.main(version_base="1.3", config_path="../../conf", config_name="denoise")
@guarded
def _main(cfg: DictConfig) -> None:
    m = run(cfg)
    s = m["summary"]
    if s["output"]:
        for pr in s["output"]:
            print(f"[{pr} protocol] Chamfer x1e4: input {s['input'][pr]['chamfer']:.3f} -> "
                  f"denoised {s['output'][pr]['chamfer']:.3f}")
    print(f"denoised cloud: {m['output']} ({m['time_s']['total']:.0f} s)")


def main() -> None:
    positional_to_override("input")
    run_app(_main)


if __name__ == "__main__":
    main()
