"""The one validation path for a vehicle log, shared by ``python -m lbo.observe`` and
:class:`lbo.Observer` (its :meth:`~lbo.Observer.run` and :meth:`~lbo.Observer.step`).

The CLI reads a table and checks its columns (:mod:`lbo.observe`); everything about the
values is checked here, on arrays, so that a log refused by the CLI is refused by the library
with the same line, and a sample refused by :meth:`~lbo.Observer.step` is one that
:meth:`~lbo.Observer.run` refuses in a whole log. Every check raises one
:class:`~lbo.core.errors.LboError` line naming the row (or step), the column and the expected form.

Also here: the checks of the settings shared by the CLI and the API (``alpha``, ``device``,
``max_gap``). This module imports numpy only (torch only to ask whether CUDA is there).
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from lbo.core.checks import number
from lbo.core.errors import LboError

MEAS = ("x_m", "y_m", "psi_m")
"""Columns of a position fix; all three NaN: a step without a fix."""
INPUTS = ("V", "delta")
TRUTH = ("x", "y", "psi")

POSITION_LIMIT = 1e7
"""Largest |x|, |y| (m): positions are metres in a local frame, not degrees nor UTM in mm."""
SPEED_LIMIT = 100.0
"""Largest |V| (m/s)."""
DEGREES_SHARE = 0.01
"""A heading column with more than this share of rows beyond 2 pi looks like degrees; fewer
are outliers, named by row."""
STEERING_SLACK = 1e-6
"""Relative slack on the steering limit (a delta_max written with rounding)."""
RANGES = (("x_m", POSITION_LIMIT, "m", "positions are metres in a local frame"),
          ("y_m", POSITION_LIMIT, "m", "positions are metres in a local frame"),
          ("x", POSITION_LIMIT, "m", "positions are metres in a local frame"),
          ("y", POSITION_LIMIT, "m", "positions are metres in a local frame"),
          ("V", SPEED_LIMIT, "m/s", "no road vehicle is that fast; speeds are in m/s"))
"""(column, largest |value|, unit, why) of the physical range checks of a log."""
_RANGE = {c: (limit, unit, why) for c, limit, unit, why in RANGES}

ALPHA_MAX = 100.0
"""Largest measurement-noise scale alpha (the paper's range is 0.25 .. 6; beyond 100 the
oracle's R overflows towards inf and says nothing)."""
MAX_GAP = 0.5
"""Default longest gap (s) in a log's ``t`` that ``resample=true`` interpolates V and delta
across (see :func:`check_gaps`)."""
TIME_UNITS = (("milliseconds", 1e3), ("microseconds", 1e6), ("nanoseconds", 1e9))
"""A median step of ``t`` within a factor 10 of ``dt`` in one of these units looks like it."""
DEVICE = re.compile(r"cpu|cuda(:[0-9]+)?")


def _at(source: str | None, text: str) -> str:
    return f"{source}: {text}" if source else text


# --------------------------------------------------------------------------- settings


def check_alpha(alpha: Any, field: str = "alpha") -> float:
    """alpha as a float, checked: a number in [0, ALPHA_MAX]."""
    return number(alpha, field, low=0.0, high=ALPHA_MAX)


def check_device(device: Any, probe: bool = True) -> str:
    """The torch device name, checked: ``cpu``, ``cuda`` or ``cuda:<n>``; with ``probe``, a
    CUDA device must be one torch sees (this imports torch, for ``cuda`` only)."""
    name = str(device)
    if not DEVICE.fullmatch(name):
        raise LboError(f"device={name}: expected cpu, cuda or cuda:<n>")
    if probe and name.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise LboError(f"device={name} needs CUDA, which torch does not see here; "
                           "use device=cpu")
        count = torch.cuda.device_count()
        if ":" in name and int(name.split(":")[1]) >= count:
            raise LboError(f"device={name}: torch sees {count} CUDA device"
                           f"{'s' if count != 1 else ''} (cuda:0 to cuda:{count - 1})")
    return name


def check_max_gap(max_gap: Any, field: str = "max_gap") -> float:
    """max_gap as a float, checked: a time in seconds > 0."""
    return number(max_gap, field, low=0.0, low_open=True, form="a time in seconds > 0")


# --------------------------------------------------------------------------- whole logs


def _finite(values: np.ndarray, names: tuple[str, ...], source: str | None) -> None:
    for c, name in enumerate(names):
        bad = ~np.isfinite(values[:, c])
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise LboError(_at(source, f"column {name!r} has NaN or inf (first at row {first})"))


def fix_mask(m: Any) -> Any:
    """Which rows hold a position fix: (..., C) measurements whose first three channels are
    ``x_m, y_m, psi_m`` (C >= 3, a NumPy array or a torch tensor) -> (...) bool, True where
    all three hold a finite value. A step without a fix leaves them NaN."""
    head = m[..., :3]
    if isinstance(head, np.ndarray):
        return np.isfinite(head).all(-1)
    return head.isfinite().all(-1)  # a torch tensor, without importing torch here


def fix_period(rate: float, dt: float) -> int:
    """Steps of ``dt`` between position fixes at ``rate`` Hz (>= 1: a rate of 1/dt or more is
    a fix at every step)."""
    return max(1, int(round(1.0 / (rate * dt))))


def check_fixes(m: np.ndarray, source: str | None = None) -> np.ndarray:
    """:func:`fix_mask` of a log's measurements m (T, 3), checked: a row with only some of
    ``x_m, y_m, psi_m`` NaN, or a log without any fix, is one :class:`LboError`."""
    empty = np.isnan(m)
    partial = empty.any(1) & ~empty.all(1)
    if partial.any():
        r = int(np.flatnonzero(partial)[0])
        gone = [c for c, e in zip(MEAS, empty[r]) if e]
        raise LboError(_at(source, f"row {r} has a partial fix ({', '.join(gone)} empty); a "
                                   "step without a fix leaves x_m, y_m and psi_m all empty"))
    fix = ~empty.all(1)
    if not fix.any():
        raise LboError(_at(source, "no position fix in any row (x_m, y_m and psi_m are "
                                   "empty everywhere)"))
    return fix


def _beyond(where: str, column: str, value: float) -> LboError:
    limit, unit, why = _RANGE[column]
    return LboError(f"{where}: {column}={value:g} {unit} is beyond {limit:g} {unit} ({why})")


def _heading(where: str, column: str, value: float) -> LboError:
    return LboError(f"{where}: {column}={value:g} rad is outside [-2 pi, 2 pi]; a heading in "
                     "rad lies within it")


def _steering(where: str, value: float, delta_max: float) -> LboError:
    return LboError(f"{where}: delta={value:g} rad is beyond the vehicle's steering limit "
                    f"delta_max={delta_max:g} rad (steering in rad, at the wheels; or set "
                    "vehicle.delta_max; a steering-wheel angle needs steering_ratio=, one "
                    "in degrees units.delta=deg)")


def check_steering(delta: np.ndarray, delta_max: float, source: str | None = None) -> None:
    """Refuse a steering angle beyond the vehicle's limit ``delta_max``, naming the row."""
    over = np.abs(delta) > delta_max * (1 + STEERING_SLACK)
    if over.any():
        r = int(np.flatnonzero(over)[0])
        raise _steering(_at(source, f"row {r}"), float(delta[r]), delta_max)


def check_samples(m: np.ndarray, u: np.ndarray, *, delta_max: float | None = None,
                  truth: np.ndarray | None = None, source: str | None = None) -> np.ndarray:
    """Check a log's values; return its fix rows (T,) bool.

    Parameters
    ----------
    m : (T, 3) ``[x_m, y_m, psi_m]``; a row all NaN is a step without a fix.
    u : (T, 2) ``[V, delta]``.
    delta_max : the vehicle's steering limit (rad); None: not checked (yet).
    truth : (T, 3) ``[x, y, psi]`` or None.
    source : prefix of the messages (``"input log.csv"``), None: none.

    Raises
    ------
    LboError
        The first of: NaN or inf in V, delta or the truth; inf in a fix; a partial fix; no fix
        at all; a heading column that looks like degrees (more than 1% of its rows beyond
        2 pi) or one heading beyond 2 pi; |x_m|, |y_m| (and |x|, |y|) beyond 1e7 m; |V| beyond
        100 m/s; |delta| beyond ``delta_max``.
    """
    _finite(u, INPUTS, source)
    if truth is not None:
        _finite(truth, TRUTH, source)
    _finite(np.where(np.isnan(m), 0.0, m), MEAS, source)  # inf; NaN is a missing fix
    fix = check_fixes(m, source)
    headings = [("psi_m", m[:, 2], fix)] + ([("psi", truth[:, 2], True)]
                                            if truth is not None else [])
    for c, psi, rows in headings:
        values = np.abs(psi)
        beyond = (values > 2 * np.pi) & rows
        if beyond.mean() > DEGREES_SHARE:
            raise LboError(_at(source, f"column {c!r} looks like degrees (|{c}| up to "
                                       f"{np.nanmax(values):g} > 2 pi); give headings in rad"))
        if beyond.any():
            r = int(np.flatnonzero(beyond)[0])
            raise _heading(_at(source, f"row {r}"), c, float(psi[r]))
    columns = {"x_m": m[:, 0], "y_m": m[:, 1], "V": u[:, 0]}
    if truth is not None:
        columns.update(x=truth[:, 0], y=truth[:, 1])
    for c, _, _, _ in RANGES:
        if c in columns:
            over = np.abs(columns[c]) > _RANGE[c][0]  # NaN (no fix) compares False
            if over.any():
                r = int(np.flatnonzero(over)[0])
                raise _beyond(_at(source, f"row {r}"), c, float(columns[c][r]))
    if delta_max is not None:
        check_steering(u[:, 1], delta_max, source)
    return fix


def check_sample(m: tuple[float, float, float] | None, u: tuple[float, float], step: int,
                 delta_max: float) -> bool:
    """The checks of :func:`check_samples` on one sample (plain floats, no numpy): whether it
    holds a fix. ``m`` None, or all NaN, is a step without a fix."""
    where = f"step {step}"
    v, delta = u
    if not (math.isfinite(v) and math.isfinite(delta)):
        raise LboError(f"{where}: input [V, delta] = [{v:g}, {delta:g}] has NaN or inf")
    fix = m is not None and not all(math.isnan(c) for c in m)
    if fix:
        if not all(math.isfinite(c) for c in m):
            bad = ", ".join(n for n, c in zip(MEAS, m) if not math.isfinite(c))
            raise LboError(f"{where}: measurement [{m[0]:g}, {m[1]:g}, {m[2]:g}] has NaN or "
                           f"inf ({bad}); pass measurement=None for a step without a fix")
        for c, value in (("x_m", m[0]), ("y_m", m[1])):
            if abs(value) > POSITION_LIMIT:
                raise _beyond(where, c, value)
        if abs(m[2]) > 2 * math.pi:
            raise _heading(where, "psi_m", m[2])
    if abs(v) > SPEED_LIMIT:
        raise _beyond(where, "V", v)
    if abs(delta) > delta_max * (1 + STEERING_SLACK):
        raise _steering(where, delta, delta_max)
    return fix


# --------------------------------------------------------------------------- time


def check_time(t: np.ndarray, source: str | None = None) -> None:
    """Refuse a ``t`` that is not strictly increasing, naming the row."""
    steps = np.diff(t)
    if (steps <= 0).any():
        j = int(np.flatnonzero(steps <= 0)[0])
        raise LboError(_at(source, f"column 't' is not strictly increasing (row {j + 1}: "
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
            raise LboError(_at(source, f"column 't' looks like {unit} (median step {median:g} "
                                       f"for dt={dt:g} s); give t in seconds"))


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
    fix = np.flatnonzero(np.isfinite(m).all(1))
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
    its chord) and 3.6 for one in km/h; the heading at the pair's middle points along the
    chord in lbo's convention (counter-clockwise from east), and along its mirror image
    about the diagonal for a compass bearing. Too few such pairs (a short or slow log):
    nothing is checked. t (T,), m (T, 3), u (T, 2); ``heading``: the convention the log was
    read in (named in the hint)."""
    i, j = _pairs(np.asarray(t, float), np.asarray(m, float))
    if len(i) < CONVENTION_MIN_PAIRS:
        return
    travelled = np.concatenate([[0.0], np.cumsum(0.5 * (u[1:, 0] + u[:-1, 0]) * np.diff(t))])
    chord = m[j, :2] - m[i, :2]
    ratio = float(np.median(np.abs(travelled[j] - travelled[i]) / np.hypot(*chord.T)))
    for unit, key, low, high in SPEED_SUSPECTS:
        if low <= ratio <= high:
            raise LboError(_at(source, f"column 'V' looks like {unit}: it travels {ratio:.2f} "
                                       "times the distance the fixes moved; give V in m/s, or "
                                       f"pass units.V={key}"))
    mid = m[(i + j) // 2, 2]
    has = np.isfinite(mid)
    if has.sum() < CONVENTION_MIN_PAIRS:
        return
    course = np.arctan2(chord[has, 1], chord[has, 0])
    along = float(np.median(np.cos(mid[has] - course)))
    mirrored = float(np.median(np.cos(np.pi / 2 - mid[has] - course)))
    if along < 0.3 and mirrored > 0.8:
        other = "compass" if heading == "enu" else "enu"
        raise LboError(_at(source, "column 'psi_m' does not point where the fixes move "
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
        raise LboError(_at(source, f"rows {j} and {j + 1} are {steps[j]:g} s apart "
                                   f"(t={t[j]:g} s to {t[j + 1]:g} s), longer than "
                                   f"max_gap={max_gap:g} s: V and delta cannot be "
                                   "interpolated across it; split the log there, or raise "
                                   "max_gap"))


# --------------------------------------------------------------------------- windows


def window_advice(name: str, window: int, dt: float) -> str:
    return (f"{name} needs a fix in every window of {window} steps ({window * dt:g} s); use an "
            "observer with a longer window, the robust one (experiment=robust), or a classical "
            "one")


def check_fix_windows(fix: np.ndarray, window: int, name: str, dt: float,
                      source: str | None = None) -> None:
    """Refuse a log in which a window of ``window`` steps after the first fix holds no fix:
    a learned observer's estimate there is NaN (the window has no fix to anchor it), whatever
    its model. Before the first fix no observer has an estimate; that is not refused."""
    at = np.flatnonzero(fix)
    gaps = np.diff(np.r_[at, len(fix)])  # steps to the next fix, or to the row past the end
    if not (gaps > window).any():
        return
    inner = gaps[:-1]
    if inner.size and inner.max() > window:
        j = int(np.argmax(inner))
        g = int(inner[j])
        raise LboError(_at(source, f"fixes are up to {g} steps ({g * dt:g} s) apart (rows "
                                   f"{at[j]} and {at[j + 1]}), but "
                                   + window_advice(name, window, dt)))
    last = int(at[-1])
    raise LboError(_at(source, f"the last {len(fix) - 1 - last} rows (after row {last}) have "
                               f"no fix, but {window_advice(name, window, dt)}; or cut the "
                               f"log at row {last}"))
