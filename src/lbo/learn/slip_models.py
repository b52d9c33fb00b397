"""What each side-slip observer brings to its training (:mod:`lbo.learn.slip_run`): its
settings, its data, its Lightning module and its checkpoint.

- ``model=slip_gru`` (:mod:`lbo.models.slip`): windows of the last ``model.window`` rows and the
  prior's estimate, the loss the squared error of the corrected beta.
- ``model=slip_filter`` (:mod:`lbo.models.slip_filter`): pieces of ``model.sequence`` rows,
  each filtered from its first row, the loss the squared error of the filter's beta after its
  first ``model.warmup`` rows (the filter starting afresh on each piece).

Both losses are in degrees squared and both report ``val_loss``, beta's RMSE (deg) on the
validation rows the loss reads.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from omegaconf import DictConfig

from lbo.core.checks import integer, number
from lbo.core.errors import LboError
from lbo.models import slip, slip_filter
from lbo.models.slip import UNIT, Prior, SlipNet, SlipObserver
from lbo.models.slip_filter import FilterObserver, LateralFilter

if TYPE_CHECKING:  # Lightning takes seconds to import: only a training run needs it
    import lightning as L

Observer = SlipObserver | FilterObserver
"""A side-slip observer: ``.prior``, ``.run(vx, delta, y, prior=...)``."""

PARAMETERS = slip_filter.SIDE_SLIP
"""Each side-slip observer's ``model`` settings besides ``name``."""


def check(model: DictConfig) -> None:
    """The model's own settings (one line naming the field)."""
    if model.name == slip.NAME:
        integer(model.window, "model.window", 2, form="an integer >= 2 (rows of a window)")
        integer(model.layers, "model.layers", 1)
    else:
        integer(model.sequence, "model.sequence", 2,
                form="an integer >= 2 (rows of a training sequence)")
        integer(model.warmup, "model.warmup", 0)
        if model.warmup >= model.sequence:
            raise LboError(f"model.warmup: expected fewer rows than model.sequence "
                           f"({model.sequence}), got {model.warmup}")
    integer(model.hidden, "model.hidden", 1)
    number(model.prior_gain, "model.prior_gain", low=0.0, low_open=True)


def run_name(model: DictConfig) -> str:
    return f"{slip.NAME}-N{model.window}" if model.name == slip.NAME else slip_filter.NAME


load = slip_filter.load_any


@dataclass(frozen=True, kw_only=True)
class Made:
    """A run's module, its training and validation data (tensors), the prior, and what the
    training learns from in words."""

    module: L.LightningModule
    train: tuple[torch.Tensor, torch.Tensor]
    val: tuple[torch.Tensor, torch.Tensor]
    prior: Prior
    what: str
    window: int = 0

    def observer(self) -> Observer:
        """The observer of the module's weights as they are (a run without a checkpoint)."""
        net = self.module.net.cpu()
        if isinstance(net, SlipNet):
            return SlipObserver(net, self.window, self.prior)
        assert isinstance(net, LateralFilter)
        return FilterObserver(net)


def make(cfg: DictConfig, optimizer: Any, start: Observer | None) -> Made:
    """The module and data of ``cfg.model`` on ``cfg.data``; ``start``: an observer of the same
    kind and shape to fine-tune (its weights, prior and normalisation kept)."""
    from lbo.learn import slip_data

    model, gain = cfg.model, float(cfg.model.prior_gain)
    if start is not None and shape(start) != shape_of(model):
        raise LboError(f"init_from: {cfg.init_from} is {_words(shape(start))}; expected "
                       f"{_words(shape_of(model))}")
    if model.name == slip.NAME:
        sets = slip_data.sets(cfg.data, int(model.window), gain, start.prior if start else None)
        net = SlipNet(int(model.hidden), int(model.layers))
        if isinstance(start, SlipObserver):  # its normalisation: the windows are its prior's
            net.load_state_dict(start.net.state_dict())
        else:
            net.set_normalisation(sets.train[0][:, -1])  # each row once: each window's last
        module = _gru_module(net, int(model.window), sets.prior, optimizer)
        what = f"{len(sets.train[0])} windows of {model.window} rows"
    else:
        sets = slip_data.sequences(cfg.data, int(model.sequence), gain,
                                   start.prior if start else None)
        lateral = LateralFilter(sets.prior, int(model.hidden))
        if isinstance(start, FilterObserver):
            lateral.load_state_dict(start.net.state_dict())
        module = _filter_module(lateral, int(model.warmup), float(cfg.get("nll") or 0.0),
                                optimizer)
        what = (f"{len(sets.train[0])} sequences of {model.sequence} rows, each filtered "
                f"afresh, its first {model.warmup} rows unscored")
    train, val = ((torch.from_numpy(a), torch.from_numpy(b)) for a, b in (sets.train, sets.val))
    return Made(module=module, train=train, val=val, prior=sets.prior, what=what,
                window=int(model.get("window", 0)))


