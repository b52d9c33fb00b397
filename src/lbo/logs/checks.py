"""The one validation path for a vehicle log, shared by ``python -m lbo.observe`` and
:class:`lbo.Observer` (its :meth:`~lbo.Observer.run` and :meth:`~lbo.Observer.step`).

The CLI reads a table and checks its columns (:mod:`lbo.observe`); everything about the
values is checked here, on arrays, so that a log refused by the CLI is refused by the library
with the same line, and a sample refused by :meth:`~lbo.Observer.step` is one that
:meth:`~lbo.Observer.run` refuses in a whole log. Every check raises one
:class:`~lbo.core.errors.LboError` line naming the row (or step), the column and the expected form.

Also here: the checks of the settings shared by the CLI and the API (``alpha``, ``device``).
A log's units and conventions (time, speed, heading) are checked in :mod:`lbo.logs.units`.
This module imports numpy only (torch only to ask whether CUDA is there).
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from lbo.core.errors import LboError, located
from lbo.logs.units import check_heading_unit
from lbo.sim.columns import INPUT, MEAS, RECEIVER, STATE
from lbo.sim.schema import FIX_RULE, check_fixes

GYRO_LIMIT = 10.0
"""Largest |r_m| (rad/s): a car's yaw rate stays within 2 rad/s; beyond 10, the gyro is in
deg/s or the column is not a yaw rate."""
POSITION_LIMIT = 1e7
"""Largest |x|, |y| (m): positions are metres in a local frame, not degrees nor UTM in mm."""
SPEED_LIMIT = 100.0
"""Largest |V| (m/s)."""
HEADING_LIMIT = 1e6
"""Largest |heading| (rad) of a log: a heading may sit on any branch (a logger that
accumulates it passes 2 pi after one lap), but beyond this float64 no longer resolves it."""
DT = 0.02
"""Period (s) of a log's rows where no ``t`` is given (lbo's dt)."""
STEERING_SLACK = 1e-6
"""Relative slack on the steering limit (a delta_max written with rounding)."""
RANGES = (("x_m", POSITION_LIMIT, "m", "positions are metres in a local frame"),
          ("y_m", POSITION_LIMIT, "m", "positions are metres in a local frame"),
          ("x", POSITION_LIMIT, "m", "positions are metres in a local frame"),
          ("y", POSITION_LIMIT, "m", "positions are metres in a local frame"),
          ("V", SPEED_LIMIT, "m/s", "no road vehicle is that fast; speeds are in m/s"))
"""(column, largest |value|, unit, why) of the physical range checks of a log."""
_RANGE = {c: (limit, unit, why) for c, limit, unit, why in RANGES}

POSITION_SIGMA_LIMIT = 1e4
"""Largest reported 1-sigma of a position, sx_m and sy_m (m): a fix known no better than
10 km is no GNSS fix (a receiver without one may report a sentinel such as 4295 km: leave its
x_m, y_m empty). Unbounded, a sigma past 1.3e154 squares to inf and every estimate after the
next fix turns NaN."""
HEADING_SIGMA_LIMIT = 1.0
"""Largest reported 1-sigma of a heading, spsi_m (rad): a heading known no better than 57 deg
is none, and a first fix's variance beyond 1 rad^2 breaks the unscented filter's circular
mean (:data:`lbo.filters.start.HEADING_VAR0`; at 1.5 rad it diverged)."""
SPEED_SIGMA_LIMIT = SPEED_LIMIT
"""Largest reported 1-sigma of a velocity, sv_m (m/s): the fastest speed's (a velocity gives
a course only where it is 5 sigma, so past 20 m/s it gives none anyway)."""
SIGMA_LIMITS = {"sx_m": (POSITION_SIGMA_LIMIT, "m"), "sy_m": (POSITION_SIGMA_LIMIT, "m"),
                "spsi_m": (HEADING_SIGMA_LIMIT, "rad"), "sv_m": (SPEED_SIGMA_LIMIT, "m/s")}
"""The accuracy channels of :data:`RECEIVER`: (largest 1-sigma, unit); each in (0, limit]."""
RECEIVER_RULE = ("an accuracy comes with what it is the accuracy of (sx_m and sy_m in (0, "
                 f"{POSITION_SIGMA_LIMIT:g}] m with x_m, y_m; spsi_m in (0, "
                 f"{HEADING_SIGMA_LIMIT:g}] rad with psi_m), a velocity as ve_m and vn_m "
                 f"(m/s, at most {SPEED_LIMIT:g} each) with an optional sv_m in (0, "
                 f"{SPEED_SIGMA_LIMIT:g}] m/s")

DEVICE = re.compile(r"cpu|cuda(:[0-9]+)?")


# --------------------------------------------------------------------------- settings


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


# --------------------------------------------------------------------------- whole logs


def _finite(values: np.ndarray, names: tuple[str, ...], source: str | None) -> None:
    for c, name in enumerate(names):
        bad = ~np.isfinite(values[:, c])
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise LboError(located(source, f"column {name!r} has NaN or inf (first at row "
                                           f"{first})"))


def fix_mask(m: Any) -> Any:
    """Which rows hold a full fix, the learned observers' (a position fix without a heading is
    for the classical ones, :func:`position_mask`): (..., C) measurements whose first three
    channels are ``x_m, y_m, psi_m`` (C >= 3, a NumPy array or a torch tensor) -> (...) bool,
    True where all three hold a finite value. A step without a fix leaves them NaN."""
    head = m[..., :3]
    if isinstance(head, np.ndarray):
        return np.isfinite(head).all(-1)
    return head.isfinite().all(-1)  # a torch tensor, without importing torch here


def fix_period(rate: float, dt: float) -> int:
    """Steps of ``dt`` between position fixes at ``rate`` Hz (>= 1: a rate of 1/dt or more is
    a fix at every step)."""
    return max(1, int(round(1.0 / (rate * dt))))


def position_mask(m: np.ndarray) -> np.ndarray:
    """Which rows hold a position (x_m and y_m finite): (..., C) -> (...) bool."""
    return np.isfinite(m[..., 0]) & np.isfinite(m[..., 1])


def _beyond(where: str, column: str, value: float) -> LboError:
    limit, unit, why = _RANGE[column]
    return LboError(f"{where}: {column}={value:g} {unit} is beyond {limit:g} {unit} ({why})")


def _heading(where: str, column: str, value: float) -> LboError:
    # one sample has no rate of turn to tell degrees from an accumulated heading in rad by
    return LboError(f"{where}: {column}={value:g} rad is outside [-2 pi, 2 pi]; step takes "
                    "a heading in rad wrapped within it (a whole log, on any branch)")


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
        raise _steering(located(source, f"row {r}"), float(delta[r]), delta_max)


def check_samples(m: np.ndarray, u: np.ndarray, *, delta_max: float | None = None,
                  truth: np.ndarray | None = None, source: str | None = None,
                  t: np.ndarray | None = None, dt: float = DT,
                  position_only: bool = True) -> np.ndarray:
    """Check a log's values; return its fix rows (T,) bool: those holding a position.

    Parameters
    ----------
    m : (T, 3) ``[x_m, y_m, psi_m]``; a row all NaN is a step without a fix, one with only
        psi_m NaN a position fix without a heading (refused unless ``position_only``).
    u : (T, 2) ``[V, delta]``.
    delta_max : the vehicle's steering limit (rad); None: not checked (yet).
    truth : (T, 3) ``[x, y, psi]`` or None.
    source : prefix of the messages (``"input log.csv"``), None: none.
    t : (T,) times (s) of the rows, or None: rows ``dt`` apart.
    position_only : whether a fix may lack its heading (the classical observers take it;
        a training set for a learned observer does not).

    Headings are rad on any branch (wrapped, or accumulated past 2 pi by a logger).

    Raises
    ------
    LboError
        The first of: NaN or inf in V, delta or the truth; inf in a fix; a heading without a
        position, x_m without y_m (or a position without a heading, unless
        ``position_only``); no fix at all; a heading beyond 1e6 rad; a heading column that
        looks like degrees by how fast it turns (:func:`check_heading_unit`); |x_m|, |y_m|
        (and |x|, |y|) beyond 1e7 m; |V| beyond 100 m/s; |delta| beyond ``delta_max``.
    """
    _finite(u, INPUT, source)
    if truth is not None:
        _finite(truth, STATE, source)
    _finite(np.where(np.isnan(m), 0.0, m), MEAS, source)  # inf; NaN is a missing fix
    fix = check_fixes(m, source, position_only)
    headings = [("psi_m", m[:, 2], np.isfinite(m[:, 2]))] + ([("psi", truth[:, 2], True)]
                                            if truth is not None else [])
    times = np.arange(len(m)) * dt if t is None else np.asarray(t, float)
    for c, psi, rows in headings:
        beyond = (np.abs(psi) > HEADING_LIMIT) & rows
        if beyond.any():
            r = int(np.flatnonzero(beyond)[0])
            raise LboError(located(source, f"row {r}: {c}={psi[r]:g} rad is beyond "
                                       f"{HEADING_LIMIT:g} rad (a heading in rad, on any branch)"))
        check_heading_unit(np.where(rows, psi, np.nan), times, c, source)
    columns = {"x_m": m[:, 0], "y_m": m[:, 1], "V": u[:, 0]}
    if truth is not None:
        columns.update(x=truth[:, 0], y=truth[:, 1])
    for c, _, _, _ in RANGES:
        if c in columns:
            over = np.abs(columns[c]) > _RANGE[c][0]  # NaN (no fix) compares False
            if over.any():
                r = int(np.flatnonzero(over)[0])
                raise _beyond(located(source, f"row {r}"), c, float(columns[c][r]))
    if delta_max is not None:
        check_steering(u[:, 1], delta_max, source)
    return fix


def check_receiver(m: np.ndarray, r: np.ndarray, source: str | None = None) -> None:
    """Refuse a receiver's channels that break :data:`RECEIVER_RULE`, naming the first row.

    m : (T, 3) ``[x_m, y_m, psi_m]``, NaN where not held.
    r : (T, 7) :data:`RECEIVER`, NaN where not held.

    One :class:`LboError` line for the first of: inf anywhere; sx_m without sy_m (or the
    reverse); an accuracy without the fix (or heading) it is of; vn_m without ve_m (or the
    reverse); sv_m without a velocity; a sigma outside (0, its limit] (:data:`SIGMA_LIMITS`:
    10 km for sx_m, sy_m, 1 rad for spsi_m, 100 m/s for sv_m); a velocity beyond 100 m/s; a
    yaw rate beyond 10 rad/s."""
    m = np.asarray(m, dtype=float)
    r = np.asarray(r, dtype=float)
    _finite(np.where(np.isnan(r), 0.0, r), RECEIVER, source)
    has = np.isfinite(r)
    sx, sy, spsi, ve, vn, sv, _ = has.T
    pos = np.isfinite(m[:, 0]) & np.isfinite(m[:, 1])
    rules = [
        (sx & ~sy, "has sx_m without sy_m"), (sy & ~sx, "has sy_m without sx_m"),
        ((sx | sy) & ~pos, "has an accuracy (sx_m, sy_m) without a position fix (x_m, y_m)"),
        (spsi & ~np.isfinite(m[:, 2]), "has spsi_m without a heading psi_m"),
        (ve & ~vn, "has ve_m without vn_m"), (vn & ~ve, "has vn_m without ve_m"),
        (sv & ~(ve & vn), "has sv_m without a velocity (ve_m, vn_m)"),
    ]
    for c in (0, 1, 2, 5):  # a 1-sigma in (0, limit]; NaN (not held) passes
        limit = SIGMA_LIMITS[RECEIVER[c]][0]
        sigma = np.where(has[:, c], r[:, c], 1.0)
        rules.append((~((sigma > 0) & (sigma <= limit)), RECEIVER[c]))
    for c in (3, 4, 6):
        limit = GYRO_LIMIT if c == 6 else SPEED_LIMIT
        rules.append((np.abs(np.where(has[:, c], r[:, c], 0.0)) > limit, RECEIVER[c]))
    firsts = [(int(np.argmax(bad)), i) for i, (bad, _) in enumerate(rules) if bad.any()]
    if not firsts:
        return
    row, i = min(firsts)
    what = rules[i][1]
    if what in RECEIVER:
        c = RECEIVER.index(what)
        value = float(r[row, c])
        limit, unit = SIGMA_LIMITS.get(what, (0.0, ""))
        what = (f"has {what}={value:g} {unit}, not a 1-sigma in (0, {limit:g}] {unit}"
                if c not in (3, 4, 6) else
                f"has {what}={value:g} m/s, beyond {SPEED_LIMIT:g} m/s" if c != 6 else
                f"has r_m={value:g} rad/s, beyond {GYRO_LIMIT:g} rad/s (a yaw rate in rad/s)")
    raise LboError(located(source, f"row {row} {what}; {RECEIVER_RULE}"))


def check_sample(m: tuple[float, float, float] | None, u: tuple[float, float], step: int,
                 delta_max: float) -> bool:
    """The checks of :func:`check_samples` on one sample (plain floats, no numpy): whether it
    holds a position fix. ``m`` None, or all NaN, is a step without a fix; NaN in psi_m alone
    a position fix without a heading."""
    where = f"step {step}"
    v, delta = u
    if not (math.isfinite(v) and math.isfinite(delta)):
        raise LboError(f"{where}: input [V, delta] = [{v:g}, {delta:g}] has NaN or inf")
    fix = m is not None and not all(math.isnan(c) for c in m)
    if fix and m is not None:  # a fix has an m
        if any(math.isinf(c) for c in m):
            bad = ", ".join(n for n, c in zip(MEAS, m) if math.isinf(c))
            raise LboError(f"{where}: measurement [{m[0]:g}, {m[1]:g}, {m[2]:g}] has inf "
                           f"({bad}); pass measurement=None for a step without a fix")
        x, y, psi = (not math.isnan(c) for c in m)
        if x != y:
            have, lack = ("x_m", "y_m") if x else ("y_m", "x_m")
            raise LboError(f"{where}: measurement [{m[0]:g}, {m[1]:g}, {m[2]:g}] has {have} "
                           f"without {lack}; {FIX_RULE.replace('a row', 'a sample')}")
        if not x:
            raise LboError(f"{where}: measurement [{m[0]:g}, {m[1]:g}, {m[2]:g}] has a heading "
                           f"without a position; {FIX_RULE.replace('a row', 'a sample')}")
        for c, value in (("x_m", m[0]), ("y_m", m[1])):
            if abs(value) > POSITION_LIMIT:
                raise _beyond(where, c, value)
        if psi and abs(m[2]) > 2 * math.pi:
            raise _heading(where, "psi_m", m[2])
    if abs(v) > SPEED_LIMIT:
        raise _beyond(where, "V", v)
    if abs(delta) > delta_max * (1 + STEERING_SLACK):
        raise _steering(where, delta, delta_max)
    return fix


# --------------------------------------------------------------------------- time


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
        raise LboError(located(source, f"fixes are up to {g} steps ({g * dt:g} s) apart (rows "
                                   f"{at[j]} and {at[j + 1]}), but "
                                   + window_advice(name, window, dt)))
    last = int(at[-1])
    raise LboError(located(source, f"the last {len(fix) - 1 - last} rows (after row {last}) have "
                               f"no fix, but {window_advice(name, window, dt)}; or cut the "
                               f"log at row {last}"))
