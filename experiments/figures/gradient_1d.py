"""``dss-fig-gradient1d``: the paper's 1D comparison of the DSS and RBF gradients (Fig. 1Dplot).

    dss-fig-gradient1d                         # writes outputs/dss-fig-gradient1d/<time>/gradient_1d.{png,json}
    dss-fig-gradient1d --publish               # writes results/figures/gradient_1d.{png,json} (tracked)
    dss-fig-gradient1d --out /tmp/f --steps 50 --distance-step 1 --optimizers adam:0.01

Scene: one white splat facing an axis-aligned camera (focal 100 px, depth Z = 2, so one world unit
is 50 pixels and sigma_k = 0.05 / 0.1 / 0.5 world units are 2.5 / 5 / 25 pixels before the 1 px^2
low-pass filter), black background, albedo shading, ``window`` large enough that every pixel in
reach counts. Only the point's x coordinate varies (the paper's 1D scenario).

(a) Gradient value vs pixel distance d = x - x_k. The target equals the current image except at one
    pixel x, d pixels to the right of the splat centre: there it shows the splat's colour when the
    splat does not cover x (the point should come), and the background when it does (the point
    should leave). The loss is that pixel's absolute error averaged over RGB (|Delta I| = 1), and
    we plot |dL/du|, u being the point's screen x in pixels (1/pixel). The DSS value outside the
    ellipse is 1/d by construction (Eq. gradcase, case (a)).
(b) Residual x - x_k (pixels) vs optimisation step: the point chases a copy of itself shifted by
    ``--shift`` pixels, L1 image loss, the same optimiser and learning rate for every curve of a
    panel. One panel per optimiser: Adam (scale-free: it only sees the gradient's sign and whether
    it is there at all) and plain SGD (the step follows the gradient's value, as in panel (a)).

Two rows, because the paper's sigma_k and ours are not quite the same knob:
- "fixed ellipse" (the paper's figure: one ellipse boundary for every curve): the cutoff C is set per
  sigma_k so that the rendered disc has radius ``--radius`` pixels; the forward image and the DSS
  gradient are then the same for all sigma_k, and sigma_k only sets the width of the Gaussian that
  the RBF gradient differentiates.
- "C = 1" (the renderer's default cutoff): sigma_k sets the splat size itself (small / medium /
  large discs); the RBF Gaussian is the splat's own.
"""

from __future__ import annotations

import argparse
import logging
import math
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
    make_optimizer,
    setup_matplotlib,
)

log = logging.getLogger("dss-fig-gradient1d")

HEIGHT, WIDTH = 96, 192
FOCAL = 100.0
DEPTH = 2.0
PX_PER_UNIT = FOCAL / DEPTH
MERGE = 0.05
SWEEP_COLUMN = WIDTH // 2 + 40  # the one differing pixel of panel (a); the splat sits to its left
RBF_COLORS = {0.5: "#8e4585", 0.1: "#ff8c00", 0.05: "#b57edc"}  # the paper's plum / orange / lavender
EXTRA_COLORS = ["#2ca02c", "#d62728", "#8c564b", "#17becf"]


def _settings(mode: str, sigma: float, cutoff: float, window: int) -> RenderSettings:
    return RenderSettings(sigma=sigma, gradient=mode, cutoff=cutoff, window=window, merge_threshold=MERGE)


def _point(x: torch.Tensor, v_px: float) -> torch.Tensor:
    """(1, 3) point at world x (a (1,) tensor, may require grad), screen row v_px, depth DEPTH."""
    y = torch.full_like(x, (v_px - HEIGHT / 2.0) / PX_PER_UNIT)
    return torch.stack([x, y, torch.full_like(x, DEPTH)], 1)


def _x_world(u_px: float) -> float:
    return (u_px - WIDTH / 2.0) / PX_PER_UNIT


_NORMAL = torch.tensor([[0.0, 0.0, -1.0]])
_WHITE = torch.ones(1, 3)


