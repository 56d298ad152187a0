"""Analytic checks of the forward pass (paper Eqs. rk, filter, rho, sumI)."""

import math

import pytest
import torch
from scenes import (
    axis_camera,
    random_scene,
    require_vector_level,
    skip_without_vector_path,
    sphere_points,
    vector_levels,
)

from dss import reference as ref
from dss.fragments import Fragments
from dss.render import RenderSettings, render

BACKENDS = ["reference", "cpp"]


def _one_splat(normal, sigma, backend, Z=2.0, C=2.0, cull=True, shading="mask"):
    cams = axis_camera()
    p = torch.tensor([[0.0, 0.0, Z]])
    n = torch.tensor([normal], dtype=torch.float32)
    s = RenderSettings(cutoff=C, sigma=sigma, backface_culling=cull, merge_threshold=0.01)
    return render(p, n, cams, s, shading=shading, backend=backend), cams


@pytest.mark.parametrize("backend", BACKENDS)
def test_facing_splat_is_the_predicted_circle(backend, request):
    if backend == "cpp":
        request.getfixturevalue("cpp_backend")
    sigma, Z, f, C = 0.2, 2.0, 100.0, 2.0
    out, _ = _one_splat([0.0, 0.0, -1.0], sigma, backend)
    s2 = sigma**2 * (f / Z) ** 2 + 1.0  # J V J^T + I, isotropic here
    r = math.sqrt(2 * C * s2)
    area = out.mask.sum().item()
    assert area == pytest.approx(math.pi * r * r, rel=0.01)
    # peak weight |J| / (2 pi sqrt(det Sigma)) times the Gaussian at the nearest pixel centre
    rho = out.fragments.rho[0, 64, 64, 0].item()
    d2 = 0.5**2 + 0.5**2
    expect = (f / Z) ** 2 / (2 * math.pi * s2) * math.exp(-0.5 * d2 / s2)
    assert rho == pytest.approx(expect, rel=1e-5)


@pytest.mark.parametrize("theta_deg", [0.0, 45.0, 70.0])
def test_tilted_normal_shrinks_minor_axis_by_cos(theta_deg):
    sigma, Z, f, C = 0.25, 2.0, 100.0, 2.0
    th = math.radians(theta_deg)
    out, _ = _one_splat([math.sin(th), 0.0, -math.cos(th)], sigma, "reference")
    m = out.mask[0]
    width = m.any(0).sum().item()  # columns covered: extent along x
    height = m.any(1).sum().item()
    jvj_x = sigma**2 * (f / Z) ** 2 * math.cos(th) ** 2
    jvj_y = sigma**2 * (f / Z) ** 2
    rx, ry = math.sqrt(2 * C * (jvj_x + 1)), math.sqrt(2 * C * (jvj_y + 1))
    assert abs(width - 2 * rx) <= 2.0
    assert abs(height - 2 * ry) <= 2.0
    assert m.sum().item() == pytest.approx(math.pi * rx * ry, rel=0.02)
    if theta_deg > 0:  # the object-space part of the minor axis scales by cos(theta)
        assert (rx**2 / (2 * C) - 1) / (ry**2 / (2 * C) - 1) == pytest.approx(math.cos(th) ** 2, rel=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_sphere_silhouette_radius(backend, request):
    if backend == "cpp":
        request.getfixturevalue("cpp_backend")
    from dss.cameras import look_at

    rad, dist, f = 0.5, 3.0, 300.0
    p, n = sphere_points(20000, rad)
    cams = look_at(torch.tensor([[0.0, 0.0, dist]]), (0, 0, 0), focal=f, image_size=(128, 128))
    analytic = f * math.tan(math.asin(rad / dist))
    # With a narrow low-pass filter the silhouette is the analytic one.
    out = render(p, n, cams, RenderSettings(filter_variance=0.01), shading="mask", backend=backend)
    assert abs(math.sqrt(out.mask.sum().item() / math.pi) - analytic) <= 1.0
    # The paper's filter (variance 1 px^2) widens edge-on rim splats by its cutoff radius
    # sqrt(2 C) px, and by nothing more.
    s = RenderSettings()
    out = render(p, n, cams, s, shading="mask", backend=backend)
    widened = analytic + math.sqrt(2 * s.cutoff * s.filter_variance)
    assert abs(math.sqrt(out.mask.sum().item() / math.pi) - widened) <= 1.0
    assert out.mask[0, 64, 64] and not out.mask[0, 5, 5]


def _two_splats(dz, merge, backend="reference"):
    cams = axis_camera(32, 32)
    p = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.0 + dz]])
    n = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    col = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    s = RenderSettings(sigma=0.05, merge_threshold=merge)
    return render(p, n, cams, s, shading="albedo", colors=col, backend=backend).images[0, 16, 16]


