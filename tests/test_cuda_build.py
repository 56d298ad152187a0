"""The CUDA kernels (dss/csrc/*_cuda.cu, cuda_common.cuh, dss_cuda.h, dss_cuda_bind.cpp).

Four tiers:
- ``nvcc``: the kernels compile with nvcc wherever nvcc exists (skipped without it; ~5 s).
- emulated: the kernels' own code, built with the host compiler against a CPU stand-in of the
  CUDA runtime (tests/cuda_emu: real threads per block, a real barrier for __syncthreads), agrees
  equal to the CPU kernel (forward bit for bit, visibility gradient to rounding). Runs everywhere there is a C++ compiler (~10 s).
- ``slow``: the torch glue compiles for CUDA (syntax check) and, in emulation, agrees with the
  CPU kernel through the same Python calls the GPU module gets (~1-2 min of compilation).
- ``gpu``: the real CUDA module against the CPU kernel (run with ``pytest -m gpu``; skipped
  without a GPU).
"""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import sys
import sysconfig
import warnings
from pathlib import Path

import pytest
import torch
from scenes import random_scene

from dss import _ext_cuda
from dss import reference as ref
from dss.reference import project_splats, tangent_planes

CSRC = Path(_ext_cuda.__file__).parent / "csrc"
EMU = Path(__file__).parent / "cuda_emu"
LAUNCHERS = ("launch_bin_count", "launch_bin_fill", "launch_rasterize_tiles", "launch_visibility",
             "launch_reduce_views")
TILE = 16


# ----------------------------------------------------------------------------------------------
# Scenes


def make_scene(seed: int, n: int, views: int, size: tuple[int, int], K: int, C: int, spread: float = 1.0,
               dup: int = 0, sigma_scale: float = 3.0, merge: float = 0.05) -> dict:
    """Random splats, attributes and cameras; ``dup`` last points copy the first ones (depth ties)."""
    pts, nrm, cams, sigma, _ = random_scene(seed, n, views, size)
    pts = pts * spread
    if dup:
        pts[n - dup:] = pts[:dup]
        nrm[n - dup:] = nrm[:dup]
        sigma[n - dup:] = sigma[:dup]
    packed = project_splats(pts, nrm, cams, sigma * sigma_scale).packed.detach().contiguous()
    g = torch.Generator().manual_seed(seed + 1000)
    attrs = torch.rand(views, n, C, generator=g)
    bg = torch.rand(C, generator=g)
    planes = tangent_planes(pts, nrm, cams)
    return dict(packed=packed, attrs=attrs, bg=bg, planes=planes, cams=cams, H=size[0], W=size[1], K=K, merge=merge, cutoff=2.0)


SCENES = {
    # partial tiles (40x56), equal depths broken by the point index, a few views
    "ties": dict(seed=0, n=300, views=3, size=(40, 56), K=5, C=3, dup=60),
    # bins of more than 256 splats (several shared-memory batches), K=8, C>4 (generic channel path)
    "deep_bins": dict(seed=1, n=2000, views=1, size=(33, 20), K=8, C=5),
    # one exact tile, K=1, one channel, most splats off screen (clamped border boxes)
    "offscreen": dict(seed=2, n=500, views=2, size=(16, 16), K=1, C=1, spread=4.0),
}


