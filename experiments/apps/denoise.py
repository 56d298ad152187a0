"""``dss-denoise``: multi-view DSS point cloud denoising (paper "Application: point cloud denoising").

    dss-denoise                                      # the shipped example (1% noise, ground truth)
    dss-denoise noisy.ply                            # model picked from the estimated noise level
    dss-denoise noisy.ply noise=0.003                # ... or from a hint (0.003 | 0.01)
    dss-denoise noisy.ply reference=l0               # L0-DSS (image filter instead of the network)
    dss-denoise noisy.ply reference=onnx reference.model=my.onnx    # any denoiser exported with dss-export
    dss-denoise noisy.ply clean=clean.ply mesh=gt.ply   # ground truth: metrics in both protocols

The noisy cloud (normals estimated when missing; rows with NaN/inf reported and dropped; points
much sparser than the surface removed, ``outliers`` in ``conf/denoise.yaml``, and written to
``outliers.ply``) is normalised to a unit bounding-box diagonal. Every cycle 2 views (the
budget, ``conf/denoise_parts/budget``; the paper: 12) are sampled around it, the *input* is rendered with the
denoiser's training render setting (the model file's metadata) or in the channel of
``conf/denoise_parts/channel`` (planes for the controls, the paper's sun lights at 64 px for the filters),
the renders are mapped through the reference generator (``conf/reference``), and DSS optimises
normals to match them (the paper's local schedule, T_n = 19 normal steps per cycle;
``cycles_by_noise`` and ``lr_points_by_noise`` for ``auto``: 4 cycles at 3x the paper's point
rate at 1% noise) while the projection term moves the points onto the planes of the corrected
normals; in the planes channel the plane fusion (``conf/denoise_parts/fusion``) then moves them onto the
surface the references show. The paper's T_p = 1 image-driven point step per cycle is
``optimizer.point_steps=1``: with learned references it made the result worse (docs/denoising.md
"How each setting was chosen" has the measurements). The stages are in
:mod:`experiments.denoising.job`. Writes into the run directory: ``config.yaml`` (the settings in
use), the denoised PLY (input units), ``before_after.png`` (rows: noisy | denoised | clean when
given), ``references.png`` (last cycle: input renders | references | final renders), ``loss.png``
+ ``loss.json``, ``metrics.json``.
"""

from __future__ import annotations

import logging
import time

import hydra
import torch
from omegaconf import DictConfig

from dss.timing import StageClock
from experiments.common import (
    OutputExistsError,
    claim_run_dir,
    guarded,
    positional_to_override,
    release_claims,
    run_app,
    run_dir,
    save_config,
    save_metrics,
)
from experiments.denoising import inputs, job, settings
from experiments.denoising.refine import normals_mode
from experiments.wandb_log import log_run

log = logging.getLogger(__name__)

__all__ = ["run", "main", "ARTEFACTS", "OutputExistsError"]

#: what a run writes into its run directory (an earlier run's are refused or, with overwrite,
#: removed first: experiments.common.claim_run_dir)
ARTEFACTS = ("denoised.ply", "outliers.ply", "before_after.png", "references.png", "loss.png", "loss.json",
             "metrics.json", "config.yaml")


def run(cfg: DictConfig) -> dict:
    """Denoise ``cfg.input`` (see the module docstring; the stages: experiments.denoising.job);
    returns the metrics dict. ``cfg`` is not changed: ``config.yaml`` records the settings in use."""
    start = time.perf_counter(), time.process_time()
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    out, files = run_dir(cfg), inputs.input_files(cfg)
    # Everything that can be refused is checked before any work or any output file: settings,
    # the outputs (claimed: writable, not another run's), the input, the model.
    dev, hint = job.check(cfg)
    claim_run_dir(out, ARTEFACTS, bool(cfg.get("overwrite", False)))
    output = inputs.resolve_output(cfg, out, "denoised.ply")
    clock = StageClock()  # where the job's time goes: metrics.json profile_s and the log
    data = job.prepare(cfg, files, hint, dev, clock)
    generator, model_note = job.reference(cfg, data, clock)
    s = settings.resolve(cfg, data.noise.used, len(data.cloud), generator)  # refuses a bad setting
    s.optimizer.check_points(len(data.cloud), f"input {files.input}")
    with clock("ground_truth"):
        truth = job.ground_truth(cfg, data, generator)
    save_config(s.config, out)
    job.log_start(data, generator, s)
    with clock("optimization"):
        refined = job.readmit(cfg, job.refine(cfg, s, data.cloud, generator, truth, dev), data)
    mode = normals_mode(cfg.normals.get("output", "auto"), refined.history)
    with clock("write"):
        written, output = job.write(cfg, refined, mode, data, output, out)
    with clock("metrics"):
        scores = job.score(cfg, data.cloud_in, refined, written, truth)
    scores.floor = job.floor(cfg, truth, len(data.cloud_in), clock)
    figures = job.draw(cfg, out, s, data, refined, written, truth, generator, clock)
    metrics = job.record(data, output, truth, s, generator, model_note, refined, mode, scores, figures, clock, start)
    save_metrics(metrics, out)
    job.log_end(metrics, clock, refined.history)
    log_run(s.config, out, metrics, refined.history, figures)
    release_claims()
    return metrics


@hydra.main(version_base="1.3", config_path="../../conf", config_name="denoise")
@guarded
def _main(cfg: DictConfig) -> None:
    m = run(cfg)
    s = m["summary"]
    if s["output"]:
        for pr in s["output"]:
            print(f"[{pr} protocol] Chamfer x1e4: input {s['input'][pr]['chamfer']:.3f} -> "
                  f"denoised {s['output'][pr]['chamfer']:.3f}")
    print(f"denoised cloud: {m['output']} ({m['time_s']['total']:.0f} s)")


def main() -> None:
    positional_to_override("input")
    run_app(_main)


if __name__ == "__main__":
    main()
