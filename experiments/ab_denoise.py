"""Interleaved A/B wall time of whole ``dss-denoise`` jobs: a git revision against the working tree.

    python -m experiments.ab_denoise --base cf05a83 [--rounds 3] [--threads 2]
        [--out results/bench/ab/denoise_quickstart_s26.json] [-- hydra overrides ...]

Each round runs the job once with the base revision (checked out into a temporary git worktree,
see ``experiments.ab_steps.base_worktree``) and once with the working tree, alternating, each
in its own process with its own kernel cache (built before the first round) and
``OMP_NUM_THREADS=--threads``. Without
overrides the job is the Quickstart's (the shipped example); anything after ``--`` is passed to
both versions, e.g. ``-- input=/tmp/noisy_100k.ply mesh=$PWD/experiments/assets/example/mesh.ply
noise=0.01`` (absolute paths: the base version runs in its worktree). The time is the job's own
"wall time" log line (from the start of ``run`` to the written outputs, without Python's start
and imports); the medians over rounds, their ratio and every run's paper-protocol Chamfer line
go to stdout and ``--out`` (JSON).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from experiments.bench_common import base_worktree, git_short, main_for, write_result

WALL = re.compile(r"wall time ([0-9.]+) s")
CHAMFER = re.compile(r"\[(\w+) protocol\] Chamfer x1e4: input ([0-9.]+) -> denoised ([0-9.]+)")


def _env(repo: Path, ext_dir: Path, threads: int) -> dict:
    return dict(os.environ, PYTHONPATH=str(repo), TORCH_EXTENSIONS_DIR=str(ext_dir), OMP_NUM_THREADS=str(threads))


def build_kernel(repo: Path, ext_dir: Path) -> None:
    """Compile ``repo``'s C++ kernel into ``ext_dir`` first, so no timed job includes the build."""
    code = "import dss._ext as e, sys; sys.exit(0 if e.load_cpu() is not None else 1)"
    out = subprocess.run([sys.executable, "-c", code], cwd=repo, env=_env(repo, ext_dir, 1), capture_output=True,
                         text=True)
    if out.returncode != 0:
        raise SystemExit(f"the C++ kernel of {repo} did not build:\n{(out.stdout + out.stderr)[-3000:]}")


def run_job(repo: Path, ext_dir: Path, threads: int, overrides: list[str], out_dir: Path) -> dict:
    """One ``dss-denoise`` run of the code in ``repo``: its wall time (s) and Chamfer lines."""
    env = _env(repo, ext_dir, threads)
    cmd = [sys.executable, "-m", "experiments.denoise", "progress=false", f"hydra.run.dir={out_dir}", *overrides]
    out = subprocess.run(cmd, cwd=repo, env=env, capture_output=True, text=True)
    text = out.stdout + out.stderr
    wall = WALL.findall(text)
    if out.returncode != 0 or not wall:
        raise SystemExit(f"dss-denoise in {repo} failed (exit {out.returncode}):\n{text[-3000:]}")
    chamfer = {p: {"input": float(a), "denoised": float(b)} for p, a, b in CHAMFER.findall(text)}
    return {"wall_s": float(wall[-1]), "chamfer_x1e4": chamfer}


def run(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    overrides = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True, help="git revision to compare the working tree with")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None, help="JSON file for the result")
    args = ap.parse_args(own)
    if args.rounds < 1:
        ap.error("--rounds must be at least 1")
    base_commit = git_short(args.base)
    runs: dict = {"base": [], "work": []}
    with base_worktree(args.base, "dss_ab_denoise_") as versions, tempfile.TemporaryDirectory() as outs:
        for repo, ext in versions.values():
            build_kernel(repo, ext)
        for r in range(args.rounds):
            for name, (repo, ext) in versions.items():
                runs[name].append(run_job(repo, ext, args.threads, overrides, Path(outs) / f"{name}{r}"))
            print(f"round {r + 1}/{args.rounds}: base {runs['base'][-1]['wall_s']:.1f} s, "
                  f"working tree {runs['work'][-1]['wall_s']:.1f} s", flush=True)
    med = {name: statistics.median(x["wall_s"] for x in per) for name, per in runs.items()}
    speedup = med["base"] / med["work"]
    print(f"dss-denoise {' '.join(overrides) or '(the Quickstart job)'}, {args.threads} thread(s): base "
          f"{args.base} {med['base']:.1f} s, working tree {med['work']:.1f} s (medians), speed-up {speedup:.2f}x")
    result = {"base": args.base, "base_commit": base_commit, "threads": args.threads, "rounds": args.rounds,
              "overrides": overrides, "median_wall_s": med, "speedup": speedup, "runs": runs,
              "command": "python -m experiments.ab_denoise " + " ".join(argv)}
    return write_result(result, args.out)


main = main_for(run)


if __name__ == "__main__":
    sys.exit(main())