def max_bin(packed: torch.Tensor, H: int, W: int) -> int:
    """Largest number of valid splats whose box touches one tile (what a tile block streams)."""
    j0, j1, i0, i1 = ref.bbox(packed, H, W)
    TX, TY = (W + TILE - 1) // TILE, (H + TILE - 1) // TILE
    best = 0
    for v in range(packed.shape[0]):
        ok = packed[v, :, 9] > 0
        for ty in range(TY):
            for tx in range(TX):
                hit = ok & (j0[v] // TILE <= tx) & (j1[v] // TILE >= tx) & (i0[v] // TILE <= ty) & (i1[v] // TILE >= ty)
                best = max(best, int(hit.sum()))
    return best


def forward_args(s: dict, with_attrs: bool = True):
    attrs = s["attrs"] if with_attrs else torch.empty(0, device=s["packed"].device)
    bg = s["bg"] if with_attrs else torch.empty(0, device=s["packed"].device)
    return (s["packed"], attrs, s["H"], s["W"], s["K"], s["cutoff"], s["merge"], bg)


def backward_args(s: dict, cache, grad, mode: int, window: int = 4, stride: int = 1):
    idx, depth, rho, images, _ = cache
    c = s["cams"]
    return (s["packed"], s["attrs"], idx, depth, rho, images, grad, c.R, c.focal, c.principal, s["bg"],
            s["planes"], window, stride, s["cutoff"], s["merge"], 1e-5, mode)


def random_grad(images: torch.Tensor, seed: int) -> torch.Tensor:
    """dL/dI with about 30% of the pixels exactly zero (the kernels skip those)."""
    g = torch.Generator().manual_seed(seed)
    grad = torch.randn(images.shape, generator=g) * (torch.rand(images.shape[:-1], generator=g) < 0.7)[..., None]
    return grad.to(images.device)


# ----------------------------------------------------------------------------------------------
# nvcc


def find_nvcc() -> str | None:
    exe = shutil.which("nvcc")
    if exe:
        return exe
    for home in (os.environ.get("CUDA_HOME"), os.environ.get("CUDA_PATH"), "/usr/local/cuda"):
        if home and (Path(home) / "bin" / "nvcc").is_file():
            return str(Path(home) / "bin" / "nvcc")
    return None


def cuda_home() -> Path | None:
    """The CUDA toolkit folder (with include/cuda_runtime_api.h); nvcc may be a wrapper script."""
    cands = [os.environ.get("CUDA_HOME"), os.environ.get("CUDA_PATH")]
    nvcc = find_nvcc()
    if nvcc:
        cands += [Path(nvcc).resolve().parent.parent, Path(nvcc).parent.parent]
    cands.append("/usr/local/cuda")
    for c in cands:
        if c and (Path(c) / "include" / "cuda_runtime_api.h").is_file():
            return Path(c)
    return None


def test_cuda_kernels_compile_with_nvcc(tmp_path):
    nvcc = find_nvcc()
    if nvcc is None:
        pytest.skip("nvcc not found (put it on PATH or set CUDA_HOME); the CUDA sources were not compiled")
    own = {f.name for f in CSRC.iterdir()}
    syms, elf = "", ""
    home = cuda_home()
    cuobjdump = shutil.which("cuobjdump") or (str(home / "bin" / "cuobjdump") if home else None)
    for src in _ext_cuda.KERNEL_SOURCES:  # one stage per file, each compiled alone
        obj = tmp_path / (src.stem + ".o")
        cmd = [nvcc, "-c", "-std=c++17", *_ext_cuda.NVCC_FLAGS, "-arch=sm_80", "-I", str(CSRC), str(src), "-o", str(obj)]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        log = r.stdout + r.stderr
        assert r.returncode == 0, f"nvcc failed:\n{' '.join(cmd)}\n{log}"
        assert obj.stat().st_size > 0
        own_warnings = [ln for ln in log.splitlines() if "warning" in ln.lower() and any(n in ln for n in own)]
        assert not own_warnings, "\n".join(own_warnings)
        nm = shutil.which("nm")
        if nm:
            syms += subprocess.run([nm, "-C", "--defined-only", str(obj)], capture_output=True, text=True).stdout
        if cuobjdump and Path(cuobjdump).is_file():
            elf += subprocess.run([cuobjdump, "-elf", str(obj)], capture_output=True, text=True).stdout
    if syms:  # the launchers the glue links against are defined, with dss_cuda.h's signatures
        for name in LAUNCHERS:
            assert f"dss_cuda::{name}(" in syms, f"{name} missing from the objects"
    if elf:  # sm_80 device code is embedded, tile kernel included
        assert "sm_80" in elf and "rasterize_tiles_kernel" in elf


# ----------------------------------------------------------------------------------------------
# Emulation: the kernels' own code on CPU threads (tests/cuda_emu)


class EmulatedKernels:
    """The launchers of the *_cuda.cu files built for the CPU; same Python calls as the CUDA module.

    The host-side steps (allocation, the scan of the tile counts) repeat dss_cuda_bind.cpp.
    """

    def __init__(self, lib_path: Path):
        P, I64, I, F = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_float
        self.lib = ctypes.CDLL(str(lib_path))
        sig = {
            "emu_bin_count": [P, I64, I64, I, I, F, P],
            "emu_bin_fill": [P, I64, I64, I, I, F, P, P],
            "emu_rasterize_tiles": [P, I64, I64, I, I, I, P, P, P, F, F, P, I, P, P, P, P, P, P],
            "emu_visibility": [P] * 12 + [I64, I64, I, I, I, I, I, I, F, F, F, I, P],
            "emu_reduce_views": [P, P, I64, I64, P],
            "emu_project_forward": [P] * 7 + [I64, I64, F, I, F, F, P],
            "emu_project_backward": [P] * 8 + [I64, I64, F, F, P, P],
            "emu_sun_forward": [P, P, P, I64, I64, F, P],
            "emu_sun_backward": [P, P, P, P, I64, I64, F, P, P],
            "emu_blend_backward": [P] * 7 + [I64, I64, I, I, I, I, F, P, P],
        }
        for name, args in sig.items():
            fn = getattr(self.lib, name)
            fn.argtypes, fn.restype = args, ctypes.c_int

    @staticmethod
    def _p(t: torch.Tensor | None) -> int | None:
        return t.data_ptr() if t is not None else None

    @staticmethod
    def _check(rc: int, what: str):
        if rc != 0:
            raise RuntimeError(f"{what} returned {rc}")

    def rasterize_forward(self, packed, attrs, H, W, K, cutoff, merge, background):
        p = self._p
        packed = packed.float().contiguous()
        V, N = packed.shape[:2]
        do_blend = attrs.numel() > 0
        C = attrs.shape[2] if do_blend else 0
        attrs = attrs.float().contiguous() if do_blend else None
        bg = background.float().contiguous() if do_blend else None
        VT = V * ((H + TILE - 1) // TILE) * ((W + TILE - 1) // TILE)
        counts = torch.zeros(VT, dtype=torch.int32)
        self._check(self.lib.emu_bin_count(p(packed), V, N, H, W, cutoff, p(counts)), "bin_count")
        bin_end = torch.cumsum(counts, 0, dtype=torch.int64)
        bin_start = bin_end - counts
        cursor = bin_start.clone()
        lst = torch.empty(max(int(bin_end[-1]) if VT else 0, 1), dtype=torch.int32)
        self._check(self.lib.emu_bin_fill(p(packed), V, N, H, W, cutoff, p(cursor), p(lst)), "bin_fill")
        assert torch.equal(cursor, bin_end), "every bin must be filled exactly"
        idx = torch.empty(V, H, W, K, dtype=torch.int32)
        depth = torch.empty(V, H, W, K)
        rho = torch.empty(V, H, W, K)
        images = torch.empty(V, H, W, C) if do_blend else torch.empty(0)
        mask = torch.empty(V, H, W, dtype=torch.bool)
        self._check(self.lib.emu_rasterize_tiles(
            p(packed), V, N, H, W, K, p(bin_start), p(bin_end), p(lst), cutoff, merge, p(attrs), C, p(bg),
            p(idx), p(depth), p(rho), p(images) if do_blend else None, p(mask)), "rasterize_tiles")
        return [idx, depth, rho, images, mask]

    def visibility_backward(self, packed, attrs, idx, depth, rho, images, grad, R, focal, principal, background,
                            planes, window, stride, cutoff, merge, eps, mode):
        ts = [t.contiguous() for t in (packed, attrs, idx, depth, rho, images, grad, R, focal, principal, background,
                                       planes)]
        V, N = packed.shape[:2]
        _, H, W, K = idx.shape
        C = attrs.shape[2]
        partial = torch.empty(V, N, 3, dtype=torch.float64)
        out = torch.empty(N, 3)
        self._check(self.lib.emu_visibility(*[self._p(t) for t in ts], V, N, H, W, K, C, window, stride, cutoff,
                                            merge, eps, mode, self._p(partial)), "visibility")
        self._check(self.lib.emu_reduce_views(self._p(ts[0]), self._p(partial), V, N, self._p(out)), "reduce_views")
        return out

    @staticmethod
    def _project_inputs(points, normals, R, t, focal, principal, sigma):
        ts = [x.float().contiguous() for x in (points, normals, R, t, focal, principal)]
        return ts + [sigma.float().expand(points.shape[0]).contiguous()]

    def project_splats_forward(self, points, normals, R, t, focal, principal, sigma, cutoff, culling, znear,
                               filter_variance):
        ts = self._project_inputs(points, normals, R, t, focal, principal, sigma)
        V, N = R.shape[0], points.shape[0]
        out = torch.empty(V, N, 10)
        self._check(self.lib.emu_project_forward(*[self._p(x) for x in ts], V, N, cutoff, int(culling), znear,
                                                 filter_variance, self._p(out)), "project_forward")
        return out

    def project_splats_backward(self, points, normals, R, t, focal, principal, sigma, packed, grad, cutoff,
                                filter_variance):
        p, n, R, t, f, _, s = self._project_inputs(points, normals, R, t, focal, principal, sigma)
        packed, grad = packed.float().contiguous(), grad.float().contiguous()
        V, N = R.shape[0], points.shape[0]
        gp, gn = torch.empty(N, 3), torch.empty(N, 3)
        self._check(self.lib.emu_project_backward(*[self._p(x) for x in (p, n, R, t, f, s, packed, grad)], V, N,
                                                  cutoff, filter_variance, self._p(gp), self._p(gn)),
                    "project_backward")
        return [gp, gn]

    def blend_backward(self, packed, attrs, idx, depth, rho, images, grad, merge):
        ts = [t.contiguous() for t in (packed, attrs, idx, depth, rho, images, grad)]
        V, N = packed.shape[:2]
        _, H, W, K = idx.shape
        C = attrs.shape[2]
        gpk, gat = torch.empty(V, N, 10), torch.empty(V, N, C)
        self._check(self.lib.emu_blend_backward(*[self._p(t) for t in ts], V, N, H, W, K, C, merge, self._p(gpk),
                                                self._p(gat)), "blend_backward")
        return [gpk, gat]

    def sun_shade_forward(self, normals, albedo, dirs, ambient):
        n, d = normals.float().contiguous(), dirs.float().contiguous()
        a = albedo.float().contiguous() if albedo.numel() else None
        out = torch.empty(d.shape[0], n.shape[0], 3)
        self._check(self.lib.emu_sun_forward(self._p(n), self._p(a), self._p(d), d.shape[0], n.shape[0], ambient,
                                             self._p(out)), "sun_forward")
        return out

    def sun_shade_backward(self, normals, albedo, dirs, ambient, grad, need_albedo):
        n, d, g = normals.float().contiguous(), dirs.float().contiguous(), grad.float().contiguous()
        a = albedo.float().contiguous() if albedo.numel() else None
        gn = torch.empty(n.shape[0], 3)
        ga = torch.empty(n.shape[0], 3) if (need_albedo and a is not None) else torch.empty(0)
        self._check(self.lib.emu_sun_backward(self._p(n), self._p(a), self._p(d), self._p(g), d.shape[0], n.shape[0],
                                              ambient, self._p(gn), self._p(ga) if ga.numel() else None),
                    "sun_backward")
        return [gn, ga]


def _cxx() -> str | None:
    return shutil.which(os.environ.get("CXX", "c++")) or shutil.which("g++") or shutil.which("clang++")


@pytest.fixture(scope="module")
def emulated(tmp_path_factory):
    cxx = _cxx()
    if cxx is None:
        pytest.skip("no C++ compiler to build the emulated CUDA kernels")
    lib = tmp_path_factory.mktemp("cuda_emu") / "libdss_cuda_emu.so"
    cmd = [cxx, "-std=c++17", "-O2", "-ffp-contract=off", "-Wno-unknown-pragmas", "-shared", "-fPIC", "-pthread",
           "-I", str(EMU), "-I", str(CSRC), str(EMU / "dss_cuda_emu.cpp"), "-o", str(lib)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"building the emulated kernels failed:\n{r.stderr}"
    return EmulatedKernels(lib)


@pytest.fixture(scope="module")
def cpu_kernel():
    from dss import _ext

    mod = _ext.load_cpu()
    if mod is None:
        pytest.fail(f"the C++ kernel did not build: {_ext.build_error()}")
    return mod


@pytest.fixture(scope="module")
def scenes():
    return {name: make_scene(**kw) for name, kw in SCENES.items()}


def test_scenes_cover_the_hard_cases(scenes):
    """The scenes really contain multi-batch bins, depth ties and off-screen splats."""
    s = scenes["deep_bins"]
    assert max_bin(s["packed"], s["H"], s["W"]) > 256
    t = scenes["ties"]["packed"]
    assert torch.equal(t[:, :60], t[:, -60:])
    o = scenes["offscreen"]["packed"]
    u, v, ok = o[..., 0], o[..., 1], o[..., 9] > 0
    assert (ok & ((u < 0) | (u > 16) | (v < 0) | (v > 16))).sum() > 50


@pytest.mark.parametrize("name", list(SCENES))
def test_emulated_forward_equals_cpu_kernel(name, scenes, emulated, cpu_kernel):
    s = scenes[name]
    for with_attrs in (True, False):
        a = cpu_kernel.rasterize_forward(*forward_args(s, with_attrs))
        b = emulated.rasterize_forward(*forward_args(s, with_attrs))
        for field, x, y in zip(("idx", "depth", "rho", "images", "mask"), a, b):
            assert x.shape == y.shape, field
            assert torch.equal(x, y), f"{name}: {field} differs in {(x != y).sum().item()} entries"
    assert (a[0] >= 0).any() and a[4].any(), "the scene must render something"


@pytest.mark.parametrize("name", list(SCENES))
@pytest.mark.parametrize("mode", [0, 1], ids=["dss", "rbf"])
@pytest.mark.parametrize("order", ["partials", "rows"])
def test_emulated_visibility_equals_cpu_kernel(name, mode, order, scenes, emulated, cpu_kernel, monkeypatch):
    """Both walks of the CUDA visibility kernel (DSS_CUDA_VIS_ORDER) give the CPU kernel's bits."""
    monkeypatch.setenv("DSS_CUDA_VIS_ORDER", order)
    s = scenes[name]
    cache = cpu_kernel.rasterize_forward(*forward_args(s))
    grad = random_grad(cache[3], 7)
    # windows of 9 columns (one run of 8 + 1), 13 (+ 5) with stride 3, 17 (two runs + 1), 5 (no
    # run), 23 (two runs + 7) with stride 2: partials that hold two or three columns each
    for window, stride in ((4, 1), (6, 3), (8, 1), (2, 1), (11, 2)):
        ga = cpu_kernel.visibility_backward(*backward_args(s, cache, grad, mode, window, stride))
        gb = emulated.visibility_backward(*backward_args(s, cache, grad, mode, window, stride))
        assert ga.abs().sum() > 0
        # Both build the same pixel records and evaluate them with the same float32 expressions
        # in the same order (emulation compiles with -ffp-contract=off, as the CPU kernel), and
        # both add them into the same partial sums (splat_math.h vis_partial; the GPU walks the
        # window partial by partial or row by row, the CPU's vector path keeps them in lanes) in
        # the same order: bit for bit. What this checks is the float32 output: float32
        # contributions summed in double come out the same here in any order (a walk that adds
        # every pixel into one sum passes it), so the sums' order is the
        # same by construction, not by this test. (The CPU kernel's AVX2 path gives the scalar
        # path's bits, tests/test_render_backward.py.)
        assert torch.equal(ga, gb), f"{(ga != gb).any(1).sum().item()} points differ, max {(ga - gb).abs().max().item()}"


def test_emulated_visibility_refuses_an_unknown_walk(scenes, emulated, cpu_kernel, monkeypatch):
    s = scenes["ties"]
    cache = cpu_kernel.rasterize_forward(*forward_args(s))
    monkeypatch.setenv("DSS_CUDA_VIS_ORDER", "columns")
    with pytest.raises(RuntimeError, match="returned"):  # cudaErrorInvalidValue (the glue names the variable)
        emulated.visibility_backward(*backward_args(s, cache, random_grad(cache[3], 7), 0))


def project_args(seed: int, n: int = 700, views: int = 3, behind: int = 40):
    """Points, normals, cameras and (N,) sigma; the last ``behind`` points behind the cameras' near plane."""
    pts, nrm, cams, sigma, _ = random_scene(seed, n, views, (40, 56))
    if behind:  # behind the first camera (it looks at the origin): Z < znear there
        c0 = cams.centers[0]
        pts[-behind:] = 1.5 * c0 + 0.1 * torch.randn(behind, 3, generator=torch.Generator().manual_seed(seed))
    return pts, nrm, cams.R, cams.t, cams.focal, cams.principal, sigma


@pytest.mark.parametrize("culling", [True, False])
@pytest.mark.parametrize("seed", [0, 1])
def test_emulated_projection_equals_cpu_kernel(seed, culling, emulated, cpu_kernel):
    """Forward and backward of the projection (splat_math.h on both sides): bit for bit."""
    args = project_args(seed)
    a = cpu_kernel.project_splats_forward(*args, 2.0, culling, 0.01, 0.3)
    b = emulated.project_splats_forward(*args, 2.0, culling, 0.01, 0.3)
    assert torch.equal(a, b), f"{(a != b).sum().item()} packed values differ"
    valid = a[..., 9] > 0
    assert valid.any() and (~valid).any(), "the scene must have valid and culled splats"
    g = torch.randn(a.shape, generator=torch.Generator().manual_seed(seed + 7))
    ga = cpu_kernel.project_splats_backward(*args, a, g, 2.0, 0.3)
    gb = emulated.project_splats_backward(*args, a, g, 2.0, 0.3)
    for x, y, what in zip(ga, gb, ("points", "normals")):
        assert x.abs().sum() > 0
        assert torch.equal(x, y), f"dL/d{what}: {(x != y).any(1).sum().item()} points differ"


@pytest.mark.parametrize("vector", [True, False], ids=["avx2", "scalar"])
@pytest.mark.parametrize("with_albedo", [True, False])
def test_emulated_sun_shading_equals_cpu_kernel(with_albedo, vector, emulated, cpu_kernel):
    """The CPU sun shader (the backward's AVX2 blocks and its baseline build) and the emulated
    CUDA one give the same bits, forward and backward; 700 points: two blocks of 256 and a partial
    one."""
    if vector and not cpu_kernel.vector_path_available():
        pytest.skip("no AVX2 on this machine: the vector path is the scalar one")
    before = cpu_kernel.set_vector_path(vector)
    try:
        _check_sun_shading(with_albedo, emulated, cpu_kernel)
    finally:
        cpu_kernel.set_vector_path(before)


def _check_sun_shading(with_albedo, emulated, cpu_kernel):
    from dss.shading import SunLights

    pts, nrm, cams, _, colors = random_scene(4, n=700, views=3)
    nrm[:20] = 0.0  # n . d exactly 0: where the clamp's gradient switches
    dirs = SunLights().world_directions(cams, nrm).float().contiguous()
    alb = colors if with_albedo else torch.empty(0)
    a = cpu_kernel.sun_shade_forward(nrm, alb, dirs, 0.1)
    b = emulated.sun_shade_forward(nrm, alb, dirs, 0.1)
    assert torch.equal(a, b)
    g = torch.randn(a.shape, generator=torch.Generator().manual_seed(5))
    for need_albedo in (True, False):
        ga = cpu_kernel.sun_shade_backward(nrm, alb, dirs, 0.1, g, need_albedo)
        gb = emulated.sun_shade_backward(nrm, alb, dirs, 0.1, g, need_albedo)
        assert ga[0].abs().sum() > 0
        for x, y in zip(ga, gb):
            assert x.shape == y.shape and torch.equal(x, y)


@pytest.mark.parametrize("name", list(SCENES))
def test_emulated_blend_backward_matches_cpu_kernel(name, scenes, emulated, cpu_kernel):
    """Same formulas, same per-splat pixel order, double sums, the same exp (splat_exp): the
    emulated CUDA blend backward gives the CPU kernel's bits."""
    s = scenes[name]
    cache = cpu_kernel.rasterize_forward(*forward_args(s))
    idx, depth, rho, images, _ = cache
    grad = random_grad(images, 9)
    ga = cpu_kernel.blend_backward(s["packed"], s["attrs"], idx, depth, rho, images, grad, s["merge"])
    gb = emulated.blend_backward(s["packed"], s["attrs"], idx, depth, rho, images, grad, s["merge"])
    assert ga[0].abs().sum() > 0 and ga[1].abs().sum() > 0
    for x, y, what in zip(ga, gb, ("packed", "attrs")):
        assert x.shape == y.shape
        assert torch.equal(x, y), f"dL/d{what}: {(x != y).sum().item()} values differ, max {(x - y).abs().max().item()}"


def test_emulated_kernels_reject_bad_sizes(scenes, emulated):
    s = scenes["ties"]
    with pytest.raises(RuntimeError, match="rasterize_tiles"):
        emulated.rasterize_forward(s["packed"], s["attrs"], s["H"], s["W"], 9, 2.0, 0.05, s["bg"])


# ----------------------------------------------------------------------------------------------
# The torch glue


def _python_include() -> str:
    return sysconfig.get_paths()["include"]


@pytest.mark.slow
def test_cuda_glue_compiles_for_cuda(tmp_path):
    """dss_cuda_bind.cpp (the GPU branch) compiles against torch's CUDA headers (syntax only)."""
    cxx = _cxx()
    home = cuda_home()
    if cxx is None or home is None:
        pytest.skip("needs a C++ compiler and a CUDA toolkit (for cuda_runtime_api.h)")
    from torch.utils.cpp_extension import include_paths

    cuda_inc = home / "include"
    stub = tmp_path / "stub" / "c10" / "cuda" / "impl"
    # A CPU-only torch install lacks this one generated header of c10/cuda; it only sets a macro.
    if not any((Path(p) / "c10/cuda/impl/cuda_cmake_macros.h").exists() for p in include_paths()):
        stub.mkdir(parents=True)
        (stub / "cuda_cmake_macros.h").write_text("#pragma once\n#define C10_CUDA_BUILD_SHARED_LIBS\n")
    cmd = [cxx, "-fsyntax-only", "-std=c++20", "-DTORCH_EXTENSION_NAME=dss_cuda", "-DTORCH_API_INCLUDE_EXTENSION_H",
           "-I", str(tmp_path / "stub"), "-I", str(CSRC)]
    for p in [*include_paths(), _python_include(), str(cuda_inc)]:
        cmd += ["-isystem", str(p)]
    cmd.append(str(CSRC / "dss_cuda_bind.cpp"))
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-5000:]


@pytest.fixture(scope="module")
def emulated_module():
    """dss_cuda_bind.cpp + the kernels built by torch.utils.cpp_extension for CPU tensors."""
    from torch.utils.cpp_extension import load

    try:
        return load(name="dss_cuda_emulated", sources=[str(EMU / "dss_cuda_emu.cpp"), str(CSRC / "dss_cuda_bind.cpp")],
                    extra_include_paths=[str(EMU), str(CSRC)],
                    extra_cflags=["-O2", "-ffp-contract=off", "-DDSS_CUDA_EMULATION", "-Wno-unknown-pragmas"])
    except Exception as e:  # no compiler / ninja
        pytest.skip(f"cannot build the emulated torch module: {e}")


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SCENES))
def test_emulated_glue_equals_cpu_kernel(name, scenes, emulated_module, cpu_kernel):
    s = scenes[name]
    a = cpu_kernel.rasterize_forward(*forward_args(s))
    b = emulated_module.rasterize_forward(*forward_args(s))
    for x, y in zip(a, b):
        assert torch.equal(x, y)
    grad = random_grad(a[3], 3)
    for mode in (0, 1):
        ga = cpu_kernel.visibility_backward(*backward_args(s, a, grad, mode))
        gb = emulated_module.visibility_backward(*backward_args(s, a, grad, mode))
        assert torch.allclose(ga, gb, rtol=1e-3, atol=1e-4 * ga.abs().max().item())