def test_front_splat_hides_the_one_behind():
    px = _two_splats(0.5, merge=0.1)
    assert torch.allclose(px, torch.tensor([1.0, 0.0, 0.0]))


def test_merge_threshold_blends_within_T_only():
    within = _two_splats(0.05, merge=0.1)
    beyond = _two_splats(0.15, merge=0.1)
    assert within[0] > 0.05 and within[1] > 0.05  # blended
    assert torch.allclose(within.sum(), torch.tensor(1.0), atol=1e-6)  # normalised
    assert torch.allclose(beyond, torch.tensor([1.0, 0.0, 0.0]))


@pytest.mark.parametrize("backend", BACKENDS)
def test_back_faces_are_culled(backend, request):
    if backend == "cpp":
        request.getfixturevalue("cpp_backend")
    out, _ = _one_splat([0.0, 0.0, 1.0], 0.1, backend)
    assert not out.mask.any()
    out, _ = _one_splat([0.0, 0.0, 1.0], 0.1, backend, cull=False)
    assert out.mask.any()


def test_normalised_sum_is_invariant_to_weight_scale():
    pts, nrm, cams, sigma, colors = random_scene(1)
    out = render(pts, nrm, cams, RenderSettings(), shading="albedo", colors=colors, sigma=sigma, backend="reference")
    f = out.fragments
    scaled = Fragments(f.idx, f.depth, f.rho * 37.5, f.merge_threshold)
    a, _ = ref.blend_cached(f, out.attributes, 0.0)
    b, _ = ref.blend_cached(scaled, out.attributes, 0.0)
    assert torch.allclose(a, b, atol=1e-6)
    assert torch.allclose(a, out.images, atol=1e-6)


def test_normal_render_returns_the_normals():
    cams = axis_camera(48, 48)
    g = torch.linspace(-0.3, 0.3, 25)
    yy, xx = torch.meshgrid(g, g, indexing="ij")
    p = torch.stack([xx.flatten(), yy.flatten(), torch.full((625,), 2.0)], 1)
    nn = torch.tensor([0.3, -0.2, -0.93])
    nn = nn / nn.norm()
    out = render(p, nn.expand(625, 3).clone(), cams, RenderSettings(sigma=0.02), shading="normals", backend="reference")
    assert out.mask.sum() > 200
    assert torch.allclose(out.images[0][out.mask[0]], nn.expand(int(out.mask.sum()), 3), atol=1e-6)


def test_depth_render_is_inverse_depth():
    cams = axis_camera(32, 32)
    p = torch.tensor([[0.0, 0.0, 2.0]])
    out = render(p, torch.tensor([[0.0, 0, -1]]), cams, RenderSettings(sigma=0.05), shading="depth", backend="reference")
    assert out.images[0, 16, 16, 0].item() == pytest.approx(0.5)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("K", [1, 5, 8])
