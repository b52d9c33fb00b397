"""What a runner reads: a log's rows as each observer takes them, and one sample's
measurements checked as a log's row is.

- :func:`as_arrays`: measurements given typed, as the arrays the checks read;
- :func:`sampled`: one sample's :class:`~lbo.sim.measurements.Measurements`, checked;
- :func:`bicycle_rows`: the classical filters' rows (:data:`lbo.filters.measure.CHANNELS`),
  the course's variance allowing for the bicycle's turn rate;
- :func:`receiver_rows`: a receiver net's rows, those and the gyro's ``r_m``;
- :func:`window_series`: the columns of a net's windows.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lbo.core.errors import LboError
from lbo.filters import measure
from lbo.logs.checks import check_receiver
from lbo.sim.columns import RECEIVER
from lbo.sim.measurements import Measurements


def sampled(k: int, m: np.ndarray, receiver: Any) -> Measurements:
    """Step ``k``'s measurements: its fix m (3,) and a receiver's channels (7,) (None: none
    held), checked as a log's row is (:func:`lbo.logs.checks.check_receiver`)."""
    if receiver is None:
        return Measurements.of(m)
    try:
        r = np.asarray(receiver, dtype=float).reshape(len(RECEIVER))
    except (TypeError, ValueError):
        raise LboError(f"step {k}: receiver must be {len(RECEIVER)} numbers "
                       f"[{', '.join(RECEIVER)}] (NaN where not held), got "
                       f"{receiver!r}") from None
    check_receiver(m[None], r[None], f"step {k}")
    return Measurements.of(m, r)


def as_arrays(m: Any, receiver: Any, where: str) -> tuple[Any, Any]:
    """An observer's measurements as the arrays its checks read: ``m`` a
    :class:`~lbo.sim.measurements.Measurements` gives its poses and, where it holds any, its
    receiver's channels; anything else is the fixes, with ``receiver`` beside them."""
    if not isinstance(m, Measurements):
        return m, receiver
    if receiver is not None:
        raise LboError(f"{where}: the receiver's channels belong in the Measurements given, "
                       "not beside them")
    return m.pose, (m.receiver if m.reads_receiver else None)


def bicycle_rows(meas: Measurements, u: np.ndarray, wheelbase: float) -> np.ndarray:
    """The filters' rows (T, 8) of measurements ``meas`` (T steps) at inputs u (T, 2)
    ``[V, delta]``: the turn rate the course's variance allows for is the bicycle's
    ``V tan(delta) / L``."""
    turn = u[:, 0] * np.tan(u[:, 1]) / wheelbase
    return measure.rows(meas, u[:, 0], turn)


def receiver_rows(meas: Measurements, u: np.ndarray, wheelbase: float) -> np.ndarray:
    """A receiver net's rows (T, 9): the filters' row (:func:`bicycle_rows`) and the gyro's
    ``r_m``."""
    return np.column_stack([bicycle_rows(meas, u, wheelbase), meas.gyro])


def window_series(rows: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Window columns (T, 5) of paper rows (T, 3), or (T, 11) (``receiver_window.COLUMNS``)
    of a receiver net's rows (T, 9) (:func:`receiver_rows`), inputs u (T, 2) between."""
    width = min(rows.shape[-1], measure.WIDTH)
    return np.concatenate([rows[:, :width], u, rows[:, width:]], axis=1)