@pytest.mark.slow
def test_emulated_glue_projection_shading_and_blend_equal_cpu_kernel(scenes, emulated_module, cpu_kernel):
    """The glue of the projection, the sun shader and the blend backward (bit for bit in emulation)."""
    from dss.shading import SunLights

    args = project_args(2)
    a = cpu_kernel.project_splats_forward(*args, 2.0, True, 0.01, 0.3)
    assert torch.equal(a, emulated_module.project_splats_forward(*args, 2.0, True, 0.01, 0.3))
    g = torch.randn(a.shape, generator=torch.Generator().manual_seed(2))
    for x, y in zip(cpu_kernel.project_splats_backward(*args, a, g, 2.0, 0.3),
                    emulated_module.project_splats_backward(*args, a, g, 2.0, 0.3)):
        assert torch.equal(x, y)
    nrm, cams = args[1], random_scene(2, 700, 3, (40, 56))[2]
    dirs = SunLights().world_directions(cams, nrm).float().contiguous()
    alb = torch.rand(len(nrm), 3)
    w = cpu_kernel.sun_shade_forward(nrm, alb, dirs, 0.2)
    assert torch.equal(w, emulated_module.sun_shade_forward(nrm, alb, dirs, 0.2))
    gw = torch.randn(w.shape, generator=torch.Generator().manual_seed(3))
    for x, y in zip(cpu_kernel.sun_shade_backward(nrm, alb, dirs, 0.2, gw, True),
                    emulated_module.sun_shade_backward(nrm, alb, dirs, 0.2, gw, True)):
        assert torch.equal(x, y)
    s = scenes["ties"]
    idx, depth, rho, images, _ = cpu_kernel.rasterize_forward(*forward_args(s))
    grad = random_grad(images, 4)
    for x, y in zip(cpu_kernel.blend_backward(s["packed"], s["attrs"], idx, depth, rho, images, grad, s["merge"]),
                    emulated_module.blend_backward(s["packed"], s["attrs"], idx, depth, rho, images, grad, s["merge"])):
        assert torch.equal(x, y)
    with pytest.raises(RuntimeError, match="sigma must be"):
        emulated_module.project_splats_forward(*args[:6], torch.ones(3), 2.0, True, 0.01, 0.3)
    with pytest.raises(RuntimeError, match="grad must be shaped like packed"):
        emulated_module.project_splats_backward(*args, a, g[:, :5], 2.0, 0.3)


