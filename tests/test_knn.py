"""kNN / radius search: both backends match an exhaustive search."""

import pytest
import torch

from dss.knn import gather_neighbors, knn, radius_neighbors

BACKENDS = ["cpp", "scipy", "torch"]


def _brute(points, query, k):
    d = ((query[:, None, :].double() - points[None, :, :].double()) ** 2).sum(-1).sqrt()
    dist, idx = torch.sort(d, dim=1)
    return dist[:, :k], idx[:, :k]


@pytest.mark.parametrize("backend", BACKENDS)
def test_knn_matches_brute_force(backend):
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(1500, 3, generator=g)
    qry = torch.rand(300, 3, generator=g)
    nb = knn(pts, 8, qry, backend=backend)
    bd, bi = _brute(pts, qry, 8)
    assert nb.idx.dtype == torch.int64 and nb.idx.shape == (300, 8)
    assert nb.dist.dtype == torch.float32
    torch.testing.assert_close(nb.dist.double(), bd, rtol=1e-5, atol=1e-6)
    # random continuous coordinates: ties have probability ~0, so the index sets agree
    assert torch.equal(nb.idx, bi)


@pytest.mark.parametrize("backend", BACKENDS)
def test_knn_self_query_and_exclude_self(backend):
    g = torch.Generator().manual_seed(1)
    pts = torch.randn(800, 3, generator=g)
    nb = knn(pts, 6, backend=backend)
    assert torch.equal(nb.idx[:, 0], torch.arange(800))  # itself first
    ex = knn(pts, 5, exclude_self=True, backend=backend)
    assert torch.equal(ex.idx, nb.idx[:, 1:])
    assert not (ex.idx == torch.arange(800)[:, None]).any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_knn_chunking_and_backends_agree(backend):
    g = torch.Generator().manual_seed(2)
    pts = torch.rand(3000, 3, generator=g)
    a = knn(pts, 10, exclude_self=True, backend="torch", chunk_rows=97)
    b = knn(pts, 10, exclude_self=True, backend=backend)
    assert torch.equal(a.idx, b.idx)
    torch.testing.assert_close(a.dist, b.dist, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_knn_pads_when_k_exceeds_n(backend):
    pts = torch.rand(4, 3)
    nb = knn(pts, 7, exclude_self=True, backend=backend)
    assert nb.idx.shape == (4, 7)
    assert (nb.idx[:, :3] >= 0).all() and (nb.idx[:, 3:] == -1).all()
    assert torch.isinf(nb.dist[:, 3:]).all()
    assert nb.mask.sum() == 12
    # every other point appears exactly once
    for i in range(4):
        assert sorted(nb.idx[i, :3].tolist()) == [j for j in range(4) if j != i]


@pytest.mark.parametrize("backend", BACKENDS)
def test_exclude_self_with_duplicates(backend):
    # 6 copies of one point plus a far point: point i must never be its own neighbour
    pts = torch.cat([torch.zeros(6, 3), torch.ones(1, 3)])
    nb = knn(pts, 3, exclude_self=True, backend=backend)
    assert not (nb.idx == torch.arange(7)[:, None]).any()
    assert (nb.dist[:6] == 0).all()


def test_drop_self_fast_path_agrees_with_the_general_one():
    """_drop_self slices off column 0 when every row starts with itself; a single row whose
    self sits elsewhere sends the batch through the general masked path: same rows either way."""
    from dss.knn import _drop_self

    g = torch.Generator().manual_seed(0)
    n, k = 200, 6
    idx = torch.randint(0, n, (n, k + 1), generator=g)
    idx[:, 0] = torch.arange(n)
    idx[:, 1:][idx[:, 1:] == torch.arange(n)[:, None]] = -1  # no second self hit
    dist = torch.rand(n, k + 1, generator=g).sort(1).values
    fast = _drop_self(idx, dist, k)
    assert torch.equal(fast[0], idx[:, 1:]) and torch.equal(fast[1], dist[:, 1:])
    swapped = idx.clone()
    swapped[0, [0, 3]] = swapped[0, [3, 0]]  # row 0: itself in column 3
    general = _drop_self(swapped, dist, k)
    assert torch.equal(general[0][1:], fast[0][1:]) and torch.equal(general[1][1:], fast[1][1:])
    assert 0 not in general[0][0].tolist() and general[0].shape == (n, k)


@pytest.mark.parametrize("backend", BACKENDS)
def test_radius_neighbors(backend):
    g = torch.Generator().manual_seed(3)
    pts = torch.rand(1000, 3, generator=g)
    r = 0.08
    nb = radius_neighbors(pts, r, 12, exclude_self=True, backend=backend)
    bd, bi = _brute(pts, pts, 13)
    bd, bi = bd[:, 1:], bi[:, 1:]
    inside = bd <= r
    assert torch.equal(nb.mask, inside)
    assert torch.equal(nb.idx[inside], bi[inside])
    assert torch.isinf(nb.dist[~inside]).all()


def test_knn_no_grad_and_gather_is_differentiable():
    pts = torch.rand(50, 3, requires_grad=True)
    nb = knn(pts, 4, exclude_self=True)
    assert not nb.dist.requires_grad
    g = gather_neighbors(pts, nb.idx)
    g.sum().backward()
    # each gathered entry contributes 1 to its source's gradient
    counts = torch.bincount(nb.idx.flatten(), minlength=50).float()
    torch.testing.assert_close(pts.grad[:, 0], counts)


def test_knn_bad_input():
    with pytest.raises(ValueError, match="shape"):
        knn(torch.rand(10), 3)
    with pytest.raises(ValueError, match="k must"):
        knn(torch.rand(10, 3), 0)
    with pytest.raises(ValueError, match="backend"):
        knn(torch.rand(10, 3), 2, backend="faiss")
    with pytest.raises(ValueError, match="NaN"):
        knn(torch.tensor([[0.0, 0, 0], [float("nan"), 0, 0]]), 1, backend="scipy")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_knn_on_gpu_stays_on_device():
    pts = torch.rand(2000, 3, device="cuda")
    nb = knn(pts, 5, exclude_self=True)
    assert nb.idx.device.type == "cuda"
    ref = knn(pts.cpu(), 5, exclude_self=True, backend="scipy")
    assert torch.equal(nb.idx.cpu(), ref.idx)


def _sphere(n, seed=0, noise=0.0):
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(n, 3, generator=g, dtype=torch.float64)
    p = p / p.norm(dim=1, keepdim=True)
    return p + noise * torch.randn(n, 3, generator=g, dtype=torch.float64)


@pytest.mark.parametrize(
    "shape",
    ["noisy_sphere", "flat", "line", "far_queries", "clustered"],
)
@pytest.mark.parametrize("k", [1, 17, 65])
def test_cpp_grid_knn_matches_the_kd_tree(shape, k):
    """The grid search (dss/csrc/knn_cpu.cpp) against cKDTree on clouds where a uniform grid is
    a poor fit: a surface, a plane and a line (axes without extent), queries far outside the
    grid, two dense clusters far apart. Same distances; the same indices (continuous random
    coordinates: no ties)."""
    g = torch.Generator().manual_seed(1)
    if shape == "noisy_sphere":
        pts, qry = _sphere(6000, noise=0.01), None
    elif shape == "flat":
        pts, qry = torch.cat([torch.rand(4000, 2, generator=g, dtype=torch.float64),
                              torch.zeros(4000, 1, dtype=torch.float64)], 1), None
    elif shape == "line":
        pts, qry = torch.rand(3000, 1, generator=g, dtype=torch.float64) * torch.tensor([[1.0, 2.0, -1.0]]), None
    elif shape == "far_queries":
        pts = _sphere(3000)
        qry = 5.0 * torch.randn(500, 3, generator=g, dtype=torch.float64)
    else:
        a = 0.01 * torch.randn(2500, 3, generator=g, dtype=torch.float64)
        pts, qry = torch.cat([a, a[:1500] + 10.0]), None
    want = knn(pts, k, qry, exclude_self=qry is None, backend="scipy")
    got = knn(pts, k, qry, exclude_self=qry is None, backend="cpp")
    assert torch.equal(got.dist, want.dist)
    assert torch.equal(got.idx, want.idx)


def test_cpp_grid_knn_radius_padding_and_ties():
    """Radius limits (inclusive, padding -1 / inf), k larger than the cloud, an empty result and
    a regular grid full of exact ties (ordered by index, the distances as cKDTree's)."""
    pts = _sphere(2000)
    r = 0.05
    want = radius_neighbors(pts, r, 40, exclude_self=True, backend="scipy")
    got = radius_neighbors(pts, r, 40, exclude_self=True, backend="cpp")
    assert torch.equal(got.idx, want.idx) and torch.equal(got.dist, want.dist)
    small = pts[:5]
    nb = knn(small, 8, backend="cpp")
    assert (nb.idx[:, 5:] == -1).all() and torch.isinf(nb.dist[:, 5:]).all()
    assert (nb.idx[:, 0] == torch.arange(5)).all()
    far = radius_neighbors(pts, 1e-9, 3, query=pts[:4] + 5.0, backend="cpp")
    assert (far.idx == -1).all()
    huge = torch.tensor([[1e300, 0.0, 0.0], [-1e300, 1e300, 0.0]], dtype=torch.float64)  # cells beyond int64
    assert torch.equal(knn(pts, 3, huge, backend="cpp").idx, knn(pts, 3, huge, backend="scipy").idx)
    ij = torch.stack(torch.meshgrid(torch.arange(30.0), torch.arange(30.0), indexing="ij"), -1).reshape(-1, 2)
    grid = torch.cat([ij, torch.zeros(900, 1)], 1).double() * 0.05
    a = knn(grid, 8, backend="cpp")
    b = knn(grid, 8, backend="scipy")
    assert torch.equal(a.dist, b.dist)
    diff = grid[:, None] - grid[a.idx]
    d2 = diff[..., 0] ** 2 + diff[..., 1] ** 2 + diff[..., 2] ** 2  # the kernel's order
    assert torch.equal(d2.sqrt(), a.dist)  # the indices hold the reported distances
    ties = d2[:, 1:] == d2[:, :-1]  # exact ties of the squared distance (not of its square root)
    assert ties.any() and (a.idx[:, 1:][ties] > a.idx[:, :-1][ties]).all()


def test_cpp_grid_knn_does_not_depend_on_the_thread_count():
    pts = _sphere(20000, noise=0.01).float()
    before = torch.get_num_threads()
    try:
        out = []
        for t in (1, 2):
            torch.set_num_threads(t)
            out.append(knn(pts, 16, exclude_self=True, backend="cpp"))
    finally:
        torch.set_num_threads(before)
    assert torch.equal(out[0].idx, out[1].idx) and torch.equal(out[0].dist, out[1].dist)


def test_cpp_knn_backend_refuses_what_it_cannot_search():
    with pytest.raises(ValueError, match="3D CPU"):
        knn(torch.rand(50, 2), 3, backend="cpp")
    with pytest.raises(ValueError, match="NaN or inf"):
        knn(torch.tensor([[0.0, 0, 0], [1, float("nan"), 0], [2, 0, 0]]), 1, backend="cpp")
