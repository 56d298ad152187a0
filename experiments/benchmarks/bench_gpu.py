"""Time the CUDA kernels (and the CUDA render step, once render() has backend="cuda") on a GPU.

    python -m experiments.benchmarks.bench_gpu                       # 20K and 100K points x 12 views x 256^2
    python -m experiments.benchmarks.bench_gpu --points 20000 --repeats 20 --out results/bench/gpu.json

Same scenes as ``dss-bench`` (experiments/benchmarks/bench_render.py: kangaroo samples when ../shared/data is
there, else a generated torus; a Fibonacci sphere if open3d is missing). Every time is the median
of ``--repeats`` runs after ``--warmup`` runs, each bracketed by torch.cuda.synchronize(). The
JSON names the device; it is printed and, with ``--out``, written atomically.

Timed, per size:
- ``kernels``: ``project_splats_forward`` + ``sun_shade_forward`` (with the lights' directions, a
  few torch ops), ``rasterize_forward`` (cache and
  blended image), ``visibility_backward`` (dss gradient, window 4), and their sum; also the
  visibility kernel's row-major walk (``visibility_backward_rows``, ``DSS_CUDA_VIS_ORDER=rows``,
  the same bits: ``visibility_walks_equal``) against its default, partial-by-partial one;
- ``render`` (only when ``dss.render`` accepts ``backend="cuda"``): one optimisation step,
  forward with autograd, L1 loss, backward; forward-only without grad; peak GPU memory.
Targets (issue 5): one H100, forward + backward at most 10 ms for 20K points, 25 ms for 100K.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import sys
import time
from functools import partial

import torch

log = logging.getLogger("dss-bench-gpu")

TARGET_STEP_MS = {20_000: 10.0, 100_000: 25.0}


def _cloud(n: int):
    """(points, normals, source) on the CPU."""
    try:
        from experiments.benchmarks.bench_render import benchmark_cloud

        return benchmark_cloud(n)
    except ImportError:  # open3d missing
        from dss.cameras import fibonacci_sphere

        p = fibonacci_sphere(n) * 0.5
        return p, p / p.norm(dim=1, keepdim=True), "Fibonacci sphere"


def _cameras(points: torch.Tensor, views: int, size: int):
    from experiments.benchmarks.bench_render import cameras_for

    return cameras_for(points, views, size)


def _timed_in_turn(fns: list, warmup: int, repeats: int) -> list[dict]:
    """Synchronised timings of several functions, called in turn (a, b, a, b, ...) so that a drift
    of the GPU's clocks falls on all of them alike."""
    for _ in range(warmup):
        for fn in fns:
            fn()
    ts = [[] for _ in fns]
    for _ in range(repeats):
        for fn, t in zip(fns, ts):
            torch.cuda.synchronize()
            t0 = time.perf_counter()
            fn()
            torch.cuda.synchronize()
            t.append(1e3 * (time.perf_counter() - t0))
    return [{"median_ms": statistics.median(t), "min_ms": min(t), "max_ms": max(t), "runs": repeats} for t in ts]


def _timed(fn, warmup: int, repeats: int) -> dict:
    """Median, min and max ms of ``repeats`` synchronised calls after ``warmup`` untimed ones."""
    return _timed_in_turn([fn], warmup, repeats)[0]


def _with_vis_order(order: str, fn):
    """fn() with the CUDA visibility kernel's window walk set to ``order`` (DSS_CUDA_VIS_ORDER)."""
    old = os.environ.get("DSS_CUDA_VIS_ORDER")
    os.environ["DSS_CUDA_VIS_ORDER"] = order
    try:
        return fn()
    finally:
        if old is None:
            del os.environ["DSS_CUDA_VIS_ORDER"]
        else:
            os.environ["DSS_CUDA_VIS_ORDER"] = old