@pytest.mark.slow
def test_emulated_glue_checks_its_inputs(scenes, emulated_module):
    s = scenes["ties"]
    with pytest.raises(RuntimeError, match="K must be in"):
        emulated_module.rasterize_forward(s["packed"], s["attrs"], s["H"], s["W"], 9, 2.0, 0.05, s["bg"])
    with pytest.raises(RuntimeError, match="attrs must be"):
        emulated_module.rasterize_forward(s["packed"], s["attrs"][:, :10], s["H"], s["W"], 5, 2.0, 0.05, s["bg"])
    with pytest.raises(RuntimeError, match="channels"):
        big = torch.rand(*s["attrs"].shape[:2], 17)
        emulated_module.rasterize_forward(s["packed"], big, s["H"], s["W"], 5, 2.0, 0.05, torch.zeros(17))
    cache = emulated_module.rasterize_forward(*forward_args(s))
    os.environ["DSS_CUDA_VIS_ORDER"] = "columns"
    try:
        with pytest.raises(RuntimeError, match="DSS_CUDA_VIS_ORDER must be 'partials'.*got 'columns'"):
            emulated_module.visibility_backward(*backward_args(s, cache, random_grad(cache[3], 7), 0))
    finally:
        del os.environ["DSS_CUDA_VIS_ORDER"]


