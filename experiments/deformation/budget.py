"""dss-deform's budget presets (``budgets`` in ``conf/deform.yaml``): a preset's settings replace
the config's, except those the command line gives."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

__all__ = ["command_line_keys", "apply_budget"]


def _leaves(node, prefix: str = "") -> dict:
    """``{"optimizer.cycles": 10, ...}``: the dotted keys of a nested preset's values."""
    out = {}
    for k, v in node.items():
        key = f"{prefix}{k}"
        if isinstance(v, (dict, DictConfig)):
            out.update(_leaves(v, key + "."))
        else:
            out[key] = OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v
    return out


def command_line_keys() -> set[str]:
    """The keys the command line set (Hydra's task overrides; empty outside a Hydra run)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return set()
    keys = set()
    for o in HydraConfig.get().overrides.task:
        key = o.split("=", 1)[0].lstrip("+~")
        keys.add(key)
    return keys


def apply_budget(cfg: DictConfig, given: set[str] | None = None) -> dict:
    """Apply the ``budget`` preset of ``cfg.budgets`` to ``cfg``: each of its settings (nested
    like the config, e.g. ``{optimizer: {cycles: 10}}``) replaces the config's, except the keys in
    ``given`` (the command line's: what a user sets explicitly wins over the preset). Returns
    the note for metrics.json: ``preset``, ``applied`` (key -> value), ``kept`` (key -> the given
    value where the preset had another)."""
    name = str(cfg.get("budget", "default"))
    presets = cfg.get("budgets") or {}
    if name not in presets:
        raise ValueError(f"budget={name!r}: no such preset (have {', '.join(sorted(presets))}; conf/deform.yaml budgets)")
    given = set() if given is None else given
    applied, kept = {}, {}
    for key, value in _leaves(presets[name] or {}).items():
        if OmegaConf.select(cfg, key, default="__missing__") == "__missing__":
            raise ValueError(f"budgets.{name}: {key} is no setting of dss-deform")
        if key in given:
            kept[key] = OmegaConf.select(cfg, key)
            continue
        OmegaConf.update(cfg, key, value, merge=False)
        applied[key] = value
    return {"preset": name, "applied": applied, "kept": kept}
