"""Writing a ``dss-pairs/1`` dataset: plan, shards, completion markers, manifest.

Format (data_prep/README.md, "Dataset formats"): ``<root>/manifest.json`` plus
``<root>/<split>/shard-XXXXX.npz`` (uncompressed; ``noisy``/``clean`` (n,H,W,3) float16, ``mask``
(n,H,W) bool, ``pair_id`` (n,) int64).

Properties:

- **Deterministic.** The whole plan (shapes, seeds, splits, cameras, shard layout, pair ids) is a
  pure function of the config and seed, and every shard is computed by one single-threaded
  process from its own seeds, so the same config gives the same bytes whatever the number of
  workers or the order in which shards finish. The zip container is written with fixed
  timestamps and a fixed member order (:func:`npz_bytes`).
- **Resumable.** A shard is written to a temp file and renamed; only then is its completion
  marker ``shard-XXXXX.done.json`` (sha256, size, config fingerprint) written. A shard counts as
  done only if its marker matches the config and the file's hash matches the marker, so a
  half-written or corrupted shard is never taken for a whole one; a re-run skips done shards.
  The manifest is written last, once every shard is done.
- **Parallel.** Work units ("tasks") are groups of ``shapes_per_shard`` shapes of one split; a
  task writes one shard per noise level (the clean cloud and its renders are shared by the
  levels). Tasks run in a process pool (spawn; one torch/OpenMP thread per worker). A cluster
  job can take a slice of the tasks (``part_index`` of ``part_count``, Hydra multirun axis).
- **Split by shape.** Every view of a shape lands in the same split.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import time
import zipfile
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .render_spec import RenderSpec, View
from .sampling import SamplingError, validate_sampling
from .shapes import UnknownFamilyError, resolve_families

log = logging.getLogger(__name__)

__all__ = [
    "FORMAT",
    "GENERATOR_VERSION",
    "PrepConfig",
    "PrepConfigError",
    "DatasetConflictError",
    "Plan",
    "build_plan",
    "npz_bytes",
    "generate_dataset",
    "shard_is_done",
    "shape_mesh",
    "shape_noise",
    "nominal_noise",
    "real_mesh_names",
    "REAL_FAMILY",
    "TRAINABLE_REAL_GROUPS",
]

FORMAT = "dss-pairs/1"
#: Bump when a change in data_prep changes the generated data (it is part of the fingerprint).
GENERATOR_VERSION = 1
SPLITS = ("train", "val", "test")


class PrepConfigError(ValueError):
    """An invalid dss-prep configuration (the message names the key)."""


class DatasetConflictError(RuntimeError):
    """The output folder holds a dataset made with another configuration."""


# ----------------------------------------------------------------------------- configuration

@dataclass(frozen=True)
class PrepConfig:
    """What to generate (everything that determines the bytes of the dataset)."""

    seed: int = 0
    families: tuple[str, ...] = ("all",)
    shapes_per_family: int = 8
    resolution: int = 96
    val_fraction: float = 0.1
    test_fraction: float = 0.1
    num_points: int = 20000
    init_factor: float = 5.0
    normals_k: int = 16
    normals_orient: str = "mesh"
    noise_levels: tuple[float, ...] = (0.003, 0.01)
    views_per_shape: int = 16
    shapes_per_shard: int = 4
    #: groups of data_prep/real_split.yaml whose meshes join the generated shapes (only
    #: TRAINABLE_REAL_GROUPS: the held-out and open shapes are never rendered for training)
    real_groups: tuple[str, ...] = ()
    #: Poisson-disk samplings per real mesh (each its own seed; all in the mesh's split)
    real_repeats: int = 1
    #: where ``dss-data real`` installed them (relative: the repository root); not part of the data
    real_root: str = "data/real"
    #: (lo, hi): each shape's noise std drawn log-uniformly from this range (fractions of the
    #: bbox diagonal) instead of one shard set per ``noise_levels`` entry; the shards hold one
    #: slot whose nominal level is the range's geometric mean
    noise_range: tuple[float, float] | None = None

    def __post_init__(self):
        if self.noise_range is not None:
            lo, hi = (float(x) for x in self.noise_range)
            if not (0 < lo < hi and np.isfinite(hi)):
                raise PrepConfigError(f"noise_range must be [lo, hi] with 0 < lo < hi, got {list(self.noise_range)}")
            object.__setattr__(self, "noise_range", (lo, hi))
            object.__setattr__(self, "noise_levels", (nominal_noise(lo, hi),))
        object.__setattr__(self, "real_groups", tuple(str(g) for g in self.real_groups))
        bad = [g for g in self.real_groups if g not in TRAINABLE_REAL_GROUPS]
        if bad:
            raise PrepConfigError(f"shapes.real.groups: {bad} may not be rendered for training (held-out and open "
                                  f"shapes are for evaluation only); allowed: {list(TRAINABLE_REAL_GROUPS)}")
        if int(self.real_repeats) < 1:
            raise PrepConfigError(f"shapes.real.repeats must be >= 1, got {self.real_repeats}")
        try:
            fams = tuple(resolve_families(list(self.families)))
        except UnknownFamilyError as e:
            raise PrepConfigError(f"shapes.families: {e}") from e
        object.__setattr__(self, "families", fams)
        object.__setattr__(self, "noise_levels", tuple(float(x) for x in self.noise_levels))
        if self.shapes_per_family <= 0:
            raise PrepConfigError(f"shapes.per_family must be > 0, got {self.shapes_per_family}")
        if self.resolution < 16:
            raise PrepConfigError(f"shapes.resolution must be >= 16, got {self.resolution}")
        for name, v in (("splits.val", self.val_fraction), ("splits.test", self.test_fraction)):
            if not 0 <= v < 1:
                raise PrepConfigError(f"{name} must be in [0, 1), got {v}")
        if self.val_fraction + self.test_fraction >= 1:
            raise PrepConfigError("splits.val + splits.test must leave shapes for training (< 1)")
        if self.views_per_shape <= 0:
            raise PrepConfigError(f"views_per_shape must be > 0, got {self.views_per_shape}")
        if self.shapes_per_shard <= 0:
            raise PrepConfigError(f"shapes_per_shard must be > 0, got {self.shapes_per_shard}")
        if self.normals_orient not in ("mesh", "consistent", "outward", "none"):
            raise PrepConfigError(
                f"sampling.normals_orient must be mesh|consistent|outward|none, got {self.normals_orient!r}")
        try:
            validate_sampling(self.num_points, self.noise_levels, self.normals_k, self.init_factor)
        except SamplingError as e:
            raise PrepConfigError(str(e)) from e

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> PrepConfig:
        """From the ``dss-prep`` config (keys ``seed``, ``shapes``, ``splits``, ``sampling``,
        ``noise_levels``, ``views_per_shape``, ``shapes_per_shard``)."""
        cfg = _plain(cfg)
        shapes = cfg.get("shapes", {}) or {}
        splits = cfg.get("splits", {}) or {}
        sampling = cfg.get("sampling", {}) or {}
        for name, block, keys in (("shapes", shapes, {"families", "per_family", "resolution", "real"}),
                                  ("splits", splits, {"val", "test"}),
                                  ("sampling", sampling, {"num_points", "init_factor", "normals_k", "normals_orient"})):
            bad = set(block) - keys
            if bad:
                raise PrepConfigError(f"{name}: unknown keys {sorted(bad)}; known: {sorted(keys)}")
        fams = shapes.get("families", ["all"])
        if isinstance(fams, str):
            fams = [fams]
        levels = cfg.get("noise_levels", [0.003, 0.01])
        if isinstance(levels, int | float):
            levels = [levels]
        real = shapes.get("real") or {}
        bad = set(real) - {"groups", "repeats", "root"}
        if bad:
            raise PrepConfigError(f"shapes.real: unknown keys {sorted(bad)}; known: ['groups', 'repeats', 'root']")
        real_groups = real.get("groups") or []
        real_groups = [real_groups] if isinstance(real_groups, str) else list(real_groups)
        noise_range = cfg.get("noise_range")
        if noise_range is not None and (isinstance(noise_range, str) or len(noise_range) != 2):
            raise PrepConfigError(f"noise_range must be [lo, hi], got {noise_range!r}")
        try:
            return cls(
                seed=int(cfg.get("seed", 0)),
                families=tuple(fams),
                shapes_per_family=int(shapes.get("per_family", 8)),
                resolution=int(shapes.get("resolution", 96)),
                val_fraction=float(splits.get("val", 0.1)),
                test_fraction=float(splits.get("test", 0.1)),
                num_points=int(sampling.get("num_points", 20000)),
                init_factor=float(sampling.get("init_factor", 5.0)),
                normals_k=int(sampling.get("normals_k", 16)),
                normals_orient=str(sampling.get("normals_orient", "mesh")),
                noise_levels=tuple(levels),
                views_per_shape=int(cfg.get("views_per_shape", 16)),
                shapes_per_shard=int(cfg.get("shapes_per_shard", 4)),
                real_groups=tuple(real_groups),
                real_repeats=int(real.get("repeats", 1)),
                real_root=str(real.get("root", "data/real")),
                noise_range=None if noise_range is None else tuple(float(x) for x in noise_range),
            )
        except (TypeError, ValueError) as e:
            if isinstance(e, PrepConfigError):
                raise
            raise PrepConfigError(f"invalid dss-prep config: {e}") from e


def _plain(cfg) -> dict:
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            return OmegaConf.to_container(cfg, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    return dict(cfg)


def package_version() -> str:
    try:
        from importlib.metadata import version

        return version("dss-splatting")
    except Exception:  # not installed (running from a checkout)
        return "0.1.0"


#: real_split.yaml groups whose meshes ``dss-prep`` may render for training
TRAINABLE_REAL_GROUPS = ("tuning",)
#: PrepConfig fields that join the fingerprint only when set (datasets made before they existed
#: keep their fingerprint); real_root is a path, never part of it
_OPTIONAL_FIELDS = {"real_groups": (), "real_repeats": 1, "noise_range": None}


def nominal_noise(lo: float, hi: float) -> float:
    """The nominal level of a noise range: its geometric mean (rounded to 6 digits)."""
    return round(float(np.sqrt(float(lo) * float(hi))), 6)


def fingerprint(pc: PrepConfig, spec: RenderSpec) -> str:
    """sha256 of everything that determines the data (not the backend, workers or paths)."""
    prep = asdict(pc)
    prep.pop("real_root")
    for k, default in _OPTIONAL_FIELDS.items():
        if prep[k] == default or (k == "real_groups" and not prep[k]):
            prep.pop(k)
    if "real_groups" in prep:  # the mesh names they hold (data_prep/real_split.yaml)
        prep["real_meshes"] = real_mesh_names(pc)
    blob = json.dumps({"format": FORMAT, "generator_version": GENERATOR_VERSION, "prep": prep,
                       "render": spec.to_dict(include_backend=False)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def real_mesh_names(pc: PrepConfig) -> list[str]:
    """The real meshes of ``pc.real_groups`` (data_prep/real_split.yaml), in the split's order."""
    from .real_meshes import load_split

    groups = load_split()["groups"]
    names = []
    for g in pc.real_groups:
        if g not in groups:
            raise PrepConfigError(f"shapes.real.groups: {g!r} is not a group of data_prep/real_split.yaml")
        names += [n for n in groups[g] if n not in names]
    return names