# ----------------------------------------------------------------------------------------------
# Loader behaviour without a GPU


def test_load_cuda_without_gpu_warns_once_and_returns_none(monkeypatch):
    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    monkeypatch.setattr(_ext_cuda, "_cache", {})
    monkeypatch.setattr(_ext_cuda, "_failed", {})
    with pytest.warns(RuntimeWarning, match="CUDA kernels are not available"):
        assert _ext_cuda.load_cuda() is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _ext_cuda.cuda_available() is False
    assert "CPU-only" in _ext_cuda.build_error() or "no CUDA device" in _ext_cuda.build_error()


def test_load_cuda_can_be_disabled(monkeypatch):
    monkeypatch.setattr(_ext_cuda, "_cache", {})
    monkeypatch.setattr(_ext_cuda, "_failed", {})
    monkeypatch.setenv("DSS_DISABLE_CUDA", "1")
    with pytest.warns(RuntimeWarning):
        assert _ext_cuda.load_cuda() is None
    assert _ext_cuda.build_error() == "disabled by DSS_DISABLE_CUDA"


def test_bench_gpu_says_it_needs_a_gpu(capsys):
    if torch.cuda.is_available():
        pytest.skip("a GPU is present (run the benchmark itself)")
    from experiments.benchmarks import bench_gpu

    with pytest.raises(SystemExit) as e:
        bench_gpu.main(["--points", "100", "--repeats", "1"])
    assert e.value.code == 2
    assert "needs a GPU" in capsys.readouterr().err


