"""LightningModule training the Pix2Pix denoiser (paper appendix "Denoising Pix2Pix").

Manual optimisation of a generator G and an optional conditional PatchGAN discriminator D:

- D step: LSGAN, ``0.5 * (mse(D(x, y), 1) + mse(D(x, G(x)), 0))`` (Mao et al. 2017);
- G step: ``lambda_gan * mse(D(x, G(x)), 1) + lambda_l1 * |G(x) - y|_1`` (lambda_l1 = 100);
- Adam(lr 2e-4, betas (0.5, 0.999)) for both; optional pix2pix "linear" schedule (constant for
  ``n_epochs`` epochs, then linear decay to 0 over ``n_epochs_decay`` epochs).

With ``discriminator=None`` (or ``lambda_gan=0``) it trains G with L1 alone.

A generator with a coverage head (``ResNetGenerator(coverage_head=True)``) is trained on its gated
output (what it returns at inference) plus ``lambda_coverage`` x the binary cross-entropy of its
coverage logit against the clean render's coverage (a pixel is covered when any channel is
non-zero: the renders' background is exactly 0). Where the clean render is covered but the gate
is shut, the L1 term sees the ungated image, so the image is trained wherever the gate may open.
Validation adds ``val/coverage_acc`` (gate vs clean coverage, over the pixels covered in either
render).

``init_from``: a checkpoint (``.ckpt``) or an exported ONNX denoiser (``.onnx``) whose generator
weights start this one (warm start: fine-tune a shipped model, e.g. with a coverage head added);
only a coverage head the file lacks keeps its initialisation; any other missing tensor or a shape
mismatch is an error.

Note on step counts: under manual optimisation Lightning's ``global_step`` counts optimizer
steps, so with a discriminator each batch advances it by 2 (``trainer.max_steps`` likewise).

Validation logs, for the output and for the noisy input (the baseline to beat), L1, SMAPE and
PSNR against the clean render over the pixels covered in either render (the shards' mask;
conventions in :mod:`pix2pix.metrics`): ``val/{l1,smape,psnr}`` and ``val/noisy_{...}``, the
full-image ``val/smape_full`` / ``val/noisy_smape_full``, and ``val/smape_reduction`` =
1 - smape(output) / smape(noisy) (the issue's target: >= 0.3). When the data's render settings
fix a background-snap threshold (:mod:`pix2pix.postprocess`), the same metrics of the snapped
output, the denoiser as the runtime ships it, are logged as ``val/snap_{...}`` and
``val/snap_smape_reduction``. Each validation also writes an image
grid (columns noisy input | network output | clean target, labelled; small renders enlarged,
:func:`make_grid`) as PNG into ``<run dir>/val_grids/`` and sends it to the loggers that take
images (TensorBoard, W&B).

The ``planes`` channel (batches with ``coords``, :mod:`pix2pix.datamodule`): every pixel holds a
plane whose inverse depth at the pixel is ``a_0 x + a_1 y + a_2``. Two terms can join the L1 on
the channels, over the surface pixels (covered by the clean and the noisy render): ``lambda_depth``
x the L1 of that implied inverse depth against the clean render's (the quantity the plane fusion
reads), and ``lambda_normal`` x the L1 between the output's and the clean planes' unit
directions (their normals; mean over the 3 components). A generator that takes ``coords``
(:class:`pix2pix.networks.PlanesGenerator`) gets the batch's pixel coordinates. Validation then adds, for the output and the noisy input, the
geometry the planes imply (:func:`pix2pix.metrics.planes_metric_sums`): ``val/depth_err`` (mean
|z - z_clean| in bounding-box diagonals, capped at 0.05), ``val/depth_bias``,
``val/depth_within_1e-3``, ``val/normal_err_deg``, ``val/surface_l1``, ``val/surface_smape``,
each also as ``val/noisy_...``, and ``val/surface_smape_reduction``, ``val/depth_err_reduction``,
``val/normal_err_reduction``.

Checkpoints carry ``checkpoint["dss_pix2pix"]``: the generator/discriminator constructor configs
(JSON) and what the model knows about its data (noise level, render settings, sizes), so that a
checkpoint can be rebuilt and exported without Hydra (:func:`load_generator`).
"""

from __future__ import annotations

import io
import logging
import time
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ._io import atomic_write_bytes
from .metrics import l1 as l1_metric
from .metrics import planes_inverse_depth, planes_metric_sums, surface_pixels
from .metrics import psnr as psnr_metric
from .metrics import smape as smape_metric
from .multiview import agreement_terms, has_multiview, probe_observations
from .networks import (
    PatchDiscriminator,
    ResNetGenerator,
    apply_coverage,
    covered,
    generator_from_config,
)
from .postprocess import background_snap_threshold, snap_background

