"""Logs in and estimates out: read a CSV or Parquet log and check it whole (columns, NaN, units,
ranges, the steering limit, the period), put it on the observer's grid (``resample``), and write a
table atomically. `python -m lbo.observe`, `python -m lbo.simulate` and the data sets built from
a user's logs (:mod:`lbo.logs.sets`) all read and write through here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import numpy as np
import pandas as pd

from lbo.core.angles import wrap_angle
from lbo.core.atomic import atomic_path
from lbo.core.errors import LboError
from lbo.logs.checks import check_receiver, check_samples
from lbo.logs.checks import check_steering as check_delta
from lbo.logs.units import MAX_GAP, check_conventions, check_gaps, check_time
from lbo.sim.columns import LOG, MEAS, RECEIVER, STATE
from lbo.sim.schema import check_outside_data_sets, check_values, write_set

FORMATS = (".csv", ".parquet")


LANDING = ((("x_m", "y_m"), (*MEAS, "sx_m", "sy_m", "spsi_m")),
           (("ve_m", "vn_m"), ("ve_m", "vn_m", "sv_m")), (("r_m",), ("r_m",)))
"""(key, columns) of the samples :func:`resample` never interpolates: a fix (its position, the
heading and accuracies that come with it), a GNSS velocity (with its sigma) and a gyro's
reading (the ``gyro`` observer holds each to the next)."""


DT_TOLERANCE = 0.01
"""Largest relative difference between the log's sampling period and the observer's dt."""


def _format(path: Path, field: str) -> str:
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise LboError(f"{field} must be a .csv or .parquet file, got {str(path)!r}")
    return suffix


def _column_names(raw: list[Any], path: Path) -> list[str]:
    """The header's names, stripped of spaces (``t, x_m``); a name given twice is refused
    (pandas would read the second ``x_m`` as ``x_m.1``, Arrow would refuse to pick one)."""
    names = [str(n).strip() for n in raw]
    names = [n if n else f"Unnamed: {i}" for i, n in enumerate(names)]
    seen: set[str] = set()
    for n in names:
        if n in seen:
            raise LboError(f"input {path}: column {n!r} appears more than once in the header; "
                           "keep one column of each name")
        seen.add(n)
    return names


def read_log(path: str | Path) -> pd.DataFrame:
    """Read a CSV or Parquet log; an unreadable or empty file, or a column name given twice,
    is one :class:`LboError`. Column names are stripped of surrounding spaces."""
    path = Path(path)
    suffix = _format(path, "input")
    if not path.is_file():
        raise LboError(f"input {path}: file not found")
    if path.stat().st_size == 0:
        raise LboError(f"input {path}: empty file (no header, no rows)")
    try:
        if suffix == ".csv":
            header = pd.read_csv(path, header=None, nrows=1, dtype=str, keep_default_na=False)
            names = _column_names(list(header.iloc[0]), path)
            df = pd.read_csv(path, header=0, names=names, skipinitialspace=True)
        else:
            import pyarrow.parquet as pq

            _column_names(pq.read_schema(path).names, path)  # (index columns among them)
            df = pd.read_parquet(path)
            df.columns = [str(c).strip() for c in df.columns]
    except LboError:
        raise
    except pd.errors.EmptyDataError:
        raise LboError(f"input {path}: empty file (no header, no rows)") from None
    except Exception as e:  # parser, Arrow, encoding: the file is not a readable table
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise LboError(f"input {path}: cannot read it as {suffix[1:]} ({reason})") from None
    if len(df) == 0:
        raise LboError(f"input {path}: empty file (a header, no rows)")
    return df


def check_log(df: pd.DataFrame, source: str = "input", heading: str = "enu",
              position_only: bool = True) -> bool:
    """Check a log's columns and values; return whether it holds the true ``x, y, psi``.

    A row whose ``x_m, y_m, psi_m`` are all empty (NaN) is a step without a position fix;
    one with ``psi_m`` alone empty a position fix without a heading, which the classical
    observers take (``position_only=False``: refused, as for a learned observer's training).
    Raises :class:`LboError` naming the first problem: missing columns (naming those found),
    a non-numeric column, ``t`` with NaN or inf or not strictly increasing, and the value
    checks of :func:`lbo.logs.checks.check_samples` (those :meth:`lbo.Observer.run` applies:
    NaN or inf other than a missing fix or heading, a heading without a position, x_m without
    y_m, no fix at all, a heading that
    looks like degrees, positions and speeds beyond any vehicle's), and a speed or heading
    that contradicts the fixes (:func:`lbo.logs.units.check_conventions`: km/h, a compass
    bearing; ``heading`` is the convention it was read in). The steering limit, the
    unit of ``t`` and the sampling period need the observer: :func:`check_steering`,
    :func:`lbo.logs.units.check_time_unit`, :func:`check_period`.
    """
    if len(df) == 0:
        raise LboError(f"{source}: empty file (no rows)")
    missing = [c for c in LOG if c not in df.columns]
    if missing:
        raise LboError(f"{source}: missing column{'s' if len(missing) > 1 else ''} "
                       f"{', '.join(missing)} (a log needs {', '.join(LOG)}; "
                       "t in s, x_m and y_m in m, psi_m in rad, V in m/s, delta in rad; "
                       f"found {', '.join(map(str, df.columns))})")
    truth = all(c in df.columns for c in STATE)
    check_values(df, ("t",), source, kinds="iuf")
    present = tuple(c for c in RECEIVER if c in df.columns)
    for c in ("V", "delta") + MEAS + (STATE if truth else ()) + present:
        if df[c].dtype.kind not in "iuf":
            raise LboError(f"{source}: column {c!r} is not numeric (dtype {df[c].dtype})")
    check_samples(df[list(MEAS)].to_numpy(dtype=float),
                  df[["V", "delta"]].to_numpy(dtype=float),
                  truth=df[list(STATE)].to_numpy(dtype=float) if truth else None,
                  source=source, t=df["t"].to_numpy(dtype=float), position_only=position_only)
    if present:
        # a log with a receiver column has receiver channels
        check_receiver(df[list(MEAS)].to_numpy(dtype=float), cast(np.ndarray, receiver(df)),
                       source)
    check_time(df["t"].to_numpy(dtype=float), source)
    check_conventions(df["t"].to_numpy(dtype=float), df[list(MEAS)].to_numpy(dtype=float),
                      df[["V", "delta"]].to_numpy(dtype=float), source, heading)
    return truth


def receiver(df: pd.DataFrame) -> np.ndarray | None:
    """A log's receiver channels (T, 7) in :data:`RECEIVER` order, NaN where a row (or
    the log) has none; None when the log has none of these columns."""
    if not any(c in df.columns for c in RECEIVER):
        return None
    return np.stack([df[c].to_numpy(dtype=float) if c in df.columns else np.full(len(df), np.nan)
                     for c in RECEIVER], axis=1)


def check_steering(df: pd.DataFrame, vehicle: Any, source: str = "input") -> None:
    """Refuse a steering angle beyond the vehicle's limit ``delta_max``, naming the row."""
    check_delta(df["delta"].to_numpy(dtype=float), vehicle.delta_max, source)


def check_output_path(output: str | Path, source: str | Path | None = None) -> Path:
    """The output path, checked: .csv or .parquet, not the input log ``source``, and not in a
    data-set cache (whose sets training and evaluation reuse as they are)."""
    output = Path(output)
    _format(output, "output")
    if source is not None and output.resolve() == Path(source).resolve():
        raise LboError(f"output must not be the input log ({source}): it would replace it")
    check_outside_data_sets(output=output)
    return output


def check_period(t: np.ndarray, dt: float, source: str = "input") -> None:
    """Refuse a log whose sampling period differs from ``dt`` by more than 1% anywhere."""
    if len(t) < 2:
        return
    steps = np.diff(t)
    off = np.abs(steps - dt) / dt
    if off.max() > DT_TOLERANCE:
        j = int(np.argmax(off))
        raise LboError(f"{source}: the sampling period ({np.median(steps):.6g} s median, "
                       f"{steps[j]:.6g} s between rows {j} and {j + 1}) differs from the "
                       f"observer's dt={dt:g} s by more than 1%; pass resample=true to "
                       f"interpolate the log to dt={dt:g} s")


def resample(df: pd.DataFrame, dt: float, columns: tuple[str, ...],
             max_gap: float | None = MAX_GAP, source: str = "input") -> pd.DataFrame:
    """``columns`` of a log on the grid ``t0, t0 + dt, ...`` up to its last ``t``.

    Fixes (``x_m, y_m, psi_m``, and the accuracies a receiver reports with them) and GNSS
    velocities are never interpolated (:data:`LANDING`): each lands on the grid row nearest to
    it, if within dt/2 (of several, the nearest wins); every other grid row is a step without
    one, also when the log had one on every row. The other columns (V, delta,
    the true state) are interpolated linearly; headings are unwrapped before and wrapped to
    (-pi, pi] after, so a jump from pi to -pi does not pass through 0.

    Raises
    ------
    LboError
        Two rows more than ``max_gap`` seconds apart (:func:`lbo.logs.units.check_gaps`): the
        inputs cannot be interpolated across a gap (None: not checked); a gap of at most
        ``dt`` never is.
    """
    t = df["t"].to_numpy(dtype=float)
    if max_gap is not None:
        check_gaps(t, max_gap, source, dt)
    n = int(np.floor((t[-1] - t[0]) / dt + 1e-9)) + 1
    grid = t[0] + dt * np.arange(n)
    out = {"t": grid}
    landed = {}
    for key, group in LANDING:
        names = [c for c in group if c in columns]
        if not names:
            continue
        # a sample lands on the grid row nearest to it, with what it carries (a fix's heading
        # and accuracies); it is held where its key columns are
        held = np.isfinite(df[[c for c in key if c in df.columns]].to_numpy(dtype=float)).all(1)
        at = np.round((t[held] - t[0]) / dt).astype(np.int64)
        off = np.abs(t[held] - (t[0] + dt * at))
        near = (at >= 0) & (at < n) & (off <= dt / 2 * (1 + 1e-9))
        rows, off, src = at[near], off[near], np.flatnonzero(held)[near]
        order = np.lexsort((off, rows))  # by grid row, the nearest sample first
        first = order[np.r_[True, rows[order][1:] != rows[order][:-1]]] if len(order) else order
        for c in names:
            landed[c] = (rows[first], src[first])
    for c in columns:
        v = df[c].to_numpy(dtype=float)
        if c in landed:
            out[c] = np.full(n, np.nan)
            out[c][landed[c][0]] = v[landed[c][1]]
        elif c == "psi":
            out[c] = wrap_angle(np.interp(grid, t, np.unwrap(v)))
        else:
            out[c] = np.interp(grid, t, v)
    return pd.DataFrame(out)


def plot_path(plot: Any, output: Path) -> Path | None:
    """Where ``plot=`` puts the figure: true, beside ``output`` (``est.csv`` -> ``est.png``);
    a path to a .png; false or null, nowhere."""
    if plot is None or plot is False:
        return None
    if plot is True:
        path = output.with_suffix(".png")
    elif isinstance(plot, str) and Path(plot).suffix.lower() == ".png":
        path = Path(plot)
    else:
        raise LboError(f"plot must be true, false or a .png file, got {plot!r}")
    check_outside_data_sets(plot=path)  # a figure there would sit among the cache's files
    return path


def write_table(df: pd.DataFrame, path: Path) -> Path:
    """Write CSV or Parquet by extension, atomically: a failed write leaves no file."""
    if path.suffix.lower() == ".parquet":
        return write_set(df, path)
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False)
    return path
