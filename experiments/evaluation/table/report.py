"""The denoising table's report: per-method summaries over the cases (means, Pareto front),
the markdown table and the accuracy-against-time chart."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["PROTOCOL", "METRIC_KEYS", "METRIC_NAMES", "HALF_KEYS", "SCORED", "mean", "summarize", "fmt",
           "render_markdown", "label_points", "plot_accuracy_vs_time"]

PROTOCOL = "paper"  # the default protocol; ``protocol=score`` switches metrics and noise unit
METRIC_KEYS = ("chamfer", "hausdorff", "p2m")
METRIC_NAMES = {"chamfer": "CD", "hausdorff": "HD", "p2m": "P2M"}
# the two one-sided halves of CD: accuracy (output -> clean) and coverage (clean -> output)
HALF_KEYS = ("chamfer_pred_to_gt", "chamfer_gt_to_pred")
#: statuses whose record still carries metrics (the output exists and is finite)
SCORED = ("ok", "worse_than_input", "reference")


def mean(vals: list[float]) -> float | None:
    vals = [v for v in vals if v is not None and math.isfinite(v)]
    return float(np.mean(vals)) if vals else None


def summarize(records: list[dict], methods: list[str], cases: list[str], held_out=()) -> list[dict]:
    """Per-method rows: ``{"method", "kind", "cases": {case: {"status", "message", chamfer,
    hausdorff, p2m}}, "mean": {metric: mean over the scored tuning cases}, "n_scored",
    "complete", "time_s" (mean over the scored tuning cases), "pareto": {metric: bool}}``, and,
    when some of ``cases`` are in ``held_out``, the same over those: ``"mean_held_out"``,
    ``"n_scored_held_out"``, ``"complete_held_out"``; ``cases``: the non-skipped case names (the
    table's columns)."""
    held = [c for c in cases if c in set(held_out)]
    tuning = [c for c in cases if c not in set(held_out)]
    from experiments.evaluation.baselines.aggregate import pareto_front

    rows = []
    for label in ["input", "floor", *methods]:
        recs = {r["case"]: r for r in records if r["method"] == label and r["case"] in cases}
        if not recs:
            continue
        cells = {}
        for c in cases:
            r = recs.get(c, {"status": "missing", "message": "no record"})
            m = r.get("metrics") or {}
            cells[c] = {"status": r["status"], "message": r.get("message", ""), "time_s": r.get("time_s"),
                        "cpu_s": r.get("cpu_s"),
                        **{k: m.get(k) for k in METRIC_KEYS + HALF_KEYS}}
        scored = [c for c in tuning if cells[c]["chamfer"] is not None]
        row = {"method": label, "kind": next(iter(recs.values())).get("kind"), "cases": cells,
               "mean": {k: mean([cells[c][k] for c in scored]) for k in METRIC_KEYS + HALF_KEYS},
               "n_scored": len(scored), "complete": bool(tuning) and len(scored) == len(tuning),
               "time_s": mean([cells[c]["time_s"] for c in scored]),
               "cpu_s": mean([cells[c]["cpu_s"] for c in scored]),
               "statuses": sorted({cells[c]["status"] for c in cases})}
        if held:
            scored_h = [c for c in held if cells[c]["chamfer"] is not None]
            row.update({"mean_held_out": {k: mean([cells[c][k] for c in scored_h]) for k in METRIC_KEYS + HALF_KEYS},
                        "n_scored_held_out": len(scored_h), "complete_held_out": len(scored_h) == len(held)})
        rows.append(row)
    methods_rows = [r for r in rows if r["kind"] not in ("input", "floor") and r["complete"]]
    # the Pareto front and the chart on CPU seconds when every method has them (one thread per
    # method: what an idle machine gives, whatever else ran), else on wall time
    clock = "cpu_s" if methods_rows and all(r.get("cpu_s") is not None for r in methods_rows) else "time_s"
    ranked = [r for r in methods_rows if r[clock] is not None]
    for r in rows:
        r["pareto"], r["clock"] = {}, clock
    for k in ("chamfer", "p2m"):
        front = pareto_front([r[clock] for r in ranked],
                             [np.nan if r["mean"][k] is None else r["mean"][k] for r in ranked])
        for r, f in zip(ranked, front):
            r["pareto"][k] = bool(f)
    return rows


def fmt(v: float | None) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.4g}"


