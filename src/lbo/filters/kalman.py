"""The vectorised EKF of the kinematic bicycle, and its noise-adaptive (Sage-Husa) form.

:func:`ekf_batch` is the paper's EKF (:class:`lbo.filters.reference.BicycleEKF`) vectorised over
trajectories; ``R`` per trajectory gives the paper's EKF (alpha=1 R everywhere) and the oracle
(R at the true alpha) in one call. :func:`adaptive_ekf_batch` learns a diagonal R from its
innovations. Both loop over :class:`KalmanStepper` (:mod:`lbo.filters.stepper`), with the
conventions of :mod:`lbo.filters.start`.

A row of ``m`` holds any allowed subset of its channels, NaN in the others: a full fix, a
position fix without a heading (``psi_m`` NaN), or nothing (a prediction-only step). The
stepper builds H and R per step from what the row holds and updates through the one
Joseph-form :func:`lbo.filters.update.joseph_update`; a channel not held teaches the adaptive
R nothing.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters import measure
from lbo.filters.start import (
    COV_FLOOR,
    CourseStart,
    batch_cov,
    check_q,
    check_trajectories,
    start_state,
)
from lbo.filters.stepper import Posterior, run_stepper
from lbo.filters.update import held_channels, joseph_update
from lbo.sim.vehicle import Vehicle, jacobian, step


def _innovation(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``m - x`` (G, 3), heading wrapped; 0 in the channels m does not hold."""
    y = np.where(np.isfinite(m), m - x, 0.0)
    y[:, 2] = wrap_angle(y[:, 2])
    return y