def bench_kernels(mod, points, normals, cams, sigma, settings, merge: float, warmup: int, repeats: int) -> dict:
    """The CUDA kernels alone, on inputs prepared outside the timed region."""
    from dss.reference import tangent_planes
    from dss.shading import SunLights

    H, W = cams.image_size
    bg = torch.zeros(3, device=points.device)
    sig = sigma.reshape(-1).float()
    sun = SunLights()
    no_albedo = torch.empty(0, device=points.device)

    def project():
        packed = mod.project_splats_forward(points, normals, cams.R, cams.t, cams.focal, cams.principal, sig,
                                            settings.cutoff, settings.backface_culling, settings.znear,
                                            settings.filter_variance)
        dirs = sun.world_directions(cams, normals).float().contiguous()
        return packed, mod.sun_shade_forward(normals, no_albedo, dirs, sun.ambient)

    packed, attrs = project()
    fwd_args = (packed, attrs, H, W, settings.K, settings.cutoff, merge, bg)
    idx, depth, rho, images, mask = mod.rasterize_forward(*fwd_args)
    g = torch.Generator(device=points.device).manual_seed(0)
    grad = torch.randn(images.shape, device=points.device, generator=g) / images.numel()
    planes = tangent_planes(points, normals, cams, settings.occlusion_depth)
    bwd_args = (packed, attrs, idx, depth, rho, images, grad, cams.R, cams.focal, cams.principal, bg, planes,
                settings.window, settings.window_stride, settings.cutoff, merge, settings.epsilon, 0)
    vis = lambda: mod.visibility_backward(*bwd_args)  # noqa: E731
    res = {
        "project_and_shade": _timed(project, warmup, repeats),
        "rasterize_forward": _timed(lambda: mod.rasterize_forward(*fwd_args), warmup, repeats),
        # the kernel's two walks over a window (same bits; visibility_backward_cuda.cu visibility_kernel), call by call in turn
        **dict(zip(("visibility_backward", "visibility_backward_rows"),
                   _timed_in_turn([partial(_with_vis_order, o, vis) for o in ("partials", "rows")], warmup, repeats))),
        "visibility_walks_equal": bool(torch.equal(_with_vis_order("partials", vis), _with_vis_order("rows", vis))),
        "covered_pixels": int(mask.sum()),
        "cached_fragments": int((idx >= 0).sum()),
    }
    res["sum_median_ms"] = sum(res[k]["median_ms"] for k in ("project_and_shade", "rasterize_forward",
                                                             "visibility_backward"))
    return res


def bench_render_step(points, normals, cams, sigma, settings, warmup: int, repeats: int) -> dict:
    """One optimisation step through render(backend="cuda"): forward with grad, L1, backward."""
    from dss.render import render

    with torch.no_grad():
        target = render(points + 0.003 * torch.randn_like(points), normals, cams, settings, backend="cuda",
                        sigma=sigma).images
    fwd, bwd, step = [], [], []
    for r in range(warmup + repeats):
        p = points.clone().requires_grad_()
        n = normals.clone().requires_grad_()
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        img = render(p, n, cams, settings, backend="cuda", sigma=sigma).images
        loss = (img - target).abs().mean()
        torch.cuda.synchronize()
        t1 = time.perf_counter()
        loss.backward()
        torch.cuda.synchronize()
        t2 = time.perf_counter()
        if r >= warmup:
            fwd.append(1e3 * (t1 - t0))
            bwd.append(1e3 * (t2 - t1))
            step.append(1e3 * (t2 - t0))

    def nograd():
        with torch.no_grad():
            render(points, normals, cams, settings, backend="cuda", sigma=sigma)

    torch.cuda.reset_peak_memory_stats()
    p = points.clone().requires_grad_()
    (render(p, normals, cams, settings, backend="cuda", sigma=sigma).images - target).abs().mean().backward()
    torch.cuda.synchronize()
    peak = torch.cuda.max_memory_allocated()
    return {
        "forward_with_grad_ms": statistics.median(fwd),
        "backward_ms": statistics.median(bwd),
        "step_ms": statistics.median(step),
        "step_min_ms": min(step),
        "forward_nograd": _timed(nograd, warmup, repeats),
        "peak_memory_mb": peak / 2**20,
        "runs": repeats,
    }


def profile_render_step(points, normals, cams, sigma, settings, steps: int = 3, rows: int = 25) -> dict:
    """torch.profiler over ``steps`` render steps (forward with grad, L1, backward): where the time goes.

    Returns the operators' table twice, by self CUDA time and by CPU time including children
    (at small sizes a step is launch-bound: the CPU column is the one that sets the step time).
    """
    from torch.profiler import ProfilerActivity, profile

    from dss.render import render

    with torch.no_grad():
        target = render(points, normals, cams, settings, backend="cuda", sigma=sigma).images

    def step():
        p = points.clone().requires_grad_()
        n = normals.clone().requires_grad_()
        img = render(p, n, cams, settings, backend="cuda", sigma=sigma).images
        (img - target).abs().mean().backward()

    step()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            step()
        torch.cuda.synchronize()
    ka = prof.key_averages()
    return {"steps": steps,
            "by_self_cuda_time": ka.table(sort_by="self_cuda_time_total", row_limit=rows),
            "by_cpu_time": ka.table(sort_by="cpu_time_total", row_limit=rows)}


