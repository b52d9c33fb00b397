"""Which rows of an observer's output ``lbo.observe`` leaves out of its scores, and why.

Two things a user reads in ``lbo.observe``'s summary:

- the ``valid:`` line: why rows are not valid, naming only the reasons that apply, each with
  its count (:func:`unscored`): before the first fix; a window net's window still filling;
  outside the training envelope (``envelope=mark``); no heading yet (the robust observer
  starts at the first row holding a position and a heading, and a log of position fixes
  without ``psi_m`` nor a GNSS velocity never gives one); a window without a fix or heading;
  a classical observer's consistency test, or its numbers not finite;
- the heading's RMSE: a classical filter whose fixes hold no heading starts it at 0 rad,
  variance 1 rad^2, and reports it valid until the course over ground gives it
  (:class:`lbo.filters.start.CourseStart`). Those rows (a standstill from the start: all of
  them) have a heading never observed; :func:`heading_unseen` finds them, and ``lbo.observe``
  leaves them out of the heading's RMSE.

Everything here reads an observer's public attributes and its output; nothing changes what
it estimates.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lbo.filters import classical, measure
from lbo.scoring.metrics import rmse
from lbo.serve.rows import bicycle_rows
from lbo.sim.measurements import Measurements

COURSE_TEXT = (f"psi_m, or a course over ground from ve_m, vn_m at |v| >= "
               f"{measure.COURSE_MIN_SPEED:g} m/s")
"""What gives a row a heading, as the summary says it."""


def heading_rows(meas: Measurements, u: np.ndarray, wheelbase: float) -> np.ndarray:
    """(T,) bool: the rows of a log, its measurements ``meas`` (T steps) at inputs u (T, 2)
    ``[V, delta]``, that hold a position and a heading: ``psi_m``, or the course over ground
    of a GNSS velocity where it is held (the car moving,
    :func:`lbo.filters.measure.course_over_ground`). The robust observer starts at the first
    of them."""
    rows = bicycle_rows(meas, u, wheelbase)
    return np.isfinite(rows[:, :2]).all(1) & measure.heading_held(rows)


def taken(obs: Any, meas: Measurements) -> Measurements:
    """What observer ``obs`` (an :class:`lbo.Observer`) is given of a log's measurements: all
    of them where it takes a receiver's channels, its fixes alone where it does not."""
    return meas if obs.takes_receiver else Measurements.of(meas.pose)


def heading_unseen(obs: Any, meas: Measurements, u: np.ndarray) -> np.ndarray:
    """(T,) bool: the rows of a log, its measurements ``meas`` (T steps; the receiver's
    channels read where ``obs`` takes them) at inputs u (T, 2), at which classical observer
    ``obs`` (an :class:`lbo.Observer`) holds a position but has not observed its heading yet:
    from its first fix until its filter first takes a heading (a fix's ``psi_m``, the course
    over ground, or the course from the fixes once the car has moved;
    :class:`lbo.filters.start.CourseStart`). All False for a learned observer (NaN there, not
    valid) and for a plug-in's filter that keeps no course start.

    Its filter is stepped again over that stretch only, from the first fix to the first
    heading (none where the first fix holds one): the same stepper and the same rows as
    :meth:`lbo.Observer.run`, so the same rows are found.
    """
    from lbo.serve.runners import ClassicalRunner

    t = len(meas)
    blind = np.zeros(t, bool)
    if obs.kind != "classical":
        return blind
    # run() wraps psi_m first; whether a row holds one is all that matters here
    runner = ClassicalRunner(obs.name, obs.vehicle, obs.noise, gyro=obs.gyro_noise)
    rows, u = runner.log_rows(taken(obs, meas), u, None)
    rows = measure.widen(rows)
    pos = np.isfinite(rows[:, :2]).all(1)
    if not pos.any():
        return blind
    first = int(np.argmax(pos))
    if measure.heading_held(rows[first:first + 1])[0]:
        return blind  # the common case: a heading with the first fix, nothing to replay
    flt = classical.stepper(obs.name, rows[first:first + 1], obs.vehicle, obs.noise,
                            obs.alpha, gyro=obs.gyro_noise)
    course = getattr(flt, "course", None)
    if course is None:  # a plug-in's filter: it does not say
        return blind
    k = first
    # a filter loops over time; this one stops at its first heading (CourseStart.blind)
    while course.blind[0]:
        blind[k] = True
        k += 1
        if k == t:
            break
        flt.update(rows[k:k + 1], u[k - 1:k])
    return blind


