"""Noise-level estimators on real meshes: ``estimate_noise_level`` with ``method="quadric"``
(the default) vs ``method="multiscale"``, ratio estimate / true noise per case.

    python -m experiments.evaluation.noise_estimate_study --out outputs/noise_study            # tuning, 20K, seeds 0 1
    python -m experiments.evaluation.noise_estimate_study --groups held_out --seeds 0 --out outputs/noise_study_held
    python -m experiments.evaluation.noise_estimate_study --generated --seeds 0 --out outputs/noise_study_gen

Cases are made as ``dss-real-bench`` makes them (Poisson-disk samples of each mesh of
``--groups`` from ``data_prep/real_split.yaml`` with the case seed, Gaussian noise of std level x
bbox diagonal per axis with the benchmark's noise seed); ``--generated`` instead uses one shape
per smooth ``data_prep.shapes`` family (index 100 of data seed 0) and the shipped example's clean
cloud. Level 0 (the clean cloud) is included. Writes ``report.json`` and ``report.md`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

LEVELS = (0.0, 0.0025, 0.005, 0.01, 0.015)
GENERATED = ("superquadric", "torus", "displaced_sphere", "revolution", "figure", "teapot")
METHODS = ("quadric", "multiscale")


def clouds(args):
    """Yield (name, case seed, clean points (N, 3) float32, noise-seed function of the level)."""
    import torch

    from data_prep.sampling import poisson_disk
    from data_prep.shards import noise_seed, shape_seed
    from experiments.evaluation.table.cases import _level_index

    torch.set_num_threads(1)  # open3d's sample elimination is then reproducible
    if args.generated:
        from data_prep.shapes import make_shape
        from dss.pointcloud import load_ply

        for fam in GENERATED:
            s = shape_seed(0, fam, 100)
            mesh = make_shape(fam, s, 96)
            for seed in args.seeds:
                yield fam, seed, poisson_disk(mesh, args.points, s + seed).points, lambda lv, s=s: noise_seed(s, 1000 + int(lv * 1e6))
        if args.points == 20000:
            pts = load_ply(Path(__file__).resolve().parents[1] / "assets" / "example" / "clean.ply",
                           compute_normals=False).points.numpy()
            yield "example", 0, pts, lambda lv: 7 + int(lv * 1e6)
        return
    from data_prep.real_meshes import real_cases
    from data_prep.shapes.meshing import Mesh
    from dss.metrics import load_mesh

    cases, skipped = real_cases(args.groups, "data/real")
    for sk in skipped:
        print("skipped", sk)
    for c in cases:
        if args.shapes and c["name"] not in args.shapes:
            continue
        v, f = load_mesh(c["mesh"])
        mesh = Mesh(np.asarray(v, np.float64), np.asarray(f, np.int64))
        for seed in args.seeds:  # as make_case_arrays: the case seed samples, the level picks the noise seed
            yield c["name"], seed, poisson_disk(mesh, args.points, seed).points, \
                lambda lv, seed=seed: noise_seed(seed, _level_index(lv, [0.003, 0.01]))


def summarize(rows):
    out = {}
    for m in METHODS:
        for lv in sorted({r["level"] for r in rows}):
            vals = [r[m] for r in rows if r["level"] == lv]
            if lv == 0:
                out[f"{m}|{lv}"] = {"max_clean": max(vals)}
                continue
            lr = np.log(np.array(vals) / lv)
            out[f"{m}|{lv}"] = {"mean_abs_log": float(np.abs(lr).mean()), "min": float(np.exp(lr.min())),
                                "max": float(np.exp(lr.max())), "worst": float(np.exp(lr[np.abs(lr).argmax()]))}
    return out


def render(rows, summ, args) -> str:
    levels = sorted({r["level"] for r in rows})
    lines = [f"# Noise estimate / true noise ({'generated' if args.generated else ', '.join(args.groups)}, "
             f"{args.points} points, seeds {args.seeds})", "",
             "Per case: quadric (default) / multiscale. Level 0: the estimate itself (% of the diagonal).", "",
             "| case | " + " | ".join(f"{lv * 100:g}%" for lv in levels) + " |", "|---" * (len(levels) + 1) + "|"]
    for key in dict.fromkeys((r["name"], r["seed"]) for r in rows):
        cells = []
        for lv in levels:
            r = next(r for r in rows if (r["name"], r["seed"]) == key and r["level"] == lv)
            cells.append(f"{r['quadric'] * 100:.3f} / {r['multiscale'] * 100:.3f}" if lv == 0
                         else f"{r['quadric'] / lv:.2f} / {r['multiscale'] / lv:.2f}")
        lines.append(f"| {key[0]} s{key[1]} | " + " | ".join(cells) + " |")
    lines += ["", "| method | " + " | ".join(f"{lv * 100:g}%" for lv in levels) + " |", "|---" * (len(levels) + 1) + "|"]
    for m in METHODS:
        cells = []
        for lv in levels:
            e = summ[f"{m}|{lv}"]
            cells.append(f"max {e['max_clean'] * 100:.3f}%" if lv == 0 else
                         f"mean abs log {e['mean_abs_log']:.3f}, range {e['min']:.2f}-{e['max']:.2f}")
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--groups", nargs="+", default=["tuning"])
    ap.add_argument("--shapes", nargs="*", default=None, help="only these meshes of the groups")
    ap.add_argument("--generated", action="store_true", help="generated smooth shapes + the example cloud")
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--levels", type=float, nargs="+", default=list(LEVELS))
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)

    from data_prep.sampling import noisy_copy
    from dss.pipeline import estimate_noise_level

    rows = []
    for name, seed, clean, nseed in clouds(args):
        for lv in args.levels:
            x = clean if lv == 0 else noisy_copy(clean, lv, nseed(lv))
            rows.append({"name": name, "seed": seed, "level": lv, "points": len(x),
                         **{m: estimate_noise_level(x, method=m) for m in METHODS}})
        print(name, seed, " ".join(f"{r['quadric']:.4f}/{r['multiscale']:.4f}" for r in rows[-len(args.levels):]),
              flush=True)
    summ = summarize(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "report.json").write_text(json.dumps({"args": {k: (str(v) if isinstance(v, Path) else v)
                                                                for k, v in vars(args).items()},
                                                       "rows": rows, "summary": summ}, indent=1))
    md = render(rows, summ, args)
    (args.out / "report.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
