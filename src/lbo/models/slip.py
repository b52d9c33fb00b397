"""A learned side-slip observer with a physical prior: the linear single-track Kalman
filter's side slip, corrected by a recurrent network (the form of Graeber et al. 2019: a model's
beta plus a learned correction).

    beta[k] = beta_lkf[k] + g(the last N rows of [vx, delta, ay_m, r_m, beta_lkf, r_lkf])

The prior (:class:`Prior`, :func:`lbo.filters.lateral.linear_single_track`) knows the car's
published parameters and tyres that stay linear; the network ``g`` (:class:`SlipNet`, a GRU)
learns what the prior misses where they do not. It reads what the car measures (the speed, the
road wheels' steering, the lateral acceleration and the yaw rate) and the prior's estimates of
them, never the side slip's reference. The yaw rate is the prior's.

:class:`SlipObserver` runs a whole log at once (:meth:`SlipObserver.run`) or one row at a time
(:meth:`SlipObserver.stream`); the two agree to float32 rounding. :func:`load` rebuilds one from
an ``lbo.train model=slip_gru`` checkpoint, reading tensors and plain containers only.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from lbo.core.errors import LboError
from lbo.filters.lateral import LateralEstimate, LateralNoise, linear_single_track
from lbo.sim.dynamic import SingleTrack

NAME = "slip_gru"
"""``model.name`` of the learned side-slip observer."""
PARAMETERS = ("hidden", "layers", "prior_gain")
"""Its ``model`` settings besides ``window`` (:class:`SlipNet`'s and the prior's)."""
FEATURES = ("vx", "delta", "ay_m", "r_m", "beta_prior", "r_prior")
"""The channels of each window row, in order: what the car measures and the prior's estimate."""
UNIT = float(np.deg2rad(1.0))
"""The network's output unit (rad): it speaks in degrees, so its loss weighs a degree as one."""


@dataclass(frozen=True)
class Prior:
    """The linear single-track Kalman filter the network corrects: the car's parameters, the
    filter's noise and the sampling period (s)."""

    car: SingleTrack
    noise: LateralNoise
    dt: float

    def run(self, vx: np.ndarray, delta: np.ndarray, y: np.ndarray,
            start: LateralEstimate | None = None) -> LateralEstimate:
        """The prior's estimate of (T,) or (G, T) rows (:func:`linear_single_track`)."""
        return linear_single_track(vx, delta, y, self.car, self.noise, self.dt, start=start)

    def as_dict(self) -> dict[str, Any]:
        """Plain numbers, as a checkpoint holds them."""
        return {"car": asdict(self.car), "noise": asdict(self.noise), "dt": self.dt}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Prior:
        return cls(SingleTrack(**d["car"]), LateralNoise(**d["noise"]), float(d["dt"]))


def features(vx: np.ndarray, delta: np.ndarray, y: np.ndarray, prior: np.ndarray
             ) -> np.ndarray:
    """The window rows (..., T, 6) of :data:`FEATURES`, float32: vx, delta (..., T), the
    measurements y (..., T, 2) [ay_m, r_m] and the prior's estimate x (..., T, 2)."""
    return np.concatenate([np.stack([vx, delta], axis=-1), y, prior], axis=-1
                          ).astype(np.float32)


def windows(rows: np.ndarray, n: int) -> np.ndarray:
    """Each row's window of the last ``n`` rows (T, n, F) of rows (T, F), a read-only view; the
    first rows' windows start with copies of row 0, as a stream's do (:class:`SlipStream`)."""
    padded = np.concatenate([np.repeat(rows[:1], n - 1, axis=0), rows])
    return np.lib.stride_tricks.sliding_window_view(padded, n, axis=0).transpose(0, 2, 1)


class SlipNet(nn.Module):
    """The correction g: a GRU over each window, its last output through a linear layer.

    forward(windows (B, N, 6) of raw :data:`FEATURES`) -> (B,) the correction to the prior's
    beta (rad). The rows are standardised by the training windows' ``mean`` and ``std`` (6,),
    held as buffers so that a checkpoint carries them."""

    mean: torch.Tensor
    std: torch.Tensor

    def __init__(self, hidden: int = 32, layers: int = 1) -> None:
        super().__init__()
        self.gru = nn.GRU(len(FEATURES), hidden, num_layers=layers, batch_first=True)
        self.head = nn.Linear(hidden, 1)
        self.register_buffer("mean", torch.zeros(len(FEATURES)))
        self.register_buffer("std", torch.ones(len(FEATURES)))

    def set_normalisation(self, rows: np.ndarray) -> None:
        """Standardise by the channels of training rows (T, 6) (a constant one by 1)."""
        std = rows.std(axis=0)
        self.mean.copy_(torch.as_tensor(rows.mean(axis=0)))
        self.std.copy_(torch.as_tensor(np.where(std > 0, std, 1.0)))

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        out, _ = self.gru((windows - self.mean) / self.std)
        return self.head(out[:, -1])[:, 0] * UNIT


