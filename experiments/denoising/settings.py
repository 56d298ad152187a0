"""The denoise job's settings for one cloud, resolved from its config without changing it.

Several settings depend on the cloud: the optimiser's ``auto`` entries on its noise level (the
``<key>_by_noise`` tables of ``conf/denoise.yaml``, interpolated in log noise), the
regularisers' neighbourhood on its point count, the budget preset (``conf/denoise_parts/budget/``) on its
point count, the render channel (``conf/denoise_parts/channel/``) and the plane fusion (``conf/denoise_parts/fusion/``) on
the reference generator. :func:`resolve` settles all of them at once into a
:class:`Settings`; each step is a function of the config and the steps before it, and
``Settings.notes`` / ``Settings.budget`` say what was chosen and why (``metrics.json``).
"""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass
from typing import Any

from omegaconf import DictConfig, OmegaConf

from dss.schedule import interpolate_by_noise

log = logging.getLogger(__name__)

__all__ = ["Settings", "resolve", "interpolate_by_noise", "by_noise", "noise_settings", "neighbourhood",
           "budget", "render_channel", "fusion_config", "optimizer_config", "BY_NOISE", "CHANNELS"]

#: optimiser settings that may be ``auto`` (taken from ``<key>_by_noise`` in conf/denoise.yaml)
BY_NOISE = (("cycles", int), ("lr_points", float), ("projection_weight", float), ("reg_cutoff", float),
            ("final_projection_k", int), ("rim_k", int), ("rim_ratio", float), ("rim_target", float),
            ("rim_iterations", int))
#: the render channels of ``conf/denoise_parts/channel/``
CHANNELS = ("auto", "planes", "sun", "point")


@dataclass(frozen=True)
class Settings:
    """Everything the job's stages read, resolved for one cloud (:func:`resolve`).

    Attributes:
        noise: the noise level in use (std, fraction of the bbox diagonal).
        points: the cloud's point count the settings were resolved for.
        optimizer: :class:`dss.optimize.OptimizerConfig` (views and seed included).
        fusion: :class:`dss.fusion.FusionConfig`, or None when the plane fusion is off.
        spec: the render spec (:class:`data_prep.render_spec.RenderSpec`): cameras, size, renderer.
        spec_source: where the spec came from (``metrics.json`` ``render.source``).
        shading: what the renders show: ``"planes"``, ``"sun"`` or a point light.
        shading_name: its name (``metrics.json`` ``render.shading``).
        notes: ``{key: what was chosen and why}`` for cycles, lr_points, projection_weight,
            reg_cutoff, final_projection_k, the rim pull's rim_k, rim_ratio, rim_target and
            rim_iterations, max_displacement (when auto) and reg_dilation.
        budget: the budget preset's note (``metrics.json`` ``budget``).
        config: a copy of the job's config holding the values in use (``config.yaml``).
    """

    noise: float
    points: int
    optimizer: Any
    fusion: Any
    spec: Any
    spec_source: str
    shading: Any
    shading_name: str
    notes: dict
    budget: dict
    config: DictConfig


def resolve(cfg: DictConfig, noise: float, n_points: int, generator) -> Settings:
    """The settings of a job with config ``cfg`` on a cloud of ``n_points`` points at ``noise``
    (std, fraction of the bbox diagonal) with reference ``generator`` (its ``name``; a model's
    render spec). ``cfg`` is not changed. Raises ValueError for a setting that cannot apply."""
    values, notes = noise_settings(cfg, noise, n_points)
    values, views, passes, budget_note = budget(cfg, n_points, values, notes)
    spec, source, shading, shading_name = render_channel(cfg, generator, budget_note)
    config = _with_values(cfg, values, views, passes)
    fusion = fusion_config(config.get("fusion"), shading)
    optimizer = optimizer_config(config.optimizer, config.views, config.seed)
    return Settings(noise=float(noise), points=int(n_points), optimizer=optimizer, fusion=fusion, spec=spec,
                    spec_source=source, shading=shading, shading_name=shading_name, notes=notes,
                    budget=budget_note, config=config)


def _with_values(cfg: DictConfig, values: dict, views: int | None, passes: int | None) -> DictConfig:
    """A copy of ``cfg`` with the resolved optimiser ``values``, ``views`` and fusion ``passes``
    (None: as given): what ``config.yaml`` records."""
    out = copy.deepcopy(cfg)
    for key, value in values.items():
        out.optimizer[key] = value
    if views is not None:
        out.views = views
    if passes is not None:
        out.fusion.passes = passes
    return out