def test_backends_agree_on_random_scenes(seed, K, cpp_backend):
    """The rasteriser contract: from the same splats, identical caches and images."""
    from dss.rasterizer import rasterize
    from dss.reference import project_splats
    from dss.shading import shade

    pts, nrm, cams, sigma, colors = random_scene(seed, n=400)
    sp = project_splats(pts, nrm, cams, sigma, 1.0)
    attrs = shade("albedo", pts, nrm, cams, colors)
    bg = torch.zeros(3)
    fa, ia, ma = rasterize(sp, cams.image_size, K, 1.0, 0.05, "reference", attributes=attrs, background=bg)
    fb, ib, mb = rasterize(sp, cams.image_size, K, 1.0, 0.05, cpp_backend, attributes=attrs, background=bg)
    assert torch.equal(fa.idx, fb.idx)
    assert torch.equal(fa.depth, fb.depth)
    assert torch.allclose(fa.rho, fb.rho, rtol=1e-5, atol=1e-7)
    assert torch.allclose(ia, ib, atol=1e-5)
    assert torch.equal(ma, mb)
    assert ma.float().mean() > 0.05
    # end to end through render() (the C++ path also fuses the projection): same images
    s = RenderSettings(K=K, merge_threshold=0.05)
    a = render(pts, nrm, cams, s, shading="albedo", colors=colors, sigma=sigma, backend="reference")
    b = render(pts, nrm, cams, s, shading="albedo", colors=colors, sigma=sigma, backend=cpp_backend)
    differ = (a.images - b.images).abs().amax(-1) > 1e-5
    assert differ.float().mean() < 1e-3  # at most a few boundary pixels flip by one ulp of q


def test_bad_render_input_messages():
    cams = axis_camera(16, 16)
    with pytest.raises(ValueError, match="empty point cloud"):
        render(torch.zeros(0, 3), torch.zeros(0, 3), cams)
    with pytest.raises(ValueError, match="NaN or inf"):
        render(torch.tensor([[0.0, 0, float("nan")]]), torch.tensor([[0.0, 0, -1]]), cams)
    with pytest.raises(ValueError, match="normals must be"):
        render(torch.zeros(3, 3), torch.zeros(2, 3), cams)
    with pytest.raises(ValueError, match="unknown backend"):
        render(torch.zeros(3, 3), torch.zeros(3, 3), cams, backend="gpu-magic")
    with pytest.raises(ValueError, match="gradient must be"):
        RenderSettings(gradient="soft")
    with pytest.raises(ValueError, match="floating-point"):
        render(torch.zeros(3, 3, dtype=torch.int64), torch.ones(3, 3), cams)


def test_fused_cpp_projection_matches_torch(cpp_backend):
    from dss import _ext
    from dss.reference import project_splats

    for seed in range(3):
        pts, nrm, cams, sigma, _ = random_scene(seed, n=500)
        nrm[:5] = 0.0  # zero normals
        for cull in (True, False):
            a = project_splats(pts, nrm, cams, sigma, 1.3, cull, 1e-3, 0.7).packed
            b = _ext.load_cpu().project_splats_forward(pts, nrm, cams.R, cams.t, cams.focal, cams.principal, sigma,
                                                       1.3, cull, 1e-3, 0.7)
            assert torch.equal(a[..., 9], b[..., 9])
            assert torch.allclose(a, b, rtol=2e-5, atol=1e-5), (a - b).abs().max()


def test_cuda_backend_needs_cuda_tensors():
    cams = axis_camera(8, 8)
    with pytest.raises(ValueError, match="backend 'cuda' needs CUDA tensors"):
        render(torch.zeros(3, 3), torch.zeros(3, 3), cams, backend="cuda")


def test_points_and_cameras_on_different_devices_are_refused():
    cams = axis_camera(8, 8)
    with pytest.raises(ValueError, match=r"must be on one device \(cameras.to\(points.device\)\)"):
        render(torch.zeros(3, 3, device="meta"), torch.zeros(3, 3, device="meta"), cams)


