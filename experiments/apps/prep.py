"""``dss-prep``: generate the denoiser's training pairs (Hydra app over :func:`run`).

    dss-prep                              # cpu preset -> data/pairs
    dss-prep prep_preset=tiny out_dir=/tmp/pairs
    dss-prep -m prep_preset=paper         # 16 slices via the joblib launcher (or submitit)
    dss-prep prep_preset=cpu_planes output=clouds out_dir=data/clouds   # clean clouds only, for
                                          # pairs rendered on the fly (experiments.onthefly)

Config: ``conf/prep.yaml`` with the shared render group ``conf/render/pairs.yaml`` and the
presets ``conf/prep_preset/{tiny,cpu,paper}.yaml``. The dataset goes to ``out_dir`` (stable, so
a re-run resumes); the Hydra run directory receives ``config.yaml`` and ``metrics.json``
(throughput, counts, stage times; ``<out_dir>/logs`` outside Hydra), and the dataset
``preview/pairs-<level>.png`` sheets.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from experiments.common import guarded

log = logging.getLogger(__name__)

__all__ = ["run", "main"]


def _abs(path: str) -> Path:
    try:
        from hydra.utils import to_absolute_path

        return Path(to_absolute_path(path))
    except ValueError:  # hydra not initialised
        return Path(path).absolute()


def _workers(cfg: DictConfig) -> int:
    w = cfg.get("workers", "auto")
    if w in (None, "auto"):
        return 1 if int(cfg.parts.count) > 1 else max(1, os.cpu_count() or 1)
    return int(w)


def _run_dir(out_dir: Path) -> Path:
    """Hydra's run directory; outside Hydra (tests, notebooks) ``<out_dir>/logs``."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    d = out_dir / "logs"
    d.mkdir(parents=True, exist_ok=True)
    return d


def run(cfg: DictConfig) -> dict[str, Any]:
    """Generate (or resume) the dataset described by ``cfg``; returns the run metrics."""
    from data_prep.preview import pairs_sheet
    from data_prep.render_spec import RenderSpec
    from data_prep.shards import PrepConfig, generate_dataset
    from experiments.common import save_config, save_metrics

    pc = PrepConfig.from_config(cfg)
    spec = RenderSpec.from_config(cfg.render, where="render (conf/render/pairs.yaml)")
    out_dir = _abs(str(cfg.out_dir))
    workers = _workers(cfg)
    rd = _run_dir(out_dir)
    save_config(cfg, rd)
    output = str(cfg.get("output", "pairs"))
    if output not in ("pairs", "clouds"):
        raise ValueError(f"output must be pairs or clouds, got {output!r}")
    if output == "clouds":
        from data_prep.clouds import generate_clouds

        stats = generate_clouds(pc, spec, out_dir, overwrite=bool(cfg.get("overwrite", False)),
                                progress=bool(cfg.get("progress", True)))
        stats.update({"out_dir": str(out_dir), "output": "clouds", "preset": cfg.get("preset")})
        save_metrics(stats, rd)
        return stats
    stats = generate_dataset(
        pc, spec, out_dir, workers=workers, part_index=int(cfg.parts.index), part_count=int(cfg.parts.count),
        overwrite=bool(cfg.get("overwrite", False)), verify_existing=bool(cfg.get("verify_existing", True)),
        progress=bool(cfg.get("progress", True)))
    stats.update({"out_dir": str(out_dir), "workers": workers, "image_size": list(spec.image_size),
                  "preset": cfg.get("preset"), "cpu_count": os.cpu_count()})
    if stats["manifest"] and cfg.get("preview", True):
        previews = []
        for level in pc.noise_levels:
            try:
                previews.append(str(pairs_sheet(out_dir, out_dir / "preview" / f"pairs-{level:g}.png",
                                                noise_level=level)))
            except ValueError as e:  # e.g. a split without shards in a tiny dataset
                log.warning("preview skipped: %s", e)
        stats["previews"] = previews
    save_metrics(stats, rd)
    log.info("dataset: %s (%s); %.2f pairs/s with %d workers; metrics in %s", out_dir,
             "complete" if stats["complete"] else "incomplete", stats["pairs_per_s"], workers, rd / "metrics.json")
    return stats


@hydra.main(version_base="1.3", config_path="../../conf", config_name="prep")
@guarded
def _main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Console entry point: an expected failure prints one line and exits 2 (experiments.common.run_app)."""
    from experiments.common import run_app

    run_app(_main)


if __name__ == "__main__":
    main()

