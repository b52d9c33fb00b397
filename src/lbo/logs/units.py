"""Is a log in lbo's units and conventions? Time in seconds, strictly increasing and without
long gaps; the speed in m/s; headings in rad, counter-clockwise from east. Each check tells a
log in another unit or convention from one in lbo's by what the log itself holds (how fast its
heading turns, how far its speed carries it against its fixes), and refuses it in one line
that names the column and the fix (``units.psi=deg``, ``units.V=kmh``, ``heading=compass``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.core.checks import number
from lbo.core.errors import LboError, located

YAW_RATE_LIMIT = 2.0
"""Fastest heading change (rad/s) of a car between two headings a :data:`RATE_SPAN` apart:
full lock at walking pace turns a 2.7 m car at about 1 rad/s, and 2 rad/s at 10 m/s would be
20 m/s^2 of lateral acceleration. Heading noise (17.4 mrad at alpha = 1, 0.1 rad at alpha = 6)
adds less than 0.3 rad/s over half a second."""
RATE_SPAN = 0.5
"""s between the two headings of a pair that :func:`check_heading_unit` compares; pairs are
at most twice that apart (a change of at most pi over a longer span could never exceed the
limit)."""
DEGREES_SHARE = 0.01
"""A heading column that turns faster than :data:`YAW_RATE_LIMIT` over more than this share
of its pairs, read as rad, looks like degrees (in degrees, a turn of 20 deg/s reads as 20
rad/s); fewer are noise or glitches."""
MAX_GAP = 0.5
"""Default longest gap (s) in a log's ``t`` that ``resample=true`` interpolates V and delta
across (see :func:`check_gaps`)."""
TIME_UNITS = (("milliseconds", 1e3), ("microseconds", 1e6), ("nanoseconds", 1e9))
"""A median step of ``t`` within a factor 10 of ``dt`` in one of these units looks like it."""


def check_max_gap(max_gap: Any, field: str = "max_gap") -> float:
    """max_gap as a float, checked: a time in seconds > 0."""
    return number(max_gap, field, low=0.0, low_open=True, form="a time in seconds > 0")


def check_time(t: np.ndarray, source: str | None = None) -> None:
    """Refuse a ``t`` that is not strictly increasing, naming the row."""
    steps = np.diff(t)
    if (steps <= 0).any():
        j = int(np.flatnonzero(steps <= 0)[0])
        raise LboError(located(source, f"column 't' is not strictly increasing (row {j + 1}: "
                                   f"t={t[j + 1]:g} s after t={t[j]:g} s); sort the log and "
                                   "drop repeats"))


def check_time_unit(t: np.ndarray, dt: float, source: str | None = None) -> None:
    """Refuse a ``t`` whose median step looks like ``dt`` in milliseconds (or micro-, nano-
    seconds): within a factor 10 of ``1000 dt``. In seconds, such a log would hold one sample
    every 2 s to 200 s (at dt=0.02 s), far too sparse to observe with; in milliseconds,
    ``resample=true`` would blow it up a thousandfold."""
    if len(t) < 2:
        return
    median = float(np.median(np.diff(t)))
    for unit, factor in TIME_UNITS:
        if 0.1 <= median / (factor * dt) <= 10:
            raise LboError(located(source, f"column 't' looks like {unit} (median step {median:g} "
                                       f"for dt={dt:g} s); give t in seconds"))


def _turn_rates(psi: np.ndarray, t: np.ndarray) -> np.ndarray:
    """|heading change| / time (rad/s) over pairs of the finite headings ``psi`` (T,) at times
    ``t`` (T,), strictly increasing: each with the first one at least :data:`RATE_SPAN` later,
    if that one is at most twice as far. The change is taken the short way round (wrapped),
    so a heading's branch, and a jump of 2 pi where a logger wraps it, change nothing."""
    at = np.flatnonzero(np.isfinite(psi))
    ta = t[at]
    k = np.searchsorted(ta, ta + RATE_SPAN)
    ok = k < len(at)
    i, j = at[ok], at[k[ok]]
    span = t[j] - t[i]
    near = span <= 2 * RATE_SPAN
    return np.abs(wrap_angle(psi[j[near]] - psi[i[near]])) / span[near]


