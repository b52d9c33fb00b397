"""Measurement noise drawn on the fly for training windows.

A data set stores one noise draw per step, so a network trained on the stored measurements
soon fits that one draw. Drawing the noise afresh for every window from the true states,
``m = z + alpha * sigma * eps`` with ``eps ~ N(0, I)``, gives a new draw every epoch. The
noise scale ``alpha`` is either fixed (the paper's protocol, alpha = 1) or drawn per window
from a distribution, so one network learns to judge the noise from the window itself.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from lbo.core.checks import number
from lbo.core.errors import LboError
from lbo.sim.logcheck import fix_period

DISTRIBUTIONS = ("fixed", "uniform", "loguniform", "levels")
SOURCES = ("stored", "drawn")


@dataclass(frozen=True)
class AlphaDraw:
    """How the noise scale alpha of each training window is chosen.

    Attributes
    ----------
    distribution : ``fixed`` (always ``alpha``), ``uniform`` or ``loguniform`` on
        ``[low, high]``, or ``levels`` (one of ``levels``, equally likely).
    alpha : the value of ``fixed``.
    low, high : the range of ``uniform`` and ``loguniform`` (``loguniform`` needs low > 0).
    levels : the values of ``levels``.
    """

    distribution: str = "fixed"
    alpha: float = 1.0
    low: float = 0.0
    high: float = 6.5
    levels: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        d = self.distribution
        if d not in DISTRIBUTIONS:
            raise LboError(f"train_noise.distribution: unknown distribution {d!r}; "
                           f"expected one of {', '.join(DISTRIBUTIONS)}")
        if d == "fixed":
            _check_alpha("train_noise.alpha", self.alpha)
        elif d in ("uniform", "loguniform"):
            _check_alpha("train_noise.low", self.low)
            _check_alpha("train_noise.high", self.high)
            if not self.high > self.low:
                raise LboError(f"train_noise.high: expected a range with high > low, got "
                               f"[{self.low}, {self.high}]")
            if d == "loguniform" and self.low <= 0:
                raise LboError(f"train_noise.low: loguniform needs low > 0, got {self.low}")
        else:
            if len(self.levels) == 0:
                raise LboError("train_noise.levels: expected a non-empty list of alpha >= 0, "
                               "got []")
            for a in self.levels:
                _check_alpha("train_noise.levels", a)

    def sample(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """(n,) float64 alpha values, drawn with ``generator``, on its device."""
        dev = generator.device
        if self.distribution == "fixed":
            return torch.full((n,), float(self.alpha), dtype=torch.float64, device=dev)
        r = torch.rand(n, generator=generator, dtype=torch.float64, device=dev)
        if self.distribution == "uniform":
            return self.low + (self.high - self.low) * r
        if self.distribution == "loguniform":
            lo, hi = np.log(self.low), np.log(self.high)
            return torch.exp(lo + (hi - lo) * r)
        levels = torch.tensor(self.levels, dtype=torch.float64, device=dev)
        return levels[(r * len(levels)).long().clamp_max(len(levels) - 1)]

    @property
    def bounds(self) -> tuple[float, float]:
        """The smallest and largest alpha this draw gives."""
        if self.distribution == "fixed":
            return float(self.alpha), float(self.alpha)
        if self.distribution == "levels":
            return float(min(self.levels)), float(max(self.levels))
        return float(self.low), float(self.high)

    @classmethod
    def from_cfg(cls, cfg) -> AlphaDraw:
        """From the Hydra group ``train_noise``."""
        levels = cfg.get("levels") or ()
        if isinstance(levels, (str, bytes)) or not isinstance(levels, Sequence):
            raise LboError(f"train_noise.levels: expected a list of alpha >= 0, got {levels!r}")
        return cls(distribution=str(cfg.get("distribution", "fixed")),
                   alpha=cfg.get("alpha", 1.0), low=cfg.get("low", 0.0),
                   high=cfg.get("high", 6.5), levels=tuple(levels))


def _check_alpha(field: str, value) -> None:
    number(value, field, low=0.0, form="a noise scale alpha >= 0")


def loss_weights(alpha: torch.Tensor, offset: float | None) -> torch.Tensor:
    """Per-window loss weights ``1 / (alpha + offset)^2`` (ones when ``offset`` is None).

    A window's squared error grows as alpha^2, so unweighted, the noisiest windows would
    dominate the loss and the low-noise ones would hardly be learned.
    """
    if offset is None:
        return torch.ones_like(alpha)
    return 1.0 / (alpha + offset) ** 2


def noisy_measurements(z: torch.Tensor, alpha: torch.Tensor, sigma: torch.Tensor,
                       generator: torch.Generator,
                       drift: tuple[float, float] | None = None) -> torch.Tensor:
    """Measurements of the true states ``z`` (B, N, 3) at noise scales ``alpha`` (B,).

    ``sigma`` (3,) are the measurement sigmas at alpha=1. ``drift`` = (sigma (m), tau (steps))
    adds a stationary Gauss-Markov GNSS drift on x and y (:func:`gauss_markov`), scaled by
    alpha like the white noise. Returns (B, N, 3), heading wrapped to (-pi, pi] like the stored
    measurements.
    """
    from lbo.models.poses import wrap_heading

    eps = torch.randn(z.shape, generator=generator, dtype=z.dtype, device=z.device)
    noise = sigma * eps
    if drift is not None and drift[0] > 0:
        b = gauss_markov(z.shape[:2], drift[1], generator, z.dtype, z.device) * drift[0]
        noise = noise + torch.cat([b, torch.zeros_like(b[..., :1])], -1)
    m = z + alpha[:, None, None] * noise
    return wrap_heading(m)


def gauss_markov(shape: tuple[int, int], tau: float, generator: torch.Generator,
                 dtype: torch.dtype = torch.float64,
                 device: torch.device | str = "cpu") -> torch.Tensor:
    """(B, N, 2) unit-variance stationary first-order Gauss-Markov sequences along N, time
    constant ``tau`` steps: ``b_k = sum_j phi^(k-j) e_j`` with ``phi = exp(-1 / tau)``, computed
    for the whole window at once as one matrix product (no loop over steps)."""
    n = shape[1]
    phi = math.exp(-1.0 / tau)
    eps = torch.randn((*shape, 2), generator=generator, dtype=dtype, device=device)
    scale = torch.full((n,), math.sqrt(1.0 - phi**2), dtype=dtype, device=device)
    scale[0] = 1.0  # b_0 ~ N(0, 1): stationary from the first step
    k = torch.arange(n, device=device)
    lag = (k[:, None] - k[None, :]).to(dtype)
    kernel = torch.where(lag >= 0, phi ** lag.clamp_min(0), torch.zeros_like(lag))
    return torch.einsum("kj,bjc->bkc", kernel * scale, eps)


def fix_periods(rates: Sequence[float] | None, dt: float,
                field: str = "fix_rates") -> tuple[int, ...]:
    """Fix rates (Hz) -> periods in steps of ``dt`` (a rate of 1/dt or more is every step).

    Raises LboError naming ``field`` unless ``rates`` is None or a list of numbers > 0.
    """
    if rates is None:
        return ()
    try:
        values = [float(r) for r in rates]
    except (TypeError, ValueError):
        values = []
    if not values or not all(np.isfinite(r) and r > 0 for r in values):
        raise LboError(f"{field}: expected null or a list of fix rates in Hz > 0 "
                       f"(e.g. [50, 10, 5, 1]), got {rates!r}")
    return tuple(fix_period(r, dt) for r in values)


def draw_fixes(n: int, window: int, periods: Sequence[int], generator: torch.Generator,
             device: torch.device | str = "cpu") -> torch.Tensor:
    """Which steps of ``n`` windows of ``window`` steps hold a position fix: (n, window) bool.

    Each window takes one of ``periods`` (steps between fixes) at random. Half the windows
    get fixes every ``period`` steps from a random phase, the other half at random steps
    with probability ``1 / period``, so that irregular fixes are seen too. A window left
    without any fix gets one at a random step.
    """
    p = torch.as_tensor(periods, device=device)[
        torch.randint(len(periods), (n,), generator=generator, device=device)]
    k = torch.arange(window, device=device)
    phase = (torch.rand(n, generator=generator, device=device) * p).long()
    regular = (k[None, :] + phase[:, None]) % p[:, None] == 0
    random = torch.rand((n, window), generator=generator, device=device) < 1.0 / p[:, None]
    mask = torch.where(torch.rand(n, generator=generator, device=device)[:, None] < 0.5,
                       regular, random)
    empty = ~mask.any(1)
    spot = torch.randint(window, (n,), generator=generator, device=device)
    mask[empty, spot[empty]] = True
    return mask
