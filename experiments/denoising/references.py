"""The job's reference generator, made from the ``reference`` block of its config
(``conf/reference/``; the generators are in :mod:`experiments.denoising.reference_generators`)."""

from __future__ import annotations

import logging

from omegaconf import DictConfig, open_dict

log = logging.getLogger(__name__)

__all__ = ["make_reference", "explicit_model", "given_reference", "warn_noise_mismatch"]


def explicit_model(cfg: DictConfig) -> bool:
    """Whether the reference names its model file (checked before any work) rather than ``auto``."""
    node = cfg.reference
    return "model" in node and node.model not in (None, "auto")


def make_reference(cfg: DictConfig, noise: float | None):
    """Instantiate ``cfg.reference``; an ``onnx`` generator with ``model: auto`` gets the shipped
    model for ``noise``; ``reference=auto`` (conf/reference/auto.yaml) the table's entry for
    ``noise``, whose fusion settings are written into ``cfg.fusion``. Returns (generator, model
    selection note)."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    from experiments.denoising.reference_generators import select_model

    node = cfg.reference
    note = None
    kwargs = {}
    if "model" in node and (node.model in (None, "auto")):
        if noise is None:
            raise ValueError("reference.model=auto needs a noise level (noise=... or the estimate)")
        path, level = select_model(noise)
        kwargs["model"] = str(path)
        note = f"shipped model for noise {level:g} ({path.name}), chosen for noise {noise:.4g}"
    try:
        generator = instantiate(node, **kwargs)
    except InstantiationException as e:
        # Hydra wraps the generator's own (clear) error; show that one to the user.
        if isinstance(e.__cause__, Exception):
            raise e.__cause__ from None
        raise
    if hasattr(generator, "resolve_for_noise"):  # reference=auto: the table's entry for this noise level
        if noise is None:
            raise ValueError("reference=auto needs a noise level (noise=... or the estimate)")
        generator, note, fusion = generator.resolve_for_noise(noise)
        if fusion:  # the entry's fusion settings, before the job's settings are resolved
            with open_dict(cfg):
                for k, v in fusion.items():
                    cfg.fusion[k] = v
    return generator, note


def given_reference(cfg: DictConfig):
    """(generator, note) of a reference that names its model file, made at once so that a bad
    file is refused before any work; None for the others (made once the noise level is known)."""
    return make_reference(cfg, None) if explicit_model(cfg) else None


def warn_noise_mismatch(generator, noise: float, hinted: bool) -> None:
    """Log a warning when ``generator`` was trained for a noise level far from ``noise``."""
    if generator.noise_level and not 0.5 < noise / generator.noise_level < 2.0:
        log.warning("the denoiser was trained for noise %.3g but this cloud's noise is %s %.3g: results may be poor",
                    generator.noise_level, "given as" if hinted else "estimated at", noise)
