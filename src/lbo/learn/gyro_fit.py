"""Learning the gyro EKF's noise from logs: a real drive's train span, with its truth or
without.

The gyro EKF (:mod:`lbo.filters.gyro`) assumes seven noises (:class:`GyroNoise`): the process
noise of position and heading, the gyro's white noise and bias walk, how far to trust the
receiver's reported accuracy and velocity sigma, and the antenna's lever the course allows
for. Set by hand they are guesses. :func:`fit` learns them as the robust observer learns its
EKF's noise: through the filter (its torch twin, :class:`lbo.models.gyro_filter.GyroFilter`),
by gradient descent on the estimates' error against the truth.

- The train log is cut into segments of ``segment`` steps from its first course over ground
  on (before it a car standing since the log began has no heading to learn from); each starts
  from the NumPy filter's state there under the current noise (recomputed every epoch, every
  log in one batch of that filter: :mod:`lbo.learn.gyro_logs`), and all run as one batch.
- The loss is the mean over x, y and psi of each one's mean square error, divided by the
  starting noise's: the square of the measure the real drive is scored by (the quadratic mean
  of RMSE ratios), against the filter the fit starts from.
- After each epoch the NumPy filter runs the validation log from its first fix; the noise
  kept is the one with the lowest measure there (its ratio to the starting noise's).
- Without truth (``objective="innovations"``, a fleet's logs) the loss is the negative
  log-likelihood of what the filter measures (fixes, course, the gyro at standstill) under
  its own predicted covariance, the maximum-likelihood fit of a Kalman filter's noise; the
  noise kept is the one with the lowest such loss on the validation segments. The truth is
  neither needed nor read. ``ahead`` adds each fix as predicted seconds before it.
- ``receiver_noise="variogram"``: the factors on the receiver's accuracy and velocity sigma are
  not learned but set from the train logs (:mod:`lbo.learn.variogram`: how slow the fixes'
  and the course's errors are, which the innovations cannot see), and the rest learned as the
  objective says.
- ``hold``: noises kept at ``start``'s values, not learned. With the variogram's factors, the
  innovations' likelihood sees the fixes vary less from one to the next than the widened
  factors say, and shrinks whatever else widens those innovations (the position's process
  noise, the course's lever); holding those at their priors keeps the widening
  (docs/logs.md, section 8).
- ``method="lbfgs"``: the classical maximum-likelihood fit, by L-BFGS (a quasi-Newton
  optimiser with a line search) in place of Adam's small steps: the peer of the learned fit.
  On a log drawn from the filter's own model it finds the noise that drew it.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from lbo.core.checks import one_of
from lbo.core.errors import LboError
from lbo.filters import classical
from lbo.filters.gyro_noise import NOISE_RANGES, FixDrift, GyroNoise
from lbo.learn.eta import more
from lbo.learn.gyro_logs import as_logs, estimates, segments
from lbo.learn.variogram import RECEIVER_NOISES, receiver_scales
from lbo.models.gyro_filter import GyroFilter, Segments
from lbo.models.poses import wrap_heading
from lbo.scoring.receiver import measure_ratio, scored_rows
from lbo.sim.columns import STATE
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

__all__ = ["METHODS", "OBJECTIVES", "GyroFit", "Settings", "adapt", "fit", "fit_and_write",
           "fix_cov", "held"]


@dataclass(frozen=True, kw_only=True)
class GyroFit:
    """What :func:`fit` learned.

    noise : the noise with the lowest measure on the validation log.
    start : the noise it started from.
    history : one row per epoch: ``epoch, loss`` (train, against the start: 1 at epoch 0)
        and ``val`` (the validation measure against the start); fitted by the innovations,
        both are nats per step from the start's (0 at epoch 0).
    best_epoch : the epoch of ``noise`` (0: the start itself).
    """

    noise: GyroNoise
    start: GyroNoise
    history: pd.DataFrame
    best_epoch: int


DRIFT_START = FixDrift(sigma=0.3, tau=30.0)
"""The fixes' drift a fit with ``drift`` starts from: a few decimetres over half a minute, a
receiver's multipath and atmosphere (the fit learns both numbers)."""


VARIOGRAM_SET = ("accuracy_scale", "velocity_scale")
"""The noises ``receiver_noise="variogram"`` sets from the train logs rather than learns."""


