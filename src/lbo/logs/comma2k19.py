"""A production car's drive as an lbo log: a comma2k19 segment (comma.ai's commute data set).

comma2k19 (github.com/commaai/comma2k19, MIT, (c) 2018 comma.ai): 33 hours of highway commute
in 1-minute segments, each logged by a comma EON on the windshield (the car's CAN bus, a phone
IMU, a u-blox receiver), with the EON's pose from a fusion of these, its camera and
post-processed raw GNSS. lbo ships the repository's example segment (:func:`example`, in
``data/comma2k19/`` with its licence: a 2018 Toyota RAV4, 60 s on a highway at 8-20 m/s) and
reads a downloaded one (:func:`read`). A segment's folder holds numpy arrays without an
extension, a ``t`` (boot time, s) and a ``value`` per stream; lbo reads:

- ``processed_log/CAN/speed`` (or ``car_speed``): speed (m/s, unsigned: reversing unseen);
  ``processed_log/CAN/steering_angle``: the steering wheel's angle (deg, left positive);
- ``processed_log/IMU/gyro``: rates (rad/s) about the EON's forward, right, down axes;
- ``processed_log/GNSS/live_gnss_ublox``: fixes at 10 Hz, [lat deg, lon deg, speed m/s,
  UTC ms, altitude m, bearing deg clockwise from north], with no accuracy;
- ``global_pose/frame_times`` (boot s), ``frame_positions`` (ECEF m), ``frame_velocities``
  (ECEF m/s), ``frame_orientations`` (Hamilton quaternions w, x, y, z whose rotation takes
  the EON's forward, right, down axes to ECEF), at 20 Hz.

:func:`to_log` makes a log of lbo's form at the vehicle's ``dt`` over the span the pose, speed,
steering and gyro all cover (``t`` from its start):

- the fixes ``x_m, y_m`` (m east and north of the first pose, :func:`lbo.logs.formats.to_local`),
  no heading (one antenna), no accuracy (``sx_m, sy_m, sv_m`` NaN), the velocity ``ve_m, vn_m``
  from the fix's speed and bearing, each at the row nearest the instant it is valid at (its
  logged time less the latency);
- the inputs: ``V`` the CAN speed; ``delta`` the road wheels' angle, (wheel - offset) / ratio
  (:class:`Steering`), clipped to ``delta_max``; ``r_m`` the gyro's down rate, negated;
- the truth ``x, y, psi``: the EON's pose (the receiver is in it: no lever arm); ``psi`` the
  horizontal direction of its forward axis, turned by the boresight.

*Fitted on the segment* (:class:`Converted` reports them; the thresholds:
:mod:`lbo.logs.alignment`). **Boresight**: the EON sits turned
on the windshield; driving straight (yaw rate under ``STRAIGHT_RATE``) above
``FIT_SPEED`` the pose's velocity points off its forward axis by that angle (-16 mrad on
the example), and the car's heading is the forward axis's turned by it (as
:mod:`lbo.logs.hguide` turns its INS's). **Latency** (``latency=None``): of a 10 ms grid over
``LATENCIES``, the one leaving the smallest RMS offset of the fixes above
``FIT_SPEED`` from the truth (0.08 s on the example). **Steering** (``steering=None``):
the least-squares line from the wheel's angle to ``atan(L r_m / V)`` (the road-wheel angle
that turns the kinematic bicycle at the gyro's rate) above ``FIT_SPEED``. On a highway it
is an *effective* ratio that holds the car's understeer: 26.7 on the example (openpilot takes
16.9 for the RAV4). *What no filter removes*: the truth shares the EON's sensors' slow errors.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.core.paths import shipped
from lbo.logs import alignment as align
from lbo.logs.alignment import FIT_SPEED, LATENCIES
from lbo.logs.formats import Origin, to_local
from lbo.sim.vehicle import Vehicle

EXAMPLE = "segment.npz"
"""The example's arrays (``data/comma2k19/``), keyed by their paths in a segment's folder."""
SPEEDS = ("processed_log/CAN/speed", "processed_log/CAN/car_speed")
"""The CAN speed's folder: the example's name, then the data set's README's."""
_FILES = {"pose_t": ("global_pose/frame_times", 0),
          "position": ("global_pose/frame_positions", 3),
          "velocity": ("global_pose/frame_velocities", 3),
          "orientation": ("global_pose/frame_orientations", 4),
          "steering_t": ("processed_log/CAN/steering_angle/t", 0),
          "steering": ("processed_log/CAN/steering_angle/value", 0),
          "gyro_t": ("processed_log/IMU/gyro/t", 0), "gyro": ("processed_log/IMU/gyro/value", 3),
          "fix_t": ("processed_log/GNSS/live_gnss_ublox/t", 0),
          "fix": ("processed_log/GNSS/live_gnss_ublox/value", 6)}
"""Field -> (path in a segment's folder, columns; 0: a vector). The speed's is in SPEEDS."""
_STREAMS = {"pose_t": ("position", "velocity", "orientation"), "speed_t": ("speed",),
            "steering_t": ("steering",), "gyro_t": ("gyro",), "fix_t": ("fix",)}


@dataclass(frozen=True, eq=False, kw_only=True)
class Segment:
    """A comma2k19 segment's arrays as logged (read-only), times in boot s.

    pose_t (P,), position (P, 3) ECEF m, velocity (P, 3) ECEF m/s, orientation (P, 4)
        quaternion [w, x, y, z] (its rotation takes forward, right, down to ECEF): the EON's.
    speed_t, speed (S,): CAN speed (m/s). steering_t, steering (A,): steering wheel (deg).
    gyro_t (G,), gyro (G, 3): rad/s about forward, right, down.
    fix_t (F,), fix (F, 6): u-blox fixes [lat deg, lon deg, speed m/s, UTC ms, alt m,
        bearing deg].
    """

    pose_t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    orientation: np.ndarray
    speed_t: np.ndarray
    speed: np.ndarray
    steering_t: np.ndarray
    steering: np.ndarray
    gyro_t: np.ndarray
    gyro: np.ndarray
    fix_t: np.ndarray
    fix: np.ndarray


@dataclass(frozen=True)
class Steering:
    """Steering wheel to road wheels: ``delta = radians(wheel - offset_deg) / ratio``."""

    ratio: float
    offset_deg: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.ratio) and self.ratio > 0 and np.isfinite(self.offset_deg)):
            raise LboError(f"steering must be a ratio > 0 and a finite offset_deg (deg), got "
                           f"ratio={self.ratio}, offset_deg={self.offset_deg}")


@dataclass(frozen=True, eq=False, kw_only=True)
class Converted:
    """:func:`to_log`'s result.

    log : the lbo log (see the module's docstring); origin : its ``x, y``'s (the first pose).
    steering, latency (s): those used, given or fitted (``fitted`` names the fitted ones).
    boresight : rad from the EON's forward axis to the car's heading (counter-clockwise).
    rms_at_zero, rms : (m) RMS offset of the ``fixes`` (how many) above FIT_SPEED from the
        truth at their logged time, and at it less the latency.
    """

    log: pd.DataFrame
    steering: Steering
    latency: float
    boresight: float
    rms_at_zero: float
    rms: float
    fixes: int
    fitted: tuple[str, ...]
    origin: Origin


def _segment(load: Any, where: str) -> Segment:
    """A :class:`Segment` from ``load(path) -> array or None`` (None: no such file)."""
    speed = next((p for p in SPEEDS if load(f"{p}/t") is not None), SPEEDS[0])
    paths = {**_FILES, "speed_t": (f"{speed}/t", 0), "speed": (f"{speed}/value", 0)}
    arrays = {k: _checked(load(path), path, cols, where) for k, (path, cols) in paths.items()}
    for t, values in _STREAMS.items():
        for v in values:
            if len(arrays[v]) != len(arrays[t]):
                raise LboError(f"segment {where}: {paths[v][0]} has {len(arrays[v])} rows; "
                               f"expected one per time of {paths[t][0]} ({len(arrays[t])})")
        if len(arrays[t]) < 2 or not np.all(np.diff(arrays[t]) > 0):
            raise LboError(f"segment {where}: {paths[t][0]} holds {len(arrays[t])} times; "
                           "expected at least 2, strictly increasing")
    for a in arrays.values():
        a.setflags(write=False)
    return Segment(**arrays)


def _checked(a: np.ndarray | None, path: str, cols: int, where: str) -> np.ndarray:
    form = "(N,)" if cols == 0 else f"(N, {cols})"
    if a is None:
        raise LboError(f"segment {where}: no {path}; a comma2k19 segment holds processed_log/ "
                       "(CAN speed and steering_angle, IMU gyro, GNSS live_gnss_ublox: t and "
                       "value each) and global_pose/ (frame_times, frame_positions, "
                       "frame_velocities, frame_orientations)")
    if cols == 0 and a.ndim == 2 and a.shape[1] == 1:
        a = a[:, 0]  # the example's CAN speed is (S, 1)
    if a.dtype.kind not in "iuf" or a.ndim < 1 or a.shape[1:] != ((cols,) if cols else ()):
        raise LboError(f"segment {where}: {path} is {a.dtype} {a.shape}; expected numbers "
                       f"{form}")
    a = np.array(a, dtype=float)
    if not np.isfinite(a).all() and not path.endswith("ublox/value"):  # (a fix may be NaN)
        raise LboError(f"segment {where}: {path} holds NaN or inf; expected finite numbers")
    return a


def read(folder: str | Path) -> Segment:
    """A downloaded segment: the folder holding ``processed_log/`` and ``global_pose/``. A
    missing folder or file, or an array of another shape, is one line naming it."""
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise LboError(f"segment: {folder} is not a folder (give a comma2k19 segment's folder, "
                       "the one holding processed_log/ and global_pose/)")

    def load(path: str) -> np.ndarray | None:
        file = folder / path
        if not file.is_file():
            return None
        try:
            a = np.load(file, allow_pickle=False)
        except (ValueError, OSError):
            a = None
        if not isinstance(a, np.ndarray):
            raise LboError(f"segment {folder}: {path} is not a numpy array (.npy format)")
        return a

    return _segment(load, str(folder))


def example() -> Segment:
    """The shipped example segment (the comma2k19 repository's ``Example_1``), read as
    :func:`read` reads a folder."""
    return _segment(shipped("comma2k19", EXAMPLE).get, f"example ({EXAMPLE})")


def _enu(v: np.ndarray, origin: Origin) -> tuple[np.ndarray, np.ndarray]:
    """(east, north) components (N,) at ``origin`` of ECEF vectors (N, 3) (pymap3d)."""
    import pymap3d

    east, north, _ = pymap3d.ecef2enuv(v[:, 0], v[:, 1], v[:, 2], origin.lat, origin.lon)
    return np.asarray(east), np.asarray(north)


def _forward(q: np.ndarray) -> np.ndarray:
    """(N, 3) ECEF direction of the EON's forward axis: the first column of the rotation
    matrix of Hamilton quaternions q (N, 4) [w, x, y, z]."""
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.column_stack([w * w + x * x - y * y - z * z, 2 * (x * y + w * z),
                            2 * (x * z - w * y)])


def _truth(segment: Segment) -> tuple[Origin, dict[str, np.ndarray]]:
    """The origin (first pose) and the pose rows: t, east, north, psi (the forward axis's,
    unwrapped), ve, vn (P,)."""
    import pymap3d

    p = segment.position
    lat, lon, _ = pymap3d.ecef2geodetic(p[:, 0], p[:, 1], p[:, 2])
    origin = Origin(float(lat[0]), float(lon[0]))
    east, north = to_local(np.asarray(lat), np.asarray(lon), origin)
    fe, fn = _enu(_forward(segment.orientation), origin)
    ve, vn = _enu(segment.velocity, origin)
    return origin, {"t": segment.pose_t, "east": east, "north": north,
                    "psi": np.unwrap(np.arctan2(fn, fe)), "ve": ve, "vn": vn}


def _boresight(pose: dict[str, np.ndarray]) -> float:
    """The angle (rad) from the forward axis's heading to the pose's course, driving straight
    (:func:`lbo.logs.alignment.boresight`; the yaw rate: the pose heading's)."""
    return align.boresight(pose["psi"], pose["ve"], pose["vn"],
                           np.gradient(pose["psi"], pose["t"]), "segment's pose")


def _fixes(segment: Segment, origin: Origin) -> dict[str, np.ndarray]:
    """The fixes that hold a position, speed and bearing: t, east, north, ve, vn (F,)."""
    held = np.isfinite(segment.fix[:, [0, 1, 2, 5]]).all(axis=1)
    f, bearing = segment.fix[held], np.radians(segment.fix[held, 5])
    east, north = to_local(f[:, 0], f[:, 1], origin)
    return {"t": segment.fix_t[held], "east": east, "north": north,
            "ve": f[:, 2] * np.sin(bearing), "vn": f[:, 2] * np.cos(bearing)}


def _offsets(pose: dict[str, np.ndarray], fix: dict[str, np.ndarray],
             latencies: np.ndarray) -> tuple[np.ndarray, int]:
    """(K,) RMS offset (m) of the fixes above ``FIT_SPEED`` (those inside the pose's span
    at every latency of ``LATENCIES`` and ``latencies``) from the truth at their logged
    time less each of ``latencies`` (K,) s, and how many fixes."""
    speed = np.hypot(np.interp(fix["t"], pose["t"], pose["ve"]),
                     np.interp(fix["t"], pose["t"], pose["vn"]))
    lo, hi = min(LATENCIES[0], latencies.min()), max(LATENCIES[1], latencies.max())
    used = (fix["t"] > pose["t"][0] + hi) & (fix["t"] < pose["t"][-1] + lo) & (speed > FIT_SPEED)
    if used.sum() < 10:
        raise LboError(f"segment: {int(used.sum())} fixes above {FIT_SPEED:g} m/s inside the "
                       "pose's span; the latency needs at least 10")
    at = fix["t"][used][None, :] - latencies[:, None]  # (K, F) the instants tried
    de = fix["east"][used] - np.interp(at, pose["t"], pose["east"])
    dn = fix["north"][used] - np.interp(at, pose["t"], pose["north"])
    return np.sqrt(np.mean(de**2 + dn**2, axis=1)), int(used.sum())


def fit_latency(segment: Segment) -> float:
    """The latency (s), on a 10 ms grid over :data:`lbo.logs.alignment.LATENCIES`, that leaves
    the smallest RMS offset of the fixes above ``FIT_SPEED`` from the truth at their logged
    time less it."""
    origin, pose = _truth(segment)
    return _latency(pose, _fixes(segment, origin))


def _latency(pose: dict[str, np.ndarray], fix: dict[str, np.ndarray]) -> float:
    """:func:`fit_latency` of the pose rows and fixes already read."""
    grid = align.latency_grid()
    rms, _ = _offsets(pose, fix, grid)
    return float(grid[int(np.argmin(rms))])


def fit_steering(V: np.ndarray, wheel_deg: np.ndarray, r: np.ndarray,
                 wheelbase: float) -> Steering:
    """The :class:`Steering` that turns the kinematic bicycle at the gyro's rate, by least
    squares on the rows above ``FIT_SPEED``: ``atan(L r / V) = radians(wheel) / ratio -
    radians(offset) / ratio``. V, wheel_deg (deg), r (rad/s, counter-clockwise) (T,)."""
    moving = V > FIT_SPEED
    if moving.sum() < 100:
        raise LboError(f"steering: {int(moving.sum())} rows above {FIT_SPEED:g} m/s; the fit "
                       "needs at least 100 (give steering=Steering(ratio, offset_deg))")
    a = np.column_stack([np.radians(wheel_deg[moving]), np.ones(int(moving.sum()))])
    (slope, icpt), *_ = np.linalg.lstsq(a, np.arctan(wheelbase * r[moving] / V[moving]),
                                        rcond=None)
    if not slope > 0:
        raise LboError(f"steering: the steering wheel's angle does not follow the gyro's yaw "
                       f"rate (slope {slope:.3g}); give steering=Steering(ratio, offset_deg)")
    return Steering(ratio=float(1 / slope), offset_deg=float(np.degrees(-icpt / slope)))


def to_log(segment: Segment, vehicle: Vehicle | None = None, steering: Steering | None = None,
           latency: float | None = None) -> Converted:
    """The segment (:func:`read`, :func:`example`) as an lbo log at ``vehicle.dt`` with the
    steering, latency and boresight used (:class:`Converted`; the columns: the module's
    docstring; ``psi_m, sx_m, sy_m, sv_m`` empty).

    vehicle : gives ``dt``, the wheelbase (of the steering fit) and ``delta_max``.
    steering : the steering ratio and offset (None: :func:`fit_steering` on the segment).
    latency : s from the instant a fix is valid to its logged time (None: :func:`fit_latency`).
    """
    vehicle = vehicle or Vehicle()
    fitted = tuple(k for k, v in (("steering", steering), ("latency", latency)) if v is None)
    origin, pose = _truth(segment)
    fix = _fixes(segment, origin)
    latency = _latency(pose, fix) if latency is None else float(latency)
    (rms_at_zero, rms), fixes = _offsets(pose, fix, np.array([0.0, latency]))
    boresight = _boresight(pose)
    times = [segment.pose_t, segment.speed_t, segment.steering_t, segment.gyro_t]
    t0, t1 = max(t[0] for t in times), min(t[-1] for t in times)
    n = int(np.floor((t1 - t0) / vehicle.dt + 1e-9)) + 1
    grid = t0 + vehicle.dt * np.arange(n)
    V = np.interp(grid, segment.speed_t, segment.speed)
    wheel = np.interp(grid, segment.steering_t, segment.steering)
    r = -np.interp(grid, segment.gyro_t, segment.gyro[:, 2])
    steering = steering or fit_steering(V, wheel, r, vehicle.wheelbase)
    delta = np.clip(np.radians(wheel - steering.offset_deg) / steering.ratio,
                    -vehicle.delta_max, vehicle.delta_max)
    psi = np.interp(grid, pose["t"], pose["psi"]) + boresight
    out = pd.DataFrame({"t": grid - t0, "x_m": np.nan, "y_m": np.nan, "psi_m": np.nan,
                        "sx_m": np.nan, "sy_m": np.nan, "ve_m": np.nan, "vn_m": np.nan,
                        "sv_m": np.nan, "V": V, "delta": delta, "r_m": r,
                        "x": np.interp(grid, pose["t"], pose["east"]),
                        "y": np.interp(grid, pose["t"], pose["north"]), "psi": wrap_angle(psi)})
    row, keep = align.on_rows(fix["t"] - latency, t0, vehicle.dt, n)
    for c, k in (("x_m", "east"), ("y_m", "north"), ("ve_m", "ve"), ("vn_m", "vn")):
        column = out[c].to_numpy(copy=True)
        column[row] = fix[k][keep]
        out[c] = column
    return Converted(log=out, steering=steering, latency=latency, boresight=boresight,
                     rms_at_zero=rms_at_zero, rms=rms, fixes=fixes, fitted=fitted, origin=origin)

