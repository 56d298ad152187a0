"""What the benchmark commands share (``ab_steps``, ``ab_kernels``, ``ab_denoise``,
``bench_regularizers``): a base revision checked out beside the working tree, the JSON result
written where ``--out`` says, and their ``main``."""

from __future__ import annotations

import contextlib
import os
import subprocess
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


@contextlib.contextmanager
def base_worktree(base: str, prefix: str):
    """Check ``base`` out into a temporary git worktree (``../shared`` linked beside it, so both
    versions see the same data); yields ``{"base": (repo, kernel cache dir), "work": (...)}``,
    the working tree second, each with its own ``TORCH_EXTENSIONS_DIR``."""
    with tempfile.TemporaryDirectory(prefix=prefix) as tmp:
        tmp = Path(tmp)
        base_repo = tmp / "repo"
        subprocess.run(["git", "worktree", "add", "--detach", "-q", str(base_repo), base], cwd=REPO, check=True)
        shared = REPO.parent / "shared"
        if shared.exists():
            (tmp / "shared").symlink_to(shared)  # the kangaroo beside the worktree too, not a torus
        try:
            yield {"base": (base_repo, tmp / "ext_base"), "work": (REPO, tmp / "ext_work")}
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base_repo)], cwd=REPO)


def run_cpp_program(source: str, args: list[str], what: str) -> str:
    """Compile a one-file C++ program with ``$CXX`` (default ``g++``) at ``-O2`` in a temporary
    folder, run it with ``args`` (``{dir}`` in one is that folder) and return its standard output;
    exits naming ``what`` when it does not compile."""
    cxx = os.environ.get("CXX", "g++")
    with tempfile.TemporaryDirectory(prefix="dss_cpp_") as tmp:
        src, exe = Path(tmp) / "prog.cpp", Path(tmp) / "prog"
        src.write_text(source)
        build = subprocess.run([cxx, "-O2", "-o", str(exe), str(src)], capture_output=True, text=True)
        if build.returncode != 0:
            raise SystemExit(f"{cxx} could not compile {what}:\n{build.stderr[-2000:]}")
        return subprocess.run([str(exe), *(a.replace("{dir}", tmp) for a in args)], capture_output=True, text=True,
                              check=True).stdout


def git_short(rev: str) -> str:
    """The abbreviated commit of ``rev`` (exits with git's message when it does not resolve)."""
    out = subprocess.run(["git", "rev-parse", "--short", rev], cwd=REPO, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"git rev-parse {rev} failed: {out.stderr.strip()}")
    return out.stdout.strip()


def write_result(result: dict, out) -> dict:
    """Write ``result`` atomically as JSON to ``out`` (nothing when ``out`` is None); returns it."""
    if out:
        from dss.io_utils import atomic_write_json

        atomic_write_json(out, result)
    return result


def main_for(run):
    """The ``main(argv=None) -> 0`` of a command whose ``run(argv)`` prints and writes its result."""

    def main(argv=None) -> int:
        run(argv)
        return 0

    return main
