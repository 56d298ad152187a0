"""Turn a sweep / results directory of ``metrics.json`` files into one table and one chart.

Every ``metrics.json`` below ``root`` (any depth: Hydra multirun ``<sweep>/<job>/``, or
``results/<method>/<case>/``) is one run. Nested dicts are flattened to dotted keys
(``{"paper": {"chamfer": 1.2}}`` -> ``paper.chamfer``); a Hydra job's
``.hydra/overrides.yaml`` adds ``override.<key>`` columns. Writes, into ``out_dir``:

* ``summary.md`` -- a markdown table (one row per run, or per group with ``group_by``),
* ``summary.json`` -- the same rows with every flattened key, the chosen axes and the Pareto
  sets,
* ``accuracy_vs_time.png`` -- each accuracy metric against wall time, the Pareto front
  (lower time and lower error) marked.

A run counts as failed when its ``status`` is not one of ``ok``/``done``/``success``, when
``failed`` is true, or when the plotted values are missing or not finite; failed runs appear in
the table (and in a group's failure rate) but not in the chart.

``python -m experiments.evaluation.baselines.aggregate SWEEP_DIR [--out DIR] [--x KEY] [--y KEY ...]
[--group-by KEY ...] [--label KEY]``; :func:`run` is the same as a function of a config dict.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from experiments.common import flatten

log = logging.getLogger(__name__)

OK_STATUSES = ("ok", "done", "success", "succeeded")
TIME_KEYS = ("wall_s", "time_s", "time_s.total", "runtime_s", "total_s", "elapsed_s", "seconds", "time")
#: dotted-key components that mark a number as not the run's result (dss-denoise's metrics.json
#: scores its input and the Chamfer floor next to its output)
NOT_RESULT = ("input", "metrics_input", "floor", "chamfer_floor")
#: default accuracy metrics, searched in this order (last dotted component, then preference)
Y_CANDIDATES = (("chamfer", ("paper", "score")), ("p2m", ("score", "paper")))


def _read_overrides(run_dir: str) -> dict:
    path = os.path.join(run_dir, ".hydra", "overrides.yaml")
    if not os.path.isfile(path):
        return {}
    import yaml

    try:
        with open(path) as f:
            items = yaml.safe_load(f) or []
    except (OSError, yaml.YAMLError) as e:
        log.warning("%s: unreadable overrides (%s)", path, e)
        return {}
    out = {}
    for it in items:
        k, _, v = str(it).partition("=")
        out[f"override.{k.lstrip('+~')}"] = v
    return out


def find_runs(root: str | os.PathLike) -> list[dict]:
    """All runs below ``root``: ``{"run": relative dir, **flattened metrics, **overrides}``.

    Unreadable or non-object ``metrics.json`` files are skipped with a warning naming them.
    """
    root = os.fspath(root)
    if not os.path.isdir(root):
        raise FileNotFoundError(f"{root}: not a directory (expected a sweep/results directory)")
    runs = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        if "metrics.json" not in filenames:
            continue
        path = os.path.join(dirpath, "metrics.json")
        try:
            with open(path) as f:
                data = json.load(f)
        except (OSError, json.JSONDecodeError) as e:
            log.warning("%s: skipped, not valid JSON (%s)", path, e)
            continue
        if not isinstance(data, dict):
            log.warning("%s: skipped, expected a JSON object", path)
            continue
        row = {"run": os.path.relpath(dirpath, root)}
        row.update(_read_overrides(dirpath))
        row.update(flatten(data))
        runs.append(row)
    return runs


def _num(v: Any) -> float:
    if isinstance(v, bool) or v is None:
        return math.nan
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def pareto_front(x: Sequence[float], y: Sequence[float]) -> np.ndarray:
    """Boolean mask of the points not dominated when minimising both x and y (non-finite
    points are never on the front; ties: equal points are all kept)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    ok = np.isfinite(x) & np.isfinite(y)
    mask = np.zeros(len(x), dtype=bool)
    for i in np.nonzero(ok)[0]:
        dominated = ok & (x <= x[i]) & (y <= y[i]) & ((x < x[i]) | (y < y[i]))
        mask[i] = not dominated.any()
    return mask


def _keys(rows: Iterable[dict]) -> list[str]:
    seen: dict = {}
    for r in rows:
        for k in r:
            seen.setdefault(k, None)
    return list(seen)


def _numeric_keys(rows: list[dict]) -> list[str]:
    return [k for k in _keys(rows) if any(math.isfinite(_num(r.get(k))) for r in rows)]


