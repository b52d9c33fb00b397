"""The classical observers by name: the one registry that ``lbo.evaluate``, ``lbo.observe``,
:class:`lbo.Observer` and ``make reproduce`` use.

- ``ekf``: the paper's EKF, R at alpha = 1 whatever the noise;
- ``oracle``: the same EKF told the true alpha (R = alpha^2 R_1);
- ``adaptive``: the Sage-Husa EKF that learns R from its innovations, starting from R_1;
- ``ukf``: the unscented filter (filterpy's, vectorised), R at alpha = 1;
- ``oracle_dynamic``: the EKF on the true dynamic car (:mod:`lbo.filters.dynamic_ekf`), told
  alpha, the car's parameters, its process noise and the sensors' errors: the floor on a test
  set drawn from ``car=dynamic`` (it needs that truth, so it scores simulated test sets
  only, not a user's log);
- ``oracle_tuned``: the kinematic EKF told alpha, with at each alpha level the process noise Q
  that serves it best on the scored set itself (:func:`lbo.scoring.grid.tuned_oracle`): the best a
  kinematic EKF with a constant diagonal Q can do there, in hindsight. On a truth that is not the
  kinematic bicycle a larger Q absorbs some of the model's error, so this is the fair
  kinematic peer; it needs the true states, so it scores simulated test sets only;
- ``pcrb``: not an observer but the bound on any observer's error (needs the true states);
- ``gyro``: the EKF of the gyro-driven model (:mod:`lbo.filters.gyro`), its heading turned by a
  gyro's yaw rate ``r_m`` with the bias as a state, its inputs ``[V, r_m]``: for a log that
  holds a gyro (``lbo.observe``, :meth:`lbo.Observer.run` with a receiver's channels).

Each runs over a batch (:func:`estimate`) or one step at a time (:func:`stepper`), with the same
numbers either way.

A classical observer of a user's own comes from an installed package, registered under the
entry-point group ``lbo.observers`` (:mod:`lbo.core.plugins`, docs/plugins.md): a stepper
class built as ``Stepper(m0, vehicle, Q, R)``. lbo's own steppers (``ekf``, ``adaptive``,
``ukf``, ``gyro``) are registered there the same way and built through it one step at a
time; over a batch lbo's own run their vectorised forms, a plug-in its stepper step by step.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from lbo.core import plugins
from lbo.core.errors import LboError
from lbo.filters import measure
from lbo.filters.consistency import Checks
from lbo.filters.gyro import gyro_ekf_batch
from lbo.filters.gyro_noise import GyroNoise
from lbo.filters.kalman import adaptive_ekf_batch, ekf_batch
from lbo.filters.stepper import Posterior, run_stepper
from lbo.filters.unscented import UKF_SPREAD, ukf_batch
from lbo.sim.noise import Noise
from lbo.sim.truth import Truth
from lbo.sim.vehicle import Vehicle

if TYPE_CHECKING:  # the dynamic EKF is imported when the oracle on a car that slips runs
    from lbo.filters.dynamic_ekf import Lateral

OBSERVERS = ("ekf", "oracle", "adaptive", "ukf")
"""Causal observers that run on a log."""
DYNAMIC = "oracle_dynamic"
"""The oracle on the true dynamic car: told the truth model, so for simulated test sets only."""
TUNED = "oracle_tuned"
"""The kinematic EKF with its Q tuned on the scored set: for simulated test sets only."""
BOUND = "pcrb"
NAMES = (*OBSERVERS, DYNAMIC, TUNED, BOUND)
"""Everything ``lbo.evaluate`` scores on the test grid."""
GYRO = "gyro"
"""The EKF of the gyro-driven model: for logs with a gyro (r_m), not the test grid's."""
ON_LOGS = (*OBSERVERS, GYRO)
"""The classical observers ``lbo.observe`` and :class:`lbo.Observer` run on a log."""

