"""``dss-sweep``: stability sweeps and the budget study, each a set of dss-denoise-table runs.

    dss-sweep                                  # study=stability: noise, density, outliers, seeds
    dss-sweep study=budget                     # DSS's views, cycles, points, image size
    dss-sweep 'axes_to_run=[noise]' +table.generated.count=0   # one axis, kangaroo only (+: table is open)

A *study* (``conf/study/<name>.yaml``) is a base table (``conf/denoise_table.yaml`` with the
study's ``table`` settings, then the command's ``table`` settings on top) and *axes*. An axis
varies one setting over a list of values while the others keep their base values: ``key`` is a
dss-denoise-table setting (``noise``, ``points``, ``outliers``, ``seed``) or ``dss.<key>``, a
dss-denoise override given to every DSS run (``dss.views``, ``dss.optimizer.cycles``); an
axis's own ``table`` settings (e.g. other methods) apply to its points only. Every point of an
axis is one dss-denoise-table run in ``out_dir/tables/<setting>/``, named by the values of all the
study's axis keys, so the base point shared by several axes runs once, and every (case, method)
record resumes as in dss-denoise-table.

Per (axis, value, method), over the cases: mean CD / HD / P2M (x1e4 / x1e3 / x1e4, ``paper``
protocol), the mean ratio of the output's CD to the input's (< 1: the method helped), the
failures (crash, time-out, NaN or invalid output, or output worse than its input in Chamfer) and
their rate, and the mean wall time. Per axis and method: the first value with a failure
("starts to fail") and, on axes with ``knee: true`` (budget knobs, cheapest value first), the
*knee*: the cheapest value whose mean CD is within ``knee_tolerance`` of the axis's best.

Outputs in ``out_dir`` (a fresh ``outputs/dss-sweep/<date>`` unless given; ``publish=true`` copies the
summary, without ``tables/``, to ``published_dir`` under ``results/``): ``sweep.json`` (every point, every record's status and metrics),
``sweep.md`` (one table per axis, failure onsets, knees), ``<axis>.png`` (CD ratio, failure rate
and time against the axis value per method), ``README.md`` (the command), ``config.yaml``.
"""

from __future__ import annotations

import logging
import math
import os
import re
import shlex
import sys
import time
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from experiments.evaluation.table.report import mean

log = logging.getLogger(__name__)

__all__ = ["run", "main", "axis_points", "aggregate_point", "knee", "first_failure"]

REPO_ROOT = Path(__file__).resolve().parents[2]
TABLE_CONF = REPO_ROOT / "conf" / "denoise_table.yaml"
DSS_PREFIX = "dss."


def _slug(v) -> str:
    s = f"{v:g}" if isinstance(v, float) else str(v)
    return re.sub(r"[^A-Za-z0-9.+-]+", "-", s)


def _key_name(key: str) -> str:
    return key[len(DSS_PREFIX):].split(".")[-1] if key.startswith(DSS_PREFIX) else key


def base_table(study_table, extra_table) -> DictConfig:
    """conf/denoise_table.yaml (without its hydra section) + the study's + the command's settings."""
    base = OmegaConf.load(TABLE_CONF)
    base.pop("hydra", None)
    for extra in (study_table, extra_table):
        if extra:
            base = OmegaConf.merge(base, extra)
    return base


