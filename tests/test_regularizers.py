"""Weighted-PCA repulsion / projection regularisers (paper "Surface regularization")."""

import math
import os

import pytest
import torch

from dss.knn import knn
from dss.regularizers import (
    ProjectionLoss,
    RegularizerConfig,
    RepulsionLoss,
    bandwidth_for,
    default_bandwidth,
    find_neighbors,
    large_deformation_bandwidth,
    local_frames,
    projection_loss,
    repulsion_loss,
)

S = 0.05  # grid spacing


def _grid(n, spacing=S):
    ij = torch.stack(
        torch.meshgrid(torch.arange(n) * spacing, torch.arange(n) * spacing, indexing="ij"), -1
    ).reshape(-1, 2)
    ij = ij - ij.mean(0)
    return torch.cat([ij, torch.zeros(len(ij), 1)], 1)


def _rotation(seed):
    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g))
    return q


def _nn_cv(points, rows):
    d = knn(points.detach(), 1, exclude_self=True).dist[rows, 0]
    return (d.std() / d.mean()).item()


def _descend(loss_fn, p, steps, step_len):
    """Normalised gradient descent: the fastest-moving point moves ``step_len`` per step."""
    p = p.clone().requires_grad_(True)
    for _ in range(steps):
        (g,) = torch.autograd.grad(loss_fn(p), p)
        assert torch.isfinite(g).all()
        with torch.no_grad():
            p -= step_len * g / g.norm(dim=1).max().clamp_min(1e-30)
    return p.detach()


def test_bandwidth_rules():
    assert default_bandwidth(1.0, 10000) == pytest.approx(0.04)
    assert large_deformation_bandwidth(4.0) == pytest.approx(0.2)
    pts = torch.tensor([[0.0, 0, 0], [3.0, 4.0, 0.0]])  # diagonal 5
    assert bandwidth_for(pts) == pytest.approx(4 * math.sqrt(5 / 2))
    assert bandwidth_for(pts, "large") == pytest.approx(0.1 * math.sqrt(5))
    with pytest.raises(ValueError, match="rule"):
        bandwidth_for(pts, "huge")
    with pytest.raises(ValueError, match="explicitly"):  # a single point has no size
        bandwidth_for(pts[:1])


@pytest.mark.parametrize("covariance_weight", ["squared", "linear"])
def test_pca_normals_of_a_sphere_are_radial(covariance_weight):
    g = torch.Generator().manual_seed(0)
    p = torch.randn(3000, 3, generator=g)
    p = p / p.norm(dim=1, keepdim=True)
    fr = local_frames(p, p, None, bandwidth=bandwidth_for(p), covariance_weight=covariance_weight)
    cos = (fr.normal * p).sum(-1).abs()
    assert cos.min() > 0.97
    # tangent basis orthonormal and orthogonal to the normal
    frame = torch.cat([fr.tangent, fr.normal[..., None]], -1)
    eye = torch.eye(3).expand_as(frame)
    torch.testing.assert_close(frame.transpose(1, 2) @ frame, eye, atol=1e-5, rtol=0)
    assert not fr.normal.requires_grad and not fr.weights.requires_grad


