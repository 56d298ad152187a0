"""dss-deform's coarse-to-fine stages: the optimiser settings of a coarse and a fine stage, the
upsampling between them, and one history of both."""

from __future__ import annotations

import dataclasses
import math

import torch

from dss.optimize import OptimizerConfig
from dss.regularizers import bandwidth_for

__all__ = ["upsample", "stage_configs", "merge_histories"]


def upsample(points: torch.Tensor, normals: torch.Tensor, n: int,
             generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` points and normals from the ``m`` of a coarse cloud ((m, 3) each, m <= n): every
    coarse point kept, and ``n - m`` more, the coarse points in turn, each placed uniformly at
    random on the disc in its tangent plane of radius half its nearest-neighbour distance (the
    share of the surface a point stands for), with its normal. The fine cycles' normal re-fit,
    projection and repulsion then settle them on the surface."""
    from scipy.spatial import cKDTree

    m = len(points)
    if n <= m:
        return points[:n].clone(), normals[:n].clone()
    p = points.detach().cpu()
    nrm = torch.nn.functional.normalize(normals.detach().cpu(), dim=1)
    d, _ = cKDTree(p.numpy()).query(p.numpy(), k=2)
    nn = torch.from_numpy(d[:, 1]).float()
    idx = torch.arange(n - m) % m
    nv = nrm[idx]
    helper = torch.where((nv[:, :1].abs() < 0.9), torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
    t1 = torch.nn.functional.normalize(torch.cross(nv, helper, dim=1), dim=1)
    t2 = torch.cross(nv, t1, dim=1)
    angle = 2 * math.pi * torch.rand(n - m, generator=generator)
    radius = 0.5 * nn[idx] * torch.rand(n - m, generator=generator).sqrt()
    new = p[idx] + radius[:, None] * (angle.cos()[:, None] * t1 + angle.sin()[:, None] * t2)
    return (torch.cat([p, new]).to(points.device), torch.cat([nrm, nv]).to(points.device))


def stage_configs(opt_cfg: OptimizerConfig, coarse_cycles: int,
                  fine_start: torch.Tensor) -> tuple[OptimizerConfig, OptimizerConfig]:
    """The coarse and the fine stage's optimiser settings: the coarse stage runs the schedule's
    first ``coarse_cycles`` cycles; the fine stage the rest, where the schedule stands after them
    (learning rates and the fill pull x lr_decay^coarse_cycles, the window x
    window_decay^coarse_cycles), with the regularisers' bandwidths of the full start cloud
    ``fine_start`` (N, 3), as a one-stage run has them, and views of their own seed."""
    c = opt_cfg
    if not 0 < coarse_cycles < c.cycles:
        raise ValueError(f"coarse.cycles must be between 1 and optimizer.cycles - 1 = {c.cycles - 1}, got {coarse_cycles}")
    coarse = dataclasses.replace(c, cycles=coarse_cycles, error_aware_cycles=0, final_normal_refresh_k=0,
                                 final_projection_k=0)
    decay = c.lr_decay ** coarse_cycles

    def bw(rule):
        return bandwidth_for(fine_start, rule) if isinstance(rule, str) else rule

    fine = dataclasses.replace(c, cycles=c.cycles - coarse_cycles, lr_points=c.lr_points * decay,
                               lr_normals=c.lr_normals * decay, fill_step=c.fill_step * decay,
                               window_start=c.window_start * c.window_decay ** coarse_cycles,
                               projection_bandwidth=bw(c.projection_bandwidth),
                               repulsion_bandwidth=bw(c.repulsion_bandwidth), seed=c.seed + 104729)
    return coarse, fine


def merge_histories(first: dict, second: dict) -> dict:
    """One history of two stages run one after the other (steps and times continued)."""
    steps, t = first["steps"], first["wall_time"]
    h = dict(second)
    for key, shift in (("step", steps), ("time", t)):
        h[key] = list(first[key]) + [x + shift for x in second[key]]
    for key, value in first.items():  # per-step and per-cycle lists: one after the other
        if key not in ("step", "time") and isinstance(value, list) and isinstance(second.get(key), list):
            h[key] = value + second[key]
    h["lr_halvings"] = first["lr_halvings"] + second["lr_halvings"]
    h["steps"] = steps + second["steps"]
    h["wall_time"] = t + second["wall_time"]
    for key in ("profile_s", "profile_cpu_s"):
        a, b = first.get(key, {}), second.get(key, {})
        h[key] = {k: a.get(k, 0.0) + b.get(k, 0.0) for k in {**a, **b}}
    h["config"] = {"coarse": first["config"], "fine": second["config"]}
    return h