class KalmanStepper:
    """The EKF of :func:`ekf_batch` one time step per call, over G trajectories:
    :meth:`predict`, then :meth:`correct`: take the row's R (:meth:`_noise`; the Sage-Husa
    EKF, :class:`AdaptiveStepper`, learns its own there), start the heading from the course
    where it is not known yet, update.

    :func:`ekf_batch` loops over it, and :class:`lbo.Observer` steps it one sample at a time,
    so streaming and batch give the same numbers.

    Parameters
    ----------
    m0 : (G, 3) first measurements (position fixes); the state starts there with P_0 = R
        (a NaN heading: see :func:`start_state` and :class:`CourseStart`).
    vehicle : Vehicle
    Q : (3, 3) process covariance.
    R : (G, 3, 3) measurement covariance.

    Attributes
    ----------
    x : (G, 3) current estimate. P : (G, 3, 3) its covariance. R : (G, 3, 3) current R.
    n_fix : (G, 3) measurements taken per channel, m0's included.
    prior : ``(x, P)`` (G, 3), (G, 3, 3), the prior the last posterior came from.
    cross : (G, 3, 3) ``cov(x_{k-1|k-1}, x_{k|k-1})`` of the last step, for smoothing.
    course : :class:`CourseStart`, the heading of trajectories that started without one.
    """

    def __init__(self, m0: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray
                 ) -> None:
        self.vehicle, self.Q = vehicle, Q
        self.R = np.array(R, dtype=float)
        m0 = measure.widen(m0)
        held = held_channels(m0[:, :3])
        self.x, self.P = start_state(m0, self.R)
        self.n_fix = held.astype(float)
        self.course = CourseStart(m0, vehicle, Q)

    def update(self, m: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """One step (the stepper contract, docs/plugins.md): :meth:`predict` with u_{k-1}
        (G, 2), then :meth:`correct` with what row m_k (G, 3) or (G, 8) holds
        (:mod:`lbo.filters.measure`); returns x_k (G, 3)."""
        self.predict(u_prev)
        return self.correct(m)

    def predict(self, u_prev: np.ndarray) -> np.ndarray:
        """The prior of the next step: x and P moved by the bicycle with u_{k-1} (G, 2) and
        its Jacobian, plus Q; kept in :attr:`prior` (with :attr:`cross`, for smoothing) for
        :meth:`correct`. Returns the predicted x (G, 3)."""
        F = jacobian(self.x, u_prev, self.vehicle.dt)
        x = step(self.x, u_prev, self.vehicle.dt, self.vehicle.wheelbase)
        self.course.advance(u_prev)
        self.cross = self.P @ F.swapaxes(-1, -2)  # cov(x_{k-1|k-1}, x_{k|k-1})
        self.prior = (x, F @ self.P @ F.swapaxes(-1, -2) + self.Q)
        return x

    def correct(self, m: np.ndarray) -> np.ndarray:
        """The posterior of the step :meth:`predict` made, from what row m (G, 3) or (G, 8)
        holds: the row's R (:meth:`_noise`), the heading started from the course where it
        is not known yet, then the Joseph update. A row's NaN channels are not measured (all
        of them: the prior is the posterior). Returns x_k (G, 3)."""
        m = measure.widen(m)
        held = held_channels(m[:, :3])
        x, P = self.prior
        P, R = self._noise(m, x, P, held)
        pos_var = 0.5 * (R[:, 0, 0] + R[:, 1, 1])
        m, R, P, start = self.course.take(m, pos_var, P, R)
        if start.any():
            self.cross = np.array(self.cross)
            self.cross[start, :, 2] = 0.0  # the flat heading prior owes nothing to the past
        self.prior = (x, P)  # the prior each posterior came from
        self.x, self.P, *_ = joseph_update(x, P, *measure.model(m, x, R))
        self.n_fix = self.n_fix + held
        return self.x

    def _noise(self, m: np.ndarray, x: np.ndarray, P: np.ndarray, held: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """The prior covariance (G, 3, 3) the update takes and the row's R (G, 3, 3), for
        rows m (G, 8) holding the channels ``held`` (G, 3) at the prior x (G, 3), P: the
        filter's R, with the accuracies the receiver reports (:func:`measure.step_cov`)."""
        return P, measure.step_cov(m, self.R)

    @property
    def coasts(self) -> bool:
        """Whether :meth:`coast` may stand for a run of prediction-only steps: trajectories
        that all know their heading (a blind one dead-reckons its course start step by
        step)."""
        return not self.course.blind.any()

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
        # the covariances: a_k = dstep/dpsi of step k
        a = np.stack([-v * np.sin(before) * dt, v * np.cos(before) * dt, np.zeros_like(v)], -1)
        P = coast_covariance(self.P, self.Q, a)
        self.x, self.P = poses[:, -1].copy(), P[:, -1].copy()
        return poses, P


def coast_covariance(P0, Q, a):
    """The covariances after each of n prediction-only steps whose Jacobians are
    ``I + a_k e3^T`` (the kinematic bicycle's: ``a_k`` is the step's derivative in the heading,
    with no heading component), in closed form (see :meth:`KalmanStepper.coast`).

    P0 : (G, 3, 3) the covariance before; Q : (3, 3) or (G, 3, 3) the process noise of
    every step; a : (G, n, 3). Returns (G, n, 3, 3), symmetric. NumPy arrays or torch
    tensors alike (the robust observer's coast, :mod:`lbo.models.recursive`, is the same sum).
    """
    S = a.cumsum(1)  # S_1 .. S_n, the running sums of a
    C1 = S.cumsum(1)
    SS = S[..., :, None] * S[..., None, :]
    C2 = SS.cumsum(1)
    count = (a[..., :1] * 0 + 1).cumsum(1)  # (G, n, 1): 1 .. n
    P0 = P0[:, None]
    Qg = (Q if Q.ndim == 3 else Q[None])[:, None]
    P = (P0 + S[..., :, None] * P0[..., 2:3, :] + P0[..., :, 2:3] * S[..., None, :]
         + P0[..., 2:3, 2:3] * SS)
    D = count * S - C1  # sum over m of S_n - S_m
    DD = (count[..., None] * SS - S[..., :, None] * C1[..., None, :]
          - C1[..., :, None] * S[..., None, :] + C2)
    P = (P + count[..., None] * Qg + D[..., :, None] * Qg[..., 2:3, :]
         + Qg[..., :, 2:3] * D[..., None, :] + Qg[..., 2:3, 2:3] * DD)
    return 0.5 * (P + P.swapaxes(-1, -2))


def compose_covariance(F, Q):
    """The covariance after each of K prediction steps ``P <- F_j P F_j^T + Q_j`` (F, Q
    (K, n, n)) as ``A_j P_0 A_j^T + B_j``: returns (A, B), each (K, n, n), the steps' maps
    composed by an inclusive scan (log2 K rounds of one batched product each, no loop over
    the steps), for Jacobians of any form (the gyro filter's coast,
    :mod:`lbo.models.recursive`). NumPy arrays or torch tensors alike."""
    A, B = F * 1, Q * 1  # copies
    shift = 1
    while shift < len(F):  # each entry takes in the one ``shift`` before it
        A_i = A[shift:]
        composed = A_i @ B[:-shift] @ A_i.swapaxes(-1, -2) + B[shift:]
        A[shift:] = A_i @ A[:-shift]
        B[shift:] = composed
        shift *= 2
    return A, B


def adaptive_settings(R0: np.ndarray, g: int, forgetting: float = 0.99,
                      prior_weight: float = 1.0, r_floor: float = 1e-4) -> dict:
    """Checked keyword arguments of a Sage-Husa :class:`KalmanStepper` (R0 (3,3) or (G,3,3))."""
    if not 0.0 < forgetting <= 1.0:
        raise LboError(f"forgetting must be in (0, 1], got {forgetting}")
    if prior_weight < 0 or r_floor < 0:
        raise LboError(f"prior_weight and r_floor must be >= 0, got {prior_weight}, {r_floor}")
    R0 = batch_cov(R0, g, "R0")
    idx = np.arange(3)
    return {"R": R0, "forgetting": forgetting, "prior_weight": prior_weight,
            "r_floor": np.maximum(r_floor * R0[:, idx, idx], COV_FLOOR)}


def _ekf_loop(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
              smooth: bool = False, lengths: np.ndarray | None = None,
              **adaptive: Any) -> Posterior:
    """Shared time loop of :func:`ekf_batch` and (with ``adaptive`` settings)
    :func:`adaptive_ekf_batch`."""
    m, u = check_trajectories(m, u)
    stepper = AdaptiveStepper if adaptive else KalmanStepper
    kf = stepper(m[:, 0], vehicle, check_q(Q), batch_cov(R, m.shape[0], "R"), **adaptive)
    return run_stepper(kf, m, u, smooth=smooth, lengths=lengths)


def ekf_batch(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
              smooth: bool = False, lengths: np.ndarray | None = None) -> Posterior:
    """The EKF of :class:`lbo.filters.reference.BicycleEKF`, vectorised over G trajectories
    (a loop over time only).

    Gives the filterpy loop's numbers to rounding (about 1e-12).

    Parameters
    ----------
    m : (G, T, 3) measurements ``[x_m, y_m, psi_m]``.
    u : (G, T, 2) inputs ``[V, delta]``.
    vehicle : Vehicle
    Q : (3, 3) process covariance.
    R : (3, 3) shared, or (G, 3, 3) per trajectory (e.g. ``noise.R(alpha_g)`` for the oracle).
    smooth : the RTS smoother's estimates and covariances instead (:mod:`lbo.filters.smoother`).
    lengths : (G,) real steps of padded trajectories, for the smoother (None: all).

    Returns
    -------
    Posterior
        ``mean`` (G, T, 3) the filtered estimates, ``mean[:, 0] = m[:, 0]`` (smoothed with
        ``smooth``), and ``cov`` (G, T, 3, 3) their covariances.
    """
    return _ekf_loop(m, u, vehicle, Q, R, smooth, lengths)


class AdaptiveStepper(KalmanStepper):
    """The Sage-Husa EKF of :func:`adaptive_ekf_batch` one step per call, built as every
    classical observer is (``(m0, vehicle, Q, R)``, docs/plugins.md): ``R`` is where it starts,
    and it learns a diagonal R from its innovations from then on (:meth:`_noise`).
    ``forgetting``, ``prior_weight``, ``r_floor`` as :func:`adaptive_settings` checks them
    (None: its defaults; r_floor (G, 3) the absolute floor on diag(R))."""

    def __init__(self, m0: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray, *,
                 forgetting: float | None = None, prior_weight: float = 0.0,
                 r_floor: np.ndarray | None = None) -> None:
        if forgetting is None or r_floor is None:  # built by name: the defaults
            settings = adaptive_settings(R, len(m0))
            R, forgetting, prior_weight, r_floor = (settings["R"], settings["forgetting"],
                                                     settings["prior_weight"],
                                                     settings["r_floor"])
        self.forgetting, self.r_floor = float(forgetting), r_floor
        m0 = measure.widen(m0).copy()
        # it learns R: the reported accuracies are not its to take
        measure.row_channels(m0).sigma[:] = np.nan
        diag = np.arange(3)
        R = np.array(R, dtype=float)
        self.r_hat = R[:, diag, diag].copy()  # (G, 3) diagonal of the learned R
        # innovations r_hat is worth, per channel (a position fix teaches psi nothing)
        self.weight = np.full(self.r_hat.shape, float(prior_weight))
        start = np.zeros_like(R)
        start[:, diag, diag] = self.r_hat
        super().__init__(m0, vehicle, Q, start)

    def _noise(self, m: np.ndarray, x: np.ndarray, P: np.ndarray, held: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """The Sage-Husa step: the prior's variances held at R / n while they settle, and R's
        diagonal a forgotten running mean of ``y^2 - diag(P_prior)`` over the held channels."""
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
        R = self.R.copy()
        R[:, diag, diag] = self.r_hat
        self.R = R
        return P, R

    @property
    def coasts(self) -> bool:
        """Never: it updates its R between fixes."""
        return False


def adaptive_ekf_batch(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray,
                       R0: np.ndarray, forgetting: float = 0.99, prior_weight: float = 1.0,
                       r_floor: float = 1e-4, smooth: bool = False,
                       lengths: np.ndarray | None = None) -> Posterior:
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

    Returns
    -------
    Posterior
        ``mean`` (G, T, 3) the filtered estimates and ``cov`` (G, T, 3, 3) their covariances.
    """
    settings = adaptive_settings(R0, np.shape(m)[0], forgetting, prior_weight, r_floor)
    return _ekf_loop(m, u, vehicle, Q, smooth=smooth, lengths=lengths,
                     **settings)
