"""What an observer gives: one step's :class:`Estimate` (its estimate, whether it is valid and
why not, its covariance, its lateral states and where it lies outside the training envelope)
and a whole log's :class:`Estimates`."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class _Pair(NamedTuple):
    state: np.ndarray
    valid: bool


class Estimate(_Pair):
    """One step's result: ``state`` (3,) ``[x, y, psi]`` (m, m, rad; psi in (-pi, pi]) and
    ``valid``; unpacks as ``state, valid``. ``reason`` (not unpacked) says why an estimate is
    not valid, None when it is:

    - ``"no position fix yet"``: before the first fix (state NaN);
    - ``"window not yet full (k of N steps): the EKF's estimate"``: a CNN's or LSTM's first
      N-1 steps;
    - ``"no fix in the last N steps (... s): ..."``: a learned observer trained with
      ``fix_rates`` whose window holds no fix has nothing to anchor its estimate to (state
      NaN); estimates resume with the next fix;
    - ``"no heading in the last N steps (... s)..."``: a net that reads a single antenna's
      receiver, on a car that has stood or crept that long (a window filter: since the log
      began; after its first estimate it carries its own through a stop, :mod:`lbo.serve.carry`);
    - ``"the network's estimate is not finite ..."``: a net with NaN or inf weights;
    - ``"outside the training envelope: ..."``: with ``envelope_mode="mark"``, a sample beyond
      what a learned observer was trained on (:mod:`lbo.models.envelope`).
    """

    reason: str | None = None
    cov: np.ndarray
    """(3, 3) covariance of ``state`` (m^2, m rad, rad^2): the filter's own P; NaN for an
    observer that gives none (the CNN and the LSTM)."""
    outside: tuple[str, ...] = ()
    """The fields of the training envelope this sample lies outside (``("speed",)``), in
    every envelope mode but ``"off"``; () inside, or without an envelope."""
    lateral: np.ndarray
    """(3,) the lateral states ``[beta, v_y, r]`` (rad, m/s, rad/s; :data:`lbo.sim.columns.
    LATERAL_ESTIMATE`) of an observer that carries a single-track body
    (:attr:`lbo.Observer.carries_lateral`); NaN for one that carries none, and where ``state``
    is NaN."""
    lateral_var: np.ndarray
    """(3,) the variances of ``lateral`` (rad^2, m^2/s^2, rad^2/s^2;
    :func:`lateral_variance`) where the observer's checkpoint holds its body's error; NaN
    elsewhere."""

    def __new__(cls, state: np.ndarray, valid: bool, reason: str | None = None,
                cov: np.ndarray | None = None, outside: tuple[str, ...] = (),
                lateral: np.ndarray | None = None,
                lateral_var: np.ndarray | None = None) -> Estimate:
        self = super().__new__(cls, state, valid)
        self.reason = None if valid else (reason or "the estimate is not finite")
        self.cov = np.full((3, 3), np.nan) if cov is None else cov
        self.outside = outside
        self.lateral = np.full(3, np.nan) if lateral is None else lateral
        self.lateral_var = np.full(3, np.nan) if lateral_var is None else lateral_var
        return self


class _Track(NamedTuple):
    state: np.ndarray
    valid: np.ndarray


class Estimates(_Track):
    """A whole log's estimates (:meth:`lbo.Observer.run`): ``state`` (T, 3) ``[x, y, psi]``
    (psi in (-pi, pi]) and ``valid`` (T,) bool; unpacks as ``state, valid``. Also, not
    unpacked:"""

    cov: np.ndarray
    """(T, 3, 3) each estimate's covariance (the filter's P); NaN where the observer gives
    none (a CNN's or LSTM's windows) and on rows that are not valid."""
    lateral: np.ndarray
    """(T, 3) ``[beta, v_y, r]`` per row, as :attr:`Estimate.lateral`."""
    lateral_var: np.ndarray
    """(T, 3) their variances per row, as :attr:`Estimate.lateral_var`."""

    def __new__(cls, state: np.ndarray, valid: np.ndarray, cov: np.ndarray,
                lateral: np.ndarray, lateral_var: np.ndarray) -> Estimates:
        self = super().__new__(cls, state, valid)
        self.cov, self.lateral, self.lateral_var = cov, lateral, lateral_var
        return self


def side_slip(body: np.ndarray | None, speed: np.ndarray,
              pose: np.ndarray | None = None) -> np.ndarray:
    """The lateral states (..., 3) ``[beta, v_y, r]`` of a carried single-track body (..., 2)
    ``[v_y, r]`` at the logged speed (...,) of the same rows: beta = atan2(v_y, V), the side
    slip at the centre of gravity. ``body`` None (nothing carried): all NaN; NaN too where
    ``pose`` (..., 3), the estimate of the row, is not finite (no estimate yet)."""
    if body is None:
        return np.full((*np.shape(speed), 3), np.nan)
    out = np.concatenate([np.arctan2(body[..., :1], speed[..., None]), body], -1)
    return out if pose is None else np.where(np.isfinite(pose).all(-1, keepdims=True), out,
                                             np.nan)


def lateral_variance(error: np.ndarray | None, lateral: np.ndarray,
                     speed: np.ndarray) -> np.ndarray:
    """The variances (..., 3) of lateral states (..., 3) ``[beta, v_y, r]`` (as
    :func:`side_slip` gives them, at the logged speed (...,)) of a single-track body whose
    error is ``error`` (2, 2) (the checkpoint's, fitted on the validation set:
    :func:`lbo.scoring.lateral.body_error`): row i of it, for v_y and r, holds a floor and a
    relative part, var_i = floor_i + part_i state_i^2 (a body whose tyres are off is off in
    proportion to how hard the car corners). Beta's is v_y's carried through
    beta = atan2(v_y, V) to first order, (V / (V^2 + v_y^2))^2 var(v_y). NaN where ``error``
    is None and where ``lateral`` is."""
    lateral = np.asarray(lateral, dtype=float)
    if error is None:
        return np.full(lateral.shape, np.nan)
    v_y, r, v = lateral[..., 1], lateral[..., 2], np.asarray(speed, dtype=float)
    var_vy = error[0, 0] + error[0, 1] * v_y ** 2
    slope = v / (v ** 2 + v_y ** 2)  # d beta / d v_y
    return np.stack([slope ** 2 * var_vy, var_vy, error[1, 0] + error[1, 1] * r ** 2], -1)
