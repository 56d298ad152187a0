"""``dss-real-bench``: dss-denoise against the best classical result on detailed real meshes.

    dss-real-bench                                  # 20K points, noise 0.25/0.5/1/1.5%, 2 seeds
    dss-real-bench 'groups=[tuning]' 'seeds=[0]'    # the cases settings are chosen on
    dss-real-bench out_dir=outputs/dss-real-bench/<date>   # resume that run
    dss-real-bench publish=true                     # + the report under results/denoise/real_<points>

Cases: every mesh of ``groups`` (``data_prep/real_split.yaml``: ``tuning``, ``held_out``,
``open``; installed by ``dss-data real``), at each of ``points`` x ``noise`` x ``seeds``:
Poisson-disk samples of the mesh (the clean cloud) plus Gaussian noise of std ``noise`` x the
bbox diagonal per axis (the noisy input), made and cached as ``dss-denoise-table`` makes them
(:func:`experiments.evaluation.table.cases.prepare_case`). Meshes that are not installed or not
usable are listed with their reason, never dropped from a mean silently.

Methods: the DSS variants of ``dss_methods`` (dss-denoise subprocesses; with ``dss_noise:
estimate`` they estimate the noise as they would on a user's scan) and every entry of
``classical`` (a method of :mod:`experiments.evaluation.baselines` with fixed parameters). Per
case, **best classical** is the lowest value of each metric over all classical entries, chosen
with the ground truth: the strongest comparison, which no user could reproduce without it.

Metrics (paper protocol: the clean cloud's bbox diagonal = 1): CD x1e4, HD x1e3, P2M x1e4, the
one-sided Hausdorff distances and their 99th percentiles
(:func:`dss.metrics.detail_metrics`), the normal error (the written normals; PCA normals of
the output for methods that write none) over all clean points and over the most curved tenth, and
CPU seconds per case (one thread: DSS's whole job without ground-truth scoring and figures; a
classical method's call in its worker).

Outputs in ``out_dir``: ``records/<case>/<method>.json`` (reused by a rerun), ``report.json``
(every record and the summaries), ``report.md`` (per noise level and group: means over shapes and
seeds; per-case tables), ``accuracy_vs_time_<points>_<noise>.png`` per level, ``README.md`` (the
command). ``publish=true`` copies those (not the clouds) to ``published_dir``.
"""

from __future__ import annotations

import logging
import math
import os
import shlex
import sys
import time
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from experiments.evaluation.table.cases import (
    load_case,
    plain,
    prepare_case,
    resolve_repo_path,
    safe_name,
)
from experiments.evaluation.table.report import fmt, label_points
from experiments.evaluation.table.runners import (
    read_json,
    reference_record,
    reusable,
    run_baseline,
    run_dss,
    versions,
)

log = logging.getLogger(__name__)

__all__ = ["run", "main", "bench_cases", "summarize_bench", "render_report", "PAPER_LABEL_FACTOR"]

#: The DSS paper's test data labelled "1% noise" measures a per-axis std of about 0.5% of the
#: bbox diagonal (a statue of its test set), so the paper's labels are about twice our levels.
PAPER_LABEL_FACTOR = 2.0
#: the metrics each record carries (report units), lower is better
KEYS = ("chamfer", "hausdorff", "p2m", "hausdorff_gt_to_pred", "gt_to_pred_p99", "normal_error_all_deg",
        "normal_error_curved_deg")
NAMES = {"chamfer": "CD", "hausdorff": "HD", "p2m": "P2M", "hausdorff_gt_to_pred": "HD clean->out",
         "gt_to_pred_p99": "p99 clean->out", "normal_error_all_deg": "normals (deg)",
         "normal_error_curved_deg": "normals, curved (deg)"}
#: profile stages of a dss-denoise run that score against ground truth or draw (not the method's work)
NOT_THE_METHOD = ("ground_truth", "metrics", "chamfer_floor", "figures")


