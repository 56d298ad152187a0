"""Where the image information goes: dss-denoise stage by stage, oracle against identity references.

    python -m experiments.evaluation.image_study                                   # the shipped example
    python -m experiments.evaluation.image_study --references oracle identity onnx # + the shipped model
    python -m experiments.evaluation.image_study --set fusion.enabled=false        # any dss-denoise override
    python -m experiments.evaluation.image_study --input noisy.ply --clean clean.ply --mesh mesh.ply --noise 0.01

Runs the denoising job (``conf/denoise.yaml`` with the given overrides) once per reference and
records, per DSS cycle: the fraction of points visible at some pixel of the cycle's views (they
receive the image gradient; the others sit behind their neighbours' splats) and of points ever
seen, the normal error of the optimised normals on seen and on hidden points, the error of the
PCA refit the next cycle starts from, Chamfer / Hausdorff; per plane-fusion pass: the fraction
of points observed, the mean consistency, Chamfer, the normal error of the references' normals
against a PCA fit of the same points; and the written result (dss-denoise's metrics). Needs a
ground-truth mesh (normal errors: angle to the closest triangle). Writes ``image_study.json`` and
``image_study.png`` into ``--out`` (default: a fresh folder under ``outputs/image_study``).
Metrics: paper protocol (Chamfer x1e4, Hausdorff x1e3), in the input's units.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import torch

log = logging.getLogger("image-study")

__all__ = ["run", "main"]


def _compose(overrides: list[str]):
    from hydra import compose, initialize_config_dir

    conf = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        return compose("denoise", overrides=overrides)


def _seen(points, normals, cams, settings, shading, backend) -> torch.Tensor:
    """(N,) bool: points visible at some pixel of ``cams`` (those the image loss reaches)."""
    from dss.render import render

    with torch.no_grad():
        out = render(points, normals, cams, settings, shading=shading, backend=backend)
    idx = out.fragments.idx[out.fragments.visible].long()
    seen = torch.zeros(len(points), dtype=torch.bool)
    seen[idx.unique().cpu()] = True
    return seen


def _normal_err(points, normals, mesh, sel=None) -> float | None:
    from dss.metrics import normal_error_deg

    if sel is not None:
        if not bool(sel.any()):
            return None
        points, normals = points[sel], normals[sel]
    return normal_error_deg(points.numpy(), normals.numpy(), mesh)["mean"]


class _Recorder:
    """The optimiser's and the fusion's callbacks: per DSS cycle and per fusion pass, what the
    image reaches and how far the result is from the ground truth (input units)."""

    def __init__(self, reference: str, cloud, clean, mesh, spec, shading, ocfg):
        self.reference, self.cloud, self.clean, self.mesh = reference, cloud, clean, mesh
        self.spec, self.shading, self.settings, self.ocfg = spec, shading, spec.render_settings(), ocfg
        self.per_cycle = ocfg.normal_steps + ocfg.point_steps
        self.center = self.scale = self.seen = self.ever = None
        self.cycles: list[dict] = []
        self.passes: list[dict] = []
        self.t0 = time.perf_counter()

    def to_input(self, p):
        return p.detach().cpu() * self.scale + self.center

    def cycle(self, step, st):
        from dss.metrics import evaluate
        from dss.pointcloud import estimate_normals, normalize_unit_diagonal

        p, n = st["points"].detach().cpu(), st["normals"].detach().cpu()
        if self.scale is None:  # the optimiser works in the normalised frame of the inliers
            _, self.center, self.scale = normalize_unit_diagonal(self.cloud.points)
        if step % self.per_cycle == 1 or self.per_cycle == 1:  # first step of a cycle: who does the image reach
            self.seen = _seen(p, n, st["cameras"].to("cpu"), self.settings, self.shading, self.spec.backend)
            self.ever = self.seen if self.ever is None else self.ever | self.seen
        if step % self.per_cycle:
            return
        pi, seen, mesh = self.to_input(p), self.seen, self.mesh  # end of the cycle
        m = evaluate(pi.numpy(), self.clean)
        refit = estimate_normals(p, k=int(self.ocfg.normal_refresh_k), orient="none")
        self.cycles.append({"cycle": int(st["cycle"]), "step": int(step), "chamfer": m.chamfer, "hausdorff": m.hausdorff,
                            "seen_fraction": float(seen.float().mean()), "seen_ever": float(self.ever.float().mean()),
                            "normal_error_seen": _normal_err(pi, n, mesh, seen),
                            "normal_error_hidden": _normal_err(pi, n, mesh, ~seen),
                            "normal_error_refit": _normal_err(pi, refit, mesh), "time_s": time.perf_counter() - self.t0})
        c = self.cycles[-1]
        log.info("%s cycle %d: Chamfer %.4f, seen %.0f%% (ever %.0f%%), normals seen %.1f / hidden %s / refit %.1f",
                 self.reference, st["cycle"], m.chamfer, 100 * c["seen_fraction"], 100 * c["seen_ever"],
                 c["normal_error_seen"] or float("nan"), c["normal_error_hidden"], c["normal_error_refit"])

    def fusion_pass(self, k, st):
        from dss.metrics import evaluate

        pi, mesh = self.to_input(st["points"]), self.mesh
        m = evaluate(pi.numpy(), self.clean)
        img_n, pca = st["image_normals"].detach().cpu(), st["normals"].detach().cpu()
        has = img_n.norm(dim=1) > 0.5
        trusted = has & (st["consistency"].detach().cpu() >= 0.5)
        self.passes.append({"pass": int(k), "chamfer": m.chamfer, "hausdorff": m.hausdorff, "observed": st["observed"],
                            "consistency_mean": st["consistency_mean"], "move_mean": st["move_mean"],
                            "spread_median": st["spread_median"], "normal_error_pca": _normal_err(pi, pca, mesh),
                            "normal_error_image": _normal_err(pi, img_n, mesh, has),
                            "normal_error_pca_where_image": _normal_err(pi, pca, mesh, has),
                            "trusted_fraction": float(trusted.float().mean()),
                            "normal_error_image_trusted": _normal_err(pi, img_n, mesh, trusted),
                            "normal_error_pca_trusted": _normal_err(pi, pca, mesh, trusted),
                            "time_s": time.perf_counter() - self.t0})
        f = self.passes[-1]
        log.info("%s fusion pass %d: Chamfer %.4f, consistency %.2f, normals image %.1f vs PCA %.1f (where seen)",
                 self.reference, k, m.chamfer, st["consistency_mean"], f["normal_error_image"] or float("nan"),
                 f["normal_error_pca_where_image"] or float("nan"))


def study_reference(base: list[str], reference: str, out: Path) -> dict:
    """One dss-denoise job with ``reference``, instrumented; returns its records."""
    from dss.metrics import evaluate
    from experiments.common import resolve_device
    from experiments.denoising import inputs, job, settings
    from experiments.denoising.references import make_reference
    from experiments.denoising.refine import normals_mode, output_normals, refine

    cfg = _compose([*base, f"reference={reference}"])
    files = inputs.input_files(cfg)
    cloud, report = job.load(cfg, files)
    cloud, _, _ = job.drop_outliers(cfg, cloud, report)
    noise = inputs.noise_level(cloud.points, inputs.noise_hint(cfg.get("noise")), files.input).used
    generator, _ = make_reference(cfg, noise)
    s = settings.resolve(cfg, noise, len(cloud), generator)
    clean, mesh, _ = inputs.load_ground_truth(files.clean, files.mesh, len(cloud), int(cfg.seed), cloud.offset)
    if mesh is None or clean is None:
        raise SystemExit("image_study needs ground truth: --clean and --mesh (the shipped example has both)")
    rec = _Recorder(reference, cloud, clean, mesh, s.spec, s.shading, s.optimizer)
    refined = refine(cloud.points, cloud.normals, generator, s.spec, s.optimizer, shading=s.shading, fusion=s.fusion,
                     noise=noise, device=resolve_device(cfg.get("device")), progress=bool(cfg.get("progress", True)),
                     desc=f"image study ({reference})", clean=clean, mesh=mesh, callback=rec.cycle,
                     fusion_callback=rec.fusion_pass)
    pts, nrm, k = refined.points, refined.normals, int(cfg.normals.k)
    mode = normals_mode(cfg.normals.get("output", "auto"), refined.history)
    m, m_in = evaluate(pts.numpy(), clean), evaluate(cloud.points.numpy(), clean)
    final = {"chamfer": m.chamfer, "hausdorff": m.hausdorff, "chamfer_input": m_in.chamfer,
             "normal_error_written": _normal_err(pts, output_normals(pts, nrm, mode, k), mesh),
             "normal_error_pca": _normal_err(pts, output_normals(pts, nrm, "pca", k), mesh),
             "normal_error_input": _normal_err(cloud.points, cloud.normals, mesh),
             "normals_output": mode, "time_s": time.perf_counter() - rec.t0}
    log.info("%s: Chamfer %.4f -> %.4f, Hausdorff %.2f, written normals %.1f deg", reference, m_in.chamfer, m.chamfer,
             m.hausdorff, final["normal_error_written"])
    return {"reference": reference, "channel": s.shading_name, "image_size": list(s.spec.image_size), "noise": noise,
            "cycles": rec.cycles, "fusion": rec.passes, "final": final, "fusion_summary": refined.history.get("fusion")}


def plot(res: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dss.io_utils import atomic_savefig

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    colors = {"oracle": "tab:green", "identity": "tab:gray", "onnx": "tab:blue", "l0": "tab:orange"}
    for r in res["runs"]:
        name, col = r["reference"], colors.get(r["reference"], None)
        cyc, fus = r["cycles"], r["fusion"]
        x = [c["cycle"] + 1 for c in cyc]
        xf = [len(cyc) + 1 + f["pass"] for f in fus]
        axes[0].plot(x + xf, [c["chamfer"] for c in cyc] + [f["chamfer"] for f in fus], "-o", ms=3, color=col, label=name)
        axes[0].plot([len(cyc) + len(fus) + 1], [r["final"]["chamfer"]], "*", ms=12, color=col)
        axes[1].plot(x, [c["normal_error_seen"] for c in cyc], "-", color=col, label=f"{name}: seen (optimised)")
        axes[1].plot(x, [c["normal_error_hidden"] for c in cyc], "--", color=col, label=f"{name}: hidden")
        axes[1].plot(x, [c["normal_error_refit"] for c in cyc], ":", color=col, label=f"{name}: PCA refit")
        if fus:
            axes[1].plot(xf, [f["normal_error_image"] for f in fus], "s", color=col, label=f"{name}: fusion, image")
            axes[1].plot(xf, [f["normal_error_pca_where_image"] for f in fus], "^", color=col,
                         label=f"{name}: fusion, PCA")
        axes[2].plot(x, [c["seen_fraction"] for c in cyc], "-", color=col, label=f"{name}: seen this cycle")
        axes[2].plot(x, [c["seen_ever"] for c in cyc], "--", color=col, label=f"{name}: ever seen")
        if fus:
            axes[2].plot(xf, [f["consistency_mean"] for f in fus], "s", color=col, label=f"{name}: fusion consistency")
    for ax, t, yl in zip(axes, ["Chamfer x1e4 (paper), * = written result", "normal error (deg, to the mesh)",
                                "fraction of points"], ["Chamfer x1e4", "degrees", "fraction"]):
        ax.set_title(t, fontsize=10)
        ax.set_xlabel("DSS cycle, then plane-fusion pass")
        ax.set_ylabel(yl)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[1].legend(fontsize=6, ncol=2)
    axes[2].legend(fontsize=6)
    fig.suptitle(res.get("title", "image study"), fontsize=10)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)
    return path


def title(references: list[str], overrides: list[str]) -> str:
    shown = [o for o in overrides if not o.startswith("progress=")]
    return f"dss-denoise stage by stage ({', '.join(references)}); {' '.join(shown) or 'the shipped example, defaults'}"


def run(references: list[str], overrides: list[str], out: Path, command: str = "") -> dict:
    from dss.io_utils import atomic_write_json

    out.mkdir(parents=True, exist_ok=True)
    runs = [study_reference(overrides, r, out) for r in references]
    res = {"command": command, "overrides": overrides, "references": references, "runs": runs,
           "protocol": "paper (Chamfer x1e4, Hausdorff x1e3, input units)",
           "title": title(references, overrides)}
    atomic_write_json(out / "image_study.json", res)
    plot(res, out / "image_study.png")
    return res


def main(argv=None):
    import sys

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--references", nargs="+", default=["oracle", "identity"],
                    help="conf/reference entries (oracle, identity, onnx, l0, ...)")
    ap.add_argument("--input", default=None, help="noisy cloud (default: the shipped example)")
    ap.add_argument("--clean", default=None)
    ap.add_argument("--mesh", default=None)
    ap.add_argument("--noise", type=float, default=None, help="noise hint (std, fraction of the bbox diagonal)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="dss-denoise overrides")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    overrides = ["progress=false", *a.set]
    for key in ("input", "clean", "mesh", "noise"):
        if getattr(a, key) is not None:
            overrides.append(f"{key}={getattr(a, key)}")
    out = a.out or Path("outputs/image_study") / time.strftime("%Y-%m-%d_%H-%M-%S")
    from experiments.figures import command_line

    res = run(a.references, overrides, out, command_line("python -m experiments.evaluation.image_study", argv))
    for r in res["runs"]:
        f = r["final"]
        print(f"{r['reference']:>9s}: Chamfer x1e4 {f['chamfer_input']:.3f} -> {f['chamfer']:.3f}, Hausdorff x1e3 "
              f"{f['hausdorff']:.2f}, written normals {f['normal_error_written']:.1f} deg (PCA of the same points "
              f"{f['normal_error_pca']:.1f})")
    print(f"wrote {out / 'image_study.json'} and {out / 'image_study.png'}", file=sys.stderr)


if __name__ == "__main__":
    main()
