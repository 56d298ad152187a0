"""Denoising with oracle references: what the DSS optimiser reaches when the images are perfect.

    python -m experiments.oracle_refine                      # the shipped example, 16 cycles
    python -m experiments.oracle_refine --reference identity # renders of the noisy input instead
    python -m experiments.oracle_refine --set projection_weight=0.02 repulsion_weight=0.05

The references are renders of the *clean* cloud from the same cameras (the spec's camera model,
the denoiser's point light) and the optimiser settings are dss-denoise's (``conf/denoise.yaml``),
so the run separates the optimiser from the image denoiser: if
the oracle run improves Chamfer and ``dss-denoise`` does not, the learned references are what
limits the pipeline. Prints Chamfer (paper protocol, x1e4) every ``--every`` steps and writes a
JSON with the curve (``--out``).
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

log = logging.getLogger("oracle-refine")

EXAMPLE = Path(__file__).parent / "assets" / "example"


def _value(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def denoise_optimizer_defaults(noise: float, n_points: int) -> dict:
    """The optimiser block of conf/denoise.yaml (dss-denoise's settings, ``auto`` entries resolved
    for ``noise`` as dss-denoise does, views from its default budget), so that the oracle run
    differs from the main job only in its references."""
    from omegaconf import OmegaConf

    from experiments.denoise import resolve_all_by_noise

    cfg = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "denoise.yaml")
    resolve_all_by_noise(cfg, noise, n_points)
    # the views of dss-denoise's default budget (an explicit views= there is not seen here)
    return {**OmegaConf.to_container(cfg.optimizer, resolve=True), "views": int(cfg.budgets.default.views)}


def normal_error_to_points_deg(points, normals, clean_points, clean_normals) -> float:
    """Mean angle (degrees, sign-free) between each normal and the normal of the nearest clean point."""
    import torch

    from dss.knn import knn

    j = knn(clean_points, 1, query=points).idx[:, 0]
    cos = (torch.nn.functional.normalize(normals, dim=1) * clean_normals[j]).sum(1).abs().clamp(max=1)
    return float(torch.rad2deg(torch.acos(cos)).mean())


def run(clean_path: Path, noisy_path: Path, reference: str = "clean", cycles: int = 16, image_size: int = 128,
        every: int = 40, overrides: dict | None = None, seed: int = 0, shading: str = "point") -> dict:
    from data_prep.render_spec import load_render_spec
    from dss.metrics import evaluate
    from dss.optimize import MultiViewOptimizer, OptimizerConfig
    from dss.pointcloud import estimate_normals, load_ply, normalize_unit_diagonal
    from experiments.reference_generators import SpecViewSampler

    clean = load_ply(clean_path)
    noisy = load_ply(noisy_path, compute_normals=False)
    # one normalisation for both clouds (the input's, as dss-denoise does)
    npt, center, scale = normalize_unit_diagonal(noisy.points)
    cp = (clean.points - center) / scale
    cn = clean.normals
    nn_ = estimate_normals(npt, k=16)  # as dss-denoise: never the file's (ground-truth) normals
    spec = load_render_spec(image_size=[image_size, image_size])
    settings = spec.render_settings()
    shading = spec.point_light() if shading == "point" else shading  # "sun": the paper's 3 RGB lights
    ref_p, ref_n = (cp, cn) if reference == "clean" else (npt, nn_)

    def ref(cams):
        from dss.render import render

        return render(ref_p, ref_n, cams, settings, shading=shading).images

    defaults = denoise_optimizer_defaults(0.01, len(npt))  # the example's noise level
    cfg = OptimizerConfig(**{**defaults, "cycles": cycles, "seed": seed, **(overrides or {})})
    sampler = SpecViewSampler(spec, views=cfg.views, seed=seed, jitter=cfg.view_jitter)
    curve = [{"step": 0, "chamfer": evaluate(npt, cp).chamfer}]
    log.info("input Chamfer %.3f (x1e4)", curve[0]["chamfer"])

    def callback(step, state):
        if step % every == 0:
            curve.append({"step": step, "chamfer": evaluate(state["points"], cp).chamfer})
            log.info("step %d: Chamfer %.3f", step, curve[-1]["chamfer"])

    t0 = time.perf_counter()
    opt = MultiViewOptimizer(npt, nn_, ref, cfg, settings, shading=shading, image_size=image_size, sampler=sampler,
                             callback=callback)
    res = opt.run()
    out = {"reference": reference, "clean": str(clean_path), "noisy": str(noisy_path), "optimizer": res.history["config"],
           "chamfer_input": curve[0]["chamfer"], "chamfer_output": evaluate(res.points, cp).chamfer,
           # how far the image term brings the normals toward the truth (nearest clean point's normal)
           "normal_error_deg": {"input": normal_error_to_points_deg(npt, nn_, cp, cn),
                                "output": normal_error_to_points_deg(res.points, res.normals, cp, cn)},
           "shading": "point light" if not isinstance(shading, str) else shading,
           "curve": curve, "wall_time_s": time.perf_counter() - t0, "protocol": "paper (Chamfer x1e4)"}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clean", type=Path, default=EXAMPLE / "clean.ply")
    ap.add_argument("--noisy", type=Path, default=EXAMPLE / "noisy_1pct.ply")
    ap.add_argument("--reference", choices=["clean", "identity"], default="clean")
    ap.add_argument("--cycles", type=int, default=16)
    ap.add_argument("--image-size", type=int, default=128)
    ap.add_argument("--every", type=int, default=40)
    ap.add_argument("--shading", choices=["point", "sun"], default="point",
                    help="point: the denoiser's light (default); sun: the paper's three RGB lights")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="OptimizerConfig overrides")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    overrides = {k: _value(v) for k, v in (s.split("=", 1) for s in a.set)}
    res = run(a.clean, a.noisy, a.reference, a.cycles, a.image_size, a.every, overrides, shading=a.shading)
    ne = res["normal_error_deg"]
    print(f"Chamfer x1e4: input {res['chamfer_input']:.3f} -> output {res['chamfer_output']:.3f} "
          f"({a.reference} references, {res['wall_time_s']:.0f} s); normal error {ne['input']:.1f} -> "
          f"{ne['output']:.1f} deg")
    if a.out:
        from dss.io_utils import atomic_write_json
        from experiments.figures import command_line

        res["command"] = command_line("python -m experiments.oracle_refine", argv)
        atomic_write_json(a.out, res)


if __name__ == "__main__":
    main()
