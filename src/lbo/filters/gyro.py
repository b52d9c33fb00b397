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

import math
from typing import Any

import numpy as np

from lbo.core.errors import LboError
from lbo.filters import measure
from lbo.filters.consistency import Checks, NisWindow, widen
from lbo.filters.gyro_noise import BIAS_SIGMA, BIAS_WALK, GYRO_SIGMA, FixDrift
from lbo.filters.start import CourseStart, batch_cov, check_trajectories, start_state
from lbo.filters.stepper import Posterior, run_stepper
from lbo.filters.update import joseph_update, nis
from lbo.sim.vehicle import Vehicle

STILL_SPEED = 0.05
"""Speed (m/s) below which the car stands: it does not turn, so its heading is held and the
gyro's reading is its bias (a zero-rate update, as INS filters make at standstill)."""


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

    @property
    def coasts(self) -> bool:
        """Whether :meth:`coast` may stand for a run of rows without a measurement: every
        trajectory knows its heading (a blind one dead-reckons its course start)."""
        return not self.course.blind.any()

    def coast(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """n rows without a measurement at once, as n calls of :meth:`update` would give them
        (poses to the last bit, covariances to rounding), where :attr:`coasts`. u : (G, n, 2)
        ``u_{k-1}`` of each row. Returns the poses (G, n, 3) and their covariances (G, n, 3, 3).

        A row where a trajectory stands takes its zero-rate update, as :meth:`update` does;
        each run of rows between such rows is predicted at once (:meth:`_moving`)."""
        g, n = u.shape[:2]
        poses, covs = np.empty((g, n, 3)), np.empty((g, n, 3, 3))
        still = (np.abs(u[..., 0] * self.scales[0]) < STILL_SPEED).any(0)
        k = 0
        while k < n:
            if still[k]:
                poses[:, k] = self.update(np.full((g, 3), np.nan), u[:, k])
                covs[:, k] = self.P[:, :3, :3]
                k += 1
                continue
            end = k + int(np.argmin(np.append(~still[k:], False)))  # the run's end
            poses[:, k:end], covs[:, k:end] = self._moving(u[:, k:end])
            k = end
        return poses, covs

    def _moving(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """j prediction-only steps of trajectories that all move, u (G, j, 2): the poses
        (G, j, 3) and their covariances (G, j, 3, 3); the state is left at the last step's.

        The bias is held, so the heading moves by the gyro alone and the poses are cumulative
        sums, added in the order :meth:`_predict` adds them; the drift decays by a constant
        factor; the covariance is the steps' maps composed
        (:func:`lbo.filters.kalman.compose_covariance`)."""
        from lbo.filters.kalman import compose_covariance

        g, j = u.shape[:2]
        v, rate = np.moveaxis(u * self.scales, -1, 0)  # (G, j) each
        dt, x = self.dt, self.x
        psi = np.cumsum(np.concatenate([x[:, 2:3], (rate - x[:, 3:4]) * dt], 1), 1)
        before = psi[:, :-1]  # the heading each step starts from
        east = np.cumsum(np.concatenate([x[:, :1], v * np.cos(before) * dt], 1), 1)
        north = np.cumsum(np.concatenate([x[:, 1:2], v * np.sin(before) * dt], 1), 1)
        drift = np.cumprod(np.concatenate(  # (G, j + 1, 0) without a drift
            [x[:, None, 4:], np.full((g, j, x.shape[1] - 4), self.phi)], 1), 1)
        F = np.tile(np.eye(x.shape[1]), (j, g, 1, 1))  # (j, G, n, n): the steps' Jacobians
        F[..., 0, 2] = (-v * np.sin(before) * dt).T
        F[..., 1, 2] = (v * np.cos(before) * dt).T
        F[..., 2, 3] = -dt
        F[..., 4:, 4:] *= self.phi
        A, B = compose_covariance(F, np.broadcast_to(self.Q, F.shape))
        P = A @ self.P @ A.swapaxes(-1, -2) + B
        P = np.moveaxis(0.5 * (P + P.swapaxes(-1, -2)), 0, 1)  # (G, j, n, n)
        self.x = np.concatenate([east[:, -1:], north[:, -1:], psi[:, -1:], x[:, 3:4],
                                 drift[:, -1]], axis=1)
        self.P = P[:, -1].copy()
        return np.stack([east[:, 1:], north[:, 1:], psi[:, 1:]], -1), P[..., :3, :3]

    def _predict(self, u_prev: np.ndarray) -> tuple[np.ndarray, ...]:
        """One step of the model with ``u_prev`` (G, 2) ``[V, r_m]`` (the course start
        dead-reckoned with it): the prior ``x, P``, ``cross``, and ``still`` (G,) bool and the
        gyro's ``rate`` (G,) as read."""
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
        return x, P, cross, still, rate

    def update(self, m: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Predict with ``u_prev`` (G, 2) ``[V, r_m]`` of the last step, update with what row
        m (G, 3) or (G, 8) holds; returns the pose (G, 3)."""
        m = measure.widen(m)
        x, P, cross, still, rate = self._predict(u_prev)
        if self.coasts and not np.isfinite(m).any():
            # no channel in any trajectory (most rows of a log) and every heading known: at
            # most the gyro's zero rate at standstill, one scalar update of the bias, taken
            # without the general one
            self.cross, self.prior = cross, (x, P)
            self.x, self.P = _standstill(x, P, still, rate, self.gyro_var)
            return self.x[:, :3]
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


def _standstill(x: np.ndarray, P: np.ndarray, still: np.ndarray, rate: np.ndarray,
                var: float) -> tuple[np.ndarray, np.ndarray]:
    """The prior x (G, n), P (G, n, n) updated, where ``still`` (G,), with the gyro's reading
    ``rate`` (G,) of the bias (variance ``var``): :func:`lbo.filters.update.joseph_update`
    of that one channel, to rounding; P only symmetrised elsewhere."""
    K = np.where(still[:, None], P[:, :, 3] / (P[:, 3, 3] + var)[:, None], 0.0)  # (G, n)
    x = x + K * (rate - x[:, 3])[:, None]
    I_KH = np.eye(x.shape[1]) - K[:, :, None] * (np.arange(x.shape[1]) == 3)
    post = I_KH @ P @ I_KH.swapaxes(-1, -2) + var * K[:, :, None] * K[:, None, :]
    return x, 0.5 * (post + post.swapaxes(-1, -2))


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