@dataclass(frozen=True, kw_only=True)
class Settings:
    """How a command fits the gyro EKF's noise (its ``learn:`` group), checked.

    epochs : full-batch steps (0: no fit); segment_s : s per segment; lr : Adam's step;
    objective : one of :data:`OBJECTIVES`; method : one of :data:`METHODS`;
    ahead_s : s ahead each fix is also predicted (``innovations`` only; 0: none);
    drift : the filter carries the fixes' drift as two more states, its size and correlation
        time learned from :data:`DRIFT_START` (:meth:`starting`);
    scales : factors on the speed and the gyro's rate are learned too, from 1;
    receiver_noise : one of :data:`RECEIVER_NOISES`, how the factors on the receiver's
        accuracy and velocity sigma are found;
    hold : names of :class:`GyroNoise`'s noises kept at the start, not learned.
    """

    epochs: int
    segment_s: float
    lr: float
    objective: str = "truth"
    method: str = "adam"
    ahead_s: float = 0.0
    drift: bool = False
    scales: bool = False
    receiver_noise: str = "learned"
    hold: tuple[str, ...] = ()

    @classmethod
    def from_cfg(cls, learn: Any, prefix: str = "learn") -> Settings:
        """From a config group, each field checked in one line naming ``<prefix>.<field>``."""
        from lbo.core.checks import boolean, integer, number

        out = cls(epochs=integer(learn.epochs, f"{prefix}.epochs", 0),
                  segment_s=number(learn.segment_s, f"{prefix}.segment_s", 0.0, low_open=True),
                  lr=number(learn.lr, f"{prefix}.lr", 0.0, low_open=True),
                  objective=one_of(learn.get("objective", "truth"), OBJECTIVES,
                                   f"{prefix}.objective"),
                  method=one_of(learn.get("method", "adam"), METHODS, f"{prefix}.method"),
                  ahead_s=number(learn.get("ahead_s", 0.0), f"{prefix}.ahead_s", 0.0),
                  drift=boolean(learn.get("drift", False), f"{prefix}.drift"),
                  scales=boolean(learn.get("scales", False), f"{prefix}.scales"),
                  receiver_noise=one_of(learn.get("receiver_noise", "learned"),
                                        RECEIVER_NOISES, f"{prefix}.receiver_noise"),
                  hold=held(learn.get("hold", []), f"{prefix}.hold"))
        if out.ahead_s and out.objective != "innovations":
            raise LboError(f"{prefix}.ahead_s applies to {prefix}.objective=innovations (the "
                           f"fit by the fixes' likelihood), got {prefix}.objective="
                           f"{out.objective}")
        out._check_hold(prefix)
        return out

    def _check_hold(self, prefix: str) -> None:
        """Before any run opens: each noise held is one the fit's filter carries, and one
        is left to learn (:func:`_holding`, which :func:`fit` checks too)."""
        set_by_logs = VARIOGRAM_SET if self.receiver_noise == "variogram" else ()
        carried, absent, none_left = _holding(
            self.starting(GyroNoise(q_position=1.0, q_heading=1.0)), self.hold, set_by_logs)
        if absent:
            raise LboError(f"{prefix}.hold: {', '.join(absent)} is not a noise this fit "
                           f"learns (it learns {', '.join(carried)}; drift_sigma and "
                           f"drift_tau with {prefix}.drift=true, speed_scale and gyro_scale "
                           f"with {prefix}.scales=true)")
        if self.epochs and none_left:
            raise LboError(f"{prefix}.hold: every noise this fit learns is held or set by "
                           f"its logs ({', '.join(carried)}): nothing is left to learn")

    def starting(self, noise: GyroNoise) -> GyroNoise:
        """The noise a fit starts from: ``noise``, with :data:`DRIFT_START` if ``drift``, with
        both scales at 1 if ``scales`` (else as ``noise`` holds them)."""
        noise = noise.with_drift(DRIFT_START if self.drift else None)
        return noise.with_scales() if self.scales else noise

    def start(self, Q: np.ndarray) -> GyroNoise:
        """:meth:`starting` from the defaults with the process sigmas of ``Q`` (3, 3), the
        classical observers' (:meth:`GyroNoise.from_q`): where every command's fit starts."""
        return self.starting(GyroNoise.from_q(Q))

    def kwargs(self, dt: float) -> dict[str, Any]:
        """The keywords of :func:`fit` (and :func:`fit_and_write`) for a log of period
        ``dt``: epochs, segment and ahead in steps, lr, objective, method, receiver_noise
        and hold."""
        return {"epochs": self.epochs, "segment": max(2, round(self.segment_s / dt)),
                "lr": self.lr, "objective": self.objective, "method": self.method,
                "ahead": round(self.ahead_s / dt), "receiver_noise": self.receiver_noise,
                "hold": self.hold}


