"""The backward pass: visibility gradient (Eqs. gradcase, filteredG) and the smooth terms."""

import pytest
import torch
from scenes import axis_camera, random_scene, skip_without_vector_path, vector_levels

from dss.render import RenderSettings, render

Z = 2.0
FOCAL = 100.0


def _chase_one_point(mode, sigma, shift_px=15, steps=120):
    """Adam on a single point until it is within 1 px of the target; returns steps or None."""
    cams = axis_camera(64, 64, FOCAL)
    tgt_p = torch.tensor([[shift_px * Z / FOCAL, 0.0, Z]])
    n = torch.tensor([[0.0, 0, -1]])
    s = RenderSettings(sigma=sigma, gradient=mode, window=24, merge_threshold=0.05)
    col = torch.ones(1, 3)
    tgt = render(tgt_p, n, cams, s, shading="albedo", colors=col).images
    p = torch.tensor([[0.0, 0.0, Z]], requires_grad=True)
    opt = torch.optim.Adam([p], lr=0.01)
    for it in range(steps):
        opt.zero_grad()
        loss = (render(p, n, cams, s, shading="albedo", colors=col).images - tgt).abs().sum()
        loss.backward()
        opt.step()
        if (p.detach()[0, :2] - tgt_p[0, :2]).norm().item() * FOCAL / Z < 1.0:
            return it + 1
    return None


def test_one_point_reaches_target_independent_of_sigma(cpp_backend):
    dss = [_chase_one_point("dss", s) for s in (0.02, 0.05, 0.1)]
    assert all(d is not None and d <= 60 for d in dss), dss
    assert max(dss) <= 1.3 * min(dss), dss  # barely depends on sigma
    rbf = [_chase_one_point("rbf", s) for s in (0.02, 0.05, 0.1)]
    # The RBF gradient vanishes beyond a few sigma: the small splats never get there.
    assert rbf[0] is None, rbf


def _wall_and_hidden_point(hidden_z):
    g = torch.linspace(-0.3, 0.3, 21)
    yy, xx = torch.meshgrid(g, g, indexing="ij")
    wall = torch.stack([xx.flatten(), yy.flatten(), torch.full((441,), Z)], 1)
    pts = torch.cat([wall, torch.tensor([[0.01, 0.01, hidden_z]])])
    nrm = torch.tensor([0.0, 0.0, -1.0]).expand(442, 3).clone()
    col = torch.cat([torch.full((441, 3), 0.3), torch.tensor([[1.0, 0.0, 0.0]])])
    return pts, nrm, col


def test_hidden_point_comes_forward_case_b(cpp_backend):
    cams = axis_camera(48, 48, FOCAL)
    s = RenderSettings(sigma=0.03, merge_threshold=0.05, window=4)
    tp, n, col = _wall_and_hidden_point(Z - 0.1)  # target: the red point in front of the wall
    tgt = render(tp, n, cams, s, shading="albedo", colors=col).images
    pts, n, col = _wall_and_hidden_point(Z + 0.5)
    for backend in ("reference", cpp_backend):
        p = pts.clone().requires_grad_()
        loss = (render(p, n, cams, s, shading="albedo", colors=col, backend=backend).images - tgt).abs().sum()
        loss.backward()
        assert p.grad[441, 2] > 0, "descent must move the hidden point towards the camera (-z)"
    p = pts.clone().requires_grad_()
    opt = torch.optim.Adam([p], lr=0.02)
    for _ in range(60):
        opt.zero_grad()
        out = render(p, n, cams, s, shading="albedo", colors=col)
        (out.images - tgt).abs().sum().backward()
        p.grad[:441] = 0  # only the hidden point moves
        opt.step()
    out = render(p.detach(), n, cams, s, shading="albedo", colors=col)
    assert p[441, 2].item() < Z + 0.05
    assert out.images[0, 24, 24, 0] > 0.6  # it shows


def test_two_points_reach_two_targets(cpp_backend):
    cams = axis_camera(64, 64, FOCAL)
    px = Z / FOCAL
    start = torch.tensor([[-10 * px, 0.0, Z], [10 * px, 0.0, Z]])
    target = torch.tensor([[-8 * px, 12 * px, Z], [12 * px, -12 * px, Z]])
    n = torch.tensor([[0.0, 0, -1]] * 2)
    col = torch.ones(2, 3)
    s = RenderSettings(sigma=0.03, merge_threshold=0.05, window=24)
    tgt = render(target, n, cams, s, shading="albedo", colors=col).images
    p = start.clone().requires_grad_()
    opt = torch.optim.Adam([p], lr=0.01)
    for _ in range(150):
        opt.zero_grad()
        (render(p, n, cams, s, shading="albedo", colors=col).images - tgt).abs().sum().backward()
        opt.step()
    d = torch.cdist(p.detach()[:, :2], target[:, :2]) / px  # pixels
    assert d.diagonal().max() < 1.5 or d.flip(1).diagonal().max() < 1.5, d


