"""The gyro-driven kinematic model and its EKF: heading from a yaw-rate gyro with a bias.

Production filters turn the heading with the gyro, not with the steering: a log without a
steering angle needs it, and a gyro measures the turn the tyres made, slip included. The
model, with the gyro's unknown bias ``b`` as a fourth state:

    x' = V cos psi,   y' = V sin psi,   psi' = r_m - b,   b' = 0 (+ a random walk),

stepped with Euler's rule at dt, as the bicycle is. The inputs are ``[V, r_m]`` in place of
``[V, delta]``. A row's measurements are those of every classical filter
(:mod:`lbo.filters.measure`: a fix, with or without heading, its reported accuracy, the
course over ground), whose Jacobian on ``b`` is 0; the bias is learned from how the heading
the gyro integrates drifts from the fixes' course, and, while the car stands
(:data:`STILL_SPEED`), from the gyro itself: a car at rest does not turn, so its heading is
held and the gyro reads its bias. The process noise adds the gyro's white noise to the
heading (``(gyro_sigma dt)^2`` a step) and the bias's walk to ``b`` (``bias_walk^2 dt``).
The heading of a log that starts without one comes from the course over ground
(:class:`lbo.filters.start.CourseStart`, its path dead-reckoned with the gyro). Told the
fixes' slow error (:class:`FixDrift`), it carries it as two more states.

A bias far beyond its prior (0.5 rad/s where the prior says 0.02) on a log that starts moving
is not learned from the fixes: the filter, sure of a wrong bias, reports a heading sd of 0.02
rad while its heading errs by 0.25 rad. So every update's innovations are tested against
their covariance (:mod:`lbo.filters.consistency`: the NIS of the last 10 updates beyond its
99.9% chi-square bound), the rows from a failed test to the next update are flagged
(:attr:`GyroStepper.inconsistent`), and, with ``relearn`` (the default), the heading's and
the bias's variances are widened by the factor the innovations outgrew them by, so the
filter learns the bias again (docs/observe.md has the numbers).
"""

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
from lbo.filters.consistency import Checks, NisWindow, widen
from lbo.filters.start import CourseStart, batch_cov, check_trajectories, start_state
from lbo.filters.stepper import Posterior, run_stepper
from lbo.filters.update import joseph_update, nis
from lbo.sim.measurements import Measurements
from lbo.sim.vehicle import Vehicle

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

STILL_SPEED = 0.05
"""Speed (m/s) below which the car stands: it does not turn, so its heading is held and the
gyro's reading is its bias (a zero-rate update, as INS filters make at standstill)."""


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


TESTED = np.arange(measure.MEASURED + 1) < measure.MEASURED
"""(5,) bool: the channels of an update whose innovations the consistency test reads."""


def _jacobian(n: int) -> np.ndarray:
    """(5, n) Jacobian of the measured channels (:data:`lbo.filters.measure.CHANNELS`'s four)
    and, at standstill, of the gyro's reading of b, on the state ``[x, y, psi, b]`` and, for
    n = 6, the fixes' drift ``[dx, dy]`` (a fix measures the position plus its drift)."""
    H = np.zeros((measure.MEASURED + 1, n))
    H[:measure.MEASURED, :3] = measure.H
    H[measure.MEASURED, 3] = 1.0
    if n == 6:
        H[0, 4] = H[1, 5] = 1.0
    return H