def axis_points(study: DictConfig, names: list[str], base: DictConfig) -> list[dict]:
    """Every point of the named axes: ``{"axis", "value", "setting", "table"}`` with ``table``
    the point's full dss-denoise-table config (``out_dir`` not yet set) and ``setting`` its
    directory name (the same for the same effective settings on two axes)."""
    axes = study.axes
    for a in axes:
        k = str(axes[a].key)
        if not k.startswith(DSS_PREFIX) and k not in base:
            raise ValueError(f"axis {a}: {k!r} is not a dss-denoise-table setting (use dss.<key> for a "
                             "dss-denoise override)")
    keys = sorted({str(axes[a].key) for a in axes})
    defaults = {}
    for k in keys:  # the base value of every axis key: the table's, or the axis's declared default
        if k.startswith(DSS_PREFIX):
            decl = [axes[a].get("default") for a in axes if str(axes[a].key) == k]
            defaults[k] = decl[0] if decl and decl[0] is not None else "default"
        else:
            defaults[k] = base[k]
    points = []
    for name in names:
        if name not in axes:
            raise ValueError(f"axes_to_run: unknown axis {name!r}; this study has {list(axes)}")
        ax = axes[name]
        key = str(ax.key)
        if ax.get("labels") is not None and len(ax.labels) != len(ax["values"]):
            raise ValueError(f"axis {name}: {len(ax.labels)} labels for {len(ax['values'])} values")
        for value in ax["values"]:
            settings = {**defaults, key: value}
            table = OmegaConf.merge(base, ax.get("table") or {})
            overrides = list(table.get("dss_overrides") or [])
            for k, v in settings.items():
                if k.startswith(DSS_PREFIX):
                    # dss-denoise's own default (declared or unknown) is not passed: the same
                    # effective settings must give the same request, so records are shared
                    if v != defaults[k]:
                        overrides.append(f"{k[len(DSS_PREFIX):]}={v}")
                else:
                    table[k] = v
            table.dss_overrides = overrides
            tag = "_".join(f"{_key_name(k)}{_slug(settings[k])}" for k in keys)
            # other settings than methods make a point of its own (other methods share the records)
            extra = {k: v for k, v in OmegaConf.to_container(ax.get("table") or OmegaConf.create({}),
                                                             resolve=True).items() if k != "methods"}
            if extra:
                tag += "_" + _slug("-".join(f"{k}{v}" for k, v in sorted(extra.items())))
            points.append({"axis": name, "value": value, "setting": tag, "table": table})
    return points


def aggregate_point(records: list[dict], methods: list[str]) -> dict:
    """Per method, over the cases of one table: ``{"n", "failures", "failure_rate", "statuses",
    "chamfer", "hausdorff", "p2m", "ratio", "time_s"}`` (means over the scored cases; ratio: the
    output's CD over the same case's input CD)."""
    inputs = {r["case"]: (r.get("metrics") or {}).get("chamfer") for r in records if r["method"] == "input"}
    out = {}
    for m in methods:
        recs = [r for r in records if r["method"] == m and r.get("status") != "skipped"]
        scored = [r for r in recs if (r.get("metrics") or {}).get("chamfer") is not None]
        fails = [r for r in recs if r.get("failed")]
        out[m] = {"n": len(recs), "failures": len(fails),
                  "failure_rate": len(fails) / len(recs) if recs else None,
                  "statuses": {r["case"]: r["status"] for r in recs},
                  **{k: mean([r["metrics"][k] for r in scored]) for k in ("chamfer", "hausdorff", "p2m")},
                  "ratio": mean([r["metrics"]["chamfer"] / inputs[r["case"]] for r in scored
                                 if inputs.get(r["case"])]),
                  "time_s": mean([r.get("time_s") for r in scored])}
    out["input"] = {"n": len(inputs), "chamfer": mean(list(inputs.values()))}
    return out


def first_failure(values: list, stats: list[dict | None]) -> object | None:
    """The first axis value (listed order) at which the method has a failure, else None."""
    for v, s in zip(values, stats):
        if s and s.get("failures"):
            return v
    return None


def knee(values: list, stats: list[dict | None], tolerance: float) -> object | None:
    """The first value (listed order: cheapest first) whose mean CD is within ``tolerance``
    (relative) of the best mean CD over the axis, among values without failures."""
    good = [(v, s["chamfer"]) for v, s in zip(values, stats)
            if s and s.get("chamfer") is not None and not s.get("failures")]
    if not good:
        return None
    best = min(c for _, c in good)
    return next(v for v, c in good if c <= best * (1 + tolerance))


def _label(value, values: list, labels: list):
    """The label shown for an axis value (None stays None: no onset, no knee)."""
    return None if value is None else labels[values.index(value)]


def _fmt(v, digits=4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.{digits}g}" if isinstance(v, float) else str(v)