def test_gradcheck_smooth_part_double():
    # Huge cutoff and merge threshold: every splat covers every pixel and is visible, so the
    # image is a smooth function of positions, normals and colours (no visibility events).
    cams = axis_camera(6, 6, 10.0)
    cams = type(cams)(cams.R.double(), cams.t.double(), cams.focal.double(), cams.principal.double(), cams.image_size)
    pts = torch.tensor([[0.05, 0.02, 2.0], [-0.1, 0.05, 2.2], [0.0, -0.1, 2.4]], dtype=torch.float64, requires_grad=True)
    nrm = torch.tensor([[0.1, 0.0, -1.0], [0.0, 0.2, -1.0], [-0.1, -0.1, -1.0]], dtype=torch.float64, requires_grad=True)
    col = torch.rand(3, 3, dtype=torch.float64, requires_grad=True)
    s = RenderSettings(cutoff=200.0, merge_threshold=10.0, K=8, sigma=0.3, gradient="none")

    def f(p, n, c):
        return render(p, n, cams, s, shading="albedo", colors=c, backend="reference").images

    assert torch.autograd.gradcheck(f, (pts, nrm, col), eps=1e-6, atol=1e-5, rtol=1e-4)

    def g(p, n):
        return render(p, n, cams, s, shading="sun", backend="reference").images

    assert torch.autograd.gradcheck(g, (pts, nrm), eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("mode", ["dss", "rbf"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cpp_and_reference_gradients_agree(seed, mode, cpp_backend):
    """Seeds cover the kernel's compiled variants: (K, channels) = (5, 3), any (3, 3), (5, 1)."""
    pts, nrm, cams, sigma, colors = random_scene(seed, n=300)
    tgt_pts = pts + 0.05 * torch.randn(pts.shape, generator=torch.Generator().manual_seed(seed + 50))
    s = RenderSettings(K=(5, 3, 5)[seed], merge_threshold=0.05, window=5, window_stride=1 + seed % 2, gradient=mode)
    shading = ("sun", "sun", "mask")[seed]
    tgt = render(tgt_pts, nrm, cams, s, shading=shading, sigma=sigma).images
    grads = {}
    for backend in ("reference", cpp_backend):
        p = pts.clone().requires_grad_()
        n = nrm.clone().requires_grad_()
        img = render(p, n, cams, s, shading=shading, sigma=sigma, backend=backend).images
        assert img.shape[-1] == (1 if shading == "mask" else 3)
        # squared error: an L1 sign flips where the two backends' images differ by one ulp
        ((img - tgt) ** 2).sum().backward()
        grads[backend] = (p.grad, n.grad)
    (gp_r, gn_r), (gp_c, gn_c) = grads["reference"], grads[cpp_backend]
    assert gp_r.abs().max() > 0
    assert torch.allclose(gp_r, gp_c, rtol=1e-3, atol=1e-4 * gp_r.abs().max().item())
    assert torch.allclose(gn_r, gn_c, rtol=1e-3, atol=1e-6)


@pytest.mark.parametrize("seed", range(5))
def test_step_along_gradient_does_not_increase_loss(seed, cpp_backend):
    pts, nrm, cams, sigma, colors = random_scene(seed, n=300)
    tgt_pts = pts + 0.05 * torch.randn(pts.shape, generator=torch.Generator().manual_seed(100 + seed))
    s = RenderSettings(merge_threshold=0.05, window=6)
    tgt = render(tgt_pts, nrm, cams, s, shading="albedo", colors=colors, sigma=sigma).images
    p = pts.clone().requires_grad_()
    loss = (render(p, nrm, cams, s, shading="albedo", colors=colors, sigma=sigma).images - tgt).abs().sum()
    loss.backward()
    for px in (0.25, 1.0):  # largest move: px pixels (focal 60 at distance 3: 1 px = 0.05)
        step = p.grad / p.grad.abs().max() * px * 0.05
        with torch.no_grad():
            after = (render(pts - step, nrm, cams, s, shading="albedo", colors=colors, sigma=sigma).images - tgt).abs().sum()
        assert after <= loss.detach()


@pytest.mark.parametrize("backend", ["reference", "cpp"])
def test_filter_drops_terms_that_cannot_help(backend, request):
    # One white splat on black, window 0 (only the pixel under its centre, where it is visible).
    # Loss = +I there: removing the splat (dI < 0) helps, the term is kept. Loss = -I: removing
    # it cannot help, Eq. filteredG zeroes the term. The RBF gradient has no such filter.
    if backend == "cpp":
        request.getfixturevalue("cpp_backend")
    cams = axis_camera(16, 16, FOCAL)
    n = torch.tensor([[0.0, 0, -1]])
    col = torch.ones(1, 3)
    start = torch.tensor([[0.3 * Z / FOCAL, 0.2 * Z / FOCAL, Z]])  # off the pixel centre
    grads = {}
    for mode in ("dss", "rbf"):
        for sign in (1.0, -1.0):
            p = start.clone().requires_grad_()
            s = RenderSettings(sigma=0.05, window=0, gradient=mode, merge_threshold=0.05)
            img = render(p, n, cams, s, shading="albedo", colors=col, backend=backend).images
            # only the visibility term: colours are constant, the splat shape is position-invariant
            (sign * img[0, 8, 8].sum()).backward()
            grads[mode, sign] = p.grad.clone()
    assert grads["dss", 1.0].abs().max() > 0
    assert grads["dss", -1.0].abs().max() == 0
    assert grads["rbf", 1.0].abs().max() > 0 and grads["rbf", -1.0].abs().max() > 0


def test_degenerate_input_gives_finite_gradients(cpp_backend):
    cams = axis_camera(32, 32, 50.0)
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 1e-9], [0.0, 0.1, 2.0], [0.05, 0.05, 2.0], [0.0, 0.0, 2.0]])
    nrm = torch.tensor([[0.0, 0, -1], [0.0, 0, -1], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0, -1]])
    tgt = torch.rand(1, 32, 32, 3)
    for backend in ("reference", cpp_backend):
        for mode in ("dss", "rbf"):
            p = pts.clone().requires_grad_()
            n = nrm.clone().requires_grad_()
            img = render(p, n, cams, RenderSettings(sigma=0.05, gradient=mode), backend=backend).images
            (img - tgt).abs().sum().backward()
            assert torch.isfinite(img).all()
            assert torch.isfinite(p.grad).all() and torch.isfinite(n.grad).all()
    # everything culled (all back-facing): empty image, zero gradients
    p = pts[2:].clone().requires_grad_()
    back = torch.tensor([[0.0, 0, 1.0]]).expand(3, 3).clone().requires_grad_()
    img = render(p, back, cams, RenderSettings(sigma=0.05)).images
    (img - tgt).abs().sum().backward()
    assert not img.any() and torch.isfinite(p.grad).all() and p.grad.abs().max() == 0


