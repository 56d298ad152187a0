"""Where the image gradient of a dss-deform run can reach the target's parts it missed.

    python -m experiments.evaluation.deform_concavities <dss-deform run dir> [--far 0.02]

The *missed* target points are those farther than ``--far`` (bbox diagonals) from every point of
the run's ``final.ply`` (on the yoga figure: the insides of the limbs along the openings). For
three sets of 12 views at the run's image size, each rendered with back-face culling off
(:func:`dss.orientation.views_seeing`), it reports

- ``target_seen``: the fraction of the missed target points that some view of the set sees
  (the image loss can only pull toward what a reference shows);
- ``result_seen``: the fraction of the result's points near them (within 2 x ``--far`` of a
  missed point) that some view sees (only a visible splat gets a visibility gradient);
- ``residual_ratio``: the mean image error |render - reference| at the pixels where the missed
  target points are visible, over the mean error on all covered pixels (> 1: the loss sees them);
- ``offset_px``: the median distance of a missed point to the result, in pixels of those views
  (the visibility gradient reaches ``window`` pixels: 16, shrinking to 8 by the end of the
  default schedule and to 7 by the end of the best preset's).

It also reports where the Hausdorff distance comes from (``hausdorff_sides``: the farthest
target point from the result and the farthest result point from the target, x1e3) and the
result's ``unseen`` points: those no view of 64 around the object (a Fibonacci sphere, back-face
culling off) sees, how many of them lie inside the target (the majority of their 8 nearest
target points' normals face away from them) and the Chamfer / Hausdorff distances without them.

The sets: ``random`` (the optimiser's view sampler, 4 cycles' draws, each cycle's 12 views
scored alone and the mean taken), ``error_aware`` (:func:`dss.views.error_aware_cameras` at
the optimiser's distance 0.5 around the largest residual of the first random set) and
``aimed`` (the 12 of 512 directions on the sampler's sphere that see the most missed points,
chosen greedily: the best any 12 views around the object can do). Writes JSON to stdout (and
``--out``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf
from scipy.spatial import cKDTree

__all__ = ["main", "trace"]


def _aimed_views(tp, tn, missed, radius: float, fov: float, size: int, settings, candidates: int, views: int):
    """(directions, candidate cameras, chosen indices): ``views`` of ``candidates`` directions on
    the sphere chosen greedily to see the most missed target points."""
    from dss.cameras import fibonacci_sphere, fit_distance, focal_from_fov, look_at
    from dss.orientation import views_seeing

    dirs = fibonacci_sphere(candidates)
    cand = look_at(dirs * fit_distance(radius, fov), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), focal_from_fov(fov, size),
                   (size, size))
    seen = torch.cat([views_seeing(tp, tn, cand[list(range(i, min(i + 64, candidates)))], settings)[:, missed]
                      for i in range(0, candidates, 64)])
    chosen, covered = [], torch.zeros(int(missed.sum()), dtype=torch.bool)
    for _ in range(views):  # greedy cover of the missed points
        gain = (seen & ~covered).sum(1)
        best = int(gain.argmax())
        chosen.append(best)
        covered |= seen[best]
    return dirs, cand, chosen


def _unseen(rp, rn, tp, tn, radius: float, fov: float, size: int, settings):
    """(note, the result's metrics, its points' distances to the target's 8 nearest): the
    result's points no view of a 64-view sphere sees (inside the shape: neither image gradient
    nor hull pull), how many lie inside the target, and the metrics without them."""
    from dss.cameras import fibonacci_sphere, fit_distance, focal_from_fov, look_at
    from dss.metrics import evaluate
    from dss.orientation import views_seeing

    ring = look_at(fibonacci_sphere(64) * fit_distance(radius, fov), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0),
                   focal_from_fov(fov, size), (size, size))
    seen_any = views_seeing(rp, rn, ring, settings).any(0)
    d_r, j = cKDTree(tp.numpy()).query(rp.numpy(), k=8)
    side = ((rp.numpy()[:, None, :] - tp.numpy()[j]) * tn.numpy()[j]).sum(-1)
    inside = torch.from_numpy((side < 0).mean(1) > 0.5)
    full, visible = evaluate(rp, tp, protocol="paper"), evaluate(rp[seen_any], tp, protocol="paper")
    unseen = {"points": int((~seen_any).sum()), "inside_target": int((~seen_any & inside).sum()),
              "chamfer_hausdorff": [full.chamfer, full.hausdorff],
              "chamfer_hausdorff_without_them": [visible.chamfer, visible.hausdorff]}
    return unseen, full, d_r


def trace(run: Path, far: float = 0.02, views: int = 12, candidates: int = 512, seed: int = 0) -> dict:
    from dss.orientation import views_seeing
    from dss.pointcloud import load_ply, normalize_unit_diagonal
    from dss.render import render
    from dss.views import SphereViewSampler, error_aware_cameras
    from experiments.common import renderer_settings
    from experiments.deformation.inputs import load_target

    cfg = OmegaConf.load(run / "config.yaml")
    target = load_target(cfg.target.path, cfg.target.points, cfg.seed)
    tp, tn = target.points, target.normals
    if cfg.normalize:
        tp, _, _ = normalize_unit_diagonal(tp)
    res = load_ply(run / "final.ply")
    rp, rn = res.points, res.normals
    settings = renderer_settings(cfg.renderer)
    size, fov = int(cfg.image_size), float(cfg.optimizer.fov_deg)
    radius = float(tp.norm(dim=1).max())
    d_t, _ = cKDTree(rp.numpy()).query(tp.numpy())
    missed = torch.from_numpy(d_t > far)
    near_r = torch.from_numpy(cKDTree(tp[missed].numpy()).query(rp.numpy())[0] < 2 * far) if missed.any() \
        else torch.zeros(len(rp), dtype=torch.bool)

    def shade(p, n, cams):
        return render(p, n, cams, settings, shading=cfg.shading).images

    def score(cams) -> dict:
        seen_t = views_seeing(tp, tn, cams, settings)  # (V, Nt)
        seen_r = views_seeing(rp, rn, cams, settings)
        ref, img = shade(tp, tn, cams), shade(rp, rn, cams)
        err = (img - ref).abs().mean(-1)  # (V, H, W)
        covered = ref.abs().amax(-1) > 1e-6
        uv, z = cams.project(tp[missed])  # (V, M, 2)
        u = uv[..., 0].round().long().clamp(0, size - 1)
        v = uv[..., 1].round().long().clamp(0, size - 1)
        vis = seen_t[:, missed] & (z > 0)
        at = torch.stack([err[i, v[i], u[i]] for i in range(len(cams))])  # (V, M)
        # the missed points' distance to the result in pixels: world distance x focal / depth
        px = torch.from_numpy(d_t[missed.numpy()]).float()[None] * cams.focal.reshape(-1, 1) / z.clamp_min(1e-6)
        return {"target_seen": float(seen_t[:, missed].any(0).float().mean()),
                "result_seen": float(seen_r[:, near_r].any(0).float().mean()) if near_r.any() else None,
                "residual_ratio": float(at[vis].mean() / err[covered].mean()) if vis.any() else None,
                "offset_px": float(px[vis].median()) if vis.any() else None}

    sampler = SphereViewSampler((0.0, 0.0, 0.0), radius, views, size, fov, float(cfg.optimizer.view_jitter), seed=seed)
    random_sets = [sampler.sample() for _ in range(4)]
    random_scores = [score(c) for c in random_sets]
    first = random_sets[0]
    residual = (shade(rp, rn, first) - shade(tp, tn, first)).abs().sum(-1)
    ea, focus = error_aware_cameras(rp, first, residual, views, distance=float(cfg.optimizer.error_aware_distance),
                                    generator=torch.Generator().manual_seed(seed))
    dirs, cand, chosen = _aimed_views(tp, tn, missed, radius, fov, size, settings, candidates, views)
    unseen, full, d_r = _unseen(rp, rn, tp, tn, radius, fov, size, settings)
    # Hausdorff x1e3 in the paper protocol's units: the distances scaled like evaluate's
    scale = full.hausdorff / max(float(d_t.max()), float(d_r[:, 0].max()))
    sides = {"target_to_result": float(d_t.max()) * scale, "result_to_target": float(d_r[:, 0].max()) * scale,
             "result_points_beyond_45": int((d_r[:, 0] * scale > 45).sum())}
    mean = {k: (float(np.mean([s[k] for s in random_scores if s[k] is not None]))
                if any(s[k] is not None for s in random_scores) else None) for k in random_scores[0]}
    return {"run": str(run), "far": far, "hausdorff_sides": sides, "unseen": unseen,
            "missed_target_points": int(missed.sum()), "target_points": len(tp),
            "result_points_near_missed": int(near_r.sum()), "views_per_set": views, "image_size": size,
            "random": mean, "random_union_of_4": score(torch_cat_cams(random_sets)),
            "error_aware": {**score(ea), "focus": [round(x, 4) for x in focus.tolist()]},
            "aimed": {**score(cand[chosen]), "directions": [[round(x, 3) for x in dirs[i].tolist()] for i in chosen]}}


def torch_cat_cams(sets):
    from dss.cameras import Cameras

    return Cameras(torch.cat([c.R for c in sets]), torch.cat([c.t for c in sets]),
                   torch.cat([c.focal.reshape(-1).expand(len(c)) for c in sets]),
                   torch.cat([c.principal.reshape(-1, 2).expand(len(c), 2) for c in sets]), sets[0].image_size)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.evaluation.deform_concavities",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("run", help="a dss-deform run directory (config.yaml, final.ply)")
    ap.add_argument("--far", type=float, default=0.02, help="missed: farther than this from the result")
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="also write the JSON here")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    result = trace(Path(args.run), args.far, args.views, seed=args.seed)
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        from dss.io_utils import atomic_write_text

        atomic_write_text(Path(args.out), text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
