"""The Lightning callbacks of a study (:mod:`lbo.tune`): pruning, and Ctrl-C taken where it is
safe. Apart from lbo.tune, so that a study's config is checked without importing Lightning."""

from __future__ import annotations

import signal
import threading
from typing import Any

import lightning as L
import optuna
from lightning.pytorch.loggers import MLFlowLogger
from optuna_integration import PyTorchLightningPruningCallback

from lbo.tuning.mirror import RUN_ATTR


class Pruning(PyTorchLightningPruningCallback):
    """Optuna's Lightning pruning callback (reports ``val_loss`` after each validation epoch,
    raises :class:`optuna.TrialPruned`), which also records the trial's MLflow run."""

    def __init__(self, trial: optuna.Trial) -> None:
        super().__init__(trial, monitor="val_loss")
        self.optuna_trial = trial  # our own reference, not the parent's private attribute

    def on_fit_start(self, trainer, pl_module) -> None:
        super().on_fit_start(trainer, pl_module)
        if isinstance(trainer.logger, MLFlowLogger):
            self.optuna_trial.set_user_attr(RUN_ATTR, trainer.logger.run_id)


class Interrupts(L.Callback):
    """Ctrl-C during a study, taken where it is safe: between trials, and in a trial's fit at
    the end of a batch (raised from this callback, which Lightning handles as its own Ctrl-C).

    Python raises KeyboardInterrupt at whatever line runs when the signal comes; inside a
    database call it can leave a connection holding SQLite's write lock, and the runs that
    the study must close then wait for that lock. The first Ctrl-C is only recorded; a second
    one interrupts at once, for a study stuck where no check comes.
    """

    def __init__(self) -> None:
        self.count = 0
        self._before: Any = None

    def install(self) -> None:
        if threading.current_thread() is threading.main_thread():
            self._before = signal.signal(signal.SIGINT, self._on_signal)

    def uninstall(self) -> None:
        if self._before is not None:
            signal.signal(signal.SIGINT, self._before)
            self._before = None

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.count += 1
        if self.count > 1:
            raise KeyboardInterrupt

    def check(self) -> None:
        """Raise KeyboardInterrupt if Ctrl-C came since the study started."""
        if self.count:
            raise KeyboardInterrupt

    def on_train_epoch_start(self, *args: Any, **kwargs: Any) -> None:
        self.check()

    def on_train_batch_end(self, *args: Any, **kwargs: Any) -> None:
        self.check()

    def on_validation_batch_end(self, *args: Any, **kwargs: Any) -> None:
        self.check()
