"""Clouds far from the origin (georeferenced scans): loaded, denoised, rendered and written back
in their own coordinates, to the precision they came in (fast)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from dss.pointcloud import PointCloudError, load_ply, save_ply

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
EXAMPLE = Path(__file__).resolve().parents[1] / "experiments" / "assets" / "example"
torch.set_num_threads(1)


def _write_double(path: Path, points: np.ndarray) -> Path:
    """A binary PLY with double coordinates (as georeferenced scans are stored)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = np.ascontiguousarray(points, "<f8")
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(rows)}\nproperty double x\n"
              "property double y\nproperty double z\nend_header\n")
    path.write_bytes(header.encode() + rows.tobytes())
    return path


def _write_float(path: Path, points: np.ndarray) -> Path:
    rows = np.ascontiguousarray(points, "<f4")
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(rows)}\nproperty float x\n"
              "property float y\nproperty float z\nend_header\n")
    path.write_bytes(header.encode() + rows.tobytes())
    return path


@pytest.fixture(scope="module")
def small_case():
    """3,000 points of the shipped example's clean surface and a 1% noisy copy (float64)."""
    clean = load_ply(EXAMPLE / "clean.ply", compute_normals=False).points.numpy().astype(np.float64)[::7][:3000]
    diag = np.linalg.norm(clean.max(0) - clean.min(0))
    noisy = clean + np.random.default_rng(0).normal(size=clean.shape) * 0.01 * diag
    return clean, noisy


def _denoise(case, offset: float, seed: int, root: Path) -> tuple[float, dict]:
    """One short dss-denoise run on the case shifted by ``offset``: (Chamfer of the written file
    against the clean cloud, both read back in float64, metrics)."""
    from dss.metrics import evaluate, load_points
    from experiments.apps.denoise import run
    from experiments.common import release_claims

    clean, noisy = case
    d = root / f"off{offset:g}_seed{seed}"
    _write_double(d / "noisy.ply", noisy + offset)
    _write_double(d / "clean.ply", clean + offset)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("denoise", [f"input={d / 'noisy.ply'}", f"clean={d / 'clean.ply'}", f"out_dir={d / 'run'}",
                                  "reference=l0", "image_size=32", "optimizer.cycles=1", "optimizer.normal_steps=2",
                                  "figures.enabled=false", "progress=false", "metrics.floor=false",
                                  "metrics.protocols=[paper]", "optimizer.final_projection_k=8", f"seed={seed}"])
    m = run(cfg)
    release_claims()
    out = load_points(m["output"])
    return evaluate(out, clean + offset).chamfer, m


def test_an_offset_of_1e6_or_1e8_gives_the_result_at_the_origin(small_case, tmp_path):
    """The same 3,000-point cloud at the origin and shifted by 1e6 and 1e8 (stored as doubles):
    the denoised files, read back in their own coordinates, score as the origin's result does,
    within the spread of two seeds at the origin, and the outputs are written as doubles."""
    c0, m0 = _denoise(small_case, 0.0, 0, tmp_path)
    c1, _ = _denoise(small_case, 0.0, 1, tmp_path)
    spread = abs(c0 - c1)
    # a double input is written as doubles, at the origin too
    assert "property double x" in Path(m0["output"]).read_bytes()[:300].decode("ascii", errors="replace")
    for offset in (1e6, 1e8):
        c, m = _denoise(small_case, offset, 0, tmp_path)
        assert abs(c - c0) <= spread, (offset, c, c0, spread)
        assert m0["input"]["offset"] is None
        assert m["input"]["offset"] == pytest.approx([offset] * 3, abs=1.0)
        assert m["summary"]["input"]["paper"]["chamfer"] == pytest.approx(m0["summary"]["input"]["paper"]["chamfer"],
                                                                          rel=1e-6)
        header = Path(m["output"]).read_bytes()[:300].decode("ascii", errors="replace")
        assert "property double x" in header
        back = load_ply(m["output"], compute_normals=False)  # centred again, the offset kept
        assert back.offset is not None and float(back.offset.max()) == pytest.approx(offset, rel=1e-6)