def test_repulsion_makes_jittered_grid_uniform_and_keeps_points_on_plane():
    n = 16
    base = _grid(n)
    g = torch.Generator().manual_seed(1)
    jitter = torch.zeros_like(base)
    jitter[:, :2] = 0.25 * S * torch.randn(len(base), 2, generator=g)
    R = _rotation(2)  # a tilted plane, so "stays on the plane" is not trivially z == 0
    p0 = (base + jitter) @ R.T
    normals = torch.tensor([0.0, 0.0, 1.0]).expand_as(p0) @ R.T
    D = 2.5 * S
    # interior rows (by grid index): boundary points are pushed outwards by design
    ij = torch.stack(torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij"), -1)
    interior = ((ij >= 3) & (ij < n - 3)).all(-1).reshape(-1)

    cv0 = _nn_cv(p0, interior)
    p_with = _descend(lambda p: repulsion_loss(p, normals, bandwidth=D), p0, 40, 0.05 * S)
    cv_with = _nn_cv(p_with, interior)
    # "without repulsion" the positions do not change: cv stays cv0
    assert cv0 > 0.2
    assert cv_with < 0.4 * cv0, (cv0, cv_with)
    # purely tangential forces: every point stays on the plane
    off_plane = (p_with @ R)[:, 2].abs().max().item()
    assert off_plane < 1e-5 * S, off_plane
    # and the loss went down
    assert repulsion_loss(p_with, normals, bandwidth=D) < repulsion_loss(p0, normals, bandwidth=D)


def _plane_distance(p):
    c = p - p.mean(0)
    _, _, vh = torch.linalg.svd(c.double(), full_matrices=False)
    return (c.double() @ vh[-1]).abs().mean().item()


@pytest.mark.parametrize("mode", ["paper", "point_to_plane"])
def test_projection_lowers_point_to_plane_distance_of_noisy_plane(mode):
    base = _grid(15)
    g = torch.Generator().manual_seed(3)
    noisy = base.clone()
    noisy[:, 2] = 0.2 * S * torch.randn(len(base), generator=g)
    R = _rotation(4)
    noisy = noisy @ R.T
    normals = torch.tensor([0.0, 0.0, 1.0]).expand_as(noisy) @ R.T
    d0 = _plane_distance(noisy)
    out = _descend(
        lambda p: projection_loss(p, normals, bandwidth=3 * S, mode=mode), noisy, 40, 0.02 * S
    )
    d1 = _plane_distance(out)
    assert d1 < 0.5 * d0, (d0, d1)
    # normal forces only: the in-plane layout hardly changes
    inplane = ((out - noisy) @ R)[:, :2].abs().max().item()
    assert inplane < 0.2 * S


def test_paper_projection_splits_into_point_to_plane_plus_spread():
    g = torch.Generator().manual_seed(5)
    p = torch.rand(400, 3, generator=g) * torch.tensor([1.0, 1.0, 0.05])
    D = 0.2
    fr = local_frames(p, None, None, bandwidth=D)
    paper = projection_loss(p, bandwidth=D, frames=fr)
    p2p = projection_loss(p, bandwidth=D, frames=fr, mode="point_to_plane")
    nb = p[fr.idx.clamp(min=0)]
    spread = (fr.weights * (((nb - fr.centroid[:, None]) * fr.normal[:, None]).sum(-1) ** 2)).sum()
    torch.testing.assert_close(paper, p2p + spread / len(p), rtol=1e-4, atol=1e-9)


def test_visibility_weight_suppresses_occluded_outlier():
    pts = _grid(15)
    normals = torch.tensor([0.0, 0.0, 1.0]).expand_as(pts)
    centre = int(pts.norm(dim=1).argmin())
    outlier = torch.tensor([[S, 0.0, S]])  # inside the centre's neighbourhood, off the plane
    P = torch.cat([pts, outlier])
    Nrm = torch.cat([normals, torch.tensor([[0.0, 0.0, 1.0]])])  # same normal: theta keeps it

    def tilt_deg(o):
        occ = torch.zeros(len(P))
        occ[-1] = o
        fr = local_frames(P, Nrm, occ, bandwidth=3 * S)
        assert (fr.idx[centre][fr.valid[centre]] == len(P) - 1).any()  # outlier is a neighbour
        return math.degrees(math.acos(min(1.0, fr.normal[centre, 2].abs().item())))

    visible, occluded = tilt_deg(0.0), tilt_deg(50.0)
    assert visible > 2.0, visible
    assert occluded < 0.05 * visible, (visible, occluded)


def test_large_projection_bandwidth_pulls_far_outlier():
    pts = _grid(12)
    outlier = torch.tensor([[0.0, 0.0, 4 * S]])
    P = torch.cat([pts, outlier])
    small = 2.5 * S  # outlier has no neighbour within D: no force
    large = 0.3
    p = P.clone().requires_grad_(True)
    ProjectionLoss(bandwidth=small)(p).backward()
    assert p.grad[-1].norm() == 0
    p.grad = None
    ProjectionLoss(bandwidth=large)(p).backward()
    g = p.grad[-1]
    assert g[2] > 0 and g[2].abs() > 10 * g[:2].abs().max()  # descent moves it down to z=0


def test_cutoff_lets_an_isolated_point_use_its_nearest_neighbours():
    """With the paper's cutoff (1 x D) a point farther than D from every neighbour is never
    moved; cutoff 3 takes its k nearest within 3D, weighted by psi with the same D."""
    P = torch.cat([_grid(12), torch.tensor([[0.0, 0.0, 4 * S]])])
    D = 2.5 * S
    p = P.clone().requires_grad_(True)
    ProjectionLoss(bandwidth=D)(p).backward()
    assert p.grad[-1].norm() == 0
    p.grad = None
    ProjectionLoss(bandwidth=D, cutoff=3.0)(p).backward()
    g = p.grad[-1]
    assert g[2] > 0 and g[2].abs() > 10 * g[:2].abs().max()
    # the grid points themselves (neighbours within D) get the same frames either way
    f1 = local_frames(P, bandwidth=D, cutoff=1.0)
    f3 = local_frames(P, bandwidth=D, cutoff=3.0)
    assert (f3.valid.sum(1) >= f1.valid.sum(1)).all() and f3.valid[-1].any() and not f1.valid[-1].any()
    with pytest.raises(ValueError, match="cutoff"):
        RegularizerConfig(cutoff=0.0)


@pytest.mark.parametrize(
    "case", ["duplicates", "all_identical", "zero_normals", "n_below_k", "single", "collinear"]
)
def test_degenerate_inputs_give_finite_values_and_gradients(case):
    g = torch.Generator().manual_seed(7)
    normals = None
    if case == "duplicates":
        base = torch.rand(30, 3, generator=g)
        pts = torch.cat([base, base[:10], base[:10]])
        normals = torch.randn(len(pts), 3, generator=g)
    elif case == "all_identical":
        pts = torch.ones(20, 3)
        normals = torch.tensor([0.0, 0.0, 1.0]).expand(20, 3).clone()
    elif case == "zero_normals":
        pts = torch.rand(40, 3, generator=g)
        normals = torch.zeros(40, 3)
    elif case == "n_below_k":
        pts = torch.rand(5, 3, generator=g)
        normals = torch.randn(5, 3, generator=g)
    elif case == "single":
        pts = torch.rand(1, 3, generator=g)
    else:
        pts = torch.linspace(0, 1, 25)[:, None] * torch.tensor([[1.0, 2.0, 3.0]])
    p = pts.clone().requires_grad_(True)
    occ = torch.arange(len(pts), dtype=torch.float32)
    mods = (
        RepulsionLoss(bandwidth=0.3),
        ProjectionLoss(bandwidth=0.3),
        ProjectionLoss(bandwidth=0.3, projection_mode="point_to_plane"),
    )
    for mod in mods:
        loss = mod(p, normals, occ)
        (grad,) = torch.autograd.grad(loss, p)
        assert torch.isfinite(loss), (case, type(mod).__name__)
        assert torch.isfinite(grad).all(), (case, type(mod).__name__)


def test_empty_cloud():
    p = torch.zeros(0, 3, requires_grad=True)
    assert repulsion_loss(p, bandwidth=0.1).item() == 0.0
    assert projection_loss(p, bandwidth=0.1).item() == 0.0


def test_module_fixes_bandwidth_from_initial_shape_and_accepts_cached_neighbors():
    g = torch.Generator().manual_seed(8)
    p0 = torch.rand(500, 3, generator=g)
    rep = RepulsionLoss(RegularizerConfig(k=8))
    assert rep.bandwidth is None
    l0 = rep(p0)
    D = rep.bandwidth
    assert D == pytest.approx(bandwidth_for(p0))
    rep(p0 * 3.0)  # a later (bigger) cloud does not change D
    assert rep.bandwidth == D
    nb = rep.find_neighbors(p0)
    torch.testing.assert_close(rep(p0, neighbors=nb), l0)
    # stale neighbour list of the wrong size is refused
    with pytest.raises(ValueError, match="recompute"):
        rep(p0[:100], neighbors=nb)
    # shared frames: repulsion and projection from one PCA
    fr = local_frames(p0, None, None, bandwidth=D, neighbors=find_neighbors(p0, 8))
    torch.testing.assert_close(rep(p0, frames=fr), l0)
    assert torch.isfinite(ProjectionLoss(bandwidth=D)(p0, frames=fr))


def test_bad_inputs_are_refused():
    p = torch.rand(10, 3)
    with pytest.raises(ValueError, match="occlusion"):
        repulsion_loss(p, None, torch.zeros(9), bandwidth=0.1)
    with pytest.raises(ValueError, match=">= 0"):
        repulsion_loss(p, None, -torch.ones(10), bandwidth=0.1)
    with pytest.raises(ValueError, match="normals"):
        projection_loss(p, torch.zeros(10, 2), bandwidth=0.1)
    with pytest.raises(ValueError, match="NaN"):
        projection_loss(torch.full((10, 3), float("nan")), bandwidth=0.1)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        repulsion_loss(torch.rand(10, 2), bandwidth=0.1)
    with pytest.raises(ValueError, match="bandwidth"):
        RegularizerConfig(bandwidth=-1.0)
    with pytest.raises(ValueError, match="projection_mode"):
        RegularizerConfig(projection_mode="foo")


def test_tiny_neighbourhood_uses_given_normal():
    # two neighbours cannot define a plane: the frame falls back to the point's own normal
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])
    n = torch.nn.functional.normalize(torch.tensor([[0.0, 1.0, 1.0]]), dim=-1).expand(3, 3)
    fr = local_frames(pts, n, None, bandwidth=0.1)
    torch.testing.assert_close(fr.normal.abs(), n.abs(), atol=1e-6, rtol=0)
    assert (fr.tangent.transpose(1, 2) @ n[..., None]).abs().max() < 1e-6