def test_bench_gpu_sets_and_restores_the_visibility_walk(monkeypatch):
    from experiments.benchmarks.bench_gpu import _with_vis_order

    monkeypatch.delenv("DSS_CUDA_VIS_ORDER", raising=False)
    assert _with_vis_order("rows", lambda: os.environ["DSS_CUDA_VIS_ORDER"]) == "rows"
    assert "DSS_CUDA_VIS_ORDER" not in os.environ
    monkeypatch.setenv("DSS_CUDA_VIS_ORDER", "partials")
    with pytest.raises(ZeroDivisionError):
        _with_vis_order("rows", lambda: 1 / 0)
    assert os.environ["DSS_CUDA_VIS_ORDER"] == "partials"


def test_bench_gpu_times_the_walks_in_turn(monkeypatch):
    from experiments.benchmarks import bench_gpu

    monkeypatch.setattr(bench_gpu.torch.cuda, "synchronize", lambda *a: None)
    calls = []
    res = bench_gpu._timed_in_turn([lambda: calls.append("a"), lambda: calls.append("b")], 1, 3)
    assert calls == ["a", "b"] * 4 and [r["runs"] for r in res] == [3, 3]
    assert all(0 <= r["min_ms"] <= r["median_ms"] <= r["max_ms"] for r in res)


