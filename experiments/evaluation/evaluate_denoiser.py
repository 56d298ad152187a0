"""Evaluate an exported denoiser (ONNX) on a dss-prep dataset split, raw and background-snapped.

    python -m experiments.evaluation.evaluate_denoiser MODEL.onnx --data data/pairs [--split val]
        [--max-pairs 256] [--out results/denoise/denoiser_eval_1pct.json]

For the model's noise level (its metadata), every pair of the split (up to ``--max-pairs``) is
denoised by onnxruntime twice: the raw network output and the output as the runtime ships it
(:mod:`pix2pix.postprocess` background snap). Reported, over the pixels covered in either render
(the shards' mask, the training validation's convention, :mod:`pix2pix.metrics`): SMAPE (paper,
channel sum), L1, PSNR of the noisy input, the raw and the snapped output against the clean
render, the SMAPE reduction relative to the noisy input (issue target: >= 30%), and SMAPE split
into the pixels the clean render covers and the halo it does not (where the noise spread the
silhouette). Writes JSON (atomically) and prints a markdown table.

A model of the ``planes`` channel (its metadata's render block) is not snapped (plane
coefficients are not intensities); for it the evaluation adds what the planes imply about the
geometry, for the network output and the noisy input (the identity control), over the surface
pixels (covered by the clean render and the noisy one, :func:`pix2pix.metrics.surface_pixels`):
surface-pixel SMAPE and L1, the implied depth's error |z - z_clean| in bounding-box diagonals
(mean capped at 0.05, median, signed median, fraction within 0.001), and the implied normals'
angle error (mean, median, degrees), with the reductions relative to the noisy input.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger("evaluate-denoiser")


def _sums(img: torch.Tensor, clean: torch.Tensor, mask: torch.Tensor) -> dict[str, float]:
    """Pooled sums over (B,3,H,W) images: SMAPE/L1 over masked pixels, and SMAPE on the clean
    render's foreground / halo (masked pixels it does not cover)."""
    from pix2pix.metrics import SMAPE_EPS

    per = ((img - clean).abs() / (img.abs() + clean.abs() + SMAPE_EPS)).sum(1)  # (B,H,W)
    l1 = (img - clean).abs().mean(1)
    fg = clean.amax(1) > 0
    m = mask
    return {"smape": float(per[m].sum()), "l1": float(l1[m].sum()),
            "smape_clean_fg": float(per[m & fg].sum()), "smape_halo": float(per[m & ~fg].sum())}


def evaluate(model: str | Path, data: str | Path, split: str = "val", max_pairs: int | None = 256,
             batch: int = 16, threads: int = 1) -> dict:
    """Metrics of ``model`` on ``split`` of the dataset at ``data`` (see module docstring)."""
    from pix2pix.augment import is_planes
    from pix2pix.datamodule import render_focal
    from pix2pix.metrics import pixel_coords, psnr
    from pix2pix.postprocess import background_snap_threshold, snap_background
    from pix2pix.runtime import OnnxDenoiser
    from pix2pix.shards import open_shard, read_manifest, select_shards

    den = OnnxDenoiser(model, intra_op_num_threads=threads, max_batch=batch, snap_background=False)
    thr = background_snap_threshold(den.render_settings)  # what the runtime's default snap uses
    level = den.noise_level
    manifest = read_manifest(data)
    planes = is_planes(den.render_settings)
    if planes != is_planes(manifest.get("render")):
        raise ValueError(f"{model} and {data} are not in the same render channel")
    coords = pixel_coords(manifest["image_size"], render_focal(manifest["render"], manifest["image_size"])) if planes else None
    geo = {"noisy": [], "raw": []}
    shards = select_shards(data, manifest, split, level)
    keys = ("noisy", "raw", "snapped")
    sums = {k: {} for k in keys}
    psnrs = {k: [] for k in keys}
    pixels, pairs = 0, 0
    for ref in shards:
        arr = open_shard(ref.path, tuple(manifest["image_size"]), int(manifest.get("channels", 3)))
        n = arr["noisy"].shape[0] if max_pairs is None else min(arr["noisy"].shape[0], max_pairs - pairs)
        for i in range(0, n, batch):
            j = min(n, i + batch)
            noisy = np.asarray(arr["noisy"][i:j], np.float32).transpose(0, 3, 1, 2)
            clean = torch.from_numpy(np.asarray(arr["clean"][i:j], np.float32).transpose(0, 3, 1, 2))
            mask = torch.from_numpy(np.array(arr["mask"][i:j], bool))
            raw = den(noisy)
            imgs = {"noisy": torch.from_numpy(noisy), "raw": torch.from_numpy(raw),
                    "snapped": torch.from_numpy(snap_background(raw, thr, channel_dim=1))}
            if planes:
                from pix2pix.metrics import planes_errors, surface_pixels

                surf = surface_pixels(imgs["noisy"], clean)
                c = coords[None].expand(j - i, -1, -1, -1)
                for k in geo:
                    e = planes_errors(imgs[k], clean, c, surf)
                    geo[k].append({n: v.numpy() for n, v in e.items()})
            for k, img in imgs.items():
                for name, v in _sums(img, clean, mask).items():
                    sums[k][name] = sums[k].get(name, 0.0) + v
                psnrs[k].append(float(psnr(img, clean, mask)) * (j - i))
            pixels += int(mask.sum())
        pairs += n
        if max_pairs is not None and pairs >= max_pairs:
            break
    if pairs == 0:
        raise ValueError(f"{data}: no {split} pairs at noise level {level}")
    res = {k: {name: v / max(pixels, 1) for name, v in sums[k].items()} | {"psnr": sum(psnrs[k]) / pairs}
           for k in keys}
    base = res["noisy"]["smape"]
    for k in ("raw", "snapped"):
        res[k]["smape_reduction"] = 1.0 - res[k]["smape"] / base
        res[k]["l1_reduction"] = 1.0 - res[k]["l1"] / res["noisy"]["l1"]
    if planes:
        del res["snapped"]  # nothing is snapped in the planes channel
        for k in geo:
            res[k]["geometry"] = _geometry(geo[k])
        g, gn = res["raw"]["geometry"], res["noisy"]["geometry"]
        for name in ("surface_smape", "surface_l1", "depth_err", "depth_err_median", "normal_err_deg",
                     "normal_err_deg_median"):
            g[name.replace("_deg", "") + "_reduction"] = 1.0 - g[name] / max(gn[name], 1e-12)
    return {"model": str(model), "data": str(data), "split": split, "noise_level": level, "pairs": pairs,
            "pixels": pixels, "background_threshold": thr, "channel": "planes" if planes else "point", "metrics": res,
            "note": "masked pixel means (pixels covered in either render); smape = smape_clean_fg + smape_halo"
                    + ("; geometry: over the surface pixels (covered by the clean and the noisy render), "
                       "depths in bbox diagonals, depth_err capped at 0.05" if planes else "")}


