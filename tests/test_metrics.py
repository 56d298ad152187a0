"""dss.metrics on hand-made cases (fast)."""

import json
import os

import numpy as np
import pytest
import torch

from dss import metrics as M

SHARED_MESH = os.path.join(
    os.path.dirname(__file__), "..", "..", "shared", "data", "Kangaroo_V10k.ply"
)


def _cube_cloud(n=500, seed=0):
    rng = np.random.default_rng(seed)
    return rng.random((n, 3)) * np.array([2.0, 1.0, 0.5]) + np.array([3.0, -1.0, 7.0])


def _tetra_mesh():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return v, f


@pytest.mark.parametrize("protocol", M.PROTOCOLS)
def test_identical_clouds_score_zero(protocol):
    c = _cube_cloud()
    r = M.evaluate(c.copy(), c, protocol=protocol)
    assert r.protocol == protocol
    assert r.chamfer == 0 and r.hausdorff == 0 and r.hausdorff_dss_script == 0
    # torch input gives the same
    r2 = M.evaluate(torch.from_numpy(c).float(), torch.from_numpy(c).float(), protocol=protocol)
    assert r2.chamfer < 1e-6


def test_normalisation_paper_and_score():
    c = _cube_cloud()
    n = M.compute_normalization(c, "paper")
    cn = n.apply(c)
    lo, hi = cn.min(0), cn.max(0)
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-12)
    assert np.linalg.norm(hi - lo) == pytest.approx(1.0)
    s = M.compute_normalization(c, "score")
    cs = s.apply(c)
    np.testing.assert_allclose((cs.min(0) + cs.max(0)) / 2, 0, atol=1e-12)
    assert np.linalg.norm(cs, axis=1).max() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="protocol"):
        M.compute_normalization(c, "nope")


@pytest.mark.parametrize("protocol", M.PROTOCOLS)
def test_shifted_cloud_gives_shift_squared(protocol):
    # a grid with spacing 1 shifted by 0.1 along x: every nearest neighbour is the shifted
    # copy of the same point (0.1 < 0.5 spacing) so each one-sided term is the shift squared
    g = np.stack(
        np.meshgrid(np.arange(6.0), np.arange(5.0), np.arange(4.0), indexing="ij"), -1
    ).reshape(-1, 3)
    shift = 0.1
    p = g + np.array([shift, 0.0, 0.0])
    r = M.evaluate(p, g, protocol=protocol)
    s = M.compute_normalization(g, protocol).scale
    expected_sq = (shift * s) ** 2
    assert r.chamfer_pred_to_gt == pytest.approx(expected_sq * 1e4, rel=1e-9)
    assert r.chamfer_gt_to_pred == pytest.approx(expected_sq * 1e4, rel=1e-9)
    assert r.chamfer == pytest.approx(2 * expected_sq * 1e4, rel=1e-9)
    assert r.hausdorff == pytest.approx(shift * s * 1e3, rel=1e-9)
    # the official DSS script's quantity: sum of the squared one-sided maxima
    assert r.hausdorff_dss_script == pytest.approx(2 * (shift * s) ** 2 * 1e3, rel=1e-9)
    assert r.scale_factors["chamfer"] == 1e4 and r.scale_factors["hausdorff"] == 1e3


def test_hand_computed_two_points():
    # C = {(0,0,0), (1,0,0)}: paper scale 1 (diagonal 1), centre (0.5,0,0)
    c = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    p = np.array([[0.0, 0.3, 0], [1.0, 0, 0.0], [2.0, 0, 0]])
    r = M.evaluate(p, c, protocol="paper")
    # P->C: 0.09, 0, 1 -> mean 1.09/3 ; C->P: 0.09, 0 -> mean 0.045
    assert r.chamfer_pred_to_gt == pytest.approx(1.09 / 3 * 1e4)
    assert r.chamfer_gt_to_pred == pytest.approx(0.045 * 1e4)
    assert r.chamfer == pytest.approx((1.09 / 3 + 0.045) * 1e4)
    assert r.hausdorff == pytest.approx(1.0 * 1e3)  # (2,0,0) is 1 from C
    assert r.hausdorff_gt_to_pred == pytest.approx(0.3 * 1e3)
    # score protocol: farthest point of C from the bbox centre at 0.5 -> scale 2
    rs = M.evaluate(p, c, protocol="score")
    assert rs.chamfer == pytest.approx(4 * (1.09 / 3 + 0.045) * 1e4)
    assert rs.hausdorff == pytest.approx(2.0 * 1e3)


