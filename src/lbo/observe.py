"""`python -m lbo.observe`: run an observer on your own vehicle log, write the estimates.

    python -m lbo.observe observer=<checkpoint | run id | models:/name/version | ekf | oracle |
        adaptive | ukf> input=my_log.csv output=estimates.csv [resample=true] [max_gap=0.5]

The log (CSV or Parquet) holds one row per sample with the columns ``t`` (s), ``x_m``,
``y_m`` (m), ``psi_m`` (rad), ``V`` (m/s) and ``delta`` (rad), and optionally the true
``x, y, psi``. A row with ``x_m, y_m, psi_m`` all empty is a step without a position fix
(GNSS slower than the inputs); the classical observers predict through it, and learned ones
trained with ``fix_rates`` take it. The whole log is checked before anything is written
(:mod:`lbo.logcheck`, the checks :class:`lbo.Observer` applies too); a failed run writes no
output file. The output has ``t, x, y, psi, valid``: ``valid`` is false before the first
fix, and on the first N-1 rows of a CNN or LSTM, whose window is not full yet (those rows
hold the EKF's estimate). An observer that knows how sure it is (every classical one, and the
robust observer) adds ``var_x, var_y`` (m^2), ``var_psi`` (rad^2) and ``cov_xy`` (m^2), its
covariance's entries; the CNN and the LSTM have none.

``smooth=true`` runs a Rauch-Tung-Striebel smoother after the filter (:mod:`lbo.smoother`),
for the best estimate of an offline log from every sample before and after each row: the
classical observers and the robust observer (in its recursive form) only. ``form=recursive``
runs the robust observer's filter from step to step instead of over a window per estimate.

``resample=true`` puts a log sampled at another (or an uneven) period onto the observer's
grid ``t0, t0 + dt, ...``: V and delta (and the true state) are interpolated linearly, but
never across a gap in ``t`` longer than ``max_gap`` seconds (0.5 s by default; such a log is
refused). Fixes are never interpolated: each lands on the grid row nearest to it (if within
dt/2), and every other row is a step without a fix, so an upsampled log has sparse fixes.
With the true state in the log, the RMSE per variable (over the valid rows) and the NRMSE
(E_ref: the paper's EKF, 0.24 m, 0.23 m, 4.1 mrad) are printed.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from lbo.atomic import atomic_path
from lbo.cli import entry
from lbo.errors import LboError
from lbo.logcheck import (
    DEGREES_SHARE,
    MAX_GAP,
    POSITION_LIMIT,
    RANGES,
    SPEED_LIMIT,
    check_alpha,
    check_conventions,
    check_device,
    check_gaps,
    check_max_gap,
    check_samples,
    check_time,
    check_time_unit,
)
from lbo.logcheck import check_steering as check_delta
from lbo.logformat import LogFormat
from lbo.metrics import PAPER_REFERENCE, nrmse, rmse
from lbo.schema import MEAS as MEAS_COLUMNS
from lbo.schema import check_values, write_set
from lbo.vehicle import wrap_angle

__all__ = ["DEGREES_SHARE", "DT_TOLERANCE", "FORMATS", "LOG_COLUMNS", "MAX_GAP",
           "OUTPUT_COLUMNS", "POSITION_LIMIT", "RANGES", "SPEED_LIMIT", "TRUTH_COLUMNS",
           "check_log", "check_output_path", "check_period", "check_steering", "main",
           "read_log", "resample", "run", "write_table"]

LOG_COLUMNS = ("t", "x_m", "y_m", "psi_m", "V", "delta")
TRUTH_COLUMNS = ("x", "y", "psi")
OUTPUT_COLUMNS = ("t", "x", "y", "psi", "valid")
COVARIANCE_COLUMNS = ("var_x", "var_y", "var_psi", "cov_xy")
"""The covariance's entries an observer that gives one adds to the output."""
FORMATS = (".csv", ".parquet")
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


