"""Exact k nearest neighbours in torch: the twin of the kernels' ``knn_grid`` (dss/csrc/knn_cpu.cpp).

The kernel scans a uniform grid; this answers the same query by brute force, :func:`torch.cdist`
over chunks of query rows and :func:`torch.topk`, with memory bounded by ``chunk_rows x M``
distances (never the whole N x M matrix). :func:`dss.knn.knn` runs it for GPU tensors and
small CPU inputs.
"""

from __future__ import annotations

import torch

__all__ = ["knn_grid"]

# Memory budget (number of float32 distances) of one brute-force chunk.
_CHUNK_ELEMENTS = 1 << 24


def knn_grid(
    ref: torch.Tensor,
    query: torch.Tensor,
    k: int,
    radius: float | None,
    chunk_rows: int | None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` nearest of ``ref`` (M, D) to each of ``query`` (N, D) within ``radius`` (None:
    any distance): idx (N, k) int64 and dist (N, k), padded with -1 / inf, sorted by distance;
    ``chunk_rows`` query rows per :func:`torch.cdist` (None: about 16M distances per chunk)."""
    ref = ref.detach()
    query = query.detach()
    n, m = query.shape[0], ref.shape[0]
    kk = min(k, m)
    if chunk_rows is None:
        chunk_rows = max(1, _CHUNK_ELEMENTS // max(m, 1))
    idx_out = torch.full((n, k), -1, dtype=torch.int64, device=query.device)
    dist_out = torch.full((n, k), float("inf"), dtype=query.dtype, device=query.device)
    if kk == 0 or n == 0:
        return idx_out, dist_out
    for start in range(0, n, chunk_rows):
        q = query[start : start + chunk_rows]
        # Exact differences (no |a|^2+|b|^2-2ab expansion): near-duplicate points must not get
        # cancellation errors.
        d = torch.cdist(q, ref, compute_mode="donot_use_mm_for_euclid_dist")
        dk, ik = torch.topk(d, kk, dim=1, largest=False, sorted=True)
        dist_out[start : start + q.shape[0], :kk] = dk
        idx_out[start : start + q.shape[0], :kk] = ik
    if radius is not None:
        outside = dist_out > radius
        idx_out[outside] = -1
        dist_out[outside] = float("inf")
    return idx_out, dist_out