def test_reused_output_blocks_are_fully_rewritten(cpp_backend):
    """The C++ kernels hand out parked output blocks again once nothing refers to them
    (cpu_runtime.cpp pooled_empty). A dense render followed by a sparse one of the same size must
    still give the sparse render's cache: every slot not written by a splat is -1 / inf / 0 and
    the mask false, as the reference rasteriser's."""
    from dss import _ext
    from dss.rasterizer import rasterize
    from dss.reference import project_splats

    _ext.empty_cache()  # only this test's blocks parked: the sparse render must get them back
    pts, nrm, cams, sigma, _ = random_scene(5, n=3000)
    dense = rasterize(project_splats(pts, nrm, cams, sigma * 2, 1.0), cams.image_size, 5, 1.0, 0.05, cpp_backend)
    assert (dense[0].idx[..., -1] >= 0).float().mean() > 0.05  # the last slot is used somewhere
    addresses = {t.data_ptr() for t in (dense[0].idx, dense[0].depth, dense[0].rho, dense[2])}
    del dense
    sp = project_splats(pts[:40], nrm[:40], cams, sigma[:40], 1.0)
    fa, _, ma = rasterize(sp, cams.image_size, 5, 1.0, 0.05, "reference")
    fb, _, mb = rasterize(sp, cams.image_size, 5, 1.0, 0.05, cpp_backend)
    assert {t.data_ptr() for t in (fb.idx, fb.depth, fb.rho, mb)} == addresses  # the blocks were reused
    assert torch.equal(fa.idx, fb.idx) and torch.equal(fa.depth, fb.depth) and torch.equal(ma, mb)
    assert torch.allclose(fa.rho, fb.rho, rtol=1e-5, atol=1e-7)
    del fb, mb
    assert _ext.empty_cache() > 0 and _ext.empty_cache() == 0  # parked again, then released


def _mapping_flags(address: int) -> list[str] | None:
    """The VmFlags of the mapping of this process that holds ``address`` (Linux), else None."""
    try:
        lines = open("/proc/self/smaps").read().splitlines()
    except OSError:
        return None
    inside = False
    for line in lines:
        head = line.split()[0] if line else ""
        if "-" in head and not head.endswith(":"):
            lo, hi = (int(x, 16) for x in head.split("-"))
            inside = lo <= address < hi
        elif inside and line.startswith("VmFlags:"):
            return line.split()[1:]
    return None


def test_large_output_blocks_are_marked_for_huge_pages(cpp_backend):
    """Output blocks of 2 MB or more (the top-K cache: 2.6 MB per array here) start on a 2 MB
    boundary and, on Linux, lie in a range advised for transparent huge pages (VmFlags "hg"), so
    that writing the cache out and reading its rows in scattered order take few TLB entries."""
    import sys

    from dss import _ext
    from dss.rasterizer import rasterize
    from dss.reference import project_splats

    _ext.empty_cache()  # a fresh block, not one parked before this code
    pts, nrm, cams, sigma, _ = random_scene(2, n=500, views=2, size=(256, 256))
    frags = rasterize(project_splats(pts, nrm, cams, sigma, 1.0), cams.image_size, 5, 1.0, 0.05, cpp_backend)[0]
    assert frags.idx.numel() * 4 >= 2 << 20
    for t in (frags.idx, frags.depth, frags.rho):
        assert t.data_ptr() % (2 << 20) == 0
        if sys.platform.startswith("linux"):
            flags = _mapping_flags(t.data_ptr())
            assert flags is not None and "hg" in flags, flags


