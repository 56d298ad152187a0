"""Build-on-first-use loader for the C++ (and, later, CUDA) kernels.

The extension is compiled once with ``torch.utils.cpp_extension.load`` (ninja) and cached in
``$TORCH_EXTENSIONS_DIR`` (default ``~/.cache/torch_extensions``). Its name carries a hash of
the sources, headers, flags, torch and Python (``dss_cpu_<hash>``), and it is built from a copy
of the sources kept beside the build, so two installs on one machine (two clones, a worktree,
a second venv) with the same kernel share one build, and installs with different kernels keep
one build each instead of rebuilding each other's. A first-use compile logs a line when it
starts, one every 15 s with the elapsed time, and one when it ends; its duration is kept
(:func:`build_seconds`) so that the apps can leave it out of their timings.
A failed build (no compiler, no ninja) warns once; callers then fall back to the pure-torch
reference.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import sys
import threading
import time
import warnings
from pathlib import Path

log = logging.getLogger(__name__)

_CSRC = Path(__file__).parent / "csrc"
# The CPU module's sources, one per stage (dss/csrc/dss_cpu.h lists what each holds): the bindings,
# the shared run-time state, the renderer's stages, the regularisers' weighted PCA and the kNN.
CPU_SOURCES = ("dss_cpu_bind.cpp", "cpu_runtime.cpp", "projection_cpu.cpp", "rasterize_cpu.cpp",
               "blend_backward_cpu.cpp", "visibility_backward_cpu.cpp", "shading_cpu.cpp", "loss_cpu.cpp",
               "ordering_cpu.cpp", "frames_cpu.cpp", "knn_cpu.cpp")
_lock = threading.Lock()
_cache: dict[str, object] = {}
_failed: dict[str, str] = {}

__all__ = ["load_cpu", "cpu_available", "build_error", "openmp_enabled", "build_seconds", "hashed_name",
           "load_hashed"]
_build_seconds = [0.0]  # compile time spent in this process (s)
#: seconds between two progress lines of a compile
PROGRESS_EVERY_S = 15.0
#: what the first compile of dss_cpu costs (wall time; docs/performance.md "The first build")
BUILD_TIME = "44 s on an idle 2-core machine, about 200 s on a busy one"


# -ffp-contract=off: no fused multiply-adds, so the kernels round as the torch expressions they
# mirror. -fno-math-errno -fno-trapping-math change no result (sqrt need not set errno, and no
# program here traps on floating-point exceptions); they let the compiler vectorise loops with
# square roots and divisions under selects (the projection kernels).
_BASE_CFLAGS = ["-O3", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math", "-std=c++17"]
# at::parallel_for is a header template that expands to `#pragma omp parallel` when torch's
# parallel backend is OpenMP (every Linux wheel): compiled without -fopenmp the pragma is
# ignored and every kernel silently runs on one thread (measured: the 20K-point visibility
# backward took 245 ms with 1 or 2 threads before, 136 ms on 2 threads with -fopenmp). The
# extension then links libgomp.so.1, the soname torch has already loaded, so there is one
# OpenMP runtime in the process.
_OPENMP_FLAGS = ["-fopenmp"]
_openmp: dict[str, bool] = {}


def hashed_name(base: str, sources: list[Path], flags: list[str] = (), headers: list[Path] = ()) -> str:
    """``<base>_<hash>``: the hash covers the sources' and headers' names and bytes, the flags,
    torch's and Python's versions, so equal kernels get equal names wherever they are installed."""
    import torch

    h = hashlib.sha256()
    for f in sorted(set(map(Path, sources)) | set(map(Path, headers)), key=lambda p: p.name):
        h.update(f.name.encode() + b"\0" + f.read_bytes() + b"\0")
    h.update(" ".join([*flags, torch.__version__, sys.version, sys.platform]).encode())
    return f"{base}_{h.hexdigest()[:12]}"


def _build_dir(name: str) -> Path:
    from torch.utils.cpp_extension import _get_build_directory

    return Path(_get_build_directory(name, False))


def _stage(name: str, files: list[Path]) -> Path:
    """Copy ``files`` into ``<build dir>/src`` (once: equal names mean equal bytes), so that the
    build never names an install's own paths and other installs reuse it without a rebuild."""
    src = _build_dir(name) / "src"
    src.mkdir(parents=True, exist_ok=True)
    for f in files:
        dst = src / f.name
        data = f.read_bytes()
        if not dst.exists() or dst.read_bytes() != data:  # untouched otherwise: ninja goes by mtime
            tmp = src / f".{f.name}.{os.getpid()}.tmp"
            tmp.write_bytes(data)
            os.replace(tmp, dst)
    return src


