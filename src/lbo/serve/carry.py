"""The window filter's window form through a stop: its own earlier estimate carried in as the
window's first fix.

A single antenna tells the heading only while the car moves (the course over ground), so the
window of a car that has stood or crept for N steps holds no heading, and a net that reads a
receiver can say nothing of it there. But a car that stands does not turn: the kinematic
bicycle's ``psi' = V tan(delta) / L`` is 0 at ``V = 0``, so the heading it had when it stopped
is still its heading. The window form therefore carries it: a window that holds no heading
gets, in its first row, the observer's own estimate at that row as a course over ground (1
sigma :data:`CARRIED_SIGMA_PSI`), and that estimate's position as its fix where the row holds
none of its own (with the accuracy the receiver reports for the window's latest fix, or the
net's own R where it reports none). The window filter then starts there and holds the
carried heading through the stop, as a filter carried from step to step would. Only the
window filter carries (:class:`lbo.serve.runners.WindowRunner`): a CNN or an LSTM reads a
carried course as any course, which it was not trained for, and gives none there.

Each such estimate depends on one made N-1 steps earlier, so a log's blind windows are
estimated in blocks of N-1 (:func:`run_blind`); a window whose first row has no estimate (a
car standing since the log began) gets none.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from lbo.filters.measure import CHANNELS

CARRIED_SIGMA_PSI = 0.05
"""1-sigma (rad) of a carried heading, read as a course (within the 0.01-0.2 rad of the
courses a receiver gives): the filter holds no other heading in such a window, so its heading
comes out as it went in whatever this is; it weighs only the heading's pull on the position."""
_X, _Y, _SX, _SY = (CHANNELS.index(c) for c in ("x_m", "y_m", "sx_m", "sy_m"))
_COURSE, _SCOURSE = CHANNELS.index("course"), CHANNELS.index("s_course")


def carried(windows: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """Receiver windows (B, N, 11) (:data:`lbo.models.receiver_window.COLUMNS`) that hold no
    heading, with each one's estimate at its first row ``prior`` (B, 3) ``[x, y, psi]`` written
    into that row: the heading as a course, the position as a fix where the row holds none.
    Returns a copy."""
    out = np.array(windows, dtype=float, copy=True)
    first = out[:, 0]
    fix = np.isfinite(first[:, _X]) & np.isfinite(first[:, _Y])
    # the accuracy the receiver reports for the window's latest fix (NaN: none reported)
    held = np.isfinite(out[:, :, _SX])
    latest = out.shape[1] - 1 - np.argmax(held[:, ::-1], axis=1)
    told = out[np.arange(len(out)), latest][:, [_SX, _SY]]
    told[~held.any(1)] = np.nan
    first[~fix, _X], first[~fix, _Y] = prior[~fix, 0], prior[~fix, 1]
    first[~fix, _SX], first[~fix, _SY] = told[~fix, 0], told[~fix, 1]
    first[:, _COURSE], first[:, _SCOURSE] = prior[:, 2], CARRIED_SIGMA_PSI
    return out


def run_blind(windows: np.ndarray, blind: np.ndarray, head: int, est: np.ndarray,
              predict: Callable[[np.ndarray], np.ndarray]) -> None:
    """Estimate the blind windows of a log in place.

    windows : (W, N, 11) every window of the log, window w ending at its row ``head + w``
        (a view: only the blind ones are copied, a block at a time).
    blind : (B,) increasing indices of the windows that hold no heading.
    est : (T, 3) the log's estimates, the observer's own from row ``head`` on (before it, a
        stand-in's, never carried), NaN at the blind windows' rows; each block is written
        there as it is made from the rows N-1 before it (:func:`carried`).
    predict : windows (b, N, 11) -> states (b, 3)."""
    n = windows.shape[1]
    ends = head + np.asarray(blind)
    start = 0
    while start < len(ends):
        # every window ending before ends[start] + N - 1 starts at a row estimated already
        stop = int(np.searchsorted(ends, ends[start] + n - 1))
        first = ends[start:stop] - (n - 1)
        prior = np.where((first >= head)[:, None], est[np.maximum(first, 0)], np.nan)
        ok = np.isfinite(prior).all(1)
        if ok.any():
            est[ends[start:stop][ok]] = predict(carried(windows[blind[start:stop][ok]],
                                                        prior[ok]))
        start = stop