def face_scan_case() -> dict | None:
    """pymeshlab's face range scan (an open surface) as an ``open`` case, or None without pymeshlab."""
    try:
        import pymeshlab
    except ImportError:
        return None
    path = Path(pymeshlab.__file__).parent / "tests" / "sample_meshes" / "rangemaps" / "face000.ply"
    return {"name": "face_scan", "mesh": str(path), "group": "open", "held_out": True} if path.is_file() else None


def bench_cases(cfg: DictConfig) -> tuple[list[dict], list[dict]]:
    """(shape cases ``{name, mesh, group, held_out}``, skipped ``{name, group, reason}``)."""
    from data_prep.real_meshes import real_cases

    groups = [str(g) for g in cfg.groups]
    cases, skipped = real_cases(groups, resolve_repo_path(str(cfg.real_root)))
    if "open" in groups and cfg.get("face_scan", True):
        face = face_scan_case()
        if face is None:
            skipped.append({"name": "face_scan", "group": "open",
                            "reason": "pymeshlab (the baselines extra) with its sample meshes is not installed"})
        else:
            cases.append(face)
    n = cfg.get("shapes_per_group")
    if n is not None:
        cases = [c for g in groups for c in [c for c in cases if c["group"] == g][:int(n)]]
    return cases, skipped


def _case_id(name: str, points: int, noise: float, seed: int) -> str:
    return safe_name(f"{name}_{points // 1000}k_n{noise:g}_s{seed}")


