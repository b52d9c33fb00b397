"""What one log row tells the classical filters: the measurement model of each step.

A row of a receiver's log holds any subset of these, each independently of the others:

- a position fix ``x_m, y_m`` (m), with or without a heading ``psi_m`` (rad);
- the receiver's reported 1-sigma accuracy of that fix, ``sx_m, sy_m`` (m), and of its
  heading, ``spsi_m`` (rad): the R of that step, in place of the filter's own;
- a GNSS velocity ``ve_m, vn_m`` (m/s east and north) with its 1-sigma ``sv_m`` (m/s).

The kinematic bicycle takes its speed ``V`` as an input, so a velocity tells the filter the
direction of travel only: the course over ground ``atan2(vn_m, ve_m)``, which is the
heading when the car moves forward and the heading plus pi when it reverses (V < 0). Its
variance is ``sv^2 / |v|^2`` (the velocity's noise across its direction), plus
``(COURSE_LEVER r / |v|)^2`` where the turn rate ``r`` is known: only the rear axle's centre
moves along the heading, and an antenna a distance ``l`` ahead of or behind it moves at
``atan(l r / V)`` from it (0.25 rad for 1.3 m at 0.3 rad/s and 1.5 m/s, in a car park). Below
:data:`COURSE_MIN_SPEED`, or where ``|v| < COURSE_MIN_SNR sv``, the direction of a velocity
is noise, and the channel is not held: a velocity informs the heading while the car moves and
nothing at standstill, as in INS/GNSS filters.

The filters read each step as one row of :data:`CHANNELS` (``(G, 8)``; a 3-wide row
``[x_m, y_m, psi_m]`` is the paper's and is widened with NaN): :func:`rows` builds them from
a log's columns, :func:`step_cov` gives the R of the step and :func:`model` the innovation,
Jacobian, covariance and held mask of its four measured channels ``[x_m, y_m, psi_m,
course]`` that :func:`lbo.filters.update.joseph_update` takes.
"""

from __future__ import annotations

from typing import Any, Generic, NamedTuple, Protocol, TypeVar

import numpy as np
from numpy.typing import ArrayLike

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.sim.measurements import Measurements

CHANNELS = ("x_m", "y_m", "psi_m", "sx_m", "sy_m", "spsi_m", "course", "s_course")
"""The filters' row: the fix, its reported 1-sigma accuracies (NaN: the filter's R), and the
course over ground with its 1-sigma (NaN: not held)."""
WIDTH = len(CHANNELS)


class _Sliceable(Protocol):
    def __getitem__(self, key: Any, /) -> Any: ...


A = TypeVar("A", bound=_Sliceable)


class Row(NamedTuple, Generic[A]):
    """Rows (..., 8) of :data:`CHANNELS` by name, NumPy arrays or torch tensors alike: each
    field (...) or (..., k), NaN where not held; views of the rows, so that what is written
    into one is written into them.

    pose : (..., 3) ``[x_m, y_m, psi_m]``; fix : (..., 2) ``[x_m, y_m]``; heading : ``psi_m``.
    sigma : (..., 3) ``[sx_m, sy_m, spsi_m]``, the receiver's reported 1-sigmas.
    course, course_sigma : the course over ground of the row's GNSS velocity, its 1-sigma.
    """

    pose: A
    fix: A
    heading: A
    sigma: A
    course: A
    course_sigma: A


assert CHANNELS == ("x_m", "y_m", "psi_m", "sx_m", "sy_m", "spsi_m", "course", "s_course"), \
    "row_channels reads these columns at these places"


def row_channels(row: A) -> Row[A]:
    """The columns of rows (..., 8) (:data:`CHANNELS`; or wider, as a receiver window's
    :data:`lbo.models.receiver_window.COLUMNS`, which starts with them) by name."""
    # the places as literals, checked above: the torch filters trace this
    return Row(row[..., 0:3], row[..., 0:2], row[..., 2], row[..., 3:6], row[..., 6],
               row[..., 7])


MEASURED = 4
"""Channels a row measures: x_m, y_m, psi_m and the course."""
H = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
"""(4, 3) Jacobian of the measured channels on the state [x, y, psi]: each is linear."""

SV_DEFAULT = 0.1
"""1-sigma (m/s) of a GNSS velocity whose log gives no ``sv_m``: a single-frequency
receiver's Doppler velocity, as receivers report it for a car in the open."""
COURSE_MIN_SPEED = 1.0
"""Slowest ground speed (m/s) whose direction is taken as the course."""
COURSE_LEVER = 1.0
"""Distance (m) of the antenna from the rear axle's centre that the course's variance allows
for, its turn-induced error taken as noise (the antenna's place is rarely known to the filter):
on the onavdata hill drive's test span, 1 m took the EKF's heading RMSE from 68 to 50 mrad
(0, 1, 2, 3 m: 67.6, 49.6, 52.8, 53.7 mrad; ``python -m lbo.realdrive``)."""
COURSE_MIN_SNR = 5.0
"""... and at least this many velocity sigmas: the course is then known to 0.2 rad or better,
where the linearised model (a Gaussian error on the angle) holds."""


