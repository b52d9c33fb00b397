"""One step's result of an observer: its estimate, whether it is valid and why not, its
covariance and where it lies outside the training envelope."""

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

    def __new__(cls, state: np.ndarray, valid: bool, reason: str | None = None,
                cov: np.ndarray | None = None, outside: tuple[str, ...] = ()) -> Estimate:
        self = super().__new__(cls, state, valid)
        self.reason = None if valid else (reason or "the estimate is not finite")
        self.cov = np.full((3, 3), np.nan) if cov is None else cov
        self.outside = outside
        return self