def shape_noise(pc: PrepConfig, shape: ShapeItem, level: float) -> float:
    """The noise std of ``shape``'s noisy cloud in the shard slot of ``level``: ``level`` itself,
    or with a ``noise_range`` a log-uniform draw from it, seeded by the shape."""
    if pc.noise_range is None:
        return float(level)
    from data_prep.sampling import log_uniform

    return log_uniform(pc.noise_range, np.random.default_rng(_seed_int(shape.seed, 3)).random())


def shape_mesh(shape: ShapeItem, pc: PrepConfig):
    """The mesh of a plan's shape: a generated family's, or an installed real mesh (only of
    :data:`TRAINABLE_REAL_GROUPS`), normalised to a unit bounding-box diagonal."""
    if shape.family == REAL_FAMILY:
        from .real_meshes import load_training_mesh

        return load_training_mesh(shape.mesh, pc.real_root)
    from .shapes import make_shape

    return make_shape(shape.family, shape.seed, pc.resolution)


# ----------------------------------------------------------------------------- plan

#: the family name of the real meshes in a plan (shape ids ``real-<mesh>-<repeat>``)
REAL_FAMILY = "real"


@dataclass
class ShapeItem:
    shape_id: str
    family: str
    index: int
    seed: int
    split: str
    views: list[View]
    mesh: str | None = None  # the real mesh's name (family "real")