def test_sun_shading_is_the_camera_space_diffuse_term():
    """SunLights turns the lights into world space (one product for all views); the result is
    the definition: ambient + max(0, (R_v n) . d_l) per light, coloured, for every view."""
    from dss.shading import SunLights

    pts, nrm, cams, _, _ = random_scene(4, n=200, views=4)
    sun = SunLights(colors=torch.tensor([[1.0, 0.2, 0.0], [0.0, 1.0, 0.0], [0.1, 0.0, 0.7]]))
    n = nrm.clone().requires_grad_()
    got = sun(pts, n, cams)
    n_cam = torch.einsum("vij,nj->vni", cams.R, nrm)
    want = (n_cam @ sun.directions.T).clamp_min(0) @ sun.colors + sun.ambient
    assert got.shape == (4, 200, 3)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    got.sum().backward()
    assert n.grad.abs().max() > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cpp_sun_shader_matches_the_torch_one(dtype, cpp_backend):
    """The cpp backend shades "sun" with the fused C++ kernels (dss.autograd.KernelSunShade): the same
    attributes as SunLights in torch, and the same gradients for normals (any length, a zero
    normal among them: torch's clamp passes the gradient at n . d = 0) and albedo; render()
    falls back to torch where the kernel cannot serve (cameras that require grad)."""
    from dss.cameras import Cameras
    from dss.render import _shade
    from dss.shading import SunLights

    pts, nrm, cams, _, colors = random_scene(6, n=2100, views=5)
    nrm = nrm * (0.5 + torch.rand(len(nrm), 1, generator=torch.Generator().manual_seed(1)))
    nrm[7] = 0.0
    pts, nrm, colors = pts.to(dtype), nrm.to(dtype), colors.to(dtype)
    cams = Cameras(cams.R.to(dtype), cams.t.to(dtype), cams.focal.to(dtype), cams.principal.to(dtype), cams.image_size)
    g = torch.randn(5, 2100, 3, generator=torch.Generator().manual_seed(2), dtype=dtype)
    sun = SunLights()
    for albedo in (None, colors):
        grads = []
        for fused in (False, True):
            n = nrm.clone().requires_grad_()
            a = None if albedo is None else albedo.clone().requires_grad_()
            out = _shade("sun", pts, n, cams, a, cpp_backend) if fused else sun(pts, n, cams, a)
            assert out.shape == (5, 2100, 3)
            assert (type(out.grad_fn).__name__ == "KernelSunShadeBackward") == fused
            (out * g).sum().backward()
            grads.append((out.detach().float(), n.grad, None if a is None else a.grad))
        (w_t, gn_t, ga_t), (w_c, gn_c, ga_c) = grads
        torch.testing.assert_close(w_c, w_t, rtol=1e-6, atol=1e-6)
        assert gn_c.dtype == dtype and gn_t[7].abs().max() > 0
        torch.testing.assert_close(gn_c, gn_t, rtol=1e-5, atol=1e-5)
        if albedo is not None:
            torch.testing.assert_close(ga_c, ga_t, rtol=1e-5, atol=1e-5)
    # cameras that require grad take the torch path, and get their gradient
    R = cams.R.clone().requires_grad_()
    out = _shade("sun", pts, nrm, Cameras(R, cams.t, cams.focal, cams.principal, cams.image_size), None, cpp_backend)
    assert type(out.grad_fn).__name__ != "KernelSunShadeBackward"
    out.sum().backward()
    assert R.grad is not None and R.grad.abs().max() > 0


@pytest.mark.parametrize("K,C", [(5, 3), (5, 1), (5, 0), (1, 3), (3, 2), (8, 1)])
def test_vector_rasteriser_gives_the_scalar_bits(K, C, cpp_backend):
    """The AVX2 tile loop (rasterize_cpu_avx2.h tile_fragments_avx2: 16 pixels' cutoff and top-K gate
    tests at once, rows skipped when every list in them is full and closer) builds exactly the
    scalar loop's caches and images, at every vector level (level 2 adds the AVX-512 build of the
    binning's box scan). The scene has many layers per pixel (full lists, the gate
    and the row skip at work), duplicated points (equal depths: the index breaks the tie), splats
    over the image border and an image whose width and height are not multiples of the 16-pixel
    tile; (K, C) cover the compiled variants and the run-time one, C = 0 the cache alone."""
    from dss import _ext
    from dss.reference import project_splats

    mod = _ext.load_cpu()
    levels = vector_levels(mod)
    pts, nrm, cams, sigma, _ = random_scene(K * 10 + C, n=2500, views=3, size=(45, 70))
    pts = torch.cat([pts * 1.3, pts[:300] * 1.3])  # 300 exact duplicates
    nrm = torch.cat([nrm, nrm[:300]])
    sigma = torch.cat([sigma, sigma[:300]]) * 2.0
    packed = project_splats(pts, nrm, cams, sigma, 1.0).packed.float().contiguous()
    attrs = torch.rand(packed.shape[0], packed.shape[1], C, generator=torch.Generator().manual_seed(3))
    bg = torch.full((C,), 0.25)
    H, W = cams.image_size
    before = mod.set_vector_level(0)
    try:
        scalar = [t.clone() for t in mod.rasterize_forward(packed, attrs, H, W, K, 1.0, 0.05, bg)]
        by_level = {}
        for level in levels:
            mod.set_vector_level(level)
            by_level[level] = [t.clone() for t in mod.rasterize_forward(packed, attrs, H, W, K, 1.0, 0.05, bg)]
    finally:
        mod.set_vector_level(before)
    idx = scalar[0]
    assert (idx[..., -1] >= 0).float().mean() > 0.2  # many full lists
    same = (idx[..., :-1] == idx[..., 1:]) & (idx[..., :-1] >= 0)
    assert not same.any()
    dup_in_one_list = ((idx[..., :, None] % 2500 == idx[..., None, :] % 2500) & (idx[..., :, None] != idx[..., None, :])
                       & (idx[..., :, None] >= 0)).any()
    assert K == 1 or dup_in_one_list  # a duplicate pair met in some list: the tie rule decided
    for level, vec in by_level.items():
        for name, a, b in zip(("idx", "depth", "rho", "images", "mask"), vec, scalar):
            assert torch.equal(a, b), f"level {level}: {name} differs"


