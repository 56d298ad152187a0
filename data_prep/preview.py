"""Preview sheets of the shape families (PNG, matplotlib Agg) and of rendered training pairs.

``dss-shapes-preview`` writes ``<out>/<family>.png`` (a grid of seeds per family) and
``<out>/overview.png`` (a few seeds of every family), plus ``<out>/preview.json`` with the mesh
statistics shown on the sheets. Meshes are decimated and drawn as flat-shaded triangles.

Usage::

    dss-shapes-preview --out data/previews/shapes --seeds 8 --resolution 96
    dss-shapes-preview --families teapot,figure --seeds 4
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from .shapes import FAMILIES, check_mesh, make_shape, resolve_families, to_open3d
from .shapes.meshing import Mesh

log = logging.getLogger(__name__)

__all__ = ["draw_mesh", "family_sheet", "overview_sheet", "pairs_sheet", "main"]


def _decimate(mesh: Mesh, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    if mesh.num_faces <= max_faces:
        return mesh.vertices, mesh.faces
    # vertex clustering keeps triangles evenly sized (quadric decimation leaves long slivers on
    # flat faces, which matplotlib's painter's-algorithm sorting draws badly)
    m = to_open3d(mesh)
    diag = mesh.bbox_diagonal()
    voxel = diag * np.sqrt(mesh.num_faces / max_faces) / 250
    m = m.simplify_vertex_clustering(voxel_size=float(voxel))
    m.remove_degenerate_triangles()
    return np.asarray(m.vertices), np.asarray(m.triangles)


def draw_mesh(ax, mesh: Mesh, max_faces: int = 6000, elev: float = 20.0, azim: float = -60.0,
              title: str | None = None) -> None:
    """Flat-shaded mesh on a matplotlib 3D axis (light from the upper left of the viewer)."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    v, f = _decimate(mesh, max_faces)
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True).clip(1e-12)
    e, a = np.radians(elev), np.radians(azim)
    view = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    up = np.array([0.0, 0.0, 1.0])
    right = np.cross(up, view)
    right /= np.linalg.norm(right)
    light = view + 0.6 * np.cross(view, right) - 0.5 * right
    light /= np.linalg.norm(light)
    shade = 0.15 + 0.85 * np.clip(n @ light, 0, 1)
    colors = np.stack([shade * 0.85, shade * 0.88, shade * 0.95, np.ones_like(shade)], 1)
    coll = Poly3DCollection(tri, facecolors=colors, edgecolors="none", linewidths=0)
    ax.add_collection3d(coll)
    c = (v.max(0) + v.min(0)) / 2
    r = (v.max(0) - v.min(0)).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    ax.set_axis_off()
    if title:
        ax.set_title(title, fontsize=7)


def _sheet(items, ncols: int, path: Path, suptitle: str, resolution: int) -> list[dict]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dss.io_utils import atomic_savefig

    nrows = int(np.ceil(len(items) / ncols))
    fig = plt.figure(figsize=(2.2 * ncols, 2.3 * nrows))
    stats = []
    for i, (family, seed) in enumerate(items):
        ax = fig.add_subplot(nrows, ncols, i + 1, projection="3d")
        mesh = make_shape(family, seed, resolution)
        rep = check_mesh(mesh)
        stats.append({"family": family, "seed": seed, **{k: rep[k] for k in ("num_faces", "watertight", "volume")}})
        draw_mesh(ax, mesh, title=f"{family} #{seed} ({rep['num_faces'] // 1000}K tris)")
    fig.suptitle(suptitle, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.35 / fig.get_figheight()))  # room for the title
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
    return stats


def family_sheet(family: str, out_dir: Path, seeds: int = 8, resolution: int = 96, ncols: int = 4) -> list[dict]:
    """``<out_dir>/<family>.png``: seeds 0..seeds-1 of one family."""
    return _sheet([(family, s) for s in range(seeds)], ncols, Path(out_dir) / f"{family}.png",
                  f"{family}: {FAMILIES[family][1]}", resolution)


def overview_sheet(families: list[str], out_dir: Path, seeds: int = 4, resolution: int = 96) -> list[dict]:
    """``<out_dir>/overview.png``: ``seeds`` examples of every family, one row per family."""
    return _sheet([(f, s) for f in families for s in range(seeds)], seeds, Path(out_dir) / "overview.png",
                  "procedural shape families", resolution)


def _planes_normal_map(a: np.ndarray) -> np.ndarray:
    """(H, W, 3) planes -> camera-space normals facing the camera as RGB (black background)."""
    n = -a / np.linalg.norm(a, axis=-1, keepdims=True).clip(1e-12)
    return np.where(np.abs(a).max(-1, keepdims=True) > 0, 0.5 + 0.5 * n, 0.0)


