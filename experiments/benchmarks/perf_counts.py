"""Count the renderer's work per workload and derive floor times (issue: speed to the limit).

    python -m experiments.benchmarks.perf_counts [--publish]   # --publish: results/bench/perf_counts.json

For each workload (points x 12 views x 256^2) it counts, from one real optimisation step of the
C++ backend (the cloud against a copy moved by 0.003 of the bbox diagonal, as dss-runtime-table):

- forward: valid splats (after back-face and near-plane culling), projected splats (V x N),
  bounding-box pixel tests, accepted fragments (inside the cutoff ellipse, approximated by
  pi rx ry), and the image elements the SMAPE loss reads;
- backward of a normal step: the visible cached fragments blend_backward visits, and the
  projection's backward per (view, point);
- backward of a position step: the same plus the visibility gradient's (point, view, pixel)
  evaluations, counted exactly: window pixels (9 x 9 at window 4) inside the image whose loss
  gradient is non-zero, the pixels the kernel evaluates.

Each count is charged a cost in floating-point operations (constants below, from the kernels'
arithmetic; a division or square root counts as one) and the bytes that must move at least once
(splats in, the top-K cache and images out; the backward reads them again with the gradient).
floor = max(flops / measured arithmetic rate, bytes / measured memory bandwidth) for the forward
and for each kind's backward; the step floor is their sum. Both rates are measured here, each
as the fastest of repeated calls (a float32 matmul on all torch threads, which reaches the
vector-FMA peak, and the faster of a numpy copy on one thread and a torch copy on all threads),
so the floor is what perfectly vectorised code with no branch or latency stall would take.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import torch

from dss.reference import bbox, project_splats
from dss.render import RenderSettings
from dss.splats import auto_sigma
from experiments import outputs
from experiments.benchmarks.bench_render import benchmark_cloud, cameras_for, machine_info

# flops per bbox pixel test: dx, dy (2), q (5 mul + 2 add), compare (1); accepted: exp (~20),
# weight (1), insertion (~K compares); per blended entry ~2C+1.
FLOPS_TEST = 10
FLOPS_ACCEPT = 30
# per (view, point): the projection (rotation 18, Jacobian / conic / weight ~80) and its
# backward (~150); per image element: SMAPE value and derivative (~10).
FLOPS_PROJECT = 100
FLOPS_PROJECT_BWD = 150
FLOPS_LOSS = 10
# per visible cached fragment in blend_backward: q and exp (~25), the per-channel and conic
# accumulations (~2C + 15).
FLOPS_BLEND_BWD = 45
# per visibility evaluation: the cache search (K), the tangent-plane depth and case tests (~15),
# g.w and the new blend (~2C + 6), g.(I_new - I) (3), the move and its coefficient (~20).
FLOPS_VISIBILITY = 50
POSITION_WINDOW = 4
TARGET_NOISE = 0.003


def _best_rate(fn, work: float, seconds: float, clock=time.perf_counter) -> float:
    """work / the fastest of repeated calls of fn over about ``seconds`` (a peak, as a floor
    needs: the mean over a second moves with whatever else shares the machine, measured 20.1 vs
    25.7 GB/s for the same copy minutes apart)."""
    fn()
    best, t_end = float("inf"), clock() + seconds
    while clock() < t_end:
        t = clock()
        fn()
        best = min(best, clock() - t)
    return work / best


def measure_rates(seconds: float = 1.0) -> dict:
    """Peak float32 arithmetic rate (torch matmul, all threads) and copy bandwidth (read + write
    bytes per second; the faster of a numpy copy on one thread and a torch copy on all threads)."""
    x = torch.rand(1024, 1024)
    y = torch.rand(1024, 1024)
    flops = _best_rate(lambda: torch.mm(x, y), 2 * 1024**3, seconds)
    m = np.random.rand(32_000_000).astype(np.float32)
    dst = np.empty_like(m)
    bw_1 = _best_rate(lambda: np.copyto(dst, m), 2 * m.nbytes, seconds)
    mt, dt = torch.from_numpy(m), torch.from_numpy(dst)
    bw_all = _best_rate(lambda: dt.copy_(mt), 2 * m.nbytes, seconds)
    return {"flops_per_s": flops, "bytes_per_s": max(bw_1, bw_all), "copy_bytes_per_s_1thread": bw_1,
            "copy_bytes_per_s_all_threads": bw_all,
            "note": "fastest call of each over ~1 s: flops: float32 matmul (torch, all threads) = the arithmetic "
                    "peak; bytes: the faster of a numpy copy (one thread) and a torch copy (all threads), "
                    "read + write"}


def measure_gpu_rates(seconds: float = 1.0, device: str = "cuda") -> dict:
    """Peak float32 arithmetic rate (an 8192^3 matmul with TF32 off: the CUDA cores' FP32, the
    unit the kernels use) and device-to-device copy bandwidth (1 GiB, read + write bytes) of a
    GPU, each the fastest of repeated synchronised calls over about ``seconds``."""
    dev = torch.device(device)
    tf32 = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = False
    try:
        n = 8192
        g = torch.Generator(device=dev).manual_seed(0)
        a = torch.rand(n, n, device=dev, generator=g)
        b = torch.rand(n, n, device=dev, generator=g)

        def mm():
            torch.mm(a, b)
            torch.cuda.synchronize(dev)

        flops = _best_rate(mm, 2 * n**3, seconds)
        x = torch.rand(2**28, device=dev, generator=g)  # 1 GiB, never zeros
        y = torch.empty_like(x)

        def cp():
            y.copy_(x)
            torch.cuda.synchronize(dev)

        bw = _best_rate(cp, 2 * x.nbytes, seconds)
    finally:
        torch.backends.cuda.matmul.allow_tf32 = tf32
    return {"device": torch.cuda.get_device_name(dev), "flops_per_s": flops, "bytes_per_s": bw,
            "torch": torch.__version__, "cuda": torch.version.cuda,
            "note": "fastest synchronised call of each over ~1 s: flops: float32 8192^3 matmul, TF32 off; bytes: "
                    "1 GiB device-to-device copy, read + write"}


def step_floors(work: dict, rates: dict) -> tuple[float, dict]:
    """A counted workload's forward floor and, per counted backward kind, its step floor (forward +
    that backward), in ms, on a device's rates."""
    fwd = floors(work, rates)["floor_ms"]
    return fwd, {k: fwd + floors(b, rates)["floor_ms"] for k, b in (work.get("backward") or {}).items()}


