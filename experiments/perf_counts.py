"""Count the renderer's work per workload and derive a floor time (issue: speed to the limit).

    python -m experiments.perf_counts [--out docs/perf_counts.json]

For each workload (points x 12 views x 256^2) it counts, from the same splats the kernels see:
valid splats (after back-face and near-plane culling), bounding-box pixel tests, accepted
fragments (inside the cutoff ellipse) and cache entries written. With a per-test cost in
floating-point operations and the bytes that must move (splats in, cache and image out), the
floor is max(ops / measured arithmetic rate, bytes / measured memory bandwidth), both rates
measured here with numpy on the same machine (all cores).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from dss.rasterizer.reference import bbox
from dss.render import RenderSettings
from dss.splats import auto_sigma, project_splats
from experiments.bench_render import benchmark_cloud, cameras_for, machine_info

# flops per bbox pixel test: dx, dy (2), q (5 mul + 2 add), compare (1); accepted: exp (~20),
# weight (1), insertion (~K compares); per blended entry ~2C+1.
FLOPS_TEST = 10
FLOPS_ACCEPT = 30


def measure_rates(seconds: float = 1.0) -> dict:
    """Peak float32 arithmetic rate (torch matmul, all threads) and copy bandwidth (numpy)."""
    x = torch.rand(1024, 1024)
    y = torch.rand(1024, 1024)
    torch.mm(x, y)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        torch.mm(x, y)
        n += 1
    flops = n * 2 * 1024**3 / (time.perf_counter() - t0)
    m = np.random.rand(32_000_000).astype(np.float32)
    dst = np.empty_like(m)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        np.copyto(dst, m)
        n += 1
    bw = n * m.nbytes * 2 / (time.perf_counter() - t0)
    return {"flops_per_s": flops, "bytes_per_s": bw,
            "note": "flops: float32 matmul (torch, all threads) = the arithmetic peak; bytes: numpy copy (read+write)"}


def count(n: int, views: int = 12, size: int = 256) -> dict:
    pts, nrm, src = benchmark_cloud(n)
    cams = cameras_for(pts, views, size)
    s = RenderSettings()
    sp = project_splats(pts, nrm, cams, auto_sigma(pts), s.cutoff, s.backface_culling, s.znear, s.filter_variance)
    pk = sp.packed
    valid = pk[..., 9] > 0
    j0, j1, i0, i1 = bbox(pk, size, size)
    area = ((j1 - j0 + 1).clamp_min(0) * (i1 - i0 + 1).clamp_min(0)).float() * valid
    # accepted fragments: pi * rx * ry approximates the cutoff ellipse's pixel count
    accepted = (np.pi * pk[..., 7] * pk[..., 8] * valid).sum().item()
    tests = area.sum().item()
    K, C = s.K, 3
    bytes_moved = (pk.numel() * 4 + views * size * size * (K * 12 + C * 4))
    ops = tests * FLOPS_TEST + accepted * FLOPS_ACCEPT
    return {"points": n, "views": views, "image_size": size, "source": src, "valid_splats": int(valid.sum()),
            "bbox_pixel_tests": tests, "accepted_fragments_approx": accepted, "flops": ops, "bytes": bytes_moved}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[8000, 20000, 100000])
    ap.add_argument("--out", default="docs/perf_counts.json")
    args = ap.parse_args(argv)
    rates = measure_rates()
    rows = []
    for n in args.sizes:
        r = count(n)
        r["floor_ms_compute"] = 1e3 * r["flops"] / rates["flops_per_s"]
        r["floor_ms_memory"] = 1e3 * r["bytes"] / rates["bytes_per_s"]
        r["floor_ms"] = max(r["floor_ms_compute"], r["floor_ms_memory"])
        rows.append(r)
        print(json.dumps(r))
    from dss.io_utils import atomic_write_json

    atomic_write_json(args.out, {"machine": machine_info(), "rates": rates, "workloads": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