# ----------------------------------------------------------------------------------------------
# On a GPU: the real module against the CPU kernel


@pytest.fixture(scope="module")
def cuda_kernel():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA GPU")
    mod = _ext_cuda.load_cuda()
    if mod is None:
        pytest.fail(f"the CUDA kernels did not build: {_ext_cuda.build_error()}")
    return mod


def _to(s: dict, device) -> dict:
    out = dict(s)
    for k in ("packed", "attrs", "bg", "planes"):
        out[k] = s[k].to(device)
    out["cams"] = s["cams"].to(device)
    return out


def _cpu(xs):
    return [x.cpu() for x in xs]


def _sphere_scene(n: int, views: int = 12, size=(256, 256), K: int = 5) -> dict:
    """A denoising-sized workload: n points on a unit sphere, 12 ring views, paper settings."""
    from dss.cameras import fibonacci_sphere, ring_cameras
    from dss.splats import auto_sigma

    pts = fibonacci_sphere(n)
    nrm = pts.clone()
    cams = ring_cameras(views, distance=3.0, elevation_deg=20.0, focal=300.0, image_size=size)
    sigma = auto_sigma(pts)
    packed = project_splats(pts, nrm, cams, sigma).packed.detach().contiguous()
    g = torch.Generator().manual_seed(n)
    attrs = torch.rand(views, n, 3, generator=g)
    return dict(packed=packed, attrs=attrs, bg=torch.zeros(3), planes=tangent_planes(pts, nrm, cams), cams=cams,
                H=size[0], W=size[1], K=K, merge=0.01 * 2 * 3**0.5, cutoff=2.0)


def _assert_equal(a: torch.Tensor, b: torch.Tensor, where: str):
    """Bit for bit, or a message with how many entries differ and by how much."""
    a, b = a.cpu(), b.cpu()
    assert a.shape == b.shape and a.dtype == b.dtype, f"{where}: {a.shape} {a.dtype} against {b.shape} {b.dtype}"
    if not torch.equal(a, b):
        d = a != b
        raise AssertionError(f"{where}: {int(d.sum())} of {a.numel()} entries differ, "
                             f"max {(a.double()[d] - b.double()[d]).abs().max().item():.3g}")


def _assert_forward_equal(a, b, where: str):
    # Bit for bit: both kernels use one float32 exp (splat_exp) and nvcc builds with
    # --fmad=false and IEEE division and sqrt (checked on an H100).
    for name, x, y in zip(("idx", "depth", "rho", "images", "mask"), a, b):
        _assert_equal(x, y, f"{where}: {name}")


@pytest.mark.gpu
@pytest.mark.parametrize("name", list(SCENES))
def test_gpu_forward_matches_cpu_kernel(name, scenes, cuda_kernel, cpu_kernel):
    s = scenes[name]
    sg = _to(s, "cuda")
    for with_attrs in (True, False):
        a = cpu_kernel.rasterize_forward(*forward_args(s, with_attrs))
        b = _cpu(cuda_kernel.rasterize_forward(*forward_args(sg, with_attrs)))
        _assert_forward_equal(a, b, name)


@pytest.mark.gpu
@pytest.mark.parametrize("name", list(SCENES))
@pytest.mark.parametrize("mode", [0, 1], ids=["dss", "rbf"])
@pytest.mark.parametrize("order", ["partials", "rows"])
def test_gpu_visibility_matches_cpu_kernel(name, mode, order, scenes, cuda_kernel, cpu_kernel, monkeypatch):
    monkeypatch.setenv("DSS_CUDA_VIS_ORDER", order)
    s = scenes[name]
    sg = _to(s, "cuda")
    cache = cpu_kernel.rasterize_forward(*forward_args(s))
    grad = random_grad(cache[3], 11)
    # Same cache on both sides, then each backend's own cache: bit for bit in both modes (the
    # forward caches are equal, see above).
    ga = cpu_kernel.visibility_backward(*backward_args(s, cache, grad, mode))
    gb = cuda_kernel.visibility_backward(*backward_args(sg, [c.cuda() for c in cache], grad.cuda(), mode))
    _assert_equal(ga, gb, f"{name}: same cache")
    cache_g = cuda_kernel.rasterize_forward(*forward_args(sg))
    gc = cuda_kernel.visibility_backward(*backward_args(sg, cache_g, grad.cuda(), mode))
    _assert_equal(ga, gc, f"{name}: own cache")


@pytest.mark.gpu
def test_gpu_kernels_are_deterministic(scenes, cuda_kernel):
    sg = _to(scenes["deep_bins"], "cuda")
    a = cuda_kernel.rasterize_forward(*forward_args(sg))
    b = cuda_kernel.rasterize_forward(*forward_args(sg))
    for x, y in zip(a, b):
        assert torch.equal(x, y)
    grad = random_grad(a[3].cpu(), 5).cuda()
    g1 = cuda_kernel.visibility_backward(*backward_args(sg, a, grad, 0))
    g2 = cuda_kernel.visibility_backward(*backward_args(sg, a, grad, 0))
    assert torch.equal(g1, g2)


@pytest.mark.gpu
def test_gpu_matches_cpu_on_a_denoising_sized_scene(cuda_kernel, cpu_kernel):
    s = _sphere_scene(20_000)
    sg = _to(s, "cuda")
    a = cpu_kernel.rasterize_forward(*forward_args(s))
    b = _cpu(cuda_kernel.rasterize_forward(*forward_args(sg)))
    _assert_forward_equal(a, b, "sphere 20K")
    assert a[4].float().mean() > 0.1
    grad = random_grad(a[3], 2)
    ga = cpu_kernel.visibility_backward(*backward_args(s, a, grad, 0))
    gb = cuda_kernel.visibility_backward(*backward_args(sg, [c.cuda() for c in a], grad.cuda(), 0))
    _assert_equal(ga, gb, "sphere 20K: visibility")


@pytest.mark.gpu
@pytest.mark.parametrize("culling", [True, False])
def test_gpu_projection_and_sun_shading_equal_cpu_kernel(culling, cuda_kernel, cpu_kernel):
    """splat_math.h and the sun shader on the GPU (--fmad=false, IEEE division and sqrt): bit for bit."""
    from dss.shading import SunLights

    args = project_args(1, n=5000, views=12)
    gargs = [x.cuda() for x in args]
    a = cpu_kernel.project_splats_forward(*args, 2.0, culling, 0.01, 0.3)
    b = cuda_kernel.project_splats_forward(*gargs, 2.0, culling, 0.01, 0.3).cpu()
    assert torch.equal(a, b), f"{(a != b).sum().item()} packed values differ, max {(a - b).abs().max().item()}"
    g = torch.randn(a.shape, generator=torch.Generator().manual_seed(3))
    ga = cpu_kernel.project_splats_backward(*args, a, g, 2.0, 0.3)
    gb = [x.cpu() for x in cuda_kernel.project_splats_backward(*gargs, a.cuda(), g.cuda(), 2.0, 0.3)]
    for x, y in zip(ga, gb):
        assert torch.equal(x, y), f"{(x != y).any(1).sum().item()} points differ, max {(x - y).abs().max().item()}"
    pts, nrm = args[0], args[1]
    cams = random_scene(1, 5000, 12, (40, 56))[2]
    dirs = SunLights().world_directions(cams, nrm).float().contiguous()
    colors = torch.rand(len(pts), 3)
    a = cpu_kernel.sun_shade_forward(nrm, colors, dirs, 0.1)
    b = cuda_kernel.sun_shade_forward(nrm.cuda(), colors.cuda(), dirs.cuda(), 0.1).cpu()
    assert torch.equal(a, b)
    g = torch.randn(a.shape, generator=torch.Generator().manual_seed(4))
    ga = cpu_kernel.sun_shade_backward(nrm, colors, dirs, 0.1, g, True)
    gb = cuda_kernel.sun_shade_backward(nrm.cuda(), colors.cuda(), dirs.cuda(), 0.1, g.cuda(), True)
    for x, y in zip(ga, gb):
        assert torch.equal(x, y.cpu())


@pytest.mark.gpu
@pytest.mark.parametrize("name", list(SCENES))
def test_gpu_blend_backward_matches_cpu_kernel(name, scenes, cuda_kernel, cpu_kernel):
    """Same cache on both sides: bit for bit (splat_exp on both, rows gathered in the CPU kernel's order)."""
    s = scenes[name]
    idx, depth, rho, images, _ = cpu_kernel.rasterize_forward(*forward_args(s))
    grad = random_grad(images, 6)
    ga = cpu_kernel.blend_backward(s["packed"], s["attrs"], idx, depth, rho, images, grad, s["merge"])
    gb = cuda_kernel.blend_backward(*[t.cuda() for t in (s["packed"], s["attrs"], idx, depth, rho, images, grad)],
                                    s["merge"])
    for i, (x, y) in enumerate(zip(ga, gb)):
        _assert_equal(x, y, f"{name}: blend backward output {i}")


@pytest.mark.gpu
def test_gpu_module_rejects_cpu_tensors(scenes, cuda_kernel):
    s = scenes["ties"]
    with pytest.raises(RuntimeError, match="CUDA tensor"):
        cuda_kernel.rasterize_forward(*forward_args(s))


GPU_CHECK = Path(__file__).resolve().parents[1] / "experiments" / "benchmarks" / "gpu_check.sh"


def test_gpu_check_fits_its_stages_into_the_deadline(tmp_path):
    """DEADLINE_S caps each stage at what is left and skips the stages that no longer fit (a lent
    GPU machine runs one command for at most 10 minutes, so the stages that ran must still leave
    their files)."""
    def check(deadline, *stages):
        env = {**os.environ, "DEADLINE_S": str(deadline), "OUT": str(tmp_path), "PYTHON": "true"}
        return subprocess.run(["bash", str(GPU_CHECK), *stages], env=env, capture_output=True, text=True,
                              cwd=GPU_CHECK.parents[1], timeout=60)

    short = check(20, "rates", "bench")
    assert short.returncode == 2
    for name in ("rates", "bench"):
        assert "skipped" in (tmp_path / f"{name}.txt").read_text()
    roomy = check(100, "rates")  # `true` stands in for python: the stage passes, capped at 100 - 15 s
    assert roomy.returncode == 0, roomy.stdout
    assert "at most 85 s" in roomy.stdout or "at most 84 s" in roomy.stdout
    assert "skipped" not in (tmp_path / "rates.txt").read_text()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))