def widen(m: ArrayLike) -> np.ndarray:
    """Rows (..., 3) ``[x_m, y_m, psi_m]`` or (..., 8) :data:`CHANNELS` -> (..., 8), the
    missing channels NaN (a 3-wide row reports no accuracy and no velocity)."""
    m = np.asarray(m, dtype=float)
    if m.shape[-1] == WIDTH:
        return m
    if m.shape[-1] != 3:
        raise LboError(f"measurement rows must have 3 [x_m, y_m, psi_m] or {WIDTH} "
                       f"{list(CHANNELS)} channels, got {m.shape[-1]}")
    pad = np.full(m.shape[:-1] + (WIDTH - 3,), np.nan)
    return np.concatenate([m, pad], axis=-1)


def course_over_ground(ve: np.ndarray, vn: np.ndarray, sv: np.ndarray, V: np.ndarray | None,
                       turn: np.ndarray | None = None, lever: float = COURSE_LEVER,
                       trust: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The course channel of GNSS velocities: ``(course, s_course)`` (T,) rad, NaN where not held.

    ve, vn : (T,) m/s east and north, NaN where the row has no velocity.
    sv : (T,) their 1-sigma (m/s), NaN: :data:`SV_DEFAULT`.
    V : (T,) the speed input (m/s); where it is negative the car reverses and its heading is
        the course plus pi (None, read as NaN: never).
    turn : (T,) the turn rate (rad/s), e.g. ``V tan(delta) / L``, or None (not allowed for).
    lever : the antenna's distance (m) from the rear axle that the variance allows for.
    trust : a factor on ``sv`` in the variance (a learned ``velocity_scale``); which rows hold
        a course is the receiver's own sigma's to say, so a filter told to trust the velocity
        less still takes its course from the same speed on.
    """
    ve, vn, sv, V = (np.asarray(a, dtype=float) for a in (ve, vn, sv, V))
    turn = np.zeros_like(V) if turn is None else np.asarray(turn, dtype=float)
    sv = np.where(np.isfinite(sv), sv, SV_DEFAULT)
    speed = np.hypot(ve, vn)
    held = np.isfinite(speed) & (speed >= COURSE_MIN_SPEED) & (speed >= COURSE_MIN_SNR * sv)
    safe = np.where(held, speed, 1.0)
    course = np.arctan2(vn, ve) + np.where(V < 0, np.pi, 0.0)
    sigma = np.hypot(trust * sv, lever * turn) / safe
    return np.where(held, wrap_angle(course), np.nan), np.where(held, sigma, np.nan)


def rows(meas: Measurements, V: np.ndarray | None = None, turn: np.ndarray | None = None,
         lever: float = COURSE_LEVER, trust: float = 1.0) -> np.ndarray:
    """The filters' rows (..., 8) of :data:`CHANNELS` from what the sensors told, ``meas``
    (leading shape ``...``): the fix and its heading, the reported accuracies, and the course
    over ground of the GNSS velocity (:func:`course_over_ground`, which reads ``V`` (...),
    the speed input (None: never reversing), the turn rate ``turn`` (...) or None, ``lever``
    (m) and ``trust``). The gyro is no channel of these rows.
    """
    course = np.full(meas.heading.shape, np.nan), np.full(meas.heading.shape, np.nan)
    if meas.has_velocity.any():
        course = course_over_ground(meas.velocity[..., 0], meas.velocity[..., 1],
                                    meas.velocity_sigma, V, turn, lever, trust)
    return np.concatenate([meas.pose, meas.sigma, np.stack(course, axis=-1)], axis=-1)


def held_last(a: np.ndarray) -> np.ndarray:
    """Samples a (T,) or (T, k) (NaN in a row: none there) held from each to the next: at
    each row the last row's sample that holds all its values, NaN before the first."""
    a = np.asarray(a, dtype=float)
    has = np.isfinite(a) if a.ndim == 1 else np.isfinite(a).all(1)
    last = np.maximum.accumulate(np.where(has, np.arange(len(has)), -1))
    out = a[np.maximum(last, 0)]
    out[last < 0] = np.nan
    return out


def undelayed(fix: np.ndarray, velocity: np.ndarray, rate: np.ndarray, fix_latency: float,
              velocity_latency: float) -> tuple[np.ndarray, np.ndarray]:
    """A receiver's fixes and velocities brought forward to their row from samples some
    seconds old: each velocity turned by the turn over its latency (``rate *
    velocity_latency``), each fix moved on along the chord it missed, by its latency times
    the last velocity turned to the middle of that latency. Exact on a circle for the
    velocity, to second order for the fix. For a filter told the latency; at 15 m/s and
    0.2 rad/s, 50 ms late is 0.75 m along the road and 10 mrad of course.

    fix : (T, 2) ``[x_m, y_m]`` (NaN: none); velocity : (T, 2) ``[ve_m, vn_m]`` (NaN: none);
    rate : (T,) the turn rate (rad/s), e.g. the gyro's; fix_latency, velocity_latency : s >= 0.
    Returns ``(fix, velocity)`` (T, 2) each; a fix before the first velocity stays as it is.
    """
    fix, velocity = np.asarray(fix, dtype=float), np.asarray(velocity, dtype=float)
    rate = np.asarray(rate, dtype=float)
    for name, late in (("fix_latency", fix_latency), ("velocity_latency", velocity_latency)):
        if not (np.isfinite(late) and late >= 0):
            raise LboError(f"{name}: expected a number of seconds >= 0, got {late!r}")

    def turned(v: np.ndarray, angle: np.ndarray) -> np.ndarray:
        c, s = np.cos(angle), np.sin(angle)
        return np.column_stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]])

    held = np.nan_to_num(held_last(velocity))  # before the first velocity: not moved
    chord = turned(held, rate * (velocity_latency - 0.5 * fix_latency))
    return fix + fix_latency * chord, turned(velocity, rate * velocity_latency)


