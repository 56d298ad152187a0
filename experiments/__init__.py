"""The command-line apps, tables, figures and benchmarks built on ``dss``.

Importing the package registers two resolvers the apps' configs use:

- ``dss_help``: the ``--help`` text. Hydra's own template lists every config group under
  ``conf/``, which all apps share, so ``dss-denoise --help`` would offer ``model=`` and ``scene=``
  that it does not read.
- ``dss_fresh``: ``${dss_fresh:<command>}`` is a fresh ``outputs/<command>/<timestamp>`` folder
  (see :mod:`experiments.outputs`), the same path every time it is resolved in one process, so
  that Hydra's run directory and the config's ``out_dir`` agree.
"""

from __future__ import annotations

from pathlib import Path

_CONF = Path(__file__).resolve().parent.parent / "conf"


def _help_template(*groups: str) -> str:
    """The body of an app's Hydra help (``string.Template``: ``$FLAGS_HELP``, ``$CONFIG``), naming
    only ``groups``; the config wraps it in Hydra's header and footer."""
    lines = []
    if groups:
        lines += ["== Configuration groups ==", "Compose your configuration from these groups (group=option)"]
        lines.append("")
        for g in groups:
            options = sorted(p.stem for p in (_CONF / g).glob("*.yaml"))
            lines.append(f"{g}: {', '.join(options)}")
        lines.append("")
    lines += ["== Config ==", "Override anything in the config (foo.bar=value)", "", "$CONFIG", "",
              "== Flags ==", "$FLAGS_HELP"]
    return "\n".join(lines)


def _register() -> None:
    try:
        from omegaconf import OmegaConf
    except ImportError:  # the benchmarks and figures run without omegaconf too
        return

    def resolve(*groups):
        return _help_template(*(str(g) for g in groups))

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
