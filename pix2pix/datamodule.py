"""Streaming the ``dss-pairs/1`` shards into Lightning (train / val / test).

:class:`PairStream` is a torch ``IterableDataset`` over memory-mapped shards (nothing is loaded
up front; only the rows read are paged in). Its order is a function of (seed, epoch) only:

1. shards are shuffled, then taken in groups of ``interleave`` shards; the rows of each group
   are pooled and permuted (so a batch mixes shapes of several shards while reading stays local
   to a few files);
2. under DDP, rank r takes every world_size-th item (truncated to equal length, so no rank waits
   on another);
3. the plan is cut into batches and worker w of the DataLoader produces batches w, w + W, ...,
   which the DataLoader hands out round-robin, i.e. in plan order: the stream is the same for
   any number of workers, and per-batch augmentation RNGs are seeded by (seed, epoch, rank,
   batch index), so runs are reproducible and a resume at an epoch boundary continues exactly.

The epoch lives in a shared-memory tensor (:meth:`PairStream.set_epoch`), so workers, persistent
or not, see it; :class:`Pix2PixDataModule.set_epoch` is called by the LightningModule at each
train epoch start (Lightning only calls ``set_epoch`` on samplers).

Samples are dicts: ``noisy``, ``clean`` (3, h, w) float32, ``mask`` (h, w) bool, ``pair_id``
int64, and for the ``planes`` channel ``coords`` (2, h, w) float32: the normalised image
coordinates ``(x, y)`` of the pixels in the full render (:func:`pix2pix.metrics.pixel_coords`;
through a crop and flips, those of the pixel the sample shows), with which a plane gives its
inverse depth (the planes losses and metrics of :mod:`pix2pix.module`). Augmentations: random
crops (train), flips only where the lighting allows, planes flips with their channel changes
(see :mod:`pix2pix.augment`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from .augment import apply_flips, is_planes, resolve_flips
from .metrics import pixel_coords
from .networks import SIZE_MULTIPLE
from .shards import (
    ShardRef,
    noise_levels_of,
    open_shard,
    read_manifest,
    select_shards,
    verify_shards,
)

log = logging.getLogger(__name__)

__all__ = ["PairStream", "Pix2PixDataModule", "render_focal"]


def render_focal(render: dict[str, Any] | None, image_size: Sequence[int]) -> float:
    """Focal length in pixels of a manifest's render block: its ``focal``, else from ``fov_deg``
    (horizontal) and the image width."""
    import math

    render = render or {}
    if render.get("focal"):
        return float(render["focal"])
    if render.get("fov_deg"):
        return 0.5 * float(image_size[1]) / math.tan(math.radians(float(render["fov_deg"])) / 2)
    raise ValueError("the dataset's render block has neither focal nor fov_deg")


def _number(name: str, value, kind: type, optional: bool = False):
    """``kind(value)``, or a ValueError naming the setting (``batch_size='abc' is not an integer``);
    None passes when ``optional``."""
    if value is None and optional:
        return None
    if isinstance(value, bool) or (kind is int and isinstance(value, float) and not value.is_integer()):
        ok = False
    else:
        try:
            value = kind(value)
            ok = True
        except (TypeError, ValueError):
            ok = False
    if not ok:
        raise ValueError(f"{name}={value!r} is not {'an integer' if kind is int else 'a number'}")
    return value


class PairStream(IterableDataset):
    """Iterable over the pairs of a list of shards (see module docstring).

    Args:
        shards: the shards to read (from :func:`pix2pix.shards.select_shards`).
        batch_size: the DataLoader's batch size (the plan is cut into batches of this size).
        image_size: (H, W) of the shards (from the manifest).
        shuffle: shuffle (train) or keep manifest order (val/test).
        seed: base seed of the shuffling and augmentation RNGs.
        crop_size: side of square crops (multiple of 4), or None for full images.
        random_crop: random crop position (train) or centred (val).
        flips: flips to apply with probability 1/2 each (already checked for lighting safety).
        interleave: shards pooled per shuffle group.
        drop_last: drop the last incomplete batch.
        max_pairs: use only the first ``max_pairs`` pairs of the plan order of epoch 0 when not
            shuffling (a fixed, evenly spread validation subset); None for all.
        rank, world_size: DDP position (set by the DataModule from the trainer).
        planes: the shards hold the ``planes`` channel: flips mirror the planes, and samples
            carry ``coords``.
        crop_min_coverage: random crops: up to 8 positions are drawn and the first whose
            covered fraction (the shards' mask) reaches this is taken (else the most covered
            one); 0 takes the first draw. Renders are mostly background, which teaches little.
        focal: the renders' focal length in pixels (needed with ``planes``).
    """

    def __init__(
        self,
        shards: Sequence[ShardRef],
        batch_size: int,
        image_size: Sequence[int],
        *,
        shuffle: bool = True,
        seed: int = 0,
        crop_size: int | None = None,
        random_crop: bool = True,
        flips: Sequence[str] = (),
        interleave: int = 4,
        drop_last: bool = False,
        max_pairs: int | None = None,
        rank: int = 0,
        world_size: int = 1,
        planes: bool = False,
        focal: float | None = None,
        crop_min_coverage: float = 0.0,
    ):
        super().__init__()
        self.crop_min_coverage = float(crop_min_coverage)
        if planes and not (focal and focal > 0):
            raise ValueError(f"planes shards need the renders' focal length, got {focal}")
        self.planes = bool(planes)
        self.focal = None if focal is None else float(focal)
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.shards = list(shards)
        self.batch_size = int(batch_size)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.shuffle = shuffle
        self.seed = int(seed)
        self.crop_size = None if crop_size is None else int(crop_size)
        self.random_crop = random_crop
        self.flips = list(flips)
        self.interleave = max(1, int(interleave))
        self.drop_last = drop_last
        self.max_pairs = max_pairs
        self.rank, self.world_size = int(rank), int(world_size)
        h, w = self.image_size
        if self.crop_size is not None:
            if self.crop_size % SIZE_MULTIPLE or self.crop_size > min(h, w):
                raise ValueError(
                    f"crop_size {self.crop_size} must be a multiple of {SIZE_MULTIPLE} and at most "
                    f"the image size {h}x{w}"
                )
        elif h % SIZE_MULTIPLE or w % SIZE_MULTIPLE:
            raise ValueError(
                f"images are {h}x{w}; without a crop_size H and W must be multiples of "
                f"{SIZE_MULTIPLE} (set a crop size)"
            )
        out_h, out_w = self.output_size
        if "transpose" in self.flips and out_h != out_w:
            log.warning("transpose dropped: output size %dx%d is not square", out_h, out_w)
            self.flips.remove("transpose")
        self._epoch = torch.zeros((), dtype=torch.int64).share_memory_()

    @property
    def output_size(self) -> tuple[int, int]:
        return (self.crop_size, self.crop_size) if self.crop_size else self.image_size

    def set_epoch(self, epoch: int) -> None:
        """Select the shuffle of ``epoch`` (visible to DataLoader workers)."""
        self._epoch.fill_(int(epoch))

    @property
    def epoch(self) -> int:
        return int(self._epoch.item())

    # ---- the plan --------------------------------------------------------------------------
    def _full_plan(self, epoch: int) -> list[tuple[int, int]]:
        """(shard index, row) for all pairs, in the epoch's order (before the rank split)."""
        if not self.shuffle:
            plan = [(s, r) for s, ref in enumerate(self.shards) for r in range(ref.num_pairs)]
            if self.max_pairs is not None and self.max_pairs < len(plan):
                # evenly spread subset, so a limited validation still covers all shards/shapes
                idx = np.linspace(0, len(plan) - 1, self.max_pairs).round().astype(int)
                plan = [plan[i] for i in idx]
            return plan
        rng = np.random.default_rng([self.seed, epoch, 7919])
        order = rng.permutation(len(self.shards))
        plan: list[tuple[int, int]] = []
        for g in range(0, len(order), self.interleave):
            pool = [(int(s), r) for s in order[g:g + self.interleave]
                    for r in range(self.shards[s].num_pairs)]
            plan += [pool[i] for i in rng.permutation(len(pool))]
        return plan

    def _rank_plan(self, epoch: int) -> list[tuple[int, int]]:
        plan = self._full_plan(epoch)
        if self.world_size > 1:
            per_rank = len(plan) // self.world_size
            plan = plan[self.rank::self.world_size][:per_rank]
        if self.drop_last:
            plan = plan[: len(plan) // self.batch_size * self.batch_size]
        return plan

    def __len__(self) -> int:
        return len(self._rank_plan(0))

    # ---- reading -------------------------------------------------------------------------------
    def _open(self, s: int, cache: dict[int, dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        if s not in cache:
            if len(cache) >= 2 * self.interleave:  # keep a bounded number of maps open
                cache.pop(next(iter(cache)))
            ref = self.shards[s]
            cache[s] = open_shard(ref.path, self.image_size, 3, ref.num_pairs)
        return cache[s]

    def _sample(self, arrays: dict[str, np.ndarray], row: int,
                rng: np.random.Generator) -> dict[str, Any]:
        h, w = self.image_size
        y0 = x0 = 0
        if self.crop_size:
            c = self.crop_size
            if self.random_crop:
                y0, x0 = self._crop_position(arrays["mask"], row, c, rng)
            else:
                y0, x0 = (h - c) // 2, (w - c) // 2
            sl = (row, slice(y0, y0 + c), slice(x0, x0 + c))
        else:
            sl = (row, slice(None), slice(None))
        items = [arrays["noisy"][sl], arrays["clean"][sl], arrays["mask"][sl]]
        if self.planes:  # the pixels' coordinates in the full render travel with them
            items.append(pixel_coords(self.image_size, self.focal, self.output_size, (y0, x0)).permute(1, 2, 0).numpy())
        if self.flips:
            items = apply_flips(items, self.flips, rng, planes=[self.planes, self.planes, False, True][:len(items)])

        def chw(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.array(a, dtype=np.float32).transpose(2, 0, 1).copy())

        sample = {
            "noisy": chw(items[0]),
            "clean": chw(items[1]),
            "mask": torch.from_numpy(np.array(items[2], dtype=bool)),
            "pair_id": torch.tensor(int(arrays["pair_id"][row]), dtype=torch.int64),
        }
        if self.planes:
            sample["coords"] = chw(items[3])
        return sample

    def _crop_position(self, mask: np.ndarray, row: int, c: int, rng: np.random.Generator) -> tuple[int, int]:
        """(y0, x0) of a random crop (``crop_min_coverage``, see the class docstring)."""
        h, w = self.image_size
        draw = lambda: (int(rng.integers(0, h - c + 1)), int(rng.integers(0, w - c + 1)))  # noqa: E731
        if self.crop_min_coverage <= 0:
            return draw()
        best, best_cov = None, -1.0
        for _ in range(8):
            y0, x0 = draw()
            cov = float(np.asarray(mask[row, y0:y0 + c, x0:x0 + c]).mean())
            if cov >= self.crop_min_coverage:
                return y0, x0
            if cov > best_cov:
                best, best_cov = (y0, x0), cov
        return best

    def __iter__(self):
        epoch = self.epoch
        plan = self._rank_plan(epoch)
        info = get_worker_info()
        wid, nw = (info.id, info.num_workers) if info is not None else (0, 1)
        cache: dict[int, dict[str, np.ndarray]] = {}
        bs = self.batch_size
        for b in range(wid, (len(plan) + bs - 1) // bs, nw):
            rng = np.random.default_rng([self.seed, epoch, self.rank, b, 104729])
            for s, r in plan[b * bs:(b + 1) * bs]:
                yield self._sample(self._open(s, cache), r, rng)


class Pix2PixDataModule(L.LightningDataModule):
    """Train/val/test loaders over a ``dss-pairs/1`` dataset, for one noise level.

    Args:
        root: dataset directory (holds ``manifest.json``).
        noise_level: which shards to use (one model per noise level); None is allowed only
            when the dataset has a single level.
        batch_size, val_batch_size: loader batch sizes (val defaults to batch_size).
        crop_size: square training crop side (multiple of 4); None trains on full renders.
        val_crop_size: centred validation crop; None validates on full renders.
        flips: ``"auto"`` (the flips the dataset's light allows), ``"none"``, or a list.
        crop_min_coverage: covered fraction a training crop should reach (:class:`PairStream`).
        interleave: shards pooled per shuffle group (train).
        max_val_pairs: fixed evenly spread validation subset (CPU budgets); None for all.
        num_workers, pin_memory, persistent_workers, prefetch_factor: DataLoader options.
        seed: shuffling/augmentation seed.
        drop_last: drop the last incomplete training batch.
        verify: check every shard used against the manifest's sha256 when its split is set up
            (once per file and process; :func:`pix2pix.shards.verify_shards`).

    A setting of the wrong type is refused naming it (``batch_size='abc' is not an integer``).
    """

    def __init__(
        self,
        root: str | Path,
        noise_level: float | None = None,
        batch_size: int = 8,
        val_batch_size: int | None = None,
        crop_size: int | None = None,
        val_crop_size: int | None = None,
        flips: str | Sequence[str] | None = "auto",
        crop_min_coverage: float = 0.0,
        interleave: int = 4,
        max_val_pairs: int | None = None,
        num_workers: int = 0,
        pin_memory: bool = False,
        persistent_workers: bool = False,
        prefetch_factor: int | None = None,
        seed: int = 0,
        drop_last: bool = True,
        verify: bool = True,
    ):
        super().__init__()
        self.root = Path(root).expanduser()
        self.noise_level = _number("noise_level", noise_level, float, optional=True)
        self.batch_size = _number("batch_size", batch_size, int)
        self.val_batch_size = _number("val_batch_size", val_batch_size, int, optional=True) or self.batch_size
        self.crop_size = _number("crop_size", crop_size, int, optional=True)
        self.val_crop_size = _number("val_crop_size", val_crop_size, int, optional=True)
        self.flips_cfg = flips if isinstance(flips, str) or flips is None else list(flips)
        self.crop_min_coverage = _number("crop_min_coverage", crop_min_coverage, float)
        self.interleave = _number("interleave", interleave, int)
        self.max_val_pairs = _number("max_val_pairs", max_val_pairs, int, optional=True)
        self.num_workers = _number("num_workers", num_workers, int)
        self.verify = bool(verify)
        self.pin_memory = pin_memory
        self.persistent_workers = persistent_workers and self.num_workers > 0
        self.prefetch_factor = prefetch_factor if self.num_workers > 0 else None
        self.seed = _number("seed", seed, int)
        self.drop_last = drop_last
        self.manifest: dict[str, Any] | None = None
        self.train_set: PairStream | None = None
        self.val_set: PairStream | None = None
        self.test_set: PairStream | None = None
        self.flips: list[str] = []

    @property
    def planes(self) -> bool:
        """Whether the dataset is in the ``planes`` channel (after the manifest is read)."""
        return is_planes((self.manifest or {}).get("render"))

    # ---- manifest ------------------------------------------------------------------------------
    def _load_manifest(self) -> dict[str, Any]:
        if self.manifest is None:
            manifest = read_manifest(self.root)
            levels = noise_levels_of(manifest)
            if self.noise_level is None:
                if len(levels) > 1:
                    raise ValueError(
                        f"{self.root} holds noise levels {levels}; the paper trains one model per "
                        "noise level: set data.noise_level (or pick an experiment=noise_*)"
                    )
                self.noise_level = levels[0] if levels else None
            self.flips = resolve_flips(self.flips_cfg, manifest.get("render"))
            self.manifest = manifest
        return self.manifest

    def _rank(self) -> tuple[int, int]:
        trainer = getattr(self, "trainer", None)
        if trainer is None:
            return 0, 1
        return int(trainer.global_rank), int(trainer.world_size)

    def _stream(self, split: str, train: bool) -> PairStream:
        manifest = self._load_manifest()
        shards = select_shards(self.root, manifest, split, self.noise_level)
        if self.verify:  # before any row is read: a memory map skips the zip CRC
            verify_shards(shards, self.root)
        rank, world = self._rank()
        return PairStream(
            shards,
            batch_size=self.batch_size if train else self.val_batch_size,
            image_size=manifest["image_size"],
            shuffle=train,
            seed=self.seed,
            crop_size=self.crop_size if train else self.val_crop_size,
            random_crop=train,
            flips=self.flips if train else (),
            interleave=self.interleave,
            drop_last=self.drop_last if train else False,
            max_pairs=None if train else self.max_val_pairs,
            rank=rank,
            world_size=world,
            planes=self.planes,
            crop_min_coverage=self.crop_min_coverage if train else 0.0,
            focal=render_focal(manifest.get("render"), manifest["image_size"]) if self.planes else None,
        )

    def setup(self, stage: str | None = None) -> None:
        self._load_manifest()
        if stage in (None, "fit"):
            self.train_set = self._stream("train", train=True)
        if stage in (None, "fit", "validate"):
            self.val_set = self._stream("val", train=False)
        if stage in (None, "test"):
            self.test_set = self._stream("test", train=False)

    def set_epoch(self, epoch: int) -> None:
        if self.train_set is not None:
            self.train_set.set_epoch(epoch)

    def info(self) -> dict[str, Any]:
        """What a trained model must remember about its data (goes into checkpoints / ONNX)."""
        manifest = self._load_manifest()
        return {
            "root": str(self.root),
            "format": manifest["format"],
            "noise_level": self.noise_level,
            "image_size": list(manifest["image_size"]),
            "crop_size": self.crop_size,
            "channels": int(manifest.get("channels", 3)),
            "render": manifest.get("render", {}),
            "flips": list(self.flips),
            "data_seed": manifest.get("seed"),
            "data_package_version": manifest.get("package_version"),
            "num_train_pairs": len(self.train_set) if self.train_set is not None else None,
        }

    # ---- loaders -------------------------------------------------------------------------------
    def _loader(self, ds: PairStream | None, name: str) -> DataLoader:
        if ds is None:
            raise RuntimeError(f"{name} set is not set up; call setup() first")
        return DataLoader(
            ds,
            batch_size=ds.batch_size,
            num_workers=self.num_workers,
            pin_memory=self.pin_memory,
            persistent_workers=self.persistent_workers,
            prefetch_factor=self.prefetch_factor,
            drop_last=False,  # the stream already dropped what it should (batch-aligned plan)
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_set, "train")

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_set, "val")

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.test_set, "test")
