"""The Python-side costs of a render step, each against its earlier version, in one process.

    python -m experiments.ab_step_overheads [--kinds normal position] [--rounds 25] [--out F]

Whole-step A/B runs (``experiments.ab_steps``) compare child processes, whose step times differ
by up to 10% from one process to the next: more than the few tenths of a millisecond that each
change outside the kernels saves. Here the variants take turns step by step in one process, on
the same cameras and targets (the 20K-point kangaroo cloud, 12 views at 256x256, visibility
window 4 for position steps, as ``dss-runtime-table``), and each earlier version is put back in
place for its own steps only:

- ``copy``: ``_KernelBlend`` returns a copy of the rendered images (session 29: a pooled copy
  of 9 MB per step; here ``images.clone()``) instead of a view;
- ``fancy_index``: ``_PermuteRows`` by ``x[order]`` and ``out[order] = grad`` instead of
  ``index_select`` / ``index_copy_``;
- ``isfinite``: ``render``'s input check by ``torch.isfinite(t).all()`` instead of
  :func:`dss.pointcloud.all_finite`;
- ``lights``: the sun lights' directions computed for every ``SunLights()`` (every render)
  instead of once.

The median forward (render + SMAPE) and backward time of each variant over ``--rounds`` rounds
(after 2 warm-up rounds; :func:`alternate_steps`, which ``experiments.ab_steps --in-process``
uses too) is printed and written to ``--out`` (JSON) with the differences to
``current``.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import torch

from experiments.bench_common import main_for, write_result
from experiments.figures import command_line


def _variants():
    """name -> a function that puts that earlier version in place (and returns its undo)."""
    import dss.render as R
    from dss import shading

    def patch(obj, name, value):
        old = getattr(obj, name)
        setattr(obj, name, value)
        return lambda: setattr(obj, name, old)

    def copy():
        fwd = R._KernelBlend.forward

        def forward(ctx, packed, attrs, points, images, mask, frags_t, cam_t, background, opts):
            fwd(ctx, packed, attrs, points, images, mask, frags_t, cam_t, background, opts)
            return images.clone()

        return patch(R._KernelBlend, "forward", staticmethod(forward))

    def fancy_index():
        def forward(ctx, x, order):
            ctx.save_for_backward(order)
            return x[order]

        def backward(ctx, grad):
            (order,) = ctx.saved_tensors
            out = torch.empty_like(grad)
            out[order] = grad
            return out, None

        undo = [patch(R._PermuteRows, "forward", staticmethod(forward)),
                patch(R._PermuteRows, "backward", staticmethod(backward))]
        return lambda: [u() for u in undo]

    def isfinite():
        return patch(R, "all_finite", lambda *ts: all(bool(torch.isfinite(t).all()) for t in ts))

    def lights():
        uncached = shading._three_orthogonal_dirs_once.__wrapped__

        @dataclasses.dataclass
        class SunLightsUncached(shading.SunLights):
            directions: torch.Tensor = dataclasses.field(default_factory=uncached)

        return patch(R, "SunLights", SunLightsUncached)

    return {"current": lambda: (lambda: None), "copy": copy, "fancy_index": fancy_index, "isfinite": isfinite,
            "lights": lights}


def alternate_steps(kind: str, variants: dict, rounds: int, n_points: int = 20000, views: int = 12,
                    size: int = 256, warmup: int = 2) -> dict:
    """Median forward / backward / step ms of each variant, the variants taking turns step by step.

    ``variants`` maps a name to ``put()``, which puts that variant in place and returns the
    function that undoes it. Each round runs one step per variant on the same cameras, target and
    parameters (4 scenes in turn, no parameter update), in the variants' order on even rounds and
    the reverse order on odd ones; the first ``warmup`` rounds are left out. Each variant's entry
    keeps its ``runs_ms`` ((forward, backward) per measured step).
    """
    from dss.losses import smape_loss
    from dss.render import render
    from experiments.bench_render import benchmark_cloud
    from experiments.runtime_table import step_scene

    pts, nrm, _ = benchmark_cloud(n_points)
    sc = step_scene(pts, views, size)
    settings, sampler, target_pts, sigma = sc.settings, sc.sampler, sc.target_points, sc.sigma
    p = pts.clone().requires_grad_(kind == "position")
    n = nrm.clone().requires_grad_(kind == "normal")
    scenes = []
    for _ in range(4):
        cams = sampler.sample()
        with torch.no_grad():
            scenes.append((cams, render(target_pts, nrm, cams, settings, backend="cpp", sigma=sigma).images))
    runs = {name: [] for name in variants}
    names = list(variants)
    for r in range(rounds + warmup):
        for name in names if r % 2 == 0 else names[::-1]:
            undo = variants[name]()
            try:
                cams, target = scenes[r % len(scenes)]
                t0 = time.perf_counter()
                img = render(p, n, cams, settings, backend="cpp", sigma=sigma).images
                loss = smape_loss(img, target, channel_reduction="mean")
                t1 = time.perf_counter()
                loss.backward()
                t2 = time.perf_counter()
            finally:
                undo()
            p.grad = n.grad = None
            del img, loss
            if r >= warmup:
                runs[name].append((1e3 * (t1 - t0), 1e3 * (t2 - t1)))
    return {name: {"forward_ms": statistics.median(f for f, _ in rs), "backward_ms": statistics.median(b for _, b in rs),
                   "step_ms": statistics.median(f + b for f, b in rs), "runs_ms": rs} for name, rs in runs.items()}


def measure(kind: str, rounds: int, n_points: int = 20000, views: int = 12, size: int = 256) -> dict:
    """Median forward / backward ms of each variant, the variants alternating step by step."""
    out = alternate_steps(kind, _variants(), rounds, n_points, views, size)
    for name in out:
        out[name]["saved_ms_by_current"] = out[name]["step_ms"] - out["current"]["step_ms"]
    return out


def run(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kinds", nargs="+", default=["normal", "position"], choices=["normal", "position"])
    ap.add_argument("--rounds", type=int, default=25)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    result = {"command": command_line("python -m experiments.ab_step_overheads", argv), "threads": args.threads,
              "rounds": args.rounds, "kinds": {}}
    for kind in args.kinds:
        r = result["kinds"][kind] = measure(kind, args.rounds)
        for name, v in r.items():
            print(f"{kind:8s} {name:12s} forward {v['forward_ms']:6.2f} backward {v['backward_ms']:6.2f} "
                  f"step {v['step_ms']:6.2f} ms (the earlier version costs {v['saved_ms_by_current']:+.2f} ms)")
    return write_result(result, args.out)


main = main_for(run)

if __name__ == "__main__":
    raise SystemExit(main())
