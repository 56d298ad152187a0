"""Interleaved A/B timing of whole optimisation steps: a git revision against the working tree.

    python -m experiments.ab_steps --base a8ccf9b [--kinds normal position] [--rounds 5]

``dss-runtime-table`` run twice minutes apart on the same code can differ by 20% on a shared
machine, more than a change that saves a few ms per step. Here the two versions take turns: the
base revision is checked out into a temporary git worktree (with ``../shared`` linked beside it,
so both time the kangaroo cloud), and each round runs one child process per version and kind,
alternating, each building its own copy of the C++ kernel (separate ``TORCH_EXTENSIONS_DIR``).
A child times steps as ``dss-runtime-table`` does, with the base revision's own
``experiments.runtime_table.time_steps`` (``render`` + SMAPE forward, then ``backward``; the
20K-point kangaroo cloud, 12 views at 256x256, visibility window 4 for position steps):
``--warmup`` steps, then ``--steps`` measured ones, and reports their medians.
The result is the median over rounds of each child's medians, and the ratio base / working
tree, written to ``--out`` (JSON) with every child's numbers. Drift in the machine's speed hits
both versions alike because they alternate.

``--in-process`` alternates step by step instead, in one process, for a base that differs from
the working tree only in the C++ kernel (``dss/csrc``; any other Python file under ``dss/``
differing is refused): both revisions' ``dss_cpu.cpp`` are built side by side (as
``experiments.ab_kernels`` does) and every step is run once per build, on the same cameras,
target and parameters, the builds' order swapped every step
(``experiments.ab_step_overheads.alternate_steps``; no parameter update). Rounds of child
processes differ by 10-15% on this machine (session 33); steps that alternate in one process see
the same machine state.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from experiments.bench_common import base_worktree, git_short, main_for, write_result
from experiments.figures import command_line


def child(kind: str, n_points: int, views: int, size: int, threads: int, warmup: int, steps: int) -> dict:
    """Time ``steps`` optimisation steps of one kind with whichever ``dss`` is first on the path,
    through that revision's ``experiments.runtime_table.time_steps`` (what ``dss-runtime-table``
    times: fresh cameras every step, render + SMAPE, backward, an Adam update not timed)."""
    import torch

    from experiments.bench_render import benchmark_cloud
    from experiments.runtime_table import time_steps

    torch.set_num_threads(threads)
    pts, nrm, _ = benchmark_cloud(n_points)
    r = time_steps(pts, nrm, "cpp", kind, views, size, warmup, steps, progress=False)
    runs = list(zip(r["forward_ms_runs"], r["backward_ms_runs"]))
    return {"forward_ms": r["forward_ms"], "backward_ms": r["backward_ms"],
            "step_ms": statistics.median(f + b for f, b in runs), "runs_ms": runs}


def in_process(args) -> dict:
    """Steps of both builds of the C++ kernel alternating in this process (``--in-process``):
    ``experiments.ab_step_overheads.alternate_steps`` with a variant per build, each putting its
    module in place of the package's (``dss._ext.load_cpu`` / ``loaded_cpu``) for its steps."""
    import tempfile

    import torch

    from dss import _ext
    from experiments import ab_kernels
    from experiments.ab_step_overheads import alternate_steps
    from experiments.bench_common import REPO

    changed = subprocess.run(["git", "diff", "--name-only", args.base, "--", "dss"], cwd=REPO, check=True,
                             capture_output=True, text=True).stdout.split()
    python = [f for f in changed if not f.startswith("dss/csrc/")]
    if python:
        raise SystemExit(f"--in-process swaps only the C++ kernel, but these files differ from {args.base}: "
                         f"{', '.join(python)}; run without --in-process")
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        mods = {"base": ab_kernels.build("dss_abs_base", ab_kernels.git_source(args.base), Path(tmp),
                                         ab_kernels.git_headers(args.base)),
                "work": ab_kernels.build("dss_abs_work", (REPO / ab_kernels.SOURCE).read_text(), Path(tmp))}

        def variant(mod):
            def put():
                before = (_ext.load_cpu, _ext.loaded_cpu)
                _ext.load_cpu = _ext.loaded_cpu = lambda: mod

                def undo():
                    _ext.load_cpu, _ext.loaded_cpu = before
                return undo
            return put

        out = {}
        for kind in args.kinds:
            med = alternate_steps(kind, {name: variant(m) for name, m in mods.items()}, args.steps, args.points,
                                  args.views, args.image_size, warmup=args.warmup)
            out[kind] = {**med, "speedup": med["base"]["step_ms"] / med["work"]["step_ms"]}
    return out


