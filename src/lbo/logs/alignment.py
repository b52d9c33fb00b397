"""Aligning a real drive's truth with its receiver: the heading's boresight, the fixes'
latency, and the fixes put on the log's rows.

A reference system (an INS, a phone's fused pose) reports the heading of its own case, which
is turned against the car; a receiver logs each fix some time after the instant it is valid
at. Both importers of real drives (:mod:`lbo.logs.hguide`, :mod:`lbo.logs.comma2k19`) fit these
the same way, here.
"""

from __future__ import annotations

import numpy as np

from lbo.core.errors import LboError

__all__ = ["FIT_SPEED", "LATENCIES", "STRAIGHT_RATE", "boresight", "latency_grid", "on_rows"]

FIT_SPEED = 2.0
"""Slowest speed (m/s) of the rows that fit the boresight, a lever arm, the latency and a
steering ratio: standing still, a latency changes nothing."""
STRAIGHT_RATE = 0.03
"""Largest yaw rate (rad/s) of the rows that fit the boresight: in a turn the velocity points
off the heading by the car's own side slip."""
LATENCIES = (-0.5, 0.5)
"""Range (s) of latencies tried, on a 10 ms grid (:func:`latency_grid`)."""


def boresight(psi: np.ndarray, ve: np.ndarray, vn: np.ndarray, rate: np.ndarray,
              where: str) -> float:
    """The angle (rad, counter-clockwise) from the reported heading ``psi`` (N,) to the
    direction the car moves in (velocity ``ve, vn`` (N,) m/s; plus pi reversing), its circular
    mean over the rows driving straight (yaw ``rate`` (N,) under :data:`STRAIGHT_RATE`) above
    :data:`FIT_SPEED`: a car moves along its heading. ``where`` names the rows in the error
    raised when fewer than 100 are such."""
    along = vn * np.sin(psi) + ve * np.cos(psi)
    straight = (np.hypot(ve, vn) > FIT_SPEED) & (np.abs(rate) < STRAIGHT_RATE)
    if straight.sum() < 100:
        raise LboError(f"{where}: {int(straight.sum())} rows driving straight above "
                       f"{FIT_SPEED:g} m/s; the boresight needs at least 100")
    course = np.arctan2(vn, ve) + np.where(along < 0, np.pi, 0.0)
    off = course[straight] - psi[straight]
    return float(np.arctan2(np.sin(off).mean(), np.cos(off).mean()))


def latency_grid() -> np.ndarray:
    """(K,) the latencies tried (s): :data:`LATENCIES` on a 10 ms grid."""
    return np.round(np.arange(LATENCIES[0], LATENCIES[1] + 1e-9, 0.01), 2)


def on_rows(t_valid: np.ndarray, t0: float, dt: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Where fixes valid at ``t_valid`` (F,) s land on a log of ``n`` rows from ``t0`` every
    ``dt`` s: the nearest row of each (F',) and which fixes land inside the log (F,) bool."""
    row = np.round((t_valid - t0) / dt).astype(np.int64)
    keep = (row >= 0) & (row < n)
    return row[keep], keep
