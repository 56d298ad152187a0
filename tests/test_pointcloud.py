import numpy as np
import pytest
import torch
from scenes import sphere_points

from dss.pointcloud import (
    PointCloud,
    PointCloudError,
    add_gaussian_noise,
    all_finite,
    bbox_diagonal,
    estimate_normals,
    load_ply,
    normalize_unit_diagonal,
    save_ply,
)


def _write_ascii_ply(path, pts, normals=None):
    """Binary little-endian PLY written by hand (so NaN and inf rows can be stored)."""
    props = "property float x\nproperty float y\nproperty float z\n"
    rows = np.asarray(pts, np.float32)
    if normals is not None:
        props += "property float nx\nproperty float ny\nproperty float nz\n"
        rows = np.concatenate([rows, np.asarray(normals, np.float32)], 1)
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(rows)}\n{props}end_header\n"
    path.write_bytes(header.encode() + rows.astype("<f4").tobytes())


def test_roundtrip_with_normals_and_colors(tmp_path):
    p, n = sphere_points(500)
    c = torch.rand(500, 3)
    save_ply(tmp_path / "a.ply", PointCloud(p, n, c))
    back = load_ply(tmp_path / "a.ply")
    assert torch.allclose(back.points, p, atol=1e-6)
    assert torch.allclose(back.normals, n, atol=1e-5)
    assert torch.allclose(back.colors, c, atol=1 / 255 + 1e-6)


def test_missing_file_is_named(tmp_path):
    with pytest.raises(PointCloudError, match="nope.ply: no such file"):
        load_ply(tmp_path / "nope.ply")


