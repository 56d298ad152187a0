"""Each app's --help starts with what the command does and its most-used options, and names the
config groups that app reads, not every group under conf/."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from experiments.app_registry import APPS, help_text

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"


def _help(module: str) -> str:
    r = subprocess.run([sys.executable, "-m", module, "--help"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return r.stdout


@pytest.mark.parametrize("module, own, foreign", [
    ("experiments.apps.denoise", ["reference: "], ["model: ", "scene: ", "study: ", "trainer: "]),
    ("experiments.apps.train", ["model: ", "trainer: ", "data: "], ["reference: ", "scene: ", "study: "]),
])
def test_help_lists_only_the_apps_groups(module, own, foreign):
    text = _help(module)
    groups = text.split("== Configuration groups ==")[1].split("== Config ==")[0]
    assert all(g in groups for g in own), groups
    assert not any(g in groups for g in foreign), groups
    assert "== Config ==" in text and "--config-name" in text  # the config and Hydra's flags are still there


def test_help_starts_with_what_the_command_does():
    text = _help("experiments.apps.render")
    head, rest = text.split("Most used", 1)
    assert head.startswith("dss-render: Render a point cloud") and "views=12" in rest.split("== Config ==")[0]
    assert "is powered by Hydra" not in head  # Hydra's header line does not come first


def _keys(node, prefix="") -> set[str]:
    keys = set()
    if isinstance(node, dict):
        for k, v in node.items():
            keys.add(prefix + str(k))
            keys |= _keys(v, f"{prefix}{k}.")
    return keys


@pytest.mark.parametrize("name", sorted(APPS))
def test_every_apps_help_names_five_options_that_exist(name):
    """The paragraph and the most-used options of each app: the options are keys of its config
    (or its config groups), its module runs that config, and its command is that module's."""
    app = APPS[name]
    text = help_text(name)
    assert text.startswith(f"{app.command}: ") and "$CONFIG" in text and "$FLAGS_HELP" in text
    assert len(app.options) == 5
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(name)
    keys = _keys(OmegaConf.to_container(cfg, resolve=False, throw_on_missing=False))
    for option, what in app.options:
        key = option.split("=")[0]
        assert key in keys or (CONF / key).is_dir(), f"{app.command} --help names {key}=, not in conf/{name}.yaml"
        assert what
    source = (ROOT / (app.module.replace(".", "/") + ".py")).read_text()
    assert f'config_name="{name}"' in source
    assert f'{app.command} = "{app.module}:' in (ROOT / "pyproject.toml").read_text()


def test_the_apps_share_one_hydra_block():
    """conf/hydra/default.yaml holds the Hydra settings; no app config repeats them (an app's
    config may only add its own groups' folder to the search path: dss-denoise's
    conf/denoise_parts)."""
    apps = sorted(p.stem for p in CONF.glob("*.yaml"))
    assert apps == sorted(APPS)
    for stem in apps:
        data = yaml.safe_load((CONF / f"{stem}.yaml").read_text())
        assert set(data.get("hydra") or {}) <= {"searchpath"}, f"conf/{stem}.yaml repeats a hydra: block"
        chosen = [e["hydra"] for e in data.get("defaults", []) if isinstance(e, dict) and "hydra" in e]
        assert chosen in (["default"], ["out_dir"]), f"conf/{stem}.yaml: defaults has no hydra: default"
