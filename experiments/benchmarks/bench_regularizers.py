"""Time the regularisers' per-step work with the C++ kernel and with its torch twin, interleaved,
and their neighbour search with cKDTree and the C++ grid.

    OMP_NUM_THREADS=2 python -m experiments.benchmarks.bench_regularizers [--points 20000 100000] [--threads 2]
        [--reps 15] [--out results/bench/regularizers.json]

One "step" is what ``MultiViewOptimizer`` does per step for a regulariser term:
``local_frames`` (weighted PCA of every point's k = 16 neighbourhood, with normals and
occlusion counts) and the gradient of the projection loss through it. The cloud is the
shipped example's noisy cloud (``experiments/assets/example``) for 20K points, and a noisy
Poisson-disk sampling of its mesh (1% of the diagonal, seeded) for other counts; the neighbour
lists are found once, as the optimiser caches them per cycle. The backends alternate rep by rep;
the medians and their ratio go to stdout and ``--out`` (JSON), with each float32 gradient's
relative distance to the float64 one (the same points through the torch twin in float64): the
kernel accumulates in double, so where the two float32 backends differ it is the closer one.
The kNN rows time one search per backend (k = 16 and 64, self excluded) and say whether the two
results were identical.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from dss.io_utils import atomic_write_json
from experiments.figures import command_line

ASSETS = Path(__file__).resolve().parents[1] / "assets" / "example"


def bench_cloud(n: int, seed: int = 0) -> torch.Tensor:
    """(n, 3) float32: the example's noisy cloud (n = its size) or a noisy sampling of its mesh."""
    from dss.metrics import load_mesh, sample_poisson_disk
    from dss.pointcloud import load_ply

    noisy = load_ply(ASSETS / "noisy_1pct.ply").points
    if n == noisy.shape[0]:
        return noisy.float()
    clean = sample_poisson_disk(load_mesh(ASSETS / "mesh.ply"), n, seed)
    diag = float(np.linalg.norm(clean.max(0) - clean.min(0)))
    rng = np.random.default_rng(seed)
    return torch.from_numpy(clean + rng.normal(0.0, 0.01 * diag, clean.shape)).float()


def time_backends(points: torch.Tensor, reps: int, k: int = 16) -> dict:
    """Median ms per step of each backend (alternating), and the cpp / torch agreement."""
    from dss.pointcloud import estimate_normals
    from dss.regularizers import bandwidth_for, find_neighbors, local_frames, projection_loss

    normals = estimate_normals(points, k=k)
    g = torch.Generator().manual_seed(0)
    occlusion = torch.randint(0, 3, (points.shape[0],), generator=g).float()
    nb = find_neighbors(points, k)
    D = bandwidth_for(points)

    def step(backend, dtype=torch.float32):
        q = points.detach().to(dtype).requires_grad_(True)
        fr = local_frames(q, normals.to(dtype), occlusion.to(dtype), bandwidth=D, neighbors=nb, pca_backend=backend)
        (grad,) = torch.autograd.grad(projection_loss(q, frames=fr, bandwidth=D), q)
        return grad.double()

    grads = {b: step(b) for b in ("torch", "cpp")}  # warm-up (and the kernel's build)
    # the same points in float64 through the torch twin: how far each float32 result is from it
    exact = step("torch", torch.float64)
    err = {b: float((g - exact).norm() / exact.norm()) for b, g in grads.items()}
    times: dict = {"torch": [], "cpp": []}
    for _ in range(reps):
        for b in times:
            t = time.perf_counter()
            step(b)
            times[b].append(1e3 * (time.perf_counter() - t))
    med = {b: statistics.median(v) for b, v in times.items()}
    rel = float((grads["cpp"] - grads["torch"]).norm() / grads["torch"].norm())
    return {"points": int(points.shape[0]), "k": k, "torch_ms": med["torch"], "cpp_ms": med["cpp"],
            "speedup": med["torch"] / med["cpp"], "grad_rel_diff": rel,
            "grad_rel_err_vs_float64": err, "runs_ms": times}


def time_knn(points: torch.Tensor, reps: int, ks=(16, 64)) -> list[dict]:
    """Median ms of one neighbour search (self excluded, as the optimiser refreshes them once per
    cycle: 16 neighbours x a dilation of round(N / 20000), so 16 at 20K and 80 at 100K points;
    64 stands for a dilated list) with cKDTree and the C++ grid, alternating."""
    from dss.knn import knn

    rows = []
    for k in ks:
        times: dict = {"scipy": [], "cpp": []}
        same = True
        for _ in range(reps):
            res = {}
            for b in times:
                t = time.perf_counter()
                res[b] = knn(points, k, exclude_self=True, backend=b)
                times[b].append(1e3 * (time.perf_counter() - t))
            same &= torch.equal(res["scipy"].idx, res["cpp"].idx) and torch.equal(res["scipy"].dist, res["cpp"].dist)
        med = {b: statistics.median(v) for b, v in times.items()}
        rows.append({"points": int(points.shape[0]), "k": k, "scipy_ms": med["scipy"], "cpp_ms": med["cpp"],
                     "speedup": med["scipy"] / med["cpp"], "identical": bool(same), "runs_ms": times})
    return rows


def run(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, nargs="+", default=[20000, 100000])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=15)
    ap.add_argument("--out", default=None, help="JSON file for the result")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows, knn_rows = [], []
    for n in args.points:
        cloud = bench_cloud(n)
        r = time_backends(cloud, args.reps)
        rows.append(r)
        for kr in time_knn(cloud, args.reps):
            knn_rows.append(kr)
            print(f"{n} points, kNN k={kr['k']}: scipy {kr['scipy_ms']:.1f} ms, cpp {kr['cpp_ms']:.1f} ms "
                  f"({kr['speedup']:.2f}x), identical: {kr['identical']}")
        print(f"{r['points']} points: torch {r['torch_ms']:.1f} ms, cpp {r['cpp_ms']:.1f} ms "
              f"({r['speedup']:.2f}x); gradients differ by {r['grad_rel_diff']:.1e} (relative), from the float64 "
              f"result by {r['grad_rel_err_vs_float64']['torch']:.1e} (torch) / "
              f"{r['grad_rel_err_vs_float64']['cpp']:.1e} (cpp)")
    result = {"threads": args.threads, "reps": args.reps, "rows": rows, "knn": knn_rows,
              "command": command_line("python -m experiments.benchmarks.bench_regularizers", argv)}
    if args.out:
        atomic_write_json(args.out, result)
    return result


def main(argv=None) -> int:
    run(argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
