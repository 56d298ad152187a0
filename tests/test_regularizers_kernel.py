"""The regularisers' weighted PCA in C++ (dss/csrc/frames_cpu.cpp) against its torch twin
(``local_frames(..., pca_backend="torch")``)."""

from dataclasses import replace

import pytest
import torch

from dss._ext import load_cpu
from dss.regularizers import (
    ProjectionLoss,
    RegularizerConfig,
    bandwidth_for,
    find_neighbors,
    local_frames,
    projection_loss,
    repulsion_loss,
)

pytestmark = pytest.mark.skipif(load_cpu() is None, reason="the C++ kernel does not build here")


def _noisy_sphere(n=3000, noise=0.01, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(n, 3, generator=g, dtype=torch.float64)
    p = p / p.norm(dim=1, keepdim=True)
    normals = p.clone()
    p = p + noise * torch.randn(n, 3, generator=g, dtype=torch.float64)
    occ = torch.randint(0, 4, (n,), generator=g).to(dtype)
    return p.to(dtype), normals.to(dtype), occ


def _projector(v):
    """(N, 3, m) orthonormal columns -> (N, 3, 3) projector onto their span (sign and basis free)."""
    return v @ v.transpose(1, 2)


def _frames_and_grads(p, normals, occ, backend, axes_from=None, **kw):
    """Frames and the projection and repulsion gradients; ``axes_from``: take the normal and
    tangent of these frames (to compare the gradients' machinery where the axes are ambiguous)."""
    q = p.detach().requires_grad_(True)
    fr = local_frames(q, normals, occ, pca_backend=backend, **kw)
    if axes_from is not None:
        fr = replace(fr, normal=axes_from.normal, tangent=axes_from.tangent)
    D = kw["bandwidth"]
    (gp,) = torch.autograd.grad(projection_loss(q, frames=fr, bandwidth=D), q, retain_graph=True)
    (gr,) = torch.autograd.grad(repulsion_loss(q, frames=fr, bandwidth=D), q)
    return fr, gp, gr


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "case",
    [
        dict(),  # the paper's settings: normals, occlusion, cutoff 1, squared weights
        dict(normals=False, occlusion=False),
        dict(covariance_weight="linear", cutoff=2.0),
        dict(min_neighbors=4, cutoff=0.5),  # rows beyond the cutoff, few-neighbour fallbacks
    ],
)
def test_cpp_frames_match_the_torch_twin(dtype, case):
    """Same valid sets; weights, centroids and eigenvalues within the dtype's precision; the
    same normal line and tangent plane (eigenvector signs are free) where it is defined; with
    the same axes, the projection and repulsion gradients through the C++ differences and
    weights within the dtype's precision."""
    case = dict(case)
    p, normals, occ = _noisy_sphere(dtype=dtype)
    if not case.pop("normals", True):
        normals = None
    if not case.pop("occlusion", True):
        occ = None
    # a bandwidth that leaves some of the 16 neighbours out (paper's rule: all within it here)
    kw = dict(bandwidth=0.6 * bandwidth_for(p), neighbors=find_neighbors(p, 16), **case)
    fc, gpc, grc = _frames_and_grads(p, normals, occ, "cpp", **kw)
    ft, gpt, grt = _frames_and_grads(p, normals, occ, "torch", axes_from=fc, **kw)
    ft = local_frames(p, normals, occ, pca_backend="torch", **kw)  # with its own axes
    tol = 2e-6 if dtype == torch.float32 else 1e-12
    assert torch.equal(fc.valid, ft.valid)
    assert 0 < int(fc.valid.sum()) < fc.valid.numel()  # both kinds of neighbour occur
    for name in ("psi", "weights", "centroid", "diff"):
        a, b = getattr(fc, name), getattr(ft, name)
        assert a.dtype == b.dtype == dtype and a.shape == b.shape
        torch.testing.assert_close(a, b, rtol=tol, atol=tol, msg=name)
    scale = float(ft.eigenvalues.abs().max())
    torch.testing.assert_close(fc.eigenvalues, ft.eigenvalues, rtol=0, atol=tol * scale)
    # The normal line is defined where the smallest eigenvalue is separated from the next one
    # (rows with fewer than 3 neighbours and no normal to fall back on have a repeated zero
    # eigenvalue: any line in a plane is a PCA result there). torch forms the covariance in the
    # points' dtype, the kernel in double: the lines agree to that rounding over the gap.
    ev = ft.eigenvalues.double()
    sep = (ev[:, 1] - ev[:, 0]) > 1e-3 * ev[:, 2].abs()
    assert float(sep.double().mean()) > 0.8
    ptol = 1e-4 if dtype == torch.float32 else 1e-9
    for a, b in ((fc.normal[..., None], ft.normal[..., None]), (fc.tangent, ft.tangent)):
        torch.testing.assert_close(_projector(a)[sep], _projector(b)[sep], rtol=0, atol=ptol)
    gtol = 1e-4 if dtype == torch.float32 else 1e-9
    for a, b in ((gpc, gpt), (grc, grt)):
        assert float((a - b).norm() / b.norm()) < gtol