def check_log(df: pd.DataFrame, source: str = "input", heading: str = "enu") -> bool:
    """Check a log's columns and values; return whether it holds the true ``x, y, psi``.

    A row whose ``x_m, y_m, psi_m`` are all empty (NaN) is a step without a position fix.
    Raises :class:`LboError` naming the first problem: missing columns (naming those found),
    a non-numeric column, ``t`` with NaN or inf or not strictly increasing, and the value
    checks of :func:`lbo.logcheck.check_samples` (those :meth:`lbo.Observer.run` applies:
    NaN or inf other than a whole missing fix, a partial fix, no fix at all, a heading that
    looks like degrees, positions and speeds beyond any vehicle's), and a speed or heading
    that contradicts the fixes (:func:`lbo.logcheck.check_conventions`: km/h, a compass
    bearing; ``heading`` is the convention it was read in). The steering limit, the
    unit of ``t`` and the sampling period need the observer: :func:`check_steering`,
    :func:`lbo.logcheck.check_time_unit`, :func:`check_period`.
    """
    if len(df) == 0:
        raise LboError(f"{source}: empty file (no rows)")
    missing = [c for c in LOG_COLUMNS if c not in df.columns]
    if missing:
        raise LboError(f"{source}: missing column{'s' if len(missing) > 1 else ''} "
                       f"{', '.join(missing)} (a log needs {', '.join(LOG_COLUMNS)}; "
                       "t in s, x_m and y_m in m, psi_m in rad, V in m/s, delta in rad; "
                       f"found {', '.join(map(str, df.columns))})")
    truth = all(c in df.columns for c in TRUTH_COLUMNS)
    check_values(df, ("t",), source, kinds="iuf")
    for c in ("V", "delta") + MEAS_COLUMNS + (TRUTH_COLUMNS if truth else ()):
        if df[c].dtype.kind not in "iuf":
            raise LboError(f"{source}: column {c!r} is not numeric (dtype {df[c].dtype})")
    check_samples(df[list(MEAS_COLUMNS)].to_numpy(dtype=float),
                  df[["V", "delta"]].to_numpy(dtype=float),
                  truth=df[list(TRUTH_COLUMNS)].to_numpy(dtype=float) if truth else None,
                  source=source)
    check_time(df["t"].to_numpy(dtype=float), source)
    check_conventions(df["t"].to_numpy(dtype=float), df[list(MEAS_COLUMNS)].to_numpy(dtype=float),
                      df[["V", "delta"]].to_numpy(dtype=float), source, heading)
    return truth


def check_steering(df: pd.DataFrame, vehicle: Any, source: str = "input") -> None:
    """Refuse a steering angle beyond the vehicle's limit ``delta_max``, naming the row."""
    check_delta(df["delta"].to_numpy(dtype=float), vehicle.delta_max, source)