def test_projection_gradient_treats_frame_and_weights_as_constants():
    # dL/dp = 2/N [sum_k w_ik (d_ik.n_i) n_i  -  sum_{j: i in N(j)} w_ji (d_ji.n_j) n_j]
    g = torch.Generator().manual_seed(9)
    p = (torch.rand(200, 3, generator=g) * torch.tensor([1.0, 1.0, 0.1])).requires_grad_(True)
    nrm = torch.nn.functional.normalize(torch.randn(200, 3, generator=g), dim=-1)
    occ = torch.randint(0, 4, (200,), generator=g).float()
    fr = local_frames(p, nrm, occ, bandwidth=0.25, k=8)
    projection_loss(p, bandwidth=0.25, frames=fr).backward()
    dn = (fr.diff.detach() * fr.normal[:, None]).sum(-1)  # (N, K)
    f = (2.0 / 200) * (fr.weights * dn)[..., None] * fr.normal[:, None]  # force on p_i per (i,k)
    expected = f.sum(1)
    idx = fr.idx.clamp(min=0).reshape(-1)
    expected = expected.index_add(0, idx, -f.reshape(-1, 3))
    torch.testing.assert_close(p.grad, expected, rtol=1e-4, atol=1e-7)


def test_dilated_neighbours_are_every_dth_of_the_nearest():
    g = torch.Generator().manual_seed(3)
    p = torch.rand(300, 3, generator=g)
    full = find_neighbors(p, 24)
    dil = find_neighbors(p, 8, dilation=3)
    assert dil.idx.shape == (300, 8)
    torch.testing.assert_close(dil.dist, full.dist[:, ::3])
    # same neighbour count, three times the reach: the farthest kept is the 22nd nearest
    assert bool((dil.dist[:, -1] > find_neighbors(p, 8).dist[:, -1]).all())
    with pytest.raises(ValueError, match="dilation"):
        find_neighbors(p, 8, dilation=0)


