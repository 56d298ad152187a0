"""Interleaved A/B timing of the C++ kernels of two source revisions on the same inputs.

    python -m experiments.ab_kernels --kernel visibility_backward --base 6647acd [--threads 1]

Times between sessions (or even between two runs minutes apart) differ by more than most kernel
changes gain, so kernel changes are judged here: the inputs of one real optimisation step (the
20K-point kangaroo cloud, 12 views at 256x256, visibility window 4, as ``dss-runtime-table``) are
captured once from the working tree's ``render()``, then the ``base`` revision's
``dss/csrc/dss_cpu.cpp`` (read with ``git show``) and the working tree's are both built in this
process and called in turn, ``--reps`` times each; the medians (after ``--skip`` warm-up calls)
and their ratio are printed and written to ``--out`` (JSON). Before each call a 64 MB buffer is
written (``--evict-mb``), so that each call starts with cold caches as in a step: back-to-back
calls measured a rasteriser variant (a task per view) 1.22x faster that gained 1.02x with the
eviction and nothing in whole steps (session 33). The kernel must have the same signature in
both revisions (``rasterize_forward``, ``visibility_backward`` and ``blend_backward`` have since
session 19, ``project_splats_forward`` and ``project_splats_backward`` since 0f36c07, the sun
shader's two since session 25; a trailing parameter that the base lacks is left out of its
calls, see :func:`accepted_args`). The numbers in docs/performance.md's sections per session
come from this comparison.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import torch

from experiments.bench_common import REPO, git_short, main_for, write_result
from experiments.figures import command_line

SOURCE = "dss/csrc/dss_cpu.cpp"
KERNELS = ("rasterize_forward", "visibility_backward", "blend_backward", "project_splats_forward",
           "project_splats_backward", "sun_shade_forward", "sun_shade_backward")
VIS_WINDOW_ARG = 12  # position of the window half size in visibility_backward's arguments


def capture_inputs(kind: str, n_points: int, views: int, size: int) -> dict:
    """The arguments of every C++ kernel call of one optimisation step (the last call of each)."""
    from dss import _ext
    from dss.losses import smape_loss
    from dss.render import render
    from experiments.bench_render import benchmark_cloud
    from experiments.runtime_table import step_scene

    mod = _ext.load_cpu()
    if mod is None:
        raise SystemExit(f"the C++ kernel did not build: {_ext.build_error()}")
    captured: dict = {}

    class Recorder:
        def __getattr__(self, name):
            fn = getattr(mod, name)

            def call(*args):
                captured[name] = args
                return fn(*args)

            return call

    pts, nrm, _ = benchmark_cloud(n_points)
    sc = step_scene(pts, views, size)
    settings, cams, sigma, target_pts = sc.settings, sc.sampler.sample(), sc.sigma, sc.target_points
    original = _ext.load_cpu
    _ext.load_cpu = lambda: Recorder()
    try:
        with torch.no_grad():
            target = render(target_pts, nrm, cams, settings, sigma=sigma, backend="cpp").images
        p = pts.clone().requires_grad_(kind == "position")
        n = nrm.clone().requires_grad_(kind == "normal")
        smape_loss(render(p, n, cams, settings, sigma=sigma, backend="cpp").images, target,
                   channel_reduction="mean").backward()
    finally:
        _ext.load_cpu = original
    return captured


def accepted_args(fn, args: list) -> list:
    """``args`` cut to the parameters the compiled ``fn`` declares (from its pybind signature).

    A base revision from before a kernel gained a trailing optional parameter (blend_backward's
    ``mask``, session 34) is called without it, the working tree with it."""
    sig = (fn.__doc__ or "").splitlines()[0] if fn.__doc__ else ""
    inner = sig[sig.find("(") + 1: sig.rfind(") ->")] if "(" in sig and ") ->" in sig else ""
    if not inner:
        return args
    depth, n = 0, 1
    for ch in inner:  # top-level commas (types such as Optional[...] hold none, but be safe)
        depth += ch in "[("
        depth -= ch in "])"
        n += ch == "," and depth == 0
    return args[:n]


def build(name: str, source_text: str, workdir: Path, headers: dict[str, str] | None = None):
    """Build one revision's kernel source as module ``name`` with the package's flags.

    ``headers`` (file name -> text): that revision's ``dss/csrc/*.h``, written beside the source
    so that its ``#include "..."`` finds them (default: the working tree's)."""
    from torch.utils.cpp_extension import load

    from dss._ext import _BASE_CFLAGS, _CSRC, _OPENMP_FLAGS, CPU_SOURCES

    src_dir = workdir / f"src_{name}"
    src_dir.mkdir(exist_ok=True)
    if headers is None:
        headers = {h.name: h.read_text() for h in _CSRC.glob("*.h")}
    for fname, text in headers.items():
        (src_dir / fname).write_text(text)
    src = src_dir / f"{name}.cpp"
    src.write_text(source_text)
    build_dir = workdir / f"build_{name}"
    build_dir.mkdir(exist_ok=True)
    # the working tree's other kernel sources, which dss_cpu.cpp's module table names (a base
    # revision from before they existed simply does not use them)
    extra = [str(_CSRC / f) for f in CPU_SOURCES if f != Path(SOURCE).name]
    return load(name=name, sources=[str(src), *extra], extra_cflags=_BASE_CFLAGS + _OPENMP_FLAGS,
                extra_ldflags=_OPENMP_FLAGS, build_directory=str(build_dir), verbose=False)


