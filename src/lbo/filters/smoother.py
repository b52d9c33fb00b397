"""Rauch-Tung-Striebel smoothing: the best estimate of an offline log, from a filter's pass.

A filter's estimate at step k uses the samples up to k. Once the whole log is in, every
estimate can also use the samples after it: the RTS smoother runs backwards over what the
filter recorded at each step,

    J_k = C_{k+1} P_{k+1|k}^-1,
    x_{k|T} = x_{k|k} + J_k (x_{k+1|T} - x_{k+1|k}),
    P_{k|T} = P_{k|k} + J_k (P_{k+1|T} - P_{k+1|k}) J_k^T,

with ``C_{k+1} = cov(x_{k|k}, x_{k+1|k})`` the cross-covariance of the prediction: ``P_{k|k}
F_k^T`` for an extended Kalman filter, the sigma points' for an unscented one (the URTS of
Sarkka, 2008). Headings are differenced with wrap-around. Vectorised over G trajectories, a
Python loop over time only.
"""

from __future__ import annotations

import numpy as np

from lbo.core.angles import wrap_angle


def rts(x_f: np.ndarray, P_f: np.ndarray, x_p: np.ndarray, P_p: np.ndarray,
        cross: np.ndarray, angles: tuple[int, ...] = (2,),
        lengths: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Smooth G filtered trajectories of T steps and n states.

    Parameters
    ----------
    x_f, P_f : (G, T, n), (G, T, n, n) the filter's posteriors ``x_{k|k}``, ``P_{k|k}``.
    x_p, P_p : (G, T, n), (G, T, n, n) its priors ``x_{k|k-1}``, ``P_{k|k-1}`` (step 0 unused).
    cross : (G, T, n, n) ``C_k = cov(x_{k-1|k-1}, x_{k|k-1})`` (step 0 unused).
    angles : the state indices that are angles (differences wrapped to (-pi, pi]).
    lengths : (G,) real steps of each trajectory, the rest padding that must not flow back
        into them (None: all T are real).

    Returns
    -------
    x_s (G, T, n), P_s (G, T, n, n): the smoothed estimates and covariances; each
    trajectory's last real step's are the filter's (and so is the padding after it).
    """
    x_s, P_s = x_f.copy(), P_f.copy()
    idx = list(angles)
    t = x_f.shape[1]
    ends = np.full(len(x_f), t) if lengths is None else np.asarray(lengths)
    for k in range(t - 2, -1, -1):
        # J = C P_p^-1, from the solve of P_p J^T = C^T (P_p symmetric); none from padding
        J = np.linalg.solve(P_p[:, k + 1], cross[:, k + 1].swapaxes(-1, -2)).swapaxes(-1, -2)
        J = np.where((k + 1 < ends)[:, None, None], J, 0.0)
        d = x_s[:, k + 1] - x_p[:, k + 1]
        d[:, idx] = wrap_angle(d[:, idx])
        x_s[:, k] = x_f[:, k] + np.einsum("gij,gj->gi", J, d)
        P = P_f[:, k] + J @ (P_s[:, k + 1] - P_p[:, k + 1]) @ J.swapaxes(-1, -2)
        P_s[:, k] = 0.5 * (P + P.swapaxes(-1, -2))
    x_s[..., idx] = wrap_angle(x_s[..., idx])
    return x_s, P_s
