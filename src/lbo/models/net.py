"""A learned observer as one module: raw windows in, absolute states out.

It holds the feature transform, the normalisation statistics of the training set (as
buffers, so they travel in every checkpoint) and the network itself.
"""

from __future__ import annotations

import numbers
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from lbo.core.errors import LboError
from lbo.models import build_model, receiver_window
from lbo.models.carried import can_carry
from lbo.models.features import (
    check_mode,
    last_measurement,
    state_to_target,
    target_to_state,
    window_features,
)
from lbo.models.motion import bicycle_step
from lbo.models.poses import wrap_heading

CHECKPOINT_FORMAT = 1
"""The layout of a saved observer (a checkpoint's ``format``), bumped when it changes; lbo
refuses checkpoints it cannot read."""

_STD_FLOOR = 1e-6

MAX_WINDOW = 10_000
"""The longest window a net is built for (200 s at 50 Hz; lbo's longest is 400 steps). The
window sizes the streaming state and ring buffers, so a checkpoint that names a larger one is
refused before anything is allocated."""


SCALINGS = ("standard", "minmax")
"""How a net's inputs and targets are scaled (the ``normalisation`` setting)."""


def check_scaling(scaling: str, field: str = "normalisation") -> str:
    """Return ``scaling`` if it is one of :data:`SCALINGS`, else raise one line naming
    ``field``."""
    if scaling not in SCALINGS:
        raise LboError(f"{field}: expected one of {list(SCALINGS)}, got {scaling!r}")
    return scaling