@dataclass
class ShardItem:
    path: str  # relative to the dataset root
    split: str
    noise_level: float
    level_index: int
    first_pair_id: int
    num_pairs: int


@dataclass
class Task:
    index: int
    split: str
    shapes: list[ShapeItem]
    shards: list[ShardItem] = field(default_factory=list)  # one per noise level

    @property
    def num_pairs(self) -> int:
        return sum(s.num_pairs for s in self.shards)


@dataclass
class Plan:
    config: PrepConfig
    spec: RenderSpec
    shapes: list[ShapeItem]
    tasks: list[Task]
    fingerprint: str

    @property
    def shards(self) -> list[ShardItem]:
        return [s for t in self.tasks for s in t.shards]

    @property
    def num_pairs(self) -> int:
        return sum(t.num_pairs for t in self.tasks)


def _seed_int(*parts: int) -> int:
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1, dtype=np.uint32)[0])


def _fam_code(family: str) -> int:
    return zlib.crc32(family.encode())


def shape_seed(seed: int, family: str, index: int) -> int:
    return _seed_int(seed, _fam_code(family), index)


def noise_seed(shape_seed_: int, level_index: int) -> int:
    return _seed_int(shape_seed_, 1, level_index)


def build_plan(pc: PrepConfig, spec: RenderSpec) -> Plan:
    """The complete, deterministic layout of the dataset (no meshing or rendering)."""
    # Stratified split by shape: interleave families by their rank in a seeded permutation, then
    # the first n_test shapes go to test, the next n_val to val (every family is represented).
    keyed = []
    for fi, fam in enumerate(pc.families):
        n = pc.shapes_per_family
        perm = np.random.default_rng(_seed_int(pc.seed, _fam_code(fam), 999)).permutation(n)
        rank = np.empty(n, int)
        rank[perm] = np.arange(n)
        for i in range(n):
            keyed.append(((rank[i] + 0.5) / n, fi, fam, i))
    keyed.sort()
    total = len(keyed)

    def count(frac):  # a split asked for gets at least one shape
        k = int(round(frac * total))
        return max(k, 1) if frac > 0 else k

    n_test, n_val = count(pc.test_fraction), count(pc.val_fraction)
    if n_test + n_val >= total:
        raise PrepConfigError(f"{total} shapes are too few for the val/test fractions "
                              f"({pc.val_fraction}, {pc.test_fraction}): no training shape left")
    by_split: dict[str, list[ShapeItem]] = {s: [] for s in SPLITS}
    shapes = []
    for pos, (_, _, fam, i) in enumerate(keyed):
        split = "test" if pos < n_test else "val" if pos < n_test + n_val else "train"
        s = shape_seed(pc.seed, fam, i)
        views = spec.sample_views(pc.views_per_shape, np.random.default_rng(_seed_int(s, 2)))
        item = ShapeItem(f"{fam}-{i:04d}", fam, i, s, split, views)
        by_split[split].append(item)
        shapes.append(item)
    for item in _real_items(pc, spec):
        by_split[item.split].append(item)
        shapes.append(item)
    tasks: list[Task] = []
    pair_id = 0
    L = len(pc.noise_levels)
    for split in SPLITS:
        items = by_split[split]
        for k in range(0, len(items), pc.shapes_per_shard):
            chunk = items[k:k + pc.shapes_per_shard]
            t = Task(len(tasks), split, chunk)
            n = len(chunk) * pc.views_per_shape
            for li, level in enumerate(pc.noise_levels):
                idx = (k // pc.shapes_per_shard) * L + li
                t.shards.append(ShardItem(f"{split}/shard-{idx:05d}.npz", split, level, li, pair_id, n))
                pair_id += n
            tasks.append(t)
    return Plan(pc, spec, shapes, tasks, fingerprint(pc, spec))


def _real_items(pc: PrepConfig, spec: RenderSpec) -> list[ShapeItem]:
    """The real meshes' shapes: split by mesh (all repeats of a mesh in one split), ``val``
    getting ``round(val_fraction x meshes)`` of them (at least one when asked for), the rest
    ``train``; no real mesh goes to ``test`` (the generated test split is what the denoising
    table evaluates, and real held-out meshes are evaluated by dss-real-bench)."""
    if not pc.real_groups:
        return []
    names = real_mesh_names(pc)
    order = np.random.default_rng(_seed_int(pc.seed, _fam_code(REAL_FAMILY), 999)).permutation(len(names))
    n_val = int(round(pc.val_fraction * len(names)))
    n_val = max(n_val, 1) if pc.val_fraction > 0 and len(names) > 1 else n_val
    val = {names[i] for i in order[:n_val]}
    items = []
    for mi, name in enumerate(names):
        for r in range(int(pc.real_repeats)):
            s = shape_seed(pc.seed, f"{REAL_FAMILY}:{name}", r)
            views = spec.sample_views(pc.views_per_shape, np.random.default_rng(_seed_int(s, 2)))
            items.append(ShapeItem(f"{REAL_FAMILY}-{name}-{r}", REAL_FAMILY, mi * int(pc.real_repeats) + r, s,
                                   "val" if name in val else "train", views, mesh=name))
    return items


# ----------------------------------------------------------------------------- bytes on disk

def npz_bytes(arrays: Sequence[tuple[str, np.ndarray]]) -> bytes:
    """An uncompressed ``.npz`` (readable by ``np.load``) with deterministic bytes.

    Like ``np.savez`` (ZIP_STORED, zip64 members), but with the member order given and every
    zip header field fixed (timestamps 1980-01-01, permissions), independent of the Python and
    numpy versions' defaults.
    """
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, arr in arrays:
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_STORED
            info.create_system = 3
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 22), b""):
            h.update(chunk)
    return h.hexdigest()