log = logging.getLogger(__name__)

__all__ = ["Pix2PixModule", "LinearDecay", "load_generator", "load_generator_weights", "CHECKPOINT_KEY",
           "make_grid", "NonFiniteLossError"]

CHECKPOINT_KEY = "dss_pix2pix"
METRIC_NAMES = ("l1", "smape", "psnr")


class NonFiniteLossError(ValueError):
    """A training loss or validation metric is NaN or inf: training stops at once (a NaN model
    would otherwise train on, be checkpointed and exported)."""


class LinearDecay:
    """pix2pix "linear" LR factor: 1 for ``n_epochs`` epochs, then linearly to 0 over
    ``n_epochs_decay`` epochs (a picklable callable so LambdaLR can save it)."""

    def __init__(self, n_epochs: int, n_epochs_decay: int):
        self.n_epochs = int(n_epochs)
        self.n_epochs_decay = max(1, int(n_epochs_decay))

    def __call__(self, epoch: int) -> float:
        return 1.0 - max(0, epoch + 1 - self.n_epochs) / float(self.n_epochs_decay + 1)


#: the grid's tiles are enlarged (nearest neighbour, by a whole factor) to at least this many pixels,
#: so that the tiny preset's 32 px renders can be seen
GRID_MIN_TILE = 192
GRID_LABELS = ("noisy input", "network output", "clean target")


