"""The Hydra apps, by config name: their command, module, what they do, their most-used options.

``conf/hydra/default.yaml`` (the Hydra settings every app shares) reads this through
``hydra.job.config_name``: the ``--help`` text starts with the app's paragraph and options
(:func:`help_text`), and :class:`experiments.common.ClaimRunDir` claims the run directory of the
apps whose module lists ``ARTEFACTS``. A new app gets an entry here and ``- hydra: default`` in
its config's defaults list.
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass
from pathlib import Path

__all__ = ["App", "APPS", "help_text"]

_CONF = Path(__file__).resolve().parent.parent / "conf"


@dataclass(frozen=True)
class App:
    """One Hydra app.

    Attributes:
        command: the console script (pyproject.toml).
        module: the module with the task function (and ``ARTEFACTS`` when it claims its run directory).
        about: what the command does and writes, one paragraph.
        options: the most-used overrides, ``(key=value, what)``; each key is a config key or group.
        groups: the config groups the app reads (folders under ``conf/``; listed with their options).
    """

    command: str
    module: str
    about: str
    options: tuple[tuple[str, str], ...]
    groups: tuple[str, ...] = ()


APPS: dict[str, App] = {
    "denoise": App(
        "dss-denoise", "experiments.apps.denoise",
        "Denoise a point cloud with multi-view DSS: render it from many views, make reference images "
        "(the renders themselves by default, a Pix2Pix model or an image filter), and move the points and "
        "normals until their renders match while the projection regulariser pulls the points onto their "
        "neighbours' planes; every setting follows the estimated noise level. Without an input it denoises "
        "the shipped example and scores it against its ground truth. Writes denoised.ply, metrics.json and "
        "figures into outputs/denoise/<date>/ (outputs/denoise/latest). docs/denoising.md.",
        (("input=PLY", "the noisy cloud (`dss-denoise scan.ply` means the same); default: the shipped example"),
         ("noise=0.005", "the noise std as a fraction of the bbox diagonal; default: estimated"),
         ("reference=identity|onnx|oracle|l0|slic", "what makes the target images"),
         ("channel=point|planes|sun|auto", "what the renders show (planes: with the plane fusion)"),
         ("device=cpu|cuda|auto", "where the optimisation runs")),
        ("reference", "denoise_parts/budget", "denoise_parts/channel", "denoise_parts/fusion")),
    "filter": App(
        "dss-filter", "experiments.apps.filter",
        "Edit geometry through image filters (the paper's DSS-based geometry filtering): render a cloud, "
        "filter the renders (L0 smoothing, SLIC superpixels), and move the points until their renders "
        "match. Without an input it filters the shipped example's clean cloud. Writes filtered.ply, "
        "metrics.json and figures into outputs/filter/<date>/.",
        (("input=PLY", "the cloud (`dss-filter cloud.ply` means the same); default: the shipped example"),
         ("reference=l0|slic|identity", "the image filter"),
         ("noise=0.01", "add Gaussian noise (fraction of the bbox diagonal) first"),
         ("shading=sun|point", "the lights the renders are filtered under"),
         ("device=cpu|cuda|auto", "where the optimisation runs")),
        ("reference",)),
    "deform": App(
        "dss-deform", "experiments.apps.deform",
        "Deform a start shape (sphere, cube, grid or a cloud) until its renders match a target's from "
        "many views: the paper's shape-from-rendering experiments. Writes final.ply, snapshots, the loss "
        "and Chamfer curves and metrics.json into outputs/deform/<date>/. docs/deformation.md.",
        (("scene=NAME", "one of the paper's experiments (conf/scene/), e.g. sphere_teapot"),
         ("target.path=PLY", "the target cloud"),
         ("start.shape=sphere|cube|grid|ply", "the start shape (start.path=PLY for ply)"),
         ("image_size=256", "render size in pixels (128: faster, coarser)"),
         ("seed=0", "camera jitter and sampling seed")),
        ("scene",)),
    "render_cloud": App(
        "dss-render", "experiments.apps.render",
        "Render a point cloud with DSS from several views: sun-shaded, normal and depth images and a grid "
        "of the views, into outputs/render/<date>/.",
        (("input=PLY", "the cloud (`dss-render cloud.ply` means the same); normals estimated when missing"),
         ("views=12", "number of views"),
         ("image_size=256", "render size in pixels"),
         ("sampler=fps|ring", "camera placement: farthest-point on a sphere, or a ring"),
         ("backend=auto|cpp|reference", "the renderer's backend"))),
    "prep": App(
        "dss-prep", "experiments.apps.prep",
        "Generate the denoiser's training pairs: generated shapes -> clean and noisy clouds -> renders of "
        "both through the same cameras and light -> resumable, deterministic shards with a manifest "
        "(the dss-pairs/1 format). Re-running the same command resumes. docs/training.md.",
        (("prep_preset=tiny|cpu|cpu_planes|paper", "the dataset's size (tiny: about a minute; cpu: dss-train's default)"),
         ("out_dir=DIR", "the dataset folder; default: data/pairs-<preset>"),
         ("noise_levels=[0.003,0.01]", "noise levels, one shard set each"),
         ("workers=auto", "processes (auto: all cores)"),
         ("overwrite=true", "replace a dataset made with another config")),
        ("render", "prep_preset")),
    "train": App(
        "dss-train", "experiments.apps.train",
        "Train the Pix2Pix image denoiser on a dss-prep dataset (Lightning), then export the best "
        "checkpoint to denoiser.onnx; checkpoints, metrics.json and labelled validation grids go into "
        "outputs/train/<date>/ (outputs/train/latest). docs/training.md.",
        (("experiment=noise_1pct|noise_0.3pct|planes_1pct|...", "a tested recipe (conf/experiment/)"),
         ("data.root=DIR", "the dss-prep dataset"),
         ("model=tiny|cpu_small|cpu_medium|paper", "the generator's size"),
         ("trainer.max_time=DD:HH:MM:SS", "stop after this long (the budget of the quick path)"),
         ("torch_threads=1", "torch threads (1 is often fastest on a busy machine)")),
        ("data", "model", "trainer", "logger", "callbacks", "experiment", "hparams_search")),
    "export": App(
        "dss-export", "experiments.apps.export",
        "Export a dss-train checkpoint to an ONNX denoiser that carries its render settings, check its "
        "parity with PyTorch, and write a model card beside it (docs/training.md).",
        (("ckpt_path=CKPT", "the checkpoint (required)"),
         ("output=ONNX", "where the model goes; default: <run dir>/denoiser.onnx"),
         ("data_root=DIR", "also check parity on this dataset's validation renders"),
         ("overwrite=true", "replace an existing output file"),
         ("opset=17", "the ONNX opset"))),
    "denoise_table": App(
        "dss-denoise-table", "experiments.evaluation.denoise_table",
        "The paper's point cloud denoising comparison: sample and perturb each test shape, run every "
        "baseline and DSS on it, score CD / HD / P2M and write table.md, table.json and an "
        "accuracy-vs-time chart into outputs/dss-denoise-table/<date>/; resumable. docs/evaluation.md.",
        (("noise=0.01", "noise level (fraction of the bbox diagonal; of the radius with protocol=score)"),
         ("points=20000", "points per clean cloud"),
         ("methods=[cgal_jet,dss_identity]", "the methods to run (default: all)"),
         ("out_dir=DIR", "an earlier run's folder: resume it"),
         ("publish=true", "also copy the summary to its place under results/"))),
    "real_bench": App(
        "dss-real-bench", "experiments.evaluation.real_benchmark",
        "dss-denoise against the best classical result per case on real meshes (Debian's "
        "libcgal-demo, installed by `dss-data real`): sample and perturb each mesh at each point count, "
        "noise level and seed, run DSS and every classical method with a few parameters, and report "
        "the lowest value per metric; writes report.md and report.json into "
        "outputs/dss-real-bench/<date>/; resumable.",
        (("groups=[tuning]", "the shape groups of data_prep/real_split.yaml (tuning, held_out, open)"),
         ("points=[20000]", "point counts per clean cloud"),
         ("noise=[0.005,0.01]", "noise levels (fraction of the bbox diagonal)"),
         ("seeds=[0]", "sampling and noise draws"),
         ("out_dir=DIR", "an earlier run's folder: resume it"))),
    "sweep": App(
        "dss-sweep", "experiments.evaluation.sweep",
        "Stability sweeps and the budget study: vary one setting at a time (noise, density, outliers, "
        "views, cycles, ...) and run a dss-denoise-table per value; writes sweep.md, sweep.json and a "
        "chart per axis into outputs/dss-sweep/<date>/; resumable. docs/evaluation.md.",
        (("study=stability|budget|width", "the study (conf/study/)"),
         ("axes_to_run=[noise]", "only these axes (default: all)"),
         ("out_dir=DIR", "an earlier run's folder: resume it"),
         ("publish=true", "also copy the summary to its place under results/"),
         ("progress=false", "no progress bars")),
        ("study",)),
}


def _groups(groups: tuple[str, ...]) -> list[str]:
    """Hydra's configuration-groups section, for ``groups`` only (Hydra's own template lists every
    group under ``conf/``, which all apps share)."""
    if not groups:
        return []
    lines = ["== Configuration groups ==", "Compose your configuration from these groups (group=option)", ""]
    for g in groups:  # a folder under conf/ (an app's own groups sit below its search path)
        options = sorted(p.stem for p in (_CONF / g).glob("*.yaml"))
        lines.append(f"{g.split('/')[-1]}: {', '.join(options)}")
    return lines + [""]


def help_text(config_name: str) -> str:
    """The body of an app's ``--help`` (a ``string.Template``: Hydra fills ``$CONFIG`` and
    ``$FLAGS_HELP``): what the command does, its most-used options, its config groups, then Hydra's
    dump of the config and its flags."""
    app = APPS.get(config_name)
    lines = []
    if app is not None:
        lines += textwrap.wrap(f"{app.command}: {app.about}", 100) + [""]
        lines += ["Most used (key=value; every key of the config below can be set the same way):"]
        width = max(len(o) for o, _ in app.options)
        lines += [f"  {o.ljust(width)}  {what}" for o, what in app.options] + [""]
    lines += _groups(app.groups if app is not None else ())
    lines += ["== Config ==", "Override anything in the config (foo.bar=value)", "", "$CONFIG", "",
              "== Flags ==", "$FLAGS_HELP"]
    return "\n".join(lines)