# ------------------------------------------------------------------------------ by noise level
def by_noise(cfg: DictConfig, noise: float, key: str, cast=float) -> tuple[Any, dict]:
    """(value, note) of ``optimizer.<key>``: as given, or for ``auto`` ``<key>_by_noise``
    interpolated at ``noise`` (:func:`interpolate_by_noise`; integers rounded). The note says
    what was chosen and why (``exact``: the interpolated value before rounding)."""
    setting = cfg.optimizer[key]
    if str(setting) != "auto":
        return setting, {"setting": cast(setting), "used": cast(setting)}
    name = f"{key}_by_noise"
    table = {float(k): float(v) for k, v in (cfg.get(name) or {}).items()}
    if not table:
        raise ValueError(f"optimizer.{key}=auto needs {name} ({{noise level: value}})")
    exact = interpolate_by_noise(table, float(noise))
    used = max(1, int(round(exact))) if cast is int else float(exact)
    return used, {"setting": "auto", "used": used, "exact": exact, "noise": noise, name: table}


def noise_settings(cfg: DictConfig, noise: float, n_points: int | None = None) -> tuple[dict, dict]:
    """({optimiser key: value}, {key: note}): every :data:`BY_NOISE` key (:func:`by_noise`), the
    point rate carrying the cycles' rounding, ``max_displacement=auto`` (``max_move`` noise
    levels) and, given the point count, the neighbourhood (:func:`neighbourhood`)."""
    values, notes = {}, {}
    for key, cast in BY_NOISE:
        if key in cfg.optimizer:  # a key the config does not name keeps OptimizerConfig's default
            values[key], notes[key] = by_noise(cfg, noise, key, cast)
    cyc, lr = notes["cycles"], notes["lr_points"]
    if cyc["setting"] == "auto" and lr["setting"] == "auto" and cyc["exact"] != cyc["used"]:
        # cycles are whole; the point rate takes the rounding so that cycles x rate (how far the
        # regularisers move the points) stays continuous in the noise level
        values["lr_points"] = lr["used"] = float(values["lr_points"]) * cyc["exact"] / cyc["used"]
        lr["cycles_rounding"] = f"x {cyc['exact']:.3g} / {cyc['used']}"
    sparse = float(cfg.get("sparse_rate_power", 0) or 0)
    if n_points is not None and sparse > 0 and lr["setting"] == "auto":
        # sparser than the tuned density: each point's neighbours span a wider patch, whose curvature
        # the plane fit takes for noise (its bias grows with the patch's area, ~1 / n_points), so
        # the regularisers move the points less far: rate x (n_points / tuned points)^power
        tuned = int(cfg.get("reg_dilation_points", 20000))
        if n_points < tuned:
            factor = (n_points / tuned) ** sparse
            values["lr_points"] = lr["used"] = float(values["lr_points"]) * factor
            lr["sparse_scale"] = f"x ({n_points} / {tuned})^{sparse:g} = {factor:.3g}"
    if str(cfg.optimizer.get("max_displacement", 0)) == "auto":
        # max_move noise levels (the noise is in bbox diagonals, the optimiser's frame)
        table = cfg.get("max_move_by_noise")
        max_move = (interpolate_by_noise({float(k): float(v) for k, v in table.items()}, float(noise)) if table
                    else float(cfg.get("max_move", 0) or 0))
        values["max_displacement"] = max_move * float(noise)
        notes["max_displacement"] = {"setting": "auto", "used": values["max_displacement"], "max_move": max_move}
    if n_points is not None:
        dilation, cutoff, notes["reg_dilation"] = neighbourhood(cfg, n_points, values["reg_cutoff"], notes["reg_cutoff"])
        if dilation is not None:
            values["reg_dilation"] = dilation
        if cutoff != values["reg_cutoff"]:
            values["reg_cutoff"] = notes["reg_cutoff"]["used"] = cutoff
    return values, notes


