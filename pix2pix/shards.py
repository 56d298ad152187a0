"""Reading the training-pair dataset format ``dss-pairs/1`` (written by :mod:`data_prep.shards`;
data_prep/README.md, "Dataset formats").

A dataset is ``<root>/manifest.json`` plus uncompressed ``.npz`` shards holding ``noisy`` and
``clean`` (n, H, W, 3) float16 renders, ``mask`` (n, H, W) bool and ``pair_id`` (n,) int64.

Shards are opened as **memory maps** (:func:`open_shard`): an uncompressed ``.npz`` is a zip
archive of ``.npy`` files stored verbatim, so each array can be mapped at its byte offset and
only the rows a reader touches are paged in. ``np.load(..., mmap_mode="r")`` does not do this
for ``.npz`` files (it reads whole members), hence the small zip-header parser here. A memory map
skips the zip CRC, so a shard is checked against the manifest's sha256 before it is used
(:func:`verify_shards`, once per file and process).
"""

from __future__ import annotations

import hashlib
import json
import math
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "FORMAT",
    "DatasetFormatError",
    "ShardRef",
    "read_manifest",
    "noise_levels_of",
    "select_shards",
    "open_shard",
    "verify_shards",
]

FORMAT = "dss-pairs/1"
REQUIRED_ARRAYS = ("noisy", "clean", "mask", "pair_id")


class DatasetFormatError(ValueError):
    """A dataset directory, manifest or shard does not follow ``dss-pairs/1``."""


@dataclass(frozen=True)
class ShardRef:
    """One shard of a split: absolute ``path``, ``num_pairs`` rows, its ``noise_level``, and the
    manifest's ``sha256`` of the file (None in a manifest without one)."""

    path: Path
    num_pairs: int
    noise_level: float | None
    split: str
    sha256: str | None = None