def gradient_at_distance(settings: RenderSettings, d: float, cams, backend: str) -> tuple[float, bool]:
    """dL/du (1/pixel) from one differing pixel d pixels right of the splat centre; and whether it is covered."""
    pc = SWEEP_COLUMN + 0.5
    x = torch.tensor([_x_world(pc - d)], requires_grad=True)
    row = HEIGHT // 2
    out = render(_point(x, row + 0.5), _NORMAL, cams, settings, shading="albedo", colors=_WHITE, backend=backend)
    covered = bool(out.mask[0, row, SWEEP_COLUMN])
    target = out.images.detach().clone()
    target[0, row, SWEEP_COLUMN] = 0.0 if covered else 1.0
    loss = (out.images - target).abs().mean(-1).sum()
    loss.backward()
    return float(x.grad[0]) / PX_PER_UNIT, covered


def residual_curve(settings: RenderSettings, shift: float, steps: int, optimizer: str, lr: float, cams,
                   backend: str) -> list[float]:
    """x_target - x_k in pixels before each step and after the last one (steps + 1 values)."""
    u0 = WIDTH / 2.0 - math.floor(shift / 2.0)  # a pixel edge, like the backward tests
    v = HEIGHT / 2.0
    xt = _x_world(u0 + shift)
    with torch.no_grad():
        target = render(_point(torch.tensor([xt]), v), _NORMAL, cams, settings, shading="albedo", colors=_WHITE,
                        backend=backend).images
    x = torch.tensor([_x_world(u0)], requires_grad=True)
    opt = make_optimizer(optimizer, [x], lr)
    res = []
    for _ in range(steps):
        res.append((xt - float(x.detach()[0])) * PX_PER_UNIT)
        opt.zero_grad()
        img = render(_point(x, v), _NORMAL, cams, settings, shading="albedo", colors=_WHITE, backend=backend).images
        (img - target).abs().mean(-1).sum().backward()
        opt.step()
    res.append((xt - float(x.detach()[0])) * PX_PER_UNIT)
    return res


def _steps_to_converge(res: list[float], tol: float = 1.0) -> int | None:
    """First step from which |residual| stays below tol pixels, or None."""
    r = np.abs(np.asarray(res))
    bad = np.nonzero(r >= tol)[0]
    if len(bad) == 0:
        return 0
    return int(bad[-1] + 1) if bad[-1] + 1 < len(r) else None


def _summarise(row: dict, distances: np.ndarray, report_distance: float) -> dict:
    """Numbers behind the claims: DSS invariant to sigma outside the ellipse, RBF sensitive."""
    sig = row["sigmas"]
    radii = np.array([row["ellipse_radius_px"][str(s)] for s in sig])
    dss = np.abs(np.array([row["gradient"]["dss"][str(s)] for s in sig]))
    rbf = np.abs(np.array([row["gradient"]["rbf"][str(s)] for s in sig]))
    outside = distances > radii.max() + 1.0
    out = {}
    if outside.any():
        o = dss[:, outside]
        out["dss_outside_max_relative_spread_over_sigma"] = float(((o.max(0) - o.min(0)) / np.maximum(o.max(0), 1e-30)).max())
        out["dss_outside_max_abs_error_vs_1_over_d"] = float(np.abs(o * distances[outside] - 1.0).max())
    inside = distances < radii.min() - 1.0
    if inside.any():
        i = dss[:, inside]
        out["dss_inside_max_relative_spread_over_sigma"] = float(((i.max(0) - i.min(0)) / np.maximum(i.max(0), 1e-30)).max())
    k = int(np.argmin(np.abs(distances - report_distance)))
    out["report_distance_px"] = float(distances[k])
    out["at_report_distance"] = {str(s): {"dss": float(dss[j, k]), "rbf": float(rbf[j, k]),
                                          "rbf_over_dss": float(rbf[j, k] / dss[j, k]) if dss[j, k] > 0 else None}
                                 for j, s in enumerate(sig)}
    inc, zero = {}, {}
    for j, s in enumerate(sig):
        beyond = distances > radii[j] + 1.0
        g = rbf[j, beyond]
        inc[str(s)] = bool(len(g) > 1 and (np.diff(g) > 1e-12 * g.max(initial=0)).any())
        nz = np.nonzero(rbf[j] > 0)[0]
        zero[str(s)] = float(distances[nz[-1] + 1]) if len(nz) and nz[-1] + 1 < len(distances) else None
    out["rbf_increases_outside_ellipse"] = inc
    out["rbf_exactly_zero_from_px"] = zero
    out["steps_to_within_1px"] = {o: {m: {str(s): _steps_to_converge(res[m][str(s)]) for s in sig} for m in ("dss", "rbf")}
                                  for o, res in row["residual"].items()}
    out["final_residual_px"] = {o: {m: {str(s): res[m][str(s)][-1] for s in sig} for m in ("dss", "rbf")}
                                for o, res in row["residual"].items()}
    return out


