"""Training pairs rendered on the fly from stored clouds (``dss-train data=onthefly``).

The image shards of ``dss-prep`` fix the views and the noise of every pair once (the ``cpu_planes``
preset: ~9.8 GB at 256 px). Here the dataset is the clean clouds (``dss-prep output=clouds``,
:mod:`data_prep.clouds`, ~0.36 MB a 20K-point shape) and every epoch draws, per shape, fresh
Gaussian noise, its PCA normals (signed by the mesh, as dss-prep), ``views_per_shape`` fresh
views of the render spec and renders the noisy and the clean cloud with DSS, on the GPU when
there is one (``device: auto``), else on the CPU (in the DataLoader workers). Samples are those
of :class:`pix2pix.datamodule.PairStream` (crops, the channel's flips, ``coords`` in the planes
channel), so the LightningModule and the export are the same as with shards.

Order and randomness are functions of (seed, epoch) only: the shapes are shuffled per epoch,
split across DDP ranks and DataLoader workers by shape, and rendered in pools of ``pool``
shapes whose views are shuffled together. Validation draws its noise and views once (epoch 0
of its own stream), so every validation sees the same pairs.

Options for learned references in the planes channel (all off by default):

- ``noise_range`` [lo, hi]: every shape and epoch draws its own noise std, log-uniformly in
  the range (a continuous range of levels; ``dss-prep prep_preset=real_planes``).
- ``cascade``: a ``dss-cascade/1`` cache (:mod:`data_prep.cascade_cache`): the network's input is
  the render of the cloud after dss-denoise's classical stage (the cached noisy draws of each
  shape, one per epoch in turn), its target the clean render: what the plane fusion's
  references see with ``fusion.reference_cloud=refined``. Only the cached shapes are used.
- ``multiview``: each batch is ``batch_size`` views of one cloud whose crops are centred on
  the projection of one anchor point of its surface, with the cameras and ``probes`` clean
  points nearest the anchor (validation: full renders, probes drawn over the whole cloud), so
  that the loss can compare the views (:mod:`pix2pix.multiview`); no flips.

This module renders with ``dss`` and serves ``pix2pix``: it lives in ``experiments`` (the
layering of DESIGN.md: ``pix2pix`` knows images, not points).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, get_worker_info

from pix2pix.augment import resolve_flips
from pix2pix.datamodule import PairStream

log = logging.getLogger(__name__)

__all__ = ["CloudPairStream", "OnTheFlyDataModule", "render_cloud_pairs"]


def render_cloud_pairs(points: np.ndarray, mesh_normals: np.ndarray, noise: float, noise_seed: int, views, spec,
                       normals_k: int = 16, device: str | torch.device = "cpu",
                       clean_normals: np.ndarray | None = None,
                       input_cloud: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Noisy and clean renders (V, H, W, 3) float32 and the mask (V, H, W) of one shape's clean
    ``points`` through ``views``: noise of std ``noise`` (bbox diagonals) from ``noise_seed``,
    PCA normals over ``normals_k`` neighbours signed by ``mesh_normals`` (dss-prep's
    ``normals_orient: mesh``), rendered with :func:`dss.render.render` on ``device``.
    ``input_cloud`` (points, normals): render this as the input ("noisy") instead (the cascade's
    refined cloud)."""
    from data_prep.sampling import noisy_copy, with_normals
    from dss.render import render

    if clean_normals is None:
        clean_normals = with_normals(points, normals_k, "mesh", mesh_normals).normals
    if input_cloud is not None:
        noisy_pts, noisy_normals = input_cloud
    else:
        noisy_pts = noisy_copy(points, noise, noise_seed)
        noisy_normals = with_normals(noisy_pts, normals_k, "mesh", mesh_normals).normals
    cams = spec.cameras(views).to(device)
    settings = spec.render_settings()
    out = {}
    with torch.no_grad():
        for name, p, n in (("clean", points, clean_normals), ("noisy", noisy_pts, noisy_normals)):
            r = render(torch.from_numpy(np.ascontiguousarray(p, np.float32)).to(device),
                       torch.from_numpy(np.ascontiguousarray(n, np.float32)).to(device), cams, settings,
                       shading=spec.shader(), backend=spec.backend)
            out[name] = r.images.float().cpu().numpy()
            out[name + "_mask"] = r.mask.cpu().numpy()
    return {"noisy": out["noisy"], "clean": out["clean"], "mask": out["clean_mask"] | out["noisy_mask"],
            "cam_R": cams.R.float().cpu().numpy(), "cam_t": cams.t.float().cpu().numpy(),
            "cam_focal": cams.focal.float().cpu().numpy(), "cam_principal": cams.principal.float().cpu().numpy()}