#: the aggregate columns: (row key of the means, row key saying they cover every case)
AGGREGATE = {"mean": ("mean", "complete"), "held-out mean": ("mean_held_out", "complete_held_out")}
#: row labels of the reference rows
LABELS = {"input": "input (noisy)", "floor": "floor (2nd clean sampling)"}


def _value(r: dict, c: str, k: str | None):
    """Row ``r``'s value in column (case or aggregate ``c``, metric ``k``)."""
    if c in AGGREGATE:
        return (r.get(AGGREGATE[c][0]) or {}).get(k)
    if c in ("time", "cpu"):
        return r.get(f"{c}_s")
    return r["cases"][c][k]


def _complete(r: dict, c: str) -> bool:
    """Whether row ``r``'s column ``c`` covers every case (only those are ranked)."""
    return r.get(AGGREGATE[c][1], False) if c in AGGREGATE else (r["complete"] if c in ("time", "cpu") else True)


def _columns(case_info: list[dict]) -> tuple[list[str], set, list[str], list[tuple]]:
    """(case columns: tuning then held out, held-out names, aggregates, (column, metric) pairs)."""
    held = {c["name"] for c in case_info if c.get("held_out")}
    names = [c["name"] for c in case_info if c["status"] != "skipped"]
    cases = [c for c in names if c not in held] + [c for c in names if c in held]
    agg = ["mean"] + (["held-out mean"] if any(c in held for c in cases) else [])
    cols = ([(c, k) for c in cases for k in METRIC_KEYS] + [(a, k) for a in agg for k in METRIC_KEYS]
            + [("time", None), ("cpu", None)])
    return cases, held, agg, cols


def _best(rows: list[dict], cols: list[tuple]) -> dict:
    """The best (lowest) method value per column (input and floor rows and incomplete means left out)."""
    best = {}
    for c, k in cols:
        vals = [_value(r, c, k) for r in rows if r["kind"] not in ("input", "floor") and _complete(r, c)]
        vals = [v for v in vals if v is not None and math.isfinite(v)]
        best[(c, k)] = min(vals) if vals else None
    return best


def _cell(r: dict, c: str, k: str | None, best: dict, cases: list[str], held: set) -> str:
    """One table cell: the value, bold when best, ``(k/n)`` for an incomplete mean, † when worse
    than the input, the status for a case without a result."""
    v = _value(r, c, k)
    if c not in AGGREGATE and c not in ("time", "cpu") and v is None:
        return r["cases"][c]["status"]
    s = fmt(v)
    if c in AGGREGATE and v is not None and not _complete(r, c):
        n = r["n_scored"] if c == "mean" else r.get("n_scored_held_out", 0)
        s += f" ({n}/{sum((x in held) == (c != 'mean') for x in cases)})"
    elif (v is not None and best[(c, k)] is not None and v == best[(c, k)] and r["kind"] not in ("input", "floor")
          and _complete(r, c)):
        s = f"**{s}**"
    if c not in AGGREGATE and k == "chamfer" and r["cases"][c]["status"] == "worse_than_input":
        s += " †"
    return s