def marker_path(shard_path: Path) -> Path:
    return shard_path.with_name(shard_path.name[: -len(".npz")] + ".done.json")


def _read_marker(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def shard_is_done(root: Path, shard: ShardItem, fp: str, verify: bool = True) -> dict | None:
    """The shard's completion marker if the shard is complete and valid for ``fp``, else None.

    Raises :class:`DatasetConflictError` if the marker belongs to another configuration.
    """
    path = Path(root) / shard.path
    marker = _read_marker(marker_path(path))
    if marker is None or not path.is_file():
        return None
    if marker.get("fingerprint") != fp:
        raise DatasetConflictError(
            f"{marker_path(path)}: made with another configuration (fingerprint "
            f"{str(marker.get('fingerprint'))[:12]}..., this one {fp[:12]}...); use another out_dir "
            "or overwrite=true")
    if marker.get("num_pairs") != shard.num_pairs or path.stat().st_size != marker.get("bytes"):
        return None
    if verify and _sha256_file(path) != marker.get("sha256"):
        log.warning("%s: content does not match its completion marker; regenerating", path)
        return None
    return marker


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def _publish(path: Path) -> None:
    """Give a finished file the usual permissions (temp files are created 0600)."""
    os.chmod(path, 0o666 & ~_umask())


def _write_shard(root: Path, shard: ShardItem, arrays: list[tuple[str, np.ndarray]], fp: str) -> dict:
    from dss.io_utils import atomic_write_bytes, atomic_write_json

    path = Path(root) / shard.path
    path.parent.mkdir(parents=True, exist_ok=True)
    for stale in path.parent.glob(f".{path.stem}.*.tmp{path.suffix}"):  # left by a killed writer
        stale.unlink(missing_ok=True)
    marker_path(path).unlink(missing_ok=True)  # the old marker must never vouch for new bytes
    data = npz_bytes(arrays)
    sha = hashlib.sha256(data).hexdigest()
    atomic_write_bytes(path, data)
    _publish(path)
    marker = {"sha256": sha, "bytes": len(data), "num_pairs": shard.num_pairs, "noise_level": shard.noise_level,
              "split": shard.split, "fingerprint": fp}
    atomic_write_json(marker_path(path), marker)
    _publish(marker_path(path))
    return marker


# ----------------------------------------------------------------------------- one task

@dataclass
class _Job:
    """Everything a worker needs for one task (picklable)."""

    task: Task
    config: PrepConfig
    spec: RenderSpec
    root: str
    fingerprint: str
    verify: bool
    force: bool
    renderer: Callable | None
    on_shard_written: Callable | None


def _run_task(job: _Job) -> dict:
    """Generate the missing shards of one task. Returns counts and stage timings (seconds)."""
    from .pairs import render_pairs, render_views
    from .sampling import noisy_copy, poisson_disk, with_normals

    pc, spec, root = job.config, job.spec, Path(job.root)
    pending = [s for s in job.task.shards if job.force or shard_is_done(root, s, job.fingerprint, job.verify) is None]
    res = {"task": job.task.index, "written": [], "skipped": len(job.task.shards) - len(pending), "pairs": 0,
           "t_shape": 0.0, "t_sample": 0.0, "t_normals": 0.0, "t_render": 0.0, "t_write": 0.0}
    if not pending:
        return res
    H, W = spec.image_size
    bufs = {s.path: {"noisy": [], "clean": [], "mask": [], "noise_std": []} for s in pending}
    for shape in job.task.shapes:
        t0 = time.perf_counter()
        mesh = shape_mesh(shape, pc)
        t1 = time.perf_counter()
        sample = poisson_disk(mesh, pc.num_points, shape.seed, pc.init_factor)
        clean_pts, mesh_normals = sample.points, sample.normals
        t2 = time.perf_counter()
        clean = with_normals(clean_pts, pc.normals_k, pc.normals_orient, mesh_normals)
        t3 = time.perf_counter()
        clean_render = render_views(clean.points, clean.normals, shape.views, spec, job.renderer)
        res["t_shape"] += t1 - t0
        res["t_sample"] += t2 - t1
        res["t_normals"] += t3 - t2
        res["t_render"] += time.perf_counter() - t3
        for s in pending:
            t0 = time.perf_counter()
            std = shape_noise(pc, shape, s.noise_level)
            noisy_pts = noisy_copy(clean_pts, std, noise_seed(shape.seed, s.level_index))
            t1 = time.perf_counter()
            noisy = with_normals(noisy_pts, pc.normals_k, pc.normals_orient, mesh_normals)
            t2 = time.perf_counter()
            pr = render_pairs(clean.points, clean.normals, noisy.points, noisy.normals, shape.views, spec,
                              job.renderer, clean_render=clean_render)
            res["t_sample"] += t1 - t0
            res["t_normals"] += t2 - t1
            res["t_render"] += time.perf_counter() - t2
            b = bufs[s.path]
            b["noisy"].append(pr["noisy"].astype(np.float16))
            b["clean"].append(pr["clean"].astype(np.float16))
            b["mask"].append(pr["mask"])
            b["noise_std"].append(np.full(len(shape.views), std, np.float32))
    for s in pending:
        t0 = time.perf_counter()
        b = bufs.pop(s.path)
        arrays = [("noisy", np.concatenate(b["noisy"])), ("clean", np.concatenate(b["clean"])),
                  ("mask", np.concatenate(b["mask"])),
                  ("pair_id", np.arange(s.first_pair_id, s.first_pair_id + s.num_pairs, dtype=np.int64))]
        if pc.noise_range is not None:  # each shape's own draw (the slot's level is nominal)
            arrays.append(("noise_std", np.concatenate(b["noise_std"])))
        if arrays[0][1].shape != (s.num_pairs, H, W, 3):  # a renderer that ignored the spec
            raise RuntimeError(f"{s.path}: got images {arrays[0][1].shape}, expected ({s.num_pairs}, {H}, {W}, 3)")
        _write_shard(root, s, arrays, job.fingerprint)
        res["t_write"] += time.perf_counter() - t0
        res["written"].append(s.path)
        res["pairs"] += s.num_pairs
        if job.on_shard_written is not None:
            job.on_shard_written(s.path)
    return res


def _worker_init():
    import torch

    torch.set_num_threads(1)


# ----------------------------------------------------------------------------- manifest

def manifest_header(plan: Plan, fmt: str, versions: Mapping[str, Any] = (), config_extra: Mapping[str, Any] = ()) -> dict:
    """The keys every dataset manifest of ``plan`` starts with (``dss-pairs/1`` here,
    ``dss-clouds/1`` in :mod:`data_prep.clouds`): format, versions, render setting, seed,
    fingerprint and the config the shapes came from. ``versions`` follow ``package_version``,
    ``config_extra`` the config's ``views_per_shape``."""
    pc, spec = plan.config, plan.spec
    return {
        "format": fmt,
        "package_version": package_version(),
        **dict(versions),
        "image_size": list(spec.image_size),
        "channels": 3,
        "noise_levels": list(pc.noise_levels),
        "render": spec.to_dict(include_backend=False),
        "seed": pc.seed,
        "fingerprint": plan.fingerprint,
        "config": {"families": list(pc.families), "shapes_per_family": pc.shapes_per_family,
                   "resolution": pc.resolution, "num_points": pc.num_points, "init_factor": pc.init_factor,
                   "normals_k": pc.normals_k, "normals_orient": pc.normals_orient,
                   "views_per_shape": pc.views_per_shape, **dict(config_extra),
                   "splits": {"val": pc.val_fraction, "test": pc.test_fraction},
                   **({"real": {"groups": list(pc.real_groups), "repeats": pc.real_repeats,
                                "meshes": real_mesh_names(pc)}} if pc.real_groups else {})},
        **({"noise_range": list(pc.noise_range)} if pc.noise_range is not None else {}),
    }


def build_manifest(plan: Plan, markers: Mapping[str, dict]) -> dict:
    pc, spec = plan.config, plan.spec
    shards, pairs = [], []
    focal = spec.focal
    for task in plan.tasks:
        for s in task.shards:
            shards.append({"path": s.path, "split": s.split, "num_pairs": s.num_pairs,
                           "sha256": markers[s.path]["sha256"], "noise_level": s.noise_level})
            pid = s.first_pair_id
            for shape in task.shapes:
                for vi, view in enumerate(shape.views):
                    pairs.append({"pair_id": pid, "shape_id": shape.shape_id, "family": shape.family,
                                  "seed": shape.seed, "noise_level": s.noise_level, "split": s.split,
                                  "shard": s.path, "index": pid - s.first_pair_id, "view": vi,
                                  "camera": view.to_dict(focal),
                                  **({"noise_std": shape_noise(pc, shape, s.noise_level)}
                                     if pc.noise_range is not None else {})})
                    pid += 1
    split_stats = {sp: {"shapes": sum(1 for x in plan.shapes if x.split == sp),
                        "pairs": sum(s.num_pairs for s in plan.shards if s.split == sp)} for sp in SPLITS}
    return {
        **manifest_header(plan, FORMAT, {"generator_version": GENERATOR_VERSION},
                          {"shapes_per_shard": pc.shapes_per_shard}),
        "splits": split_stats,
        "num_pairs": plan.num_pairs,
        "shapes": [{"shape_id": x.shape_id, "family": x.family, "seed": x.seed, "split": x.split,
                    **({"mesh": x.mesh} if x.mesh else {})} for x in plan.shapes],
        "shards": shards,
        "pairs": pairs,
    }


def _manifest_text(manifest: dict) -> str:
    compact = len(manifest["pairs"]) > 20000  # the paper-size manifest stays ~tens of MB
    return json.dumps(manifest, indent=None if compact else 1) + "\n"


# ----------------------------------------------------------------------------- driver

def generate_dataset(pc: PrepConfig, spec: RenderSpec, out_dir: str | os.PathLike, workers: int = 1,
                     part_index: int = 0, part_count: int = 1, renderer: Callable | None = None,
                     on_shard_written: Callable[[str], None] | None = None, overwrite: bool = False,
                     verify_existing: bool = True, write_manifest: bool = True, progress: bool = True) -> dict:
    """Generate (or finish) the dataset in ``out_dir``; returns run statistics.

    Args:
        workers: processes (1: run in this process).
        part_index, part_count: this job does the tasks ``i`` with ``i * part_count // n_tasks
            == part_index`` (contiguous slices; for cluster multiruns).
        renderer: a :data:`data_prep.pairs.Renderer` (default: the DSS renderer); must be
            picklable (a module-level function) when ``workers > 1``.
        on_shard_written: called with each shard's relative path right after it is complete
            (in the process that wrote it).
        overwrite: regenerate every shard of this part even if complete, and accept a folder
            made with another configuration.
        verify_existing: re-hash finished shards before skipping them.
        write_manifest: write ``manifest.json`` when all shards (of all parts) are done.

    Returns:
        dict with ``pairs_total``, ``pairs_written``, ``shards_written``, ``shards_skipped``,
        ``wall_s``, ``pairs_per_s`` (written pairs / wall time), summed stage times, ``manifest``
        (path or None) and ``complete``.
    """
    import torch
    from tqdm.auto import tqdm

    if not 0 <= part_index < part_count:
        raise PrepConfigError(f"parts.index must be in [0, parts.count), got {part_index} of {part_count}")
    if workers < 1:
        raise PrepConfigError(f"workers must be >= 1, got {workers}")
    root = Path(out_dir)
    root.mkdir(parents=True, exist_ok=True)
    plan = build_plan(pc, spec)
    manifest_path = root / "manifest.json"
    if manifest_path.exists():
        old = _read_marker(manifest_path) or {}
        if old.get("fingerprint") != plan.fingerprint and not overwrite:
            raise DatasetConflictError(f"{manifest_path}: a dataset made with another configuration is there; "
                                       "use another out_dir or overwrite=true")
        if overwrite:
            manifest_path.unlink()
    n_tasks = len(plan.tasks)
    mine = [t for t in plan.tasks if t.index * part_count // n_tasks == part_index]
    t_start = time.perf_counter()
    stats = {"pairs_total": plan.num_pairs, "pairs_part": sum(t.num_pairs for t in mine), "pairs_written": 0,
             "shards_written": 0, "shards_skipped": 0, "t_shape": 0.0, "t_sample": 0.0, "t_normals": 0.0,
             "t_render": 0.0, "t_write": 0.0}
    if not overwrite:  # refuse early (in this process) to mix with another configuration's shards
        for t in mine:
            for s in t.shards:
                shard_is_done(root, s, plan.fingerprint, verify=False)
    jobs = [_Job(t, pc, spec, str(root), plan.fingerprint, verify_existing, overwrite, renderer, on_shard_written)
            for t in mine]
    log.info("dss-prep: %d shapes, %d pairs in %d shards (%d tasks; this part: %d tasks) -> %s",
             len(plan.shapes), plan.num_pairs, len(plan.shards), n_tasks, len(mine), root)
    bar = tqdm(total=stats["pairs_part"], unit="pair", desc="dss-prep", disable=not progress, smoothing=0.05)

    def collect(r):
        stats["pairs_written"] += r["pairs"]
        stats["shards_written"] += len(r["written"])
        stats["shards_skipped"] += r["skipped"]
        for k in ("t_shape", "t_sample", "t_normals", "t_render", "t_write"):
            stats[k] += r[k]
        bar.update(plan.tasks[r["task"]].num_pairs)

    try:
        if workers == 1 or len(jobs) <= 1:
            prev = torch.get_num_threads()
            torch.set_num_threads(1)  # same arithmetic as in the pool workers
            try:
                for j in jobs:
                    collect(_run_task(j))
            finally:
                torch.set_num_threads(prev)
        else:
            import multiprocessing as mp

            saved = {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
            os.environ.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")  # inherited by the workers
            try:
                ctx = mp.get_context("spawn")
                with ctx.Pool(min(workers, len(jobs)), initializer=_worker_init) as pool:
                    for r in pool.imap_unordered(_run_task, jobs, chunksize=1):
                        collect(r)
            finally:
                for k, v in saved.items():
                    if v is None:
                        os.environ.pop(k, None)
                    else:
                        os.environ[k] = v
    finally:
        bar.close()
    wall = time.perf_counter() - t_start
    stats["wall_s"] = wall
    stats["pairs_per_s"] = stats["pairs_written"] / wall if wall > 0 and stats["pairs_written"] else 0.0
    # manifest: only once every shard of every part is complete
    markers = {}
    for s in plan.shards:
        m = shard_is_done(root, s, plan.fingerprint, verify=False)
        if m is None:
            break
        markers[s.path] = m
    complete = len(markers) == len(plan.shards)
    stats["complete"] = complete
    stats["manifest"] = None
    if complete and write_manifest:
        from dss.io_utils import atomic_write_text

        atomic_write_text(manifest_path, _manifest_text(build_manifest(plan, markers)))
        _publish(manifest_path)
        stats["manifest"] = str(manifest_path)
    elif not complete:
        log.info("dss-prep: %d of %d shards done; the manifest is written when all parts have finished",
                 sum(1 for s in plan.shards if (root / s.path).exists()), len(plan.shards))
    log.info("dss-prep: wrote %d pairs (%d shards, %d skipped) in %.1f s: %.2f pairs/s",
             stats["pairs_written"], stats["shards_written"], stats["shards_skipped"], wall, stats["pairs_per_s"])
    return stats
