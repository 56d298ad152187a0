"""Training inputs for a cascade reference: noisy clouds after dss-denoise's classical stage.

With ``fusion.reference_cloud=refined`` (:mod:`dss.fusion`, :func:`dss.pipeline.refine_with_reference`)
the plane fusion's references are made from renders of the cloud the DSS cycles and the outlier
projection left (the regularisers' projection of the noisy input), not of the noisy input. A
model for that job must be trained on such renders. This module runs the job's own classical
stage on training clouds and stores the result (a ``dss-cascade/1`` cache), which
``dss-train data=onthefly +data.cascade=<cache>`` renders as the network's input against the
clean cloud's renders:

    python -m experiments.denoising.cascade --data data/real-planes --out data/real-planes-cascade \\
        --per-family 4 --val-per-family 1 --draws 1

For every chosen shape of the ``dss-clouds/1`` dataset and draw: Gaussian noise of a std drawn
log-uniformly from the dataset's ``noise_range`` (or ``--noise``), PCA normals signed by the
mesh (as dss-prep), the noise level estimated as dss-denoise does (``dss_noise: estimate`` of
the real benchmark), then dss-denoise's optimiser settings for that level (``conf/denoise.yaml``
resolved by the app's own functions, the planes channel, identity references, no fusion) and
:func:`experiments.denoising.refine.refine`; the refined points get
:func:`dss.fusion.cascade_normals`, the normals the job renders them with. Not reproduced: the
outlier removal before the job (a few tail points of 20K at these levels).

Layout: ``<out>/manifest.json`` (format, source dataset and its fingerprint, settings, one entry
per item: ``shape_id``, ``split``, ``draw``, ``noise_std``, ``noise_seed``, ``estimated_noise``,
``file``, ``sha256``, ``cpu_s``) and ``<out>/<split>/<shape_id>-d<draw>.npz`` with ``points``
(N, 3) float32 and ``normals`` (N, 3) float32 in the clean cloud's frame. Items are written
atomically and skipped when a rerun finds them (resumable); the manifest is rewritten after each.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from data_prep.cascade_cache import CASCADE_FORMAT, read_cascade_manifest
from data_prep.sampling import log_uniform

log = logging.getLogger(__name__)

__all__ = ["classical_stage", "build_cache"]

ROOT = Path(__file__).resolve().parents[2]


def _denoise_config(overrides=()):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose("denoise", overrides=["reference=identity", "channel=planes", "fusion.enabled=false",
                                              "figures.enabled=false", "progress=false", *overrides])


def classical_stage(points: np.ndarray, normals: np.ndarray, noise: float | None = None, seed: int = 0,
                    overrides=()) -> tuple[np.ndarray, np.ndarray, dict]:
    """dss-denoise's DSS cycles and outlier projection on a noisy cloud (N, 3) with normals (N, 3),
    as the job runs them before the plane fusion: (refined points (N, 3), their
    :func:`dss.fusion.cascade_normals` (N, 3), notes). ``noise``: the level the settings are
    resolved for (None: estimated, as the job does without a hint). ``overrides``: more
    dss-denoise overrides (e.g. ``optimizer.cycles=...``)."""
    import torch

    from dss.fusion import cascade_normals
    from dss.pipeline import estimate_noise_level
    from experiments.denoising.references import make_reference
    from experiments.denoising.refine import refine
    from experiments.denoising.settings import resolve

    cfg = _denoise_config([f"seed={int(seed)}", *overrides])
    p = torch.from_numpy(np.ascontiguousarray(points, np.float32))
    n = torch.from_numpy(np.ascontiguousarray(normals, np.float32))
    used = float(noise) if noise is not None else float(estimate_noise_level(p))
    generator, _ = make_reference(cfg, used)
    s = resolve(cfg, used, len(p), generator)
    refined = refine(p, n, generator, s.spec, s.optimizer, shading=s.shading, fusion=None, noise=used,
                     progress=False, desc="classical stage")
    pts, nrm = refined.points, refined.normals
    k = int(cfg.fusion.normal_k)
    rn = cascade_normals(pts.float(), nrm.float(), k)
    return (pts.float().numpy(), rn.numpy().astype(np.float32),
            {"noise_used": used, "cycles": int(s.optimizer.cycles), "lr_points": float(s.optimizer.lr_points)})


def _choose(shapes: list[dict], split: str, per_family: int, real: int | None) -> list[dict]:
    """The first ``per_family`` shapes of each generated family in ``split`` and the first
    ``real`` real shapes (None: all), in manifest order; the real ones by sampling first
    (``real-<mesh>-<k>``: every mesh's k = 0, then k = 1, ...), so that a few cover every mesh."""
    out, seen = [], {}

    def key(s):
        if s["family"] != "real":
            return (0, 0)
        return (1, int(s["shape_id"].rsplit("-", 1)[1]))

    for s in sorted(shapes, key=key):
        if s["split"] != split:
            continue
        fam = s["family"]
        cap = (len(shapes) if real is None else real) if fam == "real" else per_family
        if seen.get(fam, 0) < cap:
            out.append(s)
            seen[fam] = seen.get(fam, 0) + 1
    return out


def build_cache(data: str | Path, out: str | Path, per_family: int = 4, val_per_family: int = 1,
                real: int | None = None, val_real: int | None = None, draws: int = 1, seed: int = 0,
                noise=None, progress: bool = True, overrides=()) -> dict:
    """Write (or finish) the cascade cache of the ``dss-clouds/1`` dataset ``data`` into ``out``
    (module docstring). Returns the manifest."""
    import torch

    from data_prep.clouds import load_cloud, read_clouds_manifest
    from data_prep.sampling import noisy_copy, with_normals
    from data_prep.shards import npz_bytes
    from dss.io_utils import atomic_write_bytes, atomic_write_text

    torch.set_num_threads(1)
    src = read_clouds_manifest(data)
    noise_range = noise or src.get("noise_range") or [min(src["noise_levels"]), max(src["noise_levels"])]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    man_path = out / "manifest.json"
    settings = {"per_family": per_family, "val_per_family": val_per_family, "real": real, "val_real": val_real,
                "draws": draws, "seed": seed, "noise_range": list(noise_range), "overrides": list(overrides)}
    items: dict[str, dict] = {}
    if man_path.is_file():
        old = read_cascade_manifest(out)
        if old["source"]["fingerprint"] != src["fingerprint"] or old["settings"]["seed"] != seed or \
                old["settings"]["noise_range"] != list(noise_range) or old["settings"]["overrides"] != list(overrides):
            raise ValueError(f"{man_path}: a cache of another dataset or settings is there; use another --out")
        items = {e["file"]: e for e in old["items"]}
    chosen = [(s, "train") for s in _choose(src["shapes"], "train", per_family, real)]
    chosen += [(s, "val") for s in _choose(src["shapes"], "val", val_per_family, val_real)]
    k = int(src["config"]["normals_k"])
    todo = [(s, d) for s, _ in chosen for d in range(draws)]
    t_all = time.process_time()
    for j, (shape, d) in enumerate(todo):
        rel = f"{shape['split']}/{shape['shape_id']}-d{d}.npz"
        if rel in items and (out / rel).is_file():
            continue
        c0 = time.process_time()
        sid = int(hashlib.sha256(shape["shape_id"].encode()).hexdigest()[:8], 16)
        std = log_uniform(noise_range, np.random.default_rng([seed, sid, d, 11]).random())
        nseed = int(np.random.default_rng([seed, sid, d, 13]).integers(2**62))
        pts, mn = load_cloud(data, shape)
        noisy = noisy_copy(pts, std, nseed)
        nn_ = with_normals(noisy, k, "mesh", mn).normals
        refined, rn, notes = classical_stage(noisy, nn_, None, seed=seed, overrides=overrides)
        blob = npz_bytes([("points", refined), ("normals", rn)])
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(out / rel, blob)
        items[rel] = {"shape_id": shape["shape_id"], "family": shape["family"], "split": shape["split"], "draw": d,
                      "noise_std": std, "noise_seed": nseed, "estimated_noise": notes["noise_used"],
                      "cycles": notes["cycles"], "file": rel, "sha256": hashlib.sha256(blob).hexdigest(),
                      "cpu_s": time.process_time() - c0}
        man = {"format": CASCADE_FORMAT, "source": {"root": str(data), "fingerprint": src["fingerprint"]},
               "settings": settings, "items": sorted(items.values(), key=lambda e: e["file"])}
        atomic_write_text(man_path, json.dumps(man, indent=1) + "\n")
        if progress:
            log.info("cascade %d/%d %s draw %d: noise %.4f (estimated %.4f), %.1f CPU s", j + 1, len(todo),
                     shape["shape_id"], d, std, notes["noise_used"], items[rel]["cpu_s"])
    man = {"format": CASCADE_FORMAT, "source": {"root": str(data), "fingerprint": src["fingerprint"]},
           "settings": settings, "items": sorted(items.values(), key=lambda e: e["file"])}
    atomic_write_text(man_path, json.dumps(man, indent=1) + "\n")
    log.info("cascade cache %s: %d items (%.0f CPU s this run)", out, len(items), time.process_time() - t_all)
    return man


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.denoising.cascade", description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="a dss-clouds/1 dataset (dss-prep output=clouds)")
    ap.add_argument("--out", required=True, help="the cache folder (resumable)")
    ap.add_argument("--per-family", type=int, default=4, help="training shapes per generated family")
    ap.add_argument("--val-per-family", type=int, default=1, help="validation shapes per generated family")
    ap.add_argument("--real", type=int, default=None, help="real training shapes (default: all)")
    ap.add_argument("--val-real", type=int, default=None, help="real validation shapes (default: all)")
    ap.add_argument("--draws", type=int, default=1, help="noise draws per shape")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="noise range (default: the dataset's noise_range)")
    ap.add_argument("overrides", nargs="*", help="dss-denoise overrides for the classical stage")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        build_cache(a.data, a.out, a.per_family, a.val_per_family, a.real, a.val_real, a.draws, a.seed, a.noise,
                    overrides=a.overrides)
    except (FileNotFoundError, ValueError) as e:
        print(f"experiments.denoising.cascade: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
