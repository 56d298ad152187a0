"""Each app's --help names the config groups that app reads, not every group under conf/."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


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
