"""The states no sensor gives, scored on a car that slips: the side slip beta (at the centre of
gravity), the lateral velocity v_y and the yaw rate r, against the truth that a
``data=dynamic`` test set holds (``Trajectories.lateral``: v_y, r), per noise level.

The estimators that give them, from the pose fixes and the logged inputs only:

- ``oracle_dynamic``: the EKF told the car (:func:`lbo.filters.classical.oracle_dynamic_lateral`),
  which carries v_y and r and the variance of beta;
- ``kinematic``: the kinematic bicycle's, from the inputs alone, on the car's geometry:
  beta = atan(l_r tan(delta) / L), v_y = V tan(beta), r = V tan(delta) / L (lbo's kinematic
  model turns the heading at that rate);
- ``zero``: straight ahead, beta = v_y = 0 (no yaw rate);
- a learned observer with a single-track body (``experiment=dynamic``, KalmanNet's peers with
  ``model.body=single_track``): the ``[v_y, r]`` its recursive form carries (:func:`carried`),
  beta = atan2(v_y, V) on the logged speed V (:func:`lbo.serve.estimate.side_slip`).

Each RMSE is over the scored rows of every trajectory of a level, pooled; ``nees_beta`` is the
mean of beta's squared error over the estimate's variance of it (1 for an honest variance;
NaN where there is none).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, cast

import numpy as np
import pandas as pd

from lbo.core.errors import LboError
from lbo.serve.estimate import lateral_variance, side_slip
from lbo.sim.dynamic import SingleTrack
from lbo.sim.noise import Noise
from lbo.sim.schema import Trajectories
from lbo.sim.truth import Truth
from lbo.sim.vehicle import Vehicle

COLUMNS = ["observer", "alpha", "rmse_beta", "rmse_vy", "rmse_r", "nees_beta"]
"""A lateral score table's columns: beta in rad, v_y in m/s, r in rad/s."""

def truth_of(arr: Trajectories, truth: Truth) -> dict[str, np.ndarray]:
    """The true ``beta``, ``vy`` and ``r`` (G, T) of a test set drawn from ``truth``'s car:
    beta = atan2(v_y, v_x), v_x the speed the car had (the logged one less the speed
    sensor's scale error)."""
    if arr.lateral is None or truth.car is None:
        raise LboError("lateral states: scored on a test set drawn from a car that slips "
                       "(data=dynamic), whose rows hold its v_y and r")
    vx = arr.u[..., 0] / (1.0 + truth.sensors.speed_scale)
    vy, r = arr.lateral[..., 0], arr.lateral[..., 1]
    return {"beta": np.arctan2(vy, vx), "vy": vy, "r": r}


def carries(net: Any) -> bool:
    """Whether a learned observer carries a single-track body's ``[v_y, r]`` in its recursive
    form: a window filter (``filternet``) or a KalmanNet peer with
    ``model.body=single_track``, in torch."""
    from lbo.models.carried import carries_body
    from lbo.models.filternet import WindowFilter

    model = getattr(net, "net", None)
    return (isinstance(model, WindowFilter) and bool(model.single_track)) or carries_body(model)


def carried(net: Any, arr: Trajectories, device: str = "cpu") -> np.ndarray:
    """(G, T, 2) the ``[v_y, r]`` a learned observer's single-track body (:func:`carries`)
    carries through the arrays in its recursive form, run on ``device`` (NaN where it has no
    estimate)."""
    from lbo.models import carried as sequence
    from lbo.models.recursive import run_arrays
    from lbo.serve.runners import is_window_filter

    if is_window_filter(net):
        pose, _, body = run_arrays(net.net, arr.m, arr.u, device=device)
    else:
        pose, body = sequence.run_arrays(sequence.in_float64(net.net).to(device), arr.m,
                                         arr.u, device)
    return np.where(np.isfinite(pose[..., :1]), body, np.nan)


