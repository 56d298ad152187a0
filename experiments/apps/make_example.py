"""Regenerate the shipped denoising example ``experiments/assets/example/`` deterministically.

    python -m experiments.apps.make_example [--out DIR] [--force]

The example is a generated shape with known ground truth, made exactly as ``dss-prep`` makes a
shape of its dataset (same seeds): family ``superquadric``, index 26 of data seed 0, i.e. shape
seed ``data_prep.shards.shape_seed(0, "superquadric", 26)``, meshed at resolution 96. With the
``cpu`` prep preset (36 shapes per family, the shipped models' data) and with the default
(8 per family) this shape is not in the training split: it is in the ``test`` split of the
``cpu`` preset and not generated at all by the default one. (With the ``paper`` preset, 311
per family, its split is whatever that plan assigns.)

Files (binary PLY, float32, about 1.6 MB together):

- ``mesh.ply``: the ground-truth mesh (unit bbox diagonal, centred at the origin).
- ``clean.ply``: 20,000 Poisson-disk samples with the mesh's normals.
- ``noisy_1pct.ply``: ``clean`` + white Gaussian noise of std 1% of the bbox diagonal (the
  prep noise seed of level index 1), points only (the pipeline estimates normals, as for a
  user's scan).
- ``README.md``: this provenance.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

log = logging.getLogger(__name__)

FAMILY, INDEX, DATA_SEED = "superquadric", 26, 0
RESOLUTION, NUM_POINTS, NOISE, NOISE_LEVEL_INDEX = 96, 20000, 0.01, 1
OUT = Path(__file__).resolve().parents[1] / "assets" / "example"


def make_example(out: str | Path = OUT, force: bool = False) -> dict:
    """Write mesh.ply, clean.ply, noisy_1pct.ply and README.md into ``out``; returns a summary."""
    import open3d as o3d
    import torch

    from data_prep.sampling import measured_noise_std, noisy_copy, poisson_disk
    from data_prep.shapes import make_shape
    from data_prep.shards import noise_seed, shape_seed
    from dss.io_utils import atomic_write_text
    from dss.ply import write_ply

    out = Path(out)
    names = ("mesh.ply", "clean.ply", "noisy_1pct.ply", "README.md")
    if not force and any((out / n).exists() for n in names):
        raise FileExistsError(f"{out} already holds example files; pass --force to regenerate them")
    # One thread, as dss-prep's workers: open3d's sample elimination and the noise are then
    # bit-reproducible (main() also sets OMP_NUM_THREADS before open3d is imported).
    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    seed = shape_seed(DATA_SEED, FAMILY, INDEX)
    mesh = make_shape(FAMILY, seed, RESOLUTION)
    clean = poisson_disk(mesh, NUM_POINTS, seed)
    noisy = noisy_copy(clean.points, NOISE, noise_seed(seed, NOISE_LEVEL_INDEX))
    torch.set_num_threads(prev)

    out.mkdir(parents=True, exist_ok=True)
    write_ply(out / "mesh.ply", mesh.vertices, faces=mesh.faces)
    write_ply(out / "clean.ply", clean.points, normals=clean.normals)
    write_ply(out / "noisy_1pct.ply", noisy)
    summary = {"family": FAMILY, "index": INDEX, "data_seed": DATA_SEED, "shape_seed": seed,
               "resolution": RESOLUTION, "vertices": len(mesh.vertices), "faces": len(mesh.faces),
               "points": NUM_POINTS, "noise_std_fraction": NOISE,
               "measured_noise_std_fraction": round(measured_noise_std(clean.points, noisy), 6),
               "sizes_bytes": {n: (out / n).stat().st_size for n in names[:3]}}
    text = (__doc__.split("\n\n", 2)[2].split("Files")[0].strip() + "\n\n"
            f"```json\n{json.dumps(summary, indent=2)}\n```\n\nRegenerate: `python -m experiments.apps.make_example --force`.\n")
    atomic_write_text(out / "README.md", "# Shipped denoising example\n\n" + text)
    return summary


def main(argv=None) -> None:
    import os

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(OUT))
    p.add_argument("--force", action="store_true", help="replace existing files")
    a = p.parse_args(argv)
    print(json.dumps(make_example(a.out, a.force), indent=2))


if __name__ == "__main__":
    main()