def gpu_floors(counts: dict, rates: dict) -> list[dict]:
    """Forward and step floors (ms) of the counted workloads on the measured GPU rates."""
    rows = []
    for w in counts["workloads"]:
        fwd, steps = step_floors(w, rates)
        rows.append({"points": w["points"], "views": w["views"], "image_size": w["image_size"], "forward_floor_ms": fwd,
                     "step_floor_ms": steps})
    return rows


def _step_counts(pts, nrm, cams, sigma, s: RenderSettings) -> dict:
    """Visible cached fragments and visibility evaluations of one position step (C++ backend)."""
    from dss.losses import smape_loss
    from dss.render import render

    g = torch.Generator().manual_seed(1)
    target = render(pts + TARGET_NOISE * torch.randn(pts.shape, generator=g), nrm, cams, s, sigma=sigma).images
    p = pts.clone().requires_grad_()
    out = render(p, nrm, cams, s, sigma=sigma)
    (grad,) = torch.autograd.grad(smape_loss(out.images, target, channel_reduction="mean"), out.images)
    frags = out.fragments
    visible = int(frags.visible.sum())
    # evaluations: for each valid splat, the window pixels inside the image with a non-zero
    # gradient (a box sum over the non-zero map, padded so centres off the image count too)
    w = s.window
    nz = (grad != 0).any(-1).float()[:, None]  # (V, 1, H, W)
    V, _, H, W = nz.shape
    box = torch.nn.functional.conv2d(torch.nn.functional.pad(nz, (2 * w,) * 4), torch.ones(1, 1, 2 * w + 1, 2 * w + 1))
    pk = out.splats.packed.detach()
    valid = pk[..., 9] > 0
    ii = torch.floor(pk[..., 1]).long() + w  # index into the map padded by w on each side
    jj = torch.floor(pk[..., 0]).long() + w
    inside = valid & (ii >= 0) & (ii < H + 2 * w) & (jj >= 0) & (jj < W + 2 * w)
    vv = torch.arange(V)[:, None].expand_as(ii)
    evals = float(box[vv[inside], 0, ii[inside], jj[inside]].sum())
    return {"visible_fragments": visible, "visibility_evaluations": evals,
            "nonzero_gradient_pixels": int(nz.sum()), "cache_entries": int((frags.idx >= 0).sum())}


def _workload(n: int, views: int, size: int):
    """The benchmark cloud of n points, its cameras, settings (window 4), sigma, source name and
    its projected splats (packed (V, N, 10))."""
    pts, nrm, src = benchmark_cloud(n)
    cams = cameras_for(pts, views, size)
    s = RenderSettings(window=POSITION_WINDOW)
    sigma = auto_sigma(pts)
    sp = project_splats(pts, nrm, cams, sigma, s.cutoff, s.backface_culling, s.znear, s.filter_variance)
    return pts, nrm, cams, s, sigma, src, sp.packed


