"""Wall and CPU time per named stage: where a job's seconds go (``metrics.json``'s ``profile_s``
and ``profile_cpu_s``)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from . import _ext

__all__ = ["StageClock", "KERNEL_BUILD"]

#: the stage a first-use kernel compile is counted under, whichever stage started it
KERNEL_BUILD = "kernel_build"


class StageClock:
    """Accumulates wall seconds (``seconds``) and process CPU seconds (``cpu_seconds``, every
    thread of the process) per stage name: ``with clock("render"): ...``. On a shared machine the
    CPU seconds of a one-thread run are what its wall time would be on an idle one. A first-use
    kernel compile inside a stage (:func:`dss._ext.build_seconds`; e.g. reading a cloud whose
    normals need the kNN kernel) is counted under :data:`KERNEL_BUILD`, not that stage.

    Args:
        sync: called before and after each stage (``torch.cuda.synchronize`` times GPU work at
            the cost of a sync per stage); None: host-side wall time (on a GPU, a stage then
            counts its launches, and the work lands in whichever later stage waits for it).
    """

    def __init__(self, sync: Callable[[], None] | None = None):
        self.seconds: dict[str, float] = {}
        self.cpu_seconds: dict[str, float] = {}
        self._sync = sync

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        if self._sync is not None:
            self._sync()
        t0, c0, b0 = time.perf_counter(), time.process_time(), _ext.build_seconds()
        try:
            yield
        finally:
            if self._sync is not None:
                self._sync()
            built = _ext.build_seconds() - b0
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0 - built
            self.cpu_seconds[name] = self.cpu_seconds.get(name, 0.0) + time.process_time() - c0
            if built > 0:  # the compiler's processes: their CPU time is not this process's
                self.seconds[KERNEL_BUILD] = self.seconds.get(KERNEL_BUILD, 0.0) + built

    def add(self, name: str, seconds: float, cpu_seconds: float | None = None) -> None:
        """Count ``seconds`` (and ``cpu_seconds``) measured elsewhere under ``name``."""
        self.seconds[name] = self.seconds.get(name, 0.0) + float(seconds)
        if cpu_seconds is not None:
            self.cpu_seconds[name] = self.cpu_seconds.get(name, 0.0) + float(cpu_seconds)

    def summary(self, total: float | None = None) -> str:
        """``"load 0.4 s, render 12.1 s, ..."`` in insertion order, and the rest of ``total`` (the
        job's seconds without a kernel build, as the apps' ``time_s.total``) as ``other``."""
        parts = [f"{k} {v:.2f} s" for k, v in self.seconds.items()]
        if total is not None:
            counted = sum(v for k, v in self.seconds.items() if k != KERNEL_BUILD)
            parts.append(f"other {max(0.0, total - counted):.2f} s")
        return ", ".join(parts)
