"""A learning curve against CPU time: what a CPU-trained model reaches per CPU hour.

:class:`LearningCurve` (a Lightning callback, ``callbacks.learning_curve`` of the ``planes_*``
experiments) appends after every validation one record to ``<run dir>/learning_curve.json``:
the global step, the epoch, the cumulative process CPU hours of training (validation included;
carried in the checkpoint, so a resumed run continues the count) and every ``val/*`` metric;
and redraws ``learning_curve.png`` (the metrics of ``plot`` against CPU hours, with the noisy
input's value where it is logged, dashed). With ``torch_threads=1`` and ``data.num_workers=0``
(the on-the-fly renders in the training process) the CPU hours are the whole cost of the run;
``max_cpu_minutes`` stops training when they reach a budget.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import lightning as L

from ._io import atomic_write_bytes

log = logging.getLogger(__name__)

__all__ = ["LearningCurve", "plot_curves"]

#: what the figure shows by default: per-view errors, the fusion's measures
DEFAULT_PLOT = ("val/depth_err", "val/normal_err_deg", "val/probe_spread_median", "val/probe_trusted",
                "val/probe_fused_err_median", "val/nll")


class LearningCurve(L.Callback):
    """Records validation metrics against cumulative CPU hours (module docstring)."""

    def __init__(self, filename: str = "learning_curve", plot=DEFAULT_PLOT, max_cpu_minutes: float | None = None):
        self.filename = str(filename)
        #: stop training once the run (resumed parts included) has used this much CPU time: on a
        #: shared machine the wall-clock limit (trainer.max_time) says little about the cost
        self.max_cpu_minutes = None if max_cpu_minutes in (None, 0) else float(max_cpu_minutes)
        self.plot = [str(p) for p in plot]
        self.cpu_s = 0.0  # before this process (from the checkpoint)
        self._t0: float | None = None

    def _now(self) -> float:
        return self.cpu_s + (time.process_time() - self._t0 if self._t0 is not None else 0.0)

    def on_fit_start(self, trainer, pl_module) -> None:
        self._t0 = time.process_time()

    def state_dict(self) -> dict[str, Any]:
        return {"cpu_s": self._now()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.cpu_s = float(state.get("cpu_s", 0.0))
        self._t0 = time.process_time()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.max_cpu_minutes is not None and self._now() >= 60.0 * self.max_cpu_minutes and not trainer.should_stop:
            log.info("CPU budget of %.1f minutes used: stopping after this batch", self.max_cpu_minutes)
            trainer.should_stop = True

    def on_validation_end(self, trainer, pl_module) -> None:
        if trainer.sanity_checking or trainer.global_rank != 0 or trainer.state.fn != "fit":
            return
        root = Path(trainer.default_root_dir)
        path = root / f"{self.filename}.json"
        records = json.loads(path.read_text())["records"] if path.is_file() else []
        metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")
                   and math.isfinite(float(v))}
        step = int(trainer.global_step)
        records = [r for r in records if r["step"] < step]  # a resumed run replaces what it redoes
        records.append({"step": step, "epoch": int(trainer.current_epoch), "cpu_h": self._now() / 3600.0,
                        "metrics": metrics})
        atomic_write_bytes(path, (json.dumps({"records": records}, indent=1) + "\n").encode())
        try:
            plot_curves({"run": records}, root / f"{self.filename}.png", self.plot)
        except Exception as e:  # a figure must never stop training
            log.warning("learning curve figure not drawn: %s", e)


def plot_curves(runs: dict[str, list[dict]], path: Path, keys=DEFAULT_PLOT) -> Path:
    """One panel per metric of ``keys`` (those any run has), a line per run (label -> records)
    against CPU hours; ``val/noisy_<name>`` / ``val/probe_noisy_<name>`` (the input's value) dashed."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    keys = [k for k in keys if any(k in r["metrics"] for recs in runs.values() for r in recs)]
    if not keys:
        raise ValueError("no metric to plot")
    cols = min(3, len(keys))
    rows = -(-len(keys) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False)
    for ax, k in zip(axes.flat, keys):
        for ci, (label, recs) in enumerate(runs.items()):
            pts = [(r["cpu_h"], r["metrics"][k]) for r in recs if k in r["metrics"]]
            if pts:
                ax.plot(*zip(*pts), marker=".", color=f"C{ci}", label=label)
            noisy = k.replace("val/probe_", "val/probe_noisy_") if "probe_" in k else k.replace("val/", "val/noisy_")
            base = [(r["cpu_h"], r["metrics"][noisy]) for r in recs if noisy in r["metrics"]]
            if base:
                ax.plot(*zip(*base), ls="--", color=f"C{ci}", alpha=0.5)
        ax.set_title(k, fontsize=9)
        ax.set_xlabel("CPU hours")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(keys):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle("validation against CPU hours (dashed: the input's renders)", fontsize=9)
    fig.tight_layout()
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    atomic_write_bytes(Path(path), buf.getvalue())
    return Path(path)


def main(argv=None) -> int:
    """``python -m pix2pix.learning_curve --out OUT label=RUN_DIR ...``: the runs' curves in one
    figure (``OUT.png``) and their records in one file (``OUT.json``)."""
    import argparse
    import sys

    ap = argparse.ArgumentParser(prog="python -m pix2pix.learning_curve", description=main.__doc__)
    ap.add_argument("runs", nargs="+", help="label=run directory (holding learning_curve.json)")
    ap.add_argument("--out", required=True, help="output path without suffix")
    ap.add_argument("--metrics", nargs="*", default=list(DEFAULT_PLOT))
    a = ap.parse_args(argv)
    runs = {}
    for item in a.runs:
        label, _, d = item.partition("=")
        path = Path(d) / "learning_curve.json"
        if not path.is_file():
            print(f"pix2pix.learning_curve: error: {path} not found", file=sys.stderr)
            return 2
        runs[label] = json.loads(path.read_text())["records"]
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    command = "python -m pix2pix.learning_curve " + " ".join(sys.argv[1:] if argv is None else argv)
    record = {"what": "validation metrics of training runs against CPU hours", "command": command, "runs": runs}
    atomic_write_bytes(out.with_suffix(".json"), (json.dumps(record, indent=1) + "\n").encode())
    plot_curves(runs, out.with_suffix(".png"), a.metrics)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