def test_malformed_file(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_text("this is not a point cloud\n")
    with pytest.raises(PointCloudError, match="bad.ply"):
        load_ply(bad)


def test_empty_cloud(tmp_path):
    f = tmp_path / "empty.ply"
    _write_ascii_ply(f, np.zeros((0, 3)))
    with pytest.raises(PointCloudError, match="empty.ply.*no points"):
        load_ply(f)
    with pytest.raises(PointCloudError, match="empty"):
        save_ply(tmp_path / "x.ply", PointCloud(torch.zeros(0, 3)))


def test_nan_rows_dropped_or_refused(tmp_path, caplog):
    p, n = sphere_points(100)
    pts = p.numpy().copy()
    pts[3, 1] = np.nan
    pts[7, 0] = np.inf
    f = tmp_path / "nan.ply"
    _write_ascii_ply(f, pts, n.numpy())
    with caplog.at_level("WARNING"):
        c = load_ply(f)
    assert len(c) == 98
    assert "2 of 100 rows" in caplog.text and "nan.ply" in caplog.text
    with pytest.raises(PointCloudError, match="nan.ply: 2 of 100 rows hold NaN/inf.*refusing"):
        load_ply(f, nan_policy="raise")


def test_missing_normals_are_computed_and_oriented(tmp_path):
    p, n = sphere_points(2000)
    f = tmp_path / "nonormals.ply"
    _write_ascii_ply(f, p.numpy())
    c = load_ply(f)
    cos = (c.normals * n).sum(1)
    assert (cos > 0.95).float().mean() > 0.99  # outward and accurate
    c2 = load_ply(f, compute_normals=False)
    assert c2.normals is None


def test_estimate_normals_consistent_on_torus():
    # A torus is not star-shaped around its centroid: orientation must come from propagation.
    u, v = torch.meshgrid(torch.linspace(0, 6.283, 80)[:-1], torch.linspace(0, 6.283, 40)[:-1], indexing="ij")
    R, r = 1.0, 0.35
    pts = torch.stack([(R + r * torch.cos(v)) * torch.cos(u), (R + r * torch.cos(v)) * torch.sin(u), r * torch.sin(v)], -1).reshape(-1, 3)
    true_n = torch.stack([torch.cos(v) * torch.cos(u), torch.cos(v) * torch.sin(u), torch.sin(v)], -1).reshape(-1, 3)
    est = estimate_normals(pts, k=12)
    agree = (est * true_n).sum(1)
    assert (agree > 0.9).float().mean() > 0.97 or (agree < -0.9).float().mean() > 0.97


def test_bbox_normalize_noise():
    p = torch.tensor([[0.0, 0, 0], [3.0, 4.0, 0.0]])
    assert bbox_diagonal(p) == pytest.approx(5.0)
    q, c, s = normalize_unit_diagonal(p)
    assert bbox_diagonal(q) == pytest.approx(1.0)
    assert torch.allclose(c, torch.tensor([1.5, 2.0, 0.0]))
    pts, _ = sphere_points(20000)
    noisy = add_gaussian_noise(pts, 0.01, seed=3)
    std = (noisy - pts).std().item()
    assert std == pytest.approx(0.01 * bbox_diagonal(pts), rel=0.03)
    assert torch.equal(noisy, add_gaussian_noise(pts, 0.01, seed=3))
    with pytest.raises(ValueError, match=">= 0"):
        add_gaussian_noise(pts, -0.1)


def _noisy_sphere(n: int, noise: float, seed: int) -> torch.Tensor:
    """n points on the unit sphere plus Gaussian noise of std ``noise`` x the bbox diagonal."""
    return add_gaussian_noise(sphere_points(n)[0], noise, seed=seed)


def test_find_outliers_takes_the_sparse_gas_and_spares_the_surface():
    from dss.pointcloud import find_outliers

    surface = _noisy_sphere(6000, 0.01, seed=1)
    g = torch.Generator().manual_seed(2)
    gas = torch.rand(600, 3, generator=g) * 2.4 - 1.2  # 10% uniform in the bounding box
    far = (gas.norm(dim=1) - 1).abs() > 0.15            # the ones clearly off the surface
    gas = gas[far]
    flagged = find_outliers(torch.cat([surface, gas]))
    assert flagged[len(surface):].float().mean() > 0.9, "most far-off points must go"
    assert flagged[: len(surface)].float().mean() < 0.002, "surface samples must stay"
    # a single point hovering over the surface (11 noise sigmas out): the local test alone sees it
    lone = torch.tensor([[0.0, 0.0, 1.4]])
    flagged = find_outliers(torch.cat([surface, lone]), z_threshold=1e9)
    assert bool(flagged[-1]) and int(flagged.sum()) <= 6
    # the dense gas is invisible to the local test alone (its points are each other's neighbours)
    assert find_outliers(torch.cat([surface, gas]), z_threshold=1e9)[len(surface):].float().mean() < 0.5


def test_find_outliers_keeps_a_clean_or_small_cloud_and_checks_arguments():
    from dss.pointcloud import find_outliers

    clean = _noisy_sphere(4000, 0.0, seed=0)
    assert int(find_outliers(clean).sum()) == 0
    assert int(find_outliers(clean[:10], k=16).sum()) == 0  # too few points to judge: nothing flagged
    for bad in ({"k": 0}, {"z_threshold": 0.0}, {"ratio_threshold": -1.0}, {"iterations": 0}):
        with pytest.raises(ValueError, match="outlier"):
            find_outliers(clean, **bad)


def test_all_finite_agrees_with_the_elementwise_test():
    """The sum's shortcut never changes the answer: NaN and inf anywhere are found, and finite
    values whose sum overflows (the shortcut cannot decide) still count as finite."""
    x = torch.randn(1000, 3)
    assert all_finite(x, x.double(), torch.arange(6).view(2, 3), torch.empty(0, 3))
    for bad in (float("nan"), float("inf"), -float("inf")):
        y = x.clone()
        y[517, 2] = bad
        assert not all_finite(x, y)
    huge = torch.full((4, 3), 3e38)  # float32 sum overflows to inf
    assert not torch.isfinite(huge.sum()) and all_finite(huge)
    both = x.clone()
    both[0, 0], both[1, 0] = float("inf"), -float("inf")  # sum NaN
    assert not all_finite(both)


def test_truncated_binary_ply_is_refused_by_name(tmp_path):
    """A binary PLY cut short must not come back as points at the origin."""
    from dss.metrics import load_points

    p, _ = sphere_points(3000)
    full = tmp_path / "full.ply"
    save_ply(full, PointCloud(p))
    data = full.read_bytes()
    cut = tmp_path / "cut.ply"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(PointCloudError, match=r"cut\.ply: truncated: the header declares 3000 vertices"):
        load_ply(cut, compute_normals=False)
    with pytest.raises(ValueError, match=r"cut\.ply: truncated"):
        load_points(cut)
    assert torch.allclose(load_ply(full, compute_normals=False).points, p)


def test_ascii_ply_inf_and_nan_tokens_follow_nan_policy(tmp_path):
    """ASCII tokens inf/nan are read as values (not the end of the data) and handled by nan_policy;
    an ASCII body with fewer rows than the header declares is refused."""
    p, _ = sphere_points(3000)
    save_ply(tmp_path / "a.ply", PointCloud(p), ascii=True)
    lines = (tmp_path / "a.ply").read_text().splitlines()
    body = lines.index("end_header") + 1
    lines[body + 9] = "inf 0 0"
    lines[body + 20] = "0 nan 1"
    f = tmp_path / "tokens.ply"
    f.write_text("\n".join(lines) + "\n")
    c = load_ply(f, compute_normals=False)
    assert len(c) == 2998
    assert int((c.points.abs().sum(1) == 0).sum()) == 0  # no row became the origin
    keep = np.ones(3000, bool)
    keep[[9, 20]] = False
    assert np.allclose(c.points.numpy(), p.numpy()[keep], atol=1e-5)
    with pytest.raises(PointCloudError, match=r"tokens\.ply: 2 of 3000 rows hold NaN/inf.*refusing"):
        load_ply(f, nan_policy="raise")
    short = tmp_path / "short.ply"
    short.write_text("\n".join(lines[: body + 100]) + "\n")
    with pytest.raises(PointCloudError, match=r"short\.ply: truncated: the header declares 3000 vertices, the file holds 100 rows"):
        load_ply(short, compute_normals=False)