def test_point_triangle_distance_cases():
    v0, v1, v2 = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])
    pts = np.array(
        [
            [0.2, 0.2, 0.5],  # above the interior: plane distance 0.5
            [-1.0, -1.0, 0.0],  # vertex region: distance to (0,0,0) = sqrt 2
            [0.5, -2.0, 0.0],  # edge region: distance 2 to edge v0-v1
            [1.0, 1.0, 0.0],  # beyond the hypotenuse: distance to (0.5,0.5) = sqrt(0.5)
        ]
    )
    k = len(pts)
    d = M.point_triangle_sq(pts, np.repeat(v0, k, 0), np.repeat(v1, k, 0), np.repeat(v2, k, 0))
    np.testing.assert_allclose(d, [0.25, 2.0, 4.0, 0.5], atol=1e-12)
    # PyTorch3D emulation: a triangle below min_triangle_area counts as its edges only
    d_small = M.point_triangle_sq(pts[:1], v0, v1, v2, min_triangle_area=1.0)
    assert d_small[0] == pytest.approx(0.2**2 + 0.5**2)
    # degenerate triangle (all on a line) does not divide by zero
    d_deg = M.point_triangle_sq(np.array([[0.5, 1.0, 0]]), v0, v1, np.array([[2.0, 0, 0]]))
    assert d_deg[0] == pytest.approx(1.0)


def test_point_to_mesh_of_vertices_is_zero_and_brute_force():
    v, f = _tetra_mesh()
    r = M.evaluate(v, v, mesh=(v, f), protocol="score")
    assert r.point_to_mesh == pytest.approx(0.0, abs=1e-9)
    assert r.p2m == pytest.approx(r.point_to_mesh + r.mesh_to_point)
    assert r.n_faces == 4
    # random points vs a random mesh: both terms equal the brute-force minima
    rng = np.random.default_rng(1)
    verts = rng.normal(size=(30, 3))
    faces = np.array([rng.choice(30, 3, replace=False) for _ in range(60)])
    pts = rng.normal(size=(200, 3)) * 1.3
    tv = verts[faces]
    P = np.repeat(pts, len(faces), 0)
    T = np.tile(tv, (len(pts), 1, 1))
    D = M.point_triangle_sq(P, T[:, 0], T[:, 1], T[:, 2]).reshape(len(pts), len(faces))
    np.testing.assert_allclose(
        M.point_to_mesh_sq(pts, verts, faces), D.min(1), rtol=1e-9, atol=1e-12
    )
    np.testing.assert_allclose(
        M.mesh_to_point_sq(pts, verts, faces, k=2, chunk=17), D.min(0), rtol=1e-9, atol=1e-12
    )
    De = M.point_triangle_sq(P, T[:, 0], T[:, 1], T[:, 2], 0.5).reshape(len(pts), len(faces))
    np.testing.assert_allclose(
        M.point_to_mesh_sq(pts, verts, faces, 0.5), De.min(1), rtol=1e-9, atol=1e-12
    )
    np.testing.assert_allclose(
        M.mesh_to_point_sq(pts, verts, faces, 0.5), De.min(0), rtol=1e-9, atol=1e-12
    )


def test_mesh_term_uses_triangle_distance_not_centroid():
    # one big triangle and a single point at one of its corners: point->triangle is 0 and
    # so is triangle->point (a centroid-based shortcut would give a positive value)
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    f = np.array([[0, 1, 2]])
    p = np.array([[0.0, 0, 0]])
    assert M.mesh_to_point_sq(p, v, f)[0] == pytest.approx(0.0)
    assert M.point_to_mesh_sq(p + [0, 0, 0.5], v, f)[0] == pytest.approx(0.25, rel=1e-6)


def test_result_to_dict_is_json_and_names_protocol():
    c = _cube_cloud()
    d = M.evaluate(c + 0.01, c, protocol="paper").to_dict()
    s = json.loads(json.dumps(d))
    assert s["protocol"] == "paper" and s["units"]["chamfer"] == "x1e4, paper protocol"
    assert s["units"]["hausdorff"].startswith("x1e3")
    both = M.evaluate_all(c + 0.01, c)
    assert set(both) == {"paper", "score"}


def test_bad_inputs_clear_errors(tmp_path):
    c = _cube_cloud()
    with pytest.raises(ValueError, match="prediction.*NaN"):
        M.evaluate(np.array([[np.nan, 0, 0]]), c)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        M.evaluate(np.zeros((4, 2)), c)
    with pytest.raises(ValueError, match="empty"):
        M.evaluate(np.zeros((0, 3)), c)
    with pytest.raises(FileNotFoundError, match="missing.ply"):
        M.load_points(tmp_path / "missing.ply")
    with pytest.raises(ValueError, match="unsupported"):
        M.load_mesh(__file__)
    v, f = _tetra_mesh()
    with pytest.raises(ValueError, match="out of range"):
        M.evaluate(c, c, mesh=(v, f + 10))
    bad = tmp_path / "bad.ply"
    bad.write_text("not a ply file")
    with pytest.raises(ValueError, match="bad.ply"):
        M.load_points(bad)