def test_min_neighbors_gives_isolated_points_a_plane():
    """A point farther than cutoff * D from every neighbour is never moved by the paper's
    projection term; with min_neighbors its nearest neighbours still count and pull it back."""
    p = _grid(12)
    lone = torch.tensor([[0.0, 0.0, 0.3]])  # 6 grid spacings above the plane
    pts = torch.cat([p, lone]).requires_grad_()
    D = 2 * S
    for m, moves in ((0, False), (4, True)):
        fr = local_frames(pts, None, None, bandwidth=D, k=8, min_neighbors=m)
        assert int(fr.valid[-1].sum()) == (4 if m else 0)
        loss = projection_loss(pts, bandwidth=D, frames=fr)
        (g,) = torch.autograd.grad(loss, pts)
        assert (g[-1, 2].abs() > 0).item() is moves
        if moves:
            assert g[-1, 2] > 0  # descent moves it down, toward the plane
    with pytest.raises(ValueError, match="min_neighbors"):
        RegularizerConfig(min_neighbors=-1)


def test_project_to_neighbour_planes_flattens_a_noisy_plane_and_pulls_in_a_tail_point():
    from dss.regularizers import project_to_neighbour_planes

    g = torch.Generator().manual_seed(5)
    p = _grid(20) @ _rotation(2).T
    normal = _rotation(2)[:, 2]
    noisy = p + 0.01 * torch.randn(len(p), 1, generator=g) * normal
    noisy[0] += 0.2 * normal  # a tail point four grid spacings off the plane
    out = project_to_neighbour_planes(noisy, k=16)
    height = lambda q: (q @ normal).abs()  # noqa: E731
    assert float(height(out).mean()) < 0.5 * float(height(noisy[1:]).mean())
    assert float(height(out)[0]) < 0.02 < float(height(noisy)[0])
    with pytest.raises(ValueError, match="too few"):
        project_to_neighbour_planes(noisy[:10], k=16)