def run(points_list=(20_000, 100_000), views: int = 12, image_size: int = 256, warmup: int = 3,
        repeats: int = 10, profile: bool = False) -> dict:
    """Benchmark every size; raises RuntimeError when there is no GPU or the kernels do not build."""
    import importlib

    from dss import _ext_cuda
    from dss.pointcloud import bbox_diagonal
    from dss.render import RenderSettings
    from dss.splats import auto_sigma

    if not torch.cuda.is_available():
        raise RuntimeError("no CUDA device: this benchmark needs a GPU")
    mod = _ext_cuda.load_cuda()
    if mod is None:
        raise RuntimeError(f"the CUDA kernels are not available: {_ext_cuda.build_error()}")
    dev = torch.device("cuda")
    settings = RenderSettings()
    render_mod = importlib.import_module("dss.render")  # the module, even if dss exports a render()
    render_has_cuda = "cuda" in getattr(render_mod, "BACKENDS", ())
    results = []
    for n in points_list:
        pts, nrm, src = _cloud(n)
        cams = _cameras(pts, views, image_size)
        sigma = auto_sigma(pts)  # an input of the step, not timed (as in dss-bench)
        merge = settings.merge_fraction * float(bbox_diagonal(pts))
        pts, nrm, sigma, cams = pts.to(dev), nrm.to(dev), sigma.to(dev), cams.to(dev)
        row = {"points": n, "views": views, "image_size": image_size, "source": src, "K": settings.K,
               "window": settings.window}
        row["kernels"] = bench_kernels(mod, pts, nrm, cams, sigma, settings, merge, warmup, repeats)
        kr = row["kernels"]
        log.info("%d points: kernels %.3f ms (forward %.3f, backward %.3f; row walk %.3f, same bits: %s)", n,
                 kr["sum_median_ms"], kr["rasterize_forward"]["median_ms"], kr["visibility_backward"]["median_ms"],
                 kr["visibility_backward_rows"]["median_ms"], kr["visibility_walks_equal"])
        if render_has_cuda:
            row["render"] = bench_render_step(pts, nrm, cams, sigma, settings, warmup, repeats)
            log.info("%d points: render step %.3f ms", n, row["render"]["step_ms"])
            if profile:
                row["profile"] = profile_render_step(pts, nrm, cams, sigma, settings)
                log.info("%d points, by self CUDA time:\n%s", n, row["profile"]["by_self_cuda_time"])
                log.info("%d points, by CPU time:\n%s", n, row["profile"]["by_cpu_time"])
            if n in TARGET_STEP_MS:
                row["target_step_ms"] = TARGET_STEP_MS[n]
                row["meets_target"] = row["render"]["step_ms"] <= TARGET_STEP_MS[n]
        else:
            row["render"] = "not measured: dss.render has no backend='cuda' yet"
        results.append(row)
    props = torch.cuda.get_device_properties(dev)
    return {
        "device": torch.cuda.get_device_name(dev),
        "compute_capability": f"{props.major}.{props.minor}",
        "gpu_memory_gb": props.total_memory / 1e9,
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "warmup": warmup,
        "repeats": repeats,
        "results": results,
    }


def add_scene_args(ap: argparse.ArgumentParser, repeats: int):
    """The sizes, views, image size and timing repeats of the GPU benchmarks ."""
    ap.add_argument("--points", type=int, nargs="+", default=[20_000, 100_000])
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--image-size", type=int, default=256)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=repeats)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_args(ap, repeats=10)
    ap.add_argument("--out", default=None, help="also write the JSON here (atomically)")
    ap.add_argument("--profile", action="store_true", help="also profile 3 render steps per size (torch.profiler)")
    args = ap.parse_args(argv)
    if args.repeats < 1 or args.warmup < 0:
        ap.error("--repeats must be >= 1 and --warmup >= 0")
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    try:
        result = run(args.points, args.views, args.image_size, args.warmup, args.repeats, args.profile)
    except RuntimeError as e:
        print(json.dumps({"error": str(e)}), file=sys.stderr)
        raise SystemExit(2) from e
    result["command"] = "python -m experiments.benchmarks.bench_gpu " + " ".join(argv if argv is not None else sys.argv[1:])
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        from dss.io_utils import atomic_write_text

        atomic_write_text(args.out, text + "\n")
    return result


if __name__ == "__main__":
    main()
