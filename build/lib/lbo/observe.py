"""`python -m lbo.observe`: run an observer on your own vehicle log, write the estimates.

    python -m lbo.observe observer=<checkpoint | run id | models:/name/version | ekf | oracle |
        adaptive | ukf> input=my_log.csv output=estimates.csv [resample=true]

The log (CSV or Parquet) holds one row per sample with the columns ``t`` (s), ``x_m``,
``y_m`` (m), ``psi_m`` (rad), ``V`` (m/s) and ``delta`` (rad), and optionally the true
``x, y, psi``. A row with ``x_m, y_m, psi_m`` all empty is a step without a position fix
(GNSS slower than the inputs); the classical observers predict through it, and learned ones
trained with ``fix_rates`` take it. The whole log is checked before anything is written; a
failed run writes no output file. The output has ``t, x, y, psi, valid``: ``valid`` is false
before the first fix, and on the first N-1 rows of a CNN or LSTM, whose window is not full
yet (those rows hold the EKF's estimate).
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
from lbo.metrics import PAPER_REFERENCE, nrmse, rmse
from lbo.schema import MEAS as MEAS_COLUMNS
from lbo.schema import check_values, fix_rows, write_set
from lbo.vehicle import wrap_angle

LOG_COLUMNS = ("t", "x_m", "y_m", "psi_m", "V", "delta")
TRUTH_COLUMNS = ("x", "y", "psi")
OUTPUT_COLUMNS = ("t", "x", "y", "psi", "valid")
FORMATS = (".csv", ".parquet")
DEGREES_SHARE = 0.01
"""A heading column with more than this share of rows beyond 2 pi looks like degrees; fewer
are outliers, named by row."""
POSITION_LIMIT = 1e7
SPEED_LIMIT = 100.0
RANGES = (("x_m", POSITION_LIMIT, "m", "positions are metres in a local frame"),
          ("y_m", POSITION_LIMIT, "m", "positions are metres in a local frame"),
          ("x", POSITION_LIMIT, "m", "positions are metres in a local frame"),
          ("y", POSITION_LIMIT, "m", "positions are metres in a local frame"),
          ("V", SPEED_LIMIT, "m/s", "no road vehicle is that fast; speeds are in m/s"))
"""(column, largest |value|, unit, why) of the physical range checks of a log."""
DT_TOLERANCE = 0.01
"""Largest relative difference between the log's sampling period and the observer's dt."""


def _format(path: Path, field: str) -> str:
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise LboError(f"{field} must be a .csv or .parquet file, got {str(path)!r}")
    return suffix


def read_log(path: str | Path) -> pd.DataFrame:
    """Read a CSV or Parquet log; an unreadable or empty file is one :class:`LboError`."""
    path = Path(path)
    suffix = _format(path, "input")
    if not path.is_file():
        raise LboError(f"input {path}: file not found")
    if path.stat().st_size == 0:
        raise LboError(f"input {path}: empty file (no header, no rows)")
    try:
        df = pd.read_csv(path) if suffix == ".csv" else pd.read_parquet(path)
    except pd.errors.EmptyDataError:
        raise LboError(f"input {path}: empty file (no header, no rows)") from None
    except Exception as e:  # parser, Arrow, encoding: the file is not a readable table
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise LboError(f"input {path}: cannot read it as {suffix[1:]} ({reason})") from None
    if len(df) == 0:
        raise LboError(f"input {path}: empty file (a header, no rows)")
    return df


def check_log(df: pd.DataFrame, source: str = "input") -> bool:
    """Check a log's columns and values; return whether it holds the true ``x, y, psi``.

    A row whose ``x_m, y_m, psi_m`` are all empty (NaN) is a step without a position fix.
    Raises :class:`LboError` naming the first problem: missing columns, a non-numeric
    column, NaN or inf (other than a whole missing fix), a partial fix, no fix at all,
    ``t`` not strictly increasing, a heading that looks like degrees (|psi| > 2 pi). The
    sampling period is checked by :func:`check_period`.
    """
    if len(df) == 0:
        raise LboError(f"{source}: empty file (no rows)")
    missing = [c for c in LOG_COLUMNS if c not in df.columns]
    if missing:
        raise LboError(f"{source}: missing column{'s' if len(missing) > 1 else ''} "
                       f"{', '.join(missing)} (a log needs {', '.join(LOG_COLUMNS)}; "
                       "t in s, x_m and y_m in m, psi_m in rad, V in m/s, delta in rad)")
    truth = all(c in df.columns for c in TRUTH_COLUMNS)
    check_values(df, ("t", "V", "delta") + (TRUTH_COLUMNS if truth else ()), source,
                 kinds="iuf")
    check_values(df.fillna({c: 0.0 for c in MEAS_COLUMNS}), MEAS_COLUMNS, source,
                 kinds="iuf")  # numeric, no inf
    fix = fix_rows(df, source)
    t = df["t"].to_numpy(dtype=float)
    steps = np.diff(t)
    if (steps <= 0).any():
        j = int(np.flatnonzero(steps <= 0)[0])
        raise LboError(f"{source}: column 't' is not strictly increasing (row {j + 1}: "
                       f"t={t[j + 1]:g} s after t={t[j]:g} s); sort the log and drop repeats")
    for c in ("psi_m", "psi") if truth else ("psi_m",):
        values = np.abs(df[c].to_numpy(dtype=float))
        beyond = (values > 2 * np.pi) & (fix if c == "psi_m" else True)
        if beyond.mean() > DEGREES_SHARE:
            raise LboError(f"{source}: column {c!r} looks like degrees (|{c}| up to "
                           f"{np.nanmax(values):g} > 2 pi); give headings in rad")
        if beyond.any():
            r = int(np.flatnonzero(beyond)[0])
            raise LboError(f"{source}: row {r}: {c}={df[c].iloc[r]:g} rad is outside "
                           "[-2 pi, 2 pi]; a heading in rad lies within it")
    for c, limit, unit, what in RANGES:
        if c not in df.columns or (c in TRUTH_COLUMNS and not truth):
            continue
        values = np.abs(df[c].to_numpy(dtype=float))
        if (values > limit).any():
            r = int(np.flatnonzero(values > limit)[0])
            raise LboError(f"{source}: row {r}: {c}={df[c].iloc[r]:g} {unit} is beyond "
                           f"{limit:g} {unit} ({what})")
    return truth


def check_steering(df: pd.DataFrame, vehicle: Any, source: str = "input") -> None:
    """Refuse a steering angle beyond the vehicle's limit ``delta_max``, naming the row."""
    delta = np.abs(df["delta"].to_numpy(dtype=float))
    over = delta > vehicle.delta_max * (1 + 1e-6)
    if over.any():
        r = int(np.flatnonzero(over)[0])
        raise LboError(f"{source}: row {r}: delta={df['delta'].iloc[r]:g} rad is beyond the "
                       f"vehicle's steering limit delta_max={vehicle.delta_max:g} rad "
                       "(steering in rad, at the wheels; or set vehicle.delta_max)")


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