class SlipObserver:
    """The learned side-slip observer: a :class:`Prior` and the :class:`SlipNet` correcting its
    beta over windows of ``window`` rows."""

    def __init__(self, net: SlipNet, window: int, prior: Prior) -> None:
        self.net, self.window, self.prior = net.eval(), int(window), prior

    def run(self, vx: np.ndarray, delta: np.ndarray, y: np.ndarray, batch: int = 4096,
            prior: LateralEstimate | None = None) -> LateralEstimate:
        """Estimate a whole log: vx, delta (T,), y (T, 2) [ay_m, r_m] -> x (T, 2) [beta, r];
        P (T, 2, 2) is NaN (the network gives no covariance). ``batch``: windows per call;
        ``prior``: the prior's estimate of this log, if made already."""
        if prior is None:
            prior = self.prior.run(vx, delta, y)
        if prior.x.ndim != 2:
            raise LboError("SlipObserver.run takes one log: vx, delta (T,) and y (T, 2)")
        rows = windows(features(vx, delta, y, prior.x), self.window)
        with torch.no_grad():
            fix = np.concatenate([self.net(torch.from_numpy(np.ascontiguousarray(
                rows[i:i + batch]))).numpy() for i in range(0, len(rows), batch)])
        x = prior.x.copy()
        x[:, 0] += fix
        return LateralEstimate(x, np.full_like(prior.P, np.nan))

    def stream(self, correct: Callable[[np.ndarray], float] | None = None) -> SlipStream:
        """A stream of rows from the start of a log (:class:`SlipStream`), its network run in
        PyTorch, or by ``correct`` (rows (N, 6) -> the correction, rad; ONNX Runtime's:
        :func:`lbo.serve.lateral.stream`)."""
        if correct is None:
            def correct(rows: np.ndarray) -> float:
                with torch.no_grad():
                    return float(self.net(torch.from_numpy(rows[None]))[0])
        return SlipStream(self, correct)


class SlipStream:
    """One row at a time, as a car runs: :meth:`step` carries the prior's filter one row and
    corrects its beta over the last ``window`` rows held; ``correct`` runs the network on
    them, (N, 6) -> the correction (rad)."""

    def __init__(self, observer: SlipObserver, correct: Callable[[np.ndarray], float]) -> None:
        self.observer, self.correct = observer, correct
        self.rows = np.zeros((observer.window, len(FEATURES)), np.float32)
        self.last: tuple[float, float] | None = None  # the previous row's vx and delta
        self.estimate: LateralEstimate | None = None  # the prior's at the previous row

    def step(self, vx: float, delta: float, ay: float, r: float) -> np.ndarray:
        """The estimate [beta rad, r rad/s] (2,) at this row, given its speed (m/s), steering
        (rad), lateral acceleration (m/s^2) and yaw rate (rad/s); a NaN measurement is not
        held."""
        y = np.array([ay, r], float)
        if self.last is None:  # the log's first row: the prior's starting state
            prior = self.observer.prior.run(np.array([vx]), np.array([delta]), y[None])
        else:
            prior = self.observer.prior.run(np.array([self.last[0], vx]),
                                            np.array([self.last[1], delta]),
                                            np.stack([np.full(2, np.nan), y]),
                                            start=self.estimate)
        self.estimate = LateralEstimate(prior.x[-1], prior.P[-1])
        row = features(np.array([vx]), np.array([delta]), y[None], prior.x[-1:])
        if self.last is None:
            self.rows[:] = row
        else:  # shifted in place: no new array a row
            self.rows[:-1] = self.rows[1:]
            self.rows[-1] = row[0]
        self.last = (float(vx), float(delta))
        return np.array([prior.x[-1, 0] + self.correct(self.rows), prior.x[-1, 1]])


def read_checkpoint(path: str | os.PathLike, *names: str
                    ) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The hyperparameters and the network's weights (its ``net.`` keys, the prefix off) of an
    ``lbo.train model=<name>`` checkpoint, one of ``names``, read by ``torch.load`` with
    ``weights_only`` (tensors and plain containers: nothing a file names is run); LboError in
    one line for a missing, damaged or foreign file."""
    path = Path(path)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise LboError(f"checkpoint {path}: no such file") from None
    except Exception as e:  # zip, pickle, EOF: not a file lbo wrote
        raise LboError(f"checkpoint {path}: not a checkpoint lbo can read ({type(e).__name__})"
                       ) from None
    hp = ckpt.get("hyper_parameters") if isinstance(ckpt, dict) else None
    if not isinstance(hp, dict) or hp.get("name") not in names:
        raise LboError(f"checkpoint {path}: not a {' or '.join(names)} checkpoint "
                       f"(lbo.train model={names[0]})")
    return hp, {k.removeprefix("net."): v for k, v in ckpt["state_dict"].items()
                if k.startswith("net.")}


def load(path: str | os.PathLike) -> SlipObserver:
    """The observer of an ``lbo.train model=slip_gru`` checkpoint (:func:`read_checkpoint`)."""
    return observer(*read_checkpoint(path, NAME))


def observer(hp: Mapping[str, Any], state: Mapping[str, torch.Tensor]) -> SlipObserver:
    """The observer a checkpoint's hyperparameters and weights describe."""
    net = SlipNet(int(hp["hidden"]), int(hp["layers"]))
    net.load_state_dict(state)
    return SlipObserver(net, int(hp["window"]), Prior.from_dict(hp["prior"]))
