"""The accuracy-vs-time chart of dss-deform's budget presets: one run per (scene, preset).

    python -m experiments.evaluation.deform_presets                      # teapot, bunny, yoga x fast, default, best
    python -m experiments.evaluation.deform_presets --out outputs/deform_presets/<date>   # resume
    python -m experiments.evaluation.deform_presets --out <dir> --publish   # then copy the summary to results/
    python -m experiments.evaluation.deform_presets --presets default --device cuda --threads 0   # GPU check

Each run is ``dss-deform scene=<scene> budget=<preset> threads=<threads> progress=false`` (with
``OMP_NUM_THREADS`` = threads) in ``<out>/runs/<scene>/<preset>/``, one at a time. A run whose
``metrics.json`` is there, made with the settings the run would use now (its ``config.yaml``
against conf/deform.yaml, the scene, the preset and the extra settings; the presets'
definitions aside) is not run again, so an interrupted command resumes with ``--out`` of its
folder; an unfinished run, or one whose settings changed, is run again.

Outputs in ``<out>`` (a fresh ``outputs/deform_presets/<date>`` unless given): ``presets.json``
(per run: Chamfer x1e4 and Hausdorff x1e3 to the target, the process's CPU seconds and wall
time, steps, points, the openings against the target's, normal error, the preset's settings,
the command), ``presets.md`` (the same as a table) and ``<scene>.png`` (Chamfer and Hausdorff
against CPU seconds, a point per preset). ``--publish`` copies these (not ``runs/``) to
``results/deform/presets/``. Exit status: the number of runs that failed.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

from experiments import outputs

COMMAND = "deform_presets"
PUBLISHED = "results/deform/presets"
SCENES = ("sphere_teapot", "sphere_bunny", "cube_yoga")
PRESETS = ("fast", "default", "best")
#: the issue's target for the best preset on the yoga figure (Chamfer x1e4, Hausdorff x1e3, CPU s)
TARGETS = {"cube_yoga": {"chamfer": 1.5, "hausdorff": 45.0, "cpu_s": 180.0}}
SUMMARY = ("presets.json", "presets.md")
#: config keys that do not change a run's result (the presets' definitions, whether it may
#: replace an earlier run's files)
IGNORED = ("budgets", "overwrite")
#: the interpreter that runs dss-deform (tests put a stand-in here)
PYTHON = sys.executable

__all__ = ["main", "run_one", "summarize", "plot_scene"]


def _overrides(scene: str, preset: str, args) -> list[str]:
    o = [f"scene={scene}", f"budget={preset}", f"seed={args.seed}", "progress=false", f"device={args.device}"]
    if args.threads > 0:
        o.append(f"threads={args.threads}")
    return o + list(args.set)


def _record(metrics: dict, scene: str, preset: str, command: str) -> dict:
    topo = metrics.get("topology") or {}
    ne = metrics.get("normal_error_deg") or {}
    return {
        "scene": scene, "preset": preset, "status": "ok",
        "chamfer": metrics["chamfer"], "hausdorff": metrics["hausdorff"],
        "cpu_time_s": metrics.get("cpu_time_s"), "wall_time_s": metrics.get("wall_time_s"),
        "steps": metrics.get("steps"), "points": metrics.get("points"),
        "openings": topo.get("openings"), "openings_target": topo.get("openings_target"),
        "holes_total": topo.get("holes_total"), "holes_total_target": topo.get("holes_total_target"),
        "views_missing_holes": topo.get("views_missing_holes"),
        "normal_error_deg": ne.get("mean"), "flipped_fraction": ne.get("flipped_fraction"),
        "nn_cv": (metrics.get("spacing") or {}).get("nn_cv"),
        "budget": metrics.get("budget"), "stages": metrics.get("stages"),
        "device": metrics.get("device"), "torch_threads": metrics.get("torch_threads"),
        "load_average": metrics.get("load_average"), "command": command,
    }


def effective_config(overrides: list[str]) -> dict:
    """The settings a dss-deform run with ``overrides`` uses (conf/deform.yaml, the scene, the
    budget preset, the overrides; resolved, without the ``budgets`` block): what its
    ``config.yaml`` holds, less the presets' definitions."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from experiments.deformation.budget import apply_budget

    conf = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("deform", overrides)
    apply_budget(cfg, {o.split("=", 1)[0].lstrip("+~") for o in overrides})
    d = OmegaConf.to_container(cfg, resolve=True)
    for key in IGNORED:
        d.pop(key, None)
    return d


