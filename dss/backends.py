"""Which implementation of the renderer runs: the backends, their choice, their compiled module.

``cpp``: the C++/OpenMP kernels (dss/csrc/*_cpu.cpp, :mod:`dss._ext`), CPU tensors; ``cuda``: the
CUDA kernels (dss/csrc/*_cuda.cu, :mod:`dss._ext_cuda`), CUDA tensors; ``reference``: the torch
twins of the kernels (:mod:`dss.reference`), any device; ``auto``: the fastest available.
"""

from __future__ import annotations

import torch

from . import _ext, _ext_cuda

__all__ = ["BACKENDS", "resolve_backend", "kernels"]

BACKENDS = ("auto", "cpp", "cuda", "reference")


def resolve_backend(backend: str, device: torch.device | None = None) -> str:
    """Pick a concrete backend: "auto" -> the fastest available for ``device``."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")
    if device is not None and device.type == "cuda":
        if backend == "cpp":
            raise ValueError("backend 'cpp' runs on CPU tensors only")
        if backend == "auto":
            return "cuda" if _ext_cuda.cuda_available() else "reference"
        if backend == "cuda" and not _ext_cuda.cuda_available():
            raise RuntimeError(f"the CUDA backend is not available: {_ext_cuda.build_error()}")
        return backend
    if backend == "cuda":
        raise ValueError("backend 'cuda' needs CUDA tensors (move points, normals and cameras to the GPU)")
    if device is not None and device.type != "cpu":
        if backend == "cpp":
            raise ValueError("backend 'cpp' runs on CPU tensors only")
        return "reference"
    if backend == "auto":
        return "cpp" if _ext.cpu_available() else "reference"
    if backend == "cpp" and not _ext.cpu_available():
        raise RuntimeError(f"the C++ backend is not available: {_ext.build_error()}")
    return backend


def kernels(backend: str):
    """The compiled module of a kernel backend ("cpp" or "cuda"); both have the same op names."""
    return _ext.load_cpu() if backend == "cpp" else _ext_cuda.load_cuda()