def read_manifest(root: str | Path) -> dict[str, Any]:
    """Load and validate ``<root>/manifest.json``; returns the parsed dict.

    Raises FileNotFoundError (no directory / no manifest: the manifest is written last, so a
    missing one also means an unfinished dataset) or DatasetFormatError.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset directory {root} does not exist")
    path = root / "manifest.json"
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found: not a dss-pairs dataset, or its generation has not finished "
            "(the manifest is written last)"
        )
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise DatasetFormatError(f"{path}: invalid JSON ({e})") from e
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        got = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
        raise DatasetFormatError(f"{path}: expected format {FORMAT!r}, got {got!r}")
    for key in ("image_size", "channels", "shards"):
        if key not in manifest:
            raise DatasetFormatError(f"{path}: missing key {key!r}")
    size = manifest["image_size"]
    if not (isinstance(size, list | tuple) and len(size) == 2 and all(int(s) > 0 for s in size)):
        raise DatasetFormatError(f"{path}: image_size must be [H, W], got {size!r}")
    for i, s in enumerate(manifest["shards"]):
        for key in ("path", "split", "num_pairs"):
            if key not in s:
                raise DatasetFormatError(f"{path}: shards[{i}] misses {key!r}")
    return manifest


def noise_levels_of(manifest: dict[str, Any]) -> list[float]:
    """Sorted distinct noise levels of the shards (falls back to manifest["noise_levels"])."""
    levels = {float(s["noise_level"]) for s in manifest["shards"] if s.get("noise_level") is not None}
    if not levels:
        levels = {float(x) for x in manifest.get("noise_levels", [])}
    return sorted(levels)


def _same_level(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-12)


def select_shards(
    root: str | Path, manifest: dict[str, Any], split: str, noise_level: float | None = None
) -> list[ShardRef]:
    """Shards of ``split`` (and of ``noise_level`` when given), in manifest order.

    Raises DatasetFormatError when a listed shard file is missing, or when nothing matches
    (naming the splits and noise levels that exist).
    """
    root = Path(root)
    out = []
    for s in manifest["shards"]:
        if s["split"] != split:
            continue
        lvl = s.get("noise_level")
        if noise_level is not None and (lvl is None or not _same_level(float(lvl), noise_level)):
            continue
        p = root / s["path"]
        if not p.is_file():
            raise DatasetFormatError(f"{root / 'manifest.json'} lists {s['path']}, but {p} is missing")
        out.append(ShardRef(p, int(s["num_pairs"]), None if lvl is None else float(lvl), split, s.get("sha256")))
    if not out:
        splits = sorted({s["split"] for s in manifest["shards"]})
        raise DatasetFormatError(
            f"{root}: no shards for split={split!r}"
            + (f" and noise_level={noise_level}" if noise_level is not None else "")
            + f" (splits present: {splits}, noise levels: {noise_levels_of(manifest)})"
        )
    return out


#: files whose sha256 matched, as (path, size, mtime): each shard is hashed once per process
_verified: set[tuple[str, int, int]] = set()


def verify_shards(shards, root: str | Path | None = None) -> int:
    """Check each shard's bytes against the manifest's sha256 (shards without one are skipped);
    returns how many were hashed. Raises DatasetFormatError naming the first that differs: a
    corrupt or changed file would otherwise train on garbage (its memory map skips the zip CRC)."""
    hashed = 0
    for ref in shards:
        if not ref.sha256:
            continue
        st = ref.path.stat()
        key = (str(ref.path.resolve()), st.st_size, st.st_mtime_ns)
        if key in _verified:
            continue
        h = hashlib.sha256()
        with open(ref.path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        hashed += 1
        if h.hexdigest() != ref.sha256:
            where = f" ({Path(root) / 'manifest.json'})" if root is not None else ""
            raise DatasetFormatError(f"{ref.path}: its sha256 does not match the manifest's{where}: the shard is "
                                     "corrupt or was changed after it was written; regenerate it (dss-prep rewrites "
                                     "shards whose hash does not match)")
        _verified.add(key)
    return hashed


def _short(e: BaseException, limit: int = 160) -> str:
    """The first line of an exception's message, at most ``limit`` characters (numpy's header
    errors quote the whole header)."""
    text = (str(e).strip().splitlines() or [type(e).__name__])[0]
    return text if len(text) <= limit else text[:limit] + "..."


_LOCAL_HEADER = struct.Struct("<IHHHHHIIIHH")  # zip local file header, 30 bytes
_LOCAL_SIG = 0x04034B50


def _npz_memmaps(path: Path) -> dict[str, np.ndarray]:
    """Map every member of an uncompressed .npz as a read-only np.memmap."""
    out: dict[str, np.ndarray] = {}
    with zipfile.ZipFile(path) as zf:
        infos = zf.infolist()
    with open(path, "rb") as f:
        for info in infos:
            if not info.filename.endswith(".npy"):
                continue
            name = info.filename[:-4]
            if info.compress_type != zipfile.ZIP_STORED:
                raise DatasetFormatError(
                    f"{path}: member {info.filename} is compressed; shards must be written with "
                    "np.savez (not savez_compressed) so they can be memory-mapped"
                )
            f.seek(info.header_offset)
            sig, *_, name_len, extra_len = _LOCAL_HEADER.unpack(f.read(_LOCAL_HEADER.size))
            if sig != _LOCAL_SIG:
                raise DatasetFormatError(f"{path}: corrupt zip header for {info.filename}")
            f.seek(info.header_offset + _LOCAL_HEADER.size + name_len + extra_len)
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
            else:
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
            if dtype.hasobject:
                raise DatasetFormatError(f"{path}: member {name} has object dtype")
            if int(np.prod(shape)) == 0:
                out[name] = np.zeros(shape, dtype)
                continue
            out[name] = np.memmap(path, dtype=dtype, mode="r", offset=f.tell(), shape=shape,
                                  order="F" if fortran else "C")
    return out


def open_shard(path: str | Path, image_size: tuple[int, int] | None = None,
               channels: int = 3, num_pairs: int | None = None) -> dict[str, np.ndarray]:
    """Open a shard as memory maps and check it: ``{"noisy", "clean", "mask", "pair_id"}``.

    Args:
        path: the shard file.
        image_size: expected (H, W) (from the manifest); None skips that check.
        channels: expected channel count of ``noisy``/``clean``.
        num_pairs: expected row count (from the manifest); None skips that check.

    Raises DatasetFormatError naming the file and what is wrong.
    """
    path = Path(path)
    try:
        arrays = _npz_memmaps(path)
    except Exception as e:  # zip, struct, numpy header (even tokenize) errors: the file is not a shard
        if isinstance(e, DatasetFormatError):
            raise
        raise DatasetFormatError(f"{path}: not a readable .npz shard ({type(e).__name__}: {_short(e)})") from e
    missing = [k for k in REQUIRED_ARRAYS if k not in arrays]
    if missing:
        raise DatasetFormatError(f"{path}: missing arrays {missing} (has {sorted(arrays)})")
    noisy, clean, mask, pid = (arrays[k] for k in REQUIRED_ARRAYS)
    n = noisy.shape[0]
    if noisy.ndim != 4 or noisy.shape != clean.shape:
        raise DatasetFormatError(
            f"{path}: noisy {noisy.shape} and clean {clean.shape} must both be (n, H, W, C)"
        )
    if noisy.shape[-1] != channels:
        raise DatasetFormatError(f"{path}: expected {channels} channels, got shape {noisy.shape}")
    if image_size is not None and tuple(noisy.shape[1:3]) != tuple(image_size):
        raise DatasetFormatError(
            f"{path}: images are {tuple(noisy.shape[1:3])}, manifest says {tuple(image_size)}"
        )
    if mask.shape != noisy.shape[:3] or pid.shape != (n,):
        raise DatasetFormatError(
            f"{path}: mask {mask.shape} / pair_id {pid.shape} do not match {n} images of "
            f"{noisy.shape[1:3]}"
        )
    if num_pairs is not None and n != num_pairs:
        raise DatasetFormatError(f"{path}: has {n} pairs, manifest says {num_pairs}")
    return arrays