def test_load_ply_centres_in_float64_and_save_ply_writes_the_input_frame_back(tmp_path):
    p = np.random.default_rng(1).normal(size=(500, 3))
    from dss.metrics import load_points

    for offset in (1e6, 1e8):
        f = _write_double(tmp_path / f"far{offset:g}.ply", p + offset)
        c = load_ply(f, compute_normals=False)
        save_ply(tmp_path / "back.ply", c)
        # relative detail survives the round trip: float32 alone holds 1e8 to 8 units
        assert np.abs(load_points(tmp_path / "back.ply") - (p + offset)).max() < 1e-6
        assert np.abs(c.coordinates() - (p + offset)).max() < 1e-6
        assert c.offset is not None
    near = load_ply(_write_double(tmp_path / "near.ply", p), compute_normals=False)
    assert near.offset is None and torch.equal(near.points, torch.from_numpy(p.astype(np.float32)))


def test_identical_points_and_collapsed_float32_clouds_name_the_cause(tmp_path):
    """All points identical, and a float32 file at 1e8 where a small cloud collapses: refused with
    the cause (not 'cannot estimate noise of an empty or zero-size point set')."""
    from experiments.apps.denoise import run
    from experiments.common import release_claims

    same = _write_float(tmp_path / "same.ply", np.full((300, 3), 0.25))
    with pytest.raises(PointCloudError, match=r"same\.ply: all 300 points are identical"):
        load_ply(same)
    p = np.random.default_rng(2).normal(size=(3000, 3)) * 0.3
    collapsed = _write_float(tmp_path / "f32_1e8.ply", p + 1e8)
    with pytest.raises(PointCloudError, match=r"f32_1e8\.ply: all 3000 points are identical .*float32 coordinates "
                                              r"there are 8 apart.*store the coordinates as double"):
        load_ply(collapsed)
    lattice = _write_float(tmp_path / "f32_1e6.ply", p + 1e6)
    with pytest.raises(PointCloudError, match=r"f32_1e6\.ply: the coordinates are float32 values up to 1e\+06, "
                                              r"which are 0\.0625 apart there.*store the coordinates as double"):
        load_ply(lattice)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("denoise", [f"input={same}", f"out_dir={tmp_path / 'run'}", "reference=l0", "progress=false"])
    with pytest.raises(PointCloudError, match=r"all 300 points are identical"):
        run(cfg)
    release_claims()
    from dss.pipeline import estimate_noise_level

    with pytest.raises(ValueError, match=r"all 300 points coincide"):
        estimate_noise_level(np.full((300, 3), 5.0))


def test_render_and_deform_of_a_far_cloud_match_the_cloud_at_the_origin(tmp_path):
    """dss-render draws the same images at 1e6 as at the origin (no lattice), and dss-deform's
    target at 1e6 is the origin's, so the deformation is the same."""
    import matplotlib.image
    from scenes import sphere_points

    from experiments.apps.render import run as render_run
    from experiments.common import release_claims
    from experiments.deformation.inputs import load_target

    p, n = sphere_points(800, 0.4)
    p = p.double().numpy()
    rows = np.concatenate([p, n.numpy().astype(np.float64)], 1)
    for name, off in (("near", 0.0), ("far", 1e6)):
        q = rows.copy()
        q[:, :3] += off
        header = ("ply\nformat binary_little_endian 1.0\nelement vertex 800\n"
                  + "".join(f"property double {c}\n" for c in ("x", "y", "z")) + "property float nx\nproperty float ny\n"
                  "property float nz\nend_header\n")
        rec = np.empty(800, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")])
        for j, c in enumerate(("x", "y", "z", "nx", "ny", "nz")):
            rec[c] = q[:, j]
        (tmp_path / f"{name}.ply").write_bytes(header.encode() + rec.tobytes())
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose("render_cloud", [f"input={tmp_path / f'{name}.ply'}", "views=2", "image_size=32",
                                           f"+out_dir={tmp_path / name}"])
        render_run(cfg)
        release_claims()
    a = matplotlib.image.imread(tmp_path / "near" / "sun.png")
    b = matplotlib.image.imread(tmp_path / "far" / "sun.png")
    assert np.abs(a - b).max() < 0.02
    near, far = load_target(str(tmp_path / "near.ply"), 100), load_target(str(tmp_path / "far.ply"), 100)
    assert far.offset is not None
    assert np.abs(far.coordinates() - near.coordinates() - 1e6).max() < 1e-6
    assert bool((far.points.std(0) > 0.1).all())  # a sphere, not a few lattice positions
