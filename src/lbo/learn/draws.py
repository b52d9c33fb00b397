"""Measurement noise, and a receiver's channels, drawn on the fly for training windows.

A data set stores one noise draw per step, so a network trained on the stored measurements
soon fits that one draw. Drawing the noise afresh for every window from the true states,
``m = z + alpha * sigma * eps`` with ``eps ~ N(0, I)``, gives a new draw every epoch. The
noise scale ``alpha`` is either fixed (the paper's protocol, alpha = 1) or drawn per window
from a distribution, so one network learns to judge the noise from the window itself.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import KW_ONLY, dataclass
from typing import Any, TypedDict

import numpy as np
import torch

from lbo.core.checks import integer, number
from lbo.core.errors import LboError
from lbo.logs.checks import fix_period
from lbo.sim.noise import check_alpha

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
    changes : for sequences trained carried (``tbptt``): how many times the level changes
        along each one (:meth:`along`), so that a filter's noise model must track the noise
        rather than fix it at a sequence's start; 0: one level per sequence.
    """

    distribution: str = "fixed"
    _: KW_ONLY
    alpha: float = 1.0
    low: float = 0.0
    high: float = 6.5
    levels: tuple[float, ...] = ()
    changes: int = 0

    def __post_init__(self) -> None:
        d = self.distribution
        if d not in DISTRIBUTIONS:
            raise LboError(f"train_noise.distribution: unknown distribution {d!r}; "
                           f"expected one of {', '.join(DISTRIBUTIONS)}")
        if d == "fixed":
            check_alpha(self.alpha, "train_noise.alpha")
        elif d in ("uniform", "loguniform"):
            check_alpha(self.low, "train_noise.low")
            check_alpha(self.high, "train_noise.high")
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
                check_alpha(a, "train_noise.levels")
        integer(self.changes, "train_noise.changes", 0,
                form="an integer >= 0 (level changes along a sequence)")

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

    def along(self, n: int, steps: int, generator: torch.Generator) -> torch.Tensor:
        """(n, steps) float64 alpha per step of n sequences: :attr:`changes` + 1 levels each,
        drawn as :meth:`sample` draws them, which change at :attr:`changes` steps drawn
        uniformly from 1 to steps - 1 (two may fall on one step); the first level holds from
        the first step."""
        dev = generator.device
        levels = self.sample(n * (self.changes + 1), generator).reshape(n, self.changes + 1)
        cuts = torch.randint(1, max(steps, 2), (n, self.changes), generator=generator,
                             device=dev)
        t = torch.arange(steps, device=dev)
        segment = (t[None, None, :] >= cuts[:, :, None]).sum(1)  # (n, steps): cuts passed
        return levels.gather(1, segment)

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
                   high=cfg.get("high", 6.5), levels=tuple(levels),
                   changes=cfg.get("changes", 0))


def loss_weights(alpha: torch.Tensor, offset: float | None) -> torch.Tensor:
    """Loss weights ``1 / (alpha + offset)^2`` of alphas (B,) per window or (B, N) per step
    (ones when ``offset`` is None).

    A window's squared error grows as alpha^2, so unweighted, the noisiest windows would
    dominate the loss and the low-noise ones would hardly be learned.
    """
    if offset is None:
        return torch.ones_like(alpha)
    return 1.0 / (alpha + offset) ** 2