def _read_normals(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(points, normals or None) of a PLY that a method wrote."""
    from dss.pointcloud import load_ply

    pc = load_ply(path, compute_normals=False)
    return pc.points.double().numpy(), None if pc.normals is None else pc.normals.double().numpy()


def _extra_metrics(pts: np.ndarray, normals: np.ndarray | None, gt: dict) -> dict:
    """:func:`dss.metrics.detail_metrics` of an output, with PCA normals where it wrote none."""
    from dss.metrics import detail_metrics
    from dss.pointcloud import estimate_normals

    if normals is None:
        import torch

        normals = estimate_normals(torch.from_numpy(np.asarray(pts, np.float32)), k=16, orient="none").double().numpy()
    return detail_metrics(pts, gt["clean"], "paper", normals, gt["clean_normals"])


def _dss_cpu(run_dir: Path) -> float | None:
    """CPU seconds of a dss-denoise run's own work (its profile without ground truth and figures)."""
    m = read_json(run_dir / "metrics.json") or {}
    prof = m.get("profile_cpu_s") or {}
    vals = [v for k, v in prof.items() if k not in NOT_THE_METHOD and isinstance(v, (int, float))]
    return float(sum(vals)) if vals else None


def _dss_noise(run_dir: Path) -> dict:
    m = read_json(run_dir / "metrics.json") or {}
    return m.get("noise") or {}


def _run_case(cfg: DictConfig, out: Path, case: dict, points: int, noise: float, seed: int, bar) -> list[dict]:
    """Every method on one (shape, points, noise, seed); their records (reused where stored)."""
    from dss.io_utils import atomic_write_json

    cid = _case_id(case["name"], points, noise, seed)
    cdir, rdir = out / "cases" / cid, out / "records" / cid
    shape = {k: v for k, v in case.items() if k in ("name", "mesh")}
    meta = prepare_case(shape, cdir, points, noise, seed, bool(cfg.get("overwrite", False)))
    info = {"case": cid, "shape": case["name"], "group": case["group"], "points": points, "noise": noise,
            "seed": seed}
    if meta["status"] == "skipped":
        return [{**info, "method": "input", "status": "skipped", "message": meta["reason"]}]
    if meta.get("remade"):
        for f in rdir.glob("*.json"):
            f.unlink()
    rdir.mkdir(parents=True, exist_ok=True)
    gt = load_case(cdir)
    gt["protocol"] = "paper"
    from dss.pointcloud import load_ply

    gt["clean_normals"] = load_ply(cdir / "clean.ply", compute_normals=False).normals.double().numpy()
    threads = int(cfg.threads) if cfg.get("threads") else None
    overwrite = bool(cfg.get("overwrite", False))
    records = []
    ipath = rdir / "input.json"
    rec = None if overwrite else read_json(ipath)
    if rec is None:
        rec = reference_record("input", cid, gt["noisy"], gt)
        rec["metrics"].update(_extra_metrics(gt["noisy"], None, gt))
        atomic_write_json(ipath, rec)
    records.append({**rec, **info, "method": "input"})
    gt["input_chamfer"] = rec["metrics"]["chamfer"]
    given = str(cfg.get("dss_noise", "estimate")) == "given"
    for label, req, kind in _requests(cfg, seed, given):
        path = rdir / f"{safe_name(label)}.json"
        limit = float(cfg.time_limit_s)
        old = None if overwrite else read_json(path)
        if reusable(old, req, limit) and old.get("status") != "crash":  # a crash is retried
            records.append({**old, **info, "method": label})
            bar.update(1)
            continue
        bar.set_description(f"{cid}: {label}")
        out_ply = out / "outputs" / cid / f"{safe_name(label)}.ply"
        if kind == "dss":
            run_dir = out / "runs" / cid / safe_name(label)
            rec = run_dss(req["overrides"], cdir, gt, noise, limit, threads, run_dir, None)
            if rec.get("metrics"):
                pts, nrm = _read_normals(run_dir / "denoised.ply")
                rec["metrics"].update(_extra_metrics(pts, nrm, gt))
                rec["cpu_s"] = _dss_cpu(run_dir)
                rec["noise_used"] = _dss_noise(run_dir)
        else:
            rec = run_baseline(req["spec"], gt, req["params"], limit, threads, out_ply)
            if rec.get("metrics"):
                pts, _ = _read_normals(out_ply)
                rec["metrics"].update(_extra_metrics(pts, None, gt))
            if out_ply.is_file():  # the classical outputs are many and cheap to remake
                out_ply.unlink()
            rec["output"] = None
        rec = {**rec, **info, "method": label, "request": req}
        atomic_write_json(path, rec)
        m = rec.get("metrics") or {}
        log.info("%s / %s: %s%s", cid, label, rec["status"],
                 f", CD {m['chamfer']:.4g} HD {m['hausdorff']:.4g}" if m.get("chamfer") is not None else "")
        records.append(rec)
        bar.update(1)
    return records


def _requests(cfg: DictConfig, seed: int, given: bool) -> list[tuple[str, dict, str]]:
    """(label, request, kind) per method: what determines a stored record besides its case."""
    out = []
    for label, ovr in (cfg.dss_methods or {}).items():
        # run_dss passes the case's level as noise=...; a later noise=null (estimate) overrides it
        o = [*plain(ovr), *plain(cfg.get("dss_overrides")), *([] if given else ["noise=null"])]
        if seed:
            o.append(f"seed={seed}")
        out.append((str(label), {"kind": "dss", "overrides": [str(x) for x in o]}, "dss"))
    for label, node in (cfg.classical or {}).items():
        out.append((str(label), {"kind": "baseline", "spec": str(node.method), "params": dict(plain(node.params))},
                    "baseline"))
    return out


# ------------------------------------------------------------------------------ summaries
def _mean(vals) -> float | None:
    vals = [v for v in vals if v is not None and math.isfinite(v)]
    return float(np.mean(vals)) if vals else None


def summarize_bench(records: list[dict], cfg: DictConfig) -> dict:
    """Per (points, noise, group): the mean over its cases of each metric for the input, each DSS
    method and the per-case best classical value (``best_classical``; ``best_classical_method``:
    how often each classical entry gave the best CD), the counts of cases where a DSS method's
    HD exceeds the input's, and the per-case rows. Means are over the cases where every row has a
    result (``n``); ``missing`` lists the cases that lack one."""
    dss = [str(k) for k in (cfg.dss_methods or {})]
    classical = [str(k) for k in (cfg.classical or {})]
    by_case: dict[str, dict] = {}
    for r in records:
        c = by_case.setdefault(r["case"], {"info": {k: r.get(k) for k in ("shape", "group", "points", "noise", "seed")},
                                           "methods": {}})
        c["methods"][r["method"]] = r
    levels: dict[tuple, dict] = {}
    for cid, c in sorted(by_case.items()):
        inf = c["info"]
        key = (inf["points"], inf["noise"], inf["group"])
        lv = levels.setdefault(key, {"points": inf["points"], "noise": inf["noise"], "group": inf["group"],
                                     "cases": {}, "missing": []})
        ms = c["methods"]
        row = {"shape": inf["shape"], "seed": inf["seed"], "values": {}, "cpu_s": {}}

        def metrics_of(label, ms=ms):  # this case's records
            r = ms.get(label)
            return (r or {}).get("metrics") if r and r.get("status") in ("ok", "worse_than_input", "reference") else None

        inp = metrics_of("input")
        cls = {lab: metrics_of(lab) for lab in classical}
        cls_ok = {lab: m for lab, m in cls.items() if m}
        if inp is None or not cls_ok or any(metrics_of(d) is None for d in dss):
            lv["missing"].append(cid)
            continue
        row["values"]["input"] = {k: inp.get(k) for k in KEYS}
        for d in dss:
            row["values"][d] = {k: metrics_of(d).get(k) for k in KEYS}
            row["cpu_s"][d] = ms[d].get("cpu_s")
            row.setdefault("noise_used", {})[d] = (ms[d].get("noise_used") or {}).get("used")
        best, which = {}, {}
        for k in KEYS:
            vals = [(m.get(k), lab) for lab, m in cls_ok.items() if m.get(k) is not None]
            if vals:
                best[k], which[k] = min(vals)
        row["values"]["best_classical"] = best
        row["best_classical_method"] = which
        row["cpu_s"]["best_classical"] = (ms[which["chamfer"]].get("cpu_s") if "chamfer" in which else None)
        row["cpu_s"].update({lab: ms[lab].get("cpu_s") for lab in cls_ok})
        row["classical"] = {lab: {k: m.get(k) for k in ("chamfer", "hausdorff")} for lab, m in cls_ok.items()}
        lv["cases"][cid] = row
    out = []
    for key in sorted(levels):
        lv = levels[key]
        rows = list(lv["cases"].values())
        labels = ["input", "best_classical", *dss]
        lv["mean"] = {lab: {k: _mean([r["values"][lab].get(k) for r in rows]) for k in KEYS} for lab in labels}
        lv["cpu_s"] = {lab: _mean([r["cpu_s"].get(lab) for r in rows]) for lab in [*dss, *classical]}
        lv["n"] = len(rows)
        lv["hd_above_input"] = {d: sum(r["values"][d]["hausdorff"] > r["values"]["input"]["hausdorff"] for r in rows)
                                for d in dss}
        wins: dict[str, int] = {}
        for r in rows:
            lab = r["best_classical_method"].get("chamfer")
            wins[lab] = wins.get(lab, 0) + 1
        lv["best_classical_method"] = dict(sorted(wins.items(), key=lambda kv: -kv[1]))
        lv["classical_mean"] = {lab: {k: _mean([r["classical"].get(lab, {}).get(k) for r in rows])
                                      for k in ("chamfer", "hausdorff")} for lab in classical}
        out.append(lv)
    return {"levels": out, "dss_methods": dss, "classical": classical}


def _ratio(a, b) -> str:
    return "-" if a is None or b is None or not b else f"{a / b:.2f}"


def render_report(summary: dict, title: str, notes: list[str], skipped: list[dict]) -> str:
    """report.md: the main table (per points, noise, group: means over shapes and seeds), then a
    per-case table per level."""
    dss = summary["dss_methods"]
    lines = [f"# {title}", "", *[f"- {n}" for n in notes], ""]
    if skipped:
        lines += ["Shapes not in the benchmark: " + "; ".join(f"{s['name']} ({s['group']}): {s['reason']}" for s in skipped), ""]
    lines += ["## Means over shapes and seeds", "",
              "CD x1e4 / HD x1e3 (paper protocol). best classical: per case, the lowest value over every classical "
              "entry (chosen with the ground truth). ratio: DSS default / best classical. HD > input: cases where "
              "the default's Hausdorff exceeds the noisy input's. CPU: seconds per case, one thread.", "",
              "| points | noise (x diag; paper's label) | group | n | input CD / HD | best classical CD / HD | "
              + " | ".join(f"{d} CD / HD" for d in dss)
              + " | default / best CD | default / best HD | HD > input | default CPU s | normals default / best (deg) |",
              "|" + "---|" * (11 + len(dss))]
    for lv in summary["levels"]:
        m = lv["mean"]
        default = dss[0] if dss else None
        cells = [f"{lv['points']}", f"{100 * lv['noise']:g}% ({100 * lv['noise'] * PAPER_LABEL_FACTOR:g}%)",
                 lv["group"], str(lv["n"]) + (f" ({len(lv['missing'])} missing)" if lv["missing"] else ""),
                 f"{fmt(m['input']['chamfer'])} / {fmt(m['input']['hausdorff'])}",
                 f"{fmt(m['best_classical']['chamfer'])} / {fmt(m['best_classical']['hausdorff'])}"]
        cells += [f"{fmt(m[d]['chamfer'])} / {fmt(m[d]['hausdorff'])}" for d in dss]
        if default:
            cells += [_ratio(m[default]["chamfer"], m["best_classical"]["chamfer"]),
                      _ratio(m[default]["hausdorff"], m["best_classical"]["hausdorff"]),
                      f"{lv['hd_above_input'][default]}/{lv['n']}", fmt(lv["cpu_s"].get(default)),
                      f"{fmt(m[default]['normal_error_all_deg'])} / {fmt(m['best_classical']['normal_error_all_deg'])}"]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "## Detail and coverage (means)", "",
              "HD clean->out: the largest distance from a clean point to the output (uncovered folds and crevices); "
              "p99: its 99th percentile (x1e3); normals, curved: mean angle at the most curved tenth of the clean "
              "points.", "",
              "| points | noise | group | method | HD clean->out | p99 clean->out | normals (deg) | normals, curved (deg) |",
              "|---|---|---|---|---|---|---|---|"]
    for lv in summary["levels"]:
        for lab in ["input", "best_classical", *dss]:
            v = lv["mean"][lab]
            lines.append(f"| {lv['points']} | {100 * lv['noise']:g}% | {lv['group']} | {lab} | "
                         f"{fmt(v['hausdorff_gt_to_pred'])} | {fmt(v['gt_to_pred_p99'])} | "
                         f"{fmt(v['normal_error_all_deg'])} | {fmt(v['normal_error_curved_deg'])} |")
    lines += ["", "## Which classical entry was best (CD), and each entry's mean", ""]
    for lv in summary["levels"]:
        best = ", ".join(f"{k} {n}" for k, n in lv["best_classical_method"].items())
        lines.append(f"- {lv['points']} points, {100 * lv['noise']:g}%, {lv['group']}: best CD from {best or '-'}")
    lines += ["", "## Per case", ""]
    for lv in summary["levels"]:
        lines += [f"### {lv['points']} points, noise {100 * lv['noise']:g}%, {lv['group']}", "",
                  "| shape | seed | input CD / HD | best classical CD / HD (entry) | "
                  + " | ".join(f"{d} CD / HD" for d in dss) + " | default noise estimate |",
                  "|" + "---|" * (5 + len(dss))]
        for r in lv["cases"].values():
            v = r["values"]
            cells = [r["shape"], str(r["seed"]), f"{fmt(v['input']['chamfer'])} / {fmt(v['input']['hausdorff'])}",
                     f"{fmt(v['best_classical'].get('chamfer'))} / {fmt(v['best_classical'].get('hausdorff'))} "
                     f"({r['best_classical_method'].get('chamfer')}, {r['best_classical_method'].get('hausdorff')})"]
            cells += [f"{fmt(v[d]['chamfer'])} / {fmt(v[d]['hausdorff'])}" for d in dss]
            est = (r.get("noise_used") or {}).get(dss[0]) if dss else None
            cells.append("-" if est is None else f"{100 * est:.3g}%")
            lines.append("| " + " | ".join(cells) + " |")
        if lv["missing"]:
            lines.append(f"\nMissing results (not in the means): {', '.join(lv['missing'])}")
        lines.append("")
    return "\n".join(lines) + "\n"


