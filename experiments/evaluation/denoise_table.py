"""``dss-denoise-table``: the paper's point cloud denoising comparison, in one resumable command.

    dss-denoise-table                                 # 20K points, 1% noise, every method
    dss-denoise-table noise=0.003                     # the 0.3% table
    dss-denoise-table out_dir=outputs/dss-denoise-table/<date>   # resume that run
    dss-denoise-table publish=true                    # + copy the summary to results/denoise/table_0.01_20000
    dss-denoise-table methods=[cgal_jet,dss_l0] 'dss_overrides=["optimizer.cycles=4"]'

Cases (``cases`` + ``meshlab_samples`` + ``generated``): the Kangaroo mesh (``../shared/data``,
skipped with the reason when absent), pymeshlab's sample meshes (bunny, cow, airplane, bone, face;
``meshlab_samples=true``, where the ``baselines`` extra is installed) and the first ``generated.count`` shapes of the ``cpu`` dss-prep preset's *test*
split in the plan's order, made exactly as dss-prep and ``experiments/apps/make_example.py`` make them
(the first is the shipped example: at 20K points and 1% noise its files are the shipped ones;
:mod:`experiments.evaluation.table.cases`).
Each case: ``points`` Poisson-disk samples of the mesh (the clean cloud, ground truth with the
mesh) plus Gaussian noise of std ``noise`` x bbox diagonal (the noisy input), seeded, cached in
``out_dir/cases/<case>/{noisy,clean,mesh}.ply`` (+ ``case.json``).

Methods: the input itself (no method) and the Chamfer floor (a second clean sampling), every
baseline of :mod:`experiments.evaluation.baselines` (``preset_params(method, noise)``, run by
:func:`~experiments.evaluation.baselines.runner.run_method` in a subprocess with a time limit), and DSS
(``dss_pix2pix``: dss-denoise with the shipped model for ``noise``; ``dss_l0``: with the L0
image filter), each a ``python -m experiments.apps.denoise`` subprocess with a time limit. A crash,
hang or NaN output is a failure record; the table carries on.

Metrics: :func:`dss.metrics.evaluate` under ``protocol``: ``paper`` (clean cloud's bbox diagonal
= 1; ``noise`` is a fraction of the bbox diagonal, the DSS paper's levels 0.3%, 1%, 2%) or ``score``
(ScoreDenoise / IterativePFN: farthest clean point at distance 1 from the bbox centre; ``noise`` is a
fraction of that bounding-sphere radius, their levels 1%, 2%, 3%; each case's noise is converted to
the bbox-diagonal fraction that the baselines' presets and dss-denoise's model choice expect, and
recorded). CD x1e4, HD x1e3, P2M x1e4 (two-sided, PyTorch3D's definition), plus the method's wall time
(baselines: the method call in its worker; DSS: the outlier removal and the optimisation, i.e. rendering, reference
generation and updates, without start-up, file input and normal estimation).

Outputs in ``out_dir`` (a fresh ``outputs/dss-denoise-table/<date>`` unless given; atomic writes): ``records/<case>/<method>.json`` (one per run; an
existing one is reused unless ``overwrite=true``, so an interrupted run resumes), ``table.json``
(every record + per-method summary), ``table.md`` (rows = methods, columns = CD/HD/P2M per case,
means over cases, mean time; best per column in bold), ``accuracy_vs_time.png`` (mean CD and mean
P2M against mean time, Pareto front marked), ``README.md`` (the command), ``outputs/`` (each
method's cloud) and ``runs/`` (DSS run directories with their logs). ``publish=true`` copies
``table.md``, ``table.json``, the chart, ``README.md`` and ``config.yaml`` to ``published_dir``
(under ``results/``, tracked), replacing what was there.
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
from omegaconf import DictConfig, OmegaConf

from experiments.evaluation.table import cases, report, runners
from experiments.evaluation.table.cases import plain, safe_name
from experiments.evaluation.table.report import PROTOCOL, fmt

log = logging.getLogger(__name__)

__all__ = ["run", "main", "NOISE_UNIT", "table_settings"]

#: the unit of ``noise`` under each protocol
NOISE_UNIT = {"paper": "diag", "score": "radius"}
UNIT_NAMES = {"diag": "bbox diagonal", "radius": "bounding-sphere radius"}


def table_settings(cfg: DictConfig) -> dict:
    """The table's settings, checked before any work: noise (in ``unit``: the protocol's),
    points, seed, outliers, protocol, methods (validated, with their parameters)."""
    noise, points, seed = float(cfg.noise), int(cfg.points), int(cfg.seed)
    outliers = float(cfg.get("outliers", 0.0) or 0.0)
    protocol = str(cfg.get("protocol", PROTOCOL))
    if protocol not in NOISE_UNIT:
        raise ValueError(f"protocol must be one of {sorted(NOISE_UNIT)}, got {protocol!r}")
    unit = NOISE_UNIT[protocol]
    if not (noise > 0 and math.isfinite(noise)):
        raise ValueError(f"noise must be a positive fraction of the {UNIT_NAMES[unit]}, got {cfg.noise}")
    if not (0.0 <= outliers <= 1.0):
        raise ValueError(f"outliers must be a fraction of points in [0, 1], got {cfg.outliers}")
    if points < 32:
        raise ValueError(f"points must be >= 32, got {points}")
    methods = runners.method_list(cfg)
    runners.check_params(cfg, methods, noise)
    return {"noise": noise, "points": points, "seed": seed, "outliers": outliers, "protocol": protocol,
            "unit": unit, "methods": methods}


def _skipped(meta: dict, methods: list[str]) -> list[dict]:
    log.warning("case %s skipped: %s", meta["name"], meta["reason"])
    return [{"case": meta["name"], "method": m, "kind": None, "status": "skipped", "failed": True,
             "message": meta["reason"], "metrics": None} for m in ["input", *methods]]


def _run_method(cfg: DictConfig, out: Path, name: str, label: str, req: dict, limit: float, cdir: Path, gt: dict,
                case_noise: float) -> dict:
    """One (case, method) record, run now (dss-denoise or a baseline) and stored."""
    from dss.io_utils import atomic_write_json

    threads = int(cfg.threads) if cfg.get("threads") else None
    out_ply = out / "outputs" / safe_name(name) / f"{safe_name(label)}.ply" if cfg.get("save_outputs", True) else None
    if label in dict(cfg.dss_methods or {}):
        rec = runners.run_dss(req["overrides"], cdir, gt, case_noise, limit, threads,
                              out / "runs" / safe_name(name) / safe_name(label), out_ply)
    else:
        rec = runners.run_baseline(req["spec"], gt, req["params"], limit, threads, out_ply,
                                   prefilter=req.get("prefilter") == "outliers")
    rec = {"case": name, "method": label, **rec, "request": req}
    atomic_write_json(out / "records" / safe_name(name) / f"{safe_name(label)}.json", rec)
    cd = (rec.get("metrics") or {}).get("chamfer")
    log.info("%s / %s: %s%s (%s s)", name, label, rec["status"], f", CD x1e4 {cd:.4g}" if cd else "",
             fmt(rec.get("time_s")))
    return rec


def _run_case(cfg: DictConfig, out: Path, case: dict, st: dict, bar) -> tuple[dict, list[dict]]:
    """(case.json, records) of one case: its files made or reused, the input and floor rows, then
    every method (a stored record with the same request is reused)."""
    name, methods, overwrite = case["name"], st["methods"], bool(cfg.get("overwrite", False))
    cdir, rdir = out / "cases" / safe_name(name), out / "records" / safe_name(name)
    bar.set_description(f"{name}: preparing")
    meta = cases.prepare_case(case, cdir, st["points"], st["noise"], st["seed"], overwrite, st["outliers"], st["unit"])
    if meta["status"] == "skipped":
        bar.update(len(methods))
        return meta, _skipped(meta, methods)
    if meta.get("remade"):
        for f in rdir.glob("*.json"):  # made for the old case files
            f.unlink()
    rdir.mkdir(parents=True, exist_ok=True)
    gt = {**cases.load_case(cdir), "protocol": st["protocol"]}
    case_noise = float(meta.get("noise_diag", st["noise"]))  # what presets and dss-denoise expect
    records = runners.reference_rows(name, gt, rdir, bool(cfg.get("floor", True)), st["seed"], overwrite)
    gt["input_chamfer"] = records[0]["metrics"]["chamfer"]
    for label in methods:
        req = runners.request(label, cfg, case_noise)
        limit = float((cfg.time_limits or {}).get(label, cfg.time_limit_s))
        old = None if overwrite else runners.read_json(rdir / f"{safe_name(label)}.json")
        if not runners.reusable(old, req, limit):
            bar.set_description(f"{name}: {label}")
            old = _run_method(cfg, out, name, label, req, limit, cdir, gt, case_noise)
        records.append(old)
        bar.update(1)
    return meta, records


def _title_and_notes(cfg: DictConfig, st: dict) -> tuple[str, list[str]]:
    points, noise, outliers, seed, protocol = st["points"], st["noise"], st["outliers"], st["seed"], st["protocol"]
    unit_name = UNIT_NAMES[st["unit"]]
    title = f"Point cloud denoising: {points} points, noise {noise:g} x {unit_name}" + (
        f", {outliers:.3g} x {points} uniform outliers" if outliers else "") + (f", seed {seed}" if seed else "") + (
        ", baselines after DSS's outlier removal" if cfg.get("baseline_outlier_removal", False) else "")
    scale = {"paper": "bbox diagonal 1", "score": "farthest point at distance 1"}[protocol]
    threads = int(cfg.threads) if cfg.get("threads") else None
    notes = [f"`{protocol}` protocol (dss/metrics.py): clean cloud's bbox centred, {scale}; CD x1e4, HD x1e3 "
             "(symmetric, not squared), P2M x1e4 (two-sided, PyTorch3D's point_mesh_face_distance, exact "
             "triangle distances); lower is better",
             "time: baselines: the method call in its worker process; DSS: the outlier removal and the optimisation (rendering, "
             "reference generation, updates), without start-up, file input and normal estimation",
             f"threads per method: {threads or 'default'}; time limit {cfg.time_limit_s:g} s per run"
             + (f" (per method: {dict(cfg.time_limits)})" if cfg.time_limits else ""),
             f"DSS overrides: {plain(cfg.get('dss_overrides'))}; baseline parameters: "
             "preset_params(method, case noise as a bbox-diagonal fraction) (+ params), see table.json"]
    return title, notes


def _readme(title: str, command: str, elapsed: float, load_average) -> str:
    return (f"# {title}\n\nProduced by (from the repository root):\n\n```\n{command}\n```\n\n"
            f"Last run: {time.strftime('%Y-%m-%d %H:%M:%S')}, {elapsed:.0f} s (resumed records not rerun), "
            f"{os.cpu_count()} CPU cores, load average {load_average}.\n\n"
            "Files: `table.md` (the table), `table.json` (every record: case, method, parameters, status, "
            "metrics, times, versions), `accuracy_vs_time.png`, `config.yaml`, `cases/` (noisy, clean, mesh "
            "PLYs), `records/` (one JSON per case and method; delete one to rerun it), `outputs/` (each "
            "method's cloud), `runs/` (DSS run directories and logs).\n")


def _write(cfg: DictConfig, out: Path, st: dict, case_info: list[dict], records: list[dict], held_out: set,
           command: str | None, t0: float) -> dict:
    """table.json, table.md, the chart, README.md (and the published copies); the run's result."""
    from dss.io_utils import atomic_write_json, atomic_write_text

    ready = [c["name"] for c in case_info if c["status"] != "skipped"]
    rows = report.summarize(records, st["methods"], ready, held_out)
    title, notes = _title_and_notes(cfg, st)
    md = report.render_markdown(rows, case_info, title, notes)
    files = {"markdown": "table.md", "json": "table.json", "readme": "README.md", "config": "config.yaml"}
    if rows and report.plot_accuracy_vs_time(rows, out / "accuracy_vs_time.png", title, st["protocol"]):
        files["chart"] = "accuracy_vs_time.png"
    elapsed = time.perf_counter() - t0
    result = {"title": title, "protocol": st["protocol"], "noise_unit": st["unit"], "points": st["points"],
              "noise": st["noise"], "seed": st["seed"], "outliers": st["outliers"], "methods": st["methods"],
              "cases": case_info, "rows": rows, "records": records, "versions": runners.versions(),
              "config": OmegaConf.to_container(cfg, resolve=True), "time_s": elapsed, "files": files,
              "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}
    atomic_write_json(out / "table.json", result)
    atomic_write_text(out / "table.md", md)
    command = command or "python -c 'experiments.evaluation.denoise_table.run(cfg)' (the config is config.yaml)"
    atomic_write_text(out / "README.md", _readme(title, command, elapsed, result["load_average"]))
    published = []
    if cfg.get("publish", False):
        from experiments import outputs

        published = [str(p) for p in outputs.publish_files(out, Path(str(cfg.published_dir)), list(files.values()))]
    return {"out_dir": str(out), "records": records, "rows": rows, "cases": case_info, "files": files,
            "time_s": elapsed, "markdown": md, "published": published}


def run(cfg: DictConfig, command: str | None = None) -> dict:
    """Build the table (see the module docstring); returns ``{"out_dir", "records", "rows",
    "cases", "files", "time_s"}``. ``command``: the command line recorded in README.md."""
    from tqdm.auto import tqdm

    from experiments.common import save_config

    t0 = time.perf_counter()
    st = table_settings(cfg)
    case_dicts = cases.case_list(cfg)
    out = Path(os.path.expanduser(str(cfg.out_dir))).absolute()
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out)
    records, case_info = [], []
    bar = tqdm(total=len(case_dicts) * len(st["methods"]), desc="denoise table", unit="run",
               disable=not cfg.get("progress", True), dynamic_ncols=True)
    for case in case_dicts:
        meta, recs = _run_case(cfg, out, case, st, bar)
        case_info.append(meta)
        records += recs
    bar.close()
    held_out = {c["name"] for c in case_dicts if c.get("held_out")}
    for meta in case_info:  # the table's markdown reads it from the case info
        meta["held_out"] = meta["name"] in held_out
    return _write(cfg, out, st, case_info, records, held_out, command, t0)


@hydra.main(version_base="1.3", config_path="../../conf", config_name="denoise_table")
def _main(cfg: DictConfig) -> None:
    res = run(cfg, command=shlex.join(["dss-denoise-table", *sys.argv[1:]]))
    print(res["markdown"])
    print(f"table: {Path(res['out_dir']) / 'table.md'} ({res['time_s']:.0f} s)")
    if res["published"]:
        print(f"published to {cfg.published_dir}: {', '.join(Path(p).name for p in res['published'])}")
    for c in res["cases"]:  # a missing optional case (a mesh outside the repository) must not pass unnoticed
        if c["status"] == "skipped":
            print(f"NOTICE: case {c['name']} was skipped: {c['reason']}", file=sys.stderr)


def main() -> None:
    _main()


if __name__ == "__main__":
    main()
