"""Keep long-lived Python objects out of the cyclic garbage collector during optimisation loops.

An optimisation step allocates thousands of short-lived container objects (autograd contexts,
argument tuples, dicts) and some live through several young collections, so CPython (3.11)
starts a full collection every ten or so steps, and a full collection walks every tracked
object, ~200K after ``import torch``. Measured on the 20K-point runtime-table step (2 threads):
a full collection took ~150 ms and came every ~11 steps, ~13 ms per step on average, spent
outside the per-step medians that ``dss-runtime-table`` reports but inside every real run.
``gc.freeze()`` moves the objects alive at the start of the loop to a permanent generation that
collections skip; the step's own garbage is collected as before.
"""

from __future__ import annotations

import contextlib
import gc

__all__ = ["frozen_gc"]


@contextlib.contextmanager
def frozen_gc():
    """Freeze the objects alive now (``gc.freeze``) for the block; unfreeze them at exit.

    Does nothing when objects are frozen already (the caller's own ``gc.freeze`` or an enclosing
    ``frozen_gc``), so it never unfreezes what it did not freeze. Garbage cycles that exist at
    entry are freed at the first full collection after exit instead of during the block.
    """
    if gc.get_freeze_count() > 0:
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()