def add_step_args(ap: argparse.ArgumentParser, threads: int, reps: int) -> None:
    """The captured step's options (kind, points, views, image size) and the timing's (threads,
    reps, skip), shared by the commands that time kernel builds on it."""
    ap.add_argument("--kind", choices=("position", "normal"), default="position")
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--image-size", type=int, default=256)
    ap.add_argument("--threads", type=int, default=threads)
    ap.add_argument("--reps", type=int, default=reps)
    ap.add_argument("--skip", type=int, default=2, help="warm-up calls of each build left out of the medians")


def time_interleaved(fns: dict, fn_args: dict, reps: int, evict_mb: int) -> dict[str, list[float]]:
    """Call every ``fns[k](*fn_args[k])`` in turn, ``reps`` rounds; the wall time of each call (ms).

    Before each call ``evict_mb`` MB are written, so that the call finds its data out of the
    caches, as in a step where other kernels run between two calls of one."""
    junk = torch.zeros(max(evict_mb, 0) << 18)  # float32: 2^18 per MB
    times: dict = {k: [] for k in fns}
    for _ in range(reps):
        for k, fn in fns.items():
            junk.add_(1.0)
            t0 = time.perf_counter()
            out = fn(*fn_args[k])
            times[k].append(1e3 * (time.perf_counter() - t0))
            del out
    return times


def git_headers(rev: str) -> dict[str, str]:
    """The revision's ``dss/csrc/*.h`` (file name -> text)."""
    folder = str(Path(SOURCE).parent)
    names = subprocess.run(["git", "ls-tree", "--name-only", f"{rev}:{folder}"], cwd=REPO, check=True,
                           capture_output=True, text=True).stdout.split()
    return {n: subprocess.run(["git", "show", f"{rev}:{folder}/{n}"], cwd=REPO, check=True, capture_output=True,
                              text=True).stdout for n in names if n.endswith(".h")}


def git_source(rev: str) -> str:
    try:
        return subprocess.run(["git", "show", f"{rev}:{SOURCE}"], cwd=REPO, check=True, capture_output=True,
                              text=True).stdout
    except subprocess.CalledProcessError as e:
        raise SystemExit(f"git show {rev}:{SOURCE} failed: {e.stderr.strip()}") from e