def _main_table(rows: list[dict], case_info: list[dict]) -> list[str]:
    cases, held, agg, cols = _columns(case_info)
    best = _best(rows, cols)
    head = ["method"] + [f"{c}{' (held out)' if c in held else ''} {METRIC_NAMES[k]}" if k
                         else {"time": "time (s)", "cpu": "CPU (s)"}[c] for c, k in cols]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        out = [LABELS.get(r["method"], r["method"])] + [_cell(r, c, k, best, cases, held) for c, k in cols]
        lines.append("| " + " | ".join(out) + " |")
    lines += ["", "† worse than the noisy input (Chamfer). Means over cases: `(k/n)` when only k of the n "
              "cases have a result (not ranked). time: mean method wall time over the scored cases; CPU: "
              "the same stages' process CPU seconds (with one thread per method, the wall time an idle "
              "machine would give)."
              + (" mean: over the tuning cases (the settings were chosen on them); held-out mean: over the "
                 "cases marked (held out), which were not looked at while tuning." if len(agg) > 1 else "")]
    return lines


def _halves_section(rows: list[dict]) -> list[str]:
    lines = ["## Accuracy and coverage", "",
             "CD = accuracy + coverage: the mean squared distance from each output point to the clean cloud, "
             "and from each clean point to the output (x1e4). A method that moves points sideways into "
             "clumps keeps its accuracy but loses coverage.", "",
             "| method | mean accuracy (output -> clean) | mean coverage (clean -> output) |", "|---|---|---|"]
    for r in rows:
        if r["complete"] or r["kind"] in ("input", "floor"):
            lines.append(f"| {LABELS.get(r['method'], r['method'])} | {fmt(r['mean'].get(HALF_KEYS[0]))} | "
                         f"{fmt(r['mean'].get(HALF_KEYS[1]))} |")
    return lines


def _cases_section(case_info: list[dict]) -> list[str]:
    lines = ["## Cases", "", "noise: the configured level (its unit in the title); noise (x diag): the same as a fraction "
             "of the clean bbox diagonal (what the baselines' presets and dss-denoise were given); measured noise: "
             "std of the noisy - clean offsets per axis, x diag.", "",
             "| case | source | points | noise | noise (x diag) | measured noise | status |", "|---|---|---|---|---|---|---|"]
    for c in case_info:
        src = c.get("source") or c.get("key", {}).get("case", {})
        src_s = src.get("mesh") or f"{src.get('family')} #{src.get('index')} (shape seed {src.get('shape_seed')})"
        st = "skipped: " + c["reason"] if c["status"] == "skipped" else "ok"
        lines.append(f"| {c['name']} | {src_s} | {c['key']['points']} | {c['key']['noise']:g} | "
                     f"{fmt(c.get('noise_diag', c['key']['noise']))} | "
                     f"{fmt((c.get('source') or {}).get('measured_noise'))} | {st} |")
    return lines


def _failures_section(rows: list[dict], case_info: list[dict]) -> list[str]:
    cases = _columns(case_info)[0]
    fails = [(c, r["method"], r["cases"][c]) for r in rows for c in cases
             if r["cases"][c]["status"] not in SCORED]
    if not fails:
        return []
    return ["", "## Failures", "", "| case | method | status | message |", "|---|---|---|---|",
            *[f"| {c} | {m} | {cell['status']} | {str(cell['message']).replace('|', '/')[:200]} |"
              for c, m, cell in fails]]


def render_markdown(rows: list[dict], case_info: list[dict], title: str, notes: list[str]) -> str:
    """The paper-style table: rows = methods, columns = CD/HD/P2M per case, means, time; the best
    method value per column in bold (input and floor rows excluded; means only of complete rows);
    a failure shows as its status; † marks an output worse than the noisy input (Chamfer).
    Held-out cases (``held_out`` in their case dict) come after the tuning cases, marked in the
    header, with their own means (``held-out mean``). Then the accuracy and coverage halves of
    CD, the cases, and the failures."""
    lines = [f"# {title}", "", *[f"- {n}" for n in notes], "", *_main_table(rows, case_info), "",
             *_halves_section(rows), "", *_cases_section(case_info), *_failures_section(rows, case_info)]
    return "\n".join(lines) + "\n"