def _geometry(parts: list[dict]) -> dict:
    """Summary of :func:`pix2pix.metrics.planes_errors` arrays pooled over the split."""
    from pix2pix.metrics import DEPTH_ERROR_CAP

    cat = {k: np.concatenate([p[k] for p in parts]).astype(np.float64) for k in parts[0]}
    d = cat["depth"]
    return {"surface_pixels": int(d.size), "surface_smape": float(cat["smape"].mean()),
            "surface_l1": float(cat["abs"].mean() / 3.0), "depth_err": float(np.minimum(d, DEPTH_ERROR_CAP).mean()),
            "depth_err_median": float(np.median(d)), "depth_signed_median": float(np.median(cat["depth_signed"])),
            "depth_within_1e-3": float((d < 1e-3).mean()), "normal_err_deg": float(cat["normal_deg"].mean()),
            "normal_err_deg_median": float(np.median(cat["normal_deg"]))}


def markdown(r: dict) -> str:
    if r.get("channel") == "planes":
        return planes_markdown(r)
    m = r["metrics"]
    rows = ["| | SMAPE | on clean surface | on halo | L1 | PSNR (dB) | SMAPE reduction |",
            "|---|---|---|---|---|---|---|"]
    for k, label in (("noisy", "noisy input"), ("raw", "network output"),
                     ("snapped", f"output, background snap < {r['background_threshold']}")):
        red = m[k].get("smape_reduction")
        rows.append(f"| {label} | {m[k]['smape']:.4f} | {m[k]['smape_clean_fg']:.4f} | {m[k]['smape_halo']:.4f} | "
                    f"{m[k]['l1']:.4f} | {m[k]['psnr']:.2f} | {'' if red is None else f'{red * 100:.1f}%'} |")
    return "\n".join(rows)


def planes_markdown(r: dict) -> str:
    """The geometry table of a planes model: network output against the noisy input."""
    m = r["metrics"]
    rows = ["| surface pixels | SMAPE | L1 | depth error, mean (capped 0.05) | median | signed median | "
            "within 0.001 | normal error, mean (deg) | median (deg) |",
            "|---|---|---|---|---|---|---|---|---|"]
    for k, label in (("noisy", "noisy input (identity)"), ("raw", "network output")):
        g = m[k]["geometry"]
        rows.append(f"| {label} | {g['surface_smape']:.4f} | {g['surface_l1']:.4f} | {g['depth_err']:.5f} | "
                    f"{g['depth_err_median']:.5f} | {g['depth_signed_median']:+.5f} | {g['depth_within_1e-3'] * 100:.1f}% | "
                    f"{g['normal_err_deg']:.2f} | {g['normal_err_deg_median']:.2f} |")
    g = m["raw"]["geometry"]
    rows.append(f"| reduction | {g['surface_smape_reduction'] * 100:.1f}% | {g['surface_l1_reduction'] * 100:.1f}% | "
                f"{g['depth_err_reduction'] * 100:.1f}% | {g['depth_err_median_reduction'] * 100:.1f}% | | | "
                f"{g['normal_err_reduction'] * 100:.1f}% | {g['normal_err_median_reduction'] * 100:.1f}% |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m experiments.evaluation.evaluate_denoiser", description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("--data", default="data/pairs")
    ap.add_argument("--split", default="val")
    ap.add_argument("--max-pairs", type=int, default=256)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(a.threads)
    r = evaluate(a.model, a.data, a.split, a.max_pairs, threads=a.threads)
    r["command"] = "python -m experiments.evaluation.evaluate_denoiser " + " ".join(argv if argv is not None else __import__("sys").argv[1:])
    if a.out:
        from dss.io_utils import atomic_write_json

        atomic_write_json(a.out, r)
    print(markdown(r))


if __name__ == "__main__":
    main()