def check_heading_unit(psi: np.ndarray, t: np.ndarray, column: str = "psi_m",
                       source: str | None = None) -> None:
    """Refuse a heading column in degrees, told from radians by how fast it turns, not by its
    range (a heading in rad that a logger accumulates reaches 110 rad after 17 laps).

    psi (T,) rad, NaN where there is none; t (T,) s. Read as rad, a heading in degrees turns
    57 times too fast: a 20 deg/s turn reads as 20 rad/s, and its changes over half a second
    (wrapped) spread over the whole circle. A column that turns faster than
    :data:`YAW_RATE_LIMIT` over more than :data:`DEGREES_SHARE` of its pairs of headings
    :data:`RATE_SPAN` apart looks like degrees, when in degrees it does not. A ``t`` that is
    not strictly increasing (refused by :func:`check_time`) is not checked."""
    t = np.asarray(t, float)
    if len(t) < 2 or not (np.diff(t) > 0).all():
        return
    rates = _turn_rates(psi, t)
    if len(rates) < 1 / DEGREES_SHARE:  # too few pairs to tell
        return
    fast = float(np.mean(rates > YAW_RATE_LIMIT))
    if fast <= DEGREES_SHARE:
        return
    degrees = _turn_rates(np.radians(psi), t)
    if np.mean(degrees > YAW_RATE_LIMIT) <= DEGREES_SHARE:
        raise LboError(located(source, f"column {column!r} looks like degrees: read as rad it "
                                   f"turns faster than {YAW_RATE_LIMIT:g} rad/s (no car can) in "
                                   f"{fast:.0%} of its {RATE_SPAN:g} s spans, in degrees at "
                                   f"most {float(np.max(degrees)):.2g} rad/s; give headings in "
                                   "rad, or pass units.psi=deg"))
    raise LboError(located(source, f"column {column!r} turns faster than {YAW_RATE_LIMIT:g} rad/s "
                               f"in {fast:.0%} of its {RATE_SPAN:g} s spans, read as rad and "
                               "as degrees alike: it is not a vehicle's heading (give the "
                               "heading of the vehicle's axis, in rad)"))


CONVENTION_SPAN = 5.0
"""s between the two fixes of a pair that :func:`check_conventions` compares."""
CONVENTION_MIN_M = 25.0
"""Shortest displacement (m) of a pair :func:`check_conventions` uses: well above GNSS noise
(6 m at alpha = 6), so that its direction and length are the car's."""
CONVENTION_MIN_PAIRS = 10
SPEED_SUSPECTS = (("km/h", "kmh", 2.9, 4.5), ("mph", "mph", 1.9, 2.6))
"""(unit, units.V, lowest, highest) ratio of the distance V integrates to over the distance
the fixes moved at which V looks like it is in that unit (3.6 for km/h, 2.24 for mph; a
winding road lengthens the path over its chord by 1.3 at most for 5 s above 25 m)."""