def neighbourhood(cfg: DictConfig, n_points: int, cutoff, cutoff_note: dict | None = None) -> tuple[int | None, Any, dict]:
    """(reg_dilation or None when given, reg_cutoff, note): the regularisers' neighbourhood keeps
    the same extent on the surface at any density.

    The projection term fits a plane to each point's ``reg_k`` nearest neighbours, a count tuned
    at ``reg_dilation_points`` (20K) points. A denser cloud puts the same count into a smaller
    patch: at 100K points and 1% noise 16 neighbours span less than the noise, and DSS removed
    half as much of it as at 20K. ``auto`` uses every d-th of the ``reg_k * d`` nearest, ``d =
    round(n_points / reg_dilation_points)`` (at least 1, at most ``reg_dilation_max``): the patch
    of the tuned setting, at the per-step cost of ``reg_k`` neighbours. When ``reg_cutoff``
    (``cutoff``, its note ``cutoff_note``) came from its table (``auto``), it is raised to at
    least ``sqrt(d)`` (the patch's radius in D, which shrinks as ``1/sqrt(N)``) so that the wider
    neighbours are not masked out again. docs/denoising.md has the measurements (a noise-scaled
    rule was tried and rejected there).
    """
    setting = cfg.optimizer.get("reg_dilation", 1)
    if str(setting) != "auto":
        return None, cutoff, {"setting": int(setting), "used": int(setting)}
    if n_points < 1:
        raise ValueError(f"reg_dilation=auto needs a positive point count, got {n_points}")
    tuned = int(cfg.get("reg_dilation_points", 20000))
    cap = int(cfg.get("reg_dilation_max", 8))
    d = int(min(cap, max(1, math.floor(n_points / tuned + 0.5))))
    note = {"setting": "auto", "used": d, "points": int(n_points), "reg_dilation_points": tuned,
            "reg_dilation_max": cap}
    if d > 1 and cutoff_note is not None and cutoff_note.get("setting") == "auto":
        wider = max(float(cutoff), math.sqrt(d))
        if wider != float(cutoff):
            note["reg_cutoff"] = f"{cutoff:g} -> {wider:.3g} (sqrt of the dilation)"
            cutoff = wider
    return d, cutoff, note


# ------------------------------------------------------------------------------ budget
def _preset(cfg: DictConfig, n_points: int) -> tuple[str, str, str, Any]:
    """(setting, preset name, reason, preset node) of ``cfg.budget`` (``conf/denoise_parts/budget/``):
    ``auto`` picks ``fast`` for more than ``budget.fast_above`` points, else ``default``."""
    node = cfg.get("budget")
    if not isinstance(node, DictConfig) or "name" not in node:
        raise ValueError(f"budget must be a preset of conf/denoise_parts/budget (default | fast | auto), got {node!r}")
    setting = str(node.name)
    if setting != "auto":
        return setting, setting, "given", node
    presets = node.get("presets") or {}
    limit = int(node.get("fast_above", 0) or 0)
    name = "fast" if limit and n_points > limit else "default"
    if name not in presets:
        raise ValueError(f"budget=auto: no preset {name!r} in budget.presets (have {sorted(presets)})")
    return setting, name, f"{n_points} points {'>' if name == 'fast' else '<='} budget.fast_above {limit}", presets[name]


def budget(cfg: DictConfig, n_points: int, values: dict, notes: dict) -> tuple[dict, int | None, int | None, dict]:
    """(optimiser values, views or None when given, fusion passes or None when given, note): the
    budget preset applied to the :func:`noise_settings` ``values`` (their ``notes``).

    The preset (``conf/denoise_parts/budget/``) sets ``views`` when it is null, the filters' and the planes
    channel's render sizes (``filter_image_size`` / ``planes_image_size`` in the note) when
    ``image_size`` is null, ``fusion.passes`` when it is null, and scales cycles that came from
    ``cycles_by_noise`` by its ``cycles_scale`` (an explicit ``optimizer.cycles`` is kept) and a
    point rate that came from ``lr_points_by_noise`` by its ``lr_points_scale`` (fewer cycles,
    longer steps: the regularisers move the points about as far)."""
    setting, name, reason, preset = _preset(cfg, n_points)
    values, views, passes = dict(values), None, None
    note = {"setting": setting, "used": name, "reason": reason}
    if cfg.get("views") is None:
        views = note["views"] = int(preset.views)
    else:
        note["views"] = f"{int(cfg.views)} (given)"
    if cfg.get("image_size") is None and preset.get("filter_image_size"):
        # an image filter renders at any size; a model ignores it (it renders at its training size)
        note["filter_image_size"] = int(preset.filter_image_size)
    if cfg.get("image_size") is None and preset.get("planes_image_size"):
        # identity and the oracle in the planes channel; a model renders at its training size
        note["planes_image_size"] = int(preset.planes_image_size)
    fusion = cfg.get("fusion")
    if fusion is not None and fusion.get("passes") is None:
        passes = note["fusion_passes"] = int(preset.get("fusion_passes", 4))
    scale = float(preset.get("cycles_scale", 1.0))
    if scale != 1.0 and notes["cycles"].get("setting") == "auto":
        values["cycles"] = max(1, int(round(int(values["cycles"]) * scale)))
        note["cycles"] = f"{notes['cycles']['used']} x {scale:g} -> {values['cycles']}"
    lr_scale = float(preset.get("lr_points_scale", 1.0))
    if lr_scale != 1.0 and notes["lr_points"].get("setting") == "auto":
        used = float(values["lr_points"])
        values["lr_points"] = used * lr_scale
        note["lr_points"] = f"{used:g} x {lr_scale:g} -> {values['lr_points']:g}"
    return values, views, passes, note


