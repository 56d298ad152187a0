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

__all__ = ["LastCheckpoint"]


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