def test_outlier_projection_moves_only_a_clump_of_outliers_and_lands_it_on_the_surface():
    from dss.regularizers import project_to_neighbour_planes

    g = torch.Generator().manual_seed(6)
    p = _grid(24) @ _rotation(3).T
    normal = _rotation(3)[:, 2]
    noisy = p + 0.005 * torch.randn(len(p), 1, generator=g) * normal
    # three neighbouring grid points lifted together: their own 16-neighbour plane is tilted
    # toward them, so one plain projection leaves them well off the surface
    clump = [300, 301, 324]
    noisy[clump] += 0.25 * normal
    height = lambda q: (q @ normal).abs()  # noqa: E731
    plain = project_to_neighbour_planes(noisy, k=16)
    out = project_to_neighbour_planes(noisy, k=16, threshold=3.0, iterations=2)
    inliers = torch.ones(len(p), dtype=torch.bool)
    inliers[clump] = False
    assert float(height(plain)[clump].max()) > 0.03
    assert float(height(out)[clump].max()) < 0.015  # ~3 noise sigmas: back on the surface
    moved = (out - noisy).norm(dim=-1) > 0
    assert not bool(moved[inliers].all()) and int(moved[inliers].sum()) < 0.05 * len(p)
    # points that did not move are bit-identical (fine detail kept)
    assert torch.equal(out[~moved], noisy[~moved])
    with pytest.raises(ValueError, match="threshold"):
        project_to_neighbour_planes(noisy, k=16, threshold=-1.0)
    with pytest.raises(ValueError, match="iterations"):
        project_to_neighbour_planes(noisy, k=16, iterations=0)


def test_outlier_projection_local_test_keeps_a_sharp_edge_and_never_writes_into_its_input():
    from dss.regularizers import project_to_neighbour_planes

    g = torch.Generator().manual_seed(7)
    flat = _grid(30).double()
    # fold the sheet along x = 0 into a 90-degree roof: near the ridge every neighbourhood's
    # plane is wrong, so every ridge point is "far from its plane"
    x = flat[:, 0]
    roof = torch.stack([x, flat[:, 1], -x.abs()], 1)
    roof = roof + 1e-3 * S * torch.randn(roof.shape, generator=g, dtype=roof.dtype)
    o = 7 * 30 + 15  # one real outlier, on the x < 0 slope, far from the ridge and the border
    roof[o, 2] += 6 * S
    before = roof.clone()
    plain = project_to_neighbour_planes(roof, k=16, threshold=3.0, iterations=1)
    local = project_to_neighbour_planes(roof, k=16, threshold=3.0, local_ratio=3.0, iterations=1)
    assert torch.equal(roof, before)  # float64 input: still a copy
    moved_plain = (plain - roof).norm(dim=-1) > 1e-9
    moved_local = (local - roof).norm(dim=-1) > 1e-9
    # the ridge away from the sheet's border (at a border corner even the neighbours disagree)
    ridge = (x.abs() < 2.5 * S) & (flat[:, 1].abs() < flat[:, 1].max() - 3 * S)
    assert int(moved_plain[ridge].sum()) > 20  # the global test alone flattens the edge
    assert int(moved_local[ridge].sum()) == 0
    slope_distance = abs(float(local[o, 2] - local[o, 0])) / 2**0.5  # to the plane z = x
    assert bool(moved_local[o]) and slope_distance < 0.1 * S
    with pytest.raises(ValueError, match="local_ratio"):
        project_to_neighbour_planes(roof, k=16, threshold=3.0, local_ratio=-1.0)