def render_markdown(result: dict) -> str:
    lines = [f"# {result['title']}", "", result["description"].strip(), "",
             f"Base: {result['base']}. Failure = crash, time-out, NaN/invalid output, or output worse than "
             "its input (Chamfer). CD x1e4, HD x1e3, P2M x1e4 (`paper` protocol); ratio = output CD / "
             "input CD, mean over cases; time = mean method wall time (s).", ""]
    for ax in result["axes"]:
        name, methods, values = ax["axis"], ax["methods"], ax["labels"]
        lines += [f"## {name}" + (f" ({ax['key']})" if ax["key"] != name else ""), "", f"![{name}]({name}.png)", "",
                  "| method | " + " | ".join(f"{ax['key_name']}={_fmt(v)}" for v in values) + " |",
                  "|---|" + "---|" * len(values)]
        lines.append("| input CD | " + " | ".join(_fmt((p or {}).get("input", {}).get("chamfer"))
                                                   for p in ax["stats"]) + " |")
        for m in methods:
            cells = []
            for p in ax["stats"]:
                s = (p or {}).get(m)
                if not s or not s["n"]:
                    cells.append("-")
                    continue
                c = f"{_fmt(s['chamfer'])} ({_fmt(s['ratio'], 2)})"
                if s["failures"]:
                    bad = sorted({st for st in s["statuses"].values() if st != "ok"})
                    c += f" **{s['failures']}/{s['n']} failed**: {', '.join(bad)}"
                c += f", {_fmt(s['time_s'], 3)} s" if s["time_s"] is not None else ""
                cells.append(c)
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
        with_knee = bool(ax["knee"])
        lines += ["", "Cells: mean CD (ratio to input), failures, time.", "",
                  "| method | failures over the axis | starts to fail at |"
                  + (f" knee (CD within {result['knee_tolerance']:.0%} of the best) |" if with_knee else ""),
                  "|---|---|---|" + ("---|" if with_knee else "")]
        for m in methods:
            st = [(p or {}).get(m) for p in ax["stats"]]
            n = sum(s["n"] for s in st if s)
            f = sum(s["failures"] for s in st if s)
            lines.append(f"| {m} | {f}/{n} | {_fmt(ax['onset'].get(m))} |"
                         + (f" {_fmt(ax['knee'].get(m))} |" if with_knee else ""))
        lines.append("")
    return "\n".join(lines) + "\n"