def load_hashed(base: str, sources: list[Path], headers: list[Path] = (), *, extra_cflags: list[str] = (),
                extra_ldflags: list[str] = (), extra_cuda_cflags: list[str] | None = None,
                what: str = "the C++ kernel", expected: str | None = None, **kw):
    """``torch.utils.cpp_extension.load`` under :func:`hashed_name`, from staged sources.

    When the module is not built yet (a first-use compile) logs a line (with ``expected``, what
    such a build takes), then the elapsed time every :data:`PROGRESS_EVERY_S`, and adds the
    build's duration to :func:`build_seconds`.
    """
    from torch.utils.cpp_extension import LIB_EXT, load

    sources, headers = [Path(s) for s in sources], [Path(h) for h in headers]
    flags = [*extra_cflags, "|", *extra_ldflags, "|", *(extra_cuda_cflags or [])]
    name = hashed_name(base, sources, flags, headers)
    src = _stage(name, sources + headers)
    compiling = not (_build_dir(name) / f"{name}{LIB_EXT}").exists()
    if compiling:
        log.warning("compiling %s (%s) once, cached in %s%s", what, name, _build_dir(name),
                    f" ({expected})" if expected else "")
    t0 = time.perf_counter()
    try:
        with _progress(what, t0) if compiling else contextlib.nullcontext():
            return load(name=name, sources=[str(src / s.name) for s in sources], extra_cflags=list(extra_cflags),
                        extra_ldflags=list(extra_ldflags), extra_include_paths=[str(src)],
                        verbose=bool(os.environ.get("DSS_VERBOSE_BUILD")),
                        **({"extra_cuda_cflags": list(extra_cuda_cflags)} if extra_cuda_cflags else {}), **kw)
    finally:
        if compiling:
            _build_seconds[0] += time.perf_counter() - t0
            log.warning("compiling %s: done after %.0f s", what, time.perf_counter() - t0)


@contextlib.contextmanager
def _progress(what: str, t0: float):
    """Log the elapsed time every :data:`PROGRESS_EVERY_S` while the body runs (a compile gives no
    output of its own for a minute or more)."""
    done = threading.Event()

    def tick():
        while not done.wait(PROGRESS_EVERY_S):
            log.warning("compiling %s: %.0f s so far", what, time.perf_counter() - t0)

    ticker = threading.Thread(target=tick, name="dss-build-progress", daemon=True)
    ticker.start()
    try:
        yield
    finally:
        done.set()
        ticker.join()


def build_seconds() -> float:
    """Seconds this process has spent compiling kernels (0 when every one was cached)."""
    return _build_seconds[0]


def _headers() -> list[Path]:
    """The headers the CPU sources include (all but the CUDA launchers' dss_cuda.h)."""
    return sorted(h for h in _CSRC.glob("*.h") if h.name != "dss_cuda.h")


def _build(name: str, sources: list[Path], **kw):
    """Compile with OpenMP when the compiler supports it, else serially (warns: 1 thread)."""

    def _load(mod_name: str, omp: bool):
        return load_hashed(mod_name, sources, _headers(), extra_cflags=_BASE_CFLAGS + (_OPENMP_FLAGS if omp else []),
                           extra_ldflags=_OPENMP_FLAGS if omp else [], expected=BUILD_TIME, **kw)

    if not os.environ.get("DSS_DISABLE_OPENMP"):
        try:
            mod = _load(name, True)
            _openmp[name] = True
            return mod
        except Exception as e:  # e.g. Apple clang without libomp
            log.warning("dss: building %s with OpenMP failed (%s); building it single-threaded", name,
                        str(e).splitlines()[0] if str(e) else type(e).__name__)
    mod = _load(name + "_serial", False)
    _openmp[name] = False
    warnings.warn(f"dss: the C++ kernel {name} was built without OpenMP and runs on one thread", RuntimeWarning,
                  stacklevel=3)
    return mod


def openmp_enabled(name: str = "dss_cpu") -> bool | None:
    """Whether the loaded kernel was built with OpenMP (None before it is loaded)."""
    return _openmp.get(name)


def load_cpu():
    """The compiled CPU module, or None when it cannot be built (warns once)."""
    name = "dss_cpu"
    with _lock:
        if name in _cache:
            return _cache[name]
        if name in _failed:
            return None
        if os.environ.get("DSS_DISABLE_CPP"):
            _failed[name] = "disabled by DSS_DISABLE_CPP"
            return None
        try:
            mod = _build(name, [_CSRC / f for f in CPU_SOURCES])
        except Exception as e:  # compiler missing, ninja missing, build error
            _failed[name] = f"{type(e).__name__}: {e}"
            warnings.warn(
                f"dss: the C++ kernel could not be built ({_failed[name].splitlines()[0]}); "
                "falling back to the (much slower) pure-PyTorch reference backend",
                RuntimeWarning,
                stacklevel=3,
            )
            return None
        _cache[name] = mod
        return mod


def loaded_cpu():
    """The CPU module if it has already been built in this process, else None (never builds:
    for optional fast paths, e.g. the fused SMAPE, that must not start a compile)."""
    return _cache.get("dss_cpu")


def empty_cache() -> int:
    """Free the output blocks the C++ kernels keep parked for reuse (up to 512 MB; see
    ``pooled_empty`` in dss/csrc/cpu_runtime.cpp); returns the bytes released (0 when the module is not loaded)."""
    mod = loaded_cpu()
    return int(mod.empty_cache()) if mod is not None else 0


def cpu_available() -> bool:
    return load_cpu() is not None


def build_error(name: str = "dss_cpu") -> str | None:
    return _failed.get(name)
