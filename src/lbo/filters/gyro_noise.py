"""The gyro EKF's noise: every noise :class:`lbo.filters.gyro.GyroStepper` assumes, as one set
(:class:`GyroNoise`) that :mod:`lbo.learn.gyro_fit` learns and a file holds, with their
defaults and ranges, and the fixes' slow drift it may carry as two more states
(:class:`FixDrift`)."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypedDict

import numpy as np

from lbo.core.errors import LboError
from lbo.core.smallfile import read_small
from lbo.filters import measure
from lbo.sim.measurements import Measurements

GYRO_SIGMA = 0.01
"""1-sigma (rad/s) of the gyro's white noise a step, by default: an automotive ESC gyro's."""
BIAS_SIGMA = 0.02
"""1-sigma (rad/s) of the bias before any fix, by default (about 1 deg/s: an uncalibrated
MEMS gyro's turn-on bias)."""
BIAS_WALK = 1e-3
"""Random walk (rad/s/sqrt(s)) of the bias, by default: it drifts with temperature."""

NOISE_RANGES = {
    "q_position": (1e-12, 100.0, "m per step"),
    "q_heading": (1e-12, 1.0, "rad per step"),
    "gyro_sigma": (1e-12, 10.0, "rad/s"),
    "bias_walk": (1e-12, 10.0, "rad/s/sqrt(s)"),
    "accuracy_scale": (1e-12, 1e3, "a factor"),
    "velocity_scale": (1e-12, 1e3, "a factor"),
    "course_lever": (1e-12, 100.0, "m"),
    "drift_sigma": (1e-6, 1e3, "m"),
    "drift_tau": (1e-2, 1e6, "s"),
    "speed_scale": (0.5, 2.0, "a factor"),
    "gyro_scale": (0.5, 2.0, "a factor"),
}
"""(smallest, largest, unit) of each noise of :class:`GyroNoise`. Past them a noise says
nothing a filter can use, and its square runs towards float64's ends (1e200 overflowed ``Q``):
a car moves under 2 m a step at 100 m/s, a heading that wanders a radian a step is not
tracked, a gyro reads within 10 rad/s (:data:`lbo.logs.checks.GYRO_LIMIT`), an antenna sits
on the car; below 1e-12 a sigma's square is lost to rounding beside any other variance, and a
covariance made of such zeros turns singular."""

DRIFT = ("drift_sigma", "drift_tau")
"""The two noises of :class:`GyroNoise` that carry the fixes' drift (both or neither)."""
SCALES = ("speed_scale", "gyro_scale")
"""The two factors of :class:`GyroNoise` on the inputs (both or neither)."""
OPTIONAL = (*DRIFT, *SCALES)
"""What a :class:`GyroNoise` may leave None (and its file leave out)."""

class GyroKeywords(TypedDict):
    """What :meth:`GyroNoise.stepper` gives: keywords of :class:`GyroStepper`."""

    gyro_sigma: float
    bias_walk: float
    drift: FixDrift | None
    speed_scale: float
    gyro_scale: float


@dataclass(frozen=True, kw_only=True)
class GyroNoise:
    """Every noise the gyro EKF assumes, as a set that :mod:`lbo.learn.gyro_fit` learns from a
    log with truth (all > 0).

    q_position : 1-sigma (m) of x and y per step of the process noise.
    q_heading : 1-sigma (rad) of psi per step (the gyro's white noise adds to it).
    gyro_sigma, bias_walk : the gyro's white noise (rad/s) and bias walk (rad/s/sqrt(s)).
    accuracy_scale : factor on the receiver's reported ``sx_m, sy_m`` (a receiver's reported
        accuracy is a scale of its error, not its size).
    velocity_scale : factor on its ``sv_m`` (or :data:`lbo.filters.measure.SV_DEFAULT`) in
        the course's variance; which rows hold a course is the reported sigma's to say.
    course_lever : the antenna's distance (m) from the rear axle that the course's variance
        allows for (:data:`lbo.filters.measure.COURSE_LEVER`).
    drift_sigma, drift_tau : the fixes' slow error (:class:`FixDrift`: its stationary
        1-sigma, m, and correlation time, s), carried as two more states; both None (the
        default): the fixes' error is taken as white.
    speed_scale, gyro_scale : factors on the speed ``V`` and the gyro's rate ``r_m`` that the
        model reads (a wheel or CAN speed off by a percent, a gyro's scale error): what dead
        reckoning through a GNSS outage needs; both None (the default): 1, not learned.
    """

    q_position: float
    q_heading: float
    gyro_sigma: float = GYRO_SIGMA
    bias_walk: float = BIAS_WALK
    accuracy_scale: float = 1.0
    velocity_scale: float = 1.0
    course_lever: float = measure.COURSE_LEVER
    drift_sigma: float | None = None
    drift_tau: float | None = None
    speed_scale: float | None = None
    gyro_scale: float | None = None

    def __post_init__(self) -> None:
        for pair, what in ((DRIFT, "the fixes' drift"), (SCALES, "the inputs' scales")):
            if len({getattr(self, k) is None for k in pair}) > 1:
                raise LboError(f"gyro noise {', '.join(pair)}: expected both ({what}) or "
                               "neither, got one")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is None and f.name in OPTIONAL:
                continue
            low, high, unit = NOISE_RANGES[f.name]
            # a bool is an int to Python, not a noise; a comparison, unlike float(), takes an
            # int of any size, and NaN fails it
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not low <= v <= high:
                got = repr(v) if len(repr(v)) <= 40 else repr(v)[:37] + "..."  # one short line
                raise LboError(f"gyro noise {f.name}: expected a number in [{low:g}, {high:g}] "
                               f"({unit}), got {got}")
            object.__setattr__(self, f.name, float(v))  # frozen: set once, checked

    def __str__(self) -> str:
        held = (f"{f.name}={getattr(self, f.name)!r}" for f in dataclasses.fields(self)
                if getattr(self, f.name) is not None)  # the drift's only where it has one
        return f"GyroNoise({', '.join(held)})"

    @property
    def drift(self) -> FixDrift | None:
        """The fixes' drift it carries, None where it takes their error as white."""
        if self.drift_sigma is None or self.drift_tau is None:
            return None
        return FixDrift(self.drift_sigma, self.drift_tau)

    def with_drift(self, drift: FixDrift | None) -> GyroNoise:
        """The same noise carrying ``drift`` (None: none)."""
        if drift is None:
            return dataclasses.replace(self, drift_sigma=None, drift_tau=None)
        return dataclasses.replace(self, drift_sigma=drift.sigma, drift_tau=drift.tau)

    def with_scales(self, speed: float | None = 1.0, gyro: float | None = 1.0) -> GyroNoise:
        """The same noise with these factors on the speed and the gyro (None: none held)."""
        return dataclasses.replace(self, speed_scale=speed, gyro_scale=gyro)

    def scaled(self, u: np.ndarray) -> np.ndarray:
        """Inputs u (..., 2) ``[V, r_m]`` times the speed's and the gyro's scales."""
        return u * np.array([self.speed_scale or 1.0, self.gyro_scale or 1.0])

    @classmethod
    def from_q(cls, Q: np.ndarray) -> GyroNoise:
        """The defaults, with the process sigmas of a diagonal (3, 3) ``Q``."""
        q = np.sqrt(np.diag(np.asarray(Q, dtype=float)))
        return cls(q_position=float(np.sqrt(q[0] * q[1])), q_heading=float(q[2]))

    @property
    def Q(self) -> np.ndarray:
        """(3, 3) process covariance of ``[x, y, psi]``."""
        return np.diag([self.q_position**2, self.q_position**2, self.q_heading**2])

    def rows(self, meas: Measurements, u: np.ndarray) -> np.ndarray:
        """The filter's rows (T, 8) of measurements ``meas`` (T steps) and inputs u (T, 2)
        ``[V, r_m]``: the fixes' reported accuracies scaled, the course's variance with the
        velocity's sigma scaled and the allowance at the lever (its rows those the reported
        sigma gives)."""
        u = self.scaled(u)
        scaled = dataclasses.replace(meas, fix_sigma=meas.fix_sigma * self.accuracy_scale)
        return measure.rows(scaled, u[:, 0], u[:, 1], self.course_lever, self.velocity_scale)

    def stepper(self) -> GyroKeywords:
        """The keyword arguments of :class:`GyroStepper` and :func:`gyro_ekf_batch`."""
        return {"gyro_sigma": self.gyro_sigma, "bias_walk": self.bias_walk,
                "drift": self.drift, "speed_scale": self.speed_scale or 1.0,
                "gyro_scale": self.gyro_scale or 1.0}

    def save(self, path: str | Path) -> None:
        """Write it as JSON (atomically); the drift's two numbers only where it carries one."""
        from lbo.core.atomic import atomic_path

        data = {k: v for k, v in dataclasses.asdict(self).items() if v is not None}
        with atomic_path(Path(path)) as tmp:
            Path(tmp).write_text(json.dumps(data, indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> GyroNoise:
        """Read what :meth:`save` wrote; anything else is a one-line error: a path that is
        not a regular file of at most 64 KiB (:func:`lbo.core.smallfile.read_small`), not
        JSON, not an object of the seven noises (with or without the drift's two and the
        scales' two), or a noise that is not a number in its range (:data:`NOISE_RANGES`;
        ``true`` is not 1)."""
        names = [f.name for f in dataclasses.fields(cls) if f.name not in OPTIONAL]
        form = (f"a JSON object of numbers with exactly {', '.join(sorted(names))} (and "
                f"{' and '.join(DRIFT)} for the fixes' drift, {' and '.join(SCALES)} for the "
                "inputs' scales, each pair both null for none)")
        raw = read_small(path, f"gyro noise {path}", form)
        try:
            data: Any = json.loads(raw.decode("utf-8"))
        except (ValueError, RecursionError) as e:  # UnicodeDecodeError is a ValueError
            raise LboError(f"gyro noise {path}: not a readable JSON file ({e})") from None
        if not isinstance(data, dict) or not set(names) <= set(data) or any(
                set(data) & set(pair) not in (set(), set(pair)) for pair in (DRIFT, SCALES)) \
                or not set(data) <= {*names, *OPTIONAL}:
            raise LboError(f"gyro noise {path}: expected {form}")
        return cls(**data)


@dataclass(frozen=True)
class FixDrift:
    """The slow part of the fixes' error, as two more states of :class:`GyroStepper`: a
    first-order Gauss-Markov drift on x and one on y, of stationary 1-sigma ``sigma`` (m) and
    correlation time ``tau`` (s) (:func:`lbo.sim.truth.gauss_markov`'s). A fix then measures
    the position plus its drift, and its R is the white rest of its error. An EKF with a white
    R cannot tell a drift from the car's own motion; told its model, it can weigh two fixes a
    second apart as the nearly common error they share."""

    sigma: float
    tau: float

    def __post_init__(self) -> None:
        for name in ("sigma", "tau"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise LboError(f"fix drift {name}: expected a number > 0, got {v!r}")