def test_cpp_frames_are_closer_to_float64_than_the_float32_twin():
    """The kernel accumulates in double: its float32 frames are at least as close to the float64
    result as torch's float32 ones (the reason it need not match them bit for bit)."""
    p, normals, occ = _noisy_sphere()
    kw = dict(bandwidth=bandwidth_for(p), neighbors=find_neighbors(p, 16))
    exact = local_frames(p.double(), normals.double(), occ.double(), pca_backend="torch", **kw)
    err = {}
    for backend in ("torch", "cpp"):
        fr = local_frames(p, normals, occ, pca_backend=backend, **kw)
        err[backend] = float((_projector(fr.normal[..., None]).double() - _projector(exact.normal[..., None])).abs().max())
    assert err["cpp"] <= err["torch"]
    assert err["cpp"] < 1e-5


def test_cpp_eigh_on_hard_matrices():
    """The kernel's 3x3 Jacobi: zero, diagonal, repeated and nearly repeated eigenvalues, exactly
    planar neighbourhoods and scenes scaled by 1e-30 and 1e30 (its power-of-two scaling): the
    eigenvalues of torch.linalg.eigh in float64, orthonormal eigenvectors with small residuals."""
    g = torch.Generator().manual_seed(3)
    base, _, _ = _noisy_sphere(n=400, noise=0.0, dtype=torch.float64)
    clouds = [
        base,  # exactly on a sphere
        torch.cat([base[:, :2], torch.zeros(400, 1, dtype=torch.float64)], 1),  # exactly planar
        torch.randn(400, 3, generator=g, dtype=torch.float64),  # isotropic: near-repeated
        torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]], dtype=torch.float64),
    ]
    for cloud in clouds:
        for scale in (1.0, 1e-30, 1e30):
            p = cloud * scale
            k = min(8, p.shape[0] - 1)
            nb = find_neighbors(p, k)
            fr = local_frames(p, None, None, bandwidth=1e9 * scale, neighbors=nb, k=k, pca_backend="cpp")
            w = fr.weights
            c = (w[..., None] * p[nb.idx]).sum(1)
            e = p[nb.idx] - c[:, None]
            cov = torch.einsum("nk,nki,nkj->nij", w * w, e, e)
            want = torch.linalg.eigh(cov).eigenvalues
            top = want.abs().amax(1, keepdim=True).clamp_min(1e-300)
            assert float(((fr.eigenvalues - want).abs() / top).max()) < 1e-12
            V = torch.cat([fr.normal[..., None], fr.tangent], -1)
            eye = torch.eye(3, dtype=torch.float64).expand_as(V)
            assert float((V.transpose(1, 2) @ V - eye).abs().max()) < 1e-12
            resid = cov @ V - V * fr.eigenvalues[:, None, :]
            assert float((resid.abs().amax((1, 2)) / top[:, 0]).max()) < 1e-12
    # a point without neighbours within the bandwidth: zero weights, the identity frame
    p = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    fr = local_frames(p, None, None, bandwidth=0.1, k=3, pca_backend="cpp")
    assert not fr.valid.any() and float(fr.weights.abs().sum()) == 0.0
    assert torch.equal(fr.eigenvalues, torch.zeros(4, 3))
    assert torch.equal(torch.cat([fr.normal[..., None], fr.tangent], -1), torch.eye(3).expand(4, 3, 3))


