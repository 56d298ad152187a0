"""Build-on-first-use loader for the C++ (and, later, CUDA) kernels.

The extension is compiled once with ``torch.utils.cpp_extension.load`` (ninja) and cached in
``$TORCH_EXTENSIONS_DIR`` (default ``~/.cache/torch_extensions``), keyed by the source hash, so
a changed kernel rebuilds and an unchanged one loads in milliseconds. A failed build (no
compiler, no ninja) warns once; callers then fall back to the pure-torch reference.
"""

from __future__ import annotations

import logging
import os
import threading
import warnings
from pathlib import Path

log = logging.getLogger(__name__)

_CSRC = Path(__file__).parent / "csrc"
_lock = threading.Lock()
_cache: dict[str, object] = {}
_failed: dict[str, str] = {}

__all__ = ["load_cpu", "cpu_available", "build_error"]


def _build(name: str, sources: list[Path], **kw):
    from torch.utils.cpp_extension import load

    return load(
        name=name,
        sources=[str(s) for s in sources],
        extra_cflags=["-O3", "-ffp-contract=off", "-std=c++17"],
        verbose=bool(os.environ.get("DSS_VERBOSE_BUILD")),
        **kw,
    )


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
            mod = _build(name, [_CSRC / "dss_cpu.cpp"])
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


def cpu_available() -> bool:
    return load_cpu() is not None


def build_error(name: str = "dss_cpu") -> str | None:
    return _failed.get(name)
