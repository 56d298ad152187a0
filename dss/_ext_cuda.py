"""Build-on-first-use loader for the CUDA kernels (``dss/csrc/dss_cuda.cu`` + ``dss_cuda_bind.cpp``).

Like :mod:`dss._ext`: compiled once with ``torch.utils.cpp_extension.load`` and cached in
``$TORCH_EXTENSIONS_DIR`` (default ``~/.cache/torch_extensions``) under a name that carries the
sources' hash (:func:`dss._ext.load_hashed`), so installs with different kernels do not rebuild
each other's.
The kernels are compiled with ``--fmad=false`` so that no fused multiply-add changes a rounding:
the per-pixel tests then round exactly like the CPU kernel's, and the two backends return the same
top-K cache. When there is no GPU, a CPU-only torch build, or the build fails, :func:`load_cuda`
warns once and returns None.

The module has the CPU module's functions, taking CUDA tensors::

    rasterize_forward(packed, attrs, H, W, K, cutoff, merge, background)
        -> [idx, depth, rho, images, mask]
    visibility_backward(packed, attrs, idx, depth, rho, images, grad, R, focal, principal,
                        background, planes, window, stride, cutoff, merge, eps, mode) -> (N, 3)
"""

from __future__ import annotations

import logging
import os
import threading
import warnings
from pathlib import Path

log = logging.getLogger(__name__)

_CSRC = Path(__file__).parent / "csrc"
SOURCES = (_CSRC / "dss_cuda.cu", _CSRC / "dss_cuda_bind.cpp")
# Flags every nvcc build of dss_cuda.cu must use (the compile test uses them too).
NVCC_FLAGS = ("-O3", "--fmad=false")

_NAME = "dss_cuda"
_lock = threading.Lock()
_cache: dict[str, object] = {}
_failed: dict[str, str] = {}

__all__ = ["load_cuda", "cuda_available", "build_error", "SOURCES", "NVCC_FLAGS"]


def _why_not() -> str | None:
    """Reason the CUDA module cannot be built here, or None."""
    if os.environ.get("DSS_DISABLE_CUDA"):
        return "disabled by DSS_DISABLE_CUDA"
    import torch

    if torch.version.cuda is None:
        return f"torch {torch.__version__} is a CPU-only build"
    if not torch.cuda.is_available():
        return "no CUDA device is available"
    return None


def _build():
    from ._ext import load_hashed

    return load_hashed(_NAME, list(SOURCES), sorted(_CSRC.glob("*.h")), extra_cflags=["-O3"],
                       extra_cuda_cflags=list(NVCC_FLAGS), what="the CUDA kernels")


def load_cuda():
    """The compiled CUDA module, or None when there is no GPU or it cannot be built (warns once)."""
    with _lock:
        if _NAME in _cache:
            return _cache[_NAME]
        if _NAME in _failed:
            return None
        reason = _why_not()
        if reason is None:
            try:
                mod = _build()
            except Exception as e:  # nvcc missing, ninja missing, build error
                reason = f"the build failed: {type(e).__name__}: {e}"
            else:
                _cache[_NAME] = mod
                return mod
        _failed[_NAME] = reason
        warnings.warn(f"dss: the CUDA kernels are not available ({reason.splitlines()[0]})", RuntimeWarning,
                      stacklevel=3)
        return None


def cuda_available() -> bool:
    """True when the CUDA module is (or can be) built and a GPU is present."""
    return load_cuda() is not None


def build_error() -> str | None:
    """Why :func:`load_cuda` returned None (None when it did not fail)."""
    return _failed.get(_NAME)
