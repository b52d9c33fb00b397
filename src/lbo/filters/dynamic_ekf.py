"""Extended Kalman filter on the true dynamic single-track car: the "dynamic oracle".

The classical filters of :mod:`lbo.filters.kalman` assume the kinematic bicycle; a log drawn from
the car that slips (:mod:`lbo.sim.dynamic`) breaks that model, and a learned observer may beat them
for that reason alone. This filter knows everything the data generator does: the car's parameters,
the sensor errors of :class:`lbo.sim.truth.Sensors` and the noise levels. Its error is the floor
that a learned observer is compared against.

The truth it is built for (``dt`` the vehicle's sampling period, ``car`` a
:class:`~lbo.sim.dynamic.SingleTrack` or any car that keeps :class:`lbo.sim.truth.Car`):

- ``s_{k+1} = car.step(s_k, u_true_k, dt) + [w_k, 0, 0]``, ``s = [x, y, psi, v_y, r]``
  (the rear axle's pose, the lateral speed of the centre of gravity, the yaw rate),
  ``w_k ~ N(0, Q)`` on the pose only;
- logged inputs ``V_log = (1 + speed_scale) V_true``, ``delta_log = delta_true +
  steering_offset``: the filter undoes both;
- measurements ``m_k = [x, y, psi]_k + v_k + [b_k, 0]``, ``v_k ~ N(0, R)`` white and ``b_k``
  (2,) a stationary first-order Gauss-Markov GNSS drift on x and y of standard deviation
  ``gnss_sigma`` and correlation time ``gnss_tau``:
  ``b_{k+1} = phi b_k + sqrt(1 - phi^2) gnss_sigma eps_k``, ``phi = exp(-dt / gnss_tau)``.

The state is ``[x, y, psi, v_y, r]``, plus ``[b_x, b_y]`` when any trajectory has drift (7
states; 5 without, which is cheaper). Conventions as :mod:`lbo.filters.start`: the estimate at step
``k`` uses ``m_0 .. m_k`` and ``u_0 .. u_{k-1}``; a row updates with the channels it holds
(a position without a heading: x and y only; a NaN row: a prediction-only step; a receiver's
row, :mod:`lbo.filters.measure`: its reported accuracy as that step's R, and its course over
ground as the heading plus the rear side slip, which this model knows) through the shared
Joseph-form :func:`lbo.filters.update.joseph_update`; heading innovations are wrapped to
(-pi, pi] while the estimated heading stays continuous; NumPy, vectorised over G trajectories
with a Python loop over time only. It starts at a full fix (a heading included).

The Jacobian of the RK4 step is taken by central differences in psi, v_y and r, all
perturbations stacked into one call of ``car.step`` on (G, 7, 5) states. The step
does not depend on x and y (their columns are the identity), so it is evaluated at the origin
and the pose added back: exact, and free of round-off at large coordinates.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.core.checks import number
from lbo.core.errors import LboError
from lbo.filters import measure
from lbo.filters.start import COV_FLOOR, batch_cov, check_q, check_trajectories
from lbo.filters.stepper import Posterior, run_stepper
from lbo.filters.update import held_channels, joseph_update
from lbo.sim.truth import Car
from lbo.sim.vehicle import Vehicle

P0_LATERAL_SIGMA = (0.5, 0.2)
"""Standard deviations of the starting v_y (m/s) and r (rad/s) about their steady state: wide
enough for a car that does not start in the linear-tyre steady state (0.2 rad/s is the yaw rate
of a 6 m/s^2 turn at 30 m/s); the lateral dynamics forget them within about 0.3 s at speed."""

Q_LATERAL_SIGMA = (1e-3, 1e-3)
"""Process noise on v_y (m/s) and r (rad/s) per step. The truth has none; a little keeps P well
conditioned. The lateral dynamics decay by about a fifth per step at 10 m/s, so it adds about
2e-3 m/s and 2e-3 rad/s of standard deviation: small beside what the pose noise makes them
(a heading error of 1 mrad a step is 50 mrad/s of apparent yaw rate)."""

FD_STEP = 1e-5
"""Central-difference step in psi (rad), v_y (m/s) and r (rad/s). The step's truncation error
is about h^2 = 1e-10 of its curvature, the round-off about 1e-16 * 0.5 m / h = 5e-12."""

_PERTURBED = (2, 3, 4)  # psi, v_y, r: the columns of the Jacobian taken by differences


def _sigma_vector(value, g: int, name: str) -> np.ndarray:
    """``value`` (scalar or (G,)) as a finite, >= 0 (G,) float array, or LboError naming it."""
    arr = np.asarray(value, dtype=float)
    if arr.shape not in ((), (g,)):
        raise LboError(f"{name} must be a float or ({g},) per trajectory, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise LboError(f"{name} must be finite and >= 0 (m), got {value!r}")
    return np.broadcast_to(arr, (g,)).copy()


def _check_inputs(u: np.ndarray, g: int, name: str) -> np.ndarray:
    u = np.asarray(u, dtype=float)
    if u.shape != (g, 2):
        raise LboError(f"{name} must be ({g}, 2) [V, delta], got {u.shape}")
    return u


class DynamicStepper:
    """EKF on the dynamic single-track car, one time step per call over G trajectories.

    The stepper contract (:mod:`lbo.filters.stepper`): :func:`dynamic_ekf_batch` loops over
    it, and a streaming observer can step it one sample at a time.

    Parameters
    ----------
    m0 : (G, 3) first measurements (fixes) ``[x_m, y_m, psi_m]``, or (G, 8) rows with a
        receiver's channels (:mod:`lbo.filters.measure`); the pose starts there (P at the
        accuracy the row reports, if any).
    vehicle : Vehicle
        Supplies ``dt``; its wheelbase must be the car's ``l_f + l_r``.
    car : the true car (:class:`lbo.sim.truth.Car`)
        The true car's parameters.
    Q : (3, 3) process covariance of x, y, psi (added after each step).
    R : (G, 3, 3) white measurement covariance at each trajectory's alpha.
    gnss_sigma : float or (G,) standard deviation (m) of the GNSS drift on x and y, already
        multiplied by alpha; 0 everywhere: no drift states.
    gnss_tau : correlation time (s) of the drift.
    steering_offset : what the logged steering angle reads above the road-wheel angle (rad).
    speed_scale : relative error of the logged speed (0.02: V reads 2 % high); > -1.
    lateral_sigma : (2,) standard deviations of the disturbances of v_y (m/s) and r (rad/s)
        per step, added to the process noise the filter keeps on them.
    u0 : (G, 2) logged inputs at step 0, or None. Given, v_y and r start in the steady state
        (``car.start``) of the true inputs they stand for; else at 0.

    The start: pose ``m0``, drift 0, and the covariance of that guess's error given only
    ``m_0`` (a flat prior on the pose, the stationary one on the drift):

        P_0 = [[R + S, 0, -S], [0, diag(P0_LATERAL_SIGMA)^2, 0], [-S, 0, S]],

    ``S = gnss_sigma^2`` on x and y (zero-padded to 3 x 3 where it meets R), diagonal floored
    at :data:`~lbo.filters.start.COV_FLOOR`. (The pose error is ``-(v_0 + b_0)``: it carries the
    first drift, hence ``R + S`` and the cross-covariance ``-S``; without drift, ``P_0 = R`` on
    the pose as in :mod:`lbo.filters.kalman`.)

    Attributes
    ----------
    x : (G, n) state estimate, n = 5 ``[x, y, psi, v_y, r]`` or 7 with ``[b_x, b_y]``; psi
        continuous.
    P : (G, n, n) its covariance.
    F : (G, n, n) Jacobian of the last prediction, at the state it started from (None before).
    Q : (G, n, n) process covariance of the full state.
    R : (G, 3, 3) white measurement covariance.
    H : (3, n) measurement matrix (pose plus drift).
    dim_x : n.
    phi : (G,) drift correlation per step, ``exp(-dt / gnss_tau)``.
    """

    def __init__(self, m0: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray, *,
                 car: Car, gnss_sigma: np.ndarray | float = 0.0, gnss_tau: float = 30.0,
                 steering_offset: float = 0.0, speed_scale: float = 0.0,
                 lateral_sigma: tuple[float, float] = (0.0, 0.0),
                 u0: np.ndarray | None = None) -> None:
        if not isinstance(vehicle, Vehicle):
            raise LboError(f"vehicle must be a lbo.sim.vehicle.Vehicle, got "
                           f"{type(vehicle).__name__}")
        if not isinstance(car, Car):
            raise LboError(f"car must be a car that keeps lbo.sim.truth.Car (a SingleTrack, or "
                           f"a registered truth model's), got {type(car).__name__}")
        if abs(car.wheelbase - vehicle.wheelbase) > 1e-6:
            field = "car.l_f + car.l_r" if hasattr(car, "l_f") else "car.wheelbase"
            raise LboError(f"{field} must be the vehicle's wheelbase ({vehicle.wheelbase} m), "
                           f"got {car.wheelbase!r}")
        m0 = np.array(m0, dtype=float)
        if m0.ndim != 2 or m0.shape[1] not in (3, measure.WIDTH):
            raise LboError(f"m0 must be (G, 3) [x_m, y_m, psi_m] or (G, {measure.WIDTH}) "
                           f"rows ({', '.join(measure.CHANNELS)}), got {m0.shape}")
        m0 = measure.widen(m0)
        if not np.isfinite(m0[:, :3]).all():
            raise LboError("m0 must be a full fix (x_m, y_m and psi_m finite) for every "
                           "trajectory; the dynamic oracle starts there, heading included")
        g = len(m0)
        Q3 = check_q(Q)
        R = np.asarray(R, dtype=float)
        if R.shape != (g, 3, 3):
            raise LboError(f"R must be ({g}, 3, 3), got {R.shape}")
        sigma = _sigma_vector(gnss_sigma, g, "gnss_sigma")
        self.gnss_tau = number(gnss_tau, "gnss_tau", low=0.0, low_open=True,
                               form="a time in s > 0")
        self.steering_offset = number(steering_offset, "steering_offset",
                                      form="a finite angle in rad")
        self.speed_scale = number(speed_scale, "speed_scale", low=-1.0, low_open=True)
        self.vehicle, self.car = vehicle, car
        self.gnss_sigma = sigma
        drift = bool(np.any(sigma > 0))
        n = 7 if drift else 5
        self.dim_x = n
        self.R = R

        self.H = np.zeros((3, n))
        self.H[:, :3] = np.eye(3)
        if drift:
            self.H[0, 5] = self.H[1, 6] = 1.0

        self.phi = np.full(g, np.exp(-vehicle.dt / self.gnss_tau))
        self.Q = np.zeros((g, n, n))
        self.Q[:, :3, :3] = Q3
        # the disturbances the car's lateral states carry, where it is told them, beside the
        # little that keeps P well conditioned
        told = np.square(np.asarray(lateral_sigma, dtype=float))
        self.Q[:, 3, 3], self.Q[:, 4, 4] = np.square(Q_LATERAL_SIGMA) + told
        var_b = sigma**2
        if drift:
            self.Q[:, 5, 5] = self.Q[:, 6, 6] = (1.0 - self.phi**2) * var_b

        self.x = np.zeros((g, n))
        self.x[:, :3] = m0[:, :3]
        if u0 is not None:
            ut = self.true_inputs(_check_inputs(u0, g, "u0"))
            self.x[:, 3:5] = car.start(self.x[:, :3], ut)[:, 3:5]
        P = np.zeros((g, n, n))
        P[:, :3, :3] = measure.step_cov(m0, R)
        P[:, 3, 3], P[:, 4, 4] = np.square(P0_LATERAL_SIGMA)
        if drift:
            for i in (0, 1):
                P[:, i, i] += var_b
                P[:, i, 5 + i] = P[:, 5 + i, i] = -var_b
                P[:, 5 + i, 5 + i] = var_b
        idx = np.arange(n)
        P[:, idx, idx] = np.maximum(P[:, idx, idx], COV_FLOOR)
        self.P = P
        self.F: np.ndarray | None = None

    def true_inputs(self, u: np.ndarray) -> np.ndarray:
        """The true inputs (G, 2) behind logged ones (G, 2): the sensor errors undone."""
        if self.speed_scale == 0 and self.steering_offset == 0:
            return u
        return np.stack([u[:, 0] / (1.0 + self.speed_scale), u[:, 1] - self.steering_offset],
                        axis=-1)

    def predict(self, u_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Prior ``(x, P)`` of the next step, (G, n) and (G, n, n), for logged inputs u_prev
        (G, 2); sets :attr:`F`. Does not change :attr:`x` or :attr:`P`."""
        g, n = self.x.shape
        ut = self.true_inputs(_check_inputs(u_prev, g, "u_prev"))
        # nominal and +-h in psi, v_y, r, at the origin (the step does not depend on x, y)
        s = np.zeros((g, 1 + 2 * len(_PERTURBED), 5))
        s[:, :, 2:] = self.x[:, None, 2:5]
        for j, col in enumerate(_PERTURBED):
            s[:, 1 + 2 * j, col] += FD_STEP
            s[:, 2 + 2 * j, col] -= FD_STEP
        out = self.car.step(s, np.broadcast_to(ut[:, None], s.shape[:2] + (2,)),
                            self.vehicle.dt)
        F = np.zeros((g, n, n))
        F[:, 0, 0] = F[:, 1, 1] = 1.0
        for j, col in enumerate(_PERTURBED):
            F[:, :5, col] = (out[:, 1 + 2 * j] - out[:, 2 + 2 * j]) / (2.0 * FD_STEP)
        x = np.empty_like(self.x)
        x[:, :5] = out[:, 0]
        x[:, :2] += self.x[:, :2]
        if n == 7:
            F[:, 5, 5] = F[:, 6, 6] = self.phi
            x[:, 5:] = self.phi[:, None] * self.x[:, 5:]
        self.F = F
        P = F @ self.P @ F.swapaxes(-1, -2) + self.Q
        return x, 0.5 * (P + P.swapaxes(-1, -2))

    def update(self, m: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Predict with the logged u_{k-1} (G, 2), update with the channels row m_k holds
        ((G, 3), or (G, 8) with a receiver's channels, :mod:`lbo.filters.measure`; NaN: not
        measured; a row of NaN gets the prediction only); returns the pose estimate x_k (G, 3).

        A reported accuracy is the step's R of its channel. The course over ground is the
        direction the rear axle moves in: the heading plus the rear side slip
        (:func:`lbo.sim.dynamic.rear_slip` of the state's v_y and r, at the true speed of
        u_{k-1}), which this model knows and the kinematic filters take as noise."""
        g = len(self.x)
        m = np.asarray(m, dtype=float)
        if m.shape not in ((g, 3), (g, measure.WIDTH)):
            raise LboError(f"m must be ({g}, 3) [x_m, y_m, psi_m] or ({g}, {measure.WIDTH}) "
                           f"rows ({', '.join(measure.CHANNELS)}), got {m.shape}")
        m = measure.widen(m)
        x, P = self.predict(u_prev)
        R = measure.step_cov(m, self.R)
        if not np.isfinite(measure.row_channels(m).course).any():  # the pose's channels alone
            held = held_channels(m[:, :3])
            y = np.where(held, m[:, :3] - x @ self.H.T, 0.0)
            y[:, 2] = wrap_angle(y[:, 2])
            self.x, self.P, *_ = joseph_update(x, P, y, self.H, R, held)
            return self.x[:, :3]
        n = x.shape[1]
        slip, jac = self._course(x, self.true_inputs(_check_inputs(u_prev, g, "u_prev")))
        meas, held, R4 = measure.measured(m, R)
        y = measure.innovation(meas, np.concatenate([x @ self.H.T, (x[:, 2] + slip)[:, None]],
                                                    axis=1), held)
        H = np.zeros((g, measure.MEASURED, n))
        H[:, :3] = self.H
        H[:, 3, 2:5] = jac  # the course: the heading plus the rear axle's slip
        self.x, self.P, *_ = joseph_update(x, P, y, H, R4, held)
        return self.x[:, :3]

    def _course(self, x: np.ndarray, ut: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rear side slip (G,) at states x (G, n) and true inputs ut (G, 2), and the
        course's Jacobian (G, 3) on psi, v_y and r (the slip's by central differences)."""
        g = len(x)
        s = np.repeat(x[:, None, :5], 5, axis=1)  # nominal, +-h in v_y, +-h in r
        s[:, 1, 3] += FD_STEP
        s[:, 2, 3] -= FD_STEP
        s[:, 3, 4] += FD_STEP
        s[:, 4, 4] -= FD_STEP
        slip = self.car.rear_slip(s, np.broadcast_to(ut[:, None], (g, 5, 2)))
        jac = np.ones((g, 3))
        jac[:, 1] = (slip[:, 1] - slip[:, 2]) / (2.0 * FD_STEP)
        jac[:, 2] = (slip[:, 3] - slip[:, 4]) / (2.0 * FD_STEP)
        return slip[:, 0], jac

    @property
    def pose_cov(self) -> np.ndarray:
        """(G, 3, 3) covariance of the pose estimate ``x[:, :3]``."""
        return self.P[:, :3, :3]


class Lateral(NamedTuple):
    """The lateral states the dynamic oracle carries beside the pose, each row's estimate and
    covariance: what no sensor of the car measures."""

    mean: np.ndarray
    """(G, T, 2) ``[v_y, r]``: the lateral speed of the centre of gravity (m/s) and the yaw
    rate (rad/s)."""
    cov: np.ndarray
    """(G, T, 2, 2) their covariance (the filter's P)."""

    def beta(self, vx: np.ndarray) -> np.ndarray:
        """(G, T) side slip at the centre of gravity (rad), ``atan2(v_y, vx)``, at the
        speeds vx (G, T) (the true ones: :meth:`DynamicStepper.true_inputs`)."""
        return np.arctan2(self.mean[..., 0], vx)

    def beta_var(self, vx: np.ndarray) -> np.ndarray:
        """(G, T) the variance of :meth:`beta` (rad^2), v_y's carried through the angle to
        first order: ``var(v_y) (vx / (vx^2 + v_y^2))^2``."""
        return self.cov[..., 0, 0] * (vx / (vx**2 + self.mean[..., 0] ** 2)) ** 2


def dynamic_ekf_lateral(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, car: Car, Q: np.ndarray,
                        R: np.ndarray, gnss_sigma: np.ndarray | float = 0.0,
                        gnss_tau: float = 30.0, steering_offset: float = 0.0,
                        speed_scale: float = 0.0,
                        lateral_sigma: tuple[float, float] = (0.0, 0.0)
                        ) -> tuple[Posterior, Lateral]:
    """The dynamic oracle of :func:`dynamic_ekf_batch` (the same arguments, the same run) with
    what it carries beside the pose: the pose's :class:`~lbo.filters.stepper.Posterior` and
    the :class:`Lateral` states, v_y and r, with their covariances, each (G, T, ...). The
    lateral states start at the steady state of the first inputs (``car.start``)."""
    kf, m, u = _stepper(m, u, vehicle, car, Q, R, gnss_sigma, gnss_tau, steering_offset,
                        speed_scale, lateral_sigma)
    g, t = m.shape[:2]
    mean, cov = np.empty((g, t, 2)), np.empty((g, t, 2, 2))

    def record(kf: DynamicStepper, k: int | slice) -> None:
        mean[:, k], cov[:, k] = kf.x[:, 3:5], kf.P[:, 3:5, 3:5]

    pose = run_stepper(kf, m, u, pose=lambda kf: kf.x[:, :3], cov=lambda kf: kf.pose_cov,
                       record=record)
    return pose, Lateral(mean, cov)


def _stepper(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, car: Car, Q: np.ndarray,
             R: np.ndarray, gnss_sigma: np.ndarray | float, gnss_tau: float,
             steering_offset: float, speed_scale: float, lateral_sigma: tuple[float, float]
             ) -> tuple[DynamicStepper, np.ndarray, np.ndarray]:
    """The checked m (G, T, 3), u (G, T, 2) and the stepper started at their first row."""
    m, u = check_trajectories(m, u)
    g, t = m.shape[:2]
    if t == 0:
        raise LboError("measurements m must have at least one step, got T = 0")
    kf = DynamicStepper(m[:, 0], vehicle, Q, np.array(batch_cov(R, g, "R")), car=car,
                        gnss_sigma=gnss_sigma, gnss_tau=gnss_tau,
                        steering_offset=steering_offset, speed_scale=speed_scale,
                        lateral_sigma=lateral_sigma, u0=u[:, 0])
    return kf, m, u


def dynamic_ekf_batch(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, car: Car,
                      Q: np.ndarray, R: np.ndarray, gnss_sigma: np.ndarray | float = 0.0,
                      gnss_tau: float = 30.0, steering_offset: float = 0.0,
                      speed_scale: float = 0.0,
                      lateral_sigma: tuple[float, float] = (0.0, 0.0)) -> Posterior:
    """The dynamic oracle: :class:`DynamicStepper` over G trajectories (loop over time only).

    Parameters
    ----------
    m : (G, T, 3) measurements ``[x_m, y_m, psi_m]``; a NaN row is a missing fix; the first
        row of every trajectory must be a fix.
    u : (G, T, 2) logged inputs ``[V, delta]``; ``u[:, k]`` moves step k to k + 1.
    vehicle : Vehicle (``dt``).
    car : the true car (:class:`lbo.sim.truth.Car`: a SingleTrack, or a registered one).
    Q : (3, 3) process covariance of x, y, psi.
    R : (3, 3) shared, or (G, 3, 3) per trajectory: the white measurement covariance at alpha.
    gnss_sigma : float or (G,) GNSS drift standard deviation (m), already times alpha.
    gnss_tau : drift correlation time (s).
    steering_offset, speed_scale : the logged inputs' errors, undone by the filter.
    lateral_sigma : (2,) the disturbances of the car's v_y (m/s) and r (rad/s) per step,
        added to the filter's process noise on them.

    Returns
    -------
    Posterior
        ``mean`` (G, T, 3) the filtered pose estimates, ``mean[:, 0] = m[:, 0]``, and
        ``cov`` (G, T, 3, 3) their covariances.
    """
    kf, m, u = _stepper(m, u, vehicle, car, Q, R, gnss_sigma, gnss_tau, steering_offset,
                        speed_scale, lateral_sigma)
    return run_stepper(kf, m, u, pose=lambda kf: kf.x[:, :3], cov=lambda kf: kf.pose_cov)