def count(n: int, views: int = 12, size: int = 256) -> dict:
    pts, nrm, cams, s, sigma, src, pk = _workload(n, views, size)
    valid = pk[..., 9] > 0
    j0, j1, i0, i1 = bbox(pk, size, size)
    area = ((j1 - j0 + 1).clamp_min(0) * (i1 - i0 + 1).clamp_min(0)).float() * valid
    # accepted fragments: pi * rx * ry approximates the cutoff ellipse's pixel count
    accepted = (np.pi * pk[..., 7] * pk[..., 8] * valid).sum().item()
    tests = area.sum().item()
    K, C = s.K, 3
    pixels = views * size * size
    cache_bytes = pixels * K * 12  # index, depth, weight per slot
    image_bytes = pixels * C * 4
    splat_bytes = pk.numel() * 4
    step = _step_counts(pts, nrm, cams, sigma, s)
    vn = views * n
    # forward: projection, rasterisation (cache + image out), loss (two images in)
    fwd_flops = tests * FLOPS_TEST + accepted * FLOPS_ACCEPT + vn * FLOPS_PROJECT + pixels * C * FLOPS_LOSS
    fwd_bytes = splat_bytes + cache_bytes + image_bytes + 2 * image_bytes
    # backward, normal step: blend backward reads the cache, image and gradient, writes the
    # splat and attribute gradients; the projection backward reads them
    nrm_flops = step["visible_fragments"] * FLOPS_BLEND_BWD + vn * FLOPS_PROJECT_BWD
    nrm_bytes = cache_bytes + 2 * image_bytes + 2 * splat_bytes
    # backward, position step: the same plus the visibility gradient (cache, image and gradient
    # read once more)
    pos_flops = nrm_flops + step["visibility_evaluations"] * FLOPS_VISIBILITY
    pos_bytes = nrm_bytes + cache_bytes + 2 * image_bytes
    return {"points": n, "views": views, "image_size": size, "source": src, "valid_splats": int(valid.sum()),
            "bbox_pixel_tests": tests, "accepted_fragments_approx": accepted, **step,
            "flops": fwd_flops, "bytes": fwd_bytes,
            "backward": {"position": {"flops": pos_flops, "bytes": pos_bytes},
                         "normal": {"flops": nrm_flops, "bytes": nrm_bytes}}}


def floors(work: dict, rates: dict) -> dict:
    """floor = max(flops / rate, bytes / bandwidth) in ms."""
    c = 1e3 * work["flops"] / rates["flops_per_s"]
    m = 1e3 * work["bytes"] / rates["bytes_per_s"]
    return {"compute_ms": c, "memory_ms": m, "floor_ms": max(c, m)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[8000, 20000, 100000])
    outputs.add_arguments(ap, published="results/bench/perf_counts.json", what="output JSON file")
    ap.add_argument("--gpu-rates", metavar="OUT", default=None,
                    help="instead: measure this machine's GPU rates and write them, with the floors of the "
                         "workloads counted in --counts on those rates, to OUT (JSON)")
    ap.add_argument("--counts", default="results/bench/perf_counts.json", help="with --gpu-rates: the counted work")
    args = ap.parse_args(argv)
    if args.gpu_rates:
        from dss.io_utils import atomic_write_json

        if not torch.cuda.is_available():
            raise SystemExit("--gpu-rates needs a CUDA GPU")
        counts = json.loads(open(args.counts).read())
        rates = measure_gpu_rates()
        res = {"command": "python -m experiments.benchmarks.perf_counts " + " ".join(argv if argv is not None else sys.argv[1:]),
               "rates": rates, "counts": args.counts, "floors": gpu_floors(counts, rates)}
        atomic_write_json(args.gpu_rates, res)
        print(json.dumps(res, indent=2))
        return 0
    rates = measure_rates()
    rows = []
    for n in args.sizes:
        r = count(n)
        fwd = floors(r, rates)
        r["floor_ms_compute"], r["floor_ms_memory"], r["floor_ms"] = fwd["compute_ms"], fwd["memory_ms"], fwd["floor_ms"]
        r["step_floor_ms"] = {}
        for kind, work in r["backward"].items():
            work.update(floors(work, rates))
            r["step_floor_ms"][kind] = fwd["floor_ms"] + work["floor_ms"]
        rows.append(r)
        print(json.dumps(r))
    from dss.io_utils import atomic_write_json

    out = outputs.folder(args, "perf_counts", name="perf_counts.json")
    atomic_write_json(out, {"machine": machine_info(), "rates": rates, "workloads": rows})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