class CloudPairStream(PairStream):
    """Iterable over pairs rendered from the clouds of ``shapes`` (module docstring).

    Args:
        root: the ``dss-clouds/1`` dataset.
        shapes: its manifest's shape entries of one split.
        spec: :class:`data_prep.render_spec.RenderSpec` of the renders.
        noise_level: noise std (bbox diagonals).
        views_per_shape: views drawn per shape and epoch.
        normals_k: PCA neighbours of the normals.
        device: where DSS renders (``cpu`` in DataLoader workers; a CUDA device only in the main
            process, ``num_workers=0``).
        pool: shapes rendered before their views are shuffled together (train).
        max_pairs: the first ``max_pairs`` pairs only (validation).
        stream: a salt that separates the train and validation draws.
        The rest as :class:`pix2pix.datamodule.PairStream`.
    """

    def __init__(self, root, shapes: list[dict], spec, noise_level: float, views_per_shape: int, batch_size: int, *,
                 shuffle: bool = True, seed: int = 0, crop_size: int | None = None, random_crop: bool = True,
                 flips=(), crop_min_coverage: float = 0.0, max_pairs: int | None = None, rank: int = 0,
                 world_size: int = 1, normals_k: int = 16, device: str = "cpu", pool: int = 4, stream: int = 0,
                 noise_range=None, cascade: str | Path | None = None, multiview: bool = False, probes: int = 2048,
                 spread_val: bool = False):
        super().__init__([], batch_size, spec.image_size, shuffle=shuffle, seed=seed, crop_size=crop_size,
                         random_crop=random_crop, flips=flips, interleave=1, drop_last=False, max_pairs=None,
                         rank=rank, world_size=world_size, planes=spec.shading == "planes", focal=spec.focal,
                         crop_min_coverage=crop_min_coverage)
        if views_per_shape < 1 or not shapes:
            raise ValueError(f"need shapes and views_per_shape >= 1 (got {len(shapes)} shapes, {views_per_shape} views)")
        self.root = Path(root)
        self.shapes = list(shapes)
        self.spec = spec
        self.noise_level = float(noise_level)
        self.views_per_shape = int(views_per_shape)
        self.normals_k = int(normals_k)
        self.device = str(device)
        self.pool = max(1, int(pool))
        self.max_pairs = max_pairs
        self.stream = int(stream)
        self.spread_val = bool(spread_val)
        self._clouds: dict[int, tuple] = {}
        self.noise_range = None if noise_range is None else tuple(float(x) for x in noise_range)
        if self.noise_range is not None and not 0 < self.noise_range[0] < self.noise_range[1]:
            raise ValueError(f"noise_range must be [lo, hi] with 0 < lo < hi, got {list(noise_range)}")
        self.multiview = bool(multiview)
        self.probes = int(probes)
        if self.multiview and self.views_per_shape % self.batch_size:
            raise ValueError(f"multiview batches are one cloud's views: views_per_shape ({self.views_per_shape}) "
                             f"must be a multiple of batch_size ({self.batch_size})")
        self.cascade = None
        if cascade is not None:
            from data_prep.cascade_cache import read_cascade_manifest

            man = read_cascade_manifest(cascade)
            split = {s["split"] for s in self.shapes}
            by_shape: dict[str, list[dict]] = {}
            for e in man["items"]:
                if e["split"] in split:
                    by_shape.setdefault(e["shape_id"], []).append(e)
            self.shapes = [s for s in self.shapes if s["shape_id"] in by_shape]
            if not self.shapes:
                raise ValueError(f"the cascade cache {cascade} holds none of this split's shapes")
            self.cascade = (Path(cascade), {k: sorted(v, key=lambda e: e["draw"]) for k, v in by_shape.items()})

    def _shape_order(self, epoch: int) -> list[int]:
        order = list(range(len(self.shapes)))
        if self.shuffle:
            order = [int(i) for i in np.random.default_rng([self.seed, epoch, self.stream, 7919]).permutation(order)]
        if self.world_size > 1:
            per_rank = len(order) // self.world_size
            order = order[self.rank::self.world_size][:per_rank]
        if self.max_pairs is not None:
            k = max(1, -(-int(self.max_pairs) // self.views_per_shape))
            if self.spread_val and not self.shuffle and k < len(order):  # evenly over the split's shapes
                order = [order[int(j)] for j in np.unique(np.linspace(0, len(order) - 1, k).round().astype(int))]
            order = order[:k]
        return order

    def __len__(self) -> int:
        n = len(self._shape_order(0)) * self.views_per_shape
        return n if self.max_pairs is None else min(n, int(self.max_pairs))

    def _cloud(self, i: int):
        if i not in self._clouds:
            from data_prep.clouds import load_cloud
            from data_prep.sampling import with_normals

            pts, mn = load_cloud(self.root, self.shapes[i])
            self._clouds[i] = (pts, mn, with_normals(pts, self.normals_k, "mesh", mn).normals)
            if len(self._clouds) > 4 * self.pool:  # a bounded cache of clean clouds
                self._clouds.pop(next(iter(self._clouds)))
        return self._clouds[i]

    def render_shape(self, i: int, epoch: int) -> dict[str, np.ndarray]:
        """The pairs of shape ``i`` in ``epoch``: noisy, clean, mask, pair_id arrays (and the
        cameras, the clean cloud and the noise std used)."""
        rng = np.random.default_rng([self.seed, epoch, self.stream, i, 104729])
        views = self.spec.sample_views(self.views_per_shape, rng)
        pts, mn, cn = self._cloud(i)
        noise_seed = int(rng.integers(2**62))
        std = self.noise_level
        if self.noise_range is not None:  # log-uniform in the range, per shape and epoch
            from data_prep.sampling import log_uniform

            std = log_uniform(self.noise_range, rng.random())
        inp = None
        if self.cascade is not None:  # the cached draws of this shape, one per epoch in turn
            from data_prep.cascade_cache import load_cascade_item

            root, by_shape = self.cascade
            entries = by_shape[self.shapes[i]["shape_id"]]
            e = entries[epoch % len(entries)]
            inp, std = load_cascade_item(root, e), float(e["noise_std"])
        pairs = render_cloud_pairs(pts, mn, std, noise_seed, views, self.spec, self.normals_k, self.device,
                                   clean_normals=cn, input_cloud=inp)
        pairs["pair_id"] = np.arange(i * self.views_per_shape, (i + 1) * self.views_per_shape, dtype=np.int64)
        pairs["noise_std"] = np.full(self.views_per_shape, std, np.float32)
        pairs["points"], pairs["normals"] = pts, cn
        return pairs

    def _multiview_samples(self, rendered: dict, rng: np.random.Generator):
        """One cloud's views as consecutive samples, each with its camera and the same probes:
        crops centred on the projection of an anchor point (the one of 16 random surface points
        that faces the most cameras), probes the clean points nearest it (validation: full
        renders, probes drawn over the cloud)."""
        from pix2pix.metrics import pixel_coords

        pts, nrm = rendered["points"], rendered["normals"]
        R, t = rendered["cam_R"], rendered["cam_t"]
        f, pp = rendered["cam_focal"], rendered["cam_principal"]
        H, W = self.image_size
        centers = -np.einsum("vji,vj->vi", R, t)  # camera centres (world)
        cand = rng.choice(len(pts), size=min(16, len(pts)), replace=False)
        facing = (np.einsum("cj,vcj->vc", nrm[cand], centers[:, None] - pts[cand][None]) > 0).sum(0)
        anchor = pts[cand[int(np.argmax(facing))]]
        c = self.crop_size
        if c:
            d2 = ((pts - anchor) ** 2).sum(1)
            probe_idx = np.argsort(d2)[:min(self.probes, len(pts))]
        else:
            probe_idx = rng.choice(len(pts), size=min(self.probes, len(pts)), replace=False)
        probe_p = torch.from_numpy(np.ascontiguousarray(pts[probe_idx], np.float32))
        probe_n = torch.from_numpy(np.ascontiguousarray(nrm[probe_idx], np.float32))

        def chw(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.array(a, dtype=np.float32).transpose(2, 0, 1).copy())

        for v in range(len(R)):
            y0 = x0 = 0
            if c:
                pc = R[v] @ anchor + t[v]
                u = pc[0] / max(pc[2], 1e-6) * f[v] + pp[v, 0]
                w_ = pc[1] / max(pc[2], 1e-6) * f[v] + pp[v, 1]
                x0 = int(np.clip(round(u - c / 2), 0, W - c))
                y0 = int(np.clip(round(w_ - c / 2), 0, H - c))
            h, w = (c, c) if c else (H, W)
            sl = (v, slice(y0, y0 + h), slice(x0, x0 + w))
            yield {
                "noisy": chw(rendered["noisy"][sl]), "clean": chw(rendered["clean"][sl]),
                "mask": torch.from_numpy(np.array(rendered["mask"][sl], dtype=bool)),
                "pair_id": torch.tensor(int(rendered["pair_id"][v]), dtype=torch.int64),
                "coords": pixel_coords(self.image_size, self.focal, (h, w), (y0, x0)),
                "cam_R": torch.from_numpy(R[v].copy()), "cam_t": torch.from_numpy(t[v].copy()),
                "cam_focal": torch.tensor(float(f[v])),
                "cam_principal": torch.tensor([float(pp[v, 0]) - x0, float(pp[v, 1]) - y0]),
                "noise_std": torch.tensor(float(rendered["noise_std"][v])),
                "probe_points": probe_p, "probe_normals": probe_n,
            }

    def __iter__(self):
        epoch = self.epoch if self.shuffle else 0
        order = self._shape_order(epoch)
        info = get_worker_info()
        wid, nw = (info.id, info.num_workers) if info is not None else (0, 1)
        mine = order[wid::nw]
        left = None if self.max_pairs is None else -(-int(self.max_pairs) // nw)
        if self.multiview:  # one cloud's views together (batches must not mix clouds)
            for g, i in enumerate(mine):
                rendered = self.render_shape(i, epoch)
                rng = np.random.default_rng([self.seed, epoch, self.stream, self.rank, wid, g, 37])
                for v0 in range(0, self.views_per_shape, self.batch_size):
                    sub = {k: (a[v0:v0 + self.batch_size] if k not in ("points", "normals") else a)
                           for k, a in rendered.items()}
                    for sample in self._multiview_samples(sub, rng):
                        if left is not None:
                            if left <= 0:
                                return
                            left -= 1
                        yield sample
            return
        for g in range(0, len(mine), self.pool if self.shuffle else 1):
            group = mine[g:g + (self.pool if self.shuffle else 1)]
            rendered = {i: self.render_shape(i, epoch) for i in group}
            items = [(i, v) for i in group for v in range(self.views_per_shape)]
            rng = np.random.default_rng([self.seed, epoch, self.stream, self.rank, wid, g, 31])
            if self.shuffle:
                items = [items[k] for k in rng.permutation(len(items))]
            for i, v in items:
                if left is not None:
                    if left <= 0:
                        return
                    left -= 1
                yield self._sample(rendered[i], v, rng)


class OnTheFlyDataModule(L.LightningDataModule):
    """Train/val loaders of pairs rendered on the fly from a ``dss-clouds/1`` dataset.

    Args:
        root: the cloud dataset (``dss-prep output=clouds``).
        noise_level: noise std (bbox diagonals); one of the manifest's levels unless
            ``any_noise``.
        views_per_shape: fresh views per shape and epoch (an epoch: every training shape once).
        batch_size, val_batch_size, crop_size, val_crop_size, flips, crop_min_coverage,
            max_val_pairs, seed: as :class:`pix2pix.datamodule.Pix2PixDataModule`.
        num_workers: DataLoader workers rendering on the CPU (a CUDA ``device`` forces 0).
        device: ``auto`` (the trainer's GPU when it has one, else the CPU), ``cpu`` or ``cuda[:N]``.
        pool: shapes whose views are shuffled together.
        any_noise: accept a noise level the manifest does not list.
        noise_range, cascade, multiview, probes: the options of the module docstring
            (``noise_range`` null: the dataset's own with ``noise_level: range``).
        val_multiview: multi-view validation batches (full renders; their probes give the
            fusion's measures, ``val/probe_*``); None: as ``multiview``. Validation then takes
            its ``max_val_pairs`` from shapes spread evenly over the split (the real meshes of
            a mixed dataset come last in it).
    """

    def __init__(self, root: str | Path, noise_level: float, views_per_shape: int = 8, batch_size: int = 8,
                 val_batch_size: int | None = None, crop_size: int | None = None, val_crop_size: int | None = None,
                 flips: Any = "auto", crop_min_coverage: float = 0.0, max_val_pairs: int | None = 64,
                 num_workers: int = 0, seed: int = 0, device: str = "auto", pool: int = 4, any_noise: bool = False,
                 pin_memory: bool = False, persistent_workers: bool = False, noise_range=None,
                 cascade: str | None = None, multiview: bool = False, probes: int = 2048,
                 val_multiview: bool | None = None, **_: Any):
        super().__init__()
        self.root = Path(root).expanduser()
        self.noise_range = None if noise_range is None else [float(x) for x in noise_range]
        self.range_from_data = str(noise_level) == "range"
        self.noise_level = float("nan") if self.range_from_data else float(noise_level)
        self.cascade = None if cascade in (None, "", "null") else str(Path(cascade).expanduser())
        self.multiview = bool(multiview)
        self.val_multiview = self.multiview if val_multiview is None else bool(val_multiview)
        self.probes = int(probes)
        self.views_per_shape = int(views_per_shape)
        self.batch_size = int(batch_size)
        self.val_batch_size = int(val_batch_size or batch_size)
        self.crop_size, self.val_crop_size = crop_size, val_crop_size
        self.flips_cfg = flips if isinstance(flips, str) or flips is None else list(flips)
        self.crop_min_coverage = float(crop_min_coverage)
        self.max_val_pairs = max_val_pairs
        self.num_workers = int(num_workers)
        self.seed = int(seed)
        self.device_cfg = str(device)
        self.pool = int(pool)
        self.any_noise = bool(any_noise)
        self.pin_memory = bool(pin_memory)
        self.persistent_workers = bool(persistent_workers)
        self.manifest: dict | None = None
        self.spec = None
        self.flips: list[str] = []
        self.train_set = self.val_set = None

    def _load(self) -> dict:
        if self.manifest is None:
            from data_prep.clouds import read_clouds_manifest
            from data_prep.render_spec import RenderSpec

            m = read_clouds_manifest(self.root)
            if self.range_from_data:  # noise_level: range -> the dataset's noise range, nominal level
                if not m.get("noise_range"):
                    raise ValueError(f"noise_level=range: {self.root} has no noise_range (dss-prep noise_range=[lo,hi])")
                self.noise_range = self.noise_range or list(m["noise_range"])
                self.noise_level = float(m["noise_levels"][0])
            if not self.any_noise and not any(abs(self.noise_level - float(x)) < 1e-9 for x in m["noise_levels"]):
                raise ValueError(f"noise_level {self.noise_level} is not one of the dataset's {m['noise_levels']} "
                                 "(any_noise=true to train at another level)")
            self.spec = RenderSpec.from_manifest(m["render"])
            self.flips = resolve_flips(self.flips_cfg, m["render"])
            self.manifest = m
        return self.manifest

    def _device(self) -> str:
        d = self.device_cfg
        if d == "auto":
            trainer = getattr(self, "trainer", None)
            root = getattr(getattr(trainer, "strategy", None), "root_device", None) if trainer is not None else None
            if root is not None and root.type == "cuda":
                return str(root)
            return "cuda" if torch.cuda.is_available() and trainer is None else "cpu"
        return d

    def _rank(self) -> tuple[int, int]:
        trainer = getattr(self, "trainer", None)
        return (0, 1) if trainer is None else (int(trainer.global_rank), int(trainer.world_size))

    def _stream(self, split: str, train: bool) -> CloudPairStream:
        m = self._load()
        shapes = [s for s in m["shapes"] if s["split"] == split]
        rank, world = self._rank()
        return CloudPairStream(
            self.root, shapes, self.spec, self.noise_level, self.views_per_shape,
            self.batch_size if train else self.val_batch_size, shuffle=train, seed=self.seed,
            crop_size=self.crop_size if train else self.val_crop_size, random_crop=train,
            flips=self.flips if train and not self.multiview else (),
            crop_min_coverage=self.crop_min_coverage if train else 0.0,
            max_pairs=None if train else self.max_val_pairs, rank=rank, world_size=world,
            normals_k=int(m["config"]["normals_k"]), device=self._device(), pool=self.pool, stream=0 if train else 1,
            noise_range=self.noise_range, cascade=self.cascade,
            multiview=self.multiview if train else self.val_multiview, probes=self.probes,
            spread_val=not train and self.val_multiview)

    def setup(self, stage: str | None = None) -> None:
        self._load()
        if stage in (None, "fit"):
            self.train_set = self._stream("train", True)
        if stage in (None, "fit", "validate"):
            self.val_set = self._stream("val", False)

    def set_epoch(self, epoch: int) -> None:
        if self.train_set is not None:
            self.train_set.set_epoch(epoch)

    def info(self) -> dict[str, Any]:
        """What a trained model must remember about its data (as Pix2PixDataModule.info)."""
        m = self._load()
        return {"root": str(self.root), "format": m["format"], "noise_level": self.noise_level,
                "image_size": list(m["image_size"]), "crop_size": self.crop_size, "channels": 3,
                "render": m["render"], "flips": list(self.flips), "data_seed": m.get("seed"),
                "data_package_version": m.get("package_version"), "on_the_fly": True,
                "views_per_shape": self.views_per_shape, "noise_range": self.noise_range,
                "cascade": self.cascade, "multiview": self.multiview,
                "num_train_pairs": len(self.train_set) if self.train_set is not None else None}

    def _loader(self, ds: CloudPairStream | None, train: bool) -> DataLoader:
        if ds is None:
            raise RuntimeError("call setup() first")
        workers = self.num_workers if ds.device == "cpu" else 0  # CUDA renders in the main process
        if workers != self.num_workers:
            log.info("on-the-fly renders on %s: DataLoader workers 0 (was %d)", ds.device, self.num_workers)
        return DataLoader(ds, batch_size=ds.batch_size, num_workers=workers, drop_last=train,
                          pin_memory=self.pin_memory, persistent_workers=self.persistent_workers and workers > 0)

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_set, True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_set, False)