def test_colors_receive_gradients():
    pts, nrm, cams, sigma, colors = random_scene(4, n=100)
    c = colors.clone().requires_grad_()
    img = render(pts, nrm, cams, RenderSettings(), shading="albedo", colors=c, sigma=sigma).images
    img.sum().backward()
    assert c.grad.abs().sum() > 0


def _shrink_scene(n=2000, size=96, views=6):
    """A sphere of radius 0.3 rendered against a target sphere of radius 0.24 (same normals)."""
    from scenes import sphere_points

    from dss.views import SphereViewSampler

    sp, sn = sphere_points(n, 0.3)
    tp, tn = sphere_points(n, 0.24)
    cams = SphereViewSampler((0.0, 0.0, 0.0), 0.5, views, size, 30.0, 0.1, seed=0).sample()
    return sp, sn, tp, tn, cams


@pytest.mark.parametrize("backend", ["reference", "cpp"])
def test_occlusion_depth_plane_shrinks_a_sphere(backend, request):
    """The visibility gradient with tangent-plane depths is a descent direction for a sphere that
    must shrink; with centre depths (the paper's text read literally) the occluded-case terms pull
    the visible surface toward every camera and the same step raises the loss (inflation)."""
    if backend == "cpp":
        backend = request.getfixturevalue("cpp_backend")
    from dss.losses import smape_loss

    sp, sn, tp, tn, cams = _shrink_scene()
    changes = {}
    for depth_mode in ("plane", "center"):
        s = RenderSettings(window=8, window_stride=1, occlusion_depth=depth_mode)
        tgt = render(tp, tn, cams, s, shading="sun", backend=backend).images
        p = sp.clone().requires_grad_()
        loss = smape_loss(render(p, sn, cams, s, shading="sun", backend=backend).images, tgt, channel_reduction="mean")
        loss.backward()
        g = p.grad
        radial = float((-g * sn).sum(1).mean())  # > 0: the descent step moves points outward
        step = g / g.norm(dim=1).max() * 0.01  # largest move: 1% of the radius-0.5 view sphere
        with torch.no_grad():
            after = smape_loss(render(sp - step, sn, cams, s, shading="sun", backend=backend).images, tgt,
                               channel_reduction="mean")
        changes[depth_mode] = (float(after - loss.detach()), radial)
    assert changes["plane"][0] < 0 and changes["plane"][1] < 0, changes  # shrinks, loss falls
    assert changes["center"][0] > changes["plane"][0], changes


