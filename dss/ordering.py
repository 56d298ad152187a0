"""Spatial (Morton / Z-order) ordering of points, for memory locality in the kernels.

The CPU kernels walk points in index order and touch, for each point, the pixels around its
splat in every view. When consecutive points are neighbours in space, they are neighbours on
screen in every view, and those pixels stay in cache. Point clouds from files or samplers come in
arbitrary order; :func:`dss.render.render` therefore renders a Morton-sorted copy and returns
everything in the caller's order (bit-identical results up to the order of exact depth ties).
The gain is measured by ``dss-bench --order`` (file order against sorted, interleaved runs;
numbers in ``results/bench/render_bench.md`` and README "Renderer speed").
"""

from __future__ import annotations

import torch

from . import reference
from .reference.ordering import morton_codes

__all__ = ["morton_codes", "spatial_order", "SORT_MIN_POINTS"]

#: (a copy of CPU points sorted lately, their order), most recent first: see :func:`spatial_order`
_recent: list[tuple[torch.Tensor, torch.Tensor]] = []
#: how many clouds' orders are kept (an optimisation step renders its cloud and, in the runtime
#: table's protocol, a moved target cloud: two at a time)
RECENT_ORDERS = 4
#: clouds above this many points are not kept (4 copies of 1M points and orders: 80 MB)
RECENT_MAX_POINTS = 1_000_000

#: below this many points the sort costs more than it saves (everything fits in cache)
SORT_MIN_POINTS = 2048


def spatial_order(points: torch.Tensor) -> torch.Tensor:
    """(N,) int64 permutation that sorts ``points`` along the Z-order curve (stable).

    CPU float32 points go through the C++ twin (``morton_order`` in dss/csrc/ordering_cpu.cpp: the same codes,
    a radix sort; ~0.5 against ~2.3 ms per 20K-point render) when the module is already loaded;
    :func:`dss.reference.morton_order` (:func:`morton_codes` + ``torch.argsort``) is its twin.

    On the CPU the orders of the last :data:`RECENT_ORDERS` clouds (of at most
    :data:`RECENT_MAX_POINTS` points) are kept with a copy of their points, and one is returned
    again (as a copy) for points equal to its copy, bit for bit (the order is a function of their
    values): steps that do not move the points (normal, colour or sigma steps) compare 20K points
    in ~0.03 ms instead of sorting them in ~0.3 ms."""
    global _recent
    from . import _ext

    p = points.detach()
    keep = p.device.type == "cpu" and p.shape[0] <= RECENT_MAX_POINTS
    if keep:
        recent = _recent
        for i, (pts, order) in enumerate(recent):
            if pts.dtype == p.dtype and pts.shape == p.shape and torch.equal(pts, p):
                _recent = [recent[i], *recent[:i], *recent[i + 1:]]
                return order.clone()  # (the caller may edit its copy)
    mod = _ext.loaded_cpu()
    if mod is not None and p.device.type == "cpu" and p.dtype == torch.float32:
        order = mod.morton_order(p)
    else:
        order = reference.morton_order(p)
    if keep:
        _recent = [(p.clone(), order.clone()), *_recent[: RECENT_ORDERS - 1]]
    return order
