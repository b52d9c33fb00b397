"""The training's progress bar: Lightning's, its epoch counted as a person counts it."""

from __future__ import annotations

from typing import Any

import lightning as L
from lightning.pytorch.callbacks import TQDMProgressBar


def epoch_words(epoch: int, max_epochs: int | None, early_stopping: bool) -> str:
    """``epoch 3 of 10`` for Lightning's ``current_epoch`` 2 of ``max_epochs`` 10 (``of at
    most 10`` where early stopping may end the run sooner; no total where there is none)."""
    if max_epochs is None or max_epochs < 0:
        return f"epoch {epoch + 1}"
    return f"epoch {epoch + 1} of {'at most ' if early_stopping else ''}{max_epochs}"


class EpochBar(TQDMProgressBar):
    """Lightning's bar, which says ``Epoch 2`` from 0 without a total, saying
    ``epoch 3 of 10`` (:func:`epoch_words`). Lightning draws its own words as the epoch
    starts; these replace them at once (in a log file both lines stand)."""

    def on_train_epoch_start(self, trainer: L.Trainer, *args: Any) -> None:
        super().on_train_epoch_start(trainer, *args)
        early = trainer.early_stopping_callback is not None
        self.train_progress_bar.set_description(
            epoch_words(trainer.current_epoch, trainer.max_epochs, early))