def test_batched_eigh_splits_over_threads_with_the_same_bits():
    """local_frames' eigh (dss.regularizers.batched_eigh) splits large CPU batches over torch's
    threads: the same eigenvalues and eigenvectors, bit for bit, as one torch.linalg.eigh call,
    for a batch that splits unevenly and for one small enough to take the plain call."""
    from dss import regularizers as R

    g = torch.Generator().manual_seed(0)
    a = torch.randn(2 * R._EIGH_MIN_CHUNK + 37, 3, 3, generator=g, dtype=torch.float64)
    cov = a @ a.transpose(1, 2)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        for mats in (cov, cov[:100]):
            want = torch.linalg.eigh(mats)
            got = R.batched_eigh(mats)
            assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
        assert R._eigh_pool is not None and R._eigh_pool_key[1] >= 2  # the split ran
    finally:
        torch.set_num_threads(before)


def test_batched_eigh_replaces_a_pool_made_by_another_process():
    """A child forked after the parent made its eigh thread pool inherits the pool object but
    not its threads: batched_eigh starts a new pool when the pool's process id is not its own
    (simulated here: forking a process that has run OpenMP is itself unsafe with libgomp)."""
    from dss import regularizers as R

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        a = torch.randn(3 * R._EIGH_MIN_CHUNK, 3, 3, dtype=torch.float64)
        cov = a @ a.transpose(1, 2)
        R.batched_eigh(cov)
        stale = R._eigh_pool
        R._eigh_pool_key = (os.getpid() + 1, R._eigh_pool_key[1])  # as a forked child sees it
        got = R.batched_eigh(cov)
        assert R._eigh_pool is not stale and R._eigh_pool_key[0] == os.getpid()
        assert torch.equal(got[1], torch.linalg.eigh(cov)[1])
    finally:
        torch.set_num_threads(before)


def test_rim_strays_move_back_onto_their_patch_and_boundaries_stay():
    """pull_rim_strays: a point on the plane of a patch but beyond its end moves back within it;
    the points inside the patch and on its straight boundary (an open surface's edge) stay."""
    from dss.regularizers import pull_rim_strays

    g = torch.Generator().manual_seed(0)
    xy = torch.rand(3000, 2, generator=g)  # a unit square patch, an open surface
    pts = torch.cat([xy, torch.zeros(3000, 1)], 1)
    stray = torch.tensor([[1.12, 0.5, 0.0]])  # on the plane, past the edge x = 1
    out, moved = pull_rim_strays(torch.cat([pts, stray]), k=16, iterations=1)
    assert float(out[-1, 0]) < 1.06 and abs(float(out[-1, 2])) < 1e-9
    inside = (out[:-1] - pts).norm(dim=1)
    assert float((inside > 1e-6).float().mean()) < 0.02  # the edge of the square is a boundary
    assert 1 <= moved < 0.02 * len(pts)
    with pytest.raises(ValueError, match="ratio"):
        pull_rim_strays(pts, ratio=0.0)


def test_readmit_near_surface_takes_points_on_the_surface_and_leaves_junk():
    """readmit_near_surface: a removed point just off the patch's plane, near its edge, is taken
    and projected onto it; one far off the plane, and one on the plane's extension far from the
    patch, are not."""
    from dss.regularizers import readmit_near_surface

    g = torch.Generator().manual_seed(0)
    xy = torch.rand(4000, 2, generator=g)
    surface = torch.cat([xy, torch.zeros(4000, 1)], 1)
    cand = torch.tensor([[0.5, 0.5, 0.004], [1.01, 0.5, -0.003], [0.5, 0.5, 0.2], [3.0, 0.5, 0.0]])
    ok, proj, normals = readmit_near_surface(cand, surface, max_distance=0.01)
    assert ok.tolist() == [True, True, False, False]
    assert torch.allclose(proj[:, 2], torch.zeros(2), atol=1e-6) and torch.allclose(normals[:, 2].abs(), torch.ones(2))
    none, _, _ = readmit_near_surface(torch.zeros(0, 3), surface, 0.01)
    assert none.shape == (0,)
