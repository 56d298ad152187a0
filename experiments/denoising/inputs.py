"""The job's inputs: which files, the noisy cloud (normals, NaN rows, outliers), its noise level,
the ground truth, the output path (the *prepare* stage of :mod:`experiments.denoising.job`)."""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from experiments.common import claim_output

log = logging.getLogger(__name__)

__all__ = ["EXAMPLE_DIR", "EXAMPLE_FILES", "InputFiles", "NoiseLevel", "NOISE_FLOOR", "input_files",
           "resolve_output", "load_input", "outlier_params", "remove_outliers", "load_ground_truth",
           "noise_hint", "noise_floor_note", "noise_level"]

EXAMPLE_DIR = Path(__file__).resolve().parents[1] / "assets" / "example"
EXAMPLE_FILES = {"input": "noisy_1pct.ply", "clean": "clean.ply", "mesh": "mesh.ply"}
OUTLIER_KEYS = ("k", "z_threshold", "ratio_threshold", "iterations")
#: the noise estimator reads a clean surface as less than this (dss.pipeline.estimate_noise_level):
#: an input estimated below it holds no noise the job can tell apart from its surface
NOISE_FLOOR = 0.001


@dataclass(frozen=True)
class InputFiles:
    """The job's files: the noisy cloud and the optional ground truth (paths as given)."""

    input: str
    clean: str | None
    mesh: str | None
    is_example: bool


@dataclass(frozen=True)
class NoiseLevel:
    """The noise level (std, fraction of the bbox diagonal): the hint, the estimate, the one used."""

    hint: float | None
    estimated: float
    used: float
    note: str | None
    estimator: str = "quadric"

    def to_dict(self) -> dict:
        return {"hint": self.hint, "estimated": self.estimated, "used": self.used, "note": self.note,
                "estimator": self.estimator}


def input_files(cfg: DictConfig) -> InputFiles:
    """``cfg.input`` and its ground truth; with no input, the shipped example and its ground truth."""
    if cfg.get("input"):
        return InputFiles(str(cfg.input), cfg.get("clean"), cfg.get("mesh"), False)
    ex = EXAMPLE_DIR
    missing = [f for f in EXAMPLE_FILES.values() if not (ex / f).is_file()]
    if missing:
        raise FileNotFoundError(f"the shipped example is incomplete: {missing} missing in {ex} "
                                "(regenerate it with python -m experiments.apps.make_example)")
    return InputFiles(str(ex / EXAMPLE_FILES["input"]), cfg.get("clean") or str(ex / EXAMPLE_FILES["clean"]),
                      cfg.get("mesh") or str(ex / EXAMPLE_FILES["mesh"]), True)


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


def noise_level(points, hint: float | None, path, estimator: str = "quadric") -> NoiseLevel:
    """The cloud's noise level (:func:`dss.pipeline.estimate_noise_level` with ``method=estimator``;
    the ``hint`` when given) and a note when the input looks noise-free (:func:`noise_floor_note`)."""
    from dss.pipeline import estimate_noise_level

    estimated = estimate_noise_level(points, method=estimator)
    used = hint if hint is not None else estimated
    return NoiseLevel(hint, estimated, used, noise_floor_note(path, estimated, hint), estimator)
