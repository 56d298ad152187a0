"""``dss-runtime-table``: the paper's Table "Runtime and GPU memory" (tab:speed), reproduced.

    dss-runtime-table                         # 8K / 20K / 100K points, 12 views, 256^2
    dss-runtime-table --measure 3 --backends cpp
    dss-runtime-table --quick --out /tmp/rt   # tiny sizes, for tests
    dss-runtime-table --backends cuda --gpu-rates gpu_rates.json   # CUDA floors on the GPU's measured rates
    dss-runtime-table --from-json rt.json --gpu-rates gpu_rates.json --out rt2   # redo the floors only

Workloads (paper Table tab:speed, 256x256 images, 12 views per optimisation step):

============================  ======  ===============  =============
application                   points  position steps   normal steps
============================  ======  ===============  =============
shape deformation             8 000   200              120
L0 surface filtering          20 000  8                152
denoising                     100 000 8                152
============================  ======  ===============  =============

For every workload and backend (``cpp`` always; ``reference``, the pure-PyTorch renderer, only up
to ``--reference-max-points``; ``cuda`` only when ``torch.cuda.is_available()``) it runs real
optimisation steps: fresh cameras from :class:`dss.views.SphereViewSampler` every step, a
target rendered from a perturbed copy of the cloud (not timed), then the timed part,
``render(..., backend=...)`` + :func:`dss.losses.smape_loss` (the forward) and
``loss.backward()`` (the backward), then an Adam update (not timed). Position steps take the
gradient w.r.t. the positions (visibility-gradient window 4), normal steps w.r.t. the normals,
each timed separately: ``--warmup`` steps, then the median over ``--measure`` steps.

Reported per workload and backend:
- average forward / backward ms: the per-kind medians averaged with the paper's step counts as
  weights (the paper's "avg. forward time" is over all steps of a run);
- total s: **estimated** as sum over kinds of (forward + backward median) x steps of that kind,
  not a full run (the paper's totals are wall-clock of whole runs and include everything else);
- peak memory: CPU: peak resident set (VmHWM, reset through /proc/self/clear_refs before the
  measurement) minus the resident set at the start of it, i.e. the working set the steps add;
  where the reset is not allowed, the growth of ``getrusage(RUSAGE_SELF).ru_maxrss`` (a lower
  bound: memory that an earlier, larger peak already touched is not counted). CUDA:
  ``torch.cuda.max_memory_allocated`` minus the allocation at the start.

Scenes are those of ``dss-bench`` (experiments/benchmarks/bench_render.py :func:`benchmark_cloud`: samples
of the kangaroo mesh in ../shared/data when it is there, else a generated torus), with the
camera distance and field of view of its :func:`cameras_for`. Writes ``<out>.json`` and
``<out>.md`` atomically (default ``results/bench/runtime_table``).
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import logging
import os
import re
import resource
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from dss.gc_pause import frozen_gc
from dss.io_utils import atomic_write_json, atomic_write_text
from dss.losses import smape_loss
from dss.render import RenderSettings, render
from dss.splats import auto_sigma
from dss.views import SphereViewSampler
from experiments import outputs
from experiments.benchmarks import perf_counts
from experiments.benchmarks.bench_render import benchmark_cloud, machine_info

log = logging.getLogger("dss-runtime-table")

BACKENDS = ("cpp", "cuda", "reference")
KINDS = ("position", "normal")
# cameras_for() in bench_render: 30 degree field of view, 5 % jitter on the sphere directions
FOV_DEG = 30.0
JITTER = 0.05
# target = the cloud moved by this fraction of its bbox diagonal (clouds are unit-diagonal)
TARGET_NOISE = 0.003
POSITION_WINDOW = 4
NOT_MEASURED_NO_GPU = "not measured (no GPU)"


@dataclass(frozen=True)
class Workload:
    key: str
    application: str
    points: int
    paper_points: int
    position_steps: int
    normal_steps: int
    paper_forward_ms: float
    paper_backward_ms: float
    paper_total_s: float
    paper_memory: str  # as printed in the paper's table

    def steps(self, kind: str) -> int:
        return self.position_steps if kind == "position" else self.normal_steps


# The paper's Table tab:speed (NVIDIA GTX 1080Ti, CUDA 10.0), copied from ../shared/paper/dss-paper.tex.
WORKLOADS = (
    Workload("deformation", "shape deformation", 8000, 8003, 200, 120, 19.3, 79.9, 336, "1.7MB"),
    Workload("filtering", "L0 surface filtering", 20000, 20000, 8, 152, 42.8, 164.6, 665, "1.8MB"),
    Workload("denoising", "denoising", 100000, 100000, 8, 152, 258.1, 680.2, 1951, "2.3MB"),
)
PAPER_DEVICE = "NVIDIA GTX 1080Ti, CUDA 10.0 (published, paper Table tab:speed)"
# Published peak rates of one H100 SXM5 80 GB (NVIDIA datasheet): FP32 (non-tensor) and HBM3
# bandwidth. A spec, not a measurement: the H100 floor below is counted work over these.
H100_PUBLISHED = {"device": "NVIDIA H100 SXM5 80 GB", "flops_per_s": 66.9e12, "bytes_per_s": 3.35e12}
PUBLISHED_GPU_RATES = {**H100_PUBLISHED, "source": "published"}  # the CUDA floors' rates without --gpu-rates
# Issue 5 targets: forward + backward of one step (12 views, 256^2).
CPU_TARGET = {"points": 20000, "step_ms": 250.0, "floor_factor": 4.0}
GPU_TARGET_STEP_MS = {20000: 10.0, 100000: 25.0}
QUICK_POINTS = {"deformation": 300, "filtering": 500, "denoising": 800}
QUICK = dict(views=2, image_size=32, warmup=1, measure=1, reference_measure=1,
             reference_max_points=500)


# ----------------------------------------------------------------------------------------------
# peak memory
class PeakMemory:
    """Peak memory a block of work adds, on the CPU (resident set) or a CUDA device.

    ``start()`` before, ``stop()`` after; ``stop`` returns (bytes, method).
    """

    def __init__(self, device: torch.device):
        self.device = device

    @staticmethod
    def _status_kb(field: str) -> int | None:
        try:
            m = re.search(rf"^{field}:\s+(\d+)\s+kB", Path("/proc/self/status").read_text(), re.M)
        except OSError:
            return None
        return int(m.group(1)) if m else None

    def start(self):
        gc.collect()
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats(self.device)
            self.base = torch.cuda.memory_allocated(self.device)
            self.method = "torch.cuda.max_memory_allocated - allocated at start"
            return
        try:  # give freed heap back to the OS so that reused pages count again
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except (OSError, AttributeError):
            pass
        self.base = None
        try:  # Linux >= 4.0: "5" resets VmHWM to the current resident set
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")
            rss = self._status_kb("VmRSS")
            if rss is not None and self._status_kb("VmHWM") is not None:
                self.base = rss * 1024
                self.method = "peak resident set (VmHWM after /proc/self/clear_refs reset) - resident set at start"
        except OSError:
            pass
        if self.base is None:
            # ru_maxrss is in kB on Linux
            self.base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
            self.method = "growth of getrusage(RUSAGE_SELF).ru_maxrss (lower bound)"

    def stop(self) -> tuple[int, str]:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            return max(0, torch.cuda.max_memory_allocated(self.device) - self.base), self.method
        if self.method.startswith("peak resident"):
            peak = self._status_kb("VmHWM") * 1024
        else:
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        return max(0, peak - self.base), self.method


# ----------------------------------------------------------------------------------------------
# timing
def _sync(device: torch.device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@dataclass
class StepScene:
    """What every timed step shares: the render settings (visibility window 4), the camera
    sampler (new views each step), the target cloud (moved by TARGET_NOISE) and sigma."""

    settings: RenderSettings
    sampler: SphereViewSampler
    target_points: torch.Tensor
    sigma: torch.Tensor


def step_scene(points: torch.Tensor, views: int, image_size: int, seed: int = 0) -> StepScene:
    """The scene of ``time_steps`` (and of the A/B tools that time or capture the same steps)
    for an (N, 3) cloud on its device; sigma is set once per run, as the optimiser does."""
    radius = float(points.norm(dim=1).max())
    sampler = SphereViewSampler((0.0, 0.0, 0.0), radius, views=views, image_size=image_size, fov_deg=FOV_DEG,
                                jitter=JITTER, seed=seed)
    gen = torch.Generator().manual_seed(seed + 1)
    noise = (TARGET_NOISE * torch.randn(points.shape, generator=gen)).to(points.device)
    return StepScene(RenderSettings(window=POSITION_WINDOW), sampler, points + noise, auto_sigma(points))


def time_steps(points: torch.Tensor, normals: torch.Tensor, backend: str, kind: str, views: int,
               image_size: int, warmup: int, measure: int, seed: int = 0, progress: bool = True) -> dict:
    """Run ``warmup + measure`` optimisation steps of one kind; median forward / backward times.

    Args:
        points, normals: (N, 3) float32 on the backend's device (cuda for ``"cuda"``).
        kind: ``"position"`` (grad w.r.t. positions, window 4) or ``"normal"`` (w.r.t. normals).
    Returns:
        dict with forward_ms, backward_ms (medians), the per-step lists, peak_memory_bytes and
        memory_method.
    """
    from tqdm.auto import tqdm

    dev = points.device
    sc = step_scene(points, views, image_size, seed)
    settings, sampler, target_points, sigma = sc.settings, sc.sampler, sc.target_points, sc.sigma
    p = points.detach().clone().requires_grad_(kind == "position")
    n = normals.detach().clone().requires_grad_(kind == "normal")
    param = p if kind == "position" else n
    opt = torch.optim.Adam([param], lr=1e-4 if kind == "position" else 1e-3)

    mem = PeakMemory(dev)
    mem.start()
    fwd, bwd = [], []
    bar = tqdm(range(warmup + measure), desc=f"{len(points)} pts {backend} {kind}", leave=False,
               disable=not progress, file=sys.stderr)
    with frozen_gc():  # as MultiViewOptimizer.run does (dss/gc_pause.py)
        for step in bar:
            cams = sampler.sample().to(dev)
            with torch.no_grad():
                target = render(target_points, normals, cams, settings, backend=backend, sigma=sigma).images
            opt.zero_grad(set_to_none=True)
            _sync(dev)
            t0 = time.perf_counter()
            img = render(p, n, cams, settings, backend=backend, sigma=sigma).images
            loss = smape_loss(img, target, channel_reduction="mean")
            _sync(dev)
            t1 = time.perf_counter()
            loss.backward()
            _sync(dev)
            t2 = time.perf_counter()
            if not torch.isfinite(loss):
                raise RuntimeError(f"{backend} {kind} step {step}: the loss is not finite")
            if param.grad is None:
                raise RuntimeError(f"{backend} {kind} step {step}: no gradient reached the {kind}s")
            with torch.no_grad():
                param.grad.nan_to_num_(0.0, 0.0, 0.0)
                opt.step()
                if kind == "normal":
                    n.copy_(torch.nn.functional.normalize(n, dim=1))
            if step >= warmup:
                fwd.append(1e3 * (t1 - t0))
                bwd.append(1e3 * (t2 - t1))
    peak, method = mem.stop()
    return {"forward_ms": statistics.median(fwd), "backward_ms": statistics.median(bwd),
            "forward_ms_runs": fwd, "backward_ms_runs": bwd, "warmup": warmup, "measured": measure,
            "peak_memory_bytes": int(peak), "memory_method": method}


def summarise(w: Workload, per_kind: dict) -> dict:
    """Step-weighted average forward / backward ms and the estimated total seconds."""
    steps = {k: w.steps(k) for k in KINDS}
    total_steps = sum(steps.values())
    fwd = sum(per_kind[k]["forward_ms"] * steps[k] for k in KINDS) / total_steps
    bwd = sum(per_kind[k]["backward_ms"] * steps[k] for k in KINDS) / total_steps
    total = sum((per_kind[k]["forward_ms"] + per_kind[k]["backward_ms"]) * steps[k] for k in KINDS) / 1e3
    peak = max(per_kind[k]["peak_memory_bytes"] for k in KINDS)
    return {"status": "measured", "forward_ms": fwd, "backward_ms": bwd, "total_s_estimated": total,
            "peak_memory_mb": peak / 2**20, "memory_method": per_kind["position"]["memory_method"],
            "per_kind": per_kind}


# ----------------------------------------------------------------------------------------------
# backends
def cuda_status() -> tuple[bool, str]:
    """(usable, label): label names the device, or says why CUDA is not measured."""
    if not torch.cuda.is_available():
        return False, NOT_MEASURED_NO_GPU
    from dss import _ext_cuda

    name = torch.cuda.get_device_name(0)
    if not _ext_cuda.cuda_available():
        return False, f"not measured: the CUDA kernels are not available on {name} ({_ext_cuda.build_error()})"
    return True, f"{name} (CUDA {torch.version.cuda})"


def run_workload(w: Workload, n_points: int, backends: list[str], args, cuda_ok: bool, cuda_label: str) -> dict:
    pts, nrm, src = benchmark_cloud(n_points)
    row = {"key": w.key, "application": w.application, "points": n_points, "paper_points": w.paper_points,
           "position_steps": w.position_steps, "normal_steps": w.normal_steps, "source": src,
           "paper_1080ti": {"forward_ms": w.paper_forward_ms, "backward_ms": w.paper_backward_ms,
                            "total_s": w.paper_total_s, "memory": w.paper_memory}}
    for b in BACKENDS:
        if b not in backends:
            row[b] = {"status": "not requested (--backends)"}
            continue
        if b == "cuda" and not cuda_ok:
            row[b] = {"status": cuda_label}
            continue
        if b == "reference" and n_points > args.reference_max_points:
            row[b] = {"status": f"skipped (above --reference-max-points {args.reference_max_points}; the pure-PyTorch "
                                "reference is for small sizes)"}
            continue
        dev = torch.device("cuda" if b == "cuda" else "cpu")
        measure = args.reference_measure if b == "reference" else args.measure
        per_kind = {}
        try:
            for kind in KINDS:
                per_kind[kind] = time_steps(pts.to(dev), nrm.to(dev), b, kind, args.views, args.image_size,
                                            args.warmup, measure, seed=args.seed, progress=not args.no_progress)
                log.info("%s, %d points, %s, %s steps: forward %.1f ms, backward %.1f ms (median of %d)", w.application,
                         n_points, b, kind, per_kind[kind]["forward_ms"], per_kind[kind]["backward_ms"], measure)
        except (RuntimeError, ValueError) as e:  # a backend that cannot run here is reported, not fatal
            log.warning("%s on %s failed: %s", w.application, b, e)
            row[b] = {"status": f"failed: {e}"}
            continue
        row[b] = summarise(w, per_kind)
        if b == "cuda":
            row[b]["device"] = cuda_label
    return row


# ----------------------------------------------------------------------------------------------
# output
def _cell(r: dict, field: str, fmt: str) -> str:
    return format(r[field], fmt) if r.get("status") == "measured" else "-"


def _status_or(r: dict, text: str) -> str:
    return text if r.get("status") == "measured" else r.get("status", "-")


def to_markdown(result: dict) -> str:
    s = result["settings"]
    m = result["machine"]
    cols = result["columns"]
    L = [f"# Runtime and memory (paper Table tab:speed), {s['image_size']}x{s['image_size']}, {s['views']} views per step",
         "", f"Command: `{result['command']}`"
         + (f" (measurements from `{result['measured_by']}`)" if result.get("measured_by") else ""), "",
         f"Machine: {m['cpu']}, {m['cores']} cores, {m['torch_threads']} torch threads, torch {m['torch']}; "
         f"1-min load average {m.get('load_average_1min_start')} at the start, {m.get('load_average_1min_end')} at the end. "
         f"Other processes used {m.get('other_processes_mean_cores', '?')} cores on average while it ran "
         "(other jobs on the machine make timings noisy). "
         f"CUDA column: {cols['cuda']}.", "",
         "Clouds: " + "; ".join(f"{w['points']} points: {w.get('source', '?')}" for w in result["workloads"])
         + ".", "",
         "Forward / backward: ms per step (median over the measured steps of each kind, averaged with the paper's "
         "step counts as weights). **Total (s) is estimated** from the measured per-step medians, "
         "sum over kinds of (forward + backward) x steps, not timed over a full run; the paper's totals are "
         "whole runs. Memory: MB the steps add (see below); the paper's memory is quoted as printed.", ""]
    hdr = ["application", "points", "steps pos / normal", "paper 1080Ti fwd / bwd (ms)", "paper total (s)", "paper memory"]
    names = {"cpp": "ours C++ (CPU)", "cuda": "ours CUDA", "reference": "PyTorch reference (CPU)"}
    for b in BACKENDS:
        hdr += [f"{names[b]} fwd / bwd (ms)", f"{names[b]} total est. (s)", f"{names[b]} peak mem (MB)"]
    L += ["| " + " | ".join(hdr) + " |", "|" + "---|" * len(hdr)]
    for r in result["workloads"]:
        pp = r["paper_1080ti"]
        cells = [r["application"], f"{r['points']}", f"{r['position_steps']} / {r['normal_steps']}",
                 f"{pp['forward_ms']} / {pp['backward_ms']}", f"{pp['total_s']}", pp["memory"]]
        for b in BACKENDS:
            x = r[b]
            if x.get("status") == "measured":
                cells += [f"{x['forward_ms']:.1f} / {x['backward_ms']:.1f}", f"{x['total_s_estimated']:.1f}",
                          f"{x['peak_memory_mb']:.0f}"]
            else:
                cells += [x.get("status", "-"), "-", "-"]
        L.append("| " + " | ".join(cells) + " |")
    L += ["", "Per kind of step (medians):", "",
          "| application | backend | kind | steps | forward (ms) | backward (ms) | (fwd + bwd) x steps (s) | measured steps | peak mem (MB) |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in result["workloads"]:
        for b in BACKENDS:
            x = r[b]
            if x.get("status") != "measured":
                continue
            for k in KINDS:
                pk = x["per_kind"][k]
                steps = r["position_steps"] if k == "position" else r["normal_steps"]
                L.append(f"| {r['application']} | {b} | {k} | {steps} | {pk['forward_ms']:.1f} | {pk['backward_ms']:.1f} | "
                         f"{(pk['forward_ms'] + pk['backward_ms']) * steps / 1e3:.1f} | {pk['measured']} | "
                         f"{pk['peak_memory_bytes'] / 2**20:.0f} |")
    if result.get("floor"):
        L += floor_markdown(result)
    L += ["", f"Steps: {s['warmup']} warm-up + {s['measure']} measured per kind "
              f"({s['reference_measure']} for the reference); position steps: gradient w.r.t. positions, "
              f"visibility window {s['position_window']}; normal steps: gradient w.r.t. normals. Each step: new "
              "SphereViewSampler cameras, target rendered from the cloud moved by "
              f"{TARGET_NOISE} x its bbox diagonal (not timed), render + SMAPE (forward), backward, Adam update (not timed).",
          f"Memory ({result['memory_method']}).",
          f"Paper columns: {PAPER_DEVICE}; the paper's memory column is printed as MB.", ""]
    return "\n".join(L)


# ----------------------------------------------------------------------------------------------
# floor and targets
def load_counts(path: str | None) -> dict | None:
    """The JSON of ``python -m experiments.benchmarks.perf_counts`` (work counts, CPU rates), or None."""
    if not path:
        return None
    p = Path(path)
    if not p.is_file():
        log.warning("%s not found: no floor comparison (run python -m experiments.benchmarks.perf_counts --out %s)", p, p)
        return None
    try:
        d = json.loads(p.read_text())
        _ = [(w["points"], w["flops"], w["bytes"], w["floor_ms"]) for w in d["workloads"]]
    except (ValueError, KeyError, TypeError) as e:
        raise SystemExit(f"{p}: not a perf_counts JSON ({e})") from e
    return d


def _published_h100_ms(work: dict) -> float:
    return perf_counts.floors(work, H100_PUBLISHED)["floor_ms"]


def _device_floors(work: dict, rates: dict) -> tuple[float, dict]:
    """Forward floor and per-kind step floors (ms) of a counted workload on a device's rates (a
    kind whose backward was not counted: the forward floor)."""
    fwd, steps = perf_counts.step_floors(work, rates)
    return fwd, {k: steps.get(k, fwd) for k in KINDS}


def check_rates_device(gpu_rates: dict | None, cuda_column: str):
    """Refuse GPU rates measured on another device than the one the CUDA column runs (ran) on."""
    if gpu_rates is not None and gpu_rates["device"] not in cuda_column:
        raise SystemExit(f"{gpu_rates['file']}: rates measured on {gpu_rates['device']!r}, but the CUDA column ran "
                         f"on another device ({cuda_column!r}); measure the rates on that GPU")


def load_gpu_rates(path: str | None) -> dict | None:
    """The rates of ``python -m experiments.benchmarks.perf_counts --gpu-rates OUT`` (a GPU's measured FP32
    matmul and copy rates), as ``{"device", "flops_per_s", "bytes_per_s", "source": "measured"}``,
    or None without a path. A missing or malformed file is an error naming it."""
    if not path:
        return None
    p = Path(path)
    if not p.is_file():
        raise SystemExit(f"{p}: no such file (write it on the GPU machine with python -m experiments.benchmarks.perf_counts "
                         f"--gpu-rates {p})")
    try:
        r = json.loads(p.read_text())["rates"]
        rates = {"device": str(r["device"]), "flops_per_s": float(r["flops_per_s"]),
                 "bytes_per_s": float(r["bytes_per_s"])}
    except (ValueError, KeyError, TypeError) as e:
        raise SystemExit(f"{p}: not a perf_counts --gpu-rates JSON (needs rates.device, rates.flops_per_s, "
                         f"rates.bytes_per_s): {e!r}") from e
    if not (rates["flops_per_s"] > 0 and rates["bytes_per_s"] > 0):
        raise SystemExit(f"{p}: rates must be positive, got {rates}")
    return {**rates, "source": "measured", "file": str(p)}


def floor_comparison(rows: list[dict], counts: dict, settings: dict, gpu_rates: dict | None = None,
                     threads: int | None = None) -> dict:
    """Measured step times against the counted floors, and the issue's targets.

    experiments/benchmarks/perf_counts.py counts the forward (projection, rasterisation, loss) and each
    kind's backward (blend backward and projection backward; for positions also the visibility
    gradient's evaluations). The forward is compared with the forward floor, forward + backward
    with the step floor of its kind (forward + that backward). Counts from before the backward
    was counted (no ``step_floor_ms``) fall back to the forward floor and say so. The CUDA
    column's floors use ``gpu_rates`` (measured, :func:`load_gpu_rates`) where given, else the
    H100's published spec; the published H100 floors are kept beside them either way.
    ``threads``: the torch threads the CPU column ran with (default: this process's).
    """
    threads = torch.get_num_threads() if threads is None else threads
    gpu = gpu_rates or PUBLISHED_GPU_RATES
    by_n = {(w["points"], w["views"], w["image_size"]): w for w in counts["workloads"]}
    out = {"counts_machine": counts.get("machine"), "cpu_rates": counts.get("rates"), "h100_published": H100_PUBLISHED,
           "gpu_rates": gpu,
           "note": "floor = max(flops / rate, bytes / bandwidth) of the counted work: forward for the forward pass, "
                   "forward + that kind's backward for a step; CPU rates measured by experiments.benchmarks.perf_counts, "
                   + (f"GPU rates measured on {gpu['device']} (perf_counts --gpu-rates)" if gpu["source"] == "measured"
                      else "H100 rates published (not measured)"),
           "workloads": [], "targets": []}
    for r in rows:
        w = by_n.get((r["points"], settings["views"], settings["image_size"]))
        if w is None:
            continue
        backward = w.get("backward") or {}
        step_floor = {k: (w.get("step_floor_ms") or {}).get(k, w["floor_ms"]) for k in KINDS}

        h100_fwd, h100_step = _device_floors(w, H100_PUBLISHED)
        gpu_fwd, gpu_step = _device_floors(w, gpu)
        f = {"key": r["key"], "points": r["points"], "cpu_floor_ms": w["floor_ms"], "cpu_step_floor_ms": step_floor,
             "step_floor_counts_backward": all(k in backward for k in KINDS),
             "h100_published_floor_ms": h100_fwd, "h100_published_step_floor_ms": h100_step,
             "gpu_floor_ms": gpu_fwd, "gpu_step_floor_ms": gpu_step,
             "flops": w["flops"], "bytes": w["bytes"], "measured": {}}
        for b in BACKENDS:
            x = r[b]
            if x.get("status") != "measured":
                continue
            per = {}
            for k in KINDS:
                fwd_floor = gpu_fwd if b == "cuda" else w["floor_ms"]
                st_floor = gpu_step[k] if b == "cuda" else step_floor[k]
                fwd = x["per_kind"][k]["forward_ms"]
                step = fwd + x["per_kind"][k]["backward_ms"]
                per[k] = {"forward_ms": fwd, "step_ms": step, "ratio_forward_to_floor": fwd / fwd_floor,
                          "ratio_step_to_floor": step / st_floor}
            f["measured"][b] = per
        out["workloads"].append(f)
        cpp = f["measured"].get("cpp")
        if r["points"] == CPU_TARGET["points"] and cpp:
            for k in KINDS:
                st, fl = cpp[k]["step_ms"], step_floor[k]
                out["targets"].append({
                    "target": f"2 CPU cores, {r['points']} points, {k} step: fwd+bwd <= {CPU_TARGET['step_ms']:.0f} ms "
                              f"and <= {CPU_TARGET['floor_factor']:.0f}x floor (measured with {threads} torch threads)",
                    "measured_ms": st, "floor_ms": fl, "ratio_to_floor": st / fl,
                    "torch_threads": threads,
                    "met": bool(st <= CPU_TARGET["step_ms"] and st <= CPU_TARGET["floor_factor"] * fl)})
        if r["points"] in GPU_TARGET_STEP_MS:
            cu = f["measured"].get("cuda")
            h100 = max(gpu_step.values())
            tgt = {"target": f"one H100, {r['points']} points: fwd+bwd <= {GPU_TARGET_STEP_MS[r['points']]:.0f} ms",
                   "floor_ms": h100, "floor_rates": gpu["source"]}
            if cu is None:
                tgt.update(measured_ms=None, met=None, status=r["cuda"].get("status", "not measured"))
            else:
                st = max(cu[k]["step_ms"] for k in KINDS)
                on_h100 = "H100" in r["cuda"].get("device", "")
                tgt.update(measured_ms=st, ratio_to_floor=st / h100, device=r["cuda"].get("device"),
                           met=bool(st <= GPU_TARGET_STEP_MS[r["points"]]) if on_h100 else None,
                           status="measured" if on_h100 else "measured on another GPU: not the target device")
            out["targets"].append(tgt)
    return out


def _ratio(x: float) -> str:
    return f"{x:.0f}x" if x >= 10 else f"{x:.1f}x"


def floor_markdown(result: dict) -> list[str]:
    fl = result["floor"]
    rates = fl.get("cpu_rates") or {}
    cm = fl.get("counts_machine") or {}
    gpu = fl.get("gpu_rates") or PUBLISHED_GPU_RATES  # (tables from before --gpu-rates)
    spec = f"({gpu['flops_per_s'] / 1e12:.1f} TFLOP/s FP32, {gpu['bytes_per_s'] / 1e12:.2f} TB/s)"
    if gpu["source"] == "measured":
        gpu_sentence = (f"GPU floors from rates measured on the {gpu['device']} {spec}, float32 matmul and device copy "
                        "(python -m experiments.benchmarks.perf_counts --gpu-rates).")
        gpu_col = "GPU floor step, measured rates (ms)"
    else:
        gpu_sentence = f"H100 floors from the published spec of the {gpu['device']} {spec}, not measured."
        gpu_col = "H100 floor step, published spec (ms)"
    L = ["", "Against the counted floors (python -m experiments.benchmarks.perf_counts): the forward against the forward's "
             "work (projection, rasterisation, loss), a step against the forward plus that kind's backward (blend and "
             "projection backward; for positions also the visibility gradient's evaluations). CPU floors from rates "
             f"measured there ({rates.get('flops_per_s', float('nan')) / 1e9:.1f} GFLOP/s float32 matmul, "
             f"{rates.get('bytes_per_s', float('nan')) / 1e9:.1f} GB/s copy; {cm.get('torch_threads')} torch threads). "
             + gpu_sentence, "",
         f"| application | points | backend | kind | CPU floor fwd / step (ms) | {gpu_col} | fwd (ms) | fwd+bwd (ms) | fwd / floor | fwd+bwd / step floor |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    if not all(f.get("step_floor_counts_backward", False) for f in fl["workloads"]):
        L.insert(2, "(These counts predate the backward count: the step floor is the forward floor.)")
    apps = {r["key"]: r["application"] for r in result["workloads"]}
    for f in fl["workloads"]:
        for b, per in f["measured"].items():
            for k in KINDS:
                m = per[k]
                L.append(f"| {apps[f['key']]} | {f['points']} | {b} | {k} | {f['cpu_floor_ms']:.2f} / "
                         f"{f['cpu_step_floor_ms'][k]:.2f} | "
                         f"{f.get('gpu_step_floor_ms', f['h100_published_step_floor_ms'])[k]:.4f} | "
                         f"{m['forward_ms']:.1f} | {m['step_ms']:.1f} | {_ratio(m['ratio_forward_to_floor'])} | "
                         f"{_ratio(m['ratio_step_to_floor'])} |")
    if fl["targets"]:
        L += ["", "Targets (issue 5):", "", "| target | measured fwd+bwd (ms) | floor (ms) | measured / floor | met |",
              "|---|---|---|---|---|"]
        for t in fl["targets"]:
            meas = f"{t['measured_ms']:.1f}" if t.get("measured_ms") is not None else t.get("status", "not measured")
            ratio = _ratio(t["ratio_to_floor"]) if t.get("ratio_to_floor") is not None else "-"
            met = {True: "yes", False: "no"}.get(t["met"], t.get("status", "not measured"))
            L.append(f"| {t['target']} | {meas} | {t['floor_ms']:.4g} | {ratio} | {met} |")
    return L


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workloads", nargs="+", choices=[w.key for w in WORKLOADS], default=[w.key for w in WORKLOADS])
    ap.add_argument("--points", type=int, nargs="+", default=None,
                    help="override the points per workload (one per chosen workload; default the paper's)")
    ap.add_argument("--backends", nargs="+", choices=BACKENDS, default=list(BACKENDS))
    ap.add_argument("--views", type=int, default=None, help="views per step (default 12)")
    ap.add_argument("--image-size", type=int, default=None, help="image side in pixels (default 256)")
    ap.add_argument("--warmup", type=int, default=None, help="untimed steps per kind (default 1)")
    ap.add_argument("--measure", type=int, default=None, help="measured steps per kind (default 5)")
    ap.add_argument("--reference-measure", type=int, default=None, help="measured steps per kind, reference (default 3)")
    ap.add_argument("--reference-max-points", type=int, default=None,
                    help="run the pure-PyTorch reference only up to this many points (default 20000)")
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: leave as is)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="tiny sizes and steps (for tests); explicit options win")
    outputs.add_arguments(ap, published="results/bench/runtime_table",
                          what="output prefix: writes <out>.json and <out>.md")
    ap.add_argument("--counts", default="results/bench/perf_counts.json",
                    help="perf_counts JSON for the floor comparison (python -m experiments.benchmarks.perf_counts); '' to skip")
    ap.add_argument("--gpu-rates", default=None, metavar="JSON",
                    help="a GPU's measured rates (python -m experiments.benchmarks.perf_counts --gpu-rates JSON, on that GPU): "
                         "the CUDA column's floors use them instead of the H100's published spec")
    ap.add_argument("--from-json", default=None, metavar="JSON",
                    help="measure nothing: read the workloads of an earlier run's JSON and redo its floor comparison "
                         "(with --counts and --gpu-rates) and markdown into --out")
    ap.add_argument("--no-progress", action="store_true", help="no tqdm bars")
    args = ap.parse_args(argv)
    defaults = dict(views=12, image_size=256, warmup=1, measure=5, reference_measure=3,
                    reference_max_points=20000)
    if args.quick:
        defaults.update(QUICK)
    for k, v in defaults.items():
        if getattr(args, k) is None:
            setattr(args, k, v)
    chosen = [w for w in WORKLOADS if w.key in args.workloads]
    if args.points is None:
        args.points = [QUICK_POINTS[w.key] if args.quick else w.points for w in chosen]
    if len(args.points) != len(chosen):
        ap.error(f"--points needs one value per workload ({len(chosen)}: {' '.join(w.key for w in chosen)})")
    for name in ("views", "image_size", "measure", "reference_measure"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1")
    if args.warmup < 0:
        ap.error("--warmup must be >= 0")
    if args.publish and "cpp" not in args.backends:
        ap.error("--publish writes the CPU table (results/bench/runtime_table); give a run without the cpp "
                 "backend an --out (the published GPU runs are in results/bench/gpu/<gpu>/)")
    args.chosen = chosen
    return args


def _cpu_seconds() -> tuple[float, float] | None:
    """(busy CPU seconds of the whole machine, of this process) since boot / start (Linux)."""
    try:
        ticks = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        hz = os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError):
        return None
    busy = (sum(ticks[:8]) - ticks[3] - ticks[4]) / hz  # all but idle and iowait; guest is inside user
    me = resource.getrusage(resource.RUSAGE_SELF)
    return busy, me.ru_utime + me.ru_stime


def _loadavg() -> float | None:
    """1-minute load average: other jobs on the machine make the timings noisy."""
    try:
        return round(os.getloadavg()[0], 2)
    except (OSError, AttributeError):
        return None


def _contention(cpu_start, wall_s: float) -> dict:
    """CPU time other processes used while the table ran: they share the cores being timed."""
    cpu_end = _cpu_seconds()
    if cpu_start is None or cpu_end is None:
        return {"wall_s": wall_s}
    mine = cpu_end[1] - cpu_start[1]
    others = max(0.0, (cpu_end[0] - cpu_start[0]) - mine)
    return {"wall_s": round(wall_s, 1), "cpu_s_this_process": round(mine, 1), "cpu_s_other_processes": round(others, 1),
            "other_processes_mean_cores": round(others / max(wall_s, 1e-9), 2)}


def _write(result: dict, out: Path):
    atomic_write_json(out.with_name(out.name + ".json"), result)
    atomic_write_text(out.with_name(out.name + ".md"), to_markdown(result))
    log.info("wrote %s.json and %s.md", out, out)


def refloor(args) -> dict:
    """--from-json: an earlier run's measurements with the floors of --counts and --gpu-rates."""
    src = Path(args.from_json)
    try:
        result = json.loads(src.read_text())
        rows, settings = result["workloads"], result["settings"]
        _ = [(r["points"], r["key"], r["cuda"], r["cpp"]) for r in rows], settings["views"], settings["image_size"]
    except FileNotFoundError:
        raise SystemExit(f"{src}: no such file") from None
    except (ValueError, KeyError, TypeError) as e:
        raise SystemExit(f"{src}: not a dss-runtime-table JSON ({e!r})") from e
    counts = load_counts(args.counts)
    if counts is None:
        raise SystemExit(f"--from-json redoes the floor comparison and needs --counts (got {args.counts!r})")
    result["measured_by"] = result.get("measured_by", result.get("command"))
    result["command"] = "dss-runtime-table " + " ".join(args.argv)
    gpu_rates = load_gpu_rates(args.gpu_rates)
    if any(r["cuda"].get("status") == "measured" for r in rows):
        check_rates_device(gpu_rates, str(result.get("columns", {}).get("cuda", "")))
    result["floor"] = floor_comparison(rows, counts, settings, gpu_rates,
                                       threads=result.get("machine", {}).get("torch_threads"))
    _write(result, outputs.folder(args, "dss-runtime-table", name="runtime_table"))
    return result


def run(argv=None) -> dict:
    args = parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    if args.from_json:
        return refloor(args)
    gpu_rates = load_gpu_rates(args.gpu_rates)  # a bad file fails before the measurements, not after
    if args.threads:
        torch.set_num_threads(args.threads)
    from dss import _ext

    if "cpp" in args.backends and not _ext.cpu_available():
        raise SystemExit(f"the C++ backend is not available: {_ext.build_error()}")
    cuda_ok, cuda_label = cuda_status()
    if cuda_ok and "cuda" in args.backends:  # before the measurements, not after
        check_rates_device(gpu_rates, cuda_label)
    load_start, cpu_start, t_start = _loadavg(), _cpu_seconds(), time.perf_counter()
    rows = []
    for w, n in zip(args.chosen, args.points):
        log.info("%s: %d points", w.application, n)
        rows.append(run_workload(w, n, args.backends, args, cuda_ok, cuda_label))
    methods = {x["memory_method"] for r in rows for b in BACKENDS if (x := r[b]).get("status") == "measured"}
    result = {
        "command": "dss-runtime-table " + " ".join(args.argv),
        "machine": {**machine_info(), "load_average_1min_start": load_start, "load_average_1min_end": _loadavg(),
                    **_contention(cpu_start, time.perf_counter() - t_start)},
        "settings": {"views": args.views, "image_size": args.image_size, "warmup": args.warmup, "measure": args.measure,
                     "reference_measure": args.reference_measure, "reference_max_points": args.reference_max_points,
                     "position_window": POSITION_WINDOW, "fov_deg": FOV_DEG, "jitter": JITTER,
                     "target_noise": TARGET_NOISE, "loss": "smape (channel mean)", "quick": args.quick},
        "columns": {"cpp": "ours, C++ kernel on the CPU", "cuda": cuda_label if not cuda_ok else f"ours, CUDA kernel on {cuda_label}",
                    "reference": "pure-PyTorch reference renderer on the CPU", "paper_1080ti": PAPER_DEVICE},
        "total_note": "total_s_estimated = sum over kinds of (median forward + median backward) x steps of that kind; "
                      "estimated from the measured per-step medians, not a full run",
        "memory_method": "; ".join(sorted(methods)) or "-",
        "workloads": rows,
    }
    counts = load_counts(args.counts)
    if counts is not None:
        result["floor"] = floor_comparison(rows, counts, result["settings"], gpu_rates)
    _write(result, outputs.folder(args, "dss-runtime-table", name="runtime_table"))
    return result


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    result = run(argv)
    print(to_markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
