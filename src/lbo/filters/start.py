"""How every classical filter starts, and the arrays it takes, checked.

Conventions shared by every filter of :mod:`lbo.filters`: a batch of ``G`` trajectories of
``T`` steps, measurements ``m`` of shape (G, T, 3) = ``[x_m, y_m, psi_m]`` (or (G, T, 8) with
a receiver's channels, :mod:`lbo.filters.measure`) and inputs ``u`` of shape (G, T, 2) =
``[V, delta]``, where ``u[:, k]`` moves ``z_k`` to ``z_{k+1}``. The estimate at step ``k`` uses
``m_0 .. m_k`` and ``u_0 .. u_{k-1}``. Every filter starts from ``z_0 = m_0`` and
``P_0 = R`` (diagonal floored at :data:`COV_FLOOR`); estimated headings stay on the branch of
the measurements (continuous, not wrapped); metrics wrap the error.

The first row of every trajectory must hold a position, as the filters start there. A
trajectory that starts without a heading takes it from the course over ground
(:class:`CourseStart`): until then its heading is 0 rad with variance :data:`HEADING_VAR0`.
"""

from __future__ import annotations

import numpy as np

from lbo.core.errors import LboError
from lbo.filters import measure
from lbo.sim.vehicle import Vehicle, step

COV_FLOOR = 1e-9
"""Smallest variance put on the diagonal of P_0 (and of the UKF's R), so alpha=0 runs."""


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


def floor_diag(cov: np.ndarray, floor: float = COV_FLOOR) -> np.ndarray:
    """Copy of cov (..., 3, 3) whose diagonal is at least ``floor``."""
    out = np.array(cov, dtype=float, copy=True)
    idx = np.arange(3)
    out[..., idx, idx] = np.maximum(out[..., idx, idx], floor)
    return out


def check_trajectories(m: np.ndarray, u: np.ndarray, receiver: bool = True
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


def start_state(m0: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Starting state (G, 3) and covariance (G, 3, 3) at the first rows m0 (G, 3) or (G, 8):
    the fix and the step's R (the accuracies it reports, :func:`lbo.filters.measure.step_cov`;
    diagonal floored). Its heading is ``psi_m``, else the course over ground (its variance
    ``s_course^2``), else 0 rad with variance :data:`HEADING_VAR0`."""
    m0 = measure.widen(m0)
    c = measure.row_channels(m0)
    x = np.array(c.pose, dtype=float)
    P = floor_diag(measure.step_cov(m0, R))
    by_course = ~np.isfinite(x[:, 2]) & np.isfinite(c.course)
    blind = ~measure.heading_held(m0)
    x[by_course, 2] = c.course[by_course]
    x[blind, 2] = 0.0
    for rows, var in ((by_course, np.square(c.course_sigma)), (blind, HEADING_VAR0)):
        P[rows, 2, :] = P[rows, :, 2] = 0.0
        P[rows, 2, 2] = var[rows] if isinstance(var, np.ndarray) else var
    return x, P

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

def batch_cov(cov: np.ndarray, g: int, name: str) -> np.ndarray:
    """(3, 3) or (G, 3, 3) -> read-only (G, 3, 3) view."""
    cov = np.asarray(cov, dtype=float)
    if cov.shape not in ((3, 3), (g, 3, 3)):
        raise LboError(f"{name} must be (3, 3) or ({g}, 3, 3), got {cov.shape}")
    return np.broadcast_to(cov, (g, 3, 3))


def check_q(Q: np.ndarray) -> np.ndarray:
    Q = np.asarray(Q, dtype=float)
    if Q.shape != (3, 3):
        raise LboError(f"process covariance Q must be (3, 3), got {Q.shape}")
    return Q
