"""Shared pytest fixtures: deterministic seeds and small scenes."""

from __future__ import annotations

import os

import pytest
import torch

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    yield


@pytest.fixture(scope="session")
def cpp_backend():
    """'cpp' when the C++ kernel builds here; the tests that need it fail loudly otherwise."""
    from dss import _ext

    if not _ext.cpu_available():
        pytest.fail(f"the C++ kernel did not build: {_ext.build_error()}")
    return "cpp"
