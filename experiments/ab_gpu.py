"""A/B of the CUDA render step: the ``dss`` first on ``PYTHONPATH`` (one tree), same scenes.

    python -m experiments.ab_gpu --points 20000 100000 --repeats 20 --label work
    PYTHONPATH=/path/to/other/tree:$PWD python experiments/ab_gpu.py --label base   # another revision's dss

Times :func:`experiments.bench_gpu.bench_render_step` (forward with grad, L1, backward; positions
and normals both require grad) on the kangaroo clouds of ``dss-bench`` and prints one JSON line
per size, naming the ``dss`` it imported, so that runs of two revisions alternated in one session
on one GPU give a fair ratio (experiments/gpu_check.sh's ``ab`` stage does that). Then

    python -m experiments.ab_gpu --summarize ab.txt --base-label .devcarry/base --out ab.json

reads those lines back: per size and tree the median step over the rounds, and base / work.
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import sys
from pathlib import Path

import torch


def summarize(lines: list[str], base_label: str, source: str) -> dict:
    """Medians per (label, points) of the JSON lines :func:`main` printed; the base / work ratio."""
    rows = [json.loads(ln) for ln in lines if ln.startswith("{")]
    if not rows:
        raise SystemExit(f"{source}: no result lines")
    labels = sorted({r["label"] for r in rows})
    if base_label not in labels or len(labels) != 2:
        raise SystemExit(f"{source}: expected two trees, one labelled {base_label!r}; found {labels}")
    work_label = next(x for x in labels if x != base_label)
    out = []
    for n in sorted({r["points"] for r in rows}):
        per = {}
        for lab, key in ((base_label, "base"), (work_label, "work")):
            rs = [r for r in rows if r["label"] == lab and r["points"] == n]
            per[key] = {"step_ms_runs": [r["step_ms"] for r in rs],
                        "step_ms": statistics.median(r["step_ms"] for r in rs),
                        "forward_with_grad_ms": statistics.median(r["forward_with_grad_ms"] for r in rs),
                        "backward_ms": statistics.median(r["backward_ms"] for r in rs),
                        "peak_memory_mb": max(r["peak_memory_mb"] for r in rs), "dss": rs[0]["dss"]}
        out.append({"points": n, **per, "speedup": per["base"]["step_ms"] / per["work"]["step_ms"]})
    return {"device": rows[0]["device"], "source": rows[0]["source"].split(" (read from")[0],
            "rounds": len(out[0]["base"]["step_ms_runs"]), "base_label": base_label, "work_label": work_label,
            "results": out}


def main(argv=None) -> list[dict]:
    from experiments.bench_gpu import _cameras, _cloud, add_scene_args, bench_render_step

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_args(ap, repeats=20)
    ap.add_argument("--label", default="work", help="name of this tree in the output")
    ap.add_argument("--summarize", default=None, help="read the JSON lines of earlier runs from this file instead")
    ap.add_argument("--base-label", default=None, help="with --summarize: the label of the base tree")
    ap.add_argument("--note", default=None, help="with --summarize: what the two trees are (kept in the JSON)")
    ap.add_argument("--out", default=None, help="with --summarize: write the summary JSON here (atomically)")
    args = ap.parse_args(argv)
    if args.summarize:
        from experiments.bench_common import write_result

        res = summarize(Path(args.summarize).read_text().splitlines(), args.base_label, args.summarize)
        res["note"] = args.note
        res["command"] = "python -m experiments.ab_gpu " + shlex.join(argv if argv is not None else sys.argv[1:])
        write_result(res, args.out)
        print(json.dumps(res, indent=2))
        return res["results"]
    import dss
    from dss.render import RenderSettings
    from dss.splats import auto_sigma

    if not torch.cuda.is_available():
        raise SystemExit(f"no CUDA device: this benchmark needs a GPU (dss from {dss.__file__})")
    dev = torch.device("cuda")
    rows = []
    for n in args.points:
        pts, nrm, src = _cloud(n)
        cams = _cameras(pts, args.views, args.image_size)
        sigma = auto_sigma(pts)
        r = bench_render_step(pts.to(dev), nrm.to(dev), cams.to(dev), sigma.to(dev), RenderSettings(), args.warmup,
                              args.repeats)
        row = {"label": args.label, "dss": dss.__file__, "points": n, "source": src,
               "device": torch.cuda.get_device_name(dev),
               **{k: r[k] for k in ("step_ms", "forward_with_grad_ms", "backward_ms", "peak_memory_mb")}}
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


if __name__ == "__main__":
    main()
