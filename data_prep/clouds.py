"""Writing a ``dss-clouds/1`` dataset: the clean clouds of the generated shapes, for training with
pairs rendered on the fly (``experiments.onthefly``) instead of stored image shards.

Layout: ``<root>/manifest.json`` plus ``<root>/<split>/<shape_id>.npz`` with ``points`` (N, 3)
float32 (the Poisson-disk samples, in the shape's unit-diagonal frame) and ``mesh_normals``
(N, 3) float16 (the normals of the triangles they lie on: the sign of the PCA normals, as
``dss-prep`` orients them). The noisy clouds, their normals and the views are drawn when the
pairs are rendered, fresh for every epoch. The shapes, seeds and the split by shape are those of
the image datasets of the same config (:func:`data_prep.shards.build_plan`), so a cloud dataset
and a shard dataset of one preset hold the same shapes in the same splits.

About 18 bytes a point: 20K-point shapes take ~0.36 MB each, the ``cpu`` preset's 360 shapes
~130 MB (its 256 px planes shards: ~9.8 GB). Files are written atomically and skipped when a
re-run finds them complete (their hash is in the manifest, written last).
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path

import numpy as np

from .render_spec import RenderSpec
from .shards import PrepConfig, build_plan, manifest_header, npz_bytes

log = logging.getLogger(__name__)

__all__ = ["CLOUDS_FORMAT", "generate_clouds", "read_clouds_manifest", "load_cloud"]

CLOUDS_FORMAT = "dss-clouds/1"


def _cloud_arrays(shape, pc: PrepConfig) -> list[tuple[str, np.ndarray]]:
    from .sampling import poisson_disk
    from .shards import shape_mesh

    mesh = shape_mesh(shape, pc)
    sample = poisson_disk(mesh, pc.num_points, shape.seed, pc.init_factor)
    return [("points", np.ascontiguousarray(sample.points, np.float32)),
            ("mesh_normals", np.ascontiguousarray(sample.normals, np.float16))]


def generate_clouds(pc: PrepConfig, spec: RenderSpec, out_dir, overwrite: bool = False, progress: bool = True) -> dict:
    """Write (or finish) the cloud dataset of ``pc`` into ``out_dir``; returns run statistics
    (``shapes_written``, ``shapes_skipped``, ``bytes``, ``wall_s``, ``manifest``)."""
    import torch
    from tqdm.auto import tqdm

    from dss.io_utils import atomic_write_bytes, atomic_write_text

    root = Path(out_dir)
    root.mkdir(parents=True, exist_ok=True)
    plan = build_plan(pc, spec)
    manifest_path = root / "manifest.json"
    if manifest_path.exists() and not overwrite:
        old = json.loads(manifest_path.read_text())
        if old.get("fingerprint") != plan.fingerprint or old.get("format") != CLOUDS_FORMAT:
            from .shards import DatasetConflictError

            raise DatasetConflictError(f"{manifest_path}: a dataset made with another configuration is there; "
                                       "use another out_dir or overwrite=true")
    t0 = time.perf_counter()
    stats = {"shapes_written": 0, "shapes_skipped": 0, "bytes": 0}
    shapes = []
    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for shape in tqdm(plan.shapes, unit="shape", desc="dss-prep clouds", disable=not progress):
            rel = f"{shape.split}/{shape.shape_id}.npz"
            path = root / rel
            if path.is_file() and not overwrite:
                data = path.read_bytes()
                stats["shapes_skipped"] += 1
            else:
                data = npz_bytes(_cloud_arrays(shape, pc))
                path.parent.mkdir(parents=True, exist_ok=True)
                atomic_write_bytes(path, data)
                stats["shapes_written"] += 1
            stats["bytes"] += len(data)
            shapes.append({"shape_id": shape.shape_id, "family": shape.family, "seed": shape.seed,
                           "split": shape.split, "file": rel, "sha256": hashlib.sha256(data).hexdigest(),
                           **({"mesh": shape.mesh} if shape.mesh else {})})
    finally:
        torch.set_num_threads(prev)
    manifest = {
        **manifest_header(plan, CLOUDS_FORMAT),
        "splits": {sp: sum(1 for s in shapes if s["split"] == sp) for sp in ("train", "val", "test")},
        "shapes": shapes,
    }
    atomic_write_text(manifest_path, json.dumps(manifest, indent=1) + "\n")
    stats.update(wall_s=time.perf_counter() - t0, manifest=str(manifest_path), complete=True,
                 shapes_total=len(shapes))
    log.info("dss-prep clouds: %d shapes (%d written, %d kept), %.1f MB -> %s", len(shapes), stats["shapes_written"],
             stats["shapes_skipped"], stats["bytes"] / 1e6, root)
    return stats


def read_format_manifest(root, fmt: str, missing: str) -> dict:
    """``<root>/manifest.json`` of a dataset whose ``format`` must be ``fmt``: FileNotFoundError
    (``"<path>: <missing>"``) when there is none, ValueError when it is another format."""
    path = Path(root) / "manifest.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {missing}")
    m = json.loads(path.read_text())
    if m.get("format") != fmt:
        raise ValueError(f"{path}: format {m.get('format')!r}, expected {fmt!r}")
    return m


def read_clouds_manifest(root) -> dict:
    """The manifest of a ``dss-clouds/1`` dataset (ValueError when it is not one)."""
    return read_format_manifest(root, CLOUDS_FORMAT, "no manifest (make the dataset with dss-prep output=clouds)")


def load_cloud(root, entry: dict) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) float32, mesh normals (N, 3) float32) of a manifest's shape entry."""
    with np.load(Path(root) / entry["file"]) as z:
        return np.asarray(z["points"], np.float32), np.asarray(z["mesh_normals"], np.float32)