def resample(df: pd.DataFrame, dt: float, columns: tuple[str, ...]) -> pd.DataFrame:
    """Linear interpolation of ``columns`` onto ``t0, t0 + dt, ...`` up to the last ``t``.

    Headings are unwrapped before and wrapped to (-pi, pi] after, so a jump from pi to -pi
    does not pass through 0. In a log with missing fixes, each fix moves to its nearest row
    of the grid instead (the others stay empty).
    """
    t = df["t"].to_numpy(dtype=float)
    n = int(np.floor((t[-1] - t[0]) / dt + 1e-9)) + 1
    grid = t[0] + dt * np.arange(n)
    out = {"t": grid}
    meas = [c for c in MEAS_COLUMNS if c in columns]
    fix = np.isfinite(df[meas].to_numpy(dtype=float)).all(1)
    # fixes are not interpolated across gaps: each lands on its nearest row of the grid
    at = np.clip(np.round((t[fix] - t[0]) / dt).astype(np.int64), 0, n - 1)
    for c in columns:
        v = df[c].to_numpy(dtype=float)
        if c in MEAS_COLUMNS and not fix.all():
            out[c] = np.full(n, np.nan)
            out[c][at] = v[fix]
        elif c in ("psi_m", "psi"):
            out[c] = wrap_angle(np.interp(grid, t, np.unwrap(v)))
        else:
            out[c] = np.interp(grid, t, v)
    return pd.DataFrame(out)


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
    output = check_output_path(str(cfg.output), source)
    df = read_log(source)
    truth = check_log(df, f"input {source}")

    alpha = cfg.alpha
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or alpha < 0:
        raise LboError(f"alpha must be a number >= 0, got {alpha!r}")
    vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
    name = str(cfg.observer)
    classical = name in CLASSICAL
    obs = Observer.load(name, vehicle if classical else None, noise if classical else None,
                        alpha=float(alpha), features=cfg.get("features"),
                        device=str(cfg.get("device", "cpu")))
    check_steering(df, obs.vehicle, f"input {source}")
    columns = LOG_COLUMNS[1:] + (TRUTH_COLUMNS if truth else ())
    if cfg.resample:
        df = resample(df, obs.dt, columns)
    check_period(df["t"].to_numpy(dtype=float), obs.dt, f"input {source}")

    m = df[["x_m", "y_m", "psi_m"]].to_numpy(dtype=float)
    u = df[["V", "delta"]].to_numpy(dtype=float)
    est, valid = obs.run(m, u)
    result: dict[str, Any] = {"output": output, "observer": obs.name, "rows": len(df),
                              "valid": int(valid.sum())}
    if truth:
        z = df[list(TRUTH_COLUMNS)].to_numpy(dtype=float)
        result["rmse"] = rmse(est, z, valid)
        result["nrmse"] = nrmse(result["rmse"]) if valid.any() else float("nan")
    out = pd.DataFrame({"t": df["t"].to_numpy(dtype=float), "x": est[:, 0], "y": est[:, 1],
                        "psi": est[:, 2], "valid": valid})
    write_table(out, output)

    what = (f"learned, window {obs.window}, features {obs.features}" if obs.kind == "learned"
            else f"classical, noise {obs.noise.name}, wheelbase {obs.vehicle.wheelbase:g} m")
    print(f"observer {obs.name} ({what}, dt {obs.dt:g} s) on {len(df)} rows"
          + (f" (resampled from {source})" if cfg.resample else ""))
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
    print(f"observed: {output}")
    return result


main = entry("observe", run)


if __name__ == "__main__":
    sys.exit(main())
