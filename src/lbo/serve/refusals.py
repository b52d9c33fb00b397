"""Why an observer refuses a sample or a log, in one line each: the text of the errors that
:class:`lbo.Observer` and ``lbo.observe`` raise, naming the observers that take it, and the
checks of one sample and of a whole log against an observer (:func:`checked_sample`,
:func:`checked_log`)."""

from __future__ import annotations

from typing import Any, cast

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters import classical
from lbo.logs.checks import check_fix_windows, check_receiver, check_sample, check_samples
from lbo.serve.rows import as_arrays
from lbo.sim.columns import RECEIVER

_ALSO = ("the robust observer (filternet) in its recursive form, and a CNN, LSTM or window "
         "filter trained on a receiver (experiment=receiver)")
"""The learned observers that take a receiver's channels."""


def no_heading(name: str) -> str:
    """Why a learned observer refuses a position fix without a heading."""
    return (f"a position fix without a heading (psi_m empty), but {name} takes full fixes "
            f"only (x_m, y_m and psi_m); the classical observers "
            f"({', '.join(classical.OBSERVERS)}) take it, {_ALSO}")


def no_receiver(name: str) -> str:
    """Why a learned observer refuses a receiver's channels."""
    return (f"{name} does not take a receiver's channels; the classical observers "
            f"({', '.join(classical.OBSERVERS)}) do, {_ALSO}")


def no_fix(name: str) -> str:
    """Why an observer trained with a fix at every step refuses a step without one."""
    return (f"no fix, but {name} was trained with a fix at every step; use an observer trained "
            "with fix_rates (experiment=robust) or a classical one")


def blind_window(name: str, n: int, dt: float, carries: bool) -> str:
    """Why a net that reads a receiver gives no estimate for a window of ``n`` steps (period
    ``dt`` s) that holds no heading; ``carries``: a window filter, which carries its own
    estimate through a stop and so is blind only on a car that has stood since it began."""
    if carries:
        return (f"no heading in the last {n} steps ({n * dt:g} s), and no estimate before them "
                f"to carry: {name} reads the heading from its window's psi_m or course over "
                "ground, and a car that has stood or crept since it began gave none")
    return (f"no heading in the last {n} steps ({n * dt:g} s): {name} reads the heading from "
            "its window's psi_m or course over ground, and a car that stood or crept that long "
            "gave none (the window filter, model=filternet, carries its own through a stop)")


def checked_log(obs: Any, m: Any, u: Any, receiver: Any, source: str | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """A log as :meth:`lbo.Observer.run` takes it, checked for ``obs``: m (T, 3), u (T, 2)
    and receiver (T, 7) or None as float arrays, and which rows hold a position fix (T,)
    bool; else one line naming the row (:func:`lbo.logs.checks.check_samples` and the
    observer's own limits: a fix without a heading, a receiver's channels, a step without a
    fix, a window without one)."""
    where = f"{source}: " if source else ""
    m, receiver = as_arrays(m, receiver, "run")
    try:
        m = np.asarray(m, dtype=float)
        u = np.asarray(u, dtype=float)
    except (TypeError, ValueError):
        raise LboError(f"{where}run needs m (T, 3) and u (T, 2) of numbers") from None
    if m.ndim != 2 or m.shape[1] != 3 or u.shape != (len(m), 2):
        raise LboError(f"run needs m (T, 3) and u (T, 2), got {m.shape} and {u.shape}")
    fix = check_samples(m, u, delta_max=obs.vehicle.delta_max, source=source)
    if receiver is not None:
        receiver = np.asarray(receiver, dtype=float)
        if receiver.shape != (len(m), len(RECEIVER)):
            raise LboError(f"run needs receiver ({len(m)}, {len(RECEIVER)}) "
                           f"[{', '.join(RECEIVER)}], got {receiver.shape}")
        if not obs.takes_receiver:
            raise LboError(f"receiver: {no_receiver(obs.name)}")
        check_receiver(m, receiver, source)
    headless = fix & np.isnan(m[:, 2])
    if not obs.takes_receiver and headless.any():
        raise LboError(f"{where}row {int(np.argmax(headless))}: {no_heading(obs.name)}")
    if not fix.all() and not obs.takes_missing_fixes:
        raise LboError(f"{where}row {int(np.flatnonzero(~fix)[0])}: {no_fix(obs.name)}")
    if obs.net is not None and obs.form == "window":
        check_fix_windows(fix, obs.window, obs.name, obs.dt, source)
    return m, u, receiver, fix


def checked_sample(obs: Any, measurement: Any, input: Any, receiver: Any, k: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, bool]:
    """Sample ``k`` as :meth:`lbo.Observer.step` takes it, checked for ``obs``: m (3,) (a
    copy, its heading wrapped; NaN where the step has no fix), u (2,), the receiver's
    channels (7,) or None, and whether it holds a position fix; else one line naming the step
    (:func:`lbo.logs.checks.check_sample` and the observer's own limits, as
    :func:`checked_log`)."""
    measurement, receiver = as_arrays(measurement, receiver, f"step {k}")
    try:
        u = np.asarray(input, dtype=float).reshape(2)
        m = (None if measurement is None
             else np.asarray(measurement, dtype=float).reshape(3))
    except (TypeError, ValueError):
        raise LboError(f"step {k}: expected measurement [x_m, y_m, psi_m] (3 numbers, or "
                       f"None) and input [V, delta] (2 numbers), got {measurement!r} and "
                       f"{input!r}") from None
    fix = check_sample(None if m is None else tuple(m.tolist()), tuple(u.tolist()), k,
                       obs.vehicle.delta_max)
    if fix and not obs.takes_receiver and np.isnan(cast(np.ndarray, m)[2]):  # a fix: an m
        raise LboError(f"step {k}: {no_heading(obs.name)}")
    if not fix:
        if not obs.takes_missing_fixes:
            raise LboError(f"step {k}: {no_fix(obs.name)}")
        m = np.full(3, np.nan)
    else:  # one branch for every observer (absolute features read the angle itself)
        m = cast(np.ndarray, m).copy()  # never the caller's array
        m[2] = wrap_angle(m[2])
    if receiver is not None and not obs.takes_receiver:
        raise LboError(f"step {k}: {no_receiver(obs.name)}")
    return m, u, receiver, fix
