"""``dss-export``: a ``dss-train`` checkpoint -> ONNX denoiser (Hydra app over :func:`run`).

    dss-export ckpt_path=outputs/train/<run>/checkpoints/best-epoch012.ckpt output=denoiser_1pct.onnx

The ONNX file has dynamic batch/height/width, passes ``onnx.checker`` and carries its metadata
(noise level, training image size, input normalisation, render settings of its training data;
see :mod:`pix2pix.export`). Parity with PyTorch is measured on random inputs and, with
``data_root``, on real validation renders; above ``parity_tolerance`` the run fails and the
ONNX file is removed. A model card (``<output>.md``) is written next to the file. The run
directory receives ``config.yaml`` and ``metrics.json`` (parity numbers, metadata).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from experiments.common import guarded

log = logging.getLogger(__name__)

__all__ = ["run", "main", "model_card", "ParityError"]


class ParityError(ValueError):
    """The ONNX file's outputs differ from PyTorch's by more than the tolerance (or are not finite)."""


def _real_renders(root: str | Path, noise_level: float | None, n: int) -> np.ndarray:
    """Up to ``n`` noisy validation renders (B, 3, H, W) float32 from a dss-pairs dataset."""
    from pix2pix.shards import open_shard, read_manifest, select_shards, verify_shards

    manifest = read_manifest(root)
    shards = select_shards(root, manifest, "val", noise_level)
    verify_shards(shards[:1], root)
    arrays = open_shard(shards[0].path, manifest["image_size"], 3, shards[0].num_pairs)
    x = np.asarray(arrays["noisy"][:n], dtype=np.float32).transpose(0, 3, 1, 2)
    h, w = x.shape[2] // 4 * 4, x.shape[3] // 4 * 4
    return np.ascontiguousarray(x[:, :, :h, :w])


def model_card(meta: dict[str, Any], parity: dict[str, float], ckpt_path: str,
               best_val: dict[str, float] | None) -> str:
    """Markdown model card from the ONNX metadata, parity numbers and validation metrics."""
    gen = meta.get("dss.generator") or {}
    lines = [
        f"# DSS Pix2Pix denoiser `{meta.get('dss.name')}`",
        "",
        f"- noise level: {meta.get('dss.noise_level')} (noise std as a fraction of the "
        "bounding-box diagonal)",
        f"- trained on {meta.get('dss.train_image_size')} px crops of "
        f"{meta.get('dss.render_image_size')} px renders; epoch {meta.get('dss.epoch')}, "
        f"global step {meta.get('dss.global_step')}",
        f"- generator: ResNet, ngf {gen.get('ngf')}, {gen.get('n_blocks')} residual blocks, "
        f"norm {(gen.get('norm_layer') or {}).get('target')}, residual prediction "
        f"{gen.get('residual')}, no tanh",
        "- input: (B, 3, H, W) float32 raw renders (H, W multiples of 4); normalisation inside "
        "the graph",
        f"- source checkpoint: `{ckpt_path}`",
        f"- render settings of the training data: `{meta.get('dss.render_settings')}`",
        "",
        "## ONNX parity with PyTorch (max abs difference)",
        "",
    ]
    lines += [f"- {k}: {v:.3g}" for k, v in parity.items()]
    if best_val:
        lines += [
            "",
            "## Validation (best checkpoint; pixels covered in either render)",
            "",
            "| metric | output vs clean | noisy input vs clean |",
            "| --- | --- | --- |",
        ]
        for m in ("l1", "smape", "psnr"):
            a, b = best_val.get(f"val/{m}"), best_val.get(f"val/noisy_{m}")
            if a is not None and b is not None:
                lines.append(f"| {m} | {a:.4f} | {b:.4f} |")
        red = best_val.get("val/smape_reduction")
        if red is not None:
            lines += ["", f"SMAPE reduction relative to the noisy input: {100 * red:.1f}%"]
    return "\n".join(lines) + "\n"


def _best_val_from_ckpt(ckpt_path: Path) -> dict[str, float] | None:
    """The val/* metrics next to the checkpoint (the training run's metrics.json), if any."""
    import json

    for cand in (ckpt_path.parent.parent / "metrics.json", ckpt_path.parent / "metrics.json"):
        if cand.is_file():
            try:
                data = json.loads(cand.read_text())
            except json.JSONDecodeError:
                return None
            return data.get("best_val") or None
    return None


def run(cfg: DictConfig) -> dict[str, Any]:
    """Export ``cfg.ckpt_path`` to ONNX, check parity; returns (and writes) the metrics."""
    import torch

    from dss.io_utils import atomic_write_json, atomic_write_text
    from pix2pix.export import export_checkpoint, onnx_parity, parse_metadata

    out_dir = Path(cfg.output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ckpt = Path(cfg.ckpt_path)
    if not ckpt.is_file():
        raise FileNotFoundError(f"ckpt_path={ckpt}: no such checkpoint file")
    output = Path(cfg.output) if cfg.get("output") else out_dir / "denoiser.onnx"
    if output.exists() and not cfg.get("overwrite", False):
        raise FileExistsError(f"{output} exists; pass overwrite=true to replace it")
    atomic_write_text(out_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))

    path, raw_meta, gen = export_checkpoint(ckpt, output, opset=int(cfg.opset), overwrite=True)
    meta = parse_metadata(raw_meta)
    rng = np.random.default_rng(int(cfg.get("seed", 0)))
    parity: dict[str, float] = {}
    for b, h, w in cfg.get("parity_sizes") or []:
        x = rng.random((int(b), 3, int(h), int(w)), dtype=np.float32)
        parity[f"random_{b}x{h}x{w}"] = onnx_parity(gen, path, x)
    if cfg.get("data_root"):
        x = _real_renders(cfg.data_root, meta.get("dss.noise_level"), int(cfg.parity_real_pairs))
        parity[f"real_{x.shape[0]}x{x.shape[2]}x{x.shape[3]}"] = onnx_parity(gen, path, x)
    tol = float(cfg.get("parity_tolerance", 1e-4))
    # NaN compares false with everything: a non-finite difference is a failed check, not a pass
    failed = {k: v for k, v in parity.items() if not v <= tol}
    worst = max(parity.values(), default=0.0, key=lambda v: v if math.isfinite(v) else math.inf)
    if failed:
        path.unlink(missing_ok=True)
        raise ParityError(f"ONNX parity {worst:.3g} exceeds {tol:g} ({', '.join(f'{k}: {v:.3g}' for k, v in failed.items())}); "
                          f"{path} removed")
    card = None
    if cfg.get("model_card", True):
        card = path.with_suffix(path.suffix + ".md")
        atomic_write_text(card, model_card(meta, parity, str(ckpt), _best_val_from_ckpt(ckpt)))
    result = {
        "ckpt_path": str(ckpt),
        "onnx": str(path),
        "model_card": None if card is None else str(card),
        "parity_max_abs": parity,
        "parity_worst": worst,
        "metadata": meta,
        "torch_version": torch.__version__,
        "opset": int(cfg.opset),
    }
    atomic_write_json(out_dir / "metrics.json", result)
    log.info("exported %s (parity %.3g)", path, worst)
    return result


@hydra.main(version_base="1.3", config_path="../../conf", config_name="export")
@guarded
def _main(cfg: DictConfig) -> None:
    """Console entry point ``dss-export``."""
    run(cfg)


def main() -> None:
    """Console entry point: an expected failure prints one line and exits 2 (experiments.common.run_app)."""
    from experiments.common import run_app

    run_app(_main)


if __name__ == "__main__":
    main()