def scored_rmse(est: np.ndarray, truth: np.ndarray, valid: np.ndarray, unseen: np.ndarray
                ) -> np.ndarray:
    """(3,) RMSE of x, y (m) over the ``valid`` rows (T,), and of psi (rad) over those whose
    heading was observed (not ``unseen``, :func:`heading_unseen`); NaN where none is."""
    out = rmse(est, truth, valid)
    out[2] = rmse(est, truth, valid & ~unseen)[2]
    return out


def psi_text(name: str, psi: float, valid: np.ndarray, unseen: np.ndarray) -> str:
    """The heading's part of a printed RMSE line: its RMSE ``psi`` (rad) and, where observer
    ``name`` had not observed its heading on some ``valid`` rows (``unseen``, (T,)), that they
    are left out of it (or that it is not scored, where that is every row)."""
    left_out = int((valid & unseen).sum())
    if not left_out:
        return f"psi {psi:.6g} rad"
    if not (valid & ~unseen).any():
        return (f"psi not scored ({name} never observed its heading: no psi_m, no course over "
                f"ground from ve_m, vn_m at |v| >= {measure.COURSE_MIN_SPEED:g} m/s, and the "
                "car never moved far enough from its first fix to take the course of its "
                "fixes)")
    return (f"psi {psi:.6g} rad over {int((valid & ~unseen).sum())} rows (the {left_out} "
            f"before {name} first observed its heading left out: it starts there from 0 rad, "
            "sd 1 rad)")


def unscored(obs: Any, est: np.ndarray, valid: np.ndarray, fix: np.ndarray,
             heading: np.ndarray, outside: np.ndarray | None) -> list[str]:
    """Why the rows not ``valid`` (T,) are not: one phrase per reason that applies, with its
    count, in row order.

    obs : the :class:`lbo.Observer`; est : (T, 3) its estimates (NaN where it has none);
    fix : (T,) rows holding a position; heading : (T,) rows holding a position and a heading
    (:func:`heading_rows`); outside : (T,) rows outside its training envelope where
    ``envelope=mark`` marked them, else None.
    """
    t = len(valid)
    rows = np.arange(t)
    bad = ~valid
    finite = np.isfinite(est).all(1)
    first_fix = int(np.argmax(fix)) if fix.any() else t
    first_heading = int(np.argmax(heading)) if heading.any() else t
    window = obs.kind == "learned" and obs.form == "window"
    groups = []
    before = bad & (rows < first_fix)
    groups.append((before, f"before the first fix (row {first_fix})" if first_fix < t else
                   "with no fix at all"))
    left = bad & ~before
    if outside is not None:
        groups.append((left & outside, "outside its training envelope (envelope=mark)"))
        left &= ~outside
    if window:  # the EKF's estimate stands in, not valid, while the window fills
        filling = left & finite & (rows < obs.window - 1)
        groups.append((filling, f"while its window of {obs.window} steps fills (the EKF's "
                                "estimate)"))
        left &= ~filling
    if obs.kind == "classical":  # valid from its first fix, heading or not
        groups.append((left & finite, "flagged by its consistency test"))
        groups.append((left & ~finite, "with an estimate that is not finite (the filter's "
                                       "numbers overflowed: check the log's values and units)"))
        return [f"{int(g.sum())} {why}" for g, why in groups if g.any()]
    unseen = left & (rows < first_heading)
    groups.append((unseen, f"with no heading yet: {obs.name} starts at the first row that "
                           f"holds a position and a heading ({COURSE_TEXT}); "
                   + ("this log holds none" if first_heading == t else
                      f"the first is row {first_heading}")))
    groups.append((left & ~unseen, "without an estimate (its window held no fix or no "
                                   "heading)"))
    return [f"{int(g.sum())} {why}" for g, why in groups if g.any()]