class GyroStepper:
    """The EKF of the gyro-driven model (see the module's docstring), one step per call over
    G trajectories.

    Parameters
    ----------
    m0 : (G, 3) or (G, 8) first rows (a position fix).
    vehicle : Vehicle (its dt).
    Q : (3, 3) process covariance of ``[x, y, psi]``.
    R : (G, 3, 3) measurement covariance where a row reports no accuracy.
    gyro_sigma, bias_sigma, bias_walk : the gyro's errors (module constants by default).
    drift : the fixes' drift (:class:`FixDrift`) as two more states, or None (R white).
    speed_scale, gyro_scale : factors on the inputs ``[V, r_m]`` the model reads.
    relearn : widen the heading's and the bias's variances where the consistency test fails
        (:func:`lbo.filters.consistency.widen`); False: flag the rows only.

    Attributes
    ----------
    x : (G, n) ``[x, y, psi, b]``, then the drift ``[dx, dy]`` (n = 6). P : (G, n, n).
    prior, cross : as the other steppers'.
    consistency : the test of its innovations (:class:`lbo.filters.consistency.NisWindow`).
    inconsistent : (G,) bool, the last test failed: the estimate's covariance is not to be
        trusted (:meth:`reason` says why).
    widened : (G,) the factor the variances were last widened by where the last test failed
        (1: not widened).
    """

    def __init__(self, m0: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray, *,
                 gyro_sigma: float = GYRO_SIGMA, bias_sigma: float = BIAS_SIGMA,
                 bias_walk: float = BIAS_WALK, drift: FixDrift | None = None,
                 speed_scale: float = 1.0, gyro_scale: float = 1.0,
                 relearn: bool = True) -> None:
        self.dt, self.R = vehicle.dt, np.asarray(R, dtype=float)
        self.scales = np.array([speed_scale, gyro_scale])
        x3, P3 = start_state(m0, self.R)
        g, n = len(x3), 4 if drift is None else 6
        self.x = np.concatenate([x3, np.zeros((g, n - 3))], axis=1)
        self.P = np.zeros((g, n, n))
        self.P[:, :3, :3] = P3
        self.P[:, 3, 3] = bias_sigma**2
        self.Q = np.zeros((n, n))
        self.Q[:3, :3] = Q
        self.Q[2, 2] += (gyro_sigma * self.dt) ** 2
        self.gyro_var = gyro_sigma**2
        self.Q[3, 3] = bias_walk**2 * self.dt
        self.phi = 1.0  # the drift's factor a step
        if drift is not None:
            # the first fix is the position plus its drift: the position's error is minus
            # the drift's, of the drift's stationary variance (the white part is P3's)
            var = drift.sigma**2
            for i in (0, 1):
                self.P[:, i, i] += var
                self.P[:, 4 + i, 4 + i] = var
                self.P[:, i, 4 + i] = self.P[:, 4 + i, i] = -var
            self.phi = math.exp(-self.dt / drift.tau)
            self.Q[4, 4] = self.Q[5, 5] = var * (1.0 - self.phi**2)
        self.H = _jacobian(n)
        self.course = CourseStart(m0, vehicle, np.asarray(Q, dtype=float))
        self.consistency = NisWindow(g, measure.MEASURED)
        self.relearn, self.widened = relearn, np.ones(g)

    @property
    def inconsistent(self) -> np.ndarray:
        """(G,) bool: the last consistency test of each trajectory failed."""
        return self.consistency.inconsistent

    def reason(self, g: int) -> str | None:
        """Why trajectory g's estimate is flagged, None where it is not."""
        why = self.consistency.reason(g)
        if why is None or self.widened[g] == 1.0:
            return why
        return (f"{why}; the heading's and the gyro bias's variances widened "
                f"{self.widened[g]:.3g}-fold to learn the bias again")

    def update(self, m: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Predict with ``u_prev`` (G, 2) ``[V, r_m]`` of the last step, update with what row
        m (G, 3) or (G, 8) holds; returns the pose (G, 3)."""
        m = measure.widen(m)
        dt = self.dt
        u_prev = u_prev * self.scales
        v, rate = u_prev[:, 0], u_prev[:, 1]
        psi, bias = self.x[:, 2], self.x[:, 3]
        x = self.x.copy()
        x[:, 0] += v * np.cos(psi) * dt
        x[:, 1] += v * np.sin(psi) * dt
        still = np.abs(v) < STILL_SPEED
        x[:, 2] += np.where(still, 0.0, rate - bias) * dt
        x[:, 4:] *= self.phi
        F = np.tile(np.eye(x.shape[1]), (len(x), 1, 1))
        F[:, 0, 2] = -v * np.sin(psi) * dt
        F[:, 1, 2] = v * np.cos(psi) * dt
        F[:, 2, 3] = np.where(still, 0.0, -dt)
        F[:, 4:, 4:] *= self.phi
        cross = self.P @ F.swapaxes(-1, -2)
        P = F @ self.P @ F.swapaxes(-1, -2) + self.Q
        self.course.advance(u_prev, turn=np.where(still, 0.0, rate - bias))
        R = measure.step_cov(m, self.R)
        m, R, P, start = self.course.take(m, 0.5 * (R[:, 0, 0] + R[:, 1, 1]), P, R)
        cross[start, :, 2] = 0.0
        self.cross, self.prior = cross, (x, P)
        seen = x[:, :3].copy()  # what the channels measure: the pose, the fixes drifted
        seen[:, :2] += x[:, 4:] if x.shape[1] == 6 else 0.0
        y, _, R4, held = measure.model(m, seen, R)
        g = len(x)
        R5 = np.zeros((g, measure.MEASURED + 1, measure.MEASURED + 1))
        R5[:, :-1, :-1] = R4
        R5[:, -1, -1] = self.gyro_var
        y5 = np.concatenate([y, (rate - x[:, 3])[:, None]], axis=1)
        held5 = np.concatenate([held, still[:, None]], axis=1)
        # the test reads the sensors' channels (fix, heading, course), not the standstill's
        # zero rate: a constraint on a car that may not quite stand (a simulated one's
        # heading walks with its process noise even at rest)
        update = joseph_update(x, P, y5, self.H, R5, held5)
        self.x, self.P = update.x, update.P
        dof = (held5 & TESTED).sum(1)
        if not dof.any():  # no fix nor course in any trajectory (most rows): nothing to test
            return self.x[:, :3]
        # failed at this update
        failed = self.consistency.push(nis(update, held5, TESTED), dof) & (dof > 0)
        self.widened[dof > 0] = 1.0
        if self.relearn and failed.any():
            # innovations its covariance cannot explain: the heading and the bias the gyro
            # drives are what a filter sure of a wrong bias gets wrong (the fixes and the
            # course measure the pose); widened, the next fixes teach the bias again
            self.widened[failed] = self.consistency.excess()[failed]
            self.P = widen(self.P, (2, 3), self.widened, failed)
            self.consistency.clear(failed)
        return self.x[:, :3]


def gyro_ekf_batch(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray,
                   R: np.ndarray, **gyro: Any) -> Posterior:
    """:class:`GyroStepper` over G trajectories (a loop over time only).

    m : (G, T, 3) or (G, T, 8) rows; u : (G, T, 2) ``[V, r_m]``; Q (3, 3); R (3, 3) or
    (G, 3, 3); ``gyro``: :class:`GyroStepper`'s keywords (the gyro's errors, the fixes'
    drift, ``relearn``). Returns the :class:`~lbo.filters.stepper.Posterior` of the poses
    (G, T, 3), their covariances (G, T, 3, 3) and the consistency test at every row (its
    ``checks``)."""
    return gyro_ekf_with_bias(m, u, vehicle, Q, R, **gyro)[0]


def gyro_ekf_with_bias(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray,
                       R: np.ndarray, **gyro: Any) -> tuple[Posterior, np.ndarray]:
    """:func:`gyro_ekf_batch`'s posterior and the gyro's bias it estimated at the last step
    (G,)."""
    m, u = check_trajectories(m, u)
    if not np.isfinite(u).all():
        raise LboError("the gyro EKF needs V and r_m at every step (NaN or inf found)")
    flt = GyroStepper(m[:, 0], vehicle, Q, batch_cov(R, m.shape[0], "R"), **gyro)
    checks = Checks.empty(*m.shape[:2])
    out = run_stepper(flt, m, u, pose=lambda kf: kf.x[:, :3], cov=lambda kf: kf.P[:, :3, :3],
                      record=lambda kf, k: kf.consistency.record(checks, k))
    return Posterior(*out, checks=checks), flt.x[:, 3]
