"""The LightningModule: loss, optimiser and logging around an :class:`WindowNet`."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, cast

import lightning as L
import torch
from lightning.pytorch.core.optimizer import LightningOptimizer
from torch.optim.lr_scheduler import LRScheduler

from lbo.core import plugins
from lbo.core.checks import SCHEDULES
from lbo.core.errors import TrainingDiverged
from lbo.learn.sequence import from_batch, train_batch
from lbo.learn.sequence import loss as sequence_loss
from lbo.models.carried import SequenceModel, eager, run, sequence_model
from lbo.models.net import CHECKPOINT_FORMAT, WindowNet

__all__ = ["CHECKPOINT_FORMAT", "SCHEDULES", "TrainingModule"]


class TrainingModule(L.LightningModule):
    """Trains an observer with MSE on its (normalised, heading-wrapped) targets.

    Parameters
    ----------
    model : ``{"name": "cnn"|"lstm", **hyperparameters}``.
    window : N.
    features : ``"relative"``, ``"frame"`` or ``"absolute"``.
    fixes : the observer takes missing fixes (a sixth, ``fix`` channel), see WindowNet.
    receiver : the observer reads a receiver's windows, see WindowNet.
    optimizer : a partial optimiser (``params -> Optimizer``), e.g. from Hydra's
        ``_partial_: true``; Adam(lr=1e-3) when None.
    meta : what a checkpoint must carry to rebuild the observer elsewhere (dt, wheelbase,
        noise preset, data hash, ...); stored in the hyperparameters.
    lr_schedule : ``"constant"``, or ``"cosine"``: the learning rate falls along a half
        cosine to zero over every step the trainer will take (``max_epochs`` of them).
    net : the :class:`WindowNet` to train, already built from the arguments above
        (:func:`lbo.learn.builders.build`); built here when None.
    tbptt : None trains windows. An integer L trains the net's model carried from step to
        step (:class:`lbo.models.carried.SequenceModel`) by truncated back-propagation
        through time: each batch's windows, with the true states of every step, cut into
        chunks of L steps, the state carried from chunk to chunk, one optimiser step per
        chunk (:func:`lbo.learn.sequence.train_batch`; Lightning's manual optimisation).
    clip : the gradient norm each chunk's step is clipped to (the trainer's
        ``gradient_clip_val``, which Lightning applies only to automatic optimisation).
    nll : with ``tbptt``, the weight of the Gaussian NLL of the errors under the filter's own
        covariance, added to each chunk's MSE (:func:`lbo.learn.sequence.loss`); the
        validation loss stays the MSE.
    compiled : with ``tbptt``, run the carried filter's step compiled
        (:class:`lbo.models.carried.Compiled`): the same numbers to rounding, a few times
        faster a step on the CPU.
    next_fix : ``(dt, wheelbase)``: train and validate by the self-supervised loss
        (:meth:`WindowNet.next_fix_loss`), the batches holding each window's next fix in place
        of its truth; None: the MSE against the truth.
    """

    def __init__(self, model: dict[str, Any], window: int, features: str = "relative", *,
                 optimizer: Callable[..., torch.optim.Optimizer] | None = None,
                 meta: dict[str, Any] | None = None, lr_schedule: str = "constant",
                 fixes: bool = False, net: WindowNet | None = None,
                 receiver: bool = False, tbptt: int | None = None,
                 clip: float | None = None, nll: float = 0.0, compiled: bool = False,
                 next_fix: tuple[float, float] | None = None) -> None:
        super().__init__()
        self.save_hyperparameters(ignore=["optimizer", "lr_schedule", "net", "clip", "compiled",
                                          "next_fix"])
        self.lr_schedule = lr_schedule
        self.hparams["format"] = CHECKPOINT_FORMAT
        # the package that registers the model: a machine without it is told what to install
        self.hparams["provider"] = plugins.provider("model", model["name"])
        kwargs = {k: v for k, v in model.items() if k != "name"}
        self.observer = net if net is not None else WindowNet(
            model["name"], window, features, fixes=fixes, receiver=receiver,
            carried=tbptt is not None, **kwargs)
        self.optimizer_factory = optimizer
        self.tbptt, self.clip, self.nll = tbptt, clip, float(nll)
        self.compiled = bool(compiled)
        self.next_fix = next_fix
        # the chunks' optimiser steps are taken here, not by Lightning
        self.automatic_optimization = tbptt is None
        self._loss_sum: torch.Tensor | float = 0.0
        self._loss_count = 0
        self._dropped = 0  # sequences dropped in this epoch: their carried filter diverged
        self._val_finite: torch.Tensor | bool = True
        # whether the first training batch's loss, before any update, was finite: where it was
        # not, the model gives no finite output with its initial weights, and no learning
        # rate mends that
        self._first_finite: bool | None = None

    def forward(self, win: torch.Tensor) -> torch.Tensor:
        return self.observer(win)

    @functools.cached_property
    def carried(self) -> SequenceModel:
        """The observer's model as the filter carried from step to step (``tbptt``): one for
        the module's life, so that a compiled step compiles once. Cached in the instance's
        ``__dict__``, past nn.Module's attribute hook: KalmanNet's peers are their own
        SequenceModel, and registered as a submodule their weights would join the
        checkpoint's state a second time."""
        return sequence_model(self.observer.net, self.compiled)

    def training_step(self, batch, batch_idx: int) -> torch.Tensor:
        if self.tbptt is not None:
            return self._carried_step(batch)
        loss = self._window_loss(batch)
        if self._first_finite is None:  # one sync, on the first batch alone
            self._first_finite = bool(torch.isfinite(loss))
        # summed here and logged once per epoch: self.log on every step costs about 1 ms,
        # 10 % of a small CNN step on the CPU (benchmarks/bench_train.py)
        n = len(batch[1])
        self._loss_sum = self._loss_sum + loss.detach() * n
        self._loss_count += n
        return loss

    def _window_loss(self, batch) -> torch.Tensor:
        """A batch of windows' loss: against the truth, or against the next fixes."""
        if self.next_fix is None:
            return self.observer.loss(*batch)
        win, after, weight = batch
        return self.observer.next_fix_loss(win, after, weight, *self.next_fix)

    def _carried_step(self, batch) -> torch.Tensor:
        """One batch of windows trained carried, chunk by chunk (see ``tbptt``); returns the
        mean loss of the chunks that took a step (not finite where none did). The sequences
        whose filter diverged are dropped and counted (``train_dropped_sequences``)."""
        # one optimiser (configure_optimizers), so Lightning hands back one, not a list
        opt = cast(LightningOptimizer, self.optimizers())

        def step(loss: torch.Tensor) -> None:
            opt.zero_grad()
            self.manual_backward(loss)
            if self.clip:
                self.clip_gradients(opt.optimizer, gradient_clip_val=self.clip,
                                    gradient_clip_algorithm="norm")
            opt.step()

        m, u, z, weight = from_batch(batch, next(self.parameters()).dtype)
        fit = train_batch(self.carried, m, u, z, cast(int, self.tbptt), step, weight,
                          self.nll)  # set: this step is tbptt's
        finite = [v for v in fit.losses if math.isfinite(v)]
        mean = torch.tensor(sum(finite) / len(finite) if finite else math.nan)
        if self._first_finite is None:
            self._first_finite = bool(finite) and len(finite) == len(fit.losses)
        self._dropped += fit.dropped
        schedule = cast(LRScheduler | None, self.lr_schedulers())  # one, or none: constant
        if schedule is not None:  # one step per batch, as the automatic loop takes them
            schedule.step()
        self._loss_sum = self._loss_sum + mean * len(m)
        self._loss_count += len(m)
        return mean

    def on_train_epoch_end(self) -> None:
        if self._loss_count:
            self._check_finite(self._loss_sum, "train_loss")
            self.log("train_loss", self._loss_sum / self._loss_count, prog_bar=True)
        if self.tbptt is not None:
            self.log("train_dropped_sequences", float(self._dropped))
        self._loss_sum, self._loss_count, self._dropped = 0.0, 0, 0

    def validation_step(self, batch, batch_idx: int) -> None:
        if self.tbptt is None:
            loss = self._window_loss(batch)
        else:  # each window carried through, from its first fix, its step eager: compiled,
            # a validation (no gradient, no covariance, its own batch size) is a graph of its
            # own, 25 s to compile on a first run for 1 s saved a validation (the car that slips)
            m, u, z, weight = from_batch(batch, next(self.parameters()).dtype)
            model = eager(self.carried)
            loss = sequence_loss(run(model, m, u, covariance=False).est, z, model.units,
                                 weight)
        self._val_finite = torch.isfinite(loss) & self._val_finite
        self.log("val_loss", loss, on_step=False, on_epoch=True, prog_bar=True,
                 batch_size=len(batch[1]))

    def on_validation_epoch_end(self) -> None:
        # before ModelCheckpoint's on_validation_end: a NaN model is never saved as best.ckpt
        finite, self._val_finite = self._val_finite, True
        self._check_finite(finite, "val_loss")

    def _check_finite(self, value: torch.Tensor | float | bool, name: str) -> None:
        """Raise TrainingDiverged when ``value`` (a loss, or a finiteness flag) is NaN/inf."""
        ok = bool(value) if isinstance(value, bool) or (
            isinstance(value, torch.Tensor) and value.dtype == torch.bool) \
            else math.isfinite(float(value))
        if ok:
            return
        if self._first_finite is False:
            raise TrainingDiverged(
                f"training cannot start: {name} was NaN or inf before any update (the first "
                f"training batch's loss too): model {self.observer.model!r} gives no finite "
                "output (or loss) on these inputs with its initial weights; check its forward "
                "and the data (a smaller optimizer.lr cannot help)")
        lr = self.trainer.optimizers[0].param_groups[0]["lr"] if self.trainer.optimizers \
            else float("nan")
        raise TrainingDiverged(
            f"training diverged: {name} became NaN or inf in epoch {self.current_epoch} "
            f"(learning rate {lr:g}); no checkpoint of the diverged weights is kept: lower "
            "optimizer.lr")

    def configure_optimizers(self) -> Any:
        # a net may ask for groups with their own rate, a multiple ``lr_scale`` of the
        # optimiser's (the window filter's single-track body)
        groups = getattr(self.observer.net, "param_groups", None)
        params = groups() if callable(groups) else self.parameters()
        opt: torch.optim.Optimizer
        if self.optimizer_factory is None:
            opt = torch.optim.Adam(params, lr=1e-3, fused=True)
        else:
            opt = self.optimizer_factory(params=params)
        for group in opt.param_groups:
            group["lr"] = group["lr"] * group.get("lr_scale", 1.0)
        if self.lr_schedule == "constant":
            return opt
        total = max(int(self.trainer.estimated_stepping_batches), 1)
        cosine = torch.optim.lr_scheduler.LambdaLR(
            opt, lambda step: 0.5 * (1.0 + math.cos(math.pi * min(step, total) / total)))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": cosine, "interval": "step"}}

