"""Tiny synthetic datasets in the ``dss-pairs/1`` format, for tests and benchmarks.

The "clean" images are smooth random shading fields inside an elliptic mask (a stand-in for a
diffusely lit surface), the "noisy" ones add Gaussian noise inside the mask whose std grows with
the noise level (``pixel_noise_per_level * noise_level``). The noise is spatially correlated
(white noise blurred with a Gaussian of ``noise_corr_px`` pixels), as in renders of noisy
clouds, where each perturbed normal shades a whole splat. They are not DSS renders; real data
comes from ``data_prep``.
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ._io import atomic_write_bytes, atomic_write_json
from .shards import FORMAT

__all__ = ["make_synthetic_pair_dataset", "synthetic_pair"]

#: default render block of synthetic datasets (light on the optical axis: all flips are safe).
SYNTHETIC_RENDER = {
    "shading": "point_light",
    "light": {"type": "point", "position": [0.0, 0.0, 0.0], "space": "camera"},
    "backend": "synthetic",
}


def _blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of (1, C, H, W) with reflection padding."""
    r = max(1, int(3 * sigma))
    k = torch.exp(-torch.arange(-r, r + 1, dtype=torch.float32) ** 2 / (2 * sigma**2))
    k = k / k.sum()
    c = x.shape[1]
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="reflect"), k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="reflect"), k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def synthetic_pair(rng: np.random.Generator, size: int | tuple[int, int], noise_level: float,
                   pixel_noise_per_level: float = 8.0, noise_corr_px: float = 1.5,
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One (noisy, clean, mask) triple: (H, W, 3) float32, (H, W, 3) float32, (H, W) bool."""
    h, w = (size, size) if isinstance(size, int) else size
    coarse = torch.from_numpy(rng.random((1, 1, max(2, h // 8), max(2, w // 8)), dtype=np.float32))
    field = F.interpolate(coarse, size=(h, w), mode="bicubic", align_corners=True)[0, 0].numpy()
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    cy, cx = rng.uniform(0.35, 0.65) * h, rng.uniform(0.35, 0.65) * w
    ry, rx = rng.uniform(0.25, 0.45) * h, rng.uniform(0.25, 0.45) * w
    mask = ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1.0
    tint = rng.uniform(0.85, 1.0, size=3).astype(np.float32)
    clean = np.clip(0.15 + 0.7 * field, 0.0, 1.0)[..., None] * tint * mask[..., None]
    noise = rng.normal(0.0, 1.0, size=clean.shape).astype(np.float32)
    if noise_corr_px > 0 and min(h, w) > 6 * noise_corr_px:
        t = _blur(torch.from_numpy(noise).permute(2, 0, 1)[None], noise_corr_px)
        noise = t[0].permute(1, 2, 0).numpy()
        noise /= max(float(noise.std()), 1e-12)
    noise *= pixel_noise_per_level * noise_level
    noisy = (clean + noise * mask[..., None]).astype(np.float32)
    return noisy, clean.astype(np.float32), mask


def make_synthetic_pair_dataset(
    root: str | Path,
    n_train: int = 8,
    n_val: int = 4,
    size: int | tuple[int, int] = 32,
    noise_level: float | list[float] = 0.01,
    n_test: int = 0,
    shard_size: int = 4,
    seed: int = 0,
    render: dict[str, Any] | None = None,
) -> Path:
    """Write a small ``dss-pairs/1`` dataset (shards, then the manifest) and return ``root``.

    Args:
        root: output directory (created).
        n_train, n_val, n_test: pairs per split **per noise level**.
        size: image size, int or (H, W).
        noise_level: one level or a list (each level gets its own shards, as in real data).
        shard_size: pairs per shard.
        seed: RNG seed (equal arguments give byte-identical shards).
        render: the manifest's render block (default: point light on the optical axis).
    """
    root = Path(root)
    h, w = (size, size) if isinstance(size, int) else tuple(size)
    levels = [float(noise_level)] if np.isscalar(noise_level) else [float(x) for x in noise_level]
    rng = np.random.default_rng(seed)
    shards: list[dict[str, Any]] = []
    pairs: list[dict[str, Any]] = []
    for split, count in (("train", n_train), ("val", n_val), ("test", n_test)):
        for level in levels:
            for start in range(0, count, shard_size):
                n = min(shard_size, count - start)
                rel = f"{split}/shard-{len([s for s in shards if s['split'] == split]):05d}.npz"
                noisy = np.empty((n, h, w, 3), np.float16)
                clean = np.empty((n, h, w, 3), np.float16)
                mask = np.empty((n, h, w), bool)
                ids = np.arange(len(pairs), len(pairs) + n, dtype=np.int64)
                for i in range(n):
                    a, b, m = synthetic_pair(rng, (h, w), level)
                    noisy[i], clean[i], mask[i] = a, b, m
                    pid = int(ids[i])
                    pairs.append({
                        "pair_id": pid, "shape_id": f"synthetic-{pid:04d}", "family": "synthetic",
                        "seed": seed, "noise_level": level, "split": split, "shard": rel,
                        "index": i, "camera": {"eye": [0.0, 0.0, -2.0], "target": [0.0, 0.0, 0.0],
                                               "up": [0.0, -1.0, 0.0], "focal": float(w)},
                    })
                buf = io.BytesIO()
                np.savez(buf, noisy=noisy, clean=clean, mask=mask, pair_id=ids)
                data = buf.getvalue()
                atomic_write_bytes(root / rel, data)
                shards.append({"path": rel, "split": split, "num_pairs": n,
                               "sha256": hashlib.sha256(data).hexdigest(), "noise_level": level})
    manifest = {
        "format": FORMAT,
        "package_version": "0.1.0",
        "image_size": [h, w],
        "channels": 3,
        "noise_levels": levels,
        "render": dict(render if render is not None else SYNTHETIC_RENDER),
        "seed": seed,
        "shards": shards,
        "pairs": pairs,
    }
    atomic_write_json(root / "manifest.json", manifest)
    json.loads((root / "manifest.json").read_text())  # fail loudly if not round-trippable
    return root
