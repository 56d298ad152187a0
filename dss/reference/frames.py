"""The regularisers' weighted PCA frames in torch: the twin of the kernels' ``local_frames_forward``
and ``neighbor_diff_forward`` / ``neighbor_diff_backward`` (dss/csrc/frames_cpu.cpp).

The kernel and these ops agree to the points' precision, not bit for bit, and the eigenvectors'
signs may differ (``dss.regularizers.LocalFrames.normal``).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["local_frames", "neighbor_diff"]

# dss.knn and dss.regularizers import this package: their helpers are imported where they are used.


def local_frames(points, normals, occlusion, idx, bandwidth, sharpness_angle, covariance_weight, cutoff,
                 min_neighbors):
    """The regularisers' weighted PCA frames (:func:`dss.regularizers.local_frames` documents the
    arguments) over the neighbour lists ``idx`` (N, K).

    Returns:
        (valid (N, K) bool, diff (N, K, 3) ``(p_i - p_k) * valid``, differentiable in ``points``,
        psi (N, K), w (N, K), centroid (N, 3), eigenvalues (N, 3) ascending, eigenvectors (N, 3, 3)
        in columns, unit normals (N, 3) or None); all but ``diff`` detached.
    """
    from ..knn import gather_neighbors
    from ..regularizers import batched_eigh

    nb = gather_neighbors(points, idx)  # (N, K, 3), differentiable
    diff = points.unsqueeze(1) - nb  # p_i - p_k
    with torch.no_grad():
        dist2 = (diff.detach() ** 2).sum(-1)
        valid = (idx >= 0) & (dist2 <= (cutoff * bandwidth) ** 2)
        if min_neighbors > 0:
            valid[:, :min_neighbors] |= idx[:, :min_neighbors] >= 0
        validf = valid.to(points.dtype)
    # Masked neighbours contribute nothing (and no gradient); outside no_grad to keep the graph.
    diff = diff * validf.unsqueeze(-1)
    with torch.no_grad():
        psi = torch.exp(-dist2 / (bandwidth * bandwidth)) * validf
        w = psi.clone()
        if normals is not None:
            nrm = F.normalize(normals.detach(), dim=-1)
            cos = (gather_neighbors(nrm, idx) * nrm.unsqueeze(1)).sum(-1)
            denom = max(1e-5, 1.0 - math.cos(sharpness_angle))
            w = w * torch.exp(-((1.0 - cos) ** 2) / denom)
        if occlusion is not None:
            occ = occlusion.detach().to(points.dtype)
            w = w * (1.0 / (gather_neighbors(occ.unsqueeze(-1), idx)[..., 0] + 1.0))
        wsum = w.sum(1, keepdim=True)
        # Rows whose weights all vanish (no neighbour, or all masked) keep w = 0.
        w = torch.where(
            wsum > 0, w / wsum.clamp_min(torch.finfo(w.dtype).tiny), torch.zeros_like(w)
        )

        nb_d = nb.detach()
        centroid = (w.unsqueeze(-1) * nb_d).sum(1)
        centred = (nb_d - centroid.unsqueeze(1)) * validf.unsqueeze(-1)
        cw = w * w if covariance_weight == "squared" else w
        cov = torch.einsum("nk,nki,nkj->nij", cw, centred, centred)
        # eigh in float64 (3x3 per point, cheap) for accurate eigenvectors of nearly planar or
        # tiny neighbourhoods; back to the working dtype afterwards.
        evals, evecs = batched_eigh(cov.double())
        evals = evals.to(points.dtype)
        evecs = evecs.to(points.dtype)
    return valid, diff, psi, w, centroid, evals, evecs, nrm if normals is not None else None


def neighbor_diff(points: torch.Tensor, idx: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(N, K, 3) ``(p_i - p_k) * valid`` for neighbour lists ``idx`` (N, K) and their mask
    ``valid`` (N, K) bool; differentiable in ``points`` (N, 3)."""
    from ..knn import gather_neighbors

    return (points.unsqueeze(1) - gather_neighbors(points, idx)) * valid.unsqueeze(-1).to(points.dtype)
