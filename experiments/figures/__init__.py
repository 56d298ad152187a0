"""Figures of the paper, each one command writing a PNG and a JSON.

- ``dss-fig-gradient1d`` (:mod:`experiments.figures.gradient_1d`): Fig. 1Dplot, the gradient value
  vs pixel distance and the residual vs optimisation step, DSS vs the RBF-derived gradient.
- ``dss-fig-twopoints`` (:mod:`experiments.figures.two_points`): Fig. twopoints, two points chasing
  two targets with DSS vs RBF.
- ``dss-fig-runtime`` (:mod:`experiments.figures.runtime_chart`): the runtime table (Table
  tab:speed) as a chart, from ``dss-runtime-table``'s JSONs; it uses none of the helpers below
  except ``command_line`` and ``setup_matplotlib``.

The first two use toy scenes in front of one axis-aligned camera (R = I, t = 0, looking down +z), so world
x/y map linearly to pixels: at depth ``Z`` one world unit is ``focal / Z`` pixels.

The helpers below are shared by the figure modules.
"""

from __future__ import annotations

import math
import platform
import sys

import torch

from dss.cameras import Cameras

__all__ = ["axis_camera", "screen_std_px", "cutoff_for_radius", "ellipse_radius_px", "make_optimizer",
           "command_line", "environment", "setup_matplotlib"]


def axis_camera(height: int, width: int, focal: float) -> Cameras:
    """One camera at the origin looking down +z (R = I, t = 0), principal point at the image centre."""
    return Cameras(torch.eye(3)[None], torch.zeros(1, 3), torch.tensor([float(focal)]),
                   torch.tensor([[width / 2.0, height / 2.0]]), (height, width))


def screen_std_px(sigma: float, px_per_unit: float, filter_variance: float = 1.0) -> float:
    """Screen-space std (pixels) of a camera-facing splat: sqrt((sigma f/Z)^2 + filter variance)."""
    return math.sqrt((sigma * px_per_unit) ** 2 + filter_variance)


def cutoff_for_radius(sigma: float, px_per_unit: float, radius_px: float, filter_variance: float = 1.0) -> float:
    """Cutoff C whose ellipse (1/2 d^T Sigma^-1 d <= C) has radius ``radius_px`` for a facing splat.

    The radius is sqrt(2 C) screen stds, so C = radius^2 / (2 std^2). Fixing the radius this way
    keeps the rendered disc (and hence the image and the DSS gradient) the same for every sigma,
    while the Gaussian that the RBF gradient differentiates still has the std set by sigma.
    """
    if radius_px <= 0:
        raise ValueError(f"radius_px must be > 0, got {radius_px}")
    std = screen_std_px(sigma, px_per_unit, filter_variance)
    return radius_px * radius_px / (2.0 * std * std)


def ellipse_radius_px(sigma: float, px_per_unit: float, cutoff: float, filter_variance: float = 1.0) -> float:
    """Radius (pixels) of the cutoff ellipse of a camera-facing splat."""
    return math.sqrt(2.0 * cutoff) * screen_std_px(sigma, px_per_unit, filter_variance)


def make_optimizer(name: str, params, lr: float) -> torch.optim.Optimizer:
    """``adam`` (torch defaults besides lr) or plain ``sgd`` (no momentum)."""
    if name == "adam":
        return torch.optim.Adam(params, lr=lr)
    if name == "sgd":
        return torch.optim.SGD(params, lr=lr)
    raise ValueError(f"unknown optimizer {name!r}; choose 'adam' or 'sgd'")


def command_line(prog: str, argv) -> str:
    """The command that reproduces a run, for the JSON."""
    args = list(sys.argv[1:] if argv is None else argv)
    return " ".join([prog, *args])


def environment(backend: str) -> dict:
    return {"torch": torch.__version__, "python": platform.python_version(), "backend": backend,
            "threads": torch.get_num_threads()}


def setup_matplotlib():
    """Import pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt

