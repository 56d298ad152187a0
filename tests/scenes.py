"""Small scenes and data helpers shared by the tests (import as `from scenes import ...`)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def sphere_points(n: int = 2000, radius: float = 1.0, center=(0.0, 0.0, 0.0)):
    """Fibonacci-sphere points (n,3) and outward unit normals."""
    from dss.cameras import fibonacci_sphere

    d = fibonacci_sphere(n)
    return d * radius + torch.tensor(center), d.clone()


def shared_file(name: str) -> Path:
    p = SHARED_DATA / name
    if not p.exists():
        pytest.skip(f"{p} is not present (../shared/data is optional for tests)")
    return p




def axis_camera(H: int = 128, W: int = 128, focal: float = 100.0):
    """One camera at the origin looking down +z (R = I, t = 0), principal point at the centre."""
    from dss.cameras import Cameras

    return Cameras(torch.eye(3)[None], torch.zeros(1, 3), torch.tensor([focal]), torch.tensor([[W / 2.0, H / 2.0]]), (H, W))


def random_scene(seed: int, n: int = 300, views: int = 3, size=(40, 56)):
    """Random points in front of a few cameras, normals roughly facing the cameras."""
    from dss.cameras import ring_cameras

    g = torch.Generator().manual_seed(seed)
    pts = (torch.rand(n, 3, generator=g) - 0.5) * 1.2
    nrm = torch.randn(n, 3, generator=g)
    nrm = nrm / nrm.norm(dim=1, keepdim=True)
    cams = ring_cameras(views, distance=3.0, elevation_deg=15.0, focal=60.0, image_size=size)
    sigma = 0.02 + 0.05 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return pts, nrm, cams, sigma, colors


def front_view_run(start: torch.Tensor, target: torch.Tensor, shading="mask", **config):
    """Optimise a flat cloud (z = 0, normals +z) against a flat target seen by one fixed camera
    on +z (64 px, splat std 0.012): the 2D silhouette experiments. ``config`` goes to
    :class:`dss.optimize.OptimizerConfig` (views=1, lr_scale=1, no momentum, L1 and no
    regularisers unless given). Returns the :class:`dss.optimize.OptimizationResult`."""
    from dss.cameras import look_at
    from dss.optimize import MultiViewOptimizer, OptimizerConfig
    from dss.render import RenderSettings, render

    up = torch.tensor([0.0, 0.0, 1.0])
    sn, tn = up.expand(len(start), 3).clone(), up.expand(len(target), 3).clone()
    st = RenderSettings(sigma=0.012)
    cams = look_at(torch.tensor([[0.0, 0.0, 2.0]]), (0, 0, 0), (0, 1, 0), 150.0, (64, 64))

    class Fixed:
        def sample(self):
            return cams

    cfg = dict(views=1, lr_scale=1.0, momentum=0.0, projection_weight=0.0, repulsion_weight=0.0, image_loss="l1")
    cfg.update(config)
    opt = MultiViewOptimizer(start, sn, lambda c: render(target, tn, c, st, shading=shading).images,
                             OptimizerConfig(**cfg), st, sampler=Fixed(), shading=shading, image_size=64)
    return opt.run()


def _cpu_flags() -> set[str]:
    import platform

    if platform.machine() not in ("x86_64", "AMD64"):
        return set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


AVX512_FLAGS = {"avx512f", "avx512vl", "avx512dq", "avx512bw"}  # what the kernels' AVX-512 path needs


def skip_without_vector_path() -> None:
    """Skip a vector-vs-scalar kernel test where the C++ module has no AVX2 path, but fail where
    the CPU has AVX2 and the build lacks the path (that would hide the path from every test)."""
    assert "avx2" not in _cpu_flags(), "this CPU has AVX2 but the kernel was built without the vector path"
    pytest.skip("no AVX2 on this CPU: the scalar path is the only one")


def vector_levels(mod) -> list[int]:
    """The kernels' vector levels (1 AVX2, 2 AVX-512) this CPU has, to compare with level 0 (the
    scalar loops). Fails where the CPU has a level's instructions and the build does not take them
    (that would hide the path from every test); skips where the CPU has no vector path at all."""
    top = mod.max_vector_level()
    flags = _cpu_flags()
    assert top >= 1 or "avx2" not in flags, "this CPU has AVX2 but the kernel was built without the vector path"
    assert top >= 2 or not AVX512_FLAGS <= flags, "this CPU has AVX-512 but the kernel does not take its path"
    if top == 0:
        pytest.skip("no AVX2 on this CPU: the scalar path is the only one")
    return list(range(1, top + 1))


def require_vector_level(mod, level: int) -> None:
    """Skip a test of vector level ``level`` (0 scalar, 1 AVX2, 2 AVX-512) where this CPU lacks
    it; fail where the CPU has it and the build does not take it."""
    if level == 0:
        return
    if level > mod.max_vector_level():
        vector_levels(mod)  # fails where the CPU has the instructions; skips where it has no vector path
        pytest.skip(f"vector level {level} needs instructions this CPU lacks")