class WindowNet(nn.Module):
    """Features -> normalisation -> CNN/LSTM -> de-normalisation -> absolute state.

    Parameters
    ----------
    model : ``"cnn"`` or ``"lstm"``.
    window : N, steps per window.
    features : ``"relative"`` (default), ``"frame"`` or ``"absolute"``, see
        :mod:`lbo.models.features`.
    fixes : the observer takes windows with missing fixes (NaN measurements) and its model
        reads the sixth channel ``fix``; trained with fixes dropped (``fix_rates``).
    receiver : the observer reads a receiver's windows (..., N, 11) of
        :data:`lbo.models.receiver_window.COLUMNS` (a paper window (..., N, 5) is widened to
        one), each channel with its mask, in the ``"frame"`` of its anchor; trained on a
        simulated receiver drawn per window (``receiver=``).
    motion : ``(dt (s), wheelbase (m))`` of the dead reckoning that carries a receiver
        window's anchor to its last step (:func:`lbo.models.receiver_window.anchor`); held
        as a buffer, so it travels in the checkpoint.
    carried : its model was trained carried from step to step (``tbptt``,
        :mod:`lbo.learn.sequence`) and runs so unless asked otherwise; needs a model that keeps
        :class:`lbo.models.carried.SequenceModel`.
    **model_kwargs : passed to :func:`lbo.models.build_model`.
    """

    if TYPE_CHECKING:  # buffers registered by name, for the type checker
        motion: torch.Tensor
        in_mean: torch.Tensor
        in_std: torch.Tensor
        out_mean: torch.Tensor
        out_std: torch.Tensor

    lateral_error: np.ndarray | None = None
    """(2, 2) the error of the ``[v_y, r]`` its single-track body carries, fitted on the
    validation set as it trained (:data:`lbo.models.checkpoint.LATERAL_ERROR`: per state, the
    floor and the relative part of its variance; set where it is read from a checkpoint that
    holds one): what its lateral states' variances are made of
    (:func:`lbo.serve.estimate.lateral_variance`). None: no variance."""

    def __init__(self, model: str, window: int, features: str = "relative", *,
                 fixes: bool = False, receiver: bool = False,
                 motion: tuple[float, float] = (0.02, 2.7), carried: bool = False,
                 **model_kwargs: Any) -> None:
        super().__init__()
        self.features = check_mode(features)
        if not (isinstance(window, numbers.Integral) and not isinstance(window, bool)
                and 1 <= window <= MAX_WINDOW):
            raise LboError(f"window: expected an integer number of steps in [1, {MAX_WINDOW}], "
                           f"got {window!r}")
        self.window: int = int(window)
        self.model: str = model  # its registered name: an observer of it is named <model>-N<window>
        self.fixes: bool = bool(fixes)
        self.receiver: bool = bool(receiver)
        if self.receiver and self.features != "frame":
            raise LboError(f"features: an observer that reads a receiver takes features=frame "
                           f"(its anchor's frame), got {self.features!r}")
        channels = len(receiver_window.FEATURES) if self.receiver else 6 if self.fixes else 5
        if self.fixes or self.receiver:
            model_kwargs["in_features"] = channels
        self._model_args: tuple[str, int, dict[str, Any]] = (  # for renew()
            model, int(window), dict(model_kwargs))
        try:
            self.net: nn.Module = build_model(model, window, **model_kwargs)
        except LboError as e:
            if self.receiver and str(e).startswith("model.in_features"):
                raise LboError(f"receiver: model {model!r} does not read a receiver's windows "
                               f"({e}); the CNN, the LSTM and the window filter (filternet) "
                               "do") from None
            raise
        self.carried = bool(carried)
        if self.carried and not can_carry(self.net):
            raise LboError(f"tbptt: model {model!r} cannot be carried from step to step (it has "
                           "no begin and advance, lbo.models.carried.SequenceModel); filternet, "
                           "kalmannet and split_kalmannet can")
        # a model with ``physical = True`` reads features and writes targets in metres and
        # radians; the statistics below then only scale its loss
        self.physical: bool = bool(getattr(self.net, "physical", False))
        self.anchor_heading: bool = (self.physical
                                     and bool(getattr(self.net, "anchor_heading", False)))
        needs = getattr(self.net, "feature_modes", None)
        if needs is not None and self.features not in needs:
            raise LboError(f"features: model {model!r} needs features in {list(needs)}, "
                           f"got {self.features!r}")
        if self.receiver:
            self.register_buffer("motion", torch.tensor(motion, dtype=torch.float64))
        self.register_buffer("in_mean", torch.zeros(channels, dtype=torch.float64))
        self.register_buffer("in_std", torch.ones(channels, dtype=torch.float64))
        self.register_buffer("out_mean", torch.zeros(3, dtype=torch.float64))
        self.register_buffer("out_std", torch.ones(3, dtype=torch.float64))

    def renew(self) -> None:
        """Draw its model anew, as its constructor draws it (from the global random state):
        every parameter the model's own initialisation gives, its normalisation and anchor
        motion kept (a net trained from scratch, :mod:`lbo.learn.net_fit`)."""
        name, window, kwargs = self._model_args
        device = self.in_mean.device
        self.net = build_model(name, window, **kwargs).to(device)

    def set_normalisation(self, in_mean, in_std, out_mean, out_std) -> None:
        """Channel statistics of the training windows' features (5,), (6,) or (15,) and
        targets (3,)."""
        for name, value in (("in_mean", in_mean), ("in_std", in_std),
                            ("out_mean", out_mean), ("out_std", out_std)):
            t = torch.as_tensor(value, dtype=torch.float64)
            if name.endswith("std"):
                t = t.clamp_min(_STD_FLOOR)
            getattr(self, name).copy_(t)

    def statistics(self, win: torch.Tensor, state: torch.Tensor,
                   scaling: str = "standard") -> dict[str, torch.Tensor]:
        """Per-channel offsets and scales of training windows' features and targets, as the
        ``in_mean, in_std, out_mean, out_std`` of :meth:`set_normalisation`.

        win : (B, N, C) raw windows; state : (B, 3) their true states at the last step.
        ``scaling``: ``"standard"``, the mean and standard deviation; ``"minmax"``, the
        minimum and the range, so the training set's inputs and targets lie in [0, 1] (the
        usual scaling of a sigmoid network, and the paper's likely one). The heading's target
        counts only the windows the loss teaches it on (:meth:`loss`)."""
        check_scaling(scaling)
        a = self.anchor(win)
        f = self.inputs(win, a)
        f = f.reshape(-1, f.shape[-1]).cpu()
        t = state_to_target(state, a, self.features).cpu()
        heading = t[:, 2]
        if self.receiver:
            heading = heading[receiver_window.heading_known(receiver_window.widen(win)).cpu()]
        if scaling == "minmax":
            lo_f = f.amin(0)
            lo_t = torch.stack([t[:, 0].amin(), t[:, 1].amin(), heading.amin()])
            hi_t = torch.stack([t[:, 0].amax(), t[:, 1].amax(), heading.amax()])
            return {"in_mean": lo_f, "in_std": f.amax(0) - lo_f,
                    "out_mean": lo_t, "out_std": hi_t - lo_t}
        return {"in_mean": f.mean(0), "in_std": f.std(0),
                "out_mean": torch.stack([t[:, 0].mean(), t[:, 1].mean(), heading.mean()]),
                "out_std": torch.stack([t[:, 0].std(), t[:, 1].std(), heading.std()])}

    def inputs(self, win: torch.Tensor, anchor: torch.Tensor | None = None) -> torch.Tensor:
        """The features of raw windows (B, N, 5) (or (B, N, 11), a receiver's): (B, N, C);
        ``anchor`` (B, 3): the windows' :meth:`anchor`, where the caller has it already."""
        if self.receiver:
            win = receiver_window.widen(win)
            return receiver_window.features(win, self.anchor(win) if anchor is None else anchor)
        return window_features(win, self.features, self.fixes)

    def anchor(self, win: torch.Tensor) -> torch.Tensor:
        """The pose each window's target is relative to (B, 3): its last measurement, or a
        receiver window's dead-reckoned anchor."""
        if self.receiver:
            dt, wheelbase = (float(v) for v in self.motion)
            return receiver_window.anchor(receiver_window.widen(win), dt, wheelbase)
        return last_measurement(win, self.fixes)

    def target_units(self, win: torch.Tensor, anchor: torch.Tensor | None = None
                     ) -> torch.Tensor:
        """Network output in target units (relative or absolute state). (B, N, 5) -> (B, 3);
        ``anchor`` as :meth:`inputs` takes it."""
        if anchor is None:
            anchor = self.anchor(win)
        out = self._run_model(self.inputs(win, anchor), anchor).to(win.dtype)
        return out if self.physical else out * self.out_std + self.out_mean

    def _run_model(self, x: torch.Tensor, anchor: torch.Tensor) -> Any:
        """The model's own output for the features x (B, N, C) of windows anchored at
        ``anchor`` (B, 3): (B, 3) by its contract, normalised unless it is ``physical``."""
        net_dtype = next(self.net.parameters()).dtype
        if self.physical:  # the model works in metres and radians itself
            if self.anchor_heading:  # it turns world-axes accuracies into the anchor's frame
                return self.net(x.to(net_dtype), anchor[..., 2].to(net_dtype))
            return self.net(x.to(net_dtype))
        return self.net(((x - self.in_mean) / self.in_std).to(net_dtype))

    def check_output(self, batch: int) -> None:
        """Run the model once on a batch of ``batch`` windows of the shape training gives it
        (raw windows (batch, N, 5) drawn at random, their features (batch, N, C)) and refuse,
        in one line naming the model and the shapes, an output that is not a (batch, 3)
        tensor or a model that fails on them. A plug-in's contract (docs/plugins.md) is so
        checked before any run or folder exists, not first met as a traceback inside a
        training step. Run in eval mode without gradients (no batch statistics move) and with
        a generator of its own (the global random state, which seeds the run, is left as it
        was)."""
        draw = torch.Generator().manual_seed(0)
        win = torch.randn(batch, self.window, 5, generator=draw, dtype=torch.float64)
        anchor = self.anchor(win)
        x = self.inputs(win, anchor)
        expected = (batch, 3)
        training = self.net.training
        self.net.eval()
        try:
            with torch.no_grad():
                out = self._run_model(x, anchor)
        except Exception as e:  # the plug-in's own failure on the contract's input: one line
            why = " ".join(str(e).split())[:300]
            raise LboError(f"model: model {self.model!r} fails on a batch of windows "
                           f"{tuple(x.shape)} ({type(e).__name__}: {why}); expected an output "
                           f"of shape {expected} (docs/plugins.md)") from None
        finally:
            self.net.train(training)
        got = (f"shape {tuple(out.shape)}" if isinstance(out, torch.Tensor)
               else f"type {type(out).__name__}")
        if got != f"shape {expected}":
            raise LboError(f"model: model {self.model!r} gives an output of {got} on a batch "
                           f"of windows {tuple(x.shape)}; expected {expected} (the state x, y, "
                           "psi of each window; docs/plugins.md)")

    def forward(self, win: torch.Tensor) -> torch.Tensor:
        """Estimated state ``[x, y, psi]`` at each window's last step. (B, N, 5) -> (B, 3)."""
        a = self.anchor(win)  # once: a receiver window's is a dead reckoning over it
        return target_to_state(self.target_units(win, a), a, self.features)

    def loss(self, win: torch.Tensor, state: torch.Tensor,
             weight: torch.Tensor | None = None) -> torch.Tensor:
        """MSE in normalised target units, the heading residual wrapped.

        state : (B, 3) true states; weight : (B,) per-window weights (None: equal), the loss
        is their weighted mean.
        """
        a = self.anchor(win)
        target = state_to_target(state, a, self.features)
        r = wrap_heading(self.target_units(win, a) - target)
        if self.receiver:  # a window without any heading tells none: its heading is not taught
            known = receiver_window.heading_known(receiver_window.widen(win))
            r = torch.cat([r[:, :2], torch.where(known[:, None], r[:, 2:], 0.0)], 1)
        return self._weighted((r / self.out_std) ** 2, weight)

    def next_fix_loss(self, win: torch.Tensor, after: torch.Tensor,
                      weight: torch.Tensor | None = None, dt: float = 0.02,
                      wheelbase: float = 2.7) -> torch.Tensor:
        """The self-supervised loss: no truth read. Each window's estimate, moved one step
        by the kinematic bicycle, against the fix of that next step, which the window does not
        hold; its MSE in the units of :meth:`loss` over the channels the fix holds.

        after : (B, 5) the next step's fix ``[x_m, y_m, psi_m]`` (NaN where it has none) and
        the window's last inputs ``[V, delta]``. The fix's noise is its own, apart from
        everything the window reads, so the loss is the estimate's error against the truth
        plus a constant (the fix's noise and one step of the process noise): its minimum is
        the truth-trained one's (the kinematic bicycle is linear in x and y, nearly so in psi
        over a step)."""
        moved = bicycle_step(self(win), after[:, 3], after[:, 4], dt, wheelbase)
        r = wrap_heading(moved - after[:, :3])
        held = torch.isfinite(r)
        return self._weighted(torch.where(held, r / self.out_std, 0.0) ** 2, weight,
                              held.sum(1).clamp(min=1) / 3)

    @staticmethod
    def _weighted(se: torch.Tensor, weight: torch.Tensor | None,
                  share: torch.Tensor | float = 1.0) -> torch.Tensor:
        """Squared errors (B, 3) as one loss: each window's mean over its channels (``share``
        (B,): the share of them it holds), weighted over windows (None: equally)."""
        per = se.mean(1) / share
        if weight is None:
            return per.mean().float()
        return ((per * weight).sum() / weight.sum()).float()