def _holding(start: GyroNoise, hold: Sequence[str], set_by_logs: Sequence[str]
             ) -> tuple[list[str], list[str], bool]:
    """What holding ``hold`` does to a fit from ``start``: the noises its filter carries
    (those ``start`` holds, in :data:`NOISE_RANGES`' order), the names of ``hold`` it does
    not carry, and whether every one it carries is held or set by the logs."""
    values = dataclasses.asdict(start)
    carried = [n for n in NOISE_RANGES if values.get(n) is not None]
    return (carried, [n for n in hold if n not in carried],
            set(carried) <= {*hold, *set_by_logs})


def held(names: Any, field: str = "hold") -> tuple[str, ...]:
    """``names`` (a list of noise names, or None) as a tuple, each one of
    :data:`lbo.filters.gyro_noise.NOISE_RANGES`'s, or one line naming ``field``."""
    from omegaconf import ListConfig

    if names is None:
        return ()
    if not isinstance(names, list | tuple | ListConfig) or not all(
            isinstance(n, str) for n in names):
        raise LboError(f"{field}: expected a list of the gyro EKF's noise names, got {names!r}")
    unknown = [n for n in names if n not in NOISE_RANGES]
    if unknown:
        raise LboError(f"{field}: expected names among {', '.join(NOISE_RANGES)}, got "
                       f"{', '.join(map(repr, unknown))}")
    return tuple(dict.fromkeys(names))


def fix_cov(preset: Noise) -> np.ndarray:
    """(3, 3) the fixes' covariance where one reports no accuracy: the EKF's R under the
    classical observers' noise ``preset``, at alpha 1 (the R every fit here takes)."""
    return classical.measurement_cov("ekf", preset, 1.0, 1)[0]