def plot_level(lv: dict, dss: list[str], classical: list[str], path: Path, title: str) -> Path:
    """Mean CD and HD against mean CPU seconds for one (points, noise, group): each DSS method and
    each classical entry a point, the per-case best classical as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dss.io_utils import atomic_savefig

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, k in zip(axes, ("chamfer", "hausdorff")):
        items = []
        for lab in classical:
            v, t = lv["classical_mean"][lab][k], lv["cpu_s"].get(lab)
            if v is not None and t:
                ax.scatter(t, v, s=22, color="C0", zorder=3)
                items.append((t, v, lab))
        for lab in dss:
            v, t = lv["mean"][lab][k], lv["cpu_s"].get(lab)
            if v is not None and t:
                ax.scatter(t, v, s=40, color="C3", zorder=4)
                items.append((t, v, lab))
        for lab, style in (("input", ":"), ("best_classical", "--")):
            v = lv["mean"][lab][k]
            if v is not None:
                ax.axhline(v, color="0.4", ls=style, lw=1, label=f"{lab.replace('_', ' ')} per case ({v:.3g})")
        ax.set_xscale("log")
        label_points(ax, items, fontsize=6.5)
        ax.set_xlabel("mean CPU seconds per case (one thread)")
        ax.set_ylabel(f"mean {NAMES[k]} ({'x1e4' if k == 'chamfer' else 'x1e3'}, paper protocol)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title + "  (red: DSS, blue: classical entries)", fontsize=9)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------ the app
def _seeds_by_group(cfg: DictConfig) -> dict[str, list[int]]:
    """``seeds_by_group`` as {group: [seeds]} (groups not named run every seed)."""
    return {str(g): [int(x) for x in v] for g, v in (cfg.get("seeds_by_group") or {}).items()}


def _levels(cfg: DictConfig) -> tuple[list[int], list[float], list[int]]:
    """(points, noise levels, seeds), every setting checked before any work (the classical
    entries' methods and parameters too)."""
    from experiments.evaluation.baselines.methods import METHODS

    points = [int(p) for p in cfg.points]
    noises = [float(n) for n in cfg.noise]
    seeds = [int(s) for s in cfg.seeds]
    if any(p < 32 for p in points) or not all(n > 0 and math.isfinite(n) for n in noises):
        raise ValueError(f"points must be >= 32 and noise levels positive, got {points}, {noises}")
    for g, v in _seeds_by_group(cfg).items():
        if g not in [str(x) for x in cfg.groups] or not all(x in seeds for x in v):
            raise ValueError(f"seeds_by_group.{g}: must name a group of groups {list(cfg.groups)} and seeds of "
                             f"seeds {seeds}, got {list(v)}")
    if str(cfg.get("dss_noise", "estimate")) not in ("estimate", "given"):
        raise ValueError(f"dss_noise must be estimate or given, got {cfg.dss_noise!r}")
    for label, node in (cfg.classical or {}).items():
        if str(node.method) not in METHODS:
            raise ValueError(f"classical.{label}: unknown method {node.method!r}; known: {sorted(METHODS)}")
        bad = sorted(set(plain(node.params) or {}) - set(METHODS[str(node.method)].defaults))
        if bad:
            raise ValueError(f"classical.{label}: unknown parameter(s) {bad} of {node.method}")
    return points, noises, seeds


def _title_and_notes(cfg: DictConfig, shapes: list[dict], points, noises, seeds) -> tuple[str, list[str]]:
    by_group = _seeds_by_group(cfg)
    title = f"Real shapes: {', '.join(map(str, points))} points, noise {', '.join(f'{100 * n:g}%' for n in noises)} " \
            f"x bbox diagonal, seeds {seeds}" + "".join(f" ({g}: {v})" for g, v in by_group.items())
    notes = [f"shapes: {', '.join(sorted({c['name'] for c in shapes}))} (groups {list(cfg.groups)}, "
             "data_prep/real_split.yaml; held_out and open were not looked at while tuning)",
             f"DSS: dss-denoise with {'the noise estimated' if str(cfg.dss_noise) == 'estimate' else 'the noise given'}; "
             f"methods {dict((k, plain(v)) for k, v in (cfg.dss_methods or {}).items())}; extra overrides "
             f"{plain(cfg.get('dss_overrides'))}",
             f"classical entries: {', '.join(f'{k} ({v.method} {dict(plain(v.params))})' for k, v in (cfg.classical or {}).items())}",
             f"noise levels in the paper's labels: x{PAPER_LABEL_FACTOR:g} (the paper's test data labelled 1% "
             "measures about 0.5% of the diagonal per axis)",
             f"threads per method: {cfg.threads}; machine: {os.cpu_count()} CPU cores"]
    return title, notes


#: what report.json keeps of each record (the records/ folder of the run keeps everything)
COMPACT_KEYS = ("case", "method", "shape", "group", "points", "noise", "seed", "status", "message", "cpu_s", "params")
COMPACT_METRICS = (*KEYS, "chamfer_pred_to_gt", "chamfer_gt_to_pred", "hausdorff_pred_to_gt", "pred_to_gt_p99",
                   "point_to_mesh")


def _compact(rec: dict) -> dict:
    """A record for report.json: its identity, status, CPU seconds and metrics (4 significant digits)."""
    out = {k: rec[k] for k in COMPACT_KEYS if rec.get(k) not in (None, "", {})}
    m = rec.get("metrics") or {}
    out["metrics"] = {k: float(f"{m[k]:.4g}") for k in COMPACT_METRICS if isinstance(m.get(k), (int, float))}
    if rec.get("noise_used"):
        out["noise_estimated"] = (rec["noise_used"] or {}).get("estimated")
    return out


def _write(cfg: DictConfig, out: Path, title: str, md: str, summary: dict, skipped: list, records: list,
           command: str | None, t0: float) -> dict:
    """The charts, report.json, report.md, README.md (and the published copies); the run's result."""
    from dss.io_utils import atomic_write_json, atomic_write_text

    files = {"markdown": "report.md", "json": "report.json", "readme": "README.md", "config": "config.yaml"}
    for lv in summary["levels"]:
        name = f"accuracy_vs_time_{lv['points']}_{lv['noise']:g}_{lv['group']}.png"
        if lv["n"]:
            plot_level(lv, summary["dss_methods"], summary["classical"], out / name,
                       f"{lv['points']} points, noise {100 * lv['noise']:g}%, {lv['group']} (n={lv['n']})")
            files[name] = name
    elapsed = time.perf_counter() - t0
    result = {"title": title, "summary": summary, "skipped": skipped, "records": [_compact(r) for r in records],
              "paper_label_factor": PAPER_LABEL_FACTOR, "versions": versions(),
              "config": OmegaConf.to_container(cfg, resolve=True), "time_s": elapsed, "files": files,
              "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}
    atomic_write_json(out / "report.json", result)
    atomic_write_text(out / "report.md", md)
    command = command or "python -c 'experiments.evaluation.real_benchmark.run(cfg)' (the config is config.yaml)"
    atomic_write_text(out / "README.md", (
        f"# {title}\n\nProduced by (from the repository root, after `dss-data real`):\n\n```\n{command}\n```\n\n"
        f"Last run: {time.strftime('%Y-%m-%d %H:%M:%S')}, {elapsed:.0f} s (stored records not rerun), "
        f"{os.cpu_count()} CPU cores.\n\nFiles: `report.md`, `report.json` (the summary and every record's metrics), "
        "`accuracy_vs_time_<points>_<noise>_<group>.png`, `config.yaml`; in the run folder only: `cases/`, "
        "`records/` (delete one to rerun it), `outputs/` and `runs/` (DSS run directories).\n"))
    published = []
    if cfg.get("publish", False):
        from experiments import outputs

        published = [str(p) for p in outputs.publish_files(out, resolve_repo_path(str(cfg.published_dir)),
                                                             list(files.values()))]
    return {"out_dir": str(out), "records": records, "summary": summary, "markdown": md, "files": files,
            "skipped": skipped, "time_s": elapsed, "published": published}


def run(cfg: DictConfig, command: str | None = None) -> dict:
    """Run the benchmark (see the module docstring); returns ``{"out_dir", "records", "summary",
    "markdown", "files", "skipped", "time_s", "published"}``."""
    from tqdm.auto import tqdm

    from experiments.common import save_config

    t0 = time.perf_counter()
    points, noises, seeds = _levels(cfg)
    shapes, skipped = bench_cases(cfg)
    if not shapes:
        raise ValueError("no real shapes to run: " + ("; ".join(f"{s['name']}: {s['reason']}" for s in skipped)
                                                       or f"groups {list(cfg.groups)} are empty"))
    out = Path(os.path.expanduser(str(cfg.out_dir))).absolute()
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out)
    n_methods = len(cfg.dss_methods or {}) + len(cfg.classical or {})
    by_group = _seeds_by_group(cfg)
    n_seeds = sum(len([s for s in seeds if s in by_group.get(c["group"], seeds)]) for c in shapes)
    bar = tqdm(total=n_seeds * len(points) * len(noises) * n_methods, desc="real bench",
               unit="run", disable=not cfg.get("progress", True), dynamic_ncols=True)
    records = []
    # cheap levels first: every case of one (points, noise, seed) before the next seed
    for p in points:
        for n in noises:
            for s in seeds:
                for case in shapes:
                    if s in by_group.get(case["group"], seeds):
                        records += _run_case(cfg, out, case, p, n, s, bar)
    bar.close()
    summary = summarize_bench(records, cfg)
    title, notes = _title_and_notes(cfg, shapes, points, noises, seeds)
    md = render_report(summary, title, notes, skipped)
    return _write(cfg, out, title, md, summary, skipped, records, command, t0)


@hydra.main(version_base="1.3", config_path="../../conf", config_name="real_bench")
def _main(cfg: DictConfig) -> None:
    from data_prep.real_meshes import RealDataError

    try:
        res = run(cfg, command=shlex.join(["dss-real-bench", *sys.argv[1:]]))
    except RealDataError as e:
        print(f"dss-real-bench: error: {e}", file=sys.stderr)
        sys.exit(2)
    print(res["markdown"].split("## Detail")[0])
    print(f"report: {Path(res['out_dir']) / 'report.md'} ({res['time_s']:.0f} s)")
    for s in res["skipped"]:
        print(f"NOTICE: {s['name']} ({s['group']}) is not in the benchmark: {s['reason']}", file=sys.stderr)


def main() -> None:
    from experiments.common import run_app

    run_app(_main, "dss-real-bench")


if __name__ == "__main__":
    main()
