"""Stage 2 of rendering: per pixel, the K front-most splats (the top-K cache of the paper).

Two backends with one contract: :mod:`.reference` (readable pure torch, the test oracle) and
:mod:`.cpp` (C++/OpenMP kernel built on first use). Both consume the packed splats of
:func:`dss.splats.project_splats` and return a :class:`Fragments` cache.
"""

from .fragments import Fragments

__all__ = ["Fragments"]
