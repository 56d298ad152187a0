"""The apps under bad input and faults: scale, claimed outputs, errors for people (fast)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from scenes import sphere_points

from dss.pointcloud import PointCloud, save_ply

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
torch.set_num_threads(1)


def compose_cfg(name: str, overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(name, overrides=overrides)


def render_cfg(cloud: Path, out: Path, *extra: str):
    return compose_cfg("render_cloud", [f"input={cloud}", "views=2", "image_size=32", f"+out_dir={out}", *extra])


@pytest.fixture(scope="module")
def sphere_ply(tmp_path_factory) -> Path:
    p, n = sphere_points(800, 0.4)
    path = tmp_path_factory.mktemp("cloud") / "sphere.ply"
    save_ply(path, PointCloud(p, n))
    return path


# ------------------------------------------------------------------------------- scale
def test_render_of_a_tiny_cloud_in_its_own_units_matches_the_unit_scale_one(sphere_ply, tmp_path):
    """A cloud 1e-6 across with normalize=false renders as the unit-scale one (not all white)."""
    import matplotlib.image

    from dss.pointcloud import load_ply
    from experiments.render import run

    c = load_ply(sphere_ply)
    small = tmp_path / "small.ply"
    save_ply(small, PointCloud(c.points * 1e-6, c.normals))
    m1 = run(render_cfg(sphere_ply, tmp_path / "unit"))
    ms = run(render_cfg(small, tmp_path / "small", "normalize=false"))
    assert m1["coverage"] > 0.05
    assert ms["coverage"] == pytest.approx(m1["coverage"], abs=1e-3)
    a = matplotlib.image.imread(tmp_path / "unit" / "sun.png")
    b = matplotlib.image.imread(tmp_path / "small" / "sun.png")
    assert np.abs(a - b).max() < 0.02
    assert ms["camera_distance"] == pytest.approx(m1["camera_distance"] * float(np.linalg.norm(
        (c.points.max(0).values - c.points.min(0).values).numpy())) * 1e-6, rel=1e-3)