def test_load_roundtrip(tmp_path):
    import open3d as o3d

    v, f = _tetra_mesh()
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f))
    path = str(tmp_path / "tet.obj")
    o3d.io.write_triangle_mesh(path, m)
    lv, lf = M.load_mesh(path)
    assert lv.shape == (4, 3) and lf.shape == (4, 3)
    np.testing.assert_allclose(np.sort(M.load_points(path), 0), np.sort(v, 0))
    # open3d mesh objects are accepted directly
    r = M.evaluate(v, v, mesh=m)
    assert r.point_to_mesh == pytest.approx(0.0, abs=1e-9)


def test_chamfer_floor_positive_and_small():
    v, f = _tetra_mesh()
    r = M.chamfer_floor((v, f), n=400, seed=0, protocol="paper")
    assert 0 < r.chamfer < 50  # two samplings differ, but only at the sampling scale
    assert r.point_to_mesh == pytest.approx(0.0, abs=1e-6)  # samples lie on the mesh
    r2 = M.chamfer_floor((v, f), n=400, seed=0, protocol="paper")
    assert r2.chamfer == pytest.approx(r.chamfer)  # seeded
    both = M.chamfer_floors((v, f), n=400, seed=0)  # one pair of samplings for every protocol
    assert set(both) == set(M.PROTOCOLS)
    assert both["paper"].chamfer == pytest.approx(r.chamfer)
    alone = M.chamfer_floor((v, f), n=400, seed=0, protocol="score").to_dict()
    for k, val in both["score"].to_dict().items():  # rescaled from the paper units: equal to rounding
        assert val == (pytest.approx(alone[k], rel=1e-9, abs=1e-12) if isinstance(val, float) else alone[k]), k


@pytest.mark.skipif(not os.path.exists(SHARED_MESH), reason="shared data not available")
def test_real_mesh_noise_orders_metrics():
    v, f = M.load_mesh(SHARED_MESH)
    c = M.sample_poisson_disk((v, f), 5000, seed=0)
    rng = np.random.default_rng(0)
    diag = np.linalg.norm(c.max(0) - c.min(0))
    lo = M.evaluate(c + rng.normal(scale=0.003 * diag, size=c.shape), c, (v, f), "score")
    hi = M.evaluate(c + rng.normal(scale=0.01 * diag, size=c.shape), c, (v, f), "score")
    assert lo.chamfer < hi.chamfer and lo.p2m < hi.p2m and lo.hausdorff < hi.hausdorff


def test_normal_error_against_a_plane():
    """Normals tilted by a known angle from a z = 0 plane; the sign of a normal does not count."""
    verts = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-0.9, 0.9, (50, 2)), rng.normal(0, 0.01, 50)]
    tilt = np.radians(np.where(np.arange(50) < 25, 10.0, 30.0))
    nrm = np.c_[np.sin(tilt), np.zeros(50), np.cos(tilt)] * np.where(np.arange(50) % 2, 1, -2)[:, None]
    e = M.normal_error_deg(pts, nrm, (verts, faces))
    assert e["mean"] == pytest.approx(20.0, abs=1e-3) and e["median"] == pytest.approx(20.0, abs=1e-3)
    assert e["p90"] == pytest.approx(30.0, abs=1e-3)
    with pytest.raises(ValueError, match="normals"):
        M.normal_error_deg(pts, nrm[:10], (verts, faces))


def test_spacing_stats_tell_a_grid_from_a_clustered_cloud():
    from dss.metrics import spacing_stats

    g = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0), indexing="ij"), -1).reshape(-1, 2)
    grid = np.concatenate([g, np.zeros((100, 1))], 1)
    s = spacing_stats(grid)
    assert s["nn_mean"] == pytest.approx(1.0) and s["nn_cv"] == pytest.approx(0.0, abs=1e-12)
    assert s["clustered_fraction"] == 0.0
    piled = grid.copy()
    piled[:30] = piled[30:60] + 1e-3  # 60 points in 30 near-coincident pairs
    assert spacing_stats(piled)["clustered_fraction"] == pytest.approx(0.6)
    with pytest.raises(ValueError, match="at least 2 points"):
        spacing_stats(grid[:1])


