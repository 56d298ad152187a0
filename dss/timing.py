"""Wall and CPU time per named stage: where a job's seconds go (``metrics.json``'s ``profile_s``
and ``profile_cpu_s``)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = ["StageClock"]


class StageClock:
    """Accumulates wall seconds (``seconds``) and process CPU seconds (``cpu_seconds``, every
    thread of the process) per stage name: ``with clock("render"): ...``. On a shared machine the
    CPU seconds of a one-thread run are what its wall time would be on an idle one.

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
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            if self._sync is not None:
                self._sync()
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0
            self.cpu_seconds[name] = self.cpu_seconds.get(name, 0.0) + time.process_time() - c0

    def add(self, name: str, seconds: float, cpu_seconds: float | None = None) -> None:
        """Count ``seconds`` (and ``cpu_seconds``) measured elsewhere under ``name``."""
        self.seconds[name] = self.seconds.get(name, 0.0) + float(seconds)
        if cpu_seconds is not None:
            self.cpu_seconds[name] = self.cpu_seconds.get(name, 0.0) + float(cpu_seconds)

    def summary(self, total: float | None = None) -> str:
        """``"load 0.4 s, render 12.1 s, ..."`` in insertion order (and the unaccounted rest)."""
        parts = [f"{k} {v:.2f} s" for k, v in self.seconds.items()]
        if total is not None:
            parts.append(f"other {max(0.0, total - sum(self.seconds.values())):.2f} s")
        return ", ".join(parts)
