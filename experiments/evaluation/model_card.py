"""Write a model card (markdown) for a trained denoiser from its training run directory.

    python -m experiments.evaluation.model_card RUN_DIR OUT.md [--onnx OUT.onnx] [--eval EVAL.json]
        [--pipeline SUMMARY.json] [--note LINE ...]

Everything in the card comes from the run: ``config.yaml`` (model, data, trainer),
``metrics.json`` (best-checkpoint validation against the clean renders and the noisy
baseline, training time, steps, throughput) and the ONNX file's metadata. With ``--onnx`` the
run's ``denoiser.onnx`` is copied there too (atomically); with ``--eval`` the card adds the shipped
model's raw and background-snapped metrics from ``experiments.evaluation.evaluate_denoiser`` (for a model of
the ``planes`` channel: the geometry its output implies against the noisy input's); with
``--pipeline`` the denoising pipeline's results against its controls
(``experiments.evaluation.pipeline_summary`` JSON, its ``command``/``commands`` entries quoted).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from omegaconf import OmegaConf

from dss.io_utils import atomic_path, atomic_write_text


def eval_section(ev: dict) -> list[str]:
    """Markdown lines for an ``experiments.evaluation.evaluate_denoiser`` result (raw and snapped output)."""
    from experiments.evaluation.evaluate_denoiser import markdown

    if ev.get("channel") == "planes":
        return ["", f"## The shipped denoiser on the {ev['split']} split ({ev['pairs']} pairs, onnxruntime)",
                "What the planes imply, over the surface pixels (covered by the clean and the noisy render): "
                "SMAPE and L1 of the plane coefficients, the implied depth's error |z - z_clean| in bounding-box "
                "diagonals (`planes_inverse_depth`; the mean capped at 0.05), the implied normals' angle error "
                "(`planes_normals`). The noisy input's row is the identity control.", "", markdown(ev), "",
                f"`{ev.get('command', 'python -m experiments.evaluation.evaluate_denoiser')}`"]
    return ["", f"## The shipped denoiser on the {ev['split']} split ({ev['pairs']} pairs, onnxruntime)",
            "The runtime snaps pixels darker than half the renders' ambient term to the black background "
            "(`pix2pix/postprocess.py`); SMAPE split into the clean render's surface and the halo the noise "
            "spreads around it.", "", markdown(ev), "",
            f"`{ev.get('command', 'python -m experiments.evaluation.evaluate_denoiser')}`"]


def pipeline_section(p: dict) -> list[str]:
    """Markdown lines for an ``experiments.evaluation.pipeline_summary`` result."""
    from experiments.evaluation.pipeline_summary import markdown

    lines = ["", "## In the denoising pipeline (dss-denoise: DSS, then the plane fusion)", ""]
    lines += [str(x) for x in p.get("notes", [])]
    lines += ["", markdown(p), ""]
    lines += [f"`{c}`" + "  " for c in p.get("commands", [])]
    return lines


def _render(run_dir: Path) -> dict:
    """The training data's render block (from the run's ONNX metadata), {} when unknown."""
    onnx_path = run_dir / "denoiser.onnx"
    if not onnx_path.is_file():
        return {}
    from pix2pix.export import read_metadata

    return read_metadata(onnx_path).get("dss.render_settings") or {}


def card(run_dir: Path, evaluation: dict | None = None, notes: list[str] | None = None,
         pipeline: dict | None = None) -> str:
    if _render(run_dir).get("shading") == "planes":
        return planes_card(run_dir, evaluation, notes, pipeline)
    cfg = OmegaConf.load(run_dir / "config.yaml")
    m = json.loads((run_dir / "metrics.json").read_text())
    val = m.get("best_val") or {}
    g = cfg.model.generator
    noise = m.get("noise_level")

    def f(key, fmt="{:.4f}"):
        v = val.get(key)
        return fmt.format(v) if isinstance(v, (int, float)) else "n/a"

    red = val.get("val/smape_reduction")
    shipped_red = (evaluation or {}).get("metrics", {}).get("snapped", {}).get("smape_reduction")
    target_red = shipped_red if isinstance(shipped_red, float) else red
    l1 = val.get("val/l1")
    nl1 = val.get("val/noisy_l1")
    lines = [
        f"# Denoiser model card: {cfg.get('task_name')}",
        "",
        f"Pix2Pix ResNet generator (`{cfg.model.get('name')}`: ngf {g.ngf}, {g.n_blocks} residual blocks, "
        f"{'residual' if g.get('residual') else 'direct'} prediction, pixel-wise normalisation, no final tanh"
        + (", a coverage head that outputs exact 0 where it predicts no clean surface" if g.get("coverage_head") else "")
        + ") "
        f"with a 70x70 PatchGAN, LSGAN + L1. Trained for one noise level: Gaussian std "
        f"{noise} of the bounding-box diagonal.",
        "",
        "## Training",
        f"- data: `{_short(cfg.data.get('root'))}` (dss-prep `cpu` preset: generated shapes, 128x128 point-light renders, "
        f"split by shape), noise level {noise}",
        f"- {m.get('global_step')} optimiser steps (G and D counted separately by Lightning), epoch {m.get('epoch')}, "
        f"{(m.get('fit_seconds') or 0) / 60:.1f} min on the 2-core CPU, {m.get('torch_threads')} torch thread(s), "
        f"{(m.get('train_images_per_s') or 0):.1f} images/s",
        f"- best checkpoint: `{Path(m.get('best_ckpt') or '').name}`",
        (f"- resumed from `{_short(m['resumed_from'], 3)}`: the time above is this run's only (the Lightning timer "
         "counted the earlier run's time against trainer.max_time)") if m.get("resumed_from") else None,
        (f"- generator warm-started from `{_short(cfg.model.init_from, 3)}` (the time above is this run's only; "
         "that model's training comes on top)") if cfg.model.get("init_from") else None,
        *[f"- {n}" for n in notes or []],
        "",
        "## Validation (best checkpoint, pixels covered in either render)",
        "| | output vs clean | noisy input vs clean |",
        "|---|---|---|",
        f"| SMAPE (paper, sum over channels) | {f('val/smape')} | {f('val/noisy_smape')} |",
        f"| L1 | {f('val/l1')} | {f('val/noisy_l1')} |",
        f"| PSNR (dB) | {f('val/psnr', '{:.2f}')} | {f('val/noisy_psnr', '{:.2f}')} |",
        "",
        f"SMAPE reduction relative to the noisy input: {red * 100:.1f}%" if isinstance(red, float) else "",
        f"L1 reduction: {(1 - l1 / nl1) * 100:.1f}%" if isinstance(l1, float) and nl1 else "",
        *(eval_section(evaluation) if evaluation else []),
        "",
        "## Limitations",
        f"- A CPU-sized model trained for {(m.get('fit_seconds') or 0) / 60:.0f} min"
        + (" in its last run (resumed; the earlier run's time comes on top)" if m.get("resumed_from") else "")
        + (" after its warm start (the warm-start model's training comes on top)" if cfg.model.get("init_from") else "")
        + " on ~4.6K pairs; the paper's model (ngf 64, 9 blocks, 256 px) "
        "trained for two days on a GPU. The issue's target (SMAPE -30% vs the noisy input) is "
        + (f"met by the shipped (snapped) output ({target_red * 100:.1f}%)." if isinstance(target_red, float)
           and target_red >= 0.3 else "NOT met by this model."),
        "- Trained on 128x128 renders of generated shapes with the point light of `conf/render/pairs.yaml`; "
        "the pipeline renders test views with that same setting (it is stored in the ONNX metadata).",
        "",
        "Generated by `python -m experiments.evaluation.model_card` from the training run.",
    ]
    return "\n".join(x for x in lines if x is not None) + "\n"


def planes_card(run_dir: Path, evaluation: dict | None = None, notes: list[str] | None = None,
                pipeline: dict | None = None) -> str:
    """The card of a ``planes`` model: its losses, the geometry its output implies, the pipeline."""
    cfg = OmegaConf.load(run_dir / "config.yaml")
    m = json.loads((run_dir / "metrics.json").read_text())
    val = m.get("best_val") or {}
    render = _render(run_dir)
    g = cfg.model.generator
    noise = m.get("noise_level")
    gan = cfg.model.get("discriminator") is not None and float(cfg.model.get("lambda_gan", 0)) > 0
    loss = (f"{cfg.model.lambda_l1:g} x L1 on the plane coefficients + {cfg.model.get('lambda_depth', 0):g} x L1 of "
            f"the implied inverse depth + {cfg.model.get('lambda_normal', 0):g} x (1 - cos) of the planes' directions"
            + (f" + {cfg.model.lambda_gan:g} x LSGAN (70x70 PatchGAN)" if gan else ", no GAN term"))

    def f(key, fmt="{:.4f}"):
        v = val.get(key)
        return fmt.format(v) if isinstance(v, (int, float)) else "n/a"

    size = render.get("image_size")
    ev_geo = ((evaluation or {}).get("metrics", {}).get("raw", {}) or {}).get("geometry") or {}
    smape_red = ev_geo.get("surface_smape_reduction", val.get("val/surface_smape_reduction"))
    lines = [
        f"# Denoiser model card: {cfg.get('task_name')}",
        "",
        f"Pix2Pix ResNet generator (`{cfg.model.get('name')}`: ngf {g.ngf}, {g.n_blocks} residual blocks, "
        f"{'residual' if g.get('residual') else 'direct'} prediction, pixel-wise normalisation, no final tanh, "
        f"per-channel input normalisation mean {list(g.input_mean) if not isinstance(g.input_mean, float) else g.input_mean}"
        f" / std {list(g.input_std) if not isinstance(g.input_std, float) else g.input_std}) in the **planes** channel "
        "(`conf/render/planes.yaml`: every pixel holds the camera-space plane `a` of the surface it shows, "
        "`1/z = a . (x, y, 1)`; `dss-denoise` renders its views in this channel and reads the network's planes "
        f"back in the plane fusion, `dss/fusion.py`). Trained for one noise level: Gaussian std {noise} of the "
        "bounding-box diagonal. Loss: " + loss + ".",
        "",
        "## Training",
        f"- data: `{_short(cfg.data.get('root'))}` (dss-prep `cpu_planes` preset: the `cpu` preset's generated shapes, "
        f"seeds and split by shape, rendered at {size} px in the planes channel), noise level {noise}; "
        f"{cfg.model.get('train_crop_size')} px crops (drawn on the surface: `data.crop_min_coverage` "
        f"{cfg.data.get('crop_min_coverage', 0)}), the planes flips (`pix2pix/augment.py`), batch {cfg.data.batch_size}",
        f"- {m.get('global_step')} optimiser steps, epoch {m.get('epoch')}, {(m.get('fit_seconds') or 0) / 60:.1f} min "
        f"on the shared 2-core CPU (no GPU), {m.get('torch_threads')} torch thread(s), "
        f"{(m.get('train_images_per_s') or 0):.1f} crops/s; the paper-sized generator (9 blocks, ngf 64, 256 px) "
        "was not trained (no GPU)",
        f"- best checkpoint (lowest `val/depth_err`): `{Path(m.get('best_ckpt') or '').name}`",
        (f"- generator warm-started from `{_short(cfg.model.init_from, 3)}` (the time above is this run's only; "
         "that model's training comes on top)") if cfg.model.get("init_from") else None,
        *[f"- {n}" for n in notes or []],
        "",
        "## Validation (best checkpoint, Lightning, surface pixels: covered by the clean and the noisy render)",
        "| | output | noisy input (identity) | reduction |",
        "|---|---|---|---|",
        f"| surface SMAPE (sum over the 3 coefficients) | {f('val/surface_smape')} | {f('val/noisy_surface_smape')} | "
        f"{f('val/surface_smape_reduction', '{:.1%}')} |",
        f"| surface L1 | {f('val/surface_l1')} | {f('val/noisy_surface_l1')} | |",
        f"| implied depth error, mean capped at 0.05 (bbox diagonals) | {f('val/depth_err', '{:.5f}')} | "
        f"{f('val/noisy_depth_err', '{:.5f}')} | {f('val/depth_err_reduction', '{:.1%}')} |",
        f"| implied depth bias (signed, bbox diagonals) | {f('val/depth_bias', '{:+.5f}')} | "
        f"{f('val/noisy_depth_bias', '{:+.5f}')} | |",
        f"| share of pixels with depth error < 0.001 | {f('val/depth_within_1e-3', '{:.1%}')} | "
        f"{f('val/noisy_depth_within_1e-3', '{:.1%}')} | |",
        f"| implied normal error, mean (deg) | {f('val/normal_err_deg', '{:.2f}')} | {f('val/noisy_normal_err_deg', '{:.2f}')} | "
        f"{f('val/normal_err_reduction', '{:.1%}')} |",
        *(eval_section(evaluation) if evaluation else []),
        *(pipeline_section(pipeline) if pipeline else []),
        "",
        "## Limitations",
        f"- A CPU-sized model trained for {(m.get('fit_seconds') or 0) / 60:.0f} min"
        + (" after its warm start" if cfg.model.get("init_from") else "")
        + " on the generated shapes; the paper-sized generator on a GPU is not trained here.",
        "- The issue's pixel target (surface SMAPE at least 30% below the noisy input's on the validation split) is "
        + (f"met ({smape_red:.1%})." if isinstance(smape_red, float) and smape_red >= 0.3 else
           (f"NOT met ({smape_red:.1%})." if isinstance(smape_red, float) else "not measured.")),
        f"- Renders at {size} px in the planes channel only: the pipeline takes the channel and size from this "
        "file's metadata (`dss.render_settings`).",
        "",
        "Generated by `python -m experiments.evaluation.model_card` from the training run.",
    ]
    return "\n".join(x for x in lines if x is not None) + "\n"


def _short(path, keep: int = 2) -> str:
    """The last ``keep`` components of a path: cards must not carry one machine's absolute paths."""
    if not path:
        return str(path)
    p = Path(str(path))
    return str(Path(*p.parts[-keep:])) if p.is_absolute() else str(p)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--onnx", type=Path, default=None)
    ap.add_argument("--eval", type=Path, default=None,
                    help="JSON written by python -m experiments.evaluation.evaluate_denoiser for this model")
    ap.add_argument("--pipeline", type=Path, default=None,
                    help="JSON written by python -m experiments.evaluation.pipeline_summary (+ notes, commands)")
    ap.add_argument("--note", action="append", default=[],
                    help="a line added to the card's Training section (repeatable), e.g. the warm start's history")
    a = ap.parse_args(argv)
    ev = json.loads(a.eval.read_text()) if a.eval else None
    pipe = json.loads(a.pipeline.read_text()) if a.pipeline else None
    atomic_write_text(a.out, card(a.run_dir, ev, a.note, pipe))
    if a.onnx is not None:
        with atomic_path(a.onnx) as tmp:
            shutil.copyfile(a.run_dir / "denoiser.onnx", tmp)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
