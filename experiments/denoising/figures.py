"""The job's figures: ``before_after.png`` (a row per cloud), ``references.png`` (the last
batch: input renders, references, result), ``loss.png`` and ``loss.json``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

__all__ = ["FIGURE_KEYS", "check_figures", "figure_cameras", "render_rows", "save_image_rows", "save_loss_curve",
           "write_figures"]

FIGURE_KEYS = ("enabled", "views", "image_size")


def check_figures(node) -> None:
    """Refuse a bad ``figures`` block before any work (the figures are drawn after it)."""
    node = node or {}
    unknown = sorted(set(node) - set(FIGURE_KEYS))
    if unknown:
        raise ValueError(f"figures: unknown keys {unknown}; known: {list(FIGURE_KEYS)}")
    enabled = node.get("enabled", True)
    if not isinstance(enabled, bool):
        raise ValueError(f"figures.enabled={enabled!r}: must be true or false")
    for key, default, allow_null in (("views", 4, False), ("image_size", None, True)):
        value = node.get(key, default)
        if value is None and allow_null:
            continue
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"figures.{key}={value!r}: must be a positive integer"
                             + (" (or null: the render size)" if allow_null else ""))


def figure_cameras(spec, n: int = 4, seed: int = 0, size: int | None = None):
    """``n`` fixed cameras seeing the whole normalised object with the spec's field of view."""
    from dss.cameras import fit_distance, focal_from_fov, fps_sphere_cameras

    H, W = (size, size) if size else spec.image_size
    dist = fit_distance(0.5, spec.fov_deg)  # a unit-diagonal box fits in a radius-0.5 sphere
    return fps_sphere_cameras(n, (0.0, 0.0, 0.0), dist, focal_from_fov(spec.fov_deg, W), (H, W), jitter=0.0,
                              generator=torch.Generator().manual_seed(seed), up=spec.up)


def render_rows(clouds: list[tuple[torch.Tensor, torch.Tensor]], cams, settings, shading, backend="auto"):
    from dss.render import render

    rows = []
    with torch.no_grad():
        for p, n in clouds:
            rows.append(render(p, n, cams, settings, shading=shading, backend=backend).images.clamp(0, 1))
    return rows


def save_image_rows(path: Path, rows: list[torch.Tensor], labels: list[str]) -> Path:
    """Grid PNG: one row per entry of ``rows`` ((V, H, W, C) each, in [0, 1]), labelled on the left."""
    from dss.viz import labelled_rows, save_png

    return save_png(path, labelled_rows([r.clamp(0, 1) for r in rows], labels))


def save_loss_curve(path: Path, history: dict, steps_per_cycle: int, title: str, image_loss: str = "l1") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dss.io_utils import atomic_savefig

    loss = np.asarray(history["loss"], np.float64)
    fig, ax = plt.subplots(figsize=(6, 3.2))
    ax.plot(np.arange(1, len(loss) + 1), loss, lw=1)
    for c in range(steps_per_cycle, len(loss), steps_per_cycle):
        ax.axvline(c + 0.5, color="0.85", lw=0.5, zorder=0)
    ax.set_xlabel("step (grey lines: new views and references)")
    # the plotted value is the step's whole objective; name the image term the config chose
    ax.set_ylabel(f"loss ({image_loss.upper()} image term + regularisers)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)
    return path


def _references_png(path: Path, ref, result, settings, shading, backend) -> Path:
    """The last batch's input renders, references and the ``result`` cloud's renders (4 views)."""
    from dss.render import render
    from dss.shading import planes_normals

    planes = isinstance(shading, str) and shading == "planes"
    cams_r, imgs, _mask, refs = ref.last
    k = min(4, len(cams_r))
    sub = cams_r[:k]
    p, n = result
    with torch.no_grad():
        final = render(p, n, sub, settings, shading=shading, backend=backend).images

    def show(x):  # planes as a normal map (camera-facing normals, world axes -> RGB)
        if not planes:
            return x.clamp(0, 1)
        covered = (x.abs().amax(-1, keepdim=True) > 0)
        return torch.where(covered, 0.5 + 0.5 * planes_normals(x, sub), torch.zeros_like(x))

    return save_image_rows(path, [show(imgs[:k]), show(refs[:k]), show(final)], ["input render", "reference", "result"])


def write_figures(out: Path, figures, seed: int, spec, rows_pts: list, labels: list, refined, title: str,
                  shading=None) -> list[str]:
    """before_after.png (a row per cloud of ``rows_pts``, in input units), references.png (last
    cycle: input renders | references | result renders), loss.png / loss.json. ``figures``: the
    config's ``figures`` block; ``refined``: :class:`experiments.denoising.refine.Refined`."""
    from dss.io_utils import atomic_write_json

    center, scale, _ = refined.norm
    fig_cfg = figures or {}
    cams = figure_cameras(spec, int(fig_cfg.get("views", 4)), int(seed), fig_cfg.get("image_size"))
    settings = spec.render_settings()
    shading = spec.shader() if shading is None else shading
    planes = isinstance(shading, str) and shading == "planes"
    clouds = [((p - center) / scale, n) for p, n in rows_pts]
    # planes are not a picture: the before/after rows use the paper's sun lights in that channel
    rows = render_rows(clouds, cams, settings, "sun" if planes else shading, spec.backend)
    written = [save_image_rows(out / "before_after.png", rows, labels).name]
    if refined.ref.last is not None:
        written.append(_references_png(out / "references.png", refined.ref, clouds[1], settings, shading,
                                       spec.backend).name)
    ocfg, history = refined.optimizer, refined.history
    steps = ocfg.normal_steps + ocfg.point_steps
    written.append(save_loss_curve(out / "loss.png", history, steps, title, str(ocfg.image_loss)).name)
    atomic_write_json(out / "loss.json", {"step": history["step"], "loss": history["loss"], "kind": history["kind"],
                                          "time": history["time"], "steps_per_cycle": steps})
    written.append("loss.json")
    return written