def run(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kernel", choices=KERNELS, default="visibility_backward")
    ap.add_argument("--base", required=True,
                    help="git revision whose dss_cpu.cpp is the baseline, or 'scalar' / 'avx2': the working "
                         "tree's own kernel with its vector paths off (set_vector_level(0)) / with the AVX2 "
                         "paths only (set_vector_level(1), no AVX-512)")
    ap.add_argument("--level", type=int, choices=(0, 1, 2), default=None,
                    help="with a git revision as --base: run both builds at this vector level "
                         "(set_vector_level; 1: the AVX2 paths, as on a CPU without AVX-512)")
    add_step_args(ap, threads=1, reps=12)
    ap.add_argument("--window", type=int, default=None,
                    help="visibility_backward only: call it with this window half size (px) instead of the "
                         "captured step's")
    ap.add_argument("--evict-mb", type=int, default=64,
                    help="before every call, write a buffer of this many MB so that the call finds its data "
                         "out of the caches, as in a step, where other kernels run between two calls of one "
                         "(0: back-to-back calls, which can favour a build whose scratch stays cached)")
    ap.add_argument("--out", default=None, help="JSON file for the result")
    args = ap.parse_args(argv)
    if args.reps <= args.skip:
        raise SystemExit("--reps must exceed --skip")
    torch.set_num_threads(args.threads)
    inputs = capture_inputs(args.kind, args.points, args.views, args.image_size)
    if args.kernel not in inputs:
        raise SystemExit(f"a {args.kind} step does not call {args.kernel}")
    call_args = list(inputs[args.kernel])
    if args.window is not None:
        if args.kernel != "visibility_backward" or args.window < 0:
            raise SystemExit("--window needs --kernel visibility_backward and a window >= 0")
        call_args[VIS_WINDOW_ARG] = args.window
    work_text = (REPO / SOURCE).read_text()
    own = {"scalar": 0, "avx2": 1}.get(args.base)  # the working tree at a lower vector level
    sources = {"base": work_text if own is not None else git_source(args.base), "work": work_text}
    with tempfile.TemporaryDirectory() as tmp:
        headers = {"base": None if own is not None else git_headers(args.base), "work": None}
        mods = {k: build(f"dss_ab_{k}", text, Path(tmp), headers[k]) for k, text in sources.items()}
        if own is not None:
            mods["base"].set_vector_level(own)
        elif args.level is not None:
            for mod in mods.values():
                if not hasattr(mod, "set_vector_level"):
                    raise SystemExit(f"--level: the build of {args.base} has no set_vector_level")
                mod.set_vector_level(args.level)
        fns = {k: getattr(mod, args.kernel) for k, mod in mods.items()}
        mod_args = {k: accepted_args(fn, call_args) for k, fn in fns.items()}
        times = time_interleaved(fns, mod_args, args.reps, args.evict_mb)
    med = {k: statistics.median(v[args.skip:]) for k, v in times.items()}
    result = {"kernel": args.kernel, "base": args.base,
              "base_commit": None if own is not None else git_short(args.base),  # "HEAD" resolved
              "kind": args.kind, "points": args.points,
              "window": call_args[VIS_WINDOW_ARG] if args.kernel == "visibility_backward" else None,
              "views": args.views, "image_size": args.image_size, "threads": args.threads,
              "evict_mb": args.evict_mb, "vector_level": {k: int(m.vector_level()) for k, m in mods.items()}
              if all(hasattr(m, "vector_level") for m in mods.values()) else None,
              "median_ms": med, "speedup": med["base"] / med["work"], "runs_ms": times,
              "command": command_line("python -m experiments.ab_kernels", argv)}
    print(f"{args.kernel}, {args.points} points, {args.threads} thread(s): base {args.base} {med['base']:.2f} ms, "
          f"working tree {med['work']:.2f} ms, speed-up {result['speedup']:.2f}x")
    return write_result(result, args.out)


main = main_for(run)


if __name__ == "__main__":
    raise SystemExit(main())