def _planes_depth_error(noisy: np.ndarray, clean: np.ndarray, render: dict) -> np.ndarray:
    """|z_noisy - z_clean| (H, W) of two planes renders (0 where either is background)."""
    H, W = noisy.shape[:2]
    f = float(render.get("focal") or 0.5 * W / np.tan(np.radians(float(render["fov_deg"])) / 2))
    x = (np.arange(W) + 0.5 - W / 2) / f
    y = (np.arange(H) + 0.5 - H / 2) / f

    def z(a):
        return 1.0 / np.clip(a[..., 0] * x[None, :] + a[..., 1] * y[:, None] + a[..., 2], 1e-3, None)

    both = (np.abs(noisy).max(-1) > 0) & (np.abs(clean).max(-1) > 0)
    return np.where(both, np.abs(z(noisy) - z(clean)), 0.0)


def pairs_sheet(dataset_dir: str | Path, out_path: str | Path, num: int = 6, split: str = "train",
                noise_level: float | None = None) -> Path:
    """A sheet of ``num`` rendered pairs (noisy | clean | |difference| x4), one per shard, from
    shards spread over the split (so several shapes and families show). Planes datasets show
    their camera-space normals (``0.5 + 0.5 n``) and the implied depth's error |z - z_clean| in
    units of 3 noise std (white: 3 std or more), over the pixels both renders cover."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dss.io_utils import atomic_savefig

    root = Path(dataset_dir)
    manifest = json.loads((root / "manifest.json").read_text())
    shards = [s for s in manifest["shards"] if s["split"] == split
              and (noise_level is None or abs(s["noise_level"] - noise_level) < 1e-12)]
    if not shards:
        raise ValueError(f"{root}: no {split} shard with noise level {noise_level}")
    pairs = {p["pair_id"]: p for p in manifest["pairs"]}
    picks = []  # (noisy, clean, record)
    chosen = [shards[i] for i in np.unique(np.linspace(0, len(shards) - 1, num).astype(int))]
    per_shard = int(np.ceil(num / len(chosen)))
    for s in chosen:
        with np.load(root / s["path"]) as z:
            ids = z["pair_id"]
            for i in np.linspace(0, len(ids) - 1, min(per_shard, len(ids))).astype(int):
                picks.append((z["noisy"][i].astype(np.float32), z["clean"][i].astype(np.float32),
                              pairs[int(ids[i])]))
    picks = picks[:num]
    planes = str(manifest.get("render", {}).get("shading")) == "planes"
    fig, axes = plt.subplots(len(picks), 3, figsize=(6, 2 * len(picks)), squeeze=False)
    for row, (noisy, clean, p) in enumerate(picks):
        cols = ((noisy, "noisy"), (clean, "clean"), (np.abs(noisy - clean) * 4, "|diff| x4"))
        if planes:
            err = _planes_depth_error(noisy, clean, manifest["render"]) / (3 * shards[0]["noise_level"])
            cols = ((_planes_normal_map(noisy), "noisy normals"), (_planes_normal_map(clean), "clean normals"),
                    (np.repeat(err[..., None], 3, -1), "|depth error| / 3 std"))
        for col, (img, name) in enumerate(cols):
            axes[row, col].imshow(np.clip(img, 0, 1))
            axes[row, col].set_axis_off()
            axes[row, col].set_title(f"{name} {p['shape_id']}" if col < 2 else name, fontsize=6)
    fig.suptitle(f"{root.name}: {split}, noise {shards[0]['noise_level']}", fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.3 / fig.get_figheight()))
    atomic_savefig(fig, Path(out_path), dpi=110)
    plt.close(fig)
    return Path(out_path)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="dss-shapes-preview", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="data/previews/shapes", help="output folder for the PNG sheets")
    ap.add_argument("--families", default="all", help="comma-separated family names or 'all'")
    ap.add_argument("--seeds", type=int, default=8, help="examples per family sheet")
    ap.add_argument("--resolution", type=int, default=96, help="marching-cubes grid resolution")
    ap.add_argument("--no-overview", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    fams = resolve_families(args.families.split(","))
    out = Path(args.out)
    stats = {}
    for fam in fams:
        stats[fam] = family_sheet(fam, out, args.seeds, args.resolution)
        log.info("wrote %s", out / f"{fam}.png")
    if not args.no_overview:
        overview_sheet(fams, out, 4, args.resolution)
        log.info("wrote %s", out / "overview.png")
    from dss.io_utils import atomic_write_json

    atomic_write_json(out / "preview.json", {"resolution": args.resolution, "families": stats})


if __name__ == "__main__":
    main()
