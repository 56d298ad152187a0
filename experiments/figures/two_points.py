"""``dss-fig-twopoints``: two points chase two targets, DSS vs RBF gradient (paper Fig. twopoints).

    dss-fig-twopoints                          # writes outputs/dss-fig-twopoints/<time>/two_points.{png,json}
    dss-fig-twopoints --publish                # writes results/figures/two_points.{png,json} (tracked)
    dss-fig-twopoints --out /tmp/f --trials 0

Scene: two white splats facing an axis-aligned camera (focal 100 px, depth Z = 2: one world unit is
50 pixels), black background, albedo shading, L1 image loss, Adam on the points' x and y. Start and
target positions are given in pixels from the image centre (x right, y down); by default those of
the backward test ``test_two_points_reach_two_targets``.

The figure follows the paper: the RBF row uses sigma_k = 5 (a Gaussian far wider than the
scene). As in :mod:`experiments.figures.gradient_1d`'s "fixed ellipse" setting, the cutoff is set
so that the rendered discs have radius ``--radius`` pixels whatever sigma_k, so both rows render the
very same images and differ only in ``RenderSettings.gradient``.

The JSON also holds a small robustness check: ``--trials`` random configurations (starts and
targets uniform within +-25 px, pairs at least ``--min-separation`` apart), run with both gradients
in the paper setting and with the renderer's default cutoff C = 1 (sigma_k then sets the splat
size), reporting how often both targets are reached (within 1.5 px).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from dss.io_utils import atomic_savefig, atomic_write_json
from dss.render import RenderSettings, render, resolve_backend
from experiments import outputs

from . import (
    axis_camera,
    command_line,
    cutoff_for_radius,
    ellipse_radius_px,
    environment,
    setup_matplotlib,
)

log = logging.getLogger("dss-fig-twopoints")

SIZE = 96
FOCAL = 100.0
DEPTH = 2.0
PX_PER_UNIT = FOCAL / DEPTH
MERGE = 0.05
START_PX = [[-10.0, 0.0], [10.0, 0.0]]
TARGET_PX = [[-8.0, 12.0], [12.0, -12.0]]
SUCCESS_PX = 1.5
_NORMALS = torch.tensor([[0.0, 0.0, -1.0]] * 2)
_WHITE = torch.ones(2, 3)


def _points(xy: torch.Tensor) -> torch.Tensor:
    """(2, 3) world points at depth DEPTH from (2, 2) world x, y (differentiable)."""
    return torch.cat([xy, torch.full((xy.shape[0], 1), DEPTH, dtype=xy.dtype)], 1)


def settings_for(mode: str, sigma: float, radius: float | None, cutoff: float, window: int) -> RenderSettings:
    """Fixed disc radius (pixels) when ``radius`` is given, else the cutoff C."""
    c = cutoff_for_radius(sigma, PX_PER_UNIT, radius) if radius else cutoff
    return RenderSettings(sigma=sigma, gradient=mode, cutoff=c, window=window, merge_threshold=MERGE)


def match_distance(xy_px: torch.Tensor, target_px: torch.Tensor) -> tuple[float, list[float]]:
    """Largest point-to-target distance (pixels) under the better of the two assignments, and both distances."""
    d = torch.cdist(xy_px, target_px)
    a = d.diagonal()
    b = d.flip(1).diagonal()
    best = a if a.max() <= b.max() else b
    return float(best.max()), [float(v) for v in best]


def optimise(start_px, target_px, settings: RenderSettings, steps: int, lr: float, cams, backend: str,
             snapshots=()) -> dict:
    """Adam on the two points' pixel offsets (lr in pixels per step); images at the ``snapshots`` steps."""
    start = torch.as_tensor(start_px, dtype=torch.float32)
    target_xy = torch.as_tensor(target_px, dtype=torch.float32)
    with torch.no_grad():
        target = render(_points(target_xy / PX_PER_UNIT), _NORMALS, cams, settings, shading="albedo", colors=_WHITE,
                        backend=backend).images
    # Optimise world coordinates (like every other experiment); lr is converted from pixels.
    p = (start / PX_PER_UNIT).clone().requires_grad_()
    opt = torch.optim.Adam([p], lr=lr / PX_PER_UNIT)
    traj, losses, snaps = [], [], {}
    for it in range(steps + 1):
        xy_px = p.detach() * PX_PER_UNIT
        traj.append(xy_px.tolist())
        img = render(_points(p), _NORMALS, cams, settings, shading="albedo", colors=_WHITE,
                     backend=backend).images
        loss = (img - target).abs().mean(-1).sum()
        losses.append(float(loss.detach()))
        if it in snapshots:
            snaps[it] = img.detach()[0, ..., 0].numpy().copy()
        if it == steps:
            break
        opt.zero_grad()
        loss.backward()
        opt.step()
    final = torch.tensor(traj[-1])
    dmax, dists = match_distance(final, target_xy)
    return {"trajectory_px": traj, "loss": losses, "final_px": traj[-1], "final_distances_px": dists,
            "max_distance_px": dmax, "reached_both": dmax < SUCCESS_PX, "snapshots": snaps,
            "target_image": target[0, ..., 0].numpy().copy()}