@pytest.mark.parametrize("area", [0.0, 1e-3])
def test_protocols_from_one_search_equal_each_alone(area):
    """evaluate_protocols rescales one protocol's distances to the other's units: every number
    equals that protocol's own evaluation (and the units differ, so rescaling is exercised)."""
    rng = np.random.default_rng(3)
    verts = rng.normal(size=(40, 3)) * [3.0, 1.0, 2.0] + 5.0
    faces = np.array([rng.choice(40, 3, replace=False) for _ in range(80)])
    clean = rng.normal(size=(300, 3)) * [3.0, 1.0, 2.0] + 5.0
    pred = clean + rng.normal(size=clean.shape) * 0.05
    both = M.evaluate_protocols(pred, clean, (verts, faces), ("score", "paper"), area)
    keys = ("chamfer", "chamfer_gt_to_pred", "hausdorff", "hausdorff_dss_script", "p2m", "mesh_to_point")
    for pr in ("paper", "score"):
        alone = M.evaluate(pred, clean, (verts, faces), pr, area)
        for k in keys:
            assert getattr(both[pr], k) == pytest.approx(getattr(alone, k), rel=1e-9), (pr, k)
    assert both["paper"].chamfer != pytest.approx(both["score"].chamfer, rel=1e-3)


def test_ply_triangles_read_without_open3d_as_open3d_reads_them(tmp_path):
    """load_mesh reads binary triangle PLYs itself (colours on faces and vertices included) and
    gives open3d's arrays; polygons and ASCII files go to open3d."""
    import open3d as o3d

    from dss.pointcloud import read_ply_triangles

    v, f = _tetra_mesh()
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v * 2.5 + 1), o3d.utility.Vector3iVector(f))
    m.vertex_colors = o3d.utility.Vector3dVector(np.full((4, 3), 0.5))
    path = str(tmp_path / "tetra.ply")
    o3d.io.write_triangle_mesh(path, m)
    got = read_ply_triangles(path)
    assert got is not None
    np.testing.assert_allclose(got[0], v * 2.5 + 1, rtol=1e-6)
    np.testing.assert_array_equal(got[1], f)
    ascii_path = str(tmp_path / "tetra_ascii.ply")
    o3d.io.write_triangle_mesh(ascii_path, m, write_ascii=True)
    assert read_ply_triangles(ascii_path) is None
    np.testing.assert_array_equal(M.load_mesh(ascii_path)[1], f)
    # a quad among the faces: not all records are (3, i, j, k), so open3d reads it
    quad = tmp_path / "quad.ply"
    body = (np.array([3], np.uint8).tobytes() + np.array([0, 1, 2], "<i4").tobytes()
            + np.array([4], np.uint8).tobytes() + np.array([0, 1, 2, 3], "<i4").tobytes())
    quad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
                     b"property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
                     + v.astype("<f4").tobytes() + body)
    assert read_ply_triangles(quad) is None
    if os.path.exists(SHARED_MESH):  # a VCG file: vertex normals and colours, face colours
        ours = M.load_mesh(SHARED_MESH)
        ref = o3d.io.read_triangle_mesh(SHARED_MESH)
        np.testing.assert_allclose(ours[0], np.asarray(ref.vertices), rtol=1e-6)
        np.testing.assert_array_equal(ours[1], np.asarray(ref.triangles))


def test_closest_triangles_without_open3d_are_exact(monkeypatch):
    """The scipy search used where open3d is missing finds each point's closest triangle (brute
    force), and point-to-mesh and mesh normals then equal open3d's answers."""
    import builtins

    rng = np.random.default_rng(4)
    verts = rng.normal(size=(40, 3))
    faces = np.array([rng.choice(40, 3, replace=False) for _ in range(90)])
    pts = rng.normal(size=(300, 3)) * 1.2
    tv = verts[faces]
    P, T = np.repeat(pts, len(faces), 0), np.tile(tv, (len(pts), 1, 1))
    D = M.point_triangle_sq(P, T[:, 0], T[:, 1], T[:, 2]).reshape(len(pts), len(faces))
    d2, tri = M._closest_triangles_exact(pts, tv, k=2, chunk=37)
    np.testing.assert_allclose(d2, D.min(1), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(D[np.arange(len(pts)), tri], D.min(1), rtol=1e-12, atol=1e-15)
    with_o3d = (M.point_to_mesh_sq(pts, verts, faces), M.mesh_normals_at(pts, (verts, faces)))
    real_import = builtins.__import__

    def no_open3d(name, *args, **kwargs):
        if name == "open3d" or name.startswith("open3d."):
            raise ImportError("open3d blocked by the test")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_open3d)
    np.testing.assert_allclose(M.point_to_mesh_sq(pts, verts, faces), with_o3d[0], rtol=1e-6, atol=1e-9)
    # the normal is one of a closest triangle's (a point nearest a shared edge or vertex ties)
    got = M.mesh_normals_at(pts, (verts, faces))
    fn = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    closest = D <= D.min(1, keepdims=True) * (1 + 1e-9) + 1e-15
    assert all((fn[closest[i]] @ got[i]).max() > 1 - 1e-9 for i in range(len(pts)))
    assert (np.abs((got * with_o3d[1]).sum(1)) > 1 - 1e-6).mean() > 0.9
