"""The side-slip observer's training sets: the real run's spans, or simulated runs of its kind.

- ``data=sideslip``: the run lbo ships (:mod:`lbo.sim.sideslip`), its first 60% to train and
  the next 20% to pick the epoch; the prior's noise read off the training span.
- ``data=sideslip_sim``: runs simulated by :mod:`lbo.sim.lateral` (cars drawn around the
  published one), ``data.train`` runs to train and ``data.val`` others to pick the epoch; the
  prior's noise read off the simulated training runs. Nothing of the real run is read.

Either way the prior is told the published car (:data:`lbo.sim.sideslip.CAR`), and a net
fine-tuned from a checkpoint (``init_from``) keeps that checkpoint's prior: its windows are
made of that filter's estimates. Each window's target is the reference beta less the prior's.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from lbo.filters.lateral import LateralEstimate, LateralNoise
from lbo.models.slip import Prior, features, windows
from lbo.sim import lateral, sideslip

REAL = "sideslip"
SIMULATED = "sideslip_sim"
DATA = (REAL, SIMULATED)
"""The ``data.name`` the side-slip observer learns on."""


@dataclass(frozen=True)
class Sets:
    """Training and validation inputs and their targets (rad), and the prior: windows
    (W, N, 6) float32 and targets (W,) for the side-slip network (:func:`sets`), or sequences
    (S, T, 5) and targets (S, T) for the learned filter (:func:`sequences`)."""

    train: tuple[np.ndarray, np.ndarray]
    val: tuple[np.ndarray, np.ndarray]
    prior: Prior


def noise_of(logs: Sequence[pd.DataFrame], gain: float) -> LateralNoise:
    """The prior's noise read off training logs (:meth:`LateralNoise.of`), averaged over them."""
    each = [LateralNoise.of(*sideslip.observed(log), process_gain=gain) for log in logs]
    return LateralNoise(*(float(np.mean([getattr(n, k) for n in each]))
                          for k in ("delta", "ay", "r")))


@functools.lru_cache(maxsize=1)
def real_spans() -> dict[str, pd.DataFrame]:
    """The shipped run's spans (:func:`lbo.sim.sideslip.split`), read once a process."""
    return sideslip.split(sideslip.example())


@functools.lru_cache(maxsize=4)
def real_estimates(prior: Prior) -> dict[str, LateralEstimate]:
    """The prior's estimate of each real span, each a log of its own (the filter starting
    afresh): 4 s of filtering, made once a process for each prior."""
    return {k: prior.run(*sideslip.observed(s)) for k, s in real_spans().items()}


def settings(data: DictConfig) -> lateral.Settings:
    """``data=sideslip_sim``'s simulation settings, checked (one line naming the field)."""
    d = OmegaConf.to_container(data, resolve=True)
    assert isinstance(d, dict)
    given: dict[str, Any] = {k: d[k] for k in ("duration", "spread", "sigma_ay", "sigma_r")}
    given |= {k: tuple(d[k]) for k in ("mu", "speed", "demand")}
    return lateral.Settings(n=int(d["train"]) + int(d["val"]), **given)


@functools.lru_cache(maxsize=2)
def _simulated(s: lateral.Settings, seed: int) -> tuple[pd.DataFrame, ...]:
    return tuple(lateral.simulate(s, seed))


def logs(data: DictConfig) -> tuple[list[pd.DataFrame], list[pd.DataFrame]]:
    """The training and validation logs ``data`` names (``data.name`` one of :data:`DATA`):
    the real run's train and validation spans, or ``data.train`` and ``data.val`` simulated
    runs."""
    if data.name == REAL:
        spans = real_spans()
        return [spans["train"]], [spans["val"]]
    runs = _simulated(settings(data), int(data.seed))
    return list(runs[:int(data.train)]), list(runs[int(data.train):])


def _prior(train: list[pd.DataFrame], gain: float, start: Prior | None) -> Prior:
    """``start`` (a fine-tuned checkpoint's prior, kept), else the published car's with the
    noise of the training logs times ``gain``."""
    return start or Prior(sideslip.CAR, noise_of(train, gain), sideslip.DT)


def sets(data: DictConfig, window: int, gain: float, start: Prior | None = None) -> Sets:
    """The windows ``data`` names for windows of ``window`` rows (every ``data.stride``-th
    row's of simulated runs), the prior's noise ``gain``; ``start``: the prior of a checkpoint
    fine-tuned from, kept."""
    train, val = logs(data)
    prior = _prior(train, gain, start)
    if data.name == REAL:
        est = real_estimates(prior)
        return Sets(_windows(train, est["train"], window, 1),
                    _windows(val, est["val"], window, 1), prior)
    stride = int(data.stride)
    return Sets(_windows(train, _estimate(prior, train), window, stride),
                _windows(val, _estimate(prior, val), window, stride), prior)


def sequences(data: DictConfig, length: int, gain: float, start: Prior | None = None) -> Sets:
    """The learned filter's sequences: the training and the validation logs each cut into
    pieces of ``length`` rows (S, length, 5) ``[vx, delta, ay_m, r_m, beta]``, each starting
    half a piece after the one before (a filter started afresh on each); the targets are
    their beta columns (S, length). The prior as in :func:`sets`."""
    train, val = logs(data)
    prior = _prior(train, gain, start)
    step = max(1, length // 2)

    def pieces(logs: list[pd.DataFrame]) -> tuple[np.ndarray, np.ndarray]:
        rows = np.ascontiguousarray(np.concatenate([
            np.lib.stride_tricks.sliding_window_view(columns(log), length, axis=0)
            .transpose(0, 2, 1)[::step] for log in logs]))
        return rows, rows[..., 4]

    return Sets(pieces(train), pieces(val), prior)


def columns(log: pd.DataFrame) -> np.ndarray:
    """(T, 5) ``[vx, delta, ay_m, r_m, beta]`` of a log, float64: what the filter reads, and
    the reference it is scored by last."""
    vx, delta, y = sideslip.observed(log)
    return np.column_stack([vx, delta, y, log["beta"].to_numpy(float)])


def _estimate(prior: Prior, logs: list[pd.DataFrame]) -> LateralEstimate:
    """The prior over logs of one length, all at once: x (G, T, 2)."""
    vx, delta, y = (np.stack(a) for a in zip(*(sideslip.observed(log) for log in logs)))
    return prior.run(vx, delta, y)


def _windows(logs: list[pd.DataFrame], est: LateralEstimate, window: int, stride: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """Every ``stride``-th row's window (W, N, 6) of each log and its target (W,): beta's
    reference less the prior's estimate ``est`` ((T, 2) for one log, (G, T, 2) for G)."""
    x = est.x if est.x.ndim == 3 else est.x[None]
    w, target = [], []
    for log, xg in zip(logs, x):
        vx, delta, y = sideslip.observed(log)
        rows = features(vx, delta, y, xg)
        w.append(windows(rows, window)[::stride])
        target.append((log["beta"].to_numpy(float) - xg[:, 0])[::stride])
    return (np.ascontiguousarray(np.concatenate(w)),
            np.concatenate(target).astype(np.float32))
