"""Wall time per named stage: where a job's seconds go (``metrics.json``'s ``profile_s``)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = ["StageClock"]


class StageClock:
    """Accumulates wall seconds per stage name: ``with clock("render"): ...``.

    Args:
        sync: called before and after each stage (``torch.cuda.synchronize`` times GPU work at
            the cost of a sync per stage); None: host-side wall time (on a GPU, a stage then
            counts its launches, and the work lands in whichever later stage waits for it).
    """

    def __init__(self, sync: Callable[[], None] | None = None):
        self.seconds: dict[str, float] = {}
        self._sync = sync

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        if self._sync is not None:
            self._sync()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            if self._sync is not None:
                self._sync()
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0

    def add(self, name: str, seconds: float) -> None:
        """Count ``seconds`` measured elsewhere under ``name``."""
        self.seconds[name] = self.seconds.get(name, 0.0) + float(seconds)

    def summary(self, total: float | None = None) -> str:
        """``"load 0.4 s, render 12.1 s, ..."`` in insertion order (and the unaccounted rest)."""
        parts = [f"{k} {v:.2f} s" for k, v in self.seconds.items()]
        if total is not None:
            parts.append(f"other {max(0.0, total - sum(self.seconds.values())):.2f} s")
        return ", ".join(parts)