def test_tangent_planes_reproduce_the_centre_depth():
    """At the splat's own centre pixel the plane depth is the centre depth; "center" is constant."""
    from dss.reference import project_splats, tangent_planes

    pts, nrm, cams, sigma, _ = random_scene(3, n=200)
    packed = project_splats(pts, nrm, cams, sigma).packed
    for mode in ("plane", "center"):
        pl = tangent_planes(pts, nrm, cams, mode)
        u, v, z = packed[..., 0], packed[..., 1], packed[..., 6]
        ok = packed[..., 9] > 0
        iz = pl[..., 0] * u + pl[..., 1] * v + pl[..., 2]
        assert torch.allclose((1 / iz)[ok], z[ok], rtol=1e-4)
    with pytest.raises(ValueError, match="occlusion_depth"):
        RenderSettings(occlusion_depth="middle")


def test_tangent_plane_kernel_matches_its_torch_twin(cpp_backend):
    """dss_cpu tangent_planes_forward (render()'s planes on the cpp backend) gives the torch
    tangent_planes' planes to float32 rounding, in both modes and for float64 inputs; points
    behind the camera get 1 / z = 0 in "center" mode. (Planes nearly through the camera centre, n . p ~ 0, are
    ill-conditioned: both sides' coefficients are then rounding noise, so they are left out.)"""
    from dss import _ext
    from dss.reference import tangent_planes

    mod = _ext.load_cpu()
    pts, nrm, cams, _, _ = random_scene(4, n=3001, views=5)
    c = -(cams.R[0].T @ cams.t[0])  # camera 0's centre (world)
    pts[:20] = c + cams.R[0].T @ torch.tensor([0.0, 0.0, -0.5]) + 0.05 * torch.randn(
        20, 3, generator=torch.Generator().manual_seed(5))  # behind camera 0
    pc = cams.to(torch.float64).world_to_camera(pts.double())
    nc = torch.einsum("vij,nj->vni", cams.R.double(), nrm.double())
    cond = ((nc * pc).sum(-1).abs() / (nc.norm(dim=-1) * pc.norm(dim=-1))) > 1e-2  # (V, N)
    assert cond.float().mean() > 0.8
    for mode in ("plane", "center"):
        want = tangent_planes(pts, nrm, cams, mode).float()
        for dt in (torch.float32, torch.float64):
            c2 = cams.to(dt)
            got = mod.tangent_planes_forward(pts.to(dt), nrm.to(dt), c2.R, c2.t, c2.focal, c2.principal,
                                             mode == "center")
            assert got.dtype == torch.float32 and got.shape == want.shape
            scale = want.abs().amax(-1, keepdim=True).clamp_min(1e-12)  # entries differ in size
            rel = ((got - want).abs() / scale).amax(-1)
            assert rel[cond].max() < 1e-4, (mode, dt, rel[cond].max().item())  # ulps / cond
            if mode == "center":  # behind camera 0: 1/z = 0
                assert (got[0, :20] == 0).all() and (want[0, :20] == 0).all()