def _quad32(conic, dx, dy):
    """The kernels' q = a dx^2 + b2 dx dy + c dy^2, float32 operations in their order."""
    return ((conic[0] * dx) * dx + (conic[1] * dx) * dy) + (conic[2] * dy) * dy


def _splat_with_a_pixel_on_its_ellipse(rng, i: int, j: int, row_minimum: bool, two_c):
    """A packed splat (10,) whose cutoff ellipse passes through the centre of pixel (i, j): its
    conic is the largest float32 scaling whose q there is still <= 2 cutoff, and that pixel holds
    the form's minimum over its row (row_minimum: the ellipse's top or bottom) or over its column
    (its left or right end). Conics from round to strongly elongated (4ac / b2^2 down to 1.001);
    a third of the boxes (rx, ry) are up to 60% loose, the rest exact."""
    import numpy as np

    f32 = np.float32
    off = rng.uniform(0.3, 6.0, 2) * rng.choice([-1.0, 1.0], 2)
    u, v = f32(j + 0.5 - off[0]), f32(i + 0.5 - off[1])
    dx, dy = (f32(j) + f32(0.5)) - u, (f32(i) + f32(0.5)) - v
    ill = np.exp(rng.uniform(np.log(1e-3), np.log(3.0)))  # 4ac / b2^2 - 1: small is elongated
    if row_minimum:  # b2 = -2 a dx / dy puts the row's minimum at dx
        a = np.exp(rng.uniform(-3, 1))
        b2 = -2 * a * float(dx) / float(dy)
        c = b2 * b2 / (4 * a) * (1 + ill) + 1e-3
    else:  # b2 = -2 c dy / dx puts the column's minimum at dy
        c = np.exp(rng.uniform(-3, 1))
        b2 = -2 * c * float(dy) / float(dx)
        a = b2 * b2 / (4 * c) * (1 + ill) + 1e-3
    conic = np.array([a, b2, c], np.float32)
    lo, hi = 0.5 * two_c / _quad32(conic, dx, dy), 2.0 * two_c / _quad32(conic, dx, dy)
    for _ in range(60):  # bisection on the scale
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _quad32((conic * mid).astype(np.float32), dx, dy) <= two_c else (lo, mid)
    conic = (conic * lo).astype(np.float32)
    a, b2, c = conic.astype(np.float64)
    assert 4 * a * c - b2 * b2 > 0  # still positive definite after rounding
    cov = np.linalg.inv(np.array([[a, b2 / 2], [b2 / 2, c]]))
    loose = rng.uniform(1.0, 1.6) if rng.random() < 1 / 3 else 1.0
    rx, ry = (np.sqrt(float(two_c) * np.diag(cov)) * loose * (1 + 1e-4)).astype(np.float32)
    return np.array([u, v, *conic, rng.uniform(0.5, 2.0), rng.uniform(1.0, 3.0), rx, ry, 1.0], np.float32)


