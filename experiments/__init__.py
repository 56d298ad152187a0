"""The command-line apps, tables, figures and benchmarks built on ``dss``.

Importing the package registers two resolvers the apps' configs use:

- ``dss_help``: ``${dss_help:<config name>}`` is the ``--help`` text of an app
  (:func:`experiments.app_registry.help_text`: what the command does, its most-used options, the
  config groups it reads; Hydra's own template lists every group under ``conf/``, which all apps
  share). ``conf/hydra/default.yaml`` uses it.
- ``dss_fresh``: ``${dss_fresh:<command>}`` is a fresh ``outputs/<command>/<timestamp>`` folder
  (see :mod:`experiments.outputs`), the same path every time it is resolved in one process, so
  that Hydra's run directory and the config's ``out_dir`` agree.
"""

from __future__ import annotations

from pathlib import Path


def _register() -> None:
    try:
        from omegaconf import OmegaConf
    except ImportError:  # the benchmarks and figures run without omegaconf too
        return

    def resolve(config_name):
        from experiments.app_registry import help_text

        return help_text(str(config_name))

    if not OmegaConf.has_resolver("dss_help"):
        OmegaConf.register_new_resolver("dss_help", resolve)
    if not OmegaConf.has_resolver("dss_fresh"):
        OmegaConf.register_new_resolver("dss_fresh", _fresh)


_FRESH: dict[str, str] = {}


def _fresh(command) -> str:
    """A not yet existing ``outputs/<command>/<timestamp>[_n]`` (created by whoever writes to it);
    the first answer is kept for the process."""
    import time

    command = str(command)
    if command not in _FRESH:
        base = Path("outputs") / command / time.strftime("%Y-%m-%d_%H-%M-%S")
        path, n = base, 1
        while path.exists():
            n += 1
            path = base.with_name(f"{base.name}_{n}")
        _FRESH[command] = str(path)
    return _FRESH[command]


_register()
