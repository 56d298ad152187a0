"""``dss-bench``: time the renderer's forward and backward passes, both backends, one run.

    dss-bench                      # 8K, 20K, 100K points x 12 views x 256^2, writes outputs/dss-bench/<time>/
    dss-bench --publish            # writes results/bench/threads2/ (run it with OMP_NUM_THREADS=2)
    dss-bench --sizes 8000 --reps 3 --windows 2 4
    dss-bench --vector-level 1     # the kernels' AVX2 paths only (0: scalar loops)

Points are sampled from the kangaroo mesh in ../shared/data when it is there (a real shape),
else from a generated torus knot. Every number is the median of ``--reps`` runs after one
warm-up run, all in this process; the JSON records the machine (threads, CPU model).
"""

from __future__ import annotations

import argparse
import logging
import os
import platform
import statistics
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from dss.cameras import fit_distance, focal_from_fov, fps_sphere_cameras
from dss.io_utils import atomic_write_json, atomic_write_text
from dss.pointcloud import normalize_unit_diagonal
from dss.render import RenderSettings, render

log = logging.getLogger("dss-bench")
SHARED = Path(__file__).resolve().parents[3] / "shared" / "data"


def benchmark_cloud(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, str]:
    """(points, normals, source) with n points on a real surface when available.

    With ``DSS_BENCH_CLOUDS=DIR`` set, the sampled cloud is read from ``DIR/cloud_<n>_<seed>.npz``
    when that file is there, and written there after sampling otherwise: a machine without open3d
    or without ../shared (a lent GPU box) then times exactly the clouds sampled here.
    """
    cache_dir = os.environ.get("DSS_BENCH_CLOUDS")
    cache = Path(cache_dir) / f"cloud_{n}_{seed}.npz" if cache_dir else None
    if cache is not None and cache.is_file():
        with np.load(cache) as z:
            src = f"{z['source']} (read from {cache})"
            return torch.from_numpy(z["points"]), torch.from_numpy(z["normals"]), src
    p, nn, src = _sample_cloud(n, seed)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_name(cache.name + ".tmp.npz")
        np.savez(tmp, points=p.numpy(), normals=nn.numpy(), source=np.array(src))
        os.replace(tmp, cache)  # atomic: a half-written cache is never read
    return p, nn, src


def _sample_cloud(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, str]:
    import open3d as o3d

    mesh_path = SHARED / "Kangaroo_V10k.ply"
    if mesh_path.exists():
        mesh = o3d.io.read_triangle_mesh(str(mesh_path))
        src = f"{mesh_path.name} (uniform surface samples)"
    else:
        # Loud: timings of the torus are not comparable with the kangaroo's (a checkout without
        # ../shared beside it, e.g. a git worktree elsewhere, silently changed the scene once).
        warnings.warn(f"{mesh_path} not found: benchmarking a generated torus instead of the kangaroo; "
                      "its times are not comparable with tables made from the kangaroo", RuntimeWarning, stacklevel=2)
        mesh = o3d.geometry.TriangleMesh.create_torus(torus_radius=1.0, tube_radius=0.3, radial_resolution=120, tubular_resolution=60)
        src = "generated torus"
    mesh.compute_triangle_normals()
    o3d.utility.random.seed(seed)
    pcd = mesh.sample_points_uniformly(n, use_triangle_normal=True)
    p = torch.from_numpy(np.asarray(pcd.points, np.float32).copy())
    nn = torch.from_numpy(np.asarray(pcd.normals, np.float32).copy())
    p, _, _ = normalize_unit_diagonal(p)
    return p, nn, src


def cameras_for(points: torch.Tensor, views: int, size: int, seed: int = 0):
    radius = float(points.norm(dim=1).max())
    fov = 30.0
    return fps_sphere_cameras(views, (0, 0, 0), fit_distance(radius, fov), focal_from_fov(fov, size), (size, size),
                              jitter=0.05, generator=torch.Generator().manual_seed(seed))


