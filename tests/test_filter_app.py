"""dss-filter: image-filter geometry editing (L0, SLIC) on clean and noisy input (fast)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from data_prep.sampling import poisson_disk
from data_prep.shapes import make_shape
from dss.ply import write_ply
from dss.pointcloud import PointCloud, load_ply, save_ply

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
torch.set_num_threads(1)


def compose_cfg(overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("filter", overrides=overrides)


@pytest.fixture(scope="module")
def cloud_file(tmp_path_factory) -> Path:
    """2K clean points with normals on a generated superquadric (grooves: detail to flatten)."""
    mesh = make_shape("superquadric", seed=4, resolution=48)
    c = poisson_disk(mesh, 2000, seed=4)
    path = tmp_path_factory.mktemp("filter") / "clean.ply"
    write_ply(path, c.points, normals=c.normals)
    return path


def overrides(cloud_file: Path, out: Path, *extra: str) -> list[str]:
    return [f"input={cloud_file}", f"out_dir={out}", "image_size=64", "optimizer.cycles=2", "figures.views=2",
            "figures.image_size=48", "progress=false", *extra]


def test_l0_filter_edits_clean_input(cloud_file, tmp_path):
    from experiments.apps.filter import run

    out = tmp_path / "l0"
    m = run(compose_cfg(overrides(cloud_file, out)))
    for f in ("filtered.ply", "before_after.png", "references.png", "loss.png", "loss.json", "metrics.json",
              "config.yaml"):
        assert (out / f).is_file(), f
    assert json.loads((out / "metrics.json").read_text())["change"] == m["change"]
    # the references are piecewise constant: sparser gradients than the renders they came from
    sp = m["gradient_sparsity"]
    assert sp["references"] > sp["input_renders"]
    # the geometry changed (normals turned towards the flat shading), but stayed a close copy
    assert m["change"]["normal_change_deg"]["mean"] > 1.0
    assert 0 < m["change"]["chamfer_to_input_paper_x1e4"] < 1.0
    res = load_ply(out / "filtered.ply")
    assert len(res) == 2000 and torch.isfinite(res.points).all()
    assert m["reference"]["name"] == "l0" and m["shading"] == "sun" and m["steps"] == 40
    assert m["input"]["normals"] == "from file" and not m["summary"]["output"]  # no ground truth given


def test_slic_filter_on_noisy_input_with_ground_truth(cloud_file, tmp_path):
    from experiments.apps.filter import run

    out = tmp_path / "slic"
    m = run(compose_cfg(overrides(cloud_file, out, "reference=slic", "reference.n_segments=40", "noise=0.01",
                                  f"clean={cloud_file}", "optimizer.cycles=1", "optimizer.normal_steps=4")))
    assert m["input"]["added_noise"] == 0.01 and m["input"]["normals"].startswith("estimated after adding noise")
    assert m["reference"] == {"name": "slic", "n_segments": 40, "compactness": 20.0, "enforce_connectivity": False}
    for pr in ("paper", "score"):
        assert m["summary"]["input"][pr]["chamfer"] > 0 and m["summary"]["output"][pr]["chamfer"] > 0
    assert m["steps"] == 5 and (out / "filtered.ply").is_file()


def test_filter_refusals(cloud_file, tmp_path):
    from experiments.apps.filter import run
    from experiments.common import OutputExistsError

    target = tmp_path / "taken.ply"
    save_ply(target, PointCloud(torch.arange(12.0).view(4, 3)))
    before = target.read_bytes()
    with pytest.raises(OutputExistsError, match=r"taken\.ply already exists"):
        run(compose_cfg(overrides(cloud_file, tmp_path / "a", f"output={target}")))
    assert target.read_bytes() == before
    with pytest.raises(ValueError, match="dss-filter takes an image filter"):
        run(compose_cfg(overrides(cloud_file, tmp_path / "b", "reference=onnx")))
    with pytest.raises(ValueError, match="noise must be >= 0"):
        run(compose_cfg(overrides(cloud_file, tmp_path / "c", "noise=-0.1")))
    with pytest.raises(ValueError, match="shading must be"):
        run(compose_cfg(overrides(cloud_file, tmp_path / "d", "shading=phong")))
    for sub in ("a", "b", "c", "d"):
        assert not list((tmp_path / sub).glob("*.ply")) if (tmp_path / sub).exists() else True
    # the edited cloud replaces an existing file only with overwrite=true
    m = run(compose_cfg(overrides(cloud_file, tmp_path / "e", f"output={target}", "overwrite=true",
                                  "optimizer.cycles=1", "optimizer.normal_steps=1")))
    assert m["output"] == str(target) and len(load_ply(target)) == 2000
    assert np.isfinite(m["time_s"]["total"])