def plot_axis(ax_res: dict, path: Path, title: str) -> Path:
    """CD ratio to the input, failure rate and time against the axis value, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dss.io_utils import atomic_savefig

    values, methods = ax_res["labels"], ax_res["methods"]
    numeric = all(isinstance(v, (int, float)) for v in values)
    xs = [float(v) for v in values] if numeric else list(range(len(values)))
    fig, axs = plt.subplots(1, 3, figsize=(15, 4.2))
    for i, m in enumerate(methods):
        st = [(p or {}).get(m) or {} for p in ax_res["stats"]]
        style = {"color": f"C{i % 10}", "marker": "o", "lw": 2.2 if m.startswith("dss") else 1.2,
                 "ls": "-" if m.startswith("dss") else "--", "label": m}
        for a, key in zip(axs, ("ratio", "failure_rate", "time_s")):
            ys = [s.get(key) if s.get(key) is not None else np.nan for s in st]
            a.plot(xs, ys, **style)
        kv = ax_res["knee"].get(m)
        if kv is not None:  # the knee: cheapest value within knee_tolerance of the best CD
            k = values.index(kv)
            axs[0].scatter([xs[k]], [st[k].get("ratio")], s=160, facecolors="none", edgecolors=style["color"],
                           lw=1.6, zorder=4, label=f"{m} knee ({kv})")
    axs[0].axhline(1.0, color="k", lw=0.8)
    axs[0].set_ylabel("output CD / input CD (mean over cases)")
    axs[0].set_yscale("log")
    axs[1].set_ylabel("failure rate (crash, time-out, NaN, worse than input)")
    axs[1].set_ylim(-0.05, 1.05)
    axs[2].set_ylabel("wall time per run (s)")
    axs[2].set_yscale("log")
    for a in axs:
        # a labelled axis (e.g. model files shown by width) is named by its label_name
        labelled = ax_res.get("labels") not in (None, ax_res["values"])
        a.set_xlabel(ax_res["key_name"] if labelled else ax_res["key"])
        if numeric and ax_res.get("log"):
            a.set_xscale("log")
        if not numeric:
            a.set_xticks(xs, [str(v) for v in values])
        a.grid(alpha=0.3)
    axs[0].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
    return path


def run(cfg: DictConfig, command: str | None = None) -> dict:
    """Run the study's axes (module docstring); returns the ``sweep.json`` content."""
    from dss.io_utils import atomic_write_json, atomic_write_text
    from experiments.common import save_config
    from experiments.evaluation.denoise_table import run as run_table

    t0 = time.perf_counter()
    study = cfg.study
    out = Path(os.path.expanduser(str(cfg.out_dir))).absolute()
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out)
    names = list(study.axes) if str(cfg.get("axes_to_run", "all")) == "all" else [str(a) for a in cfg.axes_to_run]
    base = base_table(study.get("table"), cfg.get("table"))
    points = axis_points(study, names, base)  # validates every axis before any work
    done: dict[str, dict] = {}
    by_point = []
    for i, pt in enumerate(points, 1):
        tcfg = pt["table"]
        tcfg.out_dir = str(out / "tables" / pt["setting"])
        tcfg.publish = False  # a point's table is part of this sweep's folder, never results/ on its own
        tcfg.progress = bool(cfg.get("progress", True))
        log.info("[%d/%d] %s = %s -> %s", i, len(points), pt["axis"], pt["value"], tcfg.out_dir)
        cmd = f"dss-sweep study={study.name} (axis {pt['axis']} = {pt['value']})"
        res = run_table(tcfg, command=cmd)  # finished records are reused (resume)
        done[pt["setting"]] = res
        methods = [m for m in dict.fromkeys(r["method"] for r in res["records"]) if m not in ("input", "floor")]
        by_point.append({**{k: v for k, v in pt.items() if k != "table"}, "out_dir": tcfg.out_dir,
                         "methods": methods, "stats": aggregate_point(res["records"], methods),
                         "records": [{k: r.get(k) for k in ("case", "method", "status", "message", "time_s", "metrics")}
                                     for r in res["records"]]})
    tol = float(cfg.get("knee_tolerance", 0.02))
    axes_res = []
    for name in names:
        pts = [p for p in by_point if p["axis"] == name]
        methods = list(dict.fromkeys(m for p in pts for m in p["methods"]))
        values = [p["value"] for p in pts]
        stats = [p["stats"] for p in pts]
        per = {m: [s.get(m) for s in stats] for m in methods}
        ax = study.axes[name]
        # labels: what the tables and charts show for each value (e.g. a model file's width)
        labels = list(ax.get("labels") or values)
        axes_res.append({"axis": name, "key": str(ax.key), "key_name": str(ax.get("label_name") or _key_name(str(ax.key))),
                         "log": bool(ax.get("log", False)), "values": values, "labels": labels, "methods": methods,
                         "stats": stats, "settings": [p["setting"] for p in pts],
                         "onset": {m: _label(first_failure(values, per[m]), values, labels) for m in methods},
                         "knee": {m: _label(knee(values, per[m], tol), values, labels) for m in methods}
                         if ax.get("knee") else {}})
    b = {k: base[k] for k in ("points", "noise", "outliers", "seed")}
    result = {"title": str(study.get("title", f"dss-sweep: {study.name}")), "study": str(study.name),
              "description": str(study.get("description", "")), "base": ", ".join(f"{k} {v}" for k, v in b.items()),
              "knee_tolerance": tol, "axes": axes_res, "points": by_point, "time_s": time.perf_counter() - t0,
              "command": command, "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
              "config": OmegaConf.to_container(cfg, resolve=True)}
    for ax in axes_res:
        plot_axis(ax, out / f"{ax['axis']}.png", f"{result['title']}: {ax['axis']}")
    md = render_markdown(result)
    atomic_write_json(out / "sweep.json", result)
    atomic_write_text(out / "sweep.md", md)
    atomic_write_text(out / "README.md", (
        f"# {result['title']}\n\nProduced by (from the repository root):\n\n```\n{command or 'experiments.evaluation.sweep.run(cfg)'}"
        f"\n```\n\nLast run: {time.strftime('%Y-%m-%d %H:%M:%S')}, {result['time_s']:.0f} s (resumed records not "
        f"rerun), {os.cpu_count()} CPU cores. Files: `sweep.md` (the tables), `sweep.json` (every point and "
        "record), one PNG per axis, `config.yaml`, `tables/<setting>/` (each point's dss-denoise-table "
        "output: `table.md`, `records/`; the case clouds, outputs and DSS runs are not in git).\n"))
    result["markdown"] = md
    if cfg.get("publish", False):
        from experiments import outputs

        names = ["sweep.md", "sweep.json", "README.md", "config.yaml", *(f"{ax['axis']}.png" for ax in axes_res)]
        result["published"] = [str(p) for p in outputs.publish_files(out, Path(str(cfg.published_dir)), names)]
    return result


@hydra.main(version_base="1.3", config_path="../../conf", config_name="sweep")
def _main(cfg: DictConfig) -> None:
    res = run(cfg, command=shlex.join(["dss-sweep", *sys.argv[1:]]))
    print(res["markdown"])
    print(f"sweep: {Path(str(cfg.out_dir)) / 'sweep.md'} ({res['time_s']:.0f} s)")
    if res.get("published"):
        print(f"published to {cfg.published_dir}: {', '.join(Path(p).name for p in res['published'])}")


def main() -> None:
    _main()


if __name__ == "__main__":
    main()