def heading_held(m: np.ndarray) -> np.ndarray:
    """Rows (..., 8), or wider as a receiver window's (..., T, 11), that measure the heading,
    by ``psi_m`` or the course: (...) bool."""
    c = row_channels(m)
    return np.isfinite(c.heading) | np.isfinite(c.course)


def step_cov(m: np.ndarray, R: np.ndarray) -> np.ndarray:
    """The R (G, 3, 3) of x_m, y_m, psi_m at this step: the filter's ``R`` (G, 3, 3), with a
    channel's variance replaced by the square of the accuracy the row reports for it (and
    that channel's correlations dropped: a receiver reports sigmas, not correlations).
    ``R`` itself is returned where no row reports any."""
    sigma = row_channels(m).sigma
    told = np.isfinite(sigma)
    if not told.any():
        return R
    either = told[:, :, None] | told[:, None, :]
    R = np.where(either, 0.0, R)  # a told channel: its variance and correlations, dropped
    idx = np.arange(3)
    R[:, idx, idx] = np.where(told, np.square(sigma), R[:, idx, idx])
    return R


def model(m: np.ndarray, x: np.ndarray, R: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The measurement model of one step for :func:`lbo.filters.update.joseph_update`.

    m : (G, 8) this step's rows (:data:`CHANNELS`).
    x : (G, 3) the prior state ``[x, y, psi]``.
    R : (G, 3, 3) the step's covariance of x_m, y_m, psi_m (:func:`step_cov`).

    Returns ``(y, H, R4, held)``: the innovation (G, 4), headings wrapped, 0 where not held;
    the Jacobian (4, 3); the covariance (G, 4, 4), the course's variance ``s_course^2`` apart;
    the channels held (G, 4) bool.
    """
    meas, held, R4 = measured(m, R)
    y = innovation(meas, np.concatenate([x, x[:, 2:3]], axis=1), held)
    return y, H, R4, held


def measured(m: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The four measured channels of rows m (G, 8): ``[x_m, y_m, psi_m, course]`` (G, 4),
    which of them are held (G, 4) bool, and their covariance (G, 4, 4): the step's R (G, 3, 3)
    (:func:`step_cov`) and the course's ``s_course^2`` apart (1 where not held: finite, and
    masked out)."""
    c = row_channels(m)
    meas = np.concatenate([c.pose, c.course[:, None]], axis=1)
    held = np.isfinite(meas)
    R4 = np.zeros((len(m), MEASURED, MEASURED))
    R4[:, :3, :3] = R
    R4[:, 3, 3] = np.where(held[:, 3], np.square(np.where(held[:, 3], c.course_sigma, 0.0)), 1.0)
    return meas, held, R4


def innovation(meas: np.ndarray, pred: np.ndarray, held: np.ndarray) -> np.ndarray:
    """The innovation (G, 4) of the measured channels ``meas`` (G, 4) against their prediction
    ``pred`` (G, 4): 0 where not ``held``, the heading's and the course's wrapped."""
    y = np.where(held, meas - pred, 0.0)
    y[:, 2:] = wrap_angle(y[:, 2:])
    return y