@pytest.mark.parametrize("level", [2, 1, 0], ids=["avx512", "avx2", "scalar"])
def test_tightened_boxes_keep_pixels_on_the_cutoff_ellipse(level, cpp_backend):
    """The C++ binning shrinks each splat's box to the rows and columns that can hold a pixel with
    0.5 q <= cutoff (splat_math.h tighten_box: the form's minimum over a row or a column, with a
    margin for quad()'s float32 rounding); the reference tests every pixel of the padded box. Each
    splat has one pixel centre on its cutoff ellipse where the form is minimal over that pixel's
    row or column (_splat_with_a_pixel_on_its_ellipse). The caches must be identical and hold most
    of those pixels. Without the rounding margin (the kernel edited to g = det4), or with a
    margin 10^-6 too small (g = det4 * (1 + 1e-6)), boundary rows are dropped and the caches
    differ."""
    import numpy as np

    from dss import _ext
    from dss.splats import Splats

    mod = _ext.load_cpu()
    require_vector_level(mod, level)
    rng = np.random.default_rng(7)
    H, W, V, N, cutoff = 40, 56, 2, 300, 1.0
    edge = [(v, k, int(rng.integers(0, H)), int(rng.integers(0, W))) for v in range(V) for k in range(N)]
    packed = torch.from_numpy(np.stack([_splat_with_a_pixel_on_its_ellipse(rng, i, j, k % 2 == 1, np.float32(2 * cutoff))
                                        for _, k, i, j in edge]).reshape(V, N, 10))
    want = ref.rasterize(Splats(packed), (H, W), K=8, cutoff=cutoff)
    before = mod.set_vector_level(level)
    try:
        idx, depth, rho, _, _ = mod.rasterize_forward(packed, torch.empty(0), H, W, 8, cutoff, 0.0, torch.empty(0))
    finally:
        mod.set_vector_level(before)
    assert torch.equal(idx, want.idx) and torch.equal(depth, want.depth)
    torch.testing.assert_close(rho, want.rho, rtol=1e-6, atol=1e-7)
    on_edge = sum(bool((want.idx[v, i, j] == k).any()) for v, k, i, j in edge)
    assert on_edge > 0.5 * len(edge)  # most boundary pixels made it into their (8-deep) lists


@pytest.mark.parametrize("vector", [False, True], ids=["scalar", "avx2"])
def test_kernel_exp_is_within_one_ulp_and_the_same_on_both_paths(vector, cpp_backend):
    """The kernels' exp (dss_splat::splat_exp, in float32 operations so that the CPU's scalar and
    AVX2 paths and the CUDA kernel give the same bits) is within 1 ulp of the correctly rounded
    exp over the range the splat weights use (x = -q/2 in [-cutoff, 0]) and beyond, down to the
    denormals and to 0, and its AVX2 twin gives the scalar bits."""
    import numpy as np

    from dss import _ext

    mod = _ext.load_cpu()
    if vector and not mod.vector_path_available():
        skip_without_vector_path()
    x = torch.cat([torch.linspace(-110.0, 88.0, 400_003), -torch.rand(100_000, generator=torch.Generator().manual_seed(1)) * 6,
                   torch.tensor([0.0, -0.0, 1e-30, -1e-30, -103.9, -104.0, -200.0, 88.0])]).float()
    before = mod.set_vector_path(vector)
    try:
        got = mod.splat_exp(x)
        mod.set_vector_path(False)
        scalar = mod.splat_exp(x)
    finally:
        mod.set_vector_path(before)
    assert torch.equal(got, scalar)
    want = torch.from_numpy(np.exp(x.double().numpy()).astype(np.float32))  # correctly rounded (float64 first)
    normal = want >= torch.finfo(torch.float32).tiny
    ulps = (got[normal].view(torch.int32).long() - want[normal].view(torch.int32).long()).abs()
    assert ulps.max().item() <= 1 and (ulps == 0).float().mean().item() > 0.85
    assert (got[~normal] - want[~normal]).abs().max().item() <= 2e-45  # denormals: within 1 of their ulp
    assert got[x <= -104].eq(0).all() and got[x == 0].eq(1).all()