# The peers a learned observer is scored and shown against, by where it is scored.
GRID_PEERS = ("ekf", "oracle")
"""On the kinematic test grid, in a training's final evaluation: the EKF whose NRMSE is the
reference, and the oracle whose NRMSE is the ratio's floor."""
KINEMATIC_PEERS = ("ekf", "oracle", "adaptive", BOUND)
"""In the report's robust-observer table: the EKF (R at alpha = 1), the oracle (told alpha),
the adaptive EKF and the PCRB."""
DYNAMIC_PEERS = ("ekf", "oracle", "adaptive", TUNED, DYNAMIC)
"""On a car that slips: the kinematic EKFs, the kinematic EKF tuned in hindsight and the EKF
told the car."""
LOG_PEERS = ("ekf", "adaptive", "ukf")
"""On logs: no oracle, since a log's alpha is unknown."""


def plugged() -> tuple[str, ...]:
    """The classical observers of installed packages other than lbo (entry-point group
    ``lbo.observers``)."""
    return tuple(n for n in plugins.names("observer") if n not in plugins.OWN["observer"])


def on_logs() -> tuple[str, ...]:
    """Every classical observer that runs on a log: :data:`ON_LOGS` and the plug-ins'."""
    return (*ON_LOGS, *plugged())


def check(name: str, field: str = "observer") -> None:
    """Raise one line naming ``field`` unless ``name`` is a classical observer."""
    if name == BOUND:
        raise LboError(f"{field}: pcrb is a bound on the error, not an observer; "
                       f"use one of {', '.join(OBSERVERS)} or a checkpoint")
    if name in (DYNAMIC, TUNED):
        told = "the simulated car's parameters" if name == DYNAMIC else "the true states"
        raise LboError(f"{field}: {name} is told {told} and scores simulated test sets only "
                       f"(lbo.evaluate); use one of {', '.join(OBSERVERS)} or a checkpoint")
    if name not in ON_LOGS and name not in plugged():
        raise LboError(f"{field}: unknown classical observer {name!r}; "
                       f"expected one of {', '.join(on_logs())}")


def told(name: str, noise: Noise, alpha: float) -> Noise:
    """The noise classical observer ``name`` runs with when told the noise scale ``alpha``:
    the measurement sigmas at alpha for the oracle (its R at alpha), ``noise`` itself for every
    other (R at alpha = 1). Built once where an observer is made, so that nothing after it
    carries alpha."""
    return noise.scaled(alpha) if name == "oracle" else noise


def measurement_cov(name: str, noise: Noise, alpha: float | np.ndarray, g: int) -> np.ndarray:
    """(G, 3, 3) R of each trajectory: R at its own alpha for the oracle, else R at 1."""
    scale = np.broadcast_to(np.asarray(alpha, dtype=float), (g,)) if name == "oracle" \
        else np.ones(g)
    return np.einsum("gi,ij->gij", np.square(noise.meas(scale)), np.eye(3))