def shape(observer: Observer) -> tuple[Any, ...]:
    if isinstance(observer, SlipObserver):
        return (slip.NAME, observer.window, observer.net.gru.hidden_size,
                observer.net.gru.num_layers)
    return (slip_filter.NAME, observer.net.hidden)


def shape_of(model: DictConfig) -> tuple[Any, ...]:
    if model.name == slip.NAME:
        return (slip.NAME, int(model.window), int(model.hidden), int(model.layers))
    return (slip_filter.NAME, int(model.hidden))


def _words(shape: tuple[Any, ...]) -> str:
    if shape[0] == slip.NAME:
        return f"model={shape[0]} with window {shape[1]}, hidden {shape[2]}, layers {shape[3]}"
    return f"model={shape[0]} with hidden {shape[1]}"


def _rmse_module(hparams: dict[str, Any], net: torch.nn.Module, optimizer: Any, error: Any,
                 nll: float = 0.0) -> L.LightningModule:
    """A module whose loss is the mean of the error squared (deg^2), ``error(net, batch)`` ->
    (the error (deg), its variance (deg^2) or None), plus ``nll`` times the mean Gaussian
    negative log-likelihood of the error under that variance; ``val_loss`` is the error's
    root mean square over the validation set (deg)."""
    import lightning as L

    class Module(L.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            self.save_hyperparameters(hparams)  # plain numbers only: read with weights_only
            self.net = net
            self._sums = torch.zeros(2)

        def training_step(self, batch: list[torch.Tensor], batch_idx: int) -> torch.Tensor:
            err, var = error(self.net, batch)
            loss = torch.mean(err**2)
            if nll > 0 and var is not None:  # the covariance trained to say the error's size
                loss = loss + nll * torch.mean(0.5 * (torch.log(var) + err**2 / var))
            self.log("train_loss", loss, on_step=False, on_epoch=True, batch_size=len(batch[0]))
            return loss

        def on_validation_epoch_start(self) -> None:
            self._sums = torch.zeros(2)

        def validation_step(self, batch: list[torch.Tensor], batch_idx: int) -> None:
            err = error(self.net, batch)[0].detach().cpu().double()
            self._sums += torch.stack([torch.sum(err**2), torch.tensor(float(err.numel()))])

        def on_validation_epoch_end(self) -> None:
            self.log("val_loss", torch.sqrt(self._sums[0] / self._sums[1].clamp(min=1.0)),
                     prog_bar=True)

        def configure_optimizers(self) -> Any:
            return optimizer(self.parameters())

    return Module()


def _gru_module(net: SlipNet, window: int, prior: Prior, optimizer: Any) -> L.LightningModule:
    """The side-slip network's module: windows in, the correction's error (deg) out."""
    def error(net: SlipNet, batch: list[torch.Tensor]) -> tuple[torch.Tensor, None]:
        w, target = batch  # the target: the reference less the prior
        return (net(w) - target) / UNIT, None

    return _rmse_module({
        "name": slip.NAME, "hidden": net.gru.hidden_size, "layers": net.gru.num_layers,
        "window": window, "prior": prior.as_dict()}, net, optimizer, error)


def _filter_module(net: LateralFilter, warmup: int, nll: float, optimizer: Any
                   ) -> L.LightningModule:
    """The learned filter's module: sequences in, beta's error (deg) after ``warmup`` rows and
    the filter's variance of it (deg^2), its NLL weighed by ``nll``."""
    def error(net: LateralFilter, batch: list[torch.Tensor]
              ) -> tuple[torch.Tensor, torch.Tensor]:
        rows, beta = batch
        x, P = net(rows[..., 0], rows[..., 1], rows[..., 2:4])
        return ((x[:, warmup:, 0] - beta[:, warmup:]) / UNIT, P[:, warmup:, 0, 0] / UNIT**2)

    return _rmse_module({
        "name": slip_filter.NAME, "hidden": net.hidden, "prior": net.prior.as_dict()},
        net, optimizer, error, nll)

