"""The last checkpoint: written after every training epoch and when the run is stopped.

Lightning's ``ModelCheckpoint(save_last=True)`` refreshes ``last.ckpt`` only when it also saves
a top-k checkpoint, that is when the monitored metric improved: a run killed after epochs
without improvement resumed from the last improvement. :class:`LastCheckpoint` saves
``last.ckpt`` at the end of every training epoch, whatever the metrics, and on SIGTERM (a
scheduler's stop) or SIGINT (Ctrl+C) at the step reached, so that ``ckpt_path=.../last.ckpt``
resumes there with the optimiser's state.
"""

from __future__ import annotations

import logging

from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities.exceptions import SIGTERMException

log = logging.getLogger(__name__)

__all__ = ["LastCheckpoint", "BestCheckpoint"]


class LastCheckpoint(ModelCheckpoint):
    """``<dirpath>/<filename>.ckpt`` (default ``last.ckpt``), replaced after every training epoch
    and written on SIGTERM / SIGINT; other exceptions (a bug, a bad batch) leave the last
    epoch's file in place."""

    def __init__(self, dirpath=None, filename: str = "last", every_n_epochs: int = 1):
        super().__init__(dirpath=dirpath, filename=filename, monitor=None, save_top_k=1, save_last=False,
                         every_n_epochs=every_n_epochs, save_on_train_epoch_end=True,
                         auto_insert_metric_name=False, enable_version_counter=False)

    @property
    def state_key(self) -> str:
        return self._generate_state_key(kind="last", filename=self.filename)

    def load_state_dict(self, state_dict) -> None:
        import warnings

        with warnings.catch_warnings():  # a resume into another directory writes its own last.ckpt there
            warnings.filterwarnings("ignore", message="The dirpath has changed")
            super().load_state_dict(state_dict)

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:
        if not isinstance(exception, (KeyboardInterrupt, SIGTERMException)) or trainer.sanity_checking:
            return
        if trainer.fast_dev_run:
            return
        path = self.format_checkpoint_name(self._monitor_candidates(trainer))
        self._save_checkpoint(trainer, path)
        self.last_model_path = path
        log.warning("stopped by %s at global step %d: saved %s (resume with ckpt_path=%s)",
                    "SIGTERM" if isinstance(exception, SIGTERMException) else "SIGINT", trainer.global_step, path, path)


class BestCheckpoint(ModelCheckpoint):
    """:class:`ModelCheckpoint` whose best-so-far survives a resume into another directory.

    Lightning reloads a monitor's best score only when the checkpoint directory is the one the
    resumed run saved into; resumed elsewhere, the first validation becomes the "best" and the
    export takes it, though the run had a better one. Here the earlier best is copied into this
    directory at the start of training and its score kept, so it stays the best until a better
    one comes (which then replaces the copy, never the earlier run's file). When the earlier
    best file is gone, tracking starts afresh, with a warning.
    """

    @property
    def state_key(self) -> str:
        # ModelCheckpoint's key: checkpoints written with either class resume into the other
        return ModelCheckpoint.__qualname__ + super().state_key[len(type(self).__qualname__):]

    def load_state_dict(self, state_dict) -> None:
        import warnings

        self._carried = None
        saved_dir = state_dict.get("dirpath", self.dirpath)
        if (saved_dir == self.dirpath or state_dict.get("monitor") != self.monitor
                or state_dict.get("best_model_score") is None or not state_dict.get("best_model_path")):
            return super().load_state_dict(state_dict)
        with warnings.catch_warnings():  # Lightning's "dirpath has changed": handled here
            warnings.simplefilter("ignore")
            super().load_state_dict(state_dict)
        self._carried = (state_dict["best_model_path"], state_dict["best_model_score"])

    def on_train_start(self, trainer, pl_module) -> None:
        super().on_train_start(trainer, pl_module)
        carried, self._carried = getattr(self, "_carried", None), None
        if carried is not None:
            self._carry_best(trainer, *carried)

    def _carry_best(self, trainer, path: str, score) -> None:
        import os
        import shutil
        from pathlib import Path

        src = Path(path)
        if not src.is_file():
            log.warning("the resumed run's best checkpoint %s is gone: the best is tracked afresh from here "
                        "(its score %s is not carried)", src, float(score))
            self.best_model_path = ""
            return
        dst = Path(self.dirpath) / src.name
        if trainer.is_global_zero and not dst.exists():
            dst.parent.mkdir(parents=True, exist_ok=True)
            tmp = dst.with_name(f".{dst.name}.tmp")
            shutil.copyfile(src, tmp)
            os.replace(tmp, dst)
        trainer.strategy.barrier()
        self.best_model_path = self.kth_best_model_path = str(dst)
        self.best_model_score = self.kth_value = score
        self.best_k_models = {str(dst): score}
        log.info("resumed into %s: the run's best checkpoint so far (%s %.4g) copied from %s", dst.parent,
                 self.monitor, float(score), src)
