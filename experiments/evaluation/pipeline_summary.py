"""Summarise dss-denoise runs (a model against its controls) as JSON and a markdown table.

    python -m experiments.evaluation.pipeline_summary --run model=RUN_DIR --run identity=RUN_DIR [--run oracle=RUN_DIR]
        [--table TABLE_OUT_DIR] [--methods dss_pix2pix,dss_identity] [--out summary.json] [--md summary.md]

Each ``--run LABEL=DIR`` is a ``dss-denoise`` run directory (its ``metrics.json``); ``--table``
adds every DSS run of a ``dss-denoise-table`` output folder (``runs/<case>/<method>/``), one row
per (case, method), and the mean over the cases each method has. Reported per run (paper
protocol): Chamfer x1e4, Hausdorff x1e3, P2M x1e4, the written normals' mean angle to the
ground-truth mesh (``normal_error_deg.output``, degrees), the plane fusion's mean consistency
and the share of points that took the references' normals, and the optimisation's wall time.
Ratios to the identity control (a run or method whose label contains ``identity``) are given
per case where it is there.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

__all__ = ["run_row", "summarise", "markdown"]


def run_row(run_dir: str | Path) -> dict:
    """One run's numbers from its ``metrics.json``."""
    run_dir = Path(run_dir)
    m = json.loads((run_dir / "metrics.json").read_text())
    out = (m.get("summary") or {}).get("output", {}).get("paper", {})
    ne = m.get("normal_error_deg") or {}
    fu = m.get("fusion") or {}
    ref = m.get("reference") or {}
    return {"run_dir": str(run_dir), "reference": ref.get("name"), "model": ref.get("model"),
            "chamfer": out.get("chamfer"), "hausdorff": out.get("hausdorff"), "p2m": out.get("p2m"),
            "normal_err_deg": (ne.get("output") or {}).get("mean"),
            "normal_err_deg_pca": (ne.get("pca") or {}).get("mean"),
            "consistency": fu.get("consistency_mean"), "image_normals": fu.get("image_normals"),
            "seconds": (m.get("time_s") or {}).get("optimization"), "seed": _seed(run_dir)}


def _seed(run_dir: Path):
    cfg = run_dir / "config.yaml"
    if not cfg.is_file():
        return None
    from omegaconf import OmegaConf

    return OmegaConf.load(cfg).get("seed")


KEYS = ("chamfer", "hausdorff", "p2m", "normal_err_deg", "consistency", "image_normals", "seconds")


def summarise(runs: dict[str, str | Path], table: str | Path | None = None, methods: list[str] | None = None) -> dict:
    """``{"rows": [{case, label, ...}], "means": {label: {...}}}``."""
    rows = [{"case": "run", "label": label, **run_row(d)} for label, d in runs.items()]
    if table is not None:
        base = Path(table) / "runs"
        for case in sorted(p for p in base.iterdir() if p.is_dir()):
            for mdir in sorted(p for p in case.iterdir() if p.is_dir()):
                if methods and mdir.name not in methods:
                    continue
                if (mdir / "metrics.json").is_file():
                    rows.append({"case": case.name, "label": mdir.name, **run_row(mdir)})
    for r in rows:  # ratios to the identity control of the same case
        ident = next((q for q in rows if q["case"] == r["case"] and "identity" in q["label"]), None)
        if ident is not None and r is not ident:
            for k in ("chamfer", "hausdorff", "normal_err_deg"):
                if r.get(k) is not None and ident.get(k):
                    r[f"{k}_vs_identity"] = r[k] / ident[k]
    means = {}
    cases = sorted({r["case"] for r in rows if r["case"] != "run"})
    for label in sorted({r["label"] for r in rows if r["case"] != "run"}):
        mine = [r for r in rows if r["label"] == label and r["case"] != "run"]
        means[label] = {"cases": len(mine), "of": len(cases),
                        **{k: _mean([r.get(k) for r in mine]) for k in KEYS}}
    return {"rows": rows, "means": means}


def _mean(vals):
    vals = [v for v in vals if v is not None]
    return sum(vals) / len(vals) if vals else None


def _f(v, fmt):
    return "-" if v is None else fmt.format(v)


def markdown(s: dict) -> str:
    head = ("| case | reference | Chamfer x1e4 | Hausdorff x1e3 | P2M x1e4 | normal error (deg) | "
            "vs identity: CD / HD / normals | fusion consistency | image normals | time (s) |")
    lines = [head, "|" + "---|" * 10]
    for r in s["rows"]:
        ratio = (" / ".join(_f(r.get(f"{k}_vs_identity"), "{:.2f}") for k in ("chamfer", "hausdorff", "normal_err_deg"))
                 if r.get("chamfer_vs_identity") is not None else "")
        lines.append(f"| {r['case']} | {r['label']} | {_f(r['chamfer'], '{:.4f}')} | {_f(r['hausdorff'], '{:.2f}')} | "
                     f"{_f(r['p2m'], '{:.4f}')} | {_f(r['normal_err_deg'], '{:.2f}')} | {ratio} | "
                     f"{_f(r['consistency'], '{:.3f}')} | {_f(r['image_normals'], '{:.2f}')} | {_f(r['seconds'], '{:.0f}')} |")
    for label, m in s["means"].items():
        lines.append(f"| **mean ({m['cases']}/{m['of']})** | {label} | {_f(m['chamfer'], '{:.4f}')} | "
                     f"{_f(m['hausdorff'], '{:.2f}')} | {_f(m['p2m'], '{:.4f}')} | {_f(m['normal_err_deg'], '{:.2f}')} | | "
                     f"{_f(m['consistency'], '{:.3f}')} | {_f(m['image_normals'], '{:.2f}')} | {_f(m['seconds'], '{:.0f}')} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.evaluation.pipeline_summary", description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", default=[], help="LABEL=RUN_DIR (repeatable)")
    ap.add_argument("--table", default=None, help="a dss-denoise-table out_dir")
    ap.add_argument("--methods", default=None, help="comma-separated table methods to keep")
    ap.add_argument("--out", default=None)
    ap.add_argument("--md", default=None)
    a = ap.parse_args(argv)
    runs = dict(r.split("=", 1) for r in a.run)
    s = summarise(runs, a.table, a.methods.split(",") if a.methods else None)
    md = markdown(s)
    from dss.io_utils import atomic_write_json, atomic_write_text

    if a.out:
        atomic_write_json(a.out, s)
    if a.md:
        atomic_write_text(a.md, md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