def test_cpp_frames_do_not_depend_on_the_thread_count():
    """Each point's frame is computed on its own (the Jacobi groups never mix results) and the
    backward's scatter runs in a fixed order: 1 and 2 threads give the same bits."""
    p, normals, occ = _noisy_sphere(n=5000)
    kw = dict(bandwidth=bandwidth_for(p), neighbors=find_neighbors(p, 16))
    before = torch.get_num_threads()
    out = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            fr, gp, gr = _frames_and_grads(p, normals, occ, "cpp", **kw)
            out.append([fr.psi, fr.weights, fr.centroid, fr.eigenvalues, fr.normal, fr.tangent, gp, gr])
    finally:
        torch.set_num_threads(before)
    for a, b in zip(*out):
        assert torch.equal(a, b)


def test_cpp_neighbour_differences_gradcheck():
    """The differences' hand-written backward (a scatter onto both ends of each pair) against
    finite differences, with missing (-1) and masked neighbours."""
    p, _, _ = _noisy_sphere(n=60, dtype=torch.float64)
    nb = find_neighbors(p, 6)
    idx = nb.idx.clone()
    idx[::7, -1] = -1
    from dss.autograd import NeighbourDiff
    from dss.knn import Neighbors

    fr = local_frames(p, None, None, bandwidth=bandwidth_for(p), neighbors=Neighbors(idx=idx, dist=nb.dist),
                      pca_backend="cpp")
    assert not fr.valid.all()
    q = p.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: NeighbourDiff.apply(x, fr.idx, fr.valid), (q,))


def test_pca_backend_choice_is_checked():
    p, _, _ = _noisy_sphere(n=50)
    D = bandwidth_for(p)
    with pytest.raises(ValueError, match="pca_backend"):
        local_frames(p, bandwidth=D, pca_backend="cuda")
    with pytest.raises(ValueError, match="float32/float64"):
        local_frames(p.half(), bandwidth=D, neighbors=find_neighbors(p, 8), pca_backend="cpp")
    with pytest.raises(ValueError, match="pca_backend"):
        RegularizerConfig(pca_backend="fast")
    # a neighbour list that names rows these points do not have is refused, not read out of bounds
    from dss.knn import Neighbors

    nb = find_neighbors(p, 4)
    for wrong in (p.shape[0], -2):
        idx = nb.idx.clone()
        idx[3, 1] = wrong
        with pytest.raises(RuntimeError, match="neighbour indices"):
            local_frames(p, bandwidth=D, neighbors=Neighbors(idx=idx, dist=nb.dist), pca_backend="cpp")
    # the modules pass their config's choice through (torch: the twin, not the kernel)
    term = ProjectionLoss(RegularizerConfig(pca_backend="torch"), bandwidth=D)
    fr = term.frames(p)
    ref = local_frames(p, bandwidth=D, pca_backend="torch")
    assert torch.equal(fr.eigenvalues, ref.eigenvalues)


def test_bench_regularizers_runs(tmp_path):
    """The benchmark command behind docs/performance.md's regulariser numbers, at a small size."""
    import json

    from experiments.benchmarks.bench_regularizers import run

    out = tmp_path / "reg.json"
    res = run(["--points", "1500", "--reps", "2", "--threads", "1", "--out", str(out)])
    (row,) = res["rows"]
    assert row["points"] == 1500 and row["torch_ms"] > 0 and row["cpp_ms"] > 0
    assert row["grad_rel_diff"] < 1e-4  # the two backends give the same gradient
    assert row["grad_rel_err_vs_float64"]["cpp"] < 1e-4
    assert json.loads(out.read_text())["rows"][0]["speedup"] == pytest.approx(row["speedup"])
    assert [r["k"] for r in res["knn"]] == [16, 64] and all(r["identical"] for r in res["knn"])
