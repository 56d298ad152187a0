"""``dss-fig-runtime``: the paper's runtime table as a chart, ours on a CPU and a GPU beside the paper's.

    dss-fig-runtime            # results/bench/runtime_table.json + the H100 table -> outputs/dss-fig-runtime/<time>/
    dss-fig-runtime --publish  # -> results/bench/runtime_chart.{png,json} (the tracked chart)
    dss-fig-runtime --cpu A.json --cuda B.json --out /tmp/chart

Reads the JSONs that ``dss-runtime-table`` writes (it measures nothing itself): ``--cpu``, a table
with the C++ column measured (and the PyTorch reference where it ran), and ``--cuda``, a table
with the CUDA column measured (on a GPU machine; ``experiments/benchmarks/gpu_check.sh table``). Two panels:

- left, per workload, the time of one optimisation step (forward + backward, ms, log scale) as
  the paper reports it: averaged over the run's position and normal steps with the paper's step
  counts as weights. The paper's GTX 1080Ti figures are the published ones (Table tab:speed);
- right, per workload and kind of step, the measured step over its counted floor
  (``experiments/benchmarks/perf_counts.py``: the work over the device's peak rates), with the 4x target line
  for the CPU. A ratio is only as good as the floor's rates: the JSON says which rates each
  table used (the CPU's measured; the GPU's measured with ``--gpu-rates``, else the H100's
  published spec).

Writes ``<out>.png`` and ``<out>.json`` (every plotted number, with the sources' commands) atomically.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from dss.io_utils import atomic_savefig, atomic_write_json
from experiments import outputs

from . import command_line, setup_matplotlib

log = logging.getLogger("dss-fig-runtime")

KINDS = ("position", "normal")
CPU_FLOOR_FACTOR = 4.0  # the target: a 20K step on 2 CPU cores within 4x of its counted floor
SERIES = (  # (key in the chart's JSON, label, colour)
    ("paper_1080ti", "paper, GTX 1080Ti (published)", "#9e9e9e"),
    ("reference", "ours, PyTorch reference (CPU)", "#f2b134"),
    ("cpp", "ours, C++ kernel (CPU)", "#2a7ab9"),
    ("cuda", "ours, CUDA kernel", "#d1495b"),
)


def load_table(path: str | Path, column: str) -> dict:
    """A ``dss-runtime-table`` JSON whose ``column`` (``cpp`` or ``cuda``) was measured somewhere."""
    p = Path(path)
    if not p.is_file():
        raise SystemExit(f"{p}: no such file (write it with dss-runtime-table)")
    try:
        d = json.loads(p.read_text())
        rows = d["workloads"]
        _ = [(r["key"], r["points"], r["position_steps"], r["normal_steps"], r["paper_1080ti"]["forward_ms"],
              r[column].get("status")) for r in rows]
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise SystemExit(f"{p}: not a dss-runtime-table JSON ({e!r})") from e
    if not any(r[column].get("status") == "measured" for r in rows):
        raise SystemExit(f"{p}: its {column} column was not measured in any workload "
                         f"({sorted({r[column].get('status', '?') for r in rows})})")
    return d


def _floor_rows(table: dict) -> dict:
    return {f["key"]: f for f in (table.get("floor") or {}).get("workloads", [])}


def _step_floors(f: dict | None, col: str) -> dict | None:
    """Per-kind step floors (ms) of one workload's floor row for a column, as its table computed
    them; tables of older versions fall back as dss-runtime-table did then (the forward floor where
    no step floor was counted), and a table without floors gives None."""
    if f is None:
        return None
    if col == "cpp":
        return f.get("cpu_step_floor_ms") or {k: f["cpu_floor_ms"] for k in KINDS}
    return (f.get("gpu_step_floor_ms") or f.get("h100_published_step_floor_ms")
            or {k: f["h100_published_floor_ms"] for k in KINDS})


def _gpu_floor_note(table: dict) -> str:
    fl = table.get("floor") or {}
    g = fl.get("gpu_rates")
    if g and g.get("source") == "measured":
        return f"rates measured on the {g['device']}"
    pub = fl.get("h100_published") or {}
    return f"published spec of the {pub.get('device', 'H100')}"


def chart_data(cpu: dict, cuda: dict, cpu_path: str, cuda_path: str) -> dict:
    """The numbers the chart plots, from the two tables (workloads matched by key and points)."""
    cuda_rows = {(r["key"], r["points"]): r for r in cuda["workloads"]}
    cpu_floors, cuda_floors = _floor_rows(cpu), _floor_rows(cuda)
    out = {"sources": {"cpu": {"file": str(cpu_path), "command": cpu.get("command"),
                               "machine": cpu.get("machine", {}).get("cpu"),
                               "torch_threads": cpu.get("machine", {}).get("torch_threads")},
                       "cuda": {"file": str(cuda_path), "command": cuda.get("command"),
                                "measured_by": cuda.get("measured_by"), "device": cuda.get("columns", {}).get("cuda"),
                                "floor_rates": _gpu_floor_note(cuda)}},
           "step_note": "step = forward + backward (ms); per workload averaged over its position and normal steps "
                        "with the paper's step counts as weights (the paper's 'avg. forward / backward time')",
           "workloads": []}
    for r in cpu["workloads"]:
        cu = cuda_rows.get((r["key"], r["points"]))
        pp = r["paper_1080ti"]
        w = {"key": r["key"], "application": r["application"], "points": r["points"],
             "steps": {"position": r["position_steps"], "normal": r["normal_steps"]},
             "step_ms": {"paper_1080ti": pp["forward_ms"] + pp["backward_ms"]}, "ratio_to_floor": {}, "status": {}}
        for col, row, floors in (("cpp", r, cpu_floors), ("reference", r, cpu_floors), ("cuda", cu, cuda_floors)):
            x = (row or {}).get(col) or {}
            if x.get("status") != "measured":
                w["status"][col] = x.get("status", "no such workload in the table")
                continue
            w["step_ms"][col] = x["forward_ms"] + x["backward_ms"]
            if col == "reference":
                continue
            fk = _step_floors(floors.get(r["key"]), col)
            if fk is None:
                w["status"][col] = "measured; no counted floor in its table"
                continue
            w["ratio_to_floor"][col] = {k: (x["per_kind"][k]["forward_ms"] + x["per_kind"][k]["backward_ms"]) / fk[k]
                                        for k in KINDS}
        out["workloads"].append(w)
    return out


def _plain(v: float, _pos=None) -> str:
    """Log-axis tick labels as plain numbers (1, 10, 100) instead of powers of ten."""
    return f"{v:g}"


def plot(data: dict, out_png: Path):
    plt = setup_matplotlib()
    from matplotlib.ticker import FuncFormatter
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(13, 4.8), gridspec_kw={"width_ratios": [1.1, 1]})
    ws = data["workloads"]
    names = [f"{w['application']}\n{w['points'] // 1000}K points" for w in ws]
    steps = [v for w in ws for v in w["step_ms"].values()]
    bottom = min([1.0] + [v / 2 for v in steps])  # the step chart's lower edge (ms): 1, or below the fastest
    width = 0.8 / len(SERIES)
    for i, (key, label, colour) in enumerate(SERIES):
        xs = [j + (i - (len(SERIES) - 1) / 2) * width for j in range(len(ws))]
        vals = [w["step_ms"].get(key) for w in ws]
        pts = [(x, v) for x, v in zip(xs, vals) if v is not None]
        if not pts:
            continue
        ax1.bar([p[0] for p in pts], [p[1] for p in pts], width, label=label, color=colour)
        for x, v in pts:
            ax1.text(x, v * 1.08, f"{v:.0f}" if v >= 10 else f"{v:.1f}", ha="center", va="bottom", fontsize=7)
        for x, w in zip(xs, ws):  # a column that did not run for this workload says so
            if key not in w["step_ms"]:
                ax1.text(x, 1.2 * bottom, "not run", rotation=90, ha="center", va="bottom", fontsize=6,
                         color=colour)
    ax1.set_yscale("log")
    ax1.set_ylim(bottom, max(steps) * 3)
    ax1.set_xticks(range(len(ws)), names, fontsize=8)
    ax1.set_ylabel("ms per step (forward + backward), log")
    ax1.set_title("One optimisation step, 12 views at 256x256", fontsize=10)
    ax1.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, frameon=False)
    ax1.grid(axis="y", which="both", alpha=0.25)
    ax1.yaxis.set_major_formatter(FuncFormatter(_plain))

    groups = [(w, k) for w in ws for k in KINDS]
    for i, (key, label, colour) in enumerate(s for s in SERIES if s[0] in ("cpp", "cuda")):
        xs, vals = [], []
        for j, (w, k) in enumerate(groups):
            v = w["ratio_to_floor"].get(key, {}).get(k)
            if v is not None:
                xs.append(j + (i - 0.5) * 0.38)
                vals.append(v)
        ax2.bar(xs, vals, 0.38, label=label, color=colour)
        for x, v in zip(xs, vals):
            ax2.text(x, v * 1.08, f"{v:.1f}x" if v < 10 else f"{v:.0f}x", ha="center", va="bottom", fontsize=7)
    ax2.axhline(CPU_FLOOR_FACTOR, color="#2a7ab9", ls="--", lw=1, label=f"{CPU_FLOOR_FACTOR:.0f}x floor: the CPU target")
    ax2.set_yscale("log")
    ratios = [v for w in ws for r in w["ratio_to_floor"].values() for v in r.values()]
    ax2.set_ylim(min([1.0] + [v / 2 for v in ratios]), max(ratios + [CPU_FLOOR_FACTOR]) * 2)
    ax2.set_xticks(range(len(groups)), [f"{w['points'] // 1000}K\n{k}" for w, k in groups], fontsize=8)
    ax2.set_ylabel("measured step / counted floor, log")
    ax2.set_title(f"Against the counted floors (GPU: {data['sources']['cuda']['floor_rates']})", fontsize=9)
    ax2.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=3, frameon=False)
    ax2.grid(axis="y", which="both", alpha=0.25)
    ax2.yaxis.set_major_formatter(FuncFormatter(_plain))
    ax2.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: ""))
    cpu, cuda = data["sources"]["cpu"], data["sources"]["cuda"]
    fig.suptitle(f"Runtime: CPU column on {cpu['machine']} ({cpu['torch_threads']} threads); "
                 f"{cuda['device']}", fontsize=9)
    fig.tight_layout()
    atomic_savefig(fig, out_png, dpi=130)
    plt.close(fig)


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cpu", default="results/bench/runtime_table.json",
                    help="dss-runtime-table JSON with the C++ column (default: the shipped 2-thread table)")
    ap.add_argument("--cuda", default="results/bench/gpu/h100/runtime_table_cuda_measured_floors.json",
                    help="dss-runtime-table JSON with the CUDA column (default: the shipped H100 table)")
    outputs.add_arguments(ap, published="results/bench/runtime_chart", what="output prefix: <out>.png and <out>.json")
    args = ap.parse_args(argv)
    args.out = str(outputs.folder(args, "dss-fig-runtime", name="runtime_chart"))
    return args


def run(argv=None) -> dict:
    args = parse_args(argv)
    cpu, cuda = load_table(args.cpu, "cpp"), load_table(args.cuda, "cuda")
    data = {"command": command_line("dss-fig-runtime", argv), **chart_data(cpu, cuda, args.cpu, args.cuda)}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    plot(data, out.with_name(out.name + ".png"))
    atomic_write_json(out.with_name(out.name + ".json"), data)
    log.info("wrote %s.png and %s.json", out, out)
    return data


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    run(argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
