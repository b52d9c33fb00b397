"""Model-based observers for the kinematic bicycle and the bound they cannot beat.

Conventions, shared by every function here: a batch of ``G`` trajectories of ``T`` steps,
measurements ``m`` of shape (G, T, 3) = ``[x_m, y_m, psi_m]`` and inputs ``u`` of shape
(G, T, 2) = ``[V, delta]``, where ``u[:, k]`` moves ``z_k`` to ``z_{k+1}``. The estimate at
step ``k`` uses ``m_0 .. m_k`` and ``u_0 .. u_{k-1}``. Every filter starts from
``z_0 = m_0`` and ``P_0 = R`` (diagonal floored at :data:`COV_FLOOR`), measures the state
directly (H = I) and wraps heading innovations to (-pi, pi]. Estimated headings stay on the
branch of the measurements (continuous, not wrapped); metrics wrap the error.

A row of ``m`` holds any allowed subset of its channels, NaN in the others: a full fix, a
position fix without a heading (``psi_m`` NaN), or nothing (a prediction-only step). Every
stepper builds H and R per step from what the row holds and updates through the one
Joseph-form :func:`lbo.filters.update.joseph_update`; a channel not held teaches the adaptive
R nothing. The first row of every trajectory must hold a position, as the filters start
there. A trajectory that starts without a heading takes it from the course over ground
(:class:`CourseStart`): until then its heading is 0 rad with variance :data:`HEADING_VAR0`.

- :class:`BicycleEKF` / :func:`run_filterpy_ekf`: the paper's EKF on filterpy, one trajectory
  at a time (the reference).
- :func:`ekf_batch`: the same EKF vectorised over trajectories; ``R`` per trajectory gives the
  paper's EKF (alpha=1 R everywhere) and the oracle (R at the true alpha) in one call.
- :func:`adaptive_ekf_batch`: Sage-Husa EKF that learns a diagonal R from its innovations.
- :func:`ukf` / :func:`ukf_filterpy_batch`: filterpy's unscented filter on the same model;
  :func:`ukf_batch`: the same filter vectorised over trajectories.
- :func:`pcrb`: posterior Cramer-Rao bound (Tichavsky et al. 1998) on the error variances.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from tqdm.auto import tqdm

from lbo.core.errors import LboError
from lbo.filters import measure
from lbo.filters.update import held_channels, joseph_update
from lbo.sim.vehicle import Vehicle, jacobian, step, wrap_angle

COV_FLOOR = 1e-9
"""Smallest variance put on the diagonal of P_0 (and of the UKF's R), so alpha=0 runs."""

_I3 = np.eye(3)

HEADING_VAR0 = 1.0
"""Variance (rad^2) of the starting heading (0 rad, as good as any) of a trajectory whose
first fix has none. Not that of a heading uniform on the circle (pi^2 / 3): the UKF's circular
mean of its sigma points, whose resultant is about ``1 - var / 2`` with Merwe's negative
central weight, flips to the opposite heading beyond a variance of 2. It only sets how far the
filter trusts its own motion until the course over ground gives the heading on a flat prior
(:class:`CourseStart`), which forgets it."""
COURSE_SIGMAS = 10.0
"""Distance the car must have moved from its first fix, in position-noise sigmas, before the
course over ground sets its heading: the chord's direction is then known to about
sqrt(2) / 10 = 0.14 rad at worst, and the filter refines it from the motion that follows."""
COURSE_MIN_M = 1.0
"""Floor (m) on that distance, for a noise-free (alpha = 0) log."""
FLAT_VAR = 1e6
"""Heading variance (rad^2) of the flat prior that the first heading (measured, or from the
course over ground) is taken on: whatever the filter guessed before is forgotten."""


def _residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a - b`` over the leading axis [x, y, psi] with the heading difference wrapped."""
    d = np.subtract(a, b)
    d[2] = wrap_angle(d[2])
    return d


def _floor_diag(cov: np.ndarray, floor: float = COV_FLOOR) -> np.ndarray:
    """Copy of cov (..., 3, 3) whose diagonal is at least ``floor``."""
    out = np.array(cov, dtype=float, copy=True)
    idx = np.arange(3)
    out[..., idx, idx] = np.maximum(out[..., idx, idx], floor)
    return out


def _check_trajectories(m: np.ndarray, u: np.ndarray, receiver: bool = True
                        ) -> tuple[np.ndarray, np.ndarray]:
    """m (G, T, 3), or (G, T, 8) with a receiver's channels where ``receiver``, and u
    (G, T, 2), checked; the first row of each trajectory must hold a position."""
    m = np.asarray(m, dtype=float)
    u = np.asarray(u, dtype=float)
    widths = (3, measure.WIDTH) if receiver else (3,)
    if m.ndim != 3 or m.shape[-1] not in widths:
        raise LboError(f"measurements m must be (G, T, 3) [x_m, y_m, psi_m] or (G, T, "
                       f"{measure.WIDTH}) with a receiver's channels "
                       f"({', '.join(measure.CHANNELS)}), got {m.shape}")
    if u.shape != m.shape[:2] + (2,):
        raise LboError(f"inputs u must be (G, T, 2) [V, delta] matching m {m.shape}, got {u.shape}")
    if m.shape[1] and not np.isfinite(m[:, 0, :2]).all():
        g = int(np.flatnonzero(~np.isfinite(m[:, 0, :2]).all(-1))[0])
        raise LboError(f"trajectory {g} has no position fix at its first step; the filters "
                       "start at one")
    return m, u


def _start(m0: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Starting state (G, 3) and covariance (G, 3, 3) at the first rows m0 (G, 3) or (G, 8):
    the fix and the step's R (the accuracies it reports, :func:`lbo.filters.measure.step_cov`;
    diagonal floored). Its heading is ``psi_m``, else the course over ground (its variance
    ``s_course^2``), else 0 rad with variance :data:`HEADING_VAR0`."""
    m0 = measure.widen(m0)
    x = np.array(m0[:, :3], dtype=float)
    P = _floor_diag(measure.step_cov(m0, R))
    by_course = ~np.isfinite(x[:, 2]) & np.isfinite(m0[:, 6])
    blind = ~measure.heading_held(m0)
    x[by_course, 2] = m0[by_course, 6]
    x[blind, 2] = 0.0
    for rows, var in ((by_course, np.square(m0[:, 7])), (blind, HEADING_VAR0)):
        P[rows, 2, :] = P[rows, :, 2] = 0.0
        P[rows, 2, 2] = var[rows] if np.ndim(var) else var
    return x, P


UKF_SPREAD = 0.1
"""Merwe's sigma-point spread of lbo's UKF (alpha of the scaled unscented transform)."""


class CourseStart:
    """The heading of trajectories whose fixes came without one, from the course over ground.

    The kinematic bicycle turns at ``V tan(delta) / L`` whatever its heading, so from the
    inputs alone the path since the first fix is known in the frame of the unknown starting
    heading psi_0: ``c_k`` (dead reckoning with the filter's own Euler step, turn ``a_k``).
    The fixes see the same path rotated by psi_0, so at a position fix ``p_k`` once the car
    has moved ``|c_k| >= max(COURSE_SIGMAS sigma, COURSE_MIN_M)`` (sigma: the position
    noise), ``psi_0 = angle(p_k - p_0) - angle(c_k)`` and the heading now is ``psi_0 + a_k``,
    reversing (V < 0) and curves included. Its variance: the two fixes' noise across the chord,
    ``2 sigma^2 / |c_k|^2``, plus the process noise over the k steps, ``k Q_xx / |c_k|^2 +
    k Q_psipsi``. The stepper takes it as a measurement of the heading on a flat prior
    (:data:`FLAT_VAR`), as it takes a first measured heading. Vectorised over G trajectories.

    Parameters
    ----------
    m0 : (G, 3) or (G, 8) first rows (:data:`lbo.filters.measure.CHANNELS`); a fix without a
        heading starts the course.
    vehicle : Vehicle
    Q : (3, 3) process covariance.

    Attributes
    ----------
    blind : (G,) bool, trajectories whose heading is not known yet.
    """

    def __init__(self, m0: np.ndarray, vehicle: Vehicle, Q: np.ndarray) -> None:
        self.vehicle, self.Q = vehicle, Q
        self.blind = ~measure.heading_held(measure.widen(m0))
        self.p0 = np.array(m0, dtype=float)[:, :2]
        self.c = np.zeros_like(self.p0)
        self.turn = np.zeros(len(self.p0))
        self.steps = np.zeros(len(self.p0))

    def advance(self, u_prev: np.ndarray, turn: np.ndarray | None = None) -> None:
        """Dead-reckon one step with inputs u_prev (G, 2), as :func:`lbo.sim.vehicle.step`;
        ``turn`` (G,) rad/s: the heading turns at this rate instead (a gyro-driven model)."""
        if not self.blind.any():
            return
        state = np.concatenate([self.c, self.turn[:, None]], axis=1)
        if turn is None:
            path = step(state, u_prev, self.vehicle.dt, self.vehicle.wheelbase)
        else:
            dt, v = self.vehicle.dt, u_prev[:, 0]
            path = state + dt * np.stack([v * np.cos(state[:, 2]), v * np.sin(state[:, 2]),
                                          turn], axis=1)
        self.c = np.where(self.blind[:, None], path[:, :2], self.c)
        self.turn = np.where(self.blind, path[:, 2], self.turn)
        self.steps = self.steps + self.blind

    def take(self, m: np.ndarray, pos_var: np.ndarray, P: np.ndarray, R: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """This step's heading channel: rows m (G, 8), position noise variance
        pos_var (G,), prior covariance P (G, n, n) and R (G, 3, 3).

        Returns ``(m, R, P, start)``: m with the course's heading where it sets one, R with
        its variance there, P with a flat prior heading (uncorrelated, :data:`FLAT_VAR`)
        where the first heading comes now (measured or from the course), and ``start`` (G,)
        where it does. Copies where anything changes; the inputs are not modified."""
        start = self.blind & np.isfinite(m[:, 0]) & np.isfinite(m[:, 1])
        if not start.any():
            return m, R, P, start
        measured = measure.heading_held(m)
        dist = np.hypot(*self.c.T)
        moved = dist >= np.maximum(COURSE_SIGMAS * np.sqrt(pos_var), COURSE_MIN_M)
        course = start & ~measured & moved
        start = start & (measured | moved)
        if not start.any():
            return m, R, P, start
        d = m[:, :2] - self.p0
        safe = np.where(course, dist, 1.0)
        psi = np.arctan2(d[:, 1], d[:, 0]) - np.arctan2(self.c[:, 1], self.c[:, 0]) + self.turn
        var = ((2.0 * pos_var + self.steps * self.Q[0, 0]) / safe**2
               + self.steps * self.Q[2, 2])
        m = m.copy()
        m[course, 2] = psi[course]
        R = np.array(R, dtype=float)
        R[course, 2, :] = R[course, :, 2] = 0.0
        R[course, 2, 2] = var[course]
        P = np.array(P, dtype=float)
        P[start, 2, :] = P[start, :, 2] = 0.0
        P[start, 2, 2] = FLAT_VAR
        self.blind = self.blind & ~start
        return m, R, P, start


def _innovation(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``m - x`` (G, 3), heading wrapped; 0 in the channels m does not hold."""
    y = np.where(np.isfinite(m), m - x, 0.0)
    y[:, 2] = wrap_angle(y[:, 2])
    return y


def _batch_cov(cov: np.ndarray, g: int, name: str) -> np.ndarray:
    """(3, 3) or (G, 3, 3) -> read-only (G, 3, 3) view."""
    cov = np.asarray(cov, dtype=float)
    if cov.shape not in ((3, 3), (g, 3, 3)):
        raise LboError(f"{name} must be (3, 3) or ({g}, 3, 3), got {cov.shape}")
    return np.broadcast_to(cov, (g, 3, 3))


def _check_q(Q: np.ndarray) -> np.ndarray:
    Q = np.asarray(Q, dtype=float)
    if Q.shape != (3, 3):
        raise LboError(f"process covariance Q must be (3, 3), got {Q.shape}")
    return Q


# --------------------------------------------------------------------------- filterpy EKF


class BicycleEKF(ExtendedKalmanFilter):
    """The paper's EKF: filterpy's ExtendedKalmanFilter with the bicycle step as prediction.

    Parameters
    ----------
    vehicle : Vehicle
        Supplies ``dt`` and ``wheelbase``.
    Q : (3, 3) process covariance.
    R : (3, 3) measurement covariance.

    Attributes
    ----------
    x : (3, 1) state estimate ``[x, y, psi]``; psi continuous.
    P : (3, 3) state covariance.
    F : (3, 3) Jacobian of the last prediction, evaluated at the state it started from.
    Q, R : (3, 3) process and measurement covariances (public, as in filterpy).
    """

    def __init__(self, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray) -> None:
        super().__init__(dim_x=3, dim_z=3)
        self.vehicle = vehicle
        self.Q = _check_q(Q).copy()
        self.R = np.asarray(R, dtype=float).copy()

    def predict_x(self, u: np.ndarray = 0) -> None:
        """Bicycle step ``z + f(z, u) dt``; u: (2,) ``[V, delta]``.

        Also sets ``F`` at the pre-step state, which filterpy's ``predict`` then uses for P.
        """
        z = self.x[:, 0]
        self.F = jacobian(z, u, self.vehicle.dt)
        self.x = step(z, u, self.vehicle.dt, self.vehicle.wheelbase)[:, None]

    @staticmethod
    def residual(z: np.ndarray, hx: np.ndarray) -> np.ndarray:
        """Innovation ``z - hx`` with the heading wrapped to (-pi, pi]. (3, 1) -> (3, 1)."""
        return _residual(z, hx)

    def update(self, z, HJacobian=None, Hx=None, R=None, args=(), hx_args=(), residual=None):
        """filterpy's update with H = I, h(x) = x and :meth:`residual` as defaults.

        z : (3,) or (3, 1) measurement ``[x_m, y_m, psi_m]``.
        """
        super().update(
            np.reshape(z, (3, 1)),
            HJacobian if HJacobian is not None else (lambda x: _I3),
            Hx if Hx is not None else (lambda x: x),
            R=R, args=args, hx_args=hx_args,
            residual=residual if residual is not None else self.residual,
        )


def run_filterpy_ekf(m: np.ndarray, u: np.ndarray, vehicle: Vehicle,
                     Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Run :class:`BicycleEKF` over one trajectory: the slow reference loop.

    Parameters
    ----------
    m : (T, 3) measurements.
    u : (T, 2) inputs; ``u[k]`` moves ``z_k`` to ``z_{k+1}``.
    vehicle : Vehicle
    Q, R : (3, 3) process and measurement covariances.

    Returns
    -------
    (T, 3) filtered estimates; row 0 is ``m_0``.
    """
    m, u = _check_trajectories(np.asarray(m)[None], np.asarray(u)[None], receiver=False)
    m, u = m[0], u[0]
    ekf = BicycleEKF(vehicle, Q, R)
    ekf.x = m[0][:, None].copy()
    ekf.P = _floor_diag(ekf.R)
    est = np.empty_like(m)
    est[0] = m[0]
    for k in range(1, len(m)):
        ekf.predict(u[k - 1])
        ekf.update(m[k])
        est[k] = ekf.x[:, 0]
    return est


# --------------------------------------------------------------------------- batched EKFs


class KalmanStepper:
    """The EKF of :func:`ekf_batch` (or, with ``forgetting``, the Sage-Husa EKF of
    :func:`adaptive_ekf_batch`) one time step per call, over G trajectories.

    Both batch filters loop over it, and :class:`lbo.Observer` steps it one sample at a time,
    so streaming and batch give the same numbers.

    Parameters
    ----------
    m0 : (G, 3) first measurements (position fixes); the state starts there with P_0 = R
        (a NaN heading: see :func:`_start` and :class:`CourseStart`).
    vehicle : Vehicle
    Q : (3, 3) process covariance.
    R : (G, 3, 3) measurement covariance (the starting one when adaptive).
    forgetting, prior_weight, r_floor : Sage-Husa settings (see :func:`adaptive_ekf_batch`);
        ``forgetting=None`` is the plain EKF. r_floor: (G, 3) absolute floor on diag(R).

    Attributes
    ----------
    x : (G, 3) current estimate. P : (G, 3, 3) its covariance. R : (G, 3, 3) current R.
    n_fix : (G, 3) measurements taken per channel, m0's included.
    prior : ``(x, P)`` (G, 3), (G, 3, 3), the prior the last posterior came from.
    cross : (G, 3, 3) ``cov(x_{k-1|k-1}, x_{k|k-1})`` of the last step, for smoothing.
    course : :class:`CourseStart`, the heading of trajectories that started without one.
    """

    def __init__(self, m0: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
                 forgetting: float | None = None, prior_weight: float = 0.0,
                 r_floor: np.ndarray | None = None) -> None:
        self.vehicle, self.Q = vehicle, Q
        self.forgetting, self.r_floor = forgetting, r_floor
        self.R = np.array(R, dtype=float)
        m0 = measure.widen(m0)
        held = held_channels(m0[:, :3])
        if forgetting is not None:
            m0 = m0.copy()
            m0[:, 3:6] = np.nan  # it learns R: reported accuracies are not its to take
            diag = np.arange(3)
            self.r_hat = self.R[:, diag, diag].copy()           # (G, 3) diagonal of the learned R
            # innovations r_hat is worth, per channel (a position fix teaches psi nothing)
            self.weight = np.full(self.r_hat.shape, float(prior_weight))
            self.R = np.zeros_like(self.R)
            self.R[:, diag, diag] = self.r_hat
        self.x, self.P = _start(m0, self.R)
        self.n_fix = held.astype(float)
        self.course = CourseStart(m0, vehicle, Q)

    def update(self, m: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Predict with u_{k-1} (G, 2), update with what row m_k (G, 3) or (G, 8) holds
        (:mod:`lbo.filters.measure`); returns x_k (G, 3).

        A row's NaN channels are not measured (all of them: a prediction-only step). The
        adaptive filter learns its own R and takes no reported accuracy."""
        m = measure.widen(m)
        held = held_channels(m[:, :3])
        F = jacobian(self.x, u_prev, self.vehicle.dt)
        x = step(self.x, u_prev, self.vehicle.dt, self.vehicle.wheelbase)
        self.course.advance(u_prev)
        cross = self.P @ F.swapaxes(-1, -2)  # cov(x_{k-1|k-1}, x_{k|k-1}), for smoothing
        P = F @ self.P @ F.swapaxes(-1, -2) + self.Q
        R = self.R
        if self.forgetting is not None:
            y = _innovation(m[:, :3], x)
            diag = np.arange(3)
            # P_0 = R0 is wrong by the unknown alpha^2; n measurements of noise R cannot give
            # a prior error below R / n, so hold P there until it settles (channels measured
            # now and before: a heading never measured has no such bound)
            hold = held & (self.n_fix > 0)
            floor = self.r_hat / np.where(hold, self.n_fix, 1.0)
            P = P.copy()
            P[:, diag, diag] = np.where(hold, np.maximum(P[:, diag, diag], floor),
                                        P[:, diag, diag])
            # Sage-Husa: E[y y^T] = P_prior + R, so y^2 - diag(P_prior) is one sample of R;
            # exponentially forgotten running mean, weights 1 / (b W + 1); held channels only
            self.weight = np.where(held, self.forgetting * self.weight + 1.0, self.weight)
            d = np.where(held, 1.0 / self.weight, 0.0)
            self.r_hat = np.maximum((1.0 - d) * self.r_hat + d * (y**2 - P[:, diag, diag]),
                                    self.r_floor)
            R = R.copy()
            R[:, diag, diag] = self.r_hat
            self.R = R
        else:
            R = measure.step_cov(m, R)
        pos_var = 0.5 * (R[:, 0, 0] + R[:, 1, 1])
        m, R, P, start = self.course.take(m, pos_var, P, R)
        if start.any():
            cross = np.array(cross)
            cross[start, :, 2] = 0.0  # the flat heading prior owes nothing to the past state
        self.cross = cross
        self.prior = (x, P)  # the prior each posterior came from
        self.x, self.P = joseph_update(x, P, *measure.model(m, x, R))
        self.n_fix = self.n_fix + held
        return self.x


    @property
    def coasts(self) -> bool:
        """Whether :meth:`coast` may stand for a run of prediction-only steps: a plain EKF
        (the adaptive one updates its R between fixes) whose trajectories all know their
        heading (a blind one dead-reckons its course start step by step)."""
        return self.forgetting is None and not self.course.blind.any()

    def coast(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """n prediction-only steps at once, as n calls of :meth:`update` with rows that hold
        nothing would give them (poses to the last bit, covariances to rounding), where
        :attr:`coasts`. u : (G, n, 2) the inputs ``u_{k-1}`` of each step.

        Returns the poses (G, n, 3) and covariances (G, n, 3, 3) after each step; the state is
        the last one's. No ``prior`` nor ``cross`` is kept: a smoother steps one by one.

        Why it is exact and vectorised: the bicycle's heading moves by its inputs alone, so
        the poses are cumulative sums; and each step's Jacobian is ``I + a_k e3^T`` (a_k with
        no heading component), so the product of any run of them is ``I + (sum a) e3^T`` and
        ``P_n = Phi_n P_0 Phi_n^T + sum_m Phi_{n,m} Q Phi_{n,m}^T`` takes cumulative sums of
        ``S_m = a_0 + ... + a_{m-1}`` and of ``S_m S_m^T``.
        """
        dt, wheelbase = self.vehicle.dt, self.vehicle.wheelbase
        v, delta = u[..., 0], u[..., 1]
        g, n = v.shape
        # the poses, added in the order step() adds them: cumulative sums start at the state
        psi = np.cumsum(np.concatenate([self.x[:, 2:3], v * np.tan(delta) / wheelbase * dt],
                                       axis=1), axis=1)
        before = psi[:, :-1]  # the heading each step starts from
        east = np.cumsum(np.concatenate([self.x[:, :1], v * np.cos(before) * dt], axis=1), 1)
        north = np.cumsum(np.concatenate([self.x[:, 1:2], v * np.sin(before) * dt], axis=1), 1)
        poses = np.stack([east[:, 1:], north[:, 1:], psi[:, 1:]], axis=-1)
        # the covariances: a_k = dstep/dpsi of step k, S (G, n, 3) its running sums S_1..S_n
        a = np.stack([-v * np.sin(before) * dt, v * np.cos(before) * dt, np.zeros_like(v)], -1)
        S = np.cumsum(a, axis=1)
        C1 = np.cumsum(S, axis=1)
        SS = S[..., :, None] * S[..., None, :]
        C2 = np.cumsum(SS, axis=1)
        P0, Q = self.P[:, None], self.Q
        count = np.arange(1, n + 1, dtype=float)[None, :, None]
        outer = lambda p, q: p[..., :, None] * q[..., None, :]  # noqa: E731
        P = (P0 + outer(S, P0[..., 2, :]) + outer(P0[..., :, 2], S)
             + P0[..., 2:3, 2:3] * SS)
        D = count * S - C1                                    # sum over m of S_n - S_m
        DD = count[..., None] * SS - outer(S, C1) - outer(C1, S) + C2
        P = (P + count[..., None] * Q + outer(D, np.broadcast_to(Q[2], D.shape))
             + outer(np.broadcast_to(Q[:, 2], D.shape), D) + Q[2, 2] * DD)
        P = 0.5 * (P + P.swapaxes(-1, -2))
        self.x, self.P = poses[:, -1].copy(), P[:, -1].copy()
        return poses, P


def adaptive_settings(R0: np.ndarray, g: int, forgetting: float = 0.99,
                      prior_weight: float = 1.0, r_floor: float = 1e-4) -> dict:
    """Checked keyword arguments of a Sage-Husa :class:`KalmanStepper` (R0 (3,3) or (G,3,3))."""
    if not 0.0 < forgetting <= 1.0:
        raise LboError(f"forgetting must be in (0, 1], got {forgetting}")
    if prior_weight < 0 or r_floor < 0:
        raise LboError(f"prior_weight and r_floor must be >= 0, got {prior_weight}, {r_floor}")
    R0 = _batch_cov(R0, g, "R0")
    idx = np.arange(3)
    return {"R": R0, "forgetting": forgetting, "prior_weight": prior_weight,
            "r_floor": np.maximum(r_floor * R0[:, idx, idx], COV_FLOOR)}


def _ekf_loop(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
              return_cov: bool, smooth: bool = False, lengths: np.ndarray | None = None,
              **adaptive):
    """Shared time loop of :func:`ekf_batch` and :func:`adaptive_ekf_batch`."""
    m, u = _check_trajectories(m, u)
    kf = KalmanStepper(m[:, 0], vehicle, _check_q(Q), _batch_cov(R, m.shape[0], "R"), **adaptive)
    return run_stepper(kf, m, u, return_cov, smooth=smooth, lengths=lengths)


def run_stepper(kf, m: np.ndarray, u: np.ndarray, return_cov: bool = False,
                pose: Callable[[Any], np.ndarray] = lambda kf: kf.x,
                cov: Callable[[Any], np.ndarray] = lambda kf: kf.P, smooth: bool = False,
                progress: str | None = None, lengths: np.ndarray | None = None):
    """The time loop of a batch filter: a stepper ``kf`` started at ``m[:, 0]``, updated with
    every later step. ``pose(kf)`` (G, 3) and ``cov(kf)`` (G, 3, 3) read its estimate and
    covariance. Returns (G, T, 3) estimates, and (G, T, 3, 3) covariances with
    ``return_cov``. With ``smooth`` (a stepper that records ``prior`` and ``cross``, of three
    states), the estimates and covariances are the RTS smoother's (:mod:`lbo.filters.smoother`).
    ``progress``: show a tqdm bar over the time steps with this name; ``lengths`` (G,): the
    real steps of padded trajectories, which the smoother does not smooth across."""
    from lbo.filters.smoother import rts

    g, t = m.shape[:2]
    est = np.empty((g, t, 3))
    est[:, 0] = pose(kf)
    covs = np.empty((g, t, 3, 3)) if return_cov or smooth else None
    if covs is not None:
        covs[:, 0] = cov(kf)
    if smooth:
        x_p, P_p, cross = np.zeros_like(est), np.zeros_like(covs), np.zeros_like(covs)
    bar = tqdm(total=t - 1, desc=progress, unit="step", disable=progress is None,
               mininterval=2.0)
    # rows where no trajectory holds any channel: a stepper that can (``coasts``) takes each
    # run of them in one call (most rows of a log with 1-10 Hz fixes at 50 Hz)
    quiet = ~np.isfinite(m).any(axis=(0, 2))
    can_coast = not smooth and hasattr(kf, "coast")
    k = 1
    while k < t:
        if can_coast and quiet[k] and kf.coasts:
            end = k + int(np.argmin(np.append(quiet[k:], False)))  # the run's end
            est[:, k:end], run_covs = kf.coast(u[:, k - 1:end - 1])
            if covs is not None:
                covs[:, k:end] = run_covs
            bar.update(end - k)
            k = end
            continue
        kf.update(m[:, k], u[:, k - 1])
        est[:, k] = pose(kf)
        if covs is not None:
            covs[:, k] = cov(kf)
        if smooth:
            x_p[:, k], P_p[:, k] = kf.prior
            cross[:, k] = kf.cross
        bar.update(1)
        k += 1
    bar.close()
    if smooth:
        est, covs = rts(est, covs, x_p, P_p, cross, lengths=lengths)
    return (est, covs) if return_cov else est


def ekf_batch(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
              return_cov: bool = False, smooth: bool = False,
              lengths: np.ndarray | None = None) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """The EKF of :class:`BicycleEKF`, vectorised over G trajectories (loop over time only).

    Gives the filterpy loop's numbers to rounding (about 1e-12).

    Parameters
    ----------
    m : (G, T, 3) measurements ``[x_m, y_m, psi_m]``.
    u : (G, T, 2) inputs ``[V, delta]``.
    vehicle : Vehicle
    Q : (3, 3) process covariance.
    R : (3, 3) shared, or (G, 3, 3) per trajectory (e.g. ``noise.R(alpha_g)`` for the oracle).
    return_cov : also return the posterior covariances.
    smooth : the RTS smoother's estimates and covariances instead (:mod:`lbo.filters.smoother`).
    lengths : (G,) real steps of padded trajectories, for the smoother (None: all).

    Returns
    -------
    est : (G, T, 3) filtered estimates; ``est[:, 0] = m[:, 0]`` (smoothed with ``smooth``).
    P : (G, T, 3, 3) their covariances, only when ``return_cov``.
    """
    return _ekf_loop(m, u, vehicle, Q, R, return_cov, smooth, lengths)


class AdaptiveStepper(KalmanStepper):
    """The Sage-Husa EKF of :func:`adaptive_ekf_batch` one step per call, built as every
    classical observer is (``(m0, vehicle, Q, R)``, docs/plugins.md): ``R`` is where it starts,
    and it learns R from its innovations from then on."""

    def __init__(self, m0: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray) -> None:
        super().__init__(m0, vehicle, Q, **adaptive_settings(R, len(m0)))


def adaptive_ekf_batch(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray,
                       R0: np.ndarray, forgetting: float = 0.99, prior_weight: float = 1.0,
                       r_floor: float = 1e-4,
                       return_cov: bool = False, smooth: bool = False,
                       lengths: np.ndarray | None = None
                       ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Noise-adaptive EKF: learns a diagonal R online from its innovations (Sage-Husa).

    It is never told alpha. At each step the innovation ``y = wrap(m_k - x_k^-)`` gives a
    sample ``y_i^2 - P^-_ii`` of ``R_ii``; R is their exponentially forgotten mean

        R_k = (1 - d_k) R_{k-1} + d_k (y_k^2 - diag(P_k^-)),   d_k = 1 / W_k,
        W_k = b W_{k-1} + 1,  W_0 = prior_weight,

    floored at ``r_floor * diag(R0)`` so it stays positive, and the update uses ``R_k``.
    ``prior_weight=0`` is the classic Sage-Husa weighting ``d_k = (1 - b) / (1 - b^k)``.

    ``P_0 = R0`` is too small by alpha^2 when alpha > 1, and plain Sage-Husa then needs
    hundreds of steps to shed the initial error (at alpha=6 it did worse than the fixed EKF).
    So the prior's diagonal is held at least at ``R_{k-1} / k``: the error of an estimate
    from k measurements of noise R. The hold stops mattering once P reaches its steady
    state (after about 15 steps at alpha=1, 90 at alpha=6).

    Parameters
    ----------
    m : (G, T, 3) measurements.
    u : (G, T, 2) inputs.
    vehicle : Vehicle
    Q : (3, 3) process covariance.
    R0 : (3, 3) or (G, 3, 3) starting R, normally the alpha=1 R; off-diagonals are ignored.
    forgetting : b in (0, 1]. 0.99 remembers about 100 steps (2 s): R settles within the
        first second or two of a trajectory and tracks changes of alpha on that time scale.
    prior_weight : how many innovations R0 is worth at the start; small, so that R0 is
        forgotten quickly when alpha is far from 1.
    r_floor : floor on R relative to diag(R0) (1e-4: a sigma of 1 % of R0's); an absolute
        :data:`COV_FLOOR` applies where R0 is zero.
    return_cov : also return the posterior covariances.

    Returns
    -------
    est : (G, T, 3) filtered estimates.
    P : (G, T, 3, 3) posterior covariances, only when ``return_cov``.
    """
    settings = adaptive_settings(R0, np.shape(m)[0], forgetting, prior_weight, r_floor)
    return _ekf_loop(m, u, vehicle, Q, return_cov=return_cov, smooth=smooth, lengths=lengths,
                     **settings)


# --------------------------------------------------------------------------- UKF


def _circular_mean(sigmas: np.ndarray, Wm: np.ndarray) -> np.ndarray:
    """Weighted mean of sigma points (2n+1, 3); psi by circular mean, kept on the branch of
    the first (central) sigma point so that the estimate stays continuous."""
    mean = Wm @ sigmas
    d = wrap_angle(sigmas[:, 2] - sigmas[0, 2])
    mean[2] = sigmas[0, 2] + np.arctan2(Wm @ np.sin(d), Wm @ np.cos(d))
    return mean


def ukf(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
        spread: float = UKF_SPREAD) -> np.ndarray:
    """Unscented Kalman filter (filterpy, Merwe scaled sigma points) over one trajectory.

    Same model, noise, initialisation and wrapped heading residuals as the EKF. R's
    diagonal is floored at :data:`COV_FLOOR` so the Cholesky factorisation of P survives
    alpha=0.

    Parameters
    ----------
    m : (T, 3) measurements.
    u : (T, 2) inputs.
    vehicle : Vehicle
    Q, R : (3, 3) process and measurement covariances.
    spread : Merwe's alpha (sigma-point spread); beta=2, kappa=0.

    Returns
    -------
    (T, 3) filtered estimates.
    """
    m, u = _check_trajectories(np.asarray(m)[None], np.asarray(u)[None], receiver=False)
    m, u = m[0], u[0]
    dt, wheelbase = vehicle.dt, vehicle.wheelbase
    points = MerweScaledSigmaPoints(3, alpha=spread, beta=2.0, kappa=0.0, subtract=_residual)
    flt = UnscentedKalmanFilter(
        dim_x=3, dim_z=3, dt=dt, points=points,
        fx=lambda z, dt, u: step(z, u, dt, wheelbase), hx=lambda z: z,
        x_mean_fn=_circular_mean, z_mean_fn=_circular_mean,
        residual_x=_residual, residual_z=_residual,
    )
    flt.Q = _check_q(Q).copy()
    flt.R = _floor_diag(R)
    flt.x = m[0].copy()
    flt.P = flt.R.copy()
    est = np.empty_like(m)
    est[0] = m[0]
    for k in range(1, len(m)):
        flt.predict(u=u[k - 1])
        flt.update(m[k])
        est[k] = flt.x
    return est


def ukf_filterpy_batch(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray,
                       R: np.ndarray, spread: float = UKF_SPREAD, progress: bool = False
                       ) -> np.ndarray:
    """:func:`ukf` over G trajectories, one after the other: filterpy's loop, the reference
    that :func:`ukf_batch` is tested and benchmarked against.

    Shapes as :func:`ukf_batch`; ``progress`` shows a tqdm bar.
    """
    m, u = _check_trajectories(m, u, receiver=False)
    R = _batch_cov(R, m.shape[0], "R")
    est = np.empty_like(m)
    for i in tqdm(range(m.shape[0]), desc="UKF (filterpy)", unit="traj", disable=not progress,
                  mininterval=2.0):
        est[i] = ukf(m[i], u[i], vehicle, Q, R[i], spread=spread)
    return est


def merwe_weights(n: int, spread: float, beta: float = 2.0,
                  kappa: float = 0.0) -> tuple[np.ndarray, np.ndarray, float]:
    """Merwe's scaled sigma-point weights, as filterpy: ``(Wm, Wc, lambda)``, each (2n+1,)."""
    lam = spread**2 * (n + kappa) - n
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = lam / (n + lam) + (1.0 - spread**2 + beta)
    return wm, wc, lam


def _sigma_points(x: np.ndarray, P: np.ndarray, lam: float) -> np.ndarray:
    """(G, 3), (G, 3, 3) -> (G, 7, 3): x, then x + and - the rows of the upper Cholesky factor
    of (n + lambda) P, headings wrapped (filterpy's order, with :func:`_residual` as its
    ``subtract``)."""
    n = x.shape[-1]
    rows = np.linalg.cholesky((n + lam) * P).swapaxes(-1, -2)  # upper factor U: rows U[k]
    sig = np.concatenate([x[:, None], x[:, None] + rows, x[:, None] - rows], axis=1)
    sig[:, 1:, 2] = wrap_angle(sig[:, 1:, 2])
    return sig


def _batch_mean(sig: np.ndarray, wm: np.ndarray) -> np.ndarray:
    """:func:`_circular_mean` over G sets of sigma points (G, S, 3) -> (G, 3)."""
    mean = np.einsum("s,gsi->gi", wm, sig)
    d = wrap_angle(sig[:, :, 2] - sig[:, :1, 2])
    mean[:, 2] = sig[:, 0, 2] + np.arctan2(np.sin(d) @ wm, np.cos(d) @ wm)
    return mean


def _deviations(sig: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """Sigma points minus their mean (G, S, 3), heading wrapped."""
    d = sig - mean[:, None]
    d[..., 2] = wrap_angle(d[..., 2])
    return d


class UnscentedStepper:
    """The UKF of :func:`ukf_batch` one time step per call, over G trajectories.

    The same sigma points (Merwe, beta=2, kappa=0, upper Cholesky factor, wrapped headings),
    weights and circular means as filterpy's :class:`~filterpy.kalman.UnscentedKalmanFilter`
    for the prediction. The measurement is linear (the channels a row holds, of the state
    itself), and the unscented transform of a linear map is exact: its update is the Kalman
    update, :func:`lbo.filters.update.joseph_update` as every stepper's (filterpy's
    ``P - K S K^T`` on sigma points redrawn from the prior is the same to rounding: 1e-9 over
    the test trajectories, tested). :func:`ukf_batch` loops over it and
    :class:`lbo.Observer` steps it one sample at a time, so streaming and batch agree.

    Parameters
    ----------
    m0 : (G, 3) first measurements (position fixes); the state starts there with P_0 = R
        (a NaN heading: as :class:`KalmanStepper`).
    vehicle : Vehicle
    Q : (3, 3) process covariance.
    R : (G, 3, 3) measurement covariance (diagonal floored at :data:`COV_FLOOR`).
    spread : Merwe's alpha.

    Attributes
    ----------
    x : (G, 3) current estimate. P : (G, 3, 3) its covariance.
    prior, cross, course : as :class:`KalmanStepper`'s.
    """

    def __init__(self, m0: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
                 spread: float = UKF_SPREAD) -> None:
        self.vehicle, self.Q = vehicle, _check_q(Q)
        self.R = _floor_diag(R)
        self.wm, self.wc, self.lam = merwe_weights(3, spread)
        self.x, self.P = _start(m0, self.R)
        self.course = CourseStart(m0, vehicle, self.Q)

    def update(self, m: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Predict with u_{k-1} (G, 2), update with what row m_k (G, 3) or (G, 8) holds (NaN
        channels are not measured, :mod:`lbo.filters.measure`); returns x_k (G, 3)."""
        m = measure.widen(m)
        wm, wc, lam = self.wm, self.wc, self.lam
        # predict: sigma points through the bicycle step, unscented transform plus Q
        before = _sigma_points(self.x, self.P, lam)
        sig = step(before, np.broadcast_to(u_prev[:, None], before.shape[:2] + (2,)),
                   self.vehicle.dt, self.vehicle.wheelbase)
        x = _batch_mean(sig, wm)
        d = _deviations(sig, x)
        P = np.einsum("s,gsi,gsj->gij", wc, d, d) + self.Q
        # cov(x_{k-1|k-1}, x_{k|k-1}) from the sigma points, for the URTS smoother
        cross = np.einsum("s,gsi,gsj->gij", wc, _deviations(before, self.x), d)
        self.course.advance(u_prev)
        R = measure.step_cov(m, self.R)
        m, R, P, start = self.course.take(m, 0.5 * (R[:, 0, 0] + R[:, 1, 1]), P, R)
        cross[start, :, 2] = 0.0  # the flat heading prior owes nothing to the past state
        self.cross = cross
        self.prior = (x, P)
        self.x, self.P = joseph_update(x, P, *measure.model(m, x, R))
        return self.x


def ukf_batch(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
              spread: float = UKF_SPREAD, progress: bool = False, return_cov: bool = False,
              smooth: bool = False, lengths: np.ndarray | None = None
              ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """:func:`ukf` vectorised over G trajectories (a loop over time only, of
    :class:`UnscentedStepper`): the numbers of :func:`ukf_filterpy_batch` to rounding.

    Parameters
    ----------
    m : (G, T, 3) measurements.
    u : (G, T, 2) inputs.
    vehicle : Vehicle
    Q : (3, 3) process covariance.
    R : (3, 3) shared or (G, 3, 3) per trajectory.
    spread : Merwe's alpha.
    progress : show a tqdm bar over the time steps.
    return_cov : also return the posterior covariances.
    smooth : the unscented RTS smoother's estimates instead (:mod:`lbo.filters.smoother`).

    Returns
    -------
    (G, T, 3) filtered (or smoothed) estimates, and (G, T, 3, 3) covariances with
    ``return_cov``.
    """
    m, u = _check_trajectories(m, u)
    flt = UnscentedStepper(m[:, 0], vehicle, Q, _batch_cov(R, m.shape[0], "R"), spread)
    return run_stepper(flt, m, u, return_cov, smooth=smooth,
                       progress="UKF" if progress else None, lengths=lengths)


# --------------------------------------------------------------------------- PCRB


def pcrb(z_true: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
         n_mc: int = 100, rng: np.random.Generator | int | None = None) -> np.ndarray:
    """Posterior Cramer-Rao bound on the filtering error variances of x, y and psi.

    Tichavsky's recursion for ``z_{k+1} = step(z_k, u_k) + w_k``, ``m_k = z_k + v_k``:

        J_0 = R^-1,   J_{k+1} = D22 - D12^T (J_k + D11)^-1 D12,
        D11 = E[F_k^T Q^-1 F_k],  D12 = -E[F_k]^T Q^-1,  D22 = Q^-1 + R^-1,

    with ``F_k`` the Jacobian of the step at ``z_k``. The bound is ``diag(J_k^-1)``.

    The expectations are over the states the model can reach: ``n_mc`` trajectories are
    simulated from each true ``z_0`` along the same inputs with fresh process noise
    (vectorised as (G, n_mc, 3)), and F is averaged over them at every step. The recursion
    is carried in covariance form, ``B = J^-1``:

        (J_k + D11)^-1 = B_k (I + D11 B_k)^-1,   A_k = Q^-1 - D12^T (J_k + D11)^-1 D12,
        B_{k+1} = (A_k + R^-1)^-1 = R (I + A_k R)^-1,

    so R is never inverted and a zero R (alpha=0) gives a bound of exactly 0.

    Parameters
    ----------
    z_true : (G, T, 3) true states; only ``z_true[:, 0]`` is used (it seeds the samples).
    u : (G, T, 2) inputs.
    vehicle : Vehicle
    Q : (3, 3) process covariance, positive definite.
    R : (3, 3) shared or (G, 3, 3) per trajectory; may be zero.
    n_mc : Monte-Carlo trajectories per true trajectory.
    rng : generator or seed for the process-noise samples.

    Returns
    -------
    (G, T, 3) lower bounds on the error variances (m^2, m^2, rad^2) at each step.
    """
    z_true, u = _check_trajectories(z_true, u)
    Q = _check_q(Q)
    if n_mc < 1:
        raise LboError(f"n_mc must be >= 1, got {n_mc}")
    try:
        chol_q = np.linalg.cholesky(Q)
    except np.linalg.LinAlgError:
        raise LboError("the PCRB needs a positive-definite process covariance Q") from None
    q_inv = np.linalg.inv(Q)
    rng = np.random.default_rng(rng)
    g, t = z_true.shape[:2]
    R = _batch_cov(R, g, "R")
    dt, wheelbase = vehicle.dt, vehicle.wheelbase

    z = np.repeat(z_true[:, None, 0], n_mc, axis=1)  # (G, n_mc, 3)
    B = np.array(R)
    bound = np.empty((g, t, 3))
    idx = np.arange(3)
    bound[:, 0] = B[:, idx, idx]
    for k in range(t - 1):
        uk = np.broadcast_to(u[:, None, k], (g, n_mc, 2))
        F = jacobian(z, uk, dt)  # (G, n_mc, 3, 3)
        d11 = np.einsum("gnji,jk,gnkl->gil", F, q_inv, F, optimize=True) / n_mc
        qf = q_inv @ F.mean(axis=1)  # -D12^T = Q^-1 E[F]
        # (J + D11)^-1 = B (I + D11 B)^-1 = ((I + B D11)^-1 B)^T, symmetric
        inv_jd = np.linalg.solve(_I3 + B @ d11, B)
        A = q_inv - qf @ inv_jd @ qf.swapaxes(-1, -2)
        B = np.linalg.solve(_I3 + R @ A, R)  # = (R (I + A R)^-1)^T
        B = 0.5 * (B + B.swapaxes(-1, -2))
        bound[:, k + 1] = B[:, idx, idx]
        z = step(z, uk, dt, wheelbase) + rng.standard_normal(z.shape) @ chol_q.T
    return np.maximum(bound, 0.0)