def pick_time_key(rows: list[dict]) -> str | None:
    """The wall-time column: an exact name from :data:`TIME_KEYS`, else a dotted key ending
    in one of them (shortest first)."""
    num = _numeric_keys(rows)
    for cand in TIME_KEYS:
        if cand in num:
            return cand
    for cand in TIME_KEYS:
        hits = sorted((k for k in num if k.split(".")[-1] == cand), key=len)
        if hits:
            return hits[0]
    return None


def pick_metric_keys(rows: list[dict]) -> list[str]:
    """Default accuracy columns: a Chamfer and a P2M column (protocol-preferring)."""
    num = _numeric_keys(rows)
    out = []
    for name, prefer in Y_CANDIDATES:
        # a protocol's scale factor for a metric (``...scale_factors.p2m``) is not that metric
        hits = [k for k in num if k.split(".")[-1] == name and "scale_factors" not in k.split(".")]
        if not hits:
            continue
        hits.sort(
            key=lambda k: (
                any(c in NOT_RESULT for c in k.split(".")),
                min([i for i, p in enumerate(prefer) if p in k.split(".")] or [9]),
                len(k),
            )
        )
        out.append(hits[0])
    return out


def _is_failed(row: dict, needed: Sequence[str]) -> bool:
    st = row.get("status")
    if st is not None and str(st).lower() not in OK_STATUSES:
        return True
    if row.get("failed") is True:
        return True
    return any(not math.isfinite(_num(row.get(k))) for k in needed)


def _label(row: dict, label_key: str | None) -> str:
    if label_key:
        return str(row.get(label_key, "?"))
    for k in ("method", "name"):
        if k in row:
            extra = [str(row[p]) for p in ("preset", "params_name") if p in row]
            return " ".join([str(row[k]), *extra])
    ov = sorted((k[len("override.") :], v) for k, v in row.items() if k.startswith("override."))
    if ov:
        return ",".join(f"{k}={v}" for k, v in ov)
    return row["run"]


def _group(rows: list[dict], group_by: Sequence[str], value_keys: Sequence[str]) -> list[dict]:
    groups: dict = {}
    for r in rows:
        key = tuple(str(r.get(g, "?")) for g in group_by)
        groups.setdefault(key, []).append(r)
    out = []
    for key, members in groups.items():
        good = [m for m in members if not m["_failed"]]
        g = {"label": " ".join(key), "n_runs": len(members), "n_failed": len(members) - len(good)}
        g["failure_rate"] = g["n_failed"] / len(members)
        statuses: dict = {}
        for m in members:
            st = str(m.get("status", "failed" if m["_failed"] else "ok"))
            statuses[st] = statuses.get(st, 0) + 1
        g["statuses"] = statuses
        for k in value_keys:
            vals = np.array([_num(m.get(k)) for m in good], dtype=float)
            vals = vals[np.isfinite(vals)]
            g[k] = float(vals.mean()) if len(vals) else math.nan
            g[f"{k}.std"] = float(vals.std()) if len(vals) > 1 else 0.0 if len(vals) else math.nan
        g["_failed"] = len(good) == 0
        g["runs"] = [m["run"] for m in members]
        out.append(g)
    return out


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        if not math.isfinite(v):
            return "-"
        return f"{v:.4g}"
    return "-" if v is None else str(v).replace("|", "\\|")


def _markdown(rows: list[dict], cols: list[str], title: str, notes: list[str]) -> str:
    lines = [f"# {title}", ""]
    lines += [f"- {n}" for n in notes]
    lines += ["", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(c)) for c in cols) + " |")
    return "\n".join(lines) + "\n"