def make_grid(noisy: torch.Tensor, output: torch.Tensor, clean: torch.Tensor) -> np.ndarray:
    """A header row naming the columns, then per image noisy | output | clean.

    (B, 3, H, W) x 3 -> (header + B H s, 3 W s, 3) uint8, with ``s`` the smallest whole factor that
    makes a tile at least :data:`GRID_MIN_TILE` pixels on its longer side (1 for larger renders).
    """
    rows = torch.cat([noisy, output, clean], dim=3)  # (B, 3, H, 3W)
    img = torch.cat(list(rows), dim=1)  # (3, B*H, 3W)
    img = img.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy()
    img = (img * 255.0 + 0.5).astype(np.uint8)
    H, W = noisy.shape[-2:]
    s = max(1, -(-GRID_MIN_TILE // max(H, W)))
    if s > 1:
        img = img.repeat(s, axis=0).repeat(s, axis=1)
    return np.concatenate([_grid_header(GRID_LABELS, W * s), img], axis=0)


def _grid_header(labels: tuple[str, ...], tile_width: int, height: int = 24) -> np.ndarray:
    """(height, len(labels) * tile_width, 3) uint8: each label centred over its column, black on white."""
    from PIL import Image, ImageDraw, ImageFont

    header = Image.new("RGB", (len(labels) * tile_width, height), (255, 255, 255))
    draw = ImageDraw.Draw(header)
    try:
        font = ImageFont.load_default(size=14)
    except (TypeError, OSError):  # a Pillow without FreeType: its small bitmap font
        font = ImageFont.load_default()
    for i, text in enumerate(labels):
        x = i * tile_width + max(0.0, (tile_width - draw.textlength(text, font=font)) / 2)
        draw.text((x, 4), text, fill=(0, 0, 0), font=font)
    return np.asarray(header)


def _png_bytes(img: np.ndarray) -> bytes:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.image

    buf = io.BytesIO()
    matplotlib.image.imsave(buf, img, format="png")
    return buf.getvalue()


class Pix2PixModule(L.LightningModule):
    """Pix2Pix GAN training for image denoising.

    Args:
        generator: an image-to-image network, (B,3,H,W) -> (B,3,H,W) (a ResNetGenerator).
        discriminator: conditional discriminator on cat(noisy, image) (6 channels), or None.
        lambda_l1: weight of the L1 term (pix2pix default 100).
        lambda_gan: weight of the LSGAN term of the generator loss.
        lr, lr_d: Adam learning rates of G and D (lr_d defaults to lr).
        betas: Adam betas.
        lr_schedule: ``"constant"`` or ``"linear"`` (pix2pix's linear decay).
        n_epochs, n_epochs_decay: epochs at the full rate, epochs of linear decay; None splits
            ``trainer.max_epochs`` in halves.
        train_crop_size: the image size the model is trained at (recorded into exports).
        num_grid_images: images per validation grid.
        max_grid_files: PNG grids kept in ``<run dir>/val_grids/`` (the first and the newest; 0: write
            none). A short run validates hundreds of times; the loggers still get every grid.
        name: preset name (recorded into exports).
        lambda_coverage: weight of the coverage head's cross-entropy (generators with one).
        init_from: warm-start the generator's weights from this ``.ckpt`` or ``.onnx`` file.
        lambda_depth: weight of the L1 of the implied inverse depth (planes batches, see the
            module docstring).
        lambda_normal: weight of the L1 of the planes' unit directions (planes batches).
        lambda_nll: weight of the Laplace negative log-likelihood ``e / b + log b`` of a
            generator that predicts the scale ``b`` of its inverse depth's error ``e``
            (``PlanesGenerator(uncertainty=True)``), over the surface pixels. ``e`` is detached:
            the planes learn from the L1 terms, the scale learns to predict their error.
        lambda_agree, lambda_fused: multi-view batches (:mod:`pix2pix.multiview`): weight of the
            mean spread across views of the probes' offsets (the fusion's consistency reads it),
            and of the mean |offset| the views agree on (what the fusion would move a point on
            the clean surface by); both in bounding-box diagonals.
        agree_tau: how far (bbox diagonals) the clean render's surface may be from a probe for
            the probe to count as seen; agree_min_views: views a probe needs; agree_cap: each
            probe's spread and |mean offset| are clamped at this many bbox diagonals in the loss
            (None: not clamped), so that the few probes at occlusion edges do not dominate it.
    """

    def __init__(
        self,
        generator: nn.Module,
        discriminator: nn.Module | None = None,
        lambda_l1: float = 100.0,
        lambda_gan: float = 1.0,
        lr: float = 2e-4,
        lr_d: float | None = None,
        betas: tuple[float, float] = (0.5, 0.999),
        lr_schedule: str = "constant",
        n_epochs: int | None = None,
        n_epochs_decay: int | None = None,
        train_crop_size: int | None = None,
        num_grid_images: int = 4,
        max_grid_files: int = 8,
        name: str = "custom",
        lambda_coverage: float = 10.0,
        init_from: str | None = None,
        lambda_depth: float = 0.0,
        lambda_normal: float = 0.0,
        lambda_nll: float = 0.0,
        lambda_agree: float = 0.0,
        lambda_fused: float = 0.0,
        agree_tau: float = 0.003,
        agree_min_views: int = 3,
        agree_cap: float | None = None,
    ):
        super().__init__()
        if lr_schedule not in ("constant", "linear"):
            raise ValueError(f"lr_schedule must be 'constant' or 'linear', got {lr_schedule!r}")
        # plain Python values only: checkpoints must load with torch.load(weights_only=True)
        betas = (float(betas[0]), float(betas[1]))
        self.save_hyperparameters(ignore=["generator", "discriminator"])
        self.automatic_optimization = False
        self.generator = generator
        self.discriminator = discriminator
        self.data_info: dict[str, Any] = {}
        self._val_sums: dict[str, torch.Tensor] = {}
        self._val_grid: tuple[torch.Tensor, ...] | None = None
        self._probe_values: dict[str, list[torch.Tensor]] = {}
        self._throughput = [0, 0.0]  # images, seconds in this epoch's training steps
        if init_from:
            self.warm_start = load_generator_weights(generator, init_from)

    @property
    def uses_gan(self) -> bool:
        return self.discriminator is not None and self.hparams.lambda_gan > 0

    def forward(self, noisy: torch.Tensor) -> torch.Tensor:
        return self.generator(noisy)

    # ---- optimisation --------------------------------------------------------------------------
    def configure_optimizers(self):
        hp = self.hparams
        betas = tuple(float(b) for b in hp.betas)
        opts = [torch.optim.Adam(self.generator.parameters(), lr=hp.lr, betas=betas)]
        if self.discriminator is not None:
            opts.append(torch.optim.Adam(self.discriminator.parameters(),
                                         lr=hp.lr_d or hp.lr, betas=betas))
        if hp.lr_schedule == "constant":
            return opts
        n, nd = hp.n_epochs, hp.n_epochs_decay
        if n is None or nd is None:
            max_epochs = self.trainer.max_epochs
            if not max_epochs or max_epochs < 1:
                raise ValueError(
                    "lr_schedule='linear' needs trainer.max_epochs >= 1, or model.n_epochs and "
                    "model.n_epochs_decay (use lr_schedule='constant' for time-bounded runs)"
                )
            n = max_epochs // 2 if n is None else n
            nd = max(1, max_epochs - n) if nd is None else nd
        scheds = [torch.optim.lr_scheduler.LambdaLR(o, LinearDecay(n, nd)) for o in opts]
        return opts, scheds

    def _opts(self) -> list:
        opts = self.optimizers()
        return list(opts) if isinstance(opts, list | tuple) else [opts]

    def _d_input(self, noisy: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        return torch.cat([noisy, image], dim=1)

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        t0 = time.perf_counter()
        noisy, clean = batch["noisy"], batch["clean"]
        opts = self._opts()
        opt_g = opts[0]
        image, logit, log_b = _outputs(self.generator, noisy, batch.get("coords"))
        logs: dict[str, torch.Tensor] = {}
        if logit is None:
            fake = l1_image = image
        else:
            fake = apply_coverage(image, logit)  # the inference output
            clean_cov = covered(clean)
            l1_image = torch.where(clean_cov, image, fake)
        if self.uses_gan:
            opt_d = opts[1]
            self.toggle_optimizer(opt_d)
            pred_real = self.discriminator(self._d_input(noisy, clean))
            pred_fake = self.discriminator(self._d_input(noisy, fake.detach()))
            loss_d = 0.5 * (F.mse_loss(pred_real, torch.ones_like(pred_real))
                            + F.mse_loss(pred_fake, torch.zeros_like(pred_fake)))
            self._check_finite("train/loss_d", loss_d, batch, batch_idx)
            opt_d.zero_grad(set_to_none=True)
            self.manual_backward(loss_d)
            opt_d.step()
            self.untoggle_optimizer(opt_d)
            logs["train/loss_d"] = loss_d.detach()

        self.toggle_optimizer(opt_g)
        loss_l1 = F.l1_loss(l1_image, clean)
        loss_g = self.hparams.lambda_l1 * loss_l1
        coords = batch.get("coords")
        lam_d, lam_n = float(self.hparams.get("lambda_depth", 0.0)), float(self.hparams.get("lambda_normal", 0.0))
        if coords is not None and (lam_d > 0 or lam_n > 0):
            surf = surface_pixels(noisy, clean)
            if bool(surf.any()):
                err = (planes_inverse_depth(l1_image, coords) - planes_inverse_depth(clean, coords)).abs()
                loss_depth = err[surf].mean()
                n_out = F.normalize(l1_image, dim=1, eps=1e-8)
                n_clean = F.normalize(clean, dim=1, eps=1e-8)
                loss_normal = (n_out - n_clean).abs().mean(1)[surf].mean()
                loss_g = loss_g + lam_d * loss_depth + lam_n * loss_normal
                logs["train/depth_l1"] = loss_depth.detach()
                logs["train/normal_l1"] = loss_normal.detach()
                lam_nll = float(self.hparams.get("lambda_nll", 0.0))
                if log_b is not None and lam_nll > 0:
                    ls = log_b[:, 0][surf]
                    nll = (err.detach()[surf] * torch.exp(-ls) + ls).mean()
                    loss_g = loss_g + lam_nll * nll
                    logs["train/nll"] = nll.detach()
        lam_a, lam_f = float(self.hparams.get("lambda_agree", 0.0)), float(self.hparams.get("lambda_fused", 0.0))
        if (lam_a > 0 or lam_f > 0) and has_multiview(batch):
            terms = self._agreement(l1_image, clean, noisy, batch)
            if terms is not None:
                cap = self.hparams.get("agree_cap")
                sp, fu = terms["spread"], terms["mean"].abs()
                if cap:  # probes beyond it (occlusion edges, silhouettes) stop pulling: the bulk counts
                    sp, fu = sp.clamp_max(float(cap)), fu.clamp_max(float(cap))
                spread, fused = sp.mean(), fu.mean()
                loss_g = loss_g + lam_a * spread + lam_f * fused
                logs["train/probe_spread"] = spread.detach()
                logs["train/probe_fused_err"] = fused.detach()
        if logit is not None:
            loss_cov = F.binary_cross_entropy_with_logits(logit, clean_cov.to(logit.dtype))
            loss_g = loss_g + self.hparams.lambda_coverage * loss_cov
            logs["train/coverage_bce"] = loss_cov.detach()
        if self.uses_gan:
            pred = self.discriminator(self._d_input(noisy, fake))
            loss_gan = F.mse_loss(pred, torch.ones_like(pred))
            loss_g = loss_g + self.hparams.lambda_gan * loss_gan
            logs["train/loss_g_gan"] = loss_gan.detach()
        self._check_finite("train/loss_g", loss_g, batch, batch_idx)
        opt_g.zero_grad(set_to_none=True)
        self.manual_backward(loss_g)
        opt_g.step()
        self.untoggle_optimizer(opt_g)
        logs["train/loss_g"] = loss_g.detach()
        logs["train/l1"] = loss_l1.detach()
        self.log_dict(logs, on_step=True, on_epoch=True, batch_size=noisy.shape[0])
        self.log("train/l1_step", loss_l1.detach(), on_step=True, on_epoch=False,
                 prog_bar=True, batch_size=noisy.shape[0])
        self._throughput[0] += noisy.shape[0]
        self._throughput[1] += time.perf_counter() - t0
        return loss_g.detach()

    def _agreement(self, planes: torch.Tensor, clean: torch.Tensor, noisy: torch.Tensor,
                   batch: dict) -> dict[str, torch.Tensor] | None:
        """:func:`pix2pix.multiview.agreement_terms` of the probes seen in enough views (None: none
        is), each term restricted to those."""
        off, w, z = probe_observations(planes, clean, noisy, batch, float(self.hparams.get("agree_tau", 0.003)))
        t = agreement_terms(off, w, int(self.hparams.get("agree_min_views", 3)), depth=z)
        valid = t["valid"]
        if not bool(valid.any()):
            return None
        return {k: v[valid] for k, v in t.items() if k != "valid"}

    def _check_finite(self, name: str, loss: torch.Tensor, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        """Stop before a non-finite loss reaches the weights, saying whether the batch was to blame."""
        if bool(torch.isfinite(loss)):
            return
        bad = [k for k in ("noisy", "clean") if not bool(torch.isfinite(batch[k]).all())]
        cause = (f"the batch's {' and '.join(bad)} images hold NaN/inf pixels (corrupt training data)" if bad
                 else "the model diverged (lower model.lr, or check the data)")
        raise NonFiniteLossError(f"{name} = {float(loss)} at epoch {self.current_epoch}, global step "
                                 f"{self.global_step}, batch {batch_idx}: {cause}; training stopped")

    def on_train_epoch_start(self) -> None:
        # Lightning calls set_epoch only on samplers; our iterable stream reshuffles per epoch.
        dm = getattr(self.trainer, "datamodule", None)
        if dm is not None and hasattr(dm, "set_epoch"):
            dm.set_epoch(self.current_epoch)
        self._throughput = [0, 0.0]

    def on_train_epoch_end(self) -> None:
        n, secs = self._throughput
        if secs > 0:
            self.log("train/images_per_s", n / secs, on_step=False, on_epoch=True)
        if self.hparams.lr_schedule != "constant":
            for s in self.lr_schedulers() if isinstance(self.lr_schedulers(), list) else [self.lr_schedulers()]:
                s.step()

    # ---- validation ----------------------------------------------------------------------------
    def on_validation_epoch_start(self) -> None:
        self._val_sums = {}
        self._val_grid = None
        self._probe_values: dict[str, list[torch.Tensor]] = {}

    def _accumulate(self, key: str, value: torch.Tensor, weight: float) -> None:
        v = value.detach().double() * weight
        self._val_sums[key] = self._val_sums.get(key, torch.zeros((), dtype=torch.float64, device=v.device)) + v

    def validation_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        noisy, clean = batch["noisy"], batch["clean"]
        mask = batch.get("mask")
        out, logit, log_b = _outputs(self.generator, noisy, batch.get("coords"))
        if logit is not None:
            out, gate = apply_coverage(out, logit), logit > 0
            either = covered(noisy) | covered(clean)
            hit = (gate == covered(clean)) & either
            self._accumulate("coverage_hits", hit.sum().to(torch.float64), 1.0)
            self._accumulate("coverage_pixels", either.sum().to(torch.float64), 1.0)
        b = noisy.shape[0]
        # masked l1/smape pool pixels over the whole split: weight each batch by its pixel count
        npx = float(mask.sum()) if mask is not None else float(b * noisy.shape[2] * noisy.shape[3])
        outputs = [("", out), ("noisy_", noisy)]
        thr = background_snap_threshold(self.data_info.get("render"))
        if thr is not None:  # what the shipped runtime returns (pix2pix.postprocess)
            outputs.append(("snap_", snap_background(out, thr, channel_dim=1)))
        for prefix, img in outputs:
            self._accumulate(prefix + "l1", l1_metric(img, clean, mask), npx)
            self._accumulate(prefix + "smape", smape_metric(img, clean, mask), npx)
            self._accumulate(prefix + "psnr", psnr_metric(img, clean, mask), b)
            self._accumulate(prefix + "smape_full", smape_metric(img, clean), b)
        self._accumulate("pixels", torch.ones((), device=noisy.device), npx)
        self._accumulate("count", torch.ones((), device=noisy.device), b)
        coords = batch.get("coords")
        if coords is not None:  # the geometry the planes imply (module docstring)
            surf = surface_pixels(noisy, clean)
            for prefix, img in (("", out), ("noisy_", noisy)):
                for k, v in planes_metric_sums(img, clean, coords, surf).items():
                    self._accumulate(f"planes:{prefix}{k}", v, 1.0)
            if log_b is not None and bool(surf.any()):
                err = (planes_inverse_depth(out, coords) - planes_inverse_depth(clean, coords)).abs()[surf]
                ls = log_b[:, 0][surf]
                self._accumulate("unc:nll", (err * torch.exp(-ls) + ls).sum(), 1.0)
                self._accumulate("unc:pixels", torch.tensor(float(surf.sum()), device=out.device), 1.0)
        if has_multiview(batch):  # what the plane fusion would read from these views
            for prefix, img in (("", out), ("noisy_", noisy)):
                t = self._agreement(img, clean, noisy, batch)
                if t is None:
                    continue
                # the fusion's s0: 0.15 pixel footprints, at most 0.2 noise levels
                s0 = torch.minimum(0.15 * t["depth"] / batch["cam_focal"][0], 0.2 * batch["noise_std"][0])
                n = float(len(t["spread"]))
                self._accumulate(f"probe:{prefix}spread", t["spread"].sum(), 1.0)
                self._accumulate(f"probe:{prefix}fused_err", t["mean"].abs().sum(), 1.0)
                self._accumulate(f"probe:{prefix}trusted", (t["spread"] <= s0).double().sum(), 1.0)
                self._accumulate(f"probe:{prefix}n", torch.tensor(n, device=out.device), 1.0)
                # medians need the values (the fusion reports its spread's median; means are
                # dominated by silhouette probes)
                for k, v in (("spread", t["spread"]), ("fused_err", t["mean"].abs())):
                    self._probe_values.setdefault(prefix + k, []).append(v.detach().double().cpu())
        k = self.hparams.num_grid_images
        if k > 0 and (self._val_grid is None or self._val_grid[0].shape[0] < k):
            take = (noisy[:k], out[:k], clean[:k])
            if self._val_grid is None:
                self._val_grid = tuple(t.detach().cpu() for t in take)
            else:
                need = k - self._val_grid[0].shape[0]
                self._val_grid = tuple(torch.cat([g, t[:need].detach().cpu()]) for g, t in
                                       zip(self._val_grid, take))

    def on_validation_epoch_end(self) -> None:
        if not self._val_sums:
            return
        sums = {k: self.trainer.strategy.reduce(v, reduce_op="sum") for k, v in self._val_sums.items()}
        count = sums.pop("count").clamp_min(1)
        pixels = sums.pop("pixels").clamp_min(1)
        cov = (sums.pop("coverage_hits", None), sums.pop("coverage_pixels", None))
        planes = {k[len("planes:"):]: sums.pop(k) for k in [k for k in sums if k.startswith("planes:")]}
        unc = {k[len("unc:"):]: sums.pop(k) for k in [k for k in sums if k.startswith("unc:")]}
        probe = {k[len("probe:"):]: sums.pop(k) for k in [k for k in sums if k.startswith("probe:")]}
        means = {k: float(v / (count if k.endswith(("psnr", "_full")) else pixels))
                 for k, v in sums.items()}
        means.update(_planes_means(planes))
        if unc:
            means["nll"] = float(unc["nll"] / unc["pixels"].clamp_min(1))
        for prefix in ("", "noisy_"):  # per probe: spread, |fused offset|, the fraction trusted
            if prefix + "n" in probe:
                n = probe[prefix + "n"].clamp_min(1)
                for k in ("spread", "fused_err", "trusted"):
                    means[f"probe_{prefix}{k}"] = float(probe[prefix + k] / n)
                for k in ("spread", "fused_err"):  # this process's probes (not reduced across ranks)
                    vals = self._probe_values.get(prefix + k)
                    if vals:
                        means[f"probe_{prefix}{k}_median"] = float(torch.cat(vals).median())
        for pre in ("", "snap_") if "snap_smape" in means else ("",):
            means[pre + "smape_reduction"] = 1.0 - means[pre + "smape"] / max(means["noisy_smape"], 1e-12)
        bad = sorted(k for k in ("l1", "smape", "noisy_l1", "noisy_smape") if not np.isfinite(means[k]))
        if bad:
            raise NonFiniteLossError(f"validation metrics are not finite ({', '.join(f'val/{k} = {means[k]}' for k in bad)}) "
                                     f"at epoch {self.current_epoch}: "
                                     + ("the validation data holds NaN/inf pixels" if any(k.startswith("noisy") for k in bad)
                                        else "the model's output is not finite (it diverged)"))
        means["l1_reduction"] = 1.0 - means["l1"] / max(means["noisy_l1"], 1e-12)
        means["psnr_gain"] = means["psnr"] - means["noisy_psnr"]
        if cov[0] is not None:
            means["coverage_acc"] = float(cov[0] / cov[1].clamp_min(1))
        self.log_dict({f"val/{k}": v for k, v in means.items()}, on_epoch=True, sync_dist=False)
        if not self.trainer.sanity_checking and self._val_grid is not None:
            self._save_grid()

    def _save_grid(self) -> None:
        if self.trainer.global_rank != 0:
            return
        grid = make_grid(*self._val_grid)
        step, epoch = self.global_step, self.current_epoch
        # trainer.validate() after fit (dss-train validates the best checkpoint) gets its own name
        stem = f"epoch{epoch:03d}-step{step:07d}" if self.trainer.state.fn == "fit" else f"validate-step{step:07d}"
        keep = int(self.hparams.get("max_grid_files", 8))
        if keep > 0:
            folder = Path(self.trainer.default_root_dir) / "val_grids"
            atomic_write_bytes(folder / f"{stem}.png", _png_bytes(grid))
            # names sort by epoch and step; keep the first grid (the starting point) and the newest
            grids = sorted(folder.glob("*.png"))
            for old in grids[1:len(grids) - keep + 1] if len(grids) > keep else []:
                old.unlink(missing_ok=True)
        for logger in self.loggers:
            try:
                if hasattr(logger, "log_image"):  # W&B
                    logger.log_image(key="val/grid", images=[grid],
                                     caption=["columns: " + " | ".join(GRID_LABELS)])
                elif hasattr(getattr(logger, "experiment", None), "add_image"):  # TensorBoard
                    logger.experiment.add_image("val/grid", grid, step, dataformats="HWC")
            except Exception as e:  # a logger failing to take an image must not stop training
                log.warning("could not log the validation grid to %s: %s", type(logger).__name__, e)

    # ---- checkpoints ---------------------------------------------------------------------------
    def on_fit_start(self) -> None:
        dm = getattr(self.trainer, "datamodule", None)
        if dm is not None and hasattr(dm, "info"):
            self.data_info = dm.info()
        fov = getattr(self.generator, "fov_deg", None)
        data_fov = (self.data_info.get("render") or {}).get("fov_deg")
        if fov is not None and data_fov is not None and abs(float(fov) - float(data_fov)) > 1e-6:
            raise ValueError(f"the generator's fov_deg {fov} is not the data's field of view {data_fov}: "
                             "set model.generator.fov_deg")

    def export_info(self) -> dict[str, Any]:
        """Everything needed to rebuild G and describe it (JSON-able)."""
        return {
            "version": 1,
            "name": self.hparams.name,
            "generator_class": f"{type(self.generator).__module__}.{type(self.generator).__qualname__}",
            "generator": self.generator.config() if hasattr(self.generator, "config") else None,
            "discriminator": (self.discriminator.config()
                              if self.discriminator is not None and hasattr(self.discriminator, "config")
                              else None),
            "train_crop_size": self.hparams.train_crop_size,
            "data": dict(self.data_info),
            "warm_start": getattr(self, "warm_start", None),
        }

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint[CHECKPOINT_KEY] = self.export_info()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        info = checkpoint.get(CHECKPOINT_KEY) or {}
        self.data_info = dict(info.get("data") or {})

    @classmethod
    def from_checkpoint(cls, path: str | Path, map_location: str = "cpu") -> Pix2PixModule:
        """Rebuild the module (G, D, hyperparameters, weights) from a checkpoint, without Hydra."""
        ckpt = _read_checkpoint(path, map_location)
        info = ckpt[CHECKPOINT_KEY]
        gen = generator_from_config(info["generator"])
        disc = PatchDiscriminator.from_config(info["discriminator"]) if info.get("discriminator") else None
        # init_from=None: the checkpoint holds the weights (the warm-start file may be gone)
        return cls.load_from_checkpoint(path, map_location=map_location, generator=gen,
                                        discriminator=disc, weights_only=False, init_from=None)


def _planes_means(sums: dict[str, torch.Tensor]) -> dict[str, float]:
    """Validation means of the planes metrics' pooled sums (output and ``noisy_``), with the
    reductions relative to the noisy input."""
    out: dict[str, float] = {}
    for prefix in ("", "noisy_"):
        if prefix + "pixels" not in sums:
            continue
        n = float(sums[prefix + "pixels"].clamp_min(1))
        for k in ("surface_l1", "surface_smape", "depth_err", "depth_within_1e-3", "normal_err_deg"):
            out[prefix + k] = float(sums[prefix + k]) / n
        out[prefix + "depth_bias"] = float(sums[prefix + "depth_bias"]) / float(sums[prefix + "depth_bias_pixels"].clamp_min(1))
    if "pixels" in sums and "noisy_pixels" in sums:
        for k in ("surface_smape", "depth_err", "normal_err_deg"):
            out[k.replace("_deg", "") + "_reduction"] = 1.0 - out[k] / max(out["noisy_" + k], 1e-12)
    return out


def _outputs(generator: nn.Module, x: torch.Tensor,
             coords: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """(ungated image, coverage logit or None, log uncertainty scale (B, 1, H, W) or None)."""
    if getattr(generator, "predicts_uncertainty", False):
        image, log_b = generator.forward_with_uncertainty(x, coords)
        return image, None, log_b
    return (*_image_and_coverage(generator, x, coords), None)


def _image_and_coverage(generator: nn.Module, x: torch.Tensor,
                        coords: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(ungated image, coverage logit or None) of any generator (one without a coverage head,
    or another image-to-image network, gives (G(x), None)); ``coords`` (the batch's pixel
    coordinates) go to a generator that takes them."""
    if hasattr(generator, "forward_with_coverage"):
        if coords is not None and _takes_coords(generator):
            return generator.forward_with_coverage(x, coords)
        return generator.forward_with_coverage(x)
    return generator(x), None


def _takes_coords(generator: nn.Module) -> bool:
    import inspect

    return "coords" in inspect.signature(generator.forward_with_coverage).parameters


def load_generator_weights(generator: nn.Module, path: str | Path) -> dict[str, Any]:
    """Copy the generator weights stored in ``path`` (a training checkpoint ``.ckpt`` or an
    exported ONNX denoiser ``.onnx``, whose initializers keep the parameter names) into
    ``generator``. Only a coverage head the file's model lacks keeps its initialisation
    (reported); any other missing tensor, a name the generator lacks or a shape mismatch raises
    ValueError naming the file. Returns a report dict."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"init_from={path}: no such file")
    if path.suffix == ".onnx":
        import onnx
        from onnx import numpy_helper

        state = {i.name: torch.from_numpy(numpy_helper.to_array(i).copy())
                 for i in onnx.load(str(path)).graph.initializer}
        own = generator.state_dict()
        state = {k: v for k, v in state.items() if k in own}  # graph constants are not parameters
    else:
        state = _generator_state(_read_checkpoint(path))
        own = generator.state_dict()
    if not state:
        raise ValueError(f"init_from={path}: no generator weights found in the file")
    extra = sorted(set(state) - set(own))
    bad = sorted(k for k in state if k in own and tuple(state[k].shape) != tuple(own[k].shape))
    if extra or bad:
        raise ValueError(f"init_from={path}: does not fit this generator (unknown {extra[:5]}, "
                         f"shape mismatch {[(k, tuple(state[k].shape), tuple(own[k].shape)) for k in bad[:5]]})")
    missing = sorted(set(own) - set(state))
    lost = [k for k in missing if not k.startswith("coverage.")]  # only a new coverage head may be new
    if lost:
        raise ValueError(f"init_from={path}: {len(lost)} generator tensors are not in the file ({lost[:5]}); "
                         "an ONNX export stores identical tensors once (e.g. untrained zero biases): "
                         "warm-start from the training checkpoint (.ckpt) instead")
    generator.load_state_dict(state, strict=False)
    log.info("generator warm-started from %s (%d tensors; kept their own init: %s)", path, len(state), missing)
    return {"path": str(path), "loaded": len(state), "kept_init": missing}


def _generator_state(ckpt: dict[str, Any]) -> dict[str, torch.Tensor]:
    """The generator's tensors of a Lightning checkpoint, named as in the generator itself."""
    return {k[len("generator."):]: v for k, v in ckpt["state_dict"].items() if k.startswith("generator.")}


def _read_checkpoint(path: str | Path, map_location: str = "cpu") -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as e:
        raise ValueError(f"{path}: not a readable PyTorch checkpoint ({e})") from e
    if not isinstance(ckpt, dict) or CHECKPOINT_KEY not in ckpt or "state_dict" not in ckpt:
        raise ValueError(
            f"{path}: not a dss pix2pix checkpoint (no '{CHECKPOINT_KEY}' entry); it must come "
            "from dss-train"
        )
    return ckpt


def load_generator(path: str | Path, map_location: str = "cpu") -> tuple[ResNetGenerator, dict[str, Any]]:
    """The trained generator (eval mode) and the checkpoint's ``dss_pix2pix`` info from a
    Lightning checkpoint written by ``dss-train``; info gains ``epoch`` and ``global_step``."""
    ckpt = _read_checkpoint(path, map_location)
    info = dict(ckpt[CHECKPOINT_KEY])
    if not info.get("generator"):
        raise ValueError(f"{path}: the checkpoint does not describe its generator")
    gen = generator_from_config(info["generator"])
    state = _generator_state(ckpt)
    try:
        gen.load_state_dict(state)
    except RuntimeError as e:
        raise ValueError(f"{path}: generator weights do not match its config ({e})") from e
    info["epoch"] = ckpt.get("epoch")
    info["global_step"] = ckpt.get("global_step")
    return gen.eval(), info