def _run_child(repo: Path, ext_dir: Path, args, kind: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(repo), TORCH_EXTENSIONS_DIR=str(ext_dir),
               OMP_NUM_THREADS=str(args.threads))
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--kinds", kind, "--points", str(args.points),
           "--views", str(args.views), "--image-size", str(args.image_size), "--threads", str(args.threads),
           "--warmup", str(args.warmup), "--steps", str(args.steps)]
    out = subprocess.run(cmd, cwd=repo, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"child for {repo} ({kind}) failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def run(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", help="git revision to compare the working tree with")
    ap.add_argument("--kinds", nargs="+", choices=("position", "normal"), default=["normal", "position"])
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--image-size", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--steps", type=int, default=9)
    ap.add_argument("--in-process", action="store_true",
                    help="alternate the two builds of the C++ kernel step by step in this process (the base may "
                         "differ from the working tree only in dss/csrc); --steps steps per build after --warmup "
                         "rounds")
    ap.add_argument("--out", default=None, help="JSON file for the result")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        res = child(args.kinds[0], args.points, args.views, args.image_size, args.threads, args.warmup, args.steps)
        print(json.dumps(res))
        return res
    if not args.base:
        ap.error("--base is required")
    if args.rounds < 1 or args.steps < 1:
        ap.error("--rounds and --steps must be at least 1")
    base_commit = git_short(args.base)
    if args.in_process:
        summary = in_process(args)
        for kind, r in summary.items():
            print(f"{kind} step, {args.points} points, {args.threads} thread(s), in process: base {args.base} "
                  f"{r['base']['forward_ms']:.1f} + {r['base']['backward_ms']:.1f} = {r['base']['step_ms']:.1f} ms, "
                  f"working tree {r['work']['forward_ms']:.1f} + {r['work']['backward_ms']:.1f} = "
                  f"{r['work']['step_ms']:.1f} ms, speed-up {r['speedup']:.2f}x")
        result = {"base": args.base, "base_commit": base_commit, "mode": "in-process", "points": args.points,
                  "views": args.views, "image_size": args.image_size, "threads": args.threads,
                  "warmup": args.warmup, "steps": args.steps, "summary": summary,
                  "command": command_line("python -m experiments.ab_steps", argv)}
        return write_result(result, args.out)
    with base_worktree(args.base, "dss_ab_steps_") as versions:
        rounds: dict = {k: {v: [] for v in versions} for k in args.kinds}
        for r in range(args.rounds):
            for kind in args.kinds:
                for name, (repo, ext) in versions.items():
                    rounds[kind][name].append(_run_child(repo, ext, args, kind))
                b, w = rounds[kind]["base"][-1]["step_ms"], rounds[kind]["work"][-1]["step_ms"]
                print(f"round {r + 1}/{args.rounds} {kind}: base {b:.1f} ms, working tree {w:.1f} ms", flush=True)
    summary = {}
    for kind, per in rounds.items():
        med = {name: {key: statistics.median(c[key] for c in per[name]) for key in ("forward_ms", "backward_ms", "step_ms")}
               for name in per}
        summary[kind] = {**med, "speedup": med["base"]["step_ms"] / med["work"]["step_ms"]}
        print(f"{kind} step, {args.points} points, {args.threads} thread(s): base {args.base} "
              f"{med['base']['forward_ms']:.1f} + {med['base']['backward_ms']:.1f} = {med['base']['step_ms']:.1f} ms, "
              f"working tree {med['work']['forward_ms']:.1f} + {med['work']['backward_ms']:.1f} = "
              f"{med['work']['step_ms']:.1f} ms, speed-up {summary[kind]['speedup']:.2f}x")
    result = {"base": args.base, "base_commit": base_commit, "points": args.points, "views": args.views,
              "image_size": args.image_size, "threads": args.threads, "rounds": args.rounds, "warmup": args.warmup,
              "steps": args.steps, "summary": summary, "children": rounds,
              "command": command_line("python -m experiments.ab_steps", argv)}
    return write_result(result, args.out)


main = main_for(run)


if __name__ == "__main__":
    sys.exit(main())
