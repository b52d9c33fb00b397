"""A real car drive as an lbo log: the onavdata package's HGuide n380 hill drive.

The onavdata package (PyPI; ``pip install 'lbo[real]'``) ships car drives recorded with a
tactical-grade INS/GNSS system, the Honeywell HGuide n380. lbo reads **only the hill drive**
(:data:`HILL`, 11 minutes up and down a hill, reversing included): the other is reserved for
acceptance and refused by name-check. Each holds, at 100 Hz, the INS/GNSS solution
(position, velocity, attitude) and the IMU's rates, and at 1 Hz the receiver's own fixes,
velocities and the 1-sigma accuracies it reports for them.

:func:`to_log` turns it into a log of lbo's form at the vehicle's ``dt`` (50 Hz):

- the receiver's fixes ``x_m, y_m`` (m east and north of the drive's first INS position), no
  heading (one antenna), with its accuracies ``sx_m, sy_m`` and velocities ``ve_m, vn_m``
  (sigma ``sv_m``: the RMS of its east and north sigmas), at the rows nearest to the time
  each fix was valid (see *time* below);
- the inputs: ``V``, the INS speed along the car's heading (signed: negative reversing; the
  drive has no wheel speed, which plays this part in a production car), and ``delta``, the
  steering angle that makes the kinematic bicycle turn at the gyro's yaw rate,
  ``atan(L r_m / V)`` (the drive has no steering angle either), with V floored at
  :data:`V_FLOOR` in magnitude and clipped to the vehicle's ``delta_max``;
- ``r_m``: the gyro's yaw rate (rad/s, counter-clockwise), the IMU's z rate negated (its z
  points down);
- the truth ``x, y, psi``: the INS/GNSS solution moved to the antenna by the lever arm
  (below); ``psi`` is the car's heading (the INS's, turned by the boresight below), as lbo
  measures it (counter-clockwise from east).

*Boresight, lever arm and time.* The INS reports the heading of its case, which is turned
against the car; the position of its case, while the receiver reports that of its antenna,
elsewhere on the car; and each fix is logged some time after the instant it is valid at.
:func:`fit_alignment` fits all three (:mod:`lbo.logs.alignment`'s rules and thresholds). The
boresight first, on the INS's own rows (not the receiver's): driving straight faster than
``FIT_SPEED``, a car moves along its heading, so the mean angle from the INS heading to the
direction of the INS velocity (plus pi reversing) is the angle by which the case is turned;
the car's heading is the INS heading turned by it. Then, on the fixes taken above
``FIT_SPEED``: for each latency on a 10 ms grid over ``LATENCIES``, the lever arm (forward,
left, m) is the mean of the fixes' offsets from the INS position at that latency, in the car's
frame (the least-squares fit, the car's rotations being orthonormal); the latency kept is the
one that leaves the smallest RMS offset. The log's fixes are put at their logged time minus that
latency, and the truth at the antenna, with the car's heading.

*What no filter removes.* The INS/GNSS solution is aided by the same receiver: its slow
errors (multipath, atmosphere, a few decimetres over minutes) are the truth's too, so an
observer's error against it does not see them, and the raw fixes' error is understated by as
much.
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np
import pandas as pd

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.logs import alignment as align
from lbo.logs.alignment import FIT_SPEED, LATENCIES, on_rows
from lbo.logs.formats import Origin, to_local
from lbo.sim.vehicle import Vehicle

HILL = "2021-04-27 HGuide n380 Car Hill Driving"
"""The one onavdata drive lbo reads."""
HILL_FOLDER = "2021-04-27C-car-hill-drive"
"""Its folder in the onavdata package."""
V_FLOOR = 1.0
"""Speed (m/s) below which the steering that gives the gyro's yaw rate is taken at this
speed: at a standstill no steering turns the kinematic bicycle."""
STILL_SPEED = 0.5
"""Speed (m/s) below which the car counts as standing, for :func:`drives`."""
STOP_S = 30.0
"""Shortest standstill (s) between two drives (:func:`drives`): a stop at a junction is
part of a drive."""
SPANS = {"train": (0.0, 0.39), "val": (0.39, 0.6), "test": (0.6, 1.0)}
"""The drive's time spans (fractions of its duration): train on the first, validate and test
on the later ones, one span each. The car drives three times, standing still between: the
cuts (261 s and 402 s in) fall in the stops, so that each span holds one drive (the first
114 s, the second 66 s, the third 121 s with two reversals)."""

_INS = {"lat": "PosLat (rad)", "lon": "PosLon (rad)", "vn": "VelNorth (m/s)",
        "ve": "VelEast (m/s)", "yaw": "AngleHeading (rad)", "rate": "AngleRateZ (rad/s)"}
_GNSS = {"lat": "GNSSPosLat (rad)", "lon": "GNSSPosLon (rad)", "sx": "STD GNSSPosEast (m)",
         "sy": "STD GNSSPosNorth (m)", "ve": "GNSSVelEast (m/s)", "vn": "GNSSVelNorth (m/s)",
         "sve": "STD GNSSVelEast (m/s)", "svn": "STD GNSSVelNorth (m/s)"}


@dataclass(frozen=True, kw_only=True)
class Alignment:
    """The INS's boresight and the fixes' lever arm and latency (:func:`fit_alignment`).

    boresight : rad from the INS heading to the car's (counter-clockwise).
    lever : (2,) the antenna's offset from the INS (m: forward and left in the car's frame).
    latency : s from the instant a fix is valid to its logged time.
    rms_before, rms_after : (m) RMS offset of the fits' fixes from the INS position at their
        logged time, and from the truth at the antenna at the fitted time.
    fixes : how many fixes the fit used.
    """

    boresight: float
    lever: np.ndarray
    latency: float
    rms_before: float
    rms_after: float
    fixes: int


STREAMS = ("position", "velocity", "attitude", "imu-nav", "gnss-pvt")
"""The files of an n380 recording, ``n380-<stream>.csv`` (or ``.csv.zip``), as HGuide's
logger writes them and onavdata ships them."""


def _onavdata():
    try:
        import onavdata
    except ImportError:
        raise LboError("the onavdata package is not installed: pip install 'lbo[real]'") from None
    return onavdata


def _tidy(df: pd.DataFrame) -> pd.DataFrame:
    df = df.sort_index()
    df.index = df.index.rename("t")
    return df


def read(name: str = HILL) -> pd.DataFrame:
    """The drive's rows as onavdata gives them (time-sorted, index ``t`` in s), its console
    chatter silenced. Any drive but :data:`HILL` is refused in one line."""
    if name != HILL:
        raise LboError(f"drive {name!r}: lbo reads only the onavdata hill drive ({HILL!r})")
    onavdata = _onavdata()
    with contextlib.redirect_stdout(io.StringIO()):
        return _tidy(onavdata.get_data(name))


def read_folder(folder: str | Path) -> pd.DataFrame:
    """A user's own n380 recording: the folder holding its :data:`STREAMS` files, read as
    onavdata reads its drives (its n380 settings: columns, units, the INS's aligned rows), in
    the frame :func:`read` gives. A folder of onavdata's other than the hill drive's is
    refused: that drive is not lbo's to read."""
    onavdata = _onavdata()
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise LboError(f"recording: {folder} is not a folder (give the folder of an n380 "
                       f"recording's files, n380-<stream>.csv)")
    shipped = Path(onavdata.__file__).resolve().parent / "data"
    resolved = folder.resolve()
    if resolved.is_relative_to(shipped) and resolved.name != HILL_FOLDER:
        raise LboError(f"recording: {folder} is an onavdata drive other than the hill drive; "
                       f"lbo reads only the hill drive ({HILL!r})")
    paths = []
    for stream in STREAMS:
        path = folder / f"n380-{stream}.csv"
        if not (path.is_file() or path.with_name(path.name + ".zip").is_file()):
            raise LboError(f"recording: {folder} has no n380-{stream}.csv (or .csv.zip); an "
                           f"n380 recording holds {', '.join(f'n380-{s}.csv' for s in STREAMS)}")
        paths.append(str(path))
    import tomllib

    meta = tomllib.loads((shipped / "HGuide n380" / "n380-meta.toml").read_text())
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            df = onavdata.get_data_direct(paths, meta)
    except (KeyError, ValueError, pd.errors.ParserError) as e:
        raise LboError(f"recording: {folder} is not an n380 recording onavdata can read "
                       f"({type(e).__name__}: {e})") from None
    return _tidy(df)


def _ins_track(df: pd.DataFrame, origin: Origin) -> dict[str, np.ndarray]:
    """The INS rows: t (N,), east, north (N,) m, psi (N,) rad unwrapped ENU, vn, ve, r (N,).

    Only rows that hold every INS stream (position, velocity, attitude, rate): a recording's
    streams start and end a few rows apart (measured on another n380 recording: its velocity
    stream ends first, which left the log's last speed empty), so the log covers only the span
    they all cover."""
    ins = _ins_rows(df)
    east, north = to_local(np.degrees(ins[_INS["lat"]].to_numpy()),
                           np.degrees(ins[_INS["lon"]].to_numpy()), origin)
    yaw = ins[_INS["yaw"]].to_numpy()
    return {"t": ins.index.to_numpy(dtype=float), "east": east, "north": north,
            "psi": np.unwrap(np.pi / 2 - yaw), "vn": ins[_INS["vn"]].to_numpy(),
            "ve": ins[_INS["ve"]].to_numpy(), "r": -ins[_INS["rate"]].to_numpy()}


def _at(track: dict[str, np.ndarray], t: np.ndarray) -> dict[str, np.ndarray]:
    """The INS track interpolated at times t (M,)."""
    return {k: np.interp(t, track["t"], v) for k, v in track.items() if k != "t"}


def _antenna(ins: dict[str, np.ndarray], lever: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(east, north) of the antenna at the lever arm (forward, left) from the INS."""
    c, s = np.cos(ins["psi"]), np.sin(ins["psi"])
    return (ins["east"] + c * lever[0] - s * lever[1], ins["north"] + s * lever[0] + c * lever[1])


def _fixes(df: pd.DataFrame, origin: Origin) -> dict[str, np.ndarray]:
    g = df[df[_GNSS["lat"]].notna()]
    east, north = to_local(np.degrees(g[_GNSS["lat"]].to_numpy()),
                           np.degrees(g[_GNSS["lon"]].to_numpy()), origin)
    return {"t": g.index.to_numpy(dtype=float), "east": east, "north": north,
            **{k: g[c].to_numpy(dtype=float) for k, c in _GNSS.items()
               if k not in ("lat", "lon")}}


def fit_alignment(df: pd.DataFrame) -> Alignment:
    """The boresight, lever arm and latency of the drive (see the module's docstring)."""
    origin = _origin(df)
    track, fix = _ins_track(df, origin), _fixes(df, origin)
    boresight = align.boresight(track["psi"], track["ve"], track["vn"], track["r"],
                                "the drive's INS")
    track["psi"] = track["psi"] + boresight
    inside = (fix["t"] > track["t"][0] + LATENCIES[1]) & (fix["t"] < track["t"][-1] - 0.5)
    at_fix = _at(track, fix["t"])
    moving = inside & (np.hypot(at_fix["vn"], at_fix["ve"]) > FIT_SPEED)
    if moving.sum() < 10:
        raise LboError(f"the drive has {int(moving.sum())} fixes above {FIT_SPEED:g} m/s; "
                       "the lever arm and latency need at least 10")
    t, e, n = fix["t"][moving], fix["east"][moving], fix["north"][moving]
    before = float(np.sqrt(np.mean((e - at_fix["east"][moving]) ** 2
                                   + (n - at_fix["north"][moving]) ** 2)))
    best: tuple[float, float, np.ndarray] | None = None
    for latency in align.latency_grid():
        ins = _at(track, t - latency)
        c, s = np.cos(ins["psi"]), np.sin(ins["psi"])
        de, dn = e - ins["east"], n - ins["north"]
        lever = np.array([np.mean(c * de + s * dn), np.mean(-s * de + c * dn)])
        ae, an = _antenna(ins, lever)
        rms = float(np.sqrt(np.mean((e - ae) ** 2 + (n - an) ** 2)))
        if best is None or rms < best[0]:
            best = (rms, float(latency), lever)
    rms, latency, lever = cast(tuple[float, float, np.ndarray], best)  # the grid is not empty
    return Alignment(boresight=boresight, lever=lever, latency=latency, rms_before=before,
                     rms_after=rms, fixes=int(moving.sum()))


def _ins_rows(df: pd.DataFrame) -> pd.DataFrame:
    """The rows that hold every INS stream (see :func:`_ins_track`)."""
    return df[df[list(_INS.values())].notna().all(axis=1)]


def _origin(df: pd.DataFrame) -> Origin:
    first = _ins_rows(df).iloc[0]
    return Origin(float(np.degrees(first[_INS["lat"]])), float(np.degrees(first[_INS["lon"]])))


def to_log(df: pd.DataFrame, vehicle: Vehicle | None = None,
           alignment: Alignment | None = None) -> pd.DataFrame:
    """The drive as an lbo log at ``vehicle.dt`` (see the module's docstring for each column).

    df : the drive as :func:`read` gives it (or a time slice of it).
    vehicle : gives ``dt``, the wheelbase and ``delta_max`` of the steering from the gyro.
    alignment : the boresight, lever arm and latency (None: fitted on ``df``,
        :func:`fit_alignment`).

    Returns a frame with ``t`` (s from the first INS row), ``x_m, y_m, psi_m`` (psi_m empty:
    one antenna), ``sx_m, sy_m, ve_m, vn_m, sv_m`` (at fix rows), ``V, delta, r_m`` and the
    truth ``x, y, psi``.
    """
    vehicle = vehicle or Vehicle()
    alignment = alignment or fit_alignment(df)
    origin = _origin(df)
    track, fix = _ins_track(df, origin), _fixes(df, origin)
    track["psi"] = track["psi"] + alignment.boresight
    t0 = track["t"][0]
    n = int(np.floor((track["t"][-1] - t0) / vehicle.dt + 1e-9)) + 1
    grid = t0 + vehicle.dt * np.arange(n)
    ins = _at(track, grid)
    x, y = _antenna(ins, alignment.lever)
    V = ins["vn"] * np.sin(ins["psi"]) + ins["ve"] * np.cos(ins["psi"])
    speed = np.where(np.abs(V) < V_FLOOR, np.where(V < 0, -V_FLOOR, V_FLOOR), V)
    delta = np.clip(np.arctan(vehicle.wheelbase * ins["r"] / speed), -vehicle.delta_max,
                    vehicle.delta_max)
    out = pd.DataFrame({"t": grid - t0, "x_m": np.nan, "y_m": np.nan, "psi_m": np.nan,
                        "sx_m": np.nan, "sy_m": np.nan, "ve_m": np.nan, "vn_m": np.nan,
                        "sv_m": np.nan, "V": V, "delta": delta, "r_m": ins["r"], "x": x, "y": y,
                        "psi": wrap_angle(ins["psi"])})
    row, keep = on_rows(fix["t"] - alignment.latency, t0, vehicle.dt, n)
    columns = {"x_m": fix["east"], "y_m": fix["north"], "sx_m": fix["sx"], "sy_m": fix["sy"],
               "ve_m": fix["ve"], "vn_m": fix["vn"],
               "sv_m": np.sqrt(0.5 * (fix["sve"] ** 2 + fix["svn"] ** 2))}
    for c, v in columns.items():
        out.loc[row, c] = v[keep]
    return out


def spans(log: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """The log cut into :data:`SPANS` by time, each with ``t`` from its own start."""
    t = log["t"].to_numpy()
    cut = t[0] + (t[-1] - t[0]) * np.array([a for a, _ in SPANS.values()] + [1.0 + 1e-9])
    out = {}
    for (name, _), lo, hi in zip(SPANS.items(), cut[:-1], cut[1:]):
        part = log[(t >= lo) & (t < hi)].reset_index(drop=True)
        part["t"] = part["t"] - part["t"].iloc[0]
        out[name] = part
    return out


def drives(log: pd.DataFrame, still_speed: float = STILL_SPEED,
           stop_s: float = STOP_S) -> list[pd.DataFrame]:
    """The log cut into its drives: at the middle of each standstill (``|V|`` below
    ``still_speed`` m/s) of ``stop_s`` s or more between moving rows, so that each drive
    starts and ends standing, as the car did. Each keeps ``t`` from its own start. The hill
    drive holds three (the cuts fall 254 s and 386 s in); a log without such a stop is one
    drive.

    Raises :class:`LboError` if the car never moves."""
    t = log["t"].to_numpy(float)
    moving = np.abs(log["V"].to_numpy(float)) >= still_speed
    if not moving.any():
        raise LboError(f"the log never moves faster than {still_speed:g} m/s: it holds no drive")
    at = np.flatnonzero(moving)
    gaps = np.flatnonzero(t[at[1:]] - t[at[:-1]] >= stop_s)  # long stops between moving rows
    cuts = 0.5 * (t[at[gaps]] + t[at[gaps + 1]])
    part = np.searchsorted(cuts, t, side="right")
    out = []
    for k in range(len(cuts) + 1):
        one = log[part == k].reset_index(drop=True)
        one["t"] = one["t"] - one["t"].iloc[0]
        out.append(one)
    return out