def estimate(name: str, m: np.ndarray, u: np.ndarray, vehicle: Vehicle, noise: Noise,
        alpha: float | np.ndarray = 1.0, progress: bool = False,
        truth: Truth | None = None, smooth: bool = False,
        lengths: np.ndarray | None = None, gyro: GyroNoise | None = None
        ) -> Posterior:
    """The :class:`Posterior` of observer ``name`` over G trajectories: its estimates
    (G, T, 3) and their covariances (G, T, 3, 3) (the filter's P of the pose). ``smooth``: the RTS
    smoother's estimates after the filter (:mod:`lbo.filters.smoother`; not for ``oracle_dynamic``),
    over the first ``lengths`` (G,) steps of each padded trajectory (None: all).

    A trajectory whose first row holds no position starts at its first fix (NaN before it,
    and throughout where it has none).

    m : (G, T, 3) or (G, T, 8) rows (:mod:`lbo.filters.measure`); u : (G, T, 2) inputs
    (``[V, r_m]`` for ``gyro``, else ``[V, delta]``); alpha : the noise scale the oracles are
    told, one for all or (G,) per trajectory (the others ignore it); truth : what the log was
    drawn from, which ``oracle_dynamic`` is told (a ``car=dynamic`` one); gyro : the gyro
    EKF's noise (its Q in place of ``noise``'s, and its gyro's; None: the defaults).
    """
    if name == DYNAMIC:
        if smooth:
            raise LboError("oracle_dynamic: the floor of a filter; it has no smoother")
        return _oracle_dynamic(m, u, vehicle, noise, alpha, truth)
    check(name)
    m, u = np.asarray(m, dtype=float), np.asarray(u, dtype=float)
    if m.ndim == 3 and m.shape[1] and not np.isfinite(m[:, 0, :2]).all():
        return _from_first_fixes(name, m, u, vehicle, noise, alpha, progress, smooth, lengths,
                                 gyro)
    R = measurement_cov(name, noise, alpha, np.shape(m)[0])
    try:
        if name not in ON_LOGS:  # a plug-in: its stepper, step by step
            if smooth:
                raise LboError(f"{name}: a plug-in's observer has no smoother in lbo; use ekf "
                               "or ukf")
            flt = stepper(name, m[:, 0], vehicle, noise, alpha)
            return run_stepper(flt, measure.widen(m), u, pose=lambda kf: kf.x[:, :3],
                               cov=lambda kf: kf.P[:, :3, :3])
        if name == GYRO:
            if smooth:
                raise LboError("gyro: the gyro-driven EKF has no smoother yet; use ekf or ukf")
            if gyro is None:
                return gyro_ekf_batch(m, u, vehicle, noise.Q, R)
            return gyro_ekf_batch(m, u, vehicle, gyro.Q, R, **gyro.stepper())
        if name == "adaptive":
            return adaptive_ekf_batch(m, u, vehicle, noise.Q, R, smooth=smooth, lengths=lengths)
        if name == "ukf":
            return ukf_batch(m, u, vehicle, noise.Q, R, spread=UKF_SPREAD, progress=progress,
                             smooth=smooth, lengths=lengths)
        return ekf_batch(m, u, vehicle, noise.Q, R, smooth=smooth,
                         lengths=lengths)
    except np.linalg.LinAlgError as e:  # a covariance no longer positive definite
        raise LboError(f"{name}: the filter diverged ({e}); check the data's values and "
                       "units") from None


def check_gyro_noise(name: str, gyro: GyroNoise | None) -> None:
    """A gyro noise is the gyro EKF's: one line for any other observer ``name``."""
    if gyro is not None and name != GYRO:
        raise LboError(f"gyro_noise is the noise of the gyro EKF (observer={GYRO}), not of "
                       f"{name}")


def first_fixes(m: np.ndarray) -> np.ndarray:
    """(G,) the first row of each trajectory m (G, T, C) that holds a position (T: none)."""
    pos = np.isfinite(m[..., 0]) & np.isfinite(m[..., 1])
    return np.where(pos.any(axis=1), np.argmax(pos, axis=1), m.shape[1])


def _from_first_fixes(name: str, m: np.ndarray, u: np.ndarray, vehicle: Vehicle,
                      noise: Noise, alpha: float | np.ndarray, progress: bool,
                      smooth: bool, lengths: np.ndarray | None,
                      gyro: GyroNoise | None) -> Posterior:
    """:func:`estimate` of trajectories that start between fixes (a log cut anywhere): each
    is shifted to start at its first fix, filtered with the others in one batch, and shifted
    back; the rows before it (and a trajectory without any fix) are NaN."""
    g, t = m.shape[:2]
    first = first_fixes(m)
    src = np.arange(t) + np.minimum(first, t - 1)[:, None]      # (G, T) rows read
    inside = src < t
    rows = np.arange(g)[:, None]
    m2 = np.where(inside[..., None], m[rows, np.minimum(src, t - 1)], np.nan)
    u2 = np.where(inside[..., None], u[rows, np.minimum(src, t - 1)], 0.0)
    none = first == t
    m2[none, 0, :2] = 0.0  # a placeholder start; its estimates are dropped below
    real = (t if lengths is None else np.asarray(lengths)) - np.minimum(first, t)
    out = estimate(name, m2, u2, vehicle, noise, alpha, progress, smooth=smooth,
                   lengths=np.maximum(real, 1), gyro=gyro)
    est = np.full(m.shape[:2] + (3,), np.nan)
    cov = np.full(m.shape[:2] + (3, 3), np.nan)
    back = np.arange(t) - first[:, None]                          # (G, T) row of the shift
    ok = (back >= 0) & ~none[:, None]
    gi, ki = np.nonzero(ok)
    est[gi, ki] = out.mean[gi, back[gi, ki]]
    cov[gi, ki] = out.cov[gi, back[gi, ki]]
    checks = None
    if out.checks is not None:  # the consistency test's rows, shifted back as well
        checks = Checks.empty(g, t)
        for mine, theirs in zip(checks, out.checks):
            mine[gi, ki] = theirs[gi, back[gi, ki]]
    return Posterior(est, cov, checks)