# ------------------------------------------------------------------------------ channel, fusion
def render_channel(cfg: DictConfig, generator, budget_note: dict):
    """(render spec, its source, shading, shading name) for ``generator``.

    A model renders in its training data's channel at its size (its metadata). Filters, identity
    and the oracle take ``cfg.channel`` (``conf/denoise_parts/channel/``): ``planes``
    (``conf/render/planes.yaml`` at its own size, or ``image_size``), ``point``
    (``conf/render/pairs.yaml``'s light) or ``sun`` (the paper's three RGB lights with pairs.yaml's
    cameras), both at ``image_size`` or the budget's ``filter_image_size``; ``auto``: point for
    identity (its references carry no geometry the plane fusion could use: on the real tuning
    shapes the fusion changed Chamfer by 0-3% at twice the time, docs/denoising.md), planes for
    the oracle (the fusion's upper bound), sun for image filters.
    """
    from data_prep.render_spec import load_render_spec, spec_path

    node = cfg.get("channel")
    channel = str(node.get("name", "auto")) if isinstance(node, DictConfig) else str(node or "auto")
    if channel not in CHANNELS:
        raise ValueError(f"channel must be one of {list(CHANNELS)}, got {channel!r}")
    if channel == "auto":
        channel = {"identity": "point", "oracle": "planes"}.get(generator.name, "sun")
    size = cfg.get("image_size")
    if generator.name == "onnx":
        spec, source = generator.render_spec(None)
        if size and list(spec.image_size) != [int(size)] * 2:
            log.warning("image_size=%s ignored: the model fixes the render size to %s", size, list(spec.image_size))
        return spec, source, spec.shader(), spec.describe_shading()
    if channel == "planes":
        size = size or budget_note.get("planes_image_size")
        spec = load_render_spec(spec_path("planes"), **({"image_size": [int(size)] * 2} if size else {}))
        return spec, "config (conf/render/planes.yaml)", "planes", "planes"
    size = size or budget_note.get("filter_image_size")
    spec = load_render_spec(**({"image_size": [int(size)] * 2} if size else {}))
    if channel == "sun":
        return spec, "config", "sun", "sun"
    return spec, "config", spec.point_light(), spec.describe_shading()


def fusion_config(node, shading):
    """The :class:`dss.fusion.FusionConfig` of a ``fusion`` block (``conf/denoise_parts/fusion/``), or None
    when the stage is off (``enabled: auto``: on in the planes channel). A bad block is refused."""
    from dss.fusion import FusionConfig

    node = node or {}
    enabled = str(node.get("enabled", "auto")).lower()
    if enabled not in ("auto", "true", "false"):
        raise ValueError(f"fusion.enabled must be auto, true or false, got {node.get('enabled')!r}")
    planes = isinstance(shading, str) and shading == "planes"
    if enabled == "false" or (enabled == "auto" and not planes):
        return None
    if not planes:
        raise ValueError("fusion.enabled=true needs the planes channel (channel=planes, or a model trained on it)")
    d = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else dict(node)
    d = {k: v for k, v in d.items() if k != "enabled"}
    if d.get("passes") is None:  # null: the budget preset's (budget()), else FusionConfig's
        d.pop("passes", None)
    known = set(FusionConfig.__dataclass_fields__)
    bad = set(d) - known
    if bad:
        raise ValueError(f"fusion: unknown keys {sorted(bad)}; known: {sorted(known | {'enabled'})}")
    return FusionConfig(**d)


def optimizer_config(node, views: int, seed: int):
    """The :class:`dss.optimize.OptimizerConfig` of an ``optimizer`` block with ``views`` and
    ``seed``; unknown keys are refused."""
    from dss.optimize import OptimizerConfig

    d = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else dict(node or {})
    known = set(OptimizerConfig.__dataclass_fields__)
    bad = set(d) - known
    if bad:
        raise ValueError(f"optimizer: unknown keys {sorted(bad)}; known: {sorted(known)}")
    return OptimizerConfig(**{**d, "views": int(views), "seed": int(seed)})