def _done(run_dir: Path, expected: dict) -> dict | None:
    """The finished run's metrics when ``run_dir`` holds one made with the ``expected``
    settings (:func:`effective_config`); None otherwise (absent, unfinished, other settings)."""
    import yaml

    m, c = run_dir / "metrics.json", run_dir / "config.yaml"
    if not (m.is_file() and c.is_file()):
        return None
    try:
        saved = yaml.safe_load(c.read_text())
        for key in IGNORED:
            saved.pop(key, None)
        if saved != expected:
            return None
        return json.loads(m.read_text())
    except (OSError, ValueError, yaml.YAMLError, AttributeError):
        return None


def run_one(scene: str, preset: str, out: Path, args, python: str | None = None) -> dict:
    """Run (or reuse) one (scene, preset); returns its record (``status`` ok or failed)."""
    from dss.io_utils import atomic_write_json

    run_dir = out / "runs" / scene / preset
    overrides = _overrides(scene, preset, args)
    key = {"scene": scene, "preset": preset, "overrides": overrides}
    try:
        expected = effective_config(overrides)
    except Exception as e:  # a preset or setting dss-deform would refuse: one line, no run
        print(f"[{scene} / {preset}] failed: {e}", flush=True)
        return {"scene": scene, "preset": preset, "status": "failed", "why": str(e), "command": ""}
    env = dict(os.environ)
    if args.threads > 0:
        env["OMP_NUM_THREADS"] = str(args.threads)
    command = " ".join(([f"OMP_NUM_THREADS={args.threads}"] if args.threads > 0 else []) + ["dss-deform"]
                       + [shlex.quote(o) for o in overrides])
    metrics = _done(run_dir, expected)
    if metrics is not None:
        print(f"[{scene} / {preset}] done before: Chamfer {metrics['chamfer']:.3f}", flush=True)
        return _record(metrics, scene, preset, command)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "metrics.json").unlink(missing_ok=True)
    atomic_write_json(run_dir / "run.json", key)
    argv = [python or PYTHON, "-m", "experiments.apps.deform", *overrides, "overwrite=true", f"hydra.run.dir={run_dir}"]
    print(f"[{scene} / {preset}] {command}", flush=True)
    t0 = time.perf_counter()
    try:
        with open(run_dir / "log.txt", "w") as logf:
            rc = subprocess.run(argv, env=env, stdout=logf, stderr=subprocess.STDOUT,
                                timeout=args.timeout or None).returncode
        why = f"exit {rc}"
    except subprocess.TimeoutExpired:
        rc, why = -1, f"over --timeout {args.timeout} s"
    metrics = _done(run_dir, expected) if rc == 0 else None
    if metrics is None:
        tail = (run_dir / "log.txt").read_text(errors="replace").strip().splitlines()[-3:]
        print(f"[{scene} / {preset}] failed ({why}): {' | '.join(tail)}", flush=True)
        return {"scene": scene, "preset": preset, "status": "failed", "why": why, "log_tail": tail,
                "seconds": time.perf_counter() - t0, "command": command}
    print(f"[{scene} / {preset}] Chamfer {metrics['chamfer']:.3f}, Hausdorff {metrics['hausdorff']:.1f}, "
          f"{metrics.get('cpu_time_s', 0):.0f} CPU s", flush=True)
    return _record(metrics, scene, preset, command)