def _median_time(fn, reps: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def bench_forward(points, normals, cams, backend: str, reps: int) -> float:
    s = RenderSettings()
    sigma = None

    def fwd():
        with torch.no_grad():
            render(points, normals, cams, s, backend=backend, sigma=sigma)

    from dss.splats import auto_sigma

    sigma = auto_sigma(points)  # the splat size is an input here, not part of the timed pass
    return _median_time(fwd, reps)


def bench_backward(points, normals, cams, backend: str, reps: int, window: int) -> dict:
    """Median forward-with-grad and backward times for one SMAPE-like L1 step."""
    from dss.splats import auto_sigma

    s = RenderSettings(window=window)
    sigma = auto_sigma(points)
    with torch.no_grad():
        target = render(points + 0.003 * torch.randn_like(points), normals, cams, s, backend=backend, sigma=sigma).images
    fwd_t, bwd_t = [], []
    for r in range(reps + 1):
        p = points.clone().requires_grad_()
        n = normals.clone().requires_grad_()
        t0 = time.perf_counter()
        img = render(p, n, cams, s, backend=backend, sigma=sigma).images
        loss = (img - target).abs().mean()
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        if r > 0:
            fwd_t.append(t1 - t0)
            bwd_t.append(t2 - t1)
    return {"forward_with_grad_ms": 1e3 * statistics.median(fwd_t), "backward_ms": 1e3 * statistics.median(bwd_t)}


def bench_ordering(points, normals, cams, reps: int) -> dict:
    """Median times (ms) with ``RenderSettings.spatial_sort`` off and on, measured interleaved (so
    both see the same machine load): forward without grad, and forward + backward of a position
    step and of a normal step (L1 to a perturbed render). The cloud is in its file's order."""
    from dss.splats import auto_sigma

    sigma = auto_sigma(points)
    with torch.no_grad():
        target = render(points + 0.003 * torch.randn_like(points), normals, cams, backend="cpp", sigma=sigma).images
    times: dict = {}
    for r in range(reps + 1):
        for sort in (False, True):
            s = RenderSettings(spatial_sort=sort)
            t = {}
            with torch.no_grad():
                t0 = time.perf_counter()
                render(points, normals, cams, s, backend="cpp", sigma=sigma)
                t["forward_nograd"] = time.perf_counter() - t0
            for kind in ("position", "normal"):
                p = points.clone().requires_grad_(kind == "position")
                n = normals.clone().requires_grad_(kind == "normal")
                t0 = time.perf_counter()
                loss = (render(p, n, cams, s, backend="cpp", sigma=sigma).images - target).abs().mean()
                t1 = time.perf_counter()
                loss.backward()
                t[f"{kind}_forward"], t[f"{kind}_backward"] = t1 - t0, time.perf_counter() - t1
            if r > 0:  # the first round warms up
                for k, v in t.items():
                    times.setdefault("sorted" if sort else "file_order", {}).setdefault(k, []).append(v)
    out = {mode: {k + "_ms": 1e3 * statistics.median(v) for k, v in d.items()} for mode, d in times.items()}
    out["speedup"] = {k: out["file_order"][k] / out["sorted"][k] for k in out["sorted"]}
    return out


def machine_info() -> dict:
    cpu = platform.processor()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    from dss import _ext

    mod = _ext.load_cpu()
    level = mod.vector_level() if mod is not None else None
    return {"cpu": cpu, "torch_threads": torch.get_num_threads(), "cores": os.cpu_count(), "torch": torch.__version__,
            "kernel_openmp": _ext.openmp_enabled(),
            # the vector paths the C++ kernels take (dss/csrc/cpu_runtime.cpp g_vector_level)
            "kernel_vector_isa": {0: "scalar", 1: "avx2", 2: "avx512"}.get(level)}


def main(argv=None) -> int:
    run(argv)
    return 0


def run(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[8000, 20000, 100000])
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--image-size", type=int, default=256)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--reference-reps", type=int, default=5)
    ap.add_argument("--reference-max-points", type=int, default=100000,
                    help="skip the pure-torch reference above this size (it is slow)")
    ap.add_argument("--windows", type=int, nargs="*", default=[0, 2, 4, 8, 16],
                    help="visibility-gradient window half sizes timed for the backward pass (C++ backend)")
    ap.add_argument("--backward-sizes", type=int, nargs="*", default=[20000])
    ap.add_argument("--order", action="store_true",
                    help="also compare the file's point order with render()'s spatial sort (backward sizes)")
    ap.add_argument("--vector-level", type=int, choices=(0, 1, 2), default=None,
                    help="the highest vector level the C++ kernels may take (0 scalar, 1 AVX2, 2 AVX-512; default: "
                         "the best this CPU has), to time a CPU without AVX2 or AVX-512 on one that has them")
    from experiments import outputs

    outputs.add_arguments(ap, published="results/bench/threads2")
    args = ap.parse_args(argv)
    args.out = str(outputs.folder(args, "dss-bench"))
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from dss import _ext

    if not _ext.cpu_available():
        raise SystemExit(f"the C++ backend is not available: {_ext.build_error()}")
    if args.vector_level is not None:
        _ext.load_cpu().set_vector_level(args.vector_level)
    rows, back_rows, order_rows = [], [], []
    for n in args.sizes:
        pts, nrm, src = benchmark_cloud(n)
        cams = cameras_for(pts, args.views, args.image_size)
        row = {"points": n, "views": args.views, "image_size": args.image_size, "source": src}
        row["cpp_forward_ms"] = 1e3 * bench_forward(pts, nrm, cams, "cpp", args.reps)
        log.info("%d points: cpp forward %.1f ms", n, row["cpp_forward_ms"])
        if n <= args.reference_max_points:
            row["reference_forward_ms"] = 1e3 * bench_forward(pts, nrm, cams, "reference", args.reference_reps)
            row["speedup"] = row["reference_forward_ms"] / row["cpp_forward_ms"]
            log.info("%d points: reference forward %.1f ms (x%.1f)", n, row["reference_forward_ms"], row["speedup"])
        rows.append(row)
        if n in args.backward_sizes:
            for w in args.windows:
                b = bench_backward(pts, nrm, cams, "cpp", args.reps, w)
                b.update(points=n, window=w, forward_nograd_ms=row["cpp_forward_ms"])
                b["backward_over_forward"] = b["backward_ms"] / row["cpp_forward_ms"]
                back_rows.append(b)
                log.info("%d points window %d: backward %.1f ms (%.2fx forward)", n, w, b["backward_ms"], b["backward_over_forward"])
            if args.order:
                o = bench_ordering(pts, nrm, cams, args.reps)
                o["points"] = n
                order_rows.append(o)
                log.info("%d points: spatial sort speed-ups %s", n, {k: round(v, 2) for k, v in o["speedup"].items()})
    result = {"machine": machine_info(), "forward": rows, "backward": back_rows, "ordering": order_rows,
              "command": "dss-bench " + " ".join(argv if argv is not None else __import__("sys").argv[1:])}
    out = Path(args.out)
    atomic_write_json(out / "render_bench.json", result)
    md = ["| points | views | size | C++ forward (ms) | reference forward (ms) | speed-up |", "|---|---|---|---|---|---|"]
    for r in rows:
        ref = f"{r['reference_forward_ms']:.0f}" if "reference_forward_ms" in r else "skipped"
        sp = f"{r['speedup']:.1f}x" if "speedup" in r else "-"
        md.append(f"| {r['points']} | {r['views']} | {r['image_size']} | {r['cpp_forward_ms']:.1f} | {ref} | {sp} |")
    if back_rows:
        md += ["", "| points | window (half size, px) | forward with grad (ms) | backward (ms) | backward / forward |",
               "|---|---|---|---|---|"]
        for b in back_rows:
            md.append(f"| {b['points']} | {b['window']} | {b['forward_with_grad_ms']:.1f} | {b['backward_ms']:.1f} | {b['backward_over_forward']:.2f} |")
    if order_rows:
        md += ["", "| points | pass | file order (ms) | spatially sorted (ms) | speed-up |", "|---|---|---|---|---|"]
        for o in order_rows:
            for k in o["sorted"]:
                md.append(f"| {o['points']} | {k[:-3].replace('_', ' ')} | {o['file_order'][k]:.1f} | "
                          f"{o['sorted'][k]:.1f} | {o['speedup'][k]:.2f}x |")
    md.append("")
    md.append(f"Machine: {result['machine']['cpu']}, {result['machine']['torch_threads']} torch threads; median of {args.reps} runs after a warm-up.")
    atomic_write_text(out / "render_bench.md", "\n".join(md) + "\n")
    print("\n".join(md))
    return result


if __name__ == "__main__":
    raise SystemExit(main())
