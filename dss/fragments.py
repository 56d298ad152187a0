"""The per-pixel top-K cache shared by the forward and backward passes."""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["Fragments", "visible_mask"]


@dataclass
class Fragments:
    """Top-K splats per pixel, sorted front to back (by depth, then point index).

    Attributes:
        idx: (V, H, W, K) int32 point indices, -1 where empty.
        depth: (V, H, W, K) float32 camera depths, +inf where empty.
        rho: (V, H, W, K) float32 filtered Gaussian weights rho_bar (Eq. filter) before the
            visibility test, 0 where empty.
        merge_threshold: T (camera units): entries deeper than the front one by more than T are
            occluded (weight 0 in the image, but kept for the backward pass).
    """

    idx: torch.Tensor
    depth: torch.Tensor
    rho: torch.Tensor
    merge_threshold: float

    @property
    def visible(self) -> torch.Tensor:
        """(V, H, W, K) bool: the entries that contribute to the image (h_x = 1)."""
        return visible_mask(self.idx, self.depth, self.merge_threshold)

    @property
    def K(self) -> int:
        return self.idx.shape[-1]


def visible_mask(idx: torch.Tensor, depth: torch.Tensor, merge_threshold: float) -> torch.Tensor:
    front = depth[..., :1]
    return (idx >= 0) & (depth <= front + merge_threshold)