def _plot(rows: list[dict], x_key: str, y_keys: list[str], path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dss.io_utils import atomic_savefig

    fig, axes = plt.subplots(1, len(y_keys), figsize=(5.5 * len(y_keys), 4.5), squeeze=False)
    good = [r for r in rows if not r["_failed"]]
    labels = sorted({r["label"] for r in good})
    cmap = plt.get_cmap("tab10" if len(labels) <= 10 else "tab20")
    color = {lab: cmap(i % cmap.N) for i, lab in enumerate(labels)}
    for ax, yk in zip(axes[0], y_keys):
        pts = [
            (r[x_key], r[yk], r)
            for r in good
            if math.isfinite(_num(r.get(x_key))) and math.isfinite(_num(r.get(yk)))
        ]
        for x, y, r in pts:
            ax.scatter(x, y, color=color[r["label"]], s=30, zorder=3)
        xs = np.array([p[0] for p in pts], dtype=float)
        ys = np.array([p[1] for p in pts], dtype=float)
        if len(pts):
            front = pareto_front(xs, ys)
            order = np.argsort(xs[front])
            fx, fy = xs[front][order], ys[front][order]
            ax.step(
                fx, fy, where="post", color="k", lw=1.2, ls="--", zorder=2, label="Pareto front"
            )
            ax.scatter(fx, fy, s=140, facecolors="none", edgecolors="k", lw=1.5, zorder=4)
            if len(pts) <= 40:
                for x, y, r in pts:
                    ax.annotate(
                        r["label"], (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points"
                    )
            if xs.min() > 0 and xs.max() / xs.min() > 20:
                ax.set_xscale("log")
        n_fail = sum(1 for r in rows if r["_failed"])
        ax.set_xlabel(f"{x_key} (s)")
        ax.set_ylabel(yk)
        ax.set_title(
            f"{yk} vs time" + (f" ({n_fail} failed not shown)" if n_fail else ""), fontsize=9
        )
        ax.grid(alpha=0.3)
    handles = [plt.Line2D([], [], marker="o", ls="", color=color[lab], label=lab) for lab in labels]
    handles.append(plt.Line2D([], [], ls="--", color="k", label="Pareto front"))
    fig.legend(
        handles=handles,
        loc="lower center",
        ncol=min(4, len(handles)),
        fontsize=8,
        bbox_to_anchor=(0.5, -0.02 - 0.04 * math.ceil(len(handles) / 4)),
    )
    fig.suptitle(title, fontsize=10)
    atomic_savefig(fig, path)
    plt.close(fig)


def _columns(runs: list[dict], root: str, x_key: str | None, y_keys) -> tuple[str | None, list[str]]:
    """(time column, accuracy columns): as given (checked) or picked from the runs."""
    x_key = x_key or pick_time_key(runs)
    y_keys = list(y_keys or pick_metric_keys(runs))
    if not y_keys:
        raise ValueError(
            f"{root}: no accuracy column found; pass y_keys (columns: {_keys(runs)[:30]})"
        )
    for k in [x_key, *y_keys]:
        if k is not None and k not in _keys(runs):
            raise KeyError(f"column {k!r} is in no metrics.json under {root}")
    return x_key, y_keys


def _mark_pareto(rows: list[dict], x_key: str | None, y_keys: list[str]) -> None:
    """``pareto.<y>`` per row (on the front of time and that metric; failed rows excluded), then
    the rows sorted: successful first, by the first metric."""
    for yk in y_keys:
        xs = [
            (_num(r.get(x_key)) if x_key else 0.0) if not r["_failed"] else math.nan for r in rows
        ]
        ys = [_num(r.get(yk)) if not r["_failed"] else math.nan for r in rows]
        front = pareto_front(xs, ys) if x_key else np.zeros(len(rows), bool)
        for r, f in zip(rows, front):
            r[f"pareto.{yk}"] = bool(f)
    rows.sort(
        key=lambda r: (
            r["_failed"],
            _num(r.get(y_keys[0])) if math.isfinite(_num(r.get(y_keys[0]))) else math.inf,
        )
    )


def _table(rows: list[dict], x_key: str | None, y_keys: list[str], group_by, columns) -> tuple[list[dict], list[str]]:
    """(table rows, columns) of the markdown summary."""
    if group_by:
        cols = ["label", "n_runs", "failure_rate", *([x_key] if x_key else []), *y_keys]
    else:
        cols = ["label", "status", *([x_key] if x_key else []), *y_keys]
    cols += [c for c in (columns or []) if c not in cols]
    table_rows = []
    for r in rows:
        tr = dict(r)
        tr.setdefault("status", "failed" if r["_failed"] else "ok")
        marks = [yk.split(".")[-1] for yk in y_keys if r.get(f"pareto.{yk}")]
        tr["pareto"] = ", ".join(marks) if marks else ""
        table_rows.append(tr)
    if x_key:
        cols.append("pareto")
    return table_rows, cols


def aggregate(
    root: str | os.PathLike,
    out_dir: str | os.PathLike | None = None,
    x_key: str | None = None,
    y_keys: Sequence[str] | None = None,
    group_by: Sequence[str] | None = None,
    label_key: str | None = None,
    columns: Sequence[str] | None = None,
    title: str | None = None,
) -> dict:
    """Collect the runs under ``root`` and write ``summary.md``, ``summary.json`` and
    ``accuracy_vs_time.png`` into ``out_dir`` (default: ``root``). Returns the summary dict.

    ``x_key``/``y_keys``: flattened column names (auto-detected when None: see
    :func:`pick_time_key`, :func:`pick_metric_keys`). ``group_by``: columns (``"label"``
    allowed) whose equal values form one row with mean/std over its successful runs and a
    failure rate. ``columns``: extra columns in the markdown table.
    """
    from dss.io_utils import atomic_write_json, atomic_write_text

    root = os.fspath(root)
    out_dir = os.fspath(out_dir or root)
    runs = find_runs(root)
    if not runs:
        raise FileNotFoundError(f"{root}: no metrics.json found below this directory")
    x_key, y_keys = _columns(runs, root, x_key, y_keys)
    needed = [k for k in [x_key, *y_keys] if k]
    for r in runs:
        r["label"] = _label(r, label_key)
        r["_failed"] = _is_failed(r, needed)
    rows = _group(runs, group_by, needed) if group_by else runs
    _mark_pareto(rows, x_key, y_keys)
    table_rows, cols = _table(rows, x_key, y_keys, group_by, columns)
    title = title or f"Summary of {os.path.basename(os.path.abspath(root))}"
    notes = [
        f"{len(runs)} runs from `{root}`"
        + (f", grouped by {', '.join(group_by)}" if group_by else ""),
        f"time column: `{x_key}`" if x_key else "no time column found: no chart, no Pareto front",
        f"accuracy columns: {', '.join(f'`{k}`' for k in y_keys)} (lower is better)",
        "pareto: on the front of (time, metric) for the named metric(s); failed runs excluded",
    ]
    os.makedirs(out_dir, exist_ok=True)
    md = _markdown(table_rows, cols, title, notes)
    summary = {
        "root": os.path.abspath(root),
        "x": x_key,
        "y": y_keys,
        "group_by": list(group_by or []),
        "n_runs": len(runs),
        "n_failed": sum(1 for r in runs if r["_failed"]),
        "pareto": {yk: [r["label"] for r in rows if r.get(f"pareto.{yk}")] for yk in y_keys},
        "rows": [{("failed" if k == "_failed" else k): v for k, v in r.items()} for r in rows],
        "files": {"markdown": "summary.md", "json": "summary.json"},
    }
    atomic_write_text(os.path.join(out_dir, "summary.md"), md)
    if x_key:
        _plot(rows, x_key, y_keys, os.path.join(out_dir, "accuracy_vs_time.png"), title)
        summary["files"]["chart"] = "accuracy_vs_time.png"
    atomic_write_json(os.path.join(out_dir, "summary.json"), summary)
    return summary


def run(cfg: dict) -> dict:
    """Config-driven entry: keys ``root`` (required), ``out_dir``, ``x``, ``y`` (list),
    ``group_by`` (list), ``label``, ``columns`` (list), ``title``."""
    cfg = dict(cfg)
    if "root" not in cfg:
        raise KeyError("aggregate: 'root' (the sweep/results directory) is required")
    return aggregate(
        cfg["root"],
        cfg.get("out_dir"),
        cfg.get("x"),
        cfg.get("y"),
        cfg.get("group_by"),
        cfg.get("label"),
        cfg.get("columns"),
        cfg.get("title"),
    )


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "root", help="sweep or results directory (searched recursively for metrics.json)"
    )
    ap.add_argument("--out", dest="out_dir", help="output directory (default: root)")
    ap.add_argument("--x", help="time column (default: auto)")
    ap.add_argument("--y", nargs="+", help="accuracy column(s) (default: auto)")
    ap.add_argument(
        "--group-by", nargs="+", help="columns forming one row (mean, std, failure rate)"
    )
    ap.add_argument("--label", help="column naming each run (default: method / overrides / dir)")
    ap.add_argument("--columns", nargs="+", help="extra table columns")
    ap.add_argument("--title")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        s = run({k: v for k, v in vars(a).items() if v is not None})
    except (FileNotFoundError, KeyError, ValueError) as e:
        log.error("%s", e)
        return 2
    out = a.out_dir or a.root
    log.info(
        "%d runs (%d failed) -> %s",
        s["n_runs"],
        s["n_failed"],
        ", ".join(os.path.join(out, f) for f in s["files"].values()),
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