def run(out_dir: Path, sigmas=(0.05, 0.1, 0.5), radius: float = 9.0, cutoff: float = 1.0, max_distance: float = 50.0,
        distance_step: float = 0.25, steps: int = 200, shift: float = 25.0,
        optimizers=(("adam", 0.01), ("sgd", 2e-5)), window: int = 64, backend: str = "auto", report_distance: float = 25.0, command: str = "") -> dict:
    if window < max_distance + 1:
        raise ValueError(f"window ({window} px) must exceed --max-distance ({max_distance} px): farther pixels would not count")
    if window < shift + max(ellipse_radius_px(s, PX_PER_UNIT, cutoff) for s in sigmas):
        log.warning("window %d px may not reach the whole target in panel (b)", window)
    if not 0 < distance_step <= max_distance:
        raise ValueError("need 0 < --distance-step <= --max-distance")
    backend = resolve_backend(backend)
    t0 = time.perf_counter()
    cams = axis_camera(HEIGHT, WIDTH, FOCAL)
    distances = np.arange(distance_step, max_distance + 1e-9, distance_step)
    rows = {
        "fixed_ellipse": {"title": f"paper setting: ellipse radius fixed at {radius:g} px (C set per $\\sigma_k$)",
                          "cutoff": {str(s): cutoff_for_radius(s, PX_PER_UNIT, radius) for s in sigmas}},
        "default_cutoff": {"title": f"C = {cutoff:g}: $\\sigma_k$ sets the splat size",
                           "cutoff": {str(s): float(cutoff) for s in sigmas}},
    }
    optimizers = [(str(o), float(lr)) for o, lr in optimizers]
    opt_keys = [f"{o}:{lr:g}" for o, lr in optimizers]
    if len(set(opt_keys)) != len(opt_keys):
        raise ValueError(f"repeated optimiser settings: {opt_keys}")
    total = len(rows) * 2 * len(sigmas) * (len(distances) + steps * len(optimizers))
    with tqdm(total=total, desc="gradient_1d", unit="render", disable=None) as bar:
        for row in rows.values():
            row["sigmas"] = list(sigmas)
            row["ellipse_radius_px"] = {str(s): ellipse_radius_px(s, PX_PER_UNIT, row["cutoff"][str(s)]) for s in sigmas}
            row["gradient"], row["covered"] = {}, {}
            row["residual"] = {k: {"dss": {}, "rbf": {}} for k in opt_keys}
            for mode in ("dss", "rbf"):
                row["gradient"][mode], row["covered"][mode] = {}, {}
                for s in sigmas:
                    st = _settings(mode, s, row["cutoff"][str(s)], window)
                    g, c = [], []
                    for d in distances:
                        gi, ci = gradient_at_distance(st, float(d), cams, backend)
                        g.append(gi)
                        c.append(ci)
                        bar.update()
                    row["gradient"][mode][str(s)] = g
                    row["covered"][mode][str(s)] = c
                    for key, (opt, lr) in zip(opt_keys, optimizers):
                        row["residual"][key][mode][str(s)] = residual_curve(st, shift, steps, opt, lr, cams, backend)
                        bar.update(steps)
            row["summary"] = _summarise(row, distances, report_distance)
    result = {
        "figure": "gradient_1d (paper Fig. 1Dplot)",
        "command": command,
        "runtime_s": round(time.perf_counter() - t0, 2),
        "environment": environment(backend),
        "settings": {
            "image_size": [HEIGHT, WIDTH], "focal_px": FOCAL, "depth": DEPTH, "px_per_world_unit": PX_PER_UNIT,
            "sigmas_world_units": list(sigmas), "sigmas_px_before_filter": [s * PX_PER_UNIT for s in sigmas],
            "filter_variance_px2": 1.0, "merge_threshold": MERGE, "window_px": window, "shading": "albedo (white on black)",
            "fixed_radius_px": radius, "default_cutoff": cutoff, "distance_step_px": distance_step,
            "max_distance_px": max_distance, "optimizers": opt_keys, "steps": steps,
            "shift_px": shift, "moving_coordinate": "x only",
        },
        "units": {
            "distance": "pixels, x - x_k (pixel centre minus splat centre)",
            "gradient": "dL/du in 1/pixel; L = absolute error of the one differing pixel, mean over RGB (|Delta I| = 1); "
                        "u = the point's screen x in pixels; sign < 0 means descent moves the point toward the pixel",
            "residual": "pixels, x_target - x_k; keyed by 'optimizer:lr' (lr in world units for Adam; "
                        "world units^2 per loss unit for SGD)",
        },
        "distances_px": distances.tolist(),
        "rows": rows,
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    plot(result, out_dir / "gradient_1d.png")
    atomic_write_json(out_dir / "gradient_1d.json", result)
    log.info("wrote %s and %s (%.1fs)", out_dir / "gradient_1d.png", out_dir / "gradient_1d.json", result["runtime_s"])
    return result


def _rbf_color(s: float, j: int) -> str:
    return RBF_COLORS.get(s, EXTRA_COLORS[j % len(EXTRA_COLORS)])


def plot(result: dict, path: Path) -> None:
    plt = setup_matplotlib()
    rows = result["rows"]
    d = np.asarray(result["distances_px"])
    st = result["settings"]
    opt_keys = st["optimizers"]
    ncol = 1 + len(opt_keys)
    fig, axes = plt.subplots(len(rows), ncol, figsize=(5.6 * ncol, 4.3 * len(rows)), squeeze=False)
    dss_styles = [("-", 3.0), ("--", 2.0), (":", 1.5), ("-.", 1.2)]
    for r, row in enumerate(rows.values()):
        ax_g, ax_rs = axes[r][0], axes[r][1:]
        sig = row["sigmas"]
        for j, s in enumerate(sig):
            ls, lw = dss_styles[j % len(dss_styles)]
            g = np.abs(np.asarray(row["gradient"]["dss"][str(s)]))
            ax_g.plot(d, np.where(g > 0, g, np.nan), color="navy", ls=ls, lw=lw, label=f"DSS (ours) $\\sigma_k$={s:g}")
            for ax, key in zip(ax_rs, opt_keys):
                ax.plot(row["residual"][key]["dss"][str(s)], color="navy", ls=ls, lw=lw, label=f"DSS (ours) $\\sigma_k$={s:g}")
        for j, s in enumerate(sig):
            c = _rbf_color(s, j)
            ls = "--" if s == min(sig) else "-"
            g = np.abs(np.asarray(row["gradient"]["rbf"][str(s)]))
            ax_g.plot(d, np.where(g > 0, g, np.nan), color=c, ls=ls, lw=1.8, label=f"RBF $\\sigma_k$={s:g}")
            for ax, key in zip(ax_rs, opt_keys):
                ax.plot(row["residual"][key]["rbf"][str(s)], color=c, ls=ls, lw=1.8, label=f"RBF $\\sigma_k$={s:g}")
        radii = sorted({round(v, 2) for v in row["ellipse_radius_px"].values()})
        for rad in radii:
            if rad <= d.max():
                who = [f"{s:g}" for s in sig if round(row["ellipse_radius_px"][str(s)], 2) == rad]
                ax_g.axvline(rad, color="gray", ls=":", lw=1.2)
                label = "ellipse boundary" + ("" if len(radii) == 1 else f" ($\\sigma_k$={','.join(who)})")
                ax_g.text(rad, 2e-8, " " + label, rotation=90, va="bottom", ha="right", fontsize=7, color="dimgray")
        ax_g.set_yscale("log")
        ax_g.set_ylim(1e-8, 10)
        ax_g.set_xlim(0, d.max())
        ax_g.set_xlabel("$x - x_k$ (pixels)")
        ax_g.set_ylabel("$|dL/du|$ from pixel $x$ (1/pixel)")
        ax_g.set_title(f"(a) gradient vs distance\n{row['title']}", fontsize=9)
        ax_g.grid(alpha=0.3, which="both")
        for ax, key in zip(ax_rs, opt_keys):
            ax.axhline(0, color="k", lw=0.6)
            ax.set_xlabel("optimisation step")
            ax.set_ylabel("$x - x_k$ (pixels)")
            ax.set_title(f"(b) residual vs step, {key.replace(':', ' lr=')}, target {st['shift_px']:g} px away\n"
                         f"{row['title']}", fontsize=9)
            ax.grid(alpha=0.3)
        if r == 0:
            ax_g.legend(fontsize=7, loc="upper right", ncol=2)
            ax_rs[0].legend(fontsize=7, loc="center right")
    fig.suptitle(f"DSS vs RBF gradient, one splat (1 world unit = {st['px_per_world_unit']:g} px; "
                 "zero gradients are not drawn)", fontsize=10)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)