def check_output_path(output: str | Path, source: str | Path | None = None) -> Path:
    """The output path, checked: .csv or .parquet, and not the input log ``source``."""
    output = Path(output)
    _format(output, "output")
    if source is not None and output.resolve() == Path(source).resolve():
        raise LboError(f"output must not be the input log ({source}): it would replace it")
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

    Fixes (``x_m, y_m, psi_m``) are never interpolated: each fix lands on the grid row
    nearest to it, if within dt/2 (of several, the nearest wins); every other grid row is a
    step without a fix, also when the log had a fix on every row. The other columns (V, delta,
    the true state) are interpolated linearly; headings are unwrapped before and wrapped to
    (-pi, pi] after, so a jump from pi to -pi does not pass through 0.

    Raises
    ------
    LboError
        Two rows more than ``max_gap`` seconds apart (:func:`lbo.logcheck.check_gaps`): the
        inputs cannot be interpolated across a gap (None: not checked); a gap of at most
        ``dt`` never is.
    """
    t = df["t"].to_numpy(dtype=float)
    if max_gap is not None:
        check_gaps(t, max_gap, source, dt)
    n = int(np.floor((t[-1] - t[0]) / dt + 1e-9)) + 1
    grid = t[0] + dt * np.arange(n)
    out = {"t": grid}
    meas = [c for c in MEAS_COLUMNS if c in columns]
    if meas:
        fix = np.isfinite(df[meas].to_numpy(dtype=float)).all(1)
        at = np.round((t[fix] - t[0]) / dt).astype(np.int64)
        off = np.abs(t[fix] - (t[0] + dt * at))
        near = (at >= 0) & (at < n) & (off <= dt / 2 * (1 + 1e-9))
        rows, off, src = at[near], off[near], np.flatnonzero(fix)[near]
        order = np.lexsort((off, rows))  # by grid row, the nearest fix first
        first = order[np.r_[True, rows[order][1:] != rows[order][:-1]]] if len(order) else order
    for c in columns:
        v = df[c].to_numpy(dtype=float)
        if c in MEAS_COLUMNS:
            out[c] = np.full(n, np.nan)
            out[c][rows[first]] = v[src[first]]
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
        return output.with_suffix(".png")
    if isinstance(plot, str) and Path(plot).suffix.lower() == ".png":
        return Path(plot)
    raise LboError(f"plot must be true, false or a .png file, got {plot!r}")


def write_table(df: pd.DataFrame, path: Path) -> Path:
    """Write CSV or Parquet by extension, atomically: a failed write leaves no file."""
    if path.suffix.lower() == ".parquet":
        return write_set(df, path)
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False)
    return path


def run(cfg: DictConfig) -> dict[str, Any]:
    """Observe the log ``cfg.input`` with ``cfg.observer`` and write ``cfg.output``.

    Returns
    -------
    ``output`` (Path), ``observer`` (name), ``rows``, ``valid`` (rows with a full window),
    and, when the log holds the true state, ``rmse`` (3,) (m, m, rad) and ``nrmse``.
    """
    from lbo.classical import OBSERVERS as CLASSICAL
    from lbo.noise import Noise
    from lbo.observer import Observer
    from lbo.vehicle import Vehicle

    for field in ("observer", "input", "output"):
        if cfg.get(field) is None or str(cfg.get(field)) == "":
            raise LboError(f"{field} must be given: python -m lbo.observe observer=<checkpoint "
                           "| run id | models:/name/version | ekf | oracle | adaptive | ukf> "
                           "input=<log.csv|.parquet> output=<estimates.csv|.parquet>")
    if not isinstance(cfg.observer, str):  # e.g. a run id of digits only
        raise LboError(f"observer: Hydra read {cfg.observer!r} as a number; quote it: "
                       "observer=\"'<run id>'\"")
    source = str(cfg.input)
    name = str(cfg.observer)
    classical = name in CLASSICAL
    # the settings first: no log nor checkpoint is read for a run that cannot go on
    alpha = check_alpha(cfg.alpha)
    device = check_device(cfg.get("device", "cpu"), probe=not classical)
    max_gap = check_max_gap(cfg.get("max_gap", MAX_GAP))
    output = check_output_path(str(cfg.output), source)
    plot = plot_path(cfg.get("plot"), output)
    smooth = cfg.get("smooth", False)
    if not isinstance(smooth, bool):
        raise LboError(f"smooth must be true or false, got {smooth!r}")
    form = cfg.get("form")
    fmt = LogFormat.from_cfg(cfg)
    where = f"input {source}"
    df, origin = fmt.apply(read_log(source), where)
    truth = check_log(df, where, fmt.heading)

    vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
    kw = {"alpha": alpha, "features": cfg.get("features"), "device": device}
    obs = Observer.load(name, vehicle if classical else None, noise if classical else None,
                        form=form, **kw)
    if smooth and form is None and obs.form == "window" and getattr(obs.net, "physical", False):
        # the form that has a filter to smooth, from the net already read
        obs = Observer(obs.name, obs.vehicle, obs.noise, net=obs.net, alpha=alpha,
                       engine=obs.engine, device=device, meta=obs.meta, form="recursive")
    check_steering(df, obs.vehicle, where)
    check_time_unit(df["t"].to_numpy(dtype=float), obs.dt, where)
    columns = LOG_COLUMNS[1:] + (TRUTH_COLUMNS if truth else ())
    if cfg.resample:
        df = resample(df, obs.dt, columns, max_gap, where)
    check_period(df["t"].to_numpy(dtype=float), obs.dt, where)

    m = df[["x_m", "y_m", "psi_m"]].to_numpy(dtype=float)
    u = df[["V", "delta"]].to_numpy(dtype=float)
    est, valid, cov = obs.run(m, u, source=where, cov=True, smooth=smooth)
    result: dict[str, Any] = {"output": output, "observer": obs.name, "rows": len(df),
                              "valid": int(valid.sum())}
    if truth:
        z = df[list(TRUTH_COLUMNS)].to_numpy(dtype=float)
        result["rmse"] = rmse(est, z, valid)
        result["nrmse"] = nrmse(result["rmse"]) if valid.any() else float("nan")
    out = pd.DataFrame({"t": df["t"].to_numpy(dtype=float), "x": est[:, 0], "y": est[:, 1],
                        "psi": est[:, 2], "valid": valid})
    if obs.gives_covariance:
        for name_, (i, j) in zip(COVARIANCE_COLUMNS, ((0, 0), (1, 1), (2, 2), (0, 1))):
            out[name_] = cov[:, i, j]
    if origin is not None:  # the estimate where the log's positions were: degrees
        out["lat"], out["lon"] = origin.to_geodetic(est[:, 0], est[:, 1])
    write_table(out, output)
    if plot is not None:
        from lbo import plots

        plots.save(plots.observed_log(out["t"].to_numpy(), m, np.where(valid[:, None], est, np.nan),
                                      obs.name, df[list(TRUTH_COLUMNS)].to_numpy(dtype=float)
                                      if truth else None, cov if obs.gives_covariance else None),
                   plot)

    what = (f"learned, window {obs.window}, features {obs.features}" if obs.kind == "learned"
            else f"classical, noise {obs.noise.name}, wheelbase {obs.vehicle.wheelbase:g} m")
    print(f"observer {obs.name} ({what}, dt {obs.dt:g} s) on {len(df)} rows"
          + (f" (resampled from {source})" if cfg.resample else "")
          + (", smoothed (RTS)" if smooth else ""))
    if not fmt.is_plain or origin is not None:
        print("read as: " + ", ".join(filter(None, [fmt.describe(), origin and (
            f"lat/lon -> metres east/north of {origin.lat:.7f}, {origin.lon:.7f}")])))
    fix = np.isfinite(m).all(1)
    duration = len(df) * obs.dt
    print(f"fixes: {int(fix.sum())} of {len(df)} rows ({fix.sum() / duration:.3g} Hz; inputs "
          f"at {1 / obs.dt:g} Hz)")
    if obs.kind == "learned":
        asked = (vehicle, noise.process_sigma, noise.measurement_sigma)
        if asked != (obs.vehicle, obs.noise.process_sigma, obs.noise.measurement_sigma):
            print("note: a learned observer keeps its checkpoint's vehicle and noise "
                  f"(noise {obs.noise.name}, wheelbase {obs.vehicle.wheelbase:g} m); "
                  "vehicle= and noise= apply to the classical observers")
    if result["valid"] < len(df):
        print(f"valid: {result['valid']} of {len(df)} rows; the others (before the first fix, "
              "or a learned observer's window not yet full) are not scored")
    if truth and not valid.any():
        print(f"rmse: no valid row to score (the log is shorter than the window, "
              f"N={obs.window})")
    elif truth:
        e = result["rmse"]
        print(f"rmse x {e[0]:.6g} m, y {e[1]:.6g} m, psi {e[2]:.6g} rad "
              f"({result['valid']} valid rows)")
        print(f"nrmse {result['nrmse']:.6g} (E_ref: the paper's EKF, {PAPER_REFERENCE[0]} m, "
              f"{PAPER_REFERENCE[1]} m, {PAPER_REFERENCE[2] * 1e3:g} mrad)")
    print(f"observed: {output}" + (f"; plot: {plot}" if plot is not None else ""))
    return result


main = entry("observe", run)


if __name__ == "__main__":
    sys.exit(main())