def stepper(name: str, m0: np.ndarray, vehicle: Vehicle, noise: Noise,
            alpha: float | np.ndarray = 1.0, gyro: GyroNoise | None = None) -> Any:
    """Observer ``name`` started at the first measurements m0 (G, 3); its ``update(m (G, 3),
    u_prev (G, 2))`` returns the next estimates (G, 3), as :func:`estimate` would (``gyro``
    as there)."""
    check(name)
    R = measurement_cov(name, noise, alpha, len(m0))
    # the oracle is the EKF told alpha (R above); every other name is a registered stepper
    cls = plugins.load("observer", "ekf" if name == "oracle" else name, "observer")
    if name == GYRO and gyro is not None:
        return cls(m0, vehicle, gyro.Q, R, **gyro.stepper())
    if name in ON_LOGS:
        return cls(m0, vehicle, noise.Q, R)
    try:
        return cls(measure.widen(m0), vehicle, noise.Q.copy(), R.copy())
    except LboError:
        raise
    except Exception as e:  # a plug-in's own failure, said in lbo's one line
        raise LboError(f"observer {name!r} failed to start ({type(e).__name__}: {e})") from None


def _oracle_dynamic(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, noise: Noise,
                    alpha: float | np.ndarray, truth: Truth | None) -> Posterior:
    from lbo.filters.dynamic_ekf import dynamic_ekf_batch

    return _told_the_car(dynamic_ekf_batch, m, u, vehicle, noise, alpha, truth)


def oracle_dynamic_lateral(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, noise: Noise,
                           alpha: float | np.ndarray, truth: Truth | None
                           ) -> tuple[Posterior, Lateral]:
    """``oracle_dynamic`` with the lateral states it carries (G trajectories, m (G, T, 3),
    u (G, T, 2), ``alpha`` (G,) or one): the pose's posterior and :class:`Lateral`'s v_y, r
    and their covariance (:func:`lbo.filters.dynamic_ekf.dynamic_ekf_lateral`)."""
    from lbo.filters.dynamic_ekf import dynamic_ekf_lateral

    return _told_the_car(dynamic_ekf_lateral, m, u, vehicle, noise, alpha, truth)


def _told_the_car(run: Callable[..., Any], m: np.ndarray, u: np.ndarray, vehicle: Vehicle,
                  noise: Noise, alpha: float | np.ndarray, truth: Truth | None,
                  **kwargs: Any) -> Any:
    """``run`` (the dynamic EKF) told what the set was drawn from: the car, its sensors'
    errors, the process noise's scale, its lateral states' disturbances and each trajectory's
    alpha."""
    if truth is None or truth.car is None:
        raise LboError("oracle_dynamic: the test set was not drawn from car=dynamic, so there "
                       "is no car to tell it; score it on data=dynamic (or car=dynamic)")
    g = np.shape(m)[0]
    scale = np.broadcast_to(np.asarray(alpha, dtype=float), (g,))
    R = measurement_cov("oracle", noise, scale, g)
    sensors = truth.sensors
    try:
        return run(m, u, vehicle, truth.car, truth.process_scale**2 * noise.Q, R,
                   gnss_sigma=scale * sensors.gnss_sigma, gnss_tau=sensors.gnss_tau,
                   steering_offset=sensors.steering_offset, speed_scale=sensors.speed_scale,
                   lateral_sigma=truth.lateral_sigma, **kwargs)
    except np.linalg.LinAlgError as e:
        raise LboError(f"oracle_dynamic: the filter diverged ({e}); check the data's values "
                       "and units") from None
