"""Normal orientation from the views that see each point (an addition to the paper).

An outward normal of a closed surface faces every exterior camera that sees its point: a point
visible from camera c has ``n . (c - p) > 0``. An unoriented normal (a PCA fit) can therefore be
signed by the views that see its point, without any reference to the normal it replaces. Which
views see a point is read off a render *without* back-face culling (a flipped splat is culled
exactly where it should be seen): the point is seen in view v when it is among the visible
entries (within the merge threshold of the front) of at least one pixel.

Why: :class:`dss.optimize.MultiViewOptimizer` re-fits the normals by PCA at every cycle start.
Signing the fit "to agree with the current normal" keeps a normal's sign only while the surface
under the point turns by less than 90 degrees between fits. In a large deformation (a cube's
face folding into a limb) it turns by about 90 degrees, the sign becomes a coin flip, and the
flipped normals are culled (holes and specks in every render) and receive no image gradient that
could turn them back (measured on cube -> yoga, 256 px: the flipped fraction grows at every
re-fit, from 13% after two cycles to 27% at the end; docs/deformation.md).
"""

from __future__ import annotations

from dataclasses import replace

import torch

from .cameras import Cameras
from .render import RenderSettings, render

__all__ = ["views_seeing", "view_orientation_vote", "orient_to_views"]


def views_seeing(points: torch.Tensor, normals: torch.Tensor, cameras: Cameras, settings: RenderSettings,
                 backend: str = "auto", sigma: torch.Tensor | float | None = None) -> torch.Tensor:
    """(V, N) bool: point k is visible at one pixel or more of view v, back-face culling off."""
    s = replace(settings, backface_culling=False, gradient="none")
    with torch.no_grad():
        out = render(points.detach(), normals.detach(), cameras, s, shading="mask", backend=backend, sigma=sigma)
    return out.seen()


def view_orientation_vote(points: torch.Tensor, normals: torch.Tensor, cameras: Cameras,
                          seen: torch.Tensor) -> torch.Tensor:
    """(N,) sum over the views that see each point of cos(normal, direction to the camera).

    Positive: the normal faces the views that see its point; negative: it faces away (flip it);
    zero: no view sees the point. Grazing views, whose sign is the least certain, weigh least."""
    to_cam = torch.nn.functional.normalize(cameras.centers[:, None, :].to(points.dtype) - points[None], dim=-1)
    cos = (to_cam * normals[None]).sum(-1)  # (V, N)
    return (cos * seen.to(cos.dtype)).sum(0)


def orient_to_views(points: torch.Tensor, normals: torch.Tensor, cameras: Cameras, settings: RenderSettings,
                    fallback: torch.Tensor | None = None, backend: str = "auto",
                    sigma: torch.Tensor | float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``normals`` signed to face the views that see their points.

    Args:
        points, normals: (N, 3); the normals' sign is free (a PCA fit).
        cameras: the views to vote with; settings / backend / sigma: the renderer's.
        fallback: (N, 3) normals whose sign a point no view sees keeps (default: ``normals``'s).
    Returns:
        the signed normals (N, 3) and the (N,) bool mask of the points no view sees.
    """
    p, n = points.detach(), normals.detach()
    seen = views_seeing(p, n, cameras, settings, backend, sigma)
    vote = view_orientation_vote(p, n, cameras, seen)
    unseen = ~seen.any(0)
    if fallback is not None:
        keep = (n * fallback.detach()).sum(1) >= 0
        vote = torch.where(unseen, torch.where(keep, 1.0, -1.0).to(vote.dtype), vote)
    sign = torch.where(vote < 0, -1.0, 1.0).to(n.dtype)[:, None]
    return n * sign, unseen
