"""How well ``dss.pointcloud.find_outliers`` (dss-denoise's outlier removal) finds uniform outliers,
and what it costs a cloud without them.

    python -m experiments.evaluation.outlier_study                      # -> outputs/outlier_study/<time>/outlier_study.{json,md,png}
    python -m experiments.evaluation.outlier_study --publish            # -> results/outliers/outlier_study.{json,md,png}
    python -m experiments.evaluation.outlier_study --shapes 3 --out /tmp/o.json   # quicker

Cases: dss-denoise-table's (kangaroo and the first ``--shapes`` generated test shapes), made by
its case generator (``experiments.evaluation.table.cases.make_case_arrays``: Poisson-disk samples, Gaussian noise, outliers uniform
in the clean cloud's bounding box). Settings: points / noise / outlier fraction as in the
stability sweep's outlier axis and the paper tables. Per case and setting: outliers found, the
outliers kept that lie more than 3 noise sigmas (at least 0.3% of the diagonal) off the clean
surface ("far kept"), inliers removed, and the Chamfer distance (paper protocol, x1e4) of the
*noisy* cloud as given, after the removal, and after removing exactly the true outliers (the
best any removal can do). DSS is not run: this isolates the removal step.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger("outlier-study")

ROOT = Path(__file__).resolve().parents[2]
# (points, noise std / bbox diagonal, outlier fraction of points)
SETTINGS = [(10000, 0.01, 0.1), (10000, 0.01, 0.03), (10000, 0.01, 0.01), (20000, 0.01, 0.0),
            (20000, 0.02, 0.0), (100000, 0.003, 0.0)]


def _true_outliers(noisy: np.ndarray, base: np.ndarray) -> np.ndarray:
    """(N,) bool: rows of ``noisy`` that are not rows of ``base`` (the noisy cloud before the
    outliers were added and the rows shuffled)."""
    row = np.dtype([("", noisy.dtype)] * 3)
    return ~np.isin(np.ascontiguousarray(noisy).view(row).ravel(), np.ascontiguousarray(base).view(row).ravel())


def study_case(case: dict, points: int, noise: float, outliers: float, params: dict) -> dict:
    from dss.knn import knn
    from dss.metrics import evaluate
    from dss.pointcloud import find_outliers
    from experiments.evaluation.table.cases import make_case_arrays

    _, clean, noisy, _ = make_case_arrays(case, points, noise, 0, outliers)
    is_out = _true_outliers(noisy, make_case_arrays(case, points, noise, 0, 0.0)[2]) if outliers else \
        np.zeros(len(noisy), bool)
    t0 = time.perf_counter()
    flagged = find_outliers(torch.from_numpy(noisy), **params).numpy()
    seconds = time.perf_counter() - t0
    diag = float(np.linalg.norm(clean.points.max(0) - clean.points.min(0)))
    off = knn(torch.from_numpy(clean.points).double(), 1, query=torch.from_numpy(noisy).double()).dist[:, 0].numpy()
    far = is_out & (off > 3 * max(noise, 0.001) * diag)

    def cd(pts):
        return float(evaluate(pts, clean.points).chamfer)

    return {"case": case["name"], "points": points, "noise": noise, "outlier_fraction": outliers,
            "outliers": int(is_out.sum()), "found": int((flagged & is_out).sum()), "far": int(far.sum()),
            "far_kept": int((far & ~flagged).sum()), "inliers_removed": int((flagged & ~is_out).sum()),
            "chamfer_input": cd(noisy), "chamfer_removed": cd(noisy[~flagged]),
            "chamfer_true_removed": cd(noisy[~is_out]), "seconds": seconds}


def summarize(rows: list[dict]) -> list[dict]:
    out = []
    for setting in dict.fromkeys((r["points"], r["noise"], r["outlier_fraction"]) for r in rows):
        rs = [r for r in rows if (r["points"], r["noise"], r["outlier_fraction"]) == setting]
        n_out, n_far = sum(r["outliers"] for r in rs), sum(r["far"] for r in rs)
        out.append({"points": setting[0], "noise": setting[1], "outlier_fraction": setting[2], "cases": len(rs),
                    "found_fraction": sum(r["found"] for r in rs) / n_out if n_out else None,
                    "far_found_fraction": 1 - sum(r["far_kept"] for r in rs) / n_far if n_far else None,
                    "inliers_removed_max": max(r["inliers_removed"] for r in rs),
                    "inliers_removed_fraction_max": max(r["inliers_removed"] / (r["points"]) for r in rs),
                    **{k: float(np.mean([r[k] for r in rs]))
                       for k in ("chamfer_input", "chamfer_removed", "chamfer_true_removed", "seconds")}})
    return out


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f}%"


def render_markdown(summary: list[dict], command: str, params: dict) -> str:
    lines = ["# Outlier removal before DSS (`dss.pointcloud.find_outliers`)", "",
             f"`{command}`; parameters {params} (conf/denoise.yaml `outliers`). Means over the cases; "
             "Chamfer x1e4 (paper protocol) of the noisy cloud, not of a denoised one.", "",
             "| points | noise | outliers | cases | outliers found | far ones found | inliers removed (max) "
             "| CD as given | CD after removal | CD, true outliers removed | seconds |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in summary:
        lines.append(f"| {s['points']} | {s['noise']:g} | {s['outlier_fraction']:g} | {s['cases']} | "
                     f"{_pct(s['found_fraction'])} | {_pct(s['far_found_fraction'])} | {s['inliers_removed_max']} "
                     f"({_pct(s['inliers_removed_fraction_max'])}) | {s['chamfer_input']:.4g} | "
                     f"{s['chamfer_removed']:.4g} | {s['chamfer_true_removed']:.4g} | {s['seconds']:.2f} |")
    lines += ["", "\"far\": more than 3 noise sigmas (at least 0.3% of the diagonal) off the clean surface; the "
              "outliers that are not far lie among the noisy samples and cost little."]
    return "\n".join(lines) + "\n"


def plot(summary: list[dict], path: Path) -> Path:
    from dss.io_utils import atomic_savefig
    from experiments.figures import setup_matplotlib

    plt = setup_matplotlib()
    labels = [f"{s['points'] // 1000}K, {100 * s['noise']:g}%\n{100 * s['outlier_fraction']:g}% outl." for s in summary]
    x = np.arange(len(summary))
    fig, ax = plt.subplots(figsize=(9, 4))
    for i, (key, name) in enumerate((("chamfer_input", "as given"), ("chamfer_removed", "after find_outliers"),
                                     ("chamfer_true_removed", "true outliers removed"))):
        ax.bar(x + (i - 1) * 0.27, [s[key] for s in summary], 0.27, label=name)
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("Chamfer x1e4 of the noisy cloud (mean over cases)")
    ax.set_title("Outlier removal before DSS")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return atomic_savefig(fig, path)


def main(argv=None) -> int:
    from omegaconf import OmegaConf

    from dss.io_utils import atomic_write_json, atomic_write_text
    from experiments.denoising.inputs import outlier_params
    from experiments.evaluation.table.cases import case_list
    from experiments.figures import command_line

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shapes", type=int, default=6, help="generated test shapes besides kangaroo (default 6)")
    from experiments import outputs

    outputs.add_arguments(ap, published="results/outliers/outlier_study.json", what="output JSON file (.md, .png beside it)")
    a = ap.parse_args(argv)
    a.out = Path(outputs.folder(a, "outlier_study", name="outlier_study.json"))
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    params = outlier_params(OmegaConf.load(ROOT / "conf" / "denoise.yaml").outliers)
    table_cfg = OmegaConf.load(ROOT / "conf" / "denoise_table.yaml")
    table_cfg.generated.count = a.shapes
    rows = []
    for case in case_list(table_cfg):
        for points, noise, outliers in SETTINGS:
            rows.append(study_case(case, points, noise, outliers, params))
            r = rows[-1]
            log.info("%s %d pts, noise %g, outliers %g: found %d/%d (far kept %d), inliers removed %d, "
                     "CD %.4g -> %.4g (true %.4g)", r["case"], points, noise, outliers, r["found"], r["outliers"],
                     r["far_kept"], r["inliers_removed"], r["chamfer_input"], r["chamfer_removed"],
                     r["chamfer_true_removed"])
    summary = summarize(rows)
    command = command_line("python -m experiments.evaluation.outlier_study", argv)
    worst = summary[0]
    what = (f"outlier removal: {worst['outlier_fraction']:g} uniform outliers at {worst['points']} points, "
            f"{worst['noise']:g} noise: {_pct(worst['far_found_fraction'])} of the far ones found, "
            f"noisy-cloud CD {worst['chamfer_input']:.3g} -> {worst['chamfer_removed']:.3g}")
    atomic_write_json(a.out, {"what": what, "command": command, "params": params, "summary": summary, "rows": rows})
    atomic_write_text(a.out.with_suffix(".md"), render_markdown(summary, command, params))
    plot(summary, a.out.with_suffix(".png"))
    print(render_markdown(summary, command, params))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