def _optimizer_arg(text: str) -> tuple[str, float]:
    name, _, lr = text.partition(":")
    if name not in ("adam", "sgd") or not lr:
        raise argparse.ArgumentTypeError(f"expected adam:LR or sgd:LR, got {text!r}")
    try:
        return name, float(lr)
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"bad learning rate in {text!r}") from e


def main(argv=None) -> int:
    """Console entry point; returns the exit status (the numbers are in the JSON; ``run`` returns them)."""
    ap = argparse.ArgumentParser(prog="dss-fig-gradient1d", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    outputs.add_arguments(ap, published="results/figures")
    ap.add_argument("--sigmas", type=float, nargs="+", default=[0.05, 0.1, 0.5], help="sigma_k values (world units)")
    ap.add_argument("--radius", type=float, default=9.0, help="ellipse radius (px) of the fixed-ellipse row")
    ap.add_argument("--cutoff", type=float, default=1.0, help="cutoff C of the second row")
    ap.add_argument("--max-distance", type=float, default=50.0, help="largest x - x_k in panel (a), pixels")
    ap.add_argument("--distance-step", type=float, default=0.25, help="spacing of panel (a)'s distances, pixels")
    ap.add_argument("--steps", type=int, default=200, help="optimisation steps of panel (b)")
    ap.add_argument("--shift", type=float, default=25.0, help="target offset of panel (b), pixels")
    ap.add_argument("--optimizers", type=_optimizer_arg, nargs="+", default=[("adam", 0.01), ("sgd", 2e-5)],
                    help="one residual panel per NAME:LR (adam: lr in world units, 0.01 = 0.5 px per step; "
                         "sgd: world units^2 per loss unit). Default: adam:0.01 sgd:2e-5")
    ap.add_argument("--window", type=int, default=64, help="visibility-gradient window half size, pixels")
    ap.add_argument("--report-distance", type=float, default=25.0, help="distance at which the JSON compares values")
    ap.add_argument("--backend", default="auto", choices=["auto", "cpp", "reference"])
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.manual_seed(0)
    run(outputs.folder(args, "dss-fig-gradient1d"), tuple(args.sigmas), args.radius, args.cutoff, args.max_distance, args.distance_step,
        args.steps, args.shift, tuple(args.optimizers), args.window, args.backend, args.report_distance,
        command=command_line("dss-fig-gradient1d", argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