def noisy_measurements(z: torch.Tensor, alpha: torch.Tensor, sigma: torch.Tensor,
                       generator: torch.Generator,
                       drift: tuple[float, float] | None = None) -> torch.Tensor:
    """Measurements of the true states ``z`` (B, N, 3) at noise scales ``alpha`` (B,), or
    (B, N) per step.

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
    m = z + (alpha[:, None, None] if alpha.dim() == 1 else alpha[..., None]) * noise
    return wrap_heading(m)


class TensorOptions(TypedDict):
    """The dtype and device of the tensors a draw makes: ``torch.randn(..., **opts)``."""

    dtype: torch.dtype
    device: torch.device


def gauss_markov(shape: tuple[int, ...], tau: float, generator: torch.Generator,
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


@dataclass(frozen=True)
class OutageDraw:
    """GNSS outages drawn into training windows, as their noise is drawn: a ``share`` of the
    windows loses every fix in one stretch of 1 to ``max_steps`` steps (at most the window
    less one), so that a learned filter sees outages in training as it meets them in a log.

    Half of those stretches run to the window's last step (the estimate is made inside the
    outage, from dead reckoning), the other half lie anywhere in it (the recovery after one).
    A window left without a fix keeps the one just before its stretch (or just after)."""

    share: float = 0.0
    max_steps: int = 500

    def __post_init__(self) -> None:
        number(self.share, "train_outages.share", low=0.0, high=1.0, form="a share in [0, 1]")
        integer(self.max_steps, "OutageDraw.max_steps", 1)

    @classmethod
    def from_cfg(cls, cfg: Any, dt: float, fixes: bool) -> OutageDraw | None:
        """The draw ``train_outages`` (``share``, ``max_s`` seconds) asks for at steps of
        ``dt``, or None for none (share 0); ``fixes``: whether the training drops fixes
        (``fix_rates``), which a net that takes an outage needs. One line naming the field."""
        unknown = sorted(set(cfg) - {"share", "max_s"})
        if unknown:
            raise LboError(f"train_outages.{unknown[0]}: not a field; accepted: share, max_s")
        seconds = number(cfg.get("max_s", 10.0), "train_outages.max_s", low=0.0,
                         low_open=True, form="a number of seconds > 0")
        draw = cls(share=cfg.get("share", 0.0), max_steps=max(1, round(seconds / dt)))
        if draw.share == 0:
            return None
        if not fixes:
            raise LboError(f"train_outages.share: outages need a net that reads the fix channel "
                           f"(fix_rates, e.g. experiment=robust), got {draw.share:g} with "
                           "fix_rates=null")
        return draw

    def cut(self, fix: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """``fix`` (B, N) bool (the steps that hold a fix) with the drawn outages taken out;
        every window keeps at least one fix. Draws nothing when ``share`` is 0, so a run
        without outages keeps its stream of draws."""
        if self.share <= 0:
            return fix
        b, n = fix.shape
        dev = fix.device
        hit = torch.rand(b, generator=generator, device=dev) < self.share
        longest = max(1, min(self.max_steps, n - 1))
        length = 1 + (torch.rand(b, generator=generator, device=dev) * longest).long()
        latest = n - length  # the first step of a stretch that ends at the window's last
        anywhere = (torch.rand(b, generator=generator, device=dev) * (latest + 1)).long()
        at_end = torch.rand(b, generator=generator, device=dev) < 0.5
        start = torch.where(at_end, latest, anywhere)
        k = torch.arange(n, device=dev)
        inside = hit[:, None] & (k >= start[:, None]) & (k < (start + length)[:, None])
        kept = fix & ~inside
        empty = ~kept.any(1)
        beside = torch.where(start > 0, start - 1, (start + length).clamp_max(n - 1))
        kept[empty, beside[empty]] = True
        return kept


@dataclass(frozen=True)
class ReceiverDraw:
    """A simulated receiver and gyro drawn afresh for every training window (as
    :func:`lbo.sim.receiver.sense` draws them for a log), for nets that read a receiver.

    spec : the receiver's channels (:class:`lbo.sim.receiver.ReceiverSpec`); its position
        and velocity come at the fix rows :func:`draw_fixes` picks (the window's rate), each
        channel late by its latency, with white noise and Gauss-Markov drift
        scaled by the window's alpha, and a reported accuracy that tracks the error's scale.
    heading_share : the share of windows whose fixes also carry a heading ``psi_m`` (a dual
        antenna, or the paper's sensor), of 1-sigma ``alpha * heading_sigma``.
    gyro_share : the share of windows with a gyro (the rest have none, as the paper's logs).
    dt, wheelbase : the sampling period (s) and the course's turn rate ``V tan(delta) / L``.
    """

    spec: Any
    _: KW_ONLY
    heading_share: float = 0.25
    gyro_share: float = 0.75
    heading_sigma: float = 0.01
    dt: float = 0.02
    wheelbase: float = 2.7

    def __post_init__(self) -> None:
        for name in ("heading_share", "gyro_share"):
            number(getattr(self, name), f"receiver_training.{name}", low=0.0, high=1.0,
                   form="a share in [0, 1]")

    def windows(self, z: torch.Tensor, u: torch.Tensor, alpha: torch.Tensor,
                fix: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Receiver windows (B, N, 11) (:data:`lbo.models.receiver_window.COLUMNS`) of true
        poses z (B, N, 3) and inputs u (B, N, 2) at noise scales alpha (B,), fixes at the
        rows ``fix`` (B, N) bool. Vectorised over windows and steps."""
        from lbo.filters import measure
        from lbo.models.poses import wrap_angle_torch
        from lbo.sim.receiver import SIGMA_FLOOR

        spec, dt = self.spec, self.dt
        b, n = fix.shape
        opts: TensorOptions = {"dtype": z.dtype, "device": z.device}

        def late(a: torch.Tensor, latency: float) -> torch.Tensor:
            # a (B, N, ...) as it was ``latency`` s before each row, interpolated; the first
            # rows take the window's first value (as the log's first rows do in sense())
            f = (torch.arange(n, **opts) - latency / dt).clamp_min(0.0)
            i0 = f.floor().long()
            i1 = (i0 + 1).clamp_max(n - 1)
            w = (f - i0).reshape((n,) + (1,) * (a.ndim - 2))
            return a[:, i0] * (1 - w) + a[:, i1] * w

        def error(ch: Any, width: int) -> torch.Tensor:
            e = ch.white * torch.randn((b, n, 2), generator=generator, **opts)
            if ch.drift > 0:
                e = e + ch.drift * gauss_markov((b, n), ch.tau / dt, generator, **opts)
            return e[..., :width]

        def spread() -> torch.Tensor:
            s = spec.reported_spread
            return torch.exp(s * torch.randn((b, n), generator=generator, **opts) - 0.5 * s * s)

        a = alpha[:, None]
        nan = torch.full((b, n), float("nan"), **opts)
        pos = late(z[..., :2], spec.position.latency) + a[..., None] * error(spec.position, 2)
        heading = torch.rand(b, generator=generator, **opts) < self.heading_share
        psi_err = self.heading_sigma * torch.randn((b, n), generator=generator, **opts)
        psi = wrap_angle_torch(late(z[..., 2], spec.position.latency) + a * psi_err)
        told = (a * spec.position.sigma * spread()).clamp_min(SIGMA_FLOOR)
        told_psi = (a * self.heading_sigma * spread()).clamp_min(SIGMA_FLOOR)
        held_psi = fix & heading[:, None]
        v = late(u[..., :1] * torch.stack([torch.cos(z[..., 2]), torch.sin(z[..., 2])], -1),
                 spec.velocity.latency) + a[..., None] * error(spec.velocity, 2)
        sv = torch.full((b, n), spec.velocity.sigma, **opts) * a
        sv = sv.clamp_min(SIGMA_FLOOR)
        speed = torch.hypot(v[..., 0], v[..., 1])
        moving = fix & (speed >= measure.COURSE_MIN_SPEED) & (speed >= measure.COURSE_MIN_SNR * sv)
        course = torch.atan2(v[..., 1], v[..., 0]) + torch.where(u[..., 0] < 0, math.pi, 0.0)
        turn = u[..., 0] * torch.tan(u[..., 1]) / self.wheelbase
        s_course = torch.hypot(sv, measure.COURSE_LEVER * turn) / speed.clamp_min(1e-9)
        # the gyro: the yaw rate over each step (the last repeated), a bias that starts at
        # N(0, gyro_bias^2) and walks, and its own noise; alpha scales the receiver only
        yaw = wrap_angle_torch(torch.diff(z[..., 2], dim=1)) / dt
        yaw = torch.cat([yaw, yaw[:, -1:]], 1)
        walk = spec.gyro_walk * math.sqrt(dt) * torch.randn((b, n), generator=generator, **opts)
        walk[:, 0] = spec.gyro_bias * torch.randn(b, generator=generator, **opts)
        rate = late(yaw, spec.gyro.latency) + walk.cumsum(1) + error(spec.gyro, 1)[..., 0]
        period = (max(1, round(1.0 / (spec.gyro.rate * dt))) if spec.gyro.rate is not None
                  else 1)
        phase = torch.randint(period, (b, 1), generator=generator, device=z.device)
        has_gyro = torch.rand(b, generator=generator, **opts) < self.gyro_share
        gyro_rows = ((torch.arange(n, device=z.device) + phase) % period == 0) & has_gyro[:, None]
        cols = [torch.where(fix, pos[..., 0], nan), torch.where(fix, pos[..., 1], nan),
                torch.where(held_psi, psi, nan), torch.where(fix, told, nan),
                torch.where(fix, told, nan), torch.where(held_psi, told_psi, nan),
                torch.where(moving, wrap_angle_torch(course), nan),
                torch.where(moving, s_course, nan), u[..., 0], u[..., 1],
                torch.where(gyro_rows, rate, nan)]
        return torch.stack(cols, -1)
