"""A filter carried from step to step: the contract of a learned model that runs so, and its
run over sequences.

lbo's window form starts a filter at each window's first fix; a filter in a control loop is
carried for the whole drive. A model that keeps :class:`SequenceModel` (``begin`` and
``advance``; KalmanNet and Split-KalmanNet, :mod:`lbo.models.kalmannet`) runs both ways: its
window form is ``advance`` looped over the window, and :func:`run` carries it over sequences
of any length, in chunks if need be (the truncated back-propagation through time of
:mod:`lbo.learn.sequence`, and the streaming of :mod:`lbo.serve.carried_runner`).
"""

from __future__ import annotations

import copy
import functools
import math
from typing import Any, NamedTuple, Protocol

import numpy as np
import torch

from lbo.models.poses import wrap_heading


class SequenceModel(Protocol):
    """A filter that runs step by step (``torch.nn.Module``s both)."""

    @property
    def units(self) -> torch.Tensor:
        """(3,) the measurement sigmas at alpha = 1 (m, m, rad): the loss's units."""
        ...

    def begin(self, y0: torch.Tensor, fix0: torch.Tensor, u0: torch.Tensor
              ) -> list[torch.Tensor]:
        """The state at a sequence's first step: its measured pose y0 (B, 3), fix0 (B,), its
        inputs u0 (B, 2); the state's first entry is the estimate, the pose first (then, for
        a model with a single-track body, :func:`carries_body`, its ``[v_y, r]``), and its
        fifth (B,) bool whether the filter has started (had a fix)."""
        ...

    def advance(self, state: list[torch.Tensor], u_prev: torch.Tensor, y: torch.Tensor,
                fix: torch.Tensor, u: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
        """The next state and the estimate (B, 3) from the inputs of the step before
        u_prev (B, 2), this step's measured pose y (B, 3), fix (B,) bool and inputs u (B, 2)
        (which a filter's prediction reads at the next step; a statistic may read them now)."""
        ...


STARTED = 4
"""The index in a :class:`SequenceModel`'s state of its (B,) flag: started at a fix."""


def covariance_of(model: Any) -> Any:
    """A :class:`SequenceModel`'s optional ``covariance(state) -> (B, 3, 3)``, its estimate's
    covariance (the pose's), or None where it gives none (KalmanNet's peers)."""
    method = getattr(model, "covariance", None)
    return method if callable(method) else None


def carries_body(model: Any) -> bool:
    """Whether a :class:`SequenceModel` carries a single-track body's ``[v_y, r]`` after the
    pose in its estimate (KalmanNet's peers with ``body="single_track"``)."""
    return bool(getattr(model, "single_track", False)) and is_sequence_model(model)


def body(state: list[torch.Tensor]) -> torch.Tensor:
    """(B, 2) the ``[v_y, r]`` a :class:`SequenceModel` that :func:`carries_body` holds after
    the pose in its state's estimate."""
    return state[0][:, 3:5]


def is_sequence_model(model: Any) -> bool:
    """Whether ``model`` (a net's inner model) keeps :class:`SequenceModel`: it can be carried
    from step to step, and trained so."""
    return callable(getattr(model, "begin", None)) and callable(getattr(model, "advance", None))


def can_carry(model: Any) -> bool:
    """Whether ``model`` (a net's inner model) can be trained carried: a
    :class:`SequenceModel`, or the window filter through its recursive form."""
    from lbo.models.filternet import WindowFilter

    return is_sequence_model(model) or isinstance(model, WindowFilter)


def sequence_model(model: Any, compiled: bool = False) -> SequenceModel:
    """``model`` (a net's inner model) as a :class:`SequenceModel`: itself, or the window
    filter's :class:`CarriedFilter` (its parameters shared); with ``compiled``, its step
    compiled (:class:`Compiled`). Keep the one it gives for as long as it runs: a new one
    compiles again."""
    out = model if is_sequence_model(model) else CarriedFilter(model)
    return Compiled(out) if compiled else out


def eager(model: SequenceModel) -> SequenceModel:
    """``model`` with its step run eagerly: a :class:`Compiled` one's own model, any other
    itself."""
    return model.model if isinstance(model, Compiled) else model


class Compiled:
    """A :class:`SequenceModel` whose step (``advance``) runs compiled by ``torch.compile``.

    A carried filter steps one sample at a time: a step of the window filter's recursive form
    is a few hundred operations on (B, 3, 3) tensors, each too small to keep a core busy, so
    eager PyTorch spends the step dispatching them, forward and backward. Compiled, they run
    fused: 4 to 5 times faster a training step on the CPU (``benchmarks/bench_carried.py``),
    the same numbers to float rounding. The first steps pay the compilation (33 s for the car
    that slips, seconds from torch's cache after that); ``begin``, once per sequence, stays
    eager, and so does a run without gradient (:func:`eager`). Needs the C++ compiler torch's
    inductor calls on the CPU."""

    def __init__(self, model: SequenceModel) -> None:
        self.model = model
        self.advance = torch.compile(model.advance)
        self.begin = model.begin
        # run's step with what it records of it (the masking of each estimate and covariance,
        # a sixth of the step outside the compiled graph), compiled as one
        self.recorded_step = torch.compile(functools.partial(recorded_step, model))

    @property
    def units(self) -> torch.Tensor:
        return self.model.units

    def __getattr__(self, name: str) -> Any:  # the model's own extras (``covariance``)
        if name == "model":  # not set yet (a copy being built): no recursion
            raise AttributeError(name)
        return getattr(self.model, name)


class CarriedFilter:
    """The window filter (:class:`lbo.models.filternet.WindowFilter`) as a
    :class:`SequenceModel`: the step of its recursive form
    (:class:`lbo.models.recursive.RecursiveFilter`, the one lbo runs it with), sharing its
    parameters and dtype, so that it trains as it runs. Not a module of its own: the filter's
    parameters stay the net's alone."""

    def __init__(self, net: Any) -> None:
        from lbo.models.recursive import RecursiveFilter

        self.step = RecursiveFilter(net, shared=True)

    @property
    def units(self) -> torch.Tensor:
        """(3,) the measurement sigmas at alpha = 1: the noise model's units."""
        return torch.exp(self.step.window_filter.log_r0)

    @staticmethod
    def _pack(out: list[torch.Tensor]) -> list[torch.Tensor]:
        # the recursive form's state (:data:`lbo.models.recursive.STATE_NAMES`), its started
        # flag also fifth, as a SequenceModel's state has it. Its u_prev is the step's own
        # input where the filter takes no gyro, a view of the sequence's inputs: a copy here,
        # since torch.compile guards on which inputs are views, and a state carried across a
        # chunk's boundary is none (a second compiled graph, 17 s more on a first run)
        return [*out[:3], out[3].clone(), out[-1] > 0.5, *out[4:]]

    @staticmethod
    def _row(y: torch.Tensor, fix: torch.Tensor) -> torch.Tensor:
        return torch.where(fix[:, None], y, torch.full_like(y, math.nan))

    def begin(self, y0: torch.Tensor, fix0: torch.Tensor, u0: torch.Tensor
              ) -> list[torch.Tensor]:
        state = self.step.initial_state(len(y0), y0.device, y0.dtype)
        _, _, *after = self.step(self._row(y0, fix0), u0, *state)
        return self._pack(after)

    def advance(self, state: list[torch.Tensor], u_prev: torch.Tensor, y: torch.Tensor,
                fix: torch.Tensor, u: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
        # u_prev is the state's own (the recursive form keeps the inputs it last read)
        pose, _, *after = self.step(self._row(y, fix), u, *state[:4], *state[5:])
        return self._pack(after), pose

    @staticmethod
    def covariance(state: list[torch.Tensor]) -> torch.Tensor:
        """(B, 3, 3) the covariance of the state's pose (the recursive form's P)."""
        return state[1][:, :3, :3]


class Carried(NamedTuple):
    """What :func:`run` gives: the estimates (B, L, 3) (NaN before a sequence's first fix,
    inf where the filter diverged), the state after the last step, the estimates'
    covariances (B, L, 3, 3) (NaN before the first fix), None for a model that gives none,
    and the single-track body's ``[v_y, r]`` (B, L, 2) where asked for and carried
    (:func:`carries_body`), else None."""

    est: torch.Tensor
    state: list[torch.Tensor]
    cov: torch.Tensor | None
    body: torch.Tensor | None = None


def run(model: SequenceModel, m: torch.Tensor, u: torch.Tensor,
        state: list[torch.Tensor] | None = None, u_prev: torch.Tensor | None = None,
        covariance: bool = True, lateral: bool = False) -> Carried:
    """The filter over L >= 1 steps of B sequences, m (B, L, 3) (NaN: no fix), u (B, L, 2):
    started at the first step when ``state`` is None, else carried on from ``state`` with
    the inputs of the step before ``u_prev`` (B, 2); see :class:`Carried`. ``covariance``:
    also stack the covariances (those of a model that gives them); off, ``cov`` is None.
    ``lateral``: also stack the carried ``[v_y, r]`` (of a model that :func:`carries_body`)."""
    if state is not None and u_prev is None:
        raise ValueError("u_prev: expected the inputs (B, 2) of the step before state")
    # step-major and contiguous: each step's (B, k) slice has the same strides whatever L is,
    # so a compiled step is compiled once, not again for every sequence length it meets
    fix = torch.isfinite(m).all(-1).transpose(0, 1).contiguous()  # a full pose: no partial fix
    y = torch.nan_to_num(m).transpose(0, 1).contiguous()
    u = u.transpose(0, 1).contiguous()
    u_prev = None if u_prev is None else u_prev.contiguous()
    keep_cov = covariance and covariance_of(model) is not None
    keep_body = lateral and carries_body(model)
    step = getattr(model, "recorded_step", None) or functools.partial(recorded_step, model)
    out, covs, bodies = [], [], []
    for k in range(m.shape[1]):  # a recurrence: each step needs the one before
        if state is None or u_prev is None:
            state = model.begin(y[0], fix[0], u[0])
            est, cov = recorded(model, state, wrap_heading(state[0][:, :3]), keep_cov)
        else:
            state, est, cov = step(state, u_prev, y[k], fix[k], u[k], keep_cov)
        out.append(est)
        if cov is not None:
            covs.append(cov)
        if keep_body:
            bodies.append(body(state))
        u_prev = u[k]
    if state is None:
        raise ValueError("m: expected at least one step, got shape (B, 0, 3)")
    return Carried(torch.stack(out, 1), state, torch.stack(covs, 1) if covs else None,
                   torch.stack(bodies, 1) if bodies else None)


def recorded(model: Any, state: list[torch.Tensor], est: torch.Tensor, covariance: bool
             ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """What :func:`run` records of a step: the estimate (B, 3), NaN before the sequence's
    first fix and inf where the filter diverged (so that a loss sees it), and with
    ``covariance`` its covariance (B, 3, 3) (NaN before the first fix), else None."""
    started = state[STARTED]
    held = est.nan_to_num(nan=math.inf, posinf=math.inf, neginf=-math.inf)
    est = torch.where(started[:, None], held, torch.full_like(est, math.nan))
    if not covariance:
        return est, None
    cov = covariance_of(model)(state)
    return est, torch.where(started[:, None, None], cov, torch.full_like(cov, math.nan))


def recorded_step(model: Any, state: list[torch.Tensor], u_prev: torch.Tensor,
                  y: torch.Tensor, fix: torch.Tensor, u: torch.Tensor, covariance: bool
                  ) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor | None]:
    """One ``advance`` of a :class:`SequenceModel` and what :func:`run` records of it
    (:func:`recorded`): the next state, the estimate and its covariance or None."""
    state, est = model.advance(state, u_prev, y, fix, u)
    return (state, *recorded(model, state, est, covariance))


def in_float64(model: Any) -> Any:
    """A float64 copy of ``model`` in eval mode, to run it carried over whole drives: positions
    of a drive far from the origin keep their millimetres, and the trained model is untouched."""
    return copy.deepcopy(model).double().eval()


def run_arrays(model: Any, m: np.ndarray, u: np.ndarray, device: str = "cpu"
               ) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`run` of a float64 :class:`SequenceModel` (:func:`in_float64`, on ``device``) over
    numpy arrays: m (G, T, 3) (NaN rows: no fix), u (G, T, 2) -> estimates (G, T, 3), NaN
    before each sequence's first fix, and the carried ``[v_y, r]`` (G, T, 2) of a model that
    :func:`carries_body` (else None). Rows past a padded sequence's end are run on and
    should be masked."""
    with torch.inference_mode():
        out = run(model, torch.as_tensor(np.asarray(m, np.float64), device=device),
                  torch.as_tensor(np.nan_to_num(np.asarray(u, np.float64)), device=device),
                  covariance=False, lateral=True)
    return out.est.cpu().numpy(), None if out.body is None else out.body.cpu().numpy()