def body_error(body: np.ndarray, arr: Trajectories) -> np.ndarray:
    """The error (2, 2) of a carried ``[v_y, r]`` (G, T, 2) (:func:`carried`) against the set's
    own (``arr.lateral``) over its scored rows where the body has an estimate, as
    :func:`lbo.serve.estimate.lateral_variance` reads it: per state (a row), the floor and the
    relative part of the variance of its error, var = floor + part state^2, fitted by
    maximum likelihood (:func:`_variance_fit`). Not centred: a body that is off on average
    is as far off as one that scatters. Measured on a learned observer's validation set as it
    trains (:class:`lbo.learn.callbacks.LateralError`)."""
    if arr.lateral is None:
        raise LboError("lateral states: the body's error is measured on a set drawn from a car "
                       "that slips (data=dynamic), whose rows hold its v_y and r")
    pick = arr.mask & np.isfinite(body).all(-1)
    if not pick.any():
        raise LboError("lateral states: the body has no estimate on any scored row")
    err, state = (body - arr.lateral)[pick], body[pick]
    return np.stack([_variance_fit(err[:, i] ** 2, state[:, i] ** 2) for i in range(2)])


def _variance_fit(e2: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """``[floor, part]``: the variance floor + part x2 of zero-mean Gaussian errors whose
    squares are ``e2`` (n,), at the squared states ``x2`` (n,), by maximum likelihood. For a
    ratio c = floor / part the likeliest scale is part = mean(e2 / (c + x2)), so the
    likelihood is searched over c alone, on a log grid that runs from a floor of nothing to
    a variance of the floor alone. The relative part is kept only where it is likelier by
    the likelihood-ratio test's 95% (a chi-square of one degree: 3.84 for twice the
    log-likelihood); else the floor alone, the mean of e2."""
    mean_x2 = float(np.mean(x2))
    alone = np.array([float(np.mean(e2)), 0.0])
    if mean_x2 == 0.0 or not np.any(e2):  # nothing to scale by, or no error at all
        return alone
    ratios = mean_x2 * np.logspace(-6, 6, 241)[:, None]  # c, in units of the mean state^2
    part = np.mean(e2 / (ratios + x2), axis=1, keepdims=True)
    nll = np.mean(np.log(part * (ratios + x2)), axis=1)  # per row, less 1/2 and constants
    if len(e2) * (np.log(alone[0]) - nll.min()) <= 3.84:  # twice the log-likelihood ratio
        return alone
    best = int(np.argmin(nll))
    return np.array([float(part[best, 0] * ratios[best, 0]), float(part[best, 0])])


def estimates(arr: Trajectories, vehicle: Vehicle, noise: Noise, truth: Truth,
              learned: Mapping[str, np.ndarray] | None = None,
              errors: Mapping[str, np.ndarray | None] | None = None
              ) -> dict[str, dict[str, np.ndarray | None]]:
    """Each estimator's ``beta``, ``vy``, ``r`` and ``beta_var`` (G, T) on the test arrays
    (None: not estimated); nothing but the fixes ``arr.m`` and inputs ``arr.u`` is read.
    ``learned``: each learned observer's carried ``[v_y, r]`` (G, T, 2) (:func:`carried`),
    scored first; ``errors``: the body's error (2, 2) each learned observer's checkpoint
    holds (:func:`body_error` on its validation set), of which its beta's variance is made
    (:func:`lbo.serve.estimate.lateral_variance`; none: no variance)."""
    from lbo.filters.classical import oracle_dynamic_lateral
    from lbo.filters.lateral import kinematic_beta

    car = truth.car
    if car is None:
        raise LboError("lateral states: the test set was not drawn from a car that slips")
    v, delta = arr.u[..., 0], arr.u[..., 1]
    _, lat = oracle_dynamic_lateral(arr.m, arr.u, vehicle, noise, arr.alpha, truth)
    out: dict[str, dict[str, np.ndarray | None]] = {}
    for name, body in (learned or {}).items():
        states, error = side_slip(body, v), (errors or {}).get(name)
        out[name] = {"beta": states[..., 0], "vy": body[..., 0], "r": body[..., 1],
                     "beta_var": None if error is None
                     else lateral_variance(error, states, v)[..., 0]}
    out["oracle_dynamic"] = {"beta": lat.beta(v), "vy": lat.mean[..., 0], "r": lat.mean[..., 1],
                             "beta_var": lat.beta_var(v)}
    if isinstance(car, SingleTrack):  # a plug-in's car need not say where its centre of gravity is
        kin = kinematic_beta(delta, car)
        out["kinematic"] = {"beta": kin, "vy": v * np.tan(kin),
                            "r": v * np.tan(delta) / car.wheelbase, "beta_var": None}
    zero = np.zeros_like(v)
    out["zero"] = {"beta": zero, "vy": zero, "r": None, "beta_var": None}
    return out


def of_data(test: Any, cfg: Any, learned: Mapping[str, str]) -> pd.DataFrame | None:
    """:func:`table` of the test file ``test`` of a set drawn from the car of the composed
    config ``cfg`` (its vehicle, noise, car and sensors), with the ``learned`` observers
    (label -> checkpoint) that carry a single-track body; None where the set holds no
    lateral states."""
    from lbo.scoring.grid import load_test
    from lbo.sim.truth import of_config
    from lbo.tracking.artifacts import load_net

    arr = load_test(test)
    if arr.lateral is None:
        return None
    vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
    nets = {label: load_net(path)[0] for label, path in learned.items()}
    return table(arr, vehicle, noise, of_config(cfg, vehicle.wheelbase),
                 {label: carried(net, arr) for label, net in nets.items() if carries(net)},
                 {label: net.lateral_error for label, net in nets.items()})


def rmse(est: np.ndarray | None, true: np.ndarray, pick: np.ndarray) -> float:
    """RMSE of a lateral state's estimate ``est`` against ``true`` (G, T) on the rows ``pick``
    (G, T) where it has an estimate; NaN for None."""
    if est is None:
        return float("nan")
    pick = pick & np.isfinite(est)
    return float(np.sqrt(np.mean((est - true)[pick] ** 2)))


def table(arr: Trajectories, vehicle: Vehicle, noise: Noise, truth: Truth,
          learned: Mapping[str, np.ndarray] | None = None,
          errors: Mapping[str, np.ndarray | None] | None = None) -> pd.DataFrame:
    """Rows :data:`COLUMNS`, one per estimator and noise level of the test arrays
    (``learned``, ``errors``: as :func:`estimates`)."""
    true = truth_of(arr, truth)
    rows = []
    for name, est in estimates(arr, vehicle, noise, truth, learned, errors).items():
        for alpha in np.unique(arr.alpha):
            pick = (arr.alpha == alpha)[:, None] & arr.mask  # the level's scored rows
            var = est["beta_var"]
            nees = float("nan") if var is None else float(np.mean(
                ((cast(np.ndarray, est["beta"]) - true["beta"]) ** 2 / var)[pick]))
            rows.append({"observer": name, "alpha": float(alpha),
                         **{f"rmse_{k}": rmse(est[k], true[k], pick) for k in ("beta", "vy", "r")},
                         "nees_beta": nees})
    return pd.DataFrame(rows, columns=COLUMNS)


def printable(scores: pd.DataFrame) -> str:
    """The table as a person reads it: beta in degrees, per level and estimator."""
    shown = scores.assign(rmse_beta=np.rad2deg(scores["rmse_beta"])).rename(columns={
        "rmse_beta": "beta (deg)", "rmse_vy": "v_y (m/s)", "rmse_r": "r (rad/s)",
        "nees_beta": "beta NEES"})
    with pd.option_context("display.width", 120, "display.precision", 4):
        return shown.to_string(index=False)
