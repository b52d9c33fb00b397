"""What a runner reads: a log's rows as each observer takes them, and one sample's receiver
channels checked as a log's row is.

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


def checked_receiver(k: int, m: np.ndarray, receiver: Any) -> np.ndarray:
    """Step ``k``'s receiver channels (7,) (None: none held, all NaN), checked beside its
    measurement m (3,) as a log's row is (:func:`lbo.logs.checks.check_receiver`)."""
    if receiver is None:
        return np.full(len(RECEIVER), np.nan)
    try:
        r = np.asarray(receiver, dtype=float).reshape(len(RECEIVER))
    except (TypeError, ValueError):
        raise LboError(f"step {k}: receiver must be {len(RECEIVER)} numbers "
                       f"[{', '.join(RECEIVER)}] (NaN where not held), got "
                       f"{receiver!r}") from None
    check_receiver(m[None], r[None], f"step {k}")
    return r


def bicycle_rows(m: np.ndarray, u: np.ndarray, receiver: np.ndarray, wheelbase: float
                 ) -> np.ndarray:
    """The filters' rows (T, 8) of measurements m (T, 3) and a receiver's channels (T, 7) at
    inputs u (T, 2) ``[V, delta]``: the turn rate the course's variance allows for is the
    bicycle's ``V tan(delta) / L``."""
    turn = u[:, 0] * np.tan(u[:, 1]) / wheelbase
    return measure.rows(m, receiver[:, :3], receiver[:, 3:5], receiver[:, 5], u[:, 0], turn)


def receiver_rows(m: np.ndarray, u: np.ndarray, receiver: np.ndarray, wheelbase: float
                  ) -> np.ndarray:
    """A receiver net's rows (T, 9): the filters' row (:func:`bicycle_rows`) and ``r_m``."""
    r_m = receiver[:, RECEIVER.index("r_m")]
    return np.column_stack([bicycle_rows(m, u, receiver, wheelbase), r_m])


def window_series(rows: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Window columns (T, 5) of paper rows (T, 3), or (T, 11) (``receiver_window.COLUMNS``)
    of a receiver net's rows (T, 9) (:func:`receiver_rows`), inputs u (T, 2) between."""
    width = min(rows.shape[-1], measure.WIDTH)
    return np.concatenate([rows[:, :width], u, rows[:, width:]], axis=1)