def label_points(ax, items: list[tuple[float, float, str]], fontsize: float = 7.0) -> None:
    """Name each point beside it; labels that would overlap an earlier one move down in steps of
    a line, with a leader line back to their point. The DSS variants sit within a few percent of
    each other in both time and error, so plain offsets put their names on top of each other."""
    ax.figure.canvas.draw()  # fixes the limits and scales the display transform needs
    scale = ax.figure.dpi / 72.0  # points -> pixels
    line, placed = fontsize * 1.35 * scale, []
    for x, y, text in sorted(items, key=lambda it: -it[1]):
        px, py = ax.transData.transform((x, y))
        w = len(text) * fontsize * 0.6 * scale
        lx, ly = px + 3 * scale, py + 3 * scale
        if lx + w > ax.bbox.x1:  # near the right edge: name it on the left
            lx = px - 3 * scale - w
        while any(lx < bx + bw and bx < lx + w and abs(ly - by) < line for bx, by, bw in placed):
            ly -= line
        placed.append((lx, ly, w))
        moved = abs(ly - (py + 3 * scale)) > 0.5
        ax.annotate(text, (x, y), fontsize=fontsize, xytext=((lx - px) / scale, (ly - py) / scale),
                    textcoords="offset points",
                    arrowprops={"arrowstyle": "-", "color": "0.35", "lw": 0.6, "shrinkA": 0,
                                "shrinkB": 3} if moved else None)


def plot_accuracy_vs_time(rows: list[dict], path: Path, title: str, protocol: str = PROTOCOL) -> Path | None:
    """Mean CD and mean P2M (x1e4, ``protocol``) against mean CPU seconds per method (wall time
    when some method has none; complete rows), the
    Pareto front (lower time and error) marked, the input and the floor as horizontal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dss.io_utils import atomic_savefig

    clock = next((r["clock"] for r in rows if r.get("clock")), "time_s")
    pts = [r for r in rows if r["kind"] not in ("input", "floor") and r["complete"] and r.get(clock)]
    ref = {r["kind"]: r for r in rows if r["kind"] in ("input", "floor")}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, k in zip(axes, ("chamfer", "p2m")):
        good = [r for r in pts if r["mean"][k] is not None]
        for r in good:
            on = r["pareto"].get(k, False)
            ax.scatter(r[clock], r["mean"][k], s=36, zorder=3, color="C3" if r["kind"] == "dss" else "C0")
            if on:
                ax.scatter(r[clock], r["mean"][k], s=150, facecolors="none", edgecolors="k", lw=1.4, zorder=4)
        front = sorted((r[clock], r["mean"][k]) for r in good if r["pareto"].get(k))
        if front:
            ax.step(*zip(*front), where="post", color="k", ls="--", lw=1, zorder=2, label="Pareto front")
        for kind, style in (("input", ":"), ("floor", "-.")):
            v = ref.get(kind, {}).get("mean", {}).get(k)
            if v is not None:
                ax.axhline(v, color="0.5", ls=style, lw=1, label=f"{kind} ({v:.3g})")
        times = [r[clock] for r in good]
        if times and min(times) > 0 and max(times) / min(times) > 20:
            from matplotlib.ticker import NullFormatter, ScalarFormatter

            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(ScalarFormatter())  # 1, 10, 100, not 10^0 ...
            ax.xaxis.set_minor_formatter(NullFormatter())  # minor labels overlap on short ranges
        label_points(ax, [(r[clock], r["mean"][k], r["method"]) for r in good])
        ax.set_xlabel("mean CPU seconds per case (one thread)" if clock == "cpu_s" else "mean wall time per case (s)")
        ax.set_ylabel(f"mean {METRIC_NAMES[k]} x1e4 ({protocol} protocol)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title + "  (red: DSS; circled: Pareto front; failed methods not shown)", fontsize=9)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)
    return path
