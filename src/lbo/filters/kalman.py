"""Model-based observers for the kinematic bicycle and the bound they cannot beat.

Conventions, shared by every function here: a batch of ``G`` trajectories of ``T`` steps,
measurements ``m`` of shape (G, T, 3) = ``[x_m, y_m, psi_m]`` and inputs ``u`` of shape
(G, T, 2) = ``[V, delta]``, where ``u[:, k]`` moves ``z_k`` to ``z_{k+1}``. The estimate at
step ``k`` uses ``m_0 .. m_k`` and ``u_0 .. u_{k-1}``. Every filter starts from
``z_0 = m_0`` and ``P_0 = R`` (diagonal floored at :data:`COV_FLOOR`), measures the state
directly (H = I) and wraps heading innovations to (-pi, pi]. Estimated headings stay on the
branch of the measurements (continuous, not wrapped); metrics wrap the error.

A missing position fix is a row of ``m`` that is NaN in all three channels: the batched
filters and their steppers do a prediction-only step there (no update, R not learned). The
first row of every trajectory must be a fix, as the filters start there.

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
from lbo.sim.logcheck import fix_mask
from lbo.sim.vehicle import Vehicle, jacobian, step, wrap_angle

COV_FLOOR = 1e-9
"""Smallest variance put on the diagonal of P_0 (and of the UKF's R), so alpha=0 runs."""

_I3 = np.eye(3)


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


def _check_trajectories(m: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    m = np.asarray(m, dtype=float)
    u = np.asarray(u, dtype=float)
    if m.ndim != 3 or m.shape[-1] != 3:
        raise LboError(f"measurements m must be (G, T, 3) [x_m, y_m, psi_m], got {m.shape}")
    if u.shape != m.shape[:2] + (2,):
        raise LboError(f"inputs u must be (G, T, 2) [V, delta] matching m {m.shape}, got {u.shape}")
    if m.shape[1] and not np.isfinite(m[:, 0]).all():
        g = int(np.flatnonzero(~np.isfinite(m[:, 0]).all(-1))[0])
        raise LboError(f"trajectory {g} has no fix at its first step; the filters start at a fix")
    return m, u


def _where_fix(fix: np.ndarray, updated: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """Rows of ``updated`` where ``fix`` (G,), else the prior's: a prediction-only step."""
    return np.where(fix.reshape(fix.shape + (1,) * (updated.ndim - 1)), updated, prior)


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
    m, u = _check_trajectories(np.asarray(m)[None], np.asarray(u)[None])
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
    m0 : (G, 3) first measurements (fixes); the state starts there with P_0 = R.
    vehicle : Vehicle
    Q : (3, 3) process covariance.
    R : (G, 3, 3) measurement covariance (the starting one when adaptive).
    forgetting, prior_weight, r_floor : Sage-Husa settings (see :func:`adaptive_ekf_batch`);
        ``forgetting=None`` is the plain EKF. r_floor: (G, 3) absolute floor on diag(R).

    Attributes
    ----------
    x : (G, 3) current estimate. P : (G, 3, 3) its covariance. R : (G, 3, 3) current R.
    n_fix : (G,) fixes taken, m0 included.
    """

    def __init__(self, m0: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
                 forgetting: float | None = None, prior_weight: float = 0.0,
                 r_floor: np.ndarray | None = None) -> None:
        self.vehicle, self.Q = vehicle, Q
        self.forgetting, self.r_floor = forgetting, r_floor
        self.R = np.array(R, dtype=float)
        if forgetting is not None:
            diag = np.arange(3)
            self.r_hat = self.R[:, diag, diag].copy()          # (G, 3) diagonal of the learned R
            self.weight = np.full(len(m0), float(prior_weight))  # innovations r_hat is worth
            self.R = np.zeros_like(self.R)
            self.R[:, diag, diag] = self.r_hat
        self.x = np.array(m0, dtype=float)
        self.P = _floor_diag(self.R)
        self.n_fix = np.ones(len(self.x))

    def update(self, m: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Predict with u_{k-1} (G, 2), update with m_k (G, 3); returns x_k (G, 3).

        Rows of m that are NaN (no fix) get the prediction only."""
        fix = fix_mask(m)
        F = jacobian(self.x, u_prev, self.vehicle.dt)
        x = step(self.x, u_prev, self.vehicle.dt, self.vehicle.wheelbase)
        self.cross = self.P @ F.swapaxes(-1, -2)  # cov(x_{k-1|k-1}, x_{k|k-1}), for smoothing
        P = F @ self.P @ F.swapaxes(-1, -2) + self.Q
        y = np.where(fix[:, None], m - x, 0.0)
        y[:, 2] = wrap_angle(y[:, 2])
        R = self.R
        P_prior = P
        if self.forgetting is not None:
            diag = np.arange(3)
            # P_0 = R0 is wrong by the unknown alpha^2; n fixes of noise R cannot give a
            # prior error below R / n, so hold P there until it settles.
            P = P.copy()
            P[:, diag, diag] = np.maximum(P[:, diag, diag], self.r_hat / self.n_fix[:, None])
            # Sage-Husa: E[y y^T] = P_prior + R, so y^2 - diag(P_prior) is one sample of R;
            # exponentially forgotten running mean, weights 1 / (b W + 1); fixes only.
            self.weight = np.where(fix, self.forgetting * self.weight + 1.0, self.weight)
            d = np.where(fix, 1.0 / self.weight, 0.0)[:, None]
            self.r_hat = np.maximum((1.0 - d) * self.r_hat + d * (y**2 - P[:, diag, diag]),
                                    self.r_floor)
            R[:, diag, diag] = self.r_hat
        # K = P S^-1 = (S^-1 P)^T for symmetric P, S
        K = np.linalg.solve(P + R, P).swapaxes(-1, -2)
        I_K = _I3 - K
        # Joseph form, as filterpy: stays symmetric PSD and matches the reference
        posterior = I_K @ P @ I_K.swapaxes(-1, -2) + K @ R @ K.swapaxes(-1, -2)
        self.x = _where_fix(fix, x + np.einsum("gij,gj->gi", K, y), x)
        self.P = _where_fix(fix, posterior, P_prior)
        self.prior = (x, _where_fix(fix, P, P_prior))  # the prior each posterior came from
        self.n_fix = self.n_fix + fix
        return self.x


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
    est = np.empty_like(m)
    est[:, 0] = pose(kf)
    covs = np.empty((g, t, 3, 3)) if return_cov or smooth else None
    if covs is not None:
        covs[:, 0] = cov(kf)
    if smooth:
        x_p, P_p, cross = np.zeros_like(est), np.zeros_like(covs), np.zeros_like(covs)
    steps = tqdm(range(1, t), desc=progress, unit="step", disable=progress is None,
                 mininterval=2.0)
    for k in steps:
        kf.update(m[:, k], u[:, k - 1])
        est[:, k] = pose(kf)
        if covs is not None:
            covs[:, k] = cov(kf)
        if smooth:
            x_p[:, k], P_p[:, k] = kf.prior
            cross[:, k] = kf.cross
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
        spread: float = 0.1) -> np.ndarray:
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
    m, u = _check_trajectories(np.asarray(m)[None], np.asarray(u)[None])
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
                       R: np.ndarray, spread: float = 0.1, progress: bool = False) -> np.ndarray:
    """:func:`ukf` over G trajectories, one after the other: filterpy's loop, the reference
    that :func:`ukf_batch` is tested and benchmarked against.

    Shapes as :func:`ukf_batch`; ``progress`` shows a tqdm bar.
    """
    m, u = _check_trajectories(m, u)
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
    weights, circular means, redrawn prior sigma points and covariance update as filterpy's
    :class:`~filterpy.kalman.UnscentedKalmanFilter`. :func:`ukf_batch` loops over it and
    :class:`lbo.Observer` steps it one sample at a time, so streaming and batch agree.

    Parameters
    ----------
    m0 : (G, 3) first measurements; the state starts there with P_0 = R.
    vehicle : Vehicle
    Q : (3, 3) process covariance.
    R : (G, 3, 3) measurement covariance (diagonal floored at :data:`COV_FLOOR`).
    spread : Merwe's alpha.

    Attributes
    ----------
    x : (G, 3) current estimate. P : (G, 3, 3) its covariance.
    """

    def __init__(self, m0: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
                 spread: float = 0.1) -> None:
        self.vehicle, self.Q = vehicle, _check_q(Q)
        self.R = _floor_diag(R)
        self.wm, self.wc, self.lam = merwe_weights(3, spread)
        self.x = np.array(m0, dtype=float)
        self.P = self.R.copy()

    def update(self, m: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Predict with u_{k-1} (G, 2), update with m_k (G, 3) where it is a fix (not NaN);
        returns x_k (G, 3)."""
        wm, wc, lam = self.wm, self.wc, self.lam
        # predict: sigma points through the bicycle step, unscented transform plus Q
        before = _sigma_points(self.x, self.P, lam)
        sig = step(before, np.broadcast_to(u_prev[:, None], before.shape[:2] + (2,)),
                   self.vehicle.dt, self.vehicle.wheelbase)
        x = _batch_mean(sig, wm)
        d = _deviations(sig, x)
        P = np.einsum("s,gsi,gsj->gij", wc, d, d) + self.Q
        # cov(x_{k-1|k-1}, x_{k|k-1}) from the sigma points, for the URTS smoother
        self.cross = np.einsum("s,gsi,gsj->gij", wc, _deviations(before, self.x), d)
        # update (h = identity) on sigma points redrawn from the prior, as filterpy does
        sig = _sigma_points(x, P, lam)
        zp = _batch_mean(sig, wm)
        dz = _deviations(sig, zp)
        S = np.einsum("s,gsi,gsj->gij", wc, dz, dz) + self.R
        Pxz = np.einsum("s,gsi,gsj->gij", wc, _deviations(sig, x), dz)
        K = Pxz @ np.linalg.inv(S)
        fix = fix_mask(m)
        y = np.where(fix[:, None], m - zp, 0.0)
        y[:, 2] = wrap_angle(y[:, 2])
        self.x = _where_fix(fix, x + np.einsum("gij,gj->gi", K, y), x)
        self.P = _where_fix(fix, P - K @ S @ K.swapaxes(-1, -2), P)
        self.prior = (x, P)
        return self.x


def ukf_batch(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
              spread: float = 0.1, progress: bool = False, return_cov: bool = False,
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