def plot_scene(records: list[dict], scene: str, path: Path) -> None:
    """Chamfer and Hausdorff against CPU seconds, a labelled point per preset (and the scene's
    target, where the issue sets one)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dss.io_utils import atomic_savefig

    rs = [r for r in records if r["scene"] == scene and r["status"] == "ok"]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    target = TARGETS.get(scene, {})
    for ax, key, label in ((axes[0], "chamfer", "Chamfer to the target (x1e4)"),
                           (axes[1], "hausdorff", "Hausdorff to the target (x1e3)")):
        xs = [r["cpu_time_s"] for r in rs]
        ys = [r[key] for r in rs]
        ax.plot(xs, ys, "o", ms=6)
        for r, x, y in zip(rs, xs, ys):
            ax.annotate(f"{r['preset']} ({r['openings']}/{r['openings_target']} openings)"
                        if r.get("openings_target") else r["preset"], (x, y), textcoords="offset points",
                        xytext=(5, 4), fontsize=8)
        if key in target:
            ax.axhline(target[key], color="tab:red", ls="--", lw=0.8, label=f"target: {target[key]:g}")
        if "cpu_s" in target:
            ax.axvline(target["cpu_s"], color="tab:red", ls=":", lw=0.8, label=f"{target['cpu_s']:g} CPU s (3 min)")
        if target:
            ax.legend(fontsize=7, loc="upper right")
        ax.set_xlabel("CPU seconds, whole process (one thread)" if all(r.get("torch_threads") == 1 for r in rs)
                      else "CPU seconds, whole process")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if xs:
            ax.set_xlim(0, max(max(xs), target.get("cpu_s", 0)) * 1.15)
    fig.suptitle(f"dss-deform {scene}: budget presets", fontsize=10)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)


def summarize(records: list[dict], argv: list[str]) -> tuple[dict, str]:
    """(presets.json's content, presets.md's text)."""
    doc = {"command": "python -m experiments.evaluation.deform_presets " + " ".join(shlex.quote(a) for a in argv),
           "units": {"chamfer": "x1e4", "hausdorff": "x1e3", "cpu_time_s": "process CPU seconds (user + system)",
                     "wall_time_s": "the optimisation's wall seconds"},
           "targets": TARGETS, "runs": records}
    lines = [f"`{doc['command']}`", "",
             "| scene | preset | Chamfer x1e4 | Hausdorff x1e3 | openings (target) | holes (target) | "
             "normal error, deg (flipped) | steps | points | CPU s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        if r["status"] != "ok":
            lines.append(f"| `{r['scene']}` | {r['preset']} | failed: {r.get('why')} | | | | | | | |")
            continue
        lines.append(f"| `{r['scene']}` | {r['preset']} | {r['chamfer']:.2f} | {r['hausdorff']:.1f} | "
                     f"{r['openings']} ({r['openings_target']}) | {r['holes_total']} ({r['holes_total_target']}) | "
                     f"{r['normal_error_deg']:.1f} ({100 * r['flipped_fraction']:.1f}%) | {r['steps']} | "
                     f"{r['points']} | {r['cpu_time_s']:.0f} |")
    return doc, "\n".join(lines) + "\n"


def parse_args(argv):
    ap = argparse.ArgumentParser(prog="python -m experiments.evaluation.deform_presets", description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--presets", nargs="+", default=list(PRESETS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1, help="torch and OpenMP threads per run (0: the defaults)")
    ap.add_argument("--device", default="cpu", help="dss-deform device= (cpu, cuda, auto)")
    ap.add_argument("--timeout", type=float, default=0, help="seconds per run (0: none)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="more dss-deform settings for every run (toy sizes in tests)")
    ap.add_argument("--out", default=None, help="output folder, resumed when it holds runs "
                                                "(default: a fresh outputs/deform_presets/<date>)")
    ap.add_argument("--publish", action="store_true", help=f"also copy the summary and charts to {PUBLISHED}")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    from dss.io_utils import atomic_write_json, atomic_write_text

    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    if args.publish and (args.set or args.presets != list(PRESETS) or args.scenes != list(SCENES)):
        print(f"{COMMAND}: error: --publish is for the full chart (every scene and preset, no --set)",
              file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else outputs.fresh_folder(COMMAND)
    out.mkdir(parents=True, exist_ok=True)
    print(f"{COMMAND}: writing to {out} (resume with --out {out})", flush=True)
    records = [run_one(scene, preset, out, args) for scene in args.scenes for preset in args.presets]
    doc, table = summarize(records, [a for a in argv if a != "--publish"])
    atomic_write_json(out / "presets.json", doc)
    atomic_write_text(out / "presets.md", table)
    charts = []
    for scene in args.scenes:
        if any(r["scene"] == scene and r["status"] == "ok" for r in records):
            plot_scene(records, scene, out / f"{scene}.png")
            charts.append(f"{scene}.png")
    failed = sum(r["status"] != "ok" for r in records)
    if args.publish:
        if failed:
            print(f"{COMMAND}: error: {failed} run(s) failed, nothing published", file=sys.stderr)
            return failed
        for p in outputs.publish_files(out, PUBLISHED, list(SUMMARY) + charts):
            print(f"published {p}")
    print(table)
    return failed


if __name__ == "__main__":
    sys.exit(main())
