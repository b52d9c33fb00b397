"""The posterior Cramer-Rao bound: the error variances no filter of the kinematic bicycle can
beat (Tichavsky et al. 1998)."""

from __future__ import annotations

import numpy as np

from lbo.core.errors import LboError
from lbo.filters.start import batch_cov, check_q, check_trajectories
from lbo.sim.vehicle import Vehicle, jacobian, step

_I3 = np.eye(3)


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
    z_true, u = check_trajectories(z_true, u)
    Q = check_q(Q)
    if n_mc < 1:
        raise LboError(f"n_mc must be >= 1, got {n_mc}")
    try:
        chol_q = np.linalg.cholesky(Q)
    except np.linalg.LinAlgError:
        raise LboError("the PCRB needs a positive-definite process covariance Q") from None
    q_inv = np.linalg.inv(Q)
    rng = np.random.default_rng(rng)
    g, t = z_true.shape[:2]
    R = batch_cov(R, g, "R")
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
