"""The training's progress bar: Lightning's, its epoch counted as a person counts it, and
the run's training time estimated from its first batches."""

from __future__ import annotations

import math
import time
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import TQDMProgressBar

from lbo.learn.eta import duration

ESTIMATE_AFTER = 10
"""Batches of a run's first epoch after which its training time is said (the first batch,
which warms up, is not timed unless it is the only one)."""


def epoch_words(epoch: int, max_epochs: int | None, early_stopping: bool) -> str:
    """``epoch 3 of 10`` for Lightning's ``current_epoch`` 2 of ``max_epochs`` 10 (``of at
    most 10`` where early stopping may end the run sooner; no total where there is none)."""
    if max_epochs is None or max_epochs < 0:
        return f"epoch {epoch + 1}"
    return f"epoch {epoch + 1} of {'at most ' if early_stopping else ''}{max_epochs}"


def estimate_words(batch_s: float, batches: int, epochs: int, timed: int,
                   early_stopping: bool) -> str:
    """The line that says how long a run's training will take: ``epochs`` epochs of
    ``batches`` batches at ``batch_s`` seconds a batch, the mean of ``timed`` of its first."""
    total = epochs * batches * batch_s
    return (f"estimate: {epochs} epoch{'s' if epochs != 1 else ''} x {batches} batches x "
            f"{batch_s:.3g} s (timed over {timed} of its first batches): "
            + (f"about {duration(total)}" if total >= 1 else "under 1 s") + " of training"
            + (", less if early stopping ends it" if early_stopping else "")
            + "; validation and the final evaluation come on top")


class EpochBar(TQDMProgressBar):
    """Lightning's bar, which says ``Epoch 2`` from 0 without a total, saying
    ``epoch 3 of 10`` (:func:`epoch_words`). Lightning draws its own words as the epoch
    starts; these replace them at once (in a log file both lines stand). After the first
    :data:`ESTIMATE_AFTER` batches of a run (or its first epoch, if shorter) it says how long
    the run's training will take (:func:`estimate_words`), from the time they took."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._first: int | None = None  # the epoch this fit starts at (a resumed run's > 0)
        self._clock: list[float] = []  # perf_counter at batch 0's start, then at its end

    def on_train_start(self, trainer: L.Trainer, *args: Any) -> None:
        super().on_train_start(trainer, *args)
        self._first, self._clock = trainer.current_epoch, []

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule,
                             batch: Any, batch_idx: int) -> None:
        super().on_train_batch_start(trainer, pl_module, batch, batch_idx)
        if batch_idx == 0 and trainer.current_epoch == self._first:
            self._clock = [time.perf_counter()]

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule,
                           outputs: Any, batch: Any, batch_idx: int) -> None:
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
        if trainer.current_epoch != self._first or not self._clock:
            return
        now = time.perf_counter()
        if batch_idx == 0:
            self._clock.append(now)
        batches = trainer.num_training_batches
        if not math.isfinite(batches) or batches < 1:
            return  # an iterable without a length: nothing to multiply
        if batch_idx + 1 == min(ESTIMATE_AFTER, int(batches)):
            begin, warm = self._clock
            batch_s = (now - warm) / batch_idx if batch_idx else warm - begin
            epochs = trainer.max_epochs - trainer.current_epoch \
                if trainer.max_epochs is not None and trainer.max_epochs > 0 else 1
            self.print(estimate_words(batch_s, int(batches), epochs, max(batch_idx, 1),
                                      trainer.early_stopping_callback is not None))
            self._clock = []

    def on_train_epoch_start(self, trainer: L.Trainer, *args: Any) -> None:
        super().on_train_epoch_start(trainer, *args)
        early = trainer.early_stopping_callback is not None
        self.train_progress_bar.set_description(
            epoch_words(trainer.current_epoch, trainer.max_epochs, early))