@pytest.mark.parametrize("backend", ["reference", "cpp", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_spatial_sort_changes_nothing_but_speed(backend, request):
    """render() draws a Morton-sorted copy (dss.ordering) and maps everything back: images,
    gradients (per-point sigma and colours included), the fragment cache and the splats equal
    an unsorted render's, in the caller's order."""
    from dss.optimize import occlusion_counts
    from dss.ordering import SORT_MIN_POINTS

    if backend == "cpp":
        backend = request.getfixturevalue("cpp_backend")
    pts, nrm, cams, sigma, colors = random_scene(7, n=SORT_MIN_POINTS + 500, views=2, size=(32, 40))
    sigma = sigma * 0.3
    if backend == "cuda":
        if not torch.cuda.is_available():
            pytest.skip("no CUDA GPU")
        pts, nrm, sigma, colors, cams = pts.cuda(), nrm.cuda(), sigma.cuda(), colors.cuda(), cams.to("cuda")
    res = {}
    for sort in (False, True):
        p, n, c = (t.clone().requires_grad_() for t in (pts, nrm, colors))
        out = render(p, n, cams, RenderSettings(spatial_sort=sort, merge_threshold=0.05), shading="albedo",
                     colors=c, sigma=sigma, backend=backend)
        assert (out.point_order is not None) == sort
        (out.images * torch.linspace(0, 1, 3, device=out.images.device)).sum().backward()
        res[sort] = (out.images.detach(), p.grad, n.grad, c.grad, out.fragments.idx, out.splats.packed.detach(),
                     out.attributes.detach(), occlusion_counts(out), out.sigma)
    for a, b in zip(res[False], res[True]):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    assert res[True][1].abs().max() > 0 and (res[True][4] >= 0).any()


def test_cpp_morton_order_equals_the_torch_one(cpp_backend):
    """The C++ Z-order permutation (ordering_cpu.cpp morton_order, taken by spatial_order on CPU float32)
    equals morton_codes + stable argsort exactly: flat and elongated boxes (the per-axis scale),
    exact duplicates (equal codes keep their index order), a single point, and points on the box's
    far faces (the clamp to 1023)."""
    from dss import _ext
    from dss.ordering import morton_codes, spatial_order

    mod = _ext.load_cpu()
    g = torch.Generator().manual_seed(3)
    clouds = [torch.randn(5000, 3, generator=g) * torch.tensor([1.0, 40.0, 1e-4]),
              torch.rand(3000, 3, generator=g).round(decimals=1),  # many equal codes
              torch.zeros(1, 3), torch.tensor([[0.0, 0, 0], [1, 1, 1], [1, 0, 1], [0.5, 0.5, 0.5]])]
    # on the grid lines (x = i ext / 1023): the cell an axis value falls in depends on the rounding
    # of 1023 / ext, which torch evaluates as ext.reciprocal() * 1023
    x = torch.arange(1024, dtype=torch.float32) * (1.7 / 1023)
    clouds.append(torch.stack([x, x.flip(0), x.roll(7)], 1))
    for pts in clouds:
        pts = torch.cat([pts, pts.flip(0)])
        ref = torch.argsort(morton_codes(pts), stable=True)
        assert torch.equal(mod.morton_order(pts), ref)
        assert torch.equal(spatial_order(pts), ref)
    assert len(set(morton_codes(clouds[1]).tolist())) < 3000  # the ties were there


def test_spatial_order_is_reused_only_for_equal_points():
    """spatial_order keeps its last CPU orders with copies of the points: equal points (the same
    tensor or an equal one) get theirs again, as a copy the caller may edit; points edited in any way
    (in place, even through .data or numpy, which autograd's version counter does not see) are
    sorted afresh."""
    from dss.ordering import morton_codes, spatial_order

    pts = torch.randn(4000, 3, generator=torch.Generator().manual_seed(8))
    first = spatial_order(pts)
    again = spatial_order(pts)
    assert torch.equal(first, again) and first.data_ptr() != again.data_ptr()
    again.zero_()  # the caller's copy
    assert torch.equal(spatial_order(pts.clone()), first)
    other = [torch.randn(4000, 3, generator=torch.Generator().manual_seed(9 + i)) for i in range(3)]
    for q in other:  # three more clouds in between: the first one's order is still kept
        spatial_order(q)
    assert torch.equal(spatial_order(pts), first)
    pts.data[:100] = pts.data[:100].flip(0)
    pts.numpy()[200] += 5.0
    assert torch.equal(spatial_order(pts), torch.argsort(morton_codes(pts), stable=True))
    assert not torch.equal(spatial_order(pts), first)


def test_kernel_uses_every_thread_and_gives_the_same_bits(cpp_backend):
    """The C++ kernel is built with OpenMP on Linux (without it at::parallel_for silently runs on
    one thread), and its three kernels give the same bits on 1 and 2 threads for the same inputs:
    each owns its outputs per pixel / point / view and sums in a fixed order. (torch's own ops,
    e.g. the projection, may differ in the last bit between thread counts, so the inputs are
    fixed here.)"""
    import sys

    from dss import _ext
    from dss.reference import tangent_planes

    if sys.platform.startswith("linux"):
        assert _ext.openmp_enabled() is True
    mod = _ext.load_cpu()
    pts, nrm, cams, sigma, _ = random_scene(3, n=1500, views=3, size=(48, 64))
    out = render(pts, nrm, cams, RenderSettings(window=4, spatial_sort=False), sigma=sigma, backend=cpp_backend)
    packed, attrs = out.splats.packed.detach().float().contiguous(), out.attributes.detach().float().contiguous()
    planes = tangent_planes(pts, nrm, cams).float().contiguous()
    H, W = cams.image_size
    bg = torch.zeros(3)
    before = torch.get_num_threads()
    res = {}
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            idx, depth, rho, images, _ = mod.rasterize_forward(packed, attrs, H, W, 5, 3.0, 0.05, bg)
            grad = torch.linspace(-1, 1, images.numel()).view_as(images).contiguous()
            g_packed, g_attrs = mod.blend_backward(packed, attrs, idx, depth, rho, images, grad, 0.05)
            g_vis = mod.visibility_backward(packed, attrs, idx, depth, rho, images, grad, cams.R.float(),
                                            cams.focal.float(), cams.principal.float(), bg, planes, 4, 1, 3.0, 0.05,
                                            1e-6, 0)
            res[threads] = (idx, depth, rho, images, g_packed, g_attrs, g_vis)
    finally:
        torch.set_num_threads(before)
    for a, b in zip(res[1], res[2]):
        assert torch.equal(a, b)
    assert (res[2][0] >= 0).any() and res[2][4].abs().max() > 0 and res[2][6].abs().max() > 0



def test_blend_backward_with_the_mask_gives_the_bits_without_it(cpp_backend):
    """blend_backward given the rasteriser's mask (what render() passes: it then visits only the
    mask's pixels, never reading the cache rows of the others) gives exactly what it gives when it
    finds those pixels itself from every cache row; a mask of the wrong shape is refused."""
    from dss import _ext

    mod = _ext.load_cpu()
    pts, nrm, cams, sigma, _ = random_scene(5, n=1500, views=3, size=(48, 64))
    out = render(pts, nrm, cams, RenderSettings(spatial_sort=False), sigma=sigma, backend=cpp_backend)
    packed, attrs = out.splats.packed.detach().float().contiguous(), out.attributes.detach().float().contiguous()
    H, W = cams.image_size
    idx, depth, rho, images, mask = mod.rasterize_forward(packed, attrs, H, W, 5, 3.0, 0.05, torch.zeros(3))
    assert 0.05 < mask.float().mean() < 0.95
    grad = torch.linspace(-1, 1, images.numel()).view_as(images).contiguous()
    with_mask = mod.blend_backward(packed, attrs, idx, depth, rho, images, grad, 0.05, mask)
    without = mod.blend_backward(packed, attrs, idx, depth, rho, images, grad, 0.05)
    assert with_mask[0].abs().sum() > 0
    for a, b in zip(with_mask, without):
        assert torch.equal(a, b)
    with pytest.raises(RuntimeError, match="mask must be"):
        mod.blend_backward(packed, attrs, idx, depth, rho, images, grad, 0.05, mask[:, 1:])

def test_cpp_projection_backward_equals_torch_autograd(cpp_backend):
    """project_splats_backward (the C++ projection's hand-written backward that render() uses
    with the cpp backend) gives the gradients torch autograd takes through
    dss.reference.project_splats, for every differentiable field (centre, conic, peak weight, depth,
    extents) with normals of any length and gradient rows that are zero (alone and in groups), and
    the same bits on 1 and 2 threads."""
    from dss import _ext
    from dss.reference import project_splats

    pts, nrm, cams, sigma, _ = random_scene(11, n=400, views=3, size=(48, 64))
    nrm = nrm * (0.5 + torch.rand(len(nrm), 1, generator=torch.Generator().manual_seed(1)))
    p, n = pts.clone().requires_grad_(), nrm.clone().requires_grad_()
    ref = project_splats(p, n, cams, sigma, 1.0, True, 1e-3, 1.0).packed
    valid = ref[..., 9:10].detach() > 0
    assert 0 < valid.float().mean() < 1  # both culled and rendered splats
    g = torch.randn(ref.shape, generator=torch.Generator().manual_seed(2))
    g[..., 9] = 0
    # rows of zeros, as most splats of a real step have: whole groups of 8 points in some views
    # (the kernel skips those) and single rows (computed beside non-zero ones)
    g[:, (torch.arange(len(pts)) // 8) % 3 == 0] = 0
    g[torch.rand(g.shape[:2], generator=torch.Generator().manual_seed(4)) < 0.3] = 0
    (ref * g * valid).sum().backward()  # culled splats are never read: no gradient through them
    mod = _ext.load_cpu()
    packed = mod.project_splats_forward(pts, nrm, cams.R, cams.t, cams.focal, cams.principal, sigma, 1.0, True,
                                        1e-3, 1.0)
    torch.testing.assert_close(packed, ref.detach(), rtol=1e-5, atol=1e-5)
    before = torch.get_num_threads()
    res = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            res.append(mod.project_splats_backward(pts, nrm, cams.R, cams.t, cams.focal, cams.principal, sigma,
                                                   packed, g, 1.0, 1.0))
    finally:
        torch.set_num_threads(before)
    assert all(torch.equal(a, b) for a, b in zip(*res))
    gp, gn = res[0]
    for ours, theirs in ((gp, p.grad), (gn, n.grad)):
        assert theirs.abs().max() > 0
        assert (ours - theirs).norm() <= 1e-5 * theirs.norm()


def test_vector_projection_gives_the_scalar_bits(cpp_backend):
    """The projection kernels' AVX2 loops (projection_cpu.cpp project_forward_avx2 and
    project_backward_avx2: eight points side by side, the branches turned into selects) give the
    baseline loops' packed splats and gradients bit for bit, including culled splats, points
    behind the near plane (zero gradient) and a point count that is not a multiple of the vector
    width, the 64-point transpose block or the 1024-point work item."""
    from dss import _ext

    mod = _ext.load_cpu()
    if not mod.vector_path_available():
        skip_without_vector_path()
    pts, nrm, cams, sigma, _ = random_scene(5, n=2077, views=3, size=(48, 64))
    nrm = nrm * (0.5 + torch.rand(len(nrm), 1, generator=torch.Generator().manual_seed(1)))
    behind = cams.R[0].T @ (cams.t.new_tensor([0.1, -0.2, -1.0]) - cams.t[0])  # z = -1 in camera 0
    pts[:40] = behind + 0.01 * torch.randn(40, 3, generator=torch.Generator().manual_seed(3))
    g = torch.randn(3, len(pts), 10, generator=torch.Generator().manual_seed(2))
    g[:, (torch.arange(len(pts)) // 8) % 4 == 1] = 0  # groups the vector path skips
    before = mod.set_vector_path(True)
    res = []
    try:
        for vec in (True, False):
            mod.set_vector_path(vec)
            packed = mod.project_splats_forward(pts, nrm, cams.R, cams.t, cams.focal, cams.principal, sigma, 1.0,
                                                True, 1e-3, 1.0).clone()
            res.append([packed, *mod.project_splats_backward(pts, nrm, cams.R, cams.t, cams.focal, cams.principal,
                                                             sigma, packed, g, 1.0, 1.0)])
    finally:
        mod.set_vector_path(before)
    valid = res[1][0][..., 9]
    assert 0 < valid.mean() < 1 and (valid[0, :40] == 0).all()
    assert res[1][1].abs().max() > 0 and res[1][2].abs().max() > 0
    for name, a, b in zip(("packed", "grad points", "grad normals"), *res):
        assert torch.equal(a, b), f"{name} differs"


def test_float64_inputs_render_and_differentiate_on_both_backends(cpp_backend):
    """float64 points, normals, sigma and cameras render on both backends (the C++ kernels compute
    in float32 and hand float64 gradients back) and the two backends' position gradients agree."""
    pts, nrm, cams, sigma, _ = random_scene(0, n=300)
    cams = cams.to(torch.float64)
    grads = {}
    for backend in ("reference", cpp_backend):
        p, n = pts.double().requires_grad_(), nrm.double().requires_grad_()
        out = render(p, n, cams, RenderSettings(merge_threshold=0.05), sigma=sigma.double(), backend=backend)
        (out.images * torch.linspace(0, 1, 3, dtype=out.images.dtype)).sum().backward()
        assert p.grad.dtype == n.grad.dtype == torch.float64 and torch.isfinite(p.grad).all()
        grads[backend] = p.grad
    ref = grads["reference"]
    assert ref.abs().max() > 0 and (grads[cpp_backend] - ref).norm() <= 1e-3 * ref.norm()
    # float64 points with the float32 cameras: rendered in float32, gradients back in float64
    p = pts.double().requires_grad_()
    out = render(p, nrm, cams.to(torch.float32), RenderSettings(merge_threshold=0.05), sigma=sigma, backend=cpp_backend)
    (out.images * torch.linspace(0, 1, 3)).sum().backward()
    assert out.images.dtype == torch.float32 and p.grad.dtype == torch.float64
    assert (p.grad - ref).norm() <= 1e-3 * ref.norm()


@pytest.mark.parametrize(("K", "C", "window", "size"), [(5, 3, 4, (48, 64)), (5, 1, 4, (48, 64)), (3, 3, 7, (48, 64)),
                                                         (8, 2, 8, (48, 64)), (5, 3, 12, (48, 64)),
                                                         (2, 1, 5, (48, 64)), (5, 3, 4, (30, 10))])
def test_vector_visibility_path_gives_the_scalar_bits(K, C, window, size, cpp_backend):
    """Each vector evaluation of the dss rule (every case computed in every lane) gives exactly
    the scalar evaluation's gradient: the same float32 operations per lane and the contributions
    added in the same partial sums in the same order (dss/csrc/splat_math.h vis_partial: lane l
    of every run into partial l). Level 1 (AVX2) takes 8 pixels per vector, level 2 (AVX-512,
    where the CPU has it) a whole window row of 9 to 15 columns per vector. The parameters cover
    the compiled (K, C) variants and the run-time one, windows whose rows are runs of 8 plus a
    rest (4: 8 + 1, 5: 8 + 3, 7: 8 + 7, 8: 16 + 1, 12: 24 + 1; 16 lanes take windows 4, 5 and 7),
    and points near and beyond the image border (runs partly off the image use masked loads); an
    image 10 pixels wide has windows whose 16-lane rows run past the image's right edge. With
    AVX2, windows of 9 to 15 columns wholly on the image (most points here) take the chunked walk
    across row ends (VisFlatPlan), whose lanes are moved to their columns' partials; the others
    the row walk. Narrower windows take the scalar path (nothing to compare)."""
    from dss import _ext
    from dss.reference import tangent_planes

    mod = _ext.load_cpu()
    levels = vector_levels(mod)
    pts, nrm, cams, sigma, _ = random_scene(K * 10 + C, n=1200, views=3, size=size)
    pts = pts * 1.4  # some splats off the image, some straddling its border
    out = render(pts, nrm, cams, RenderSettings(window=4, spatial_sort=False), sigma=sigma, backend=cpp_backend)
    packed = out.splats.packed.detach().float().contiguous()
    attrs = torch.rand(packed.shape[0], packed.shape[1], C, generator=torch.Generator().manual_seed(C))
    planes = tangent_planes(pts, nrm, cams).float().contiguous()
    H, W = cams.image_size
    bg = torch.full((C,), 0.25)
    idx, depth, rho, images, _ = mod.rasterize_forward(packed, attrs, H, W, K, 3.0, 0.05, bg)
    g = torch.Generator().manual_seed(7)
    grad = torch.randn(images.shape, generator=g) * (torch.rand(images.shape[:-1] + (1,), generator=g) > 0.2)
    args = (packed, attrs, idx, depth, rho, images, grad.contiguous(), cams.R.float(), cams.focal.float(),
            cams.principal.float(), bg, planes, window, 1, 3.0, 0.05, 1e-6, 0)
    before = mod.set_vector_level(0)
    try:
        g_scalar = mod.visibility_backward(*args)
        g_vec = {}
        for level in levels:
            mod.set_vector_level(level)
            assert mod.vector_level() == level
            g_vec[level] = mod.visibility_backward(*args)
    finally:
        mod.set_vector_level(before)
    assert g_scalar.abs().max() > 0
    for level, g in g_vec.items():
        assert torch.equal(g, g_scalar), f"level {level}: {(g != g_scalar).any(1).sum().item()} points differ"


def test_vector_level_is_set_checked_and_capped(cpp_backend):
    """set_vector_level(0-2) picks the highest vector path the kernels may take (0 scalar, 1 AVX2,
    2 AVX-512), capped at what this CPU and build have; set_vector_path(False / True) is level 0 /
    every level; other values are refused."""
    from dss import _ext

    mod = _ext.load_cpu()
    top = mod.max_vector_level()
    before = mod.set_vector_level(2)
    try:
        assert mod.vector_level() == top
        assert mod.set_vector_level(1) == 2 and mod.vector_level() == min(1, top)
        assert mod.set_vector_path(False) is True and mod.vector_level() == 0
        assert mod.set_vector_path(True) is False and mod.vector_level() == top
        with pytest.raises(RuntimeError, match="vector level must be 0"):
            mod.set_vector_level(3)
        assert mod.vector_level() == top
    finally:
        mod.set_vector_level(before)