def _mse(est: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    d = est - truth
    d = wrap_heading(d)
    return (d**2).mean(dim=(0, 1))


def _pooled(logs: list[pd.DataFrame], noise: GyroNoise, reference: list[np.ndarray],
            vehicle: Vehicle, R: np.ndarray) -> float:
    """:func:`measure_ratio` of ``noise`` against the reference estimates, over the scored
    rows of every log pooled."""
    est = np.concatenate(estimates(logs, noise, vehicle, R))
    truth = np.concatenate([log[list(STATE)].to_numpy(float) for log in logs])
    rows = np.concatenate([scored_rows(log) for log in logs])
    return measure_ratio(est, np.concatenate(reference), truth, rows)


METHODS = ("adam", "lbfgs")
"""How :func:`fit` minimises: Adam's small steps, or L-BFGS, the classical quasi-Newton
maximum-likelihood fit."""
LBFGS_ITERATIONS = 5
"""L-BFGS iterations per epoch (each on the segments that epoch's noise starts)."""
OBJECTIVES = ("truth", "innovations")
"""What :func:`fit` minimises: the estimates' error against the truth, or the filter's
innovations' negative log-likelihood, which needs no truth."""


def _innovations(model: GyroFilter, seg: Segments, ahead: int = 0) -> torch.Tensor:
    """The mean negative log-likelihood per step of the segments' measurements under the
    filter's own predictions (:meth:`GyroFilter.run`), over the steps that measure
    anything; with ``ahead`` steps, plus the mean one of each fix predicted that many steps
    before it (:meth:`GyroFilter.ahead`)."""
    x, P, nll = model.states(seg)  # one pass of the filter serves both terms
    loss = nll[:, 1:].sum() / torch.count_nonzero(nll[:, 1:]).clamp(min=1)
    if ahead:
        loss = loss + model.ahead(seg, ahead, (x, P)).mean()
    return loss


def fit(train: pd.DataFrame | Sequence[pd.DataFrame],
        val: pd.DataFrame | Sequence[pd.DataFrame], vehicle: Vehicle, R: np.ndarray,
        start: GyroNoise, epochs: int = 12, segment: int = 500, lr: float = 0.1,
        progress: Callable[[str], None] | None = print,
        objective: str = "truth", ahead: int = 0, method: str = "adam",
        receiver_noise: str = "learned", hold: Sequence[str] = ()) -> GyroFit:
    """Learn the gyro EKF's noise on ``train`` (one log or several), keep the best on ``val``
    (one or several).

    vehicle : its dt; R (3, 3) : the fixes' covariance where one reports no accuracy;
    start : the noise to start from; epochs : full-batch Adam steps (lr on the noises' logs);
    segment : steps per segment; progress : called with one line per epoch (None: silent);
    objective : ``truth`` (the logs hold it: the loss is the estimates' error, the best
        noise the one with the lowest measure on ``val``'s scored rows, pooled), or
        ``innovations`` (no truth needed, none read: the loss and the choice on ``val`` are
        the mean negative log-likelihood per step of the fixes, course and standstill gyro
        under the filter's own prediction; ``loss`` and ``val`` in the history are then its
        change from the starting noise's, in nats per step);
    ahead : with ``innovations``, steps: each fix is also scored under the prediction made
        that many steps before it, with no measurement between (:meth:`GyroFilter.ahead`),
        its mean negative log-likelihood added to the loss (0: none);
    method : ``adam`` (``epochs`` steps of Adam at ``lr``) or ``lbfgs``, the classical
        maximum-likelihood fit by a quasi-Newton optimiser (:data:`METHODS`: each epoch up to
        :data:`LBFGS_ITERATIONS` L-BFGS iterations with a strong-Wolfe line search on that
        epoch's segments; ``lr`` unused);
    receiver_noise : ``learned``, or ``variogram``: ``start``'s factors on the receiver's
        accuracy and velocity sigma replaced by those ``train`` calls for
        (:func:`lbo.learn.variogram.receiver_scales`) and not learned
        (:data:`RECEIVER_NOISES`); the history's ratios are then against that start;
    hold : names of noises kept at ``start``'s values (:func:`held`); each one the filter
        carries (``drift_*`` with ``start``'s drift, ``*_scale`` of the speed and the gyro
        with its scales), and at least one noise left to learn.
    """
    if epochs < 0 or segment < 2:
        raise LboError(f"fit needs epochs >= 0 and segment >= 2, got {epochs} and {segment}")
    one_of(objective, OBJECTIVES, "objective")
    if ahead < 0 or (ahead and objective != "innovations"):
        raise LboError(f"fit: ahead is a number of steps >= 0 for objective='innovations', "
                       f"got {ahead} for {objective!r}")
    one_of(method, METHODS, "method")
    one_of(receiver_noise, RECEIVER_NOISES, "receiver_noise")
    own = val is train  # the logs are their own validation (adapt): one pass serves both
    train, val = as_logs(train), as_logs(val)
    set_by_logs = VARIOGRAM_SET if receiver_noise == "variogram" else ()
    if set_by_logs:
        start = dataclasses.replace(start, **dict(zip(set_by_logs, receiver_scales(train))))
    hold = held(hold)
    carried, absent, none_left = _holding(start, hold, set_by_logs)
    if absent:
        raise LboError(f"hold: {', '.join(absent)} is not a noise of this filter (it "
                       f"carries {', '.join(carried)})")
    if epochs and none_left:
        raise LboError(f"hold: every noise of the filter is held or set by its logs "
                       f"({', '.join(carried)}): nothing is left to learn")
    model = GyroFilter(start, vehicle.dt, torch.as_tensor(R))
    # what the innovations cannot judge stays as the logs say; what is held, as it starts
    for name in (*set_by_logs, *hold):
        model.log[name].requires_grad_(False)
    learned = [p for p in model.parameters() if p.requires_grad]
    opt: torch.optim.Optimizer = (
        torch.optim.Adam(learned, lr=lr) if method == "adam" else
        torch.optim.LBFGS(learned, lr=1.0, max_iter=LBFGS_ITERATIONS,
                          line_search_fn="strong_wolfe"))
    supervised = objective == "truth"
    reference = estimates(val, start, vehicle, R) if supervised else []
    scale: torch.Tensor | None = None
    best: tuple[float, int, GyroNoise] = (1.0 if supervised else 0.0, 0, start)
    val_start = 0.0
    history = []
    nll_now = torch.zeros(())  # the NLL of the train segments at train_loss's last call


    def train_loss(seg: Segments) -> torch.Tensor:
        """The loss on the train segments, against the starting noise's."""
        nonlocal scale
        if supervised:
            mse = _mse(model(seg), seg.truth)
            if scale is None:
                scale = mse.detach()
            return (mse / scale).mean()
        nonlocal nll_now
        nll = _innovations(model, seg, ahead)
        nll_now = nll.detach()
        if scale is None:
            scale = nll_now
        return nll - scale

    begin = time.perf_counter()
    for epoch in range(epochs + 1):
        noise = model.noise()
        seg = segments(train, noise, vehicle, R, segment)
        loss = train_loss(seg)
        if not torch.isfinite(loss):
            raise LboError(f"gyro noise fit: the loss is not finite at epoch {epoch} (noise "
                           f"{noise}); lower lr (now {lr:g})")
        if supervised:
            score = 1.0 if epoch == 0 else _pooled(val, noise, reference, vehicle, R)
        else:
            if own:  # the same segments under the same noise: the number the loss just took
                held_out = float(nll_now)
            else:
                with torch.no_grad():
                    held_out = float(_innovations(
                        model, segments(val, noise, vehicle, R, segment), ahead))
            if epoch == 0:
                val_start = held_out
            score = held_out - val_start
        if score < best[0]:
            best = (score, epoch, noise)
        history.append({"epoch": epoch, "loss": loss.item(), "val": score})
        if progress is not None:
            progress(f"epoch {epoch}/{epochs}: train {loss.item():.3f}, validation {score:.3f} "
                     + ("(against the starting noise)" if supervised else
                        "(innovations' NLL per step, nats, from the starting noise's)"))
        if epoch < epochs and method == "adam":
            opt.zero_grad()
            loss.backward()
            opt.step()
        elif epoch < epochs:
            _lbfgs_step(opt, partial(train_loss, seg))
        if epoch == 0 and epochs > 0 and progress is not None:  # the others take as long
            progress(more(epochs, "epoch", time.perf_counter() - begin,
                          "epoch 0's time, its step included"))
    return GyroFit(noise=best[2], start=start, history=pd.DataFrame(history),
                   best_epoch=best[1])


def _lbfgs_step(opt: torch.optim.Optimizer, loss: Callable[[], torch.Tensor]) -> None:
    """One step of L-BFGS, which calls ``loss`` as often as its line search needs."""
    def closure() -> float:
        opt.zero_grad()
        value = loss()
        value.backward()
        return float(value.detach())

    opt.step(closure)


def fit_and_write(out: Path, name: str, train: pd.DataFrame | Sequence[pd.DataFrame],
                  val: pd.DataFrame | Sequence[pd.DataFrame], vehicle: Vehicle, R: np.ndarray,
                  start: GyroNoise, where: str, **how: Any) -> GyroNoise:
    """:func:`fit` (``how``: its keywords from ``epochs`` on, progress aside), one printed line
    per epoch, written into the folder ``out`` as ``<name>.json`` (the noise kept,
    :meth:`GyroNoise.save`) and ``<name>_history.csv``; ``where`` says in the first line what
    it learns on. Returns the noise kept."""
    from lbo.logs.io import write_table

    said = [f"{how.get('epochs', 12)} epochs"]
    if how.get("objective", "truth") != "truth":
        said.append("by its innovations' likelihood, no truth read")
    if how.get("receiver_noise") == "variogram":
        said.append("the receiver's noise set by its variogram")
    if how.get("hold"):
        said.append(f"{', '.join(how['hold'])} held")
    print(f"learning the gyro EKF's noise {where} ({', '.join(said)}; keeps the best on its "
          "validation drives)")
    fitted = fit(train, val, vehicle, R, start, progress=lambda line: print("  " + line), **how)
    fitted.noise.save(Path(out) / f"{name}.json")
    write_table(fitted.history, Path(out) / f"{name}_history.csv")
    print(f"  kept epoch {fitted.best_epoch}: {fitted.noise}")
    return fitted.noise


def adapt(log: pd.DataFrame, start: GyroNoise, vehicle: Vehicle, preset: Noise,
          epochs: int = 12, segment_s: float = 10.0, lr: float = 0.1, ahead: int = 0,
          progress: Callable[[str], None] | None = None, receiver_noise: str = "learned"
          ) -> GyroFit:
    """The gyro EKF's noise fitted on the very log it is to filter, by its innovations
    (:func:`fit` with ``objective="innovations"``, the log its own validation): offline, for
    it reads the whole log first. Any truth columns are dropped unread.

    preset : the classical observers' noise (its R where a fix reports no accuracy);
    segment_s : seconds per segment (at least one such span after the first course);
    progress, receiver_noise : as :func:`fit`'s (None: silent)."""
    R = fix_cov(preset)
    blind = log.drop(columns=list(STATE), errors="ignore")
    segment = max(2, round(segment_s / vehicle.dt))
    return fit(blind, blind, vehicle, R, start, epochs=epochs, segment=segment, lr=lr,
               progress=progress, objective="innovations", ahead=ahead,
               receiver_noise=receiver_noise)