def random_configs(n: int, seed: int, spread: float = 25.0, min_separation: float = 20.0):
    """n (start, target) pairs of (2, 2) pixel offsets, each pair at least ``min_separation`` apart."""
    g = torch.Generator().manual_seed(seed)
    out = []
    while len(out) < n:
        p = (torch.rand(4, 2, generator=g) * 2 - 1) * spread
        if (p[0] - p[1]).norm() >= min_separation and (p[2] - p[3]).norm() >= min_separation:
            out.append((p[:2].tolist(), p[2:].tolist()))
    return out


def run(out_dir: Path, sigma: float = 5.0, radius: float = 9.0, steps: int = 48, snapshots=(0, 12, 24, 36, 48),
        lr_px: float = 1.0, window: int = 64, start_px=None, target_px=None, trials: int = 12,
        trial_steps: int = 100, trial_settings=None, min_separation: float = 20.0, seed: int = 0,
        backend: str = "auto", command: str = "") -> dict:
    backend = resolve_backend(backend)
    start_px = START_PX if start_px is None else start_px
    target_px = TARGET_PX if target_px is None else target_px
    snapshots = sorted(set(int(s) for s in snapshots))
    if snapshots and (snapshots[0] < 0 or snapshots[-1] > steps):
        raise ValueError(f"snapshot steps must lie in [0, {steps}], got {snapshots}")
    if trial_settings is None:
        trial_settings = [{"name": f"paper: disc radius {radius:g} px, sigma_k={sigma:g}", "sigma": sigma, "radius": radius},
                          {"name": "C=1, sigma_k=0.1 (medium splats)", "sigma": 0.1, "cutoff": 1.0},
                          {"name": "C=1, sigma_k=0.5 (large splats)", "sigma": 0.5, "cutoff": 1.0}]
    t0 = time.perf_counter()
    cams = axis_camera(SIZE, SIZE, FOCAL)
    configs = random_configs(trials, seed, min_separation=min_separation) if trials > 0 else []
    total = 2 * steps + len(configs) * len(trial_settings) * 2 * trial_steps
    methods = {}
    trial_rows = []
    with tqdm(total=total, desc="two_points", unit="step", disable=None) as bar:
        for mode in ("rbf", "dss"):
            st = settings_for(mode, sigma, radius, 1.0, window)
            methods[mode] = optimise(start_px, target_px, st, steps, lr_px, cams, backend, snapshots)
            bar.update(steps)
        for ts in trial_settings:
            row = {"setting": ts["name"], "sigma": ts["sigma"], "radius_px": ts.get("radius"), "cutoff": ts.get("cutoff"),
                   "max_distance_px": {"dss": [], "rbf": []}}
            for start, target in configs:
                for mode in ("dss", "rbf"):
                    st = settings_for(mode, ts["sigma"], ts.get("radius"), ts.get("cutoff", 1.0), window)
                    r = optimise(start, target, st, trial_steps, lr_px, cams, backend)
                    row["max_distance_px"][mode].append(r["max_distance_px"])
                    bar.update(trial_steps)
            c_used = settings_for("dss", ts["sigma"], ts.get("radius"), ts.get("cutoff", 1.0), window).cutoff
            row["ellipse_radius_px"] = ellipse_radius_px(ts["sigma"], PX_PER_UNIT, c_used)
            row["reached_both"] = {m: int(sum(d < SUCCESS_PX for d in v)) for m, v in row["max_distance_px"].items()}
            row["trials"] = len(configs)
            trial_rows.append(row)
    result = {
        "figure": "two_points (paper Fig. twopoints)",
        "command": command,
        "runtime_s": round(time.perf_counter() - t0, 2),
        "environment": environment(backend),
        "settings": {
            "image_size": [SIZE, SIZE], "focal_px": FOCAL, "depth": DEPTH, "px_per_world_unit": PX_PER_UNIT,
            "sigma_world_units": sigma, "disc_radius_px": radius, "cutoff": settings_for("dss", sigma, radius, 1.0, window).cutoff,
            "merge_threshold": MERGE, "window_px": window, "shading": "albedo (white on black)", "loss": "L1, mean over RGB",
            "optimizer": "adam", "lr_px_per_step": lr_px, "lr_world_units": lr_px / PX_PER_UNIT, "steps": steps,
            "snapshots": snapshots, "start_px": start_px, "target_px": target_px,
            "coordinates": "pixels from the image centre, x right, y down",
            "success_threshold_px": SUCCESS_PX,
        },
        "methods": {m: {k: v for k, v in r.items() if k not in ("snapshots", "target_image")} for m, r in methods.items()},
        "trials": {"n": len(configs), "steps": trial_steps, "seed": seed, "min_separation_px": min_separation,
                   "configs_px": configs, "settings": trial_rows},
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    plot(result, methods, out_dir / "two_points.png")
    atomic_write_json(out_dir / "two_points.json", result)
    log.info("wrote %s and %s (%.1fs)", out_dir / "two_points.png", out_dir / "two_points.json", result["runtime_s"])
    for m, r in result["methods"].items():
        log.info("%s: final distances %s px", m, [round(d, 2) for d in r["final_distances_px"]])
    return result


def plot(result: dict, methods: dict, path: Path) -> None:
    plt = setup_matplotlib()
    st = result["settings"]
    snaps = st["snapshots"]
    ncol = 1 + len(snaps)
    fig, axes = plt.subplots(2, ncol, figsize=(1.7 * ncol, 4.1), squeeze=False)
    labels = {"rbf": f"RBF $\\sigma_k$={st['sigma_world_units']:g}", "dss": "Ours (DSS)"}
    c = SIZE / 2.0
    tx = [t[0] + c for t in st["target_px"]]
    ty = [t[1] + c for t in st["target_px"]]
    for r, mode in enumerate(("rbf", "dss")):
        res = methods[mode]
        panels = [("target", res["target_image"])] + [("initialization" if s == 0 else f"step {s}", res["snapshots"][s])
                                                      for s in snaps]
        for j, (title, img) in enumerate(panels):
            ax = axes[r][j]
            ax.imshow(img, cmap="gray", vmin=0, vmax=1, extent=(0, SIZE, SIZE, 0), interpolation="nearest")
            if j > 0:  # where the targets are
                ax.plot(tx, ty, "+", color="red", ms=6, mew=1.2)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 1:
                ax.set_xlabel(title, fontsize=8)
            if j == 0:
                d = res["final_distances_px"]
                ax.set_ylabel(f"{labels[mode]}\nfinal dist. {d[0]:.1f}, {d[1]:.1f} px", fontsize=8)
    lines = [f"Two points, Adam {st['lr_px_per_step']:g} px/step, discs of radius {st['disc_radius_px']:g} px (same images "
             "in both rows); red +: targets."]
    tr = result["trials"]
    if tr["n"]:
        lines.append(f"{tr['n']} random configurations, {tr['steps']} steps; both targets reached "
                     f"(within {st['success_threshold_px']:g} px):")
        lines += [f"{row['setting']}:  DSS {row['reached_both']['dss']}/{tr['n']},  RBF {row['reached_both']['rbf']}/{tr['n']}"
                  for row in tr["settings"]]
    fig.text(0.5, 0.005, "\n".join(lines), ha="center", va="bottom", fontsize=7)
    fig.tight_layout(rect=(0, 0.035 * len(lines), 1, 1))
    atomic_savefig(fig, path)
    plt.close(fig)


def _pairs(text: str) -> list[list[float]]:
    try:
        v = json.loads(text)
        arr = np.asarray(v, dtype=float)
    except (ValueError, TypeError) as e:
        raise argparse.ArgumentTypeError(f"expected JSON like [[-10,0],[10,0]], got {text!r}") from e
    if arr.shape != (2, 2):
        raise argparse.ArgumentTypeError(f"expected two (x, y) pairs, got shape {arr.shape}")
    return arr.tolist()


def main(argv=None) -> int:
    """Console entry point; returns the exit status (the numbers are in the JSON; ``run`` returns them)."""
    ap = argparse.ArgumentParser(prog="dss-fig-twopoints", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    outputs.add_arguments(ap, published="results/figures")
    ap.add_argument("--sigma", type=float, default=5.0, help="sigma_k of both rows (world units; paper: 5)")
    ap.add_argument("--radius", type=float, default=9.0, help="rendered disc radius in pixels (sets the cutoff)")
    ap.add_argument("--steps", type=int, default=48)
    ap.add_argument("--snapshots", type=int, nargs="+", default=[0, 12, 24, 36, 48])
    ap.add_argument("--lr", type=float, default=1.0, help="Adam learning rate in pixels per step")
    ap.add_argument("--window", type=int, default=64, help="visibility-gradient window half size, pixels")
    ap.add_argument("--start", type=_pairs, default=None, help="start offsets in px, JSON [[x,y],[x,y]]")
    ap.add_argument("--target", type=_pairs, default=None, help="target offsets in px, JSON [[x,y],[x,y]]")
    ap.add_argument("--trials", type=int, default=12, help="random configurations for the robustness check (0: none)")
    ap.add_argument("--trial-steps", type=int, default=100)
    ap.add_argument("--min-separation", type=float, default=20.0, help="px between the two starts and the two targets")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--backend", default="auto", choices=["auto", "cpp", "reference"])
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.manual_seed(0)
    run(outputs.folder(args, "dss-fig-twopoints"), args.sigma, args.radius, args.steps, args.snapshots, args.lr, args.window, args.start,
        args.target, args.trials, args.trial_steps, None, args.min_separation, args.seed, args.backend,
        command=command_line("dss-fig-twopoints", argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