def _pairs(t: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fix rows (i, j), j the first fix ``CONVENTION_SPAN`` s after i, at least
    ``CONVENTION_MIN_M`` apart."""
    fix = np.flatnonzero(np.isfinite(m[:, :2]).all(1))  # the course needs no heading
    if len(fix) < 2:
        return fix[:0], fix[:0]
    tf = t[fix]
    k = np.searchsorted(tf, tf + CONVENTION_SPAN)
    ok = k < len(fix)
    i, j = fix[ok], fix[k[ok]]
    far = np.hypot(*(m[j, :2] - m[i, :2]).T) >= CONVENTION_MIN_M
    return i[far], j[far]


def check_conventions(t: np.ndarray, m: np.ndarray, u: np.ndarray,
                      source: str | None = None, heading: str = "enu") -> None:
    """Refuse a log whose speed or heading contradicts its own fixes.

    Over pairs of fixes 5 s apart that moved at least 25 m: the distance ``V`` integrates to
    over the distance the fixes moved is about 1 for a speed in m/s (the path's length over
    its chord) and 3.6 for one in km/h. The heading at the pair's middle points along the
    chord, or against it where ``V`` is negative over the pair (a car reversing); a heading
    that points along the chord's line either way passes (reversing with an unsigned speed).
    Otherwise, it is refused with the reading in which it does point where the car moves
    (signed by ``V``), and only then: the heading read as degrees (on a straight road,
    where :func:`check_heading_unit` cannot tell them: about 6 headings in 10, those whose
    degrees read as rad point neither along nor against the road), or its mirror image
    about the diagonal (the other heading convention). Too few such pairs (a short or slow
    log): nothing is checked. t (T,), m (T, 3), u (T, 2); ``heading``: the convention the log was
    read in (named in the hint)."""
    i, j = _pairs(np.asarray(t, float), np.asarray(m, float))
    if len(i) < CONVENTION_MIN_PAIRS:
        return
    travelled = np.concatenate([[0.0], np.cumsum(0.5 * (u[1:, 0] + u[:-1, 0]) * np.diff(t))])
    chord = m[j, :2] - m[i, :2]
    ratio = float(np.median(np.abs(travelled[j] - travelled[i]) / np.hypot(*chord.T)))
    for unit, key, low, high in SPEED_SUSPECTS:
        if low <= ratio <= high:
            raise LboError(located(source, f"column 'V' looks like {unit}: it travels {ratio:.2f} "
                                       "times the distance the fixes moved; give V in m/s, or "
                                       f"pass units.V={key}"))
    mid = m[(i + j) // 2, 2]
    has = np.isfinite(mid)
    if has.sum() < CONVENTION_MIN_PAIRS:
        return
    course = np.arctan2(chord[has, 1], chord[has, 0])
    # where V integrates backwards over the pair, the car moves against its heading
    back = np.where(travelled[j[has]] < travelled[i[has]], np.pi, 0.0)

    def agreement(psi: np.ndarray) -> float:
        """Median cosine between the motion a heading reading implies and the fixes'."""
        return float(np.median(np.cos(psi + back - course)))

    along = agreement(mid[has])
    # a heading along the chord's line but against V's sign: a car reversing with an
    # unsigned speed (or a forward one with a negative V); neither convention is at fault
    if along >= 0.8 or agreement(mid[has] + np.pi) > 0.8:
        return
    # degrees are tried only where most headings lie beyond 2 pi, as most in degrees do: any
    # heading in rad, read as degrees, points within 3 degrees of east, so a road running
    # east or west would agree with it (a compass heading was wrapped when turned to ENU:
    # its degrees are lost, not tried)
    if heading == "enu" and np.median(np.abs(mid[has])) > 2 * np.pi \
            and agreement(np.radians(mid[has])) > 0.8:
        raise LboError(located(source, "column 'psi_m' looks like degrees: it does not point where "
                                   "the fixes move, but read as degrees it does; give headings "
                                   "in rad, or pass units.psi=deg"))
    if along < 0.3 and agreement(np.pi / 2 - mid[has]) > 0.8:
        other = "compass" if heading == "enu" else "enu"
        raise LboError(located(source, "column 'psi_m' does not point where the fixes move "
                                   f"(read as heading={heading}), but its mirror image does: "
                                   f"pass heading={other} (enu: counter-clockwise from east; "
                                   "compass: clockwise from north)"))


def check_gaps(t: np.ndarray, max_gap: float, source: str | None = None,
               dt: float = 0.0) -> None:
    """Refuse two consecutive rows more than ``max_gap`` seconds apart: V and delta would be
    interpolated across the gap, which no log holds. A gap of at most ``dt`` (the grid's
    step) is never refused: no grid row falls inside it but the nearest ones.

    Why 0.5 s: in seven of lbo's simulated manoeuvres (``python -m lbo.simulate``, alpha=1,
    inputs and fixes thinned to one row per gap, then resampled to 0.02 s), interpolated V
    and delta moved the EKF's position RMSE by about 2% at most at 0.2 s gaps, 10% at 0.5 s,
    but by up to 27% at 1 s. A 10 Hz CAN log, with jitter or a dropped sample, passes; a
    second without inputs does not.
    """
    steps = np.diff(t)
    over = steps > max(max_gap, dt)
    if over.any():
        j = int(np.flatnonzero(over)[0])
        raise LboError(located(source, f"rows {j} and {j + 1} are {steps[j]:g} s apart "
                                   f"(t={t[j]:g} s to {t[j + 1]:g} s), longer than "
                                   f"max_gap={max_gap:g} s: V and delta cannot be "
                                   "interpolated across it; split the log there, or raise "
                                   "max_gap"))
