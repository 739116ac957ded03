"""Training callbacks: a ``last.ckpt`` that is always current."""

from __future__ import annotations

import logging
from pathlib import Path

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint

__all__ = ["LastCheckpoint"]

log = logging.getLogger(__name__)


class LastCheckpoint(ModelCheckpoint):
    """Writes ``<dirpath>/last.ckpt`` every ``every_n_train_steps`` steps, when training ends and on Ctrl-C.

    Lightning's ``ModelCheckpoint(save_last=True)`` saves only at its own triggers, so a run that stops at
    ``max_steps`` in the middle of an epoch, or is interrupted, would leave a stale ``last.ckpt``. This one
    also saves in ``on_train_end`` and on ``KeyboardInterrupt`` (which reaches every DDP process, so the
    collective save cannot hang), making ``last.ckpt`` the state to resume from with ``ckpt_path=last``.
    """

    def __init__(self, dirpath: str, every_n_train_steps: int = 100):
        super().__init__(
            dirpath=dirpath,
            save_top_k=0,
            save_last=True,
            every_n_train_steps=int(every_n_train_steps),
            enable_version_counter=False,
        )

    @property
    def last_path(self) -> Path:
        return Path(self.dirpath) / f"{self.CHECKPOINT_NAME_LAST}{self.FILE_EXTENSION}"

    def _save_now(self, trainer: L.Trainer) -> None:
        if trainer.global_step > 0 and (
            trainer.global_step != self._last_global_step_saved or not self.last_path.exists()
        ):
            trainer.save_checkpoint(str(self.last_path))
            self._last_global_step_saved = trainer.global_step
            self.last_model_path = str(self.last_path)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._save_now(trainer)

    def on_exception(
        self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException
    ) -> None:
        if isinstance(exception, KeyboardInterrupt) and trainer.state.fn == "fit":
            log.warning("interrupted at step %d: writing %s", trainer.global_step, self.last_path)
            self._save_now(trainer)
