"""The envelope of a learned observer: the range of inputs it was trained on, and the rows of a
log that lie outside it.

A network has no model to fall back on where its training data ends. A CNN trained on 1-25
m/s, run at 60 m/s, returns estimates several times worse than an EKF's, and nothing in them
says so. Every checkpoint that ``lbo.train`` writes therefore stores the envelope of its
training inputs (``meta["envelope"]``), and :class:`~lbo.serve.observer.Observer` checks each
row of a log against it:

- ``speed`` and ``steering``: the logged V (m/s) and delta (rad), row by row;
- ``fix_period``: the mean number of steps between position fixes over the last N rows (the
  observer's window), judged from the first full window on;
- ``alpha``: the measurement-noise scale, estimated from the fixes themselves (see
  :func:`alpha_estimates`); None in an envelope trained on real logs, whose noise scale is
  unknown, and then not checked.

Each bound has a slack (:data:`SLACK`, :data:`ALPHA_SLACK`, :data:`PERIOD_SLACK`) so that a
log at the edge of the training range is not flagged by rounding or by the scatter of the
noise estimate.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, NamedTuple, TypedDict

import numpy as np

from lbo.core.errors import LboError

if TYPE_CHECKING:
    from lbo.sim.noise import Noise
    from lbo.sim.vehicle import Vehicle

FIELDS = ("speed", "steering", "alpha", "fix_period")
"""What an envelope bounds, in the order lines and reasons name them."""

UNITS = {"speed": "m/s", "steering": "rad", "alpha": "", "fix_period": "steps"}

SLACK = 0.05
"""Speed and steering: a row is outside when it is beyond a bound by more than this fraction of
the trained range (plus :data:`_FLOOR`)."""

_FLOOR = {"speed": 0.1, "steering": 0.005}

ALPHA_SLACK = 0.3
"""Relative slack on the estimated alpha. Over :data:`ALPHA_TRIPLES` triples of white noise
the estimate scatters by about 7% (one sigma), so 30% flags a true excursion, not chance."""

ALPHA_TRIPLES = 100
"""Fix triples (consecutive, equally spaced fixes) per alpha estimate."""

ALPHA_MIN_TRIPLES = 50
"""Fewer triples than this so far: alpha is not judged yet."""

PERIOD_SLACK = 1.5
"""A mean fix spacing more than this factor beyond the trained spacings is outside."""

MODES = ("warn", "mark", "off")
"""What an observer does with rows outside its envelope: ``warn`` (say so, estimates stay
valid), ``mark`` (say so, and set those rows' ``valid`` to false) or ``off`` (no check)."""


class EnvelopeWarning(UserWarning):
    """A learned observer was given samples outside the envelope of its training inputs."""


class EnvelopeTerms(TypedDict):
    """What :meth:`Envelope.check` and :meth:`Envelope.stream` read besides the log: the
    sampling period (s), the wheelbase (m), the measurement sigma (m) and the window (steps)."""

    dt: float
    wheelbase: float
    sigma: float
    window: int


def observer_terms(vehicle: Vehicle, noise: Noise, window: int) -> EnvelopeTerms:
    """The :class:`EnvelopeTerms` of an observer of ``window`` samples on ``vehicle`` with
    ``noise`` (its measurement sigma: the RMS of x's and y's at alpha = 1)."""
    sx, sy = noise.measurement_sigma[:2]
    return {"dt": vehicle.dt, "wheelbase": vehicle.wheelbase,
            "sigma": float(np.sqrt((sx ** 2 + sy ** 2) / 2)), "window": window}


def check_mode(mode: Any) -> str:
    """Return ``mode`` if it is one of :data:`MODES`, else one line naming ``envelope``."""
    if mode not in MODES:
        raise LboError(f"envelope: expected one of {', '.join(MODES)}, got {mode!r}")
    return mode


@dataclass(frozen=True, kw_only=True)
class Envelope:
    """The range of inputs a learned observer was trained on.

    Attributes
    ----------
    speed : (low, high) of the training rows' V (m/s).
    steering : (low, high) of the training rows' delta (rad).
    alpha : (low, high) of the training noise scale, or None where it is unknown.
    fix_period : (low, high) steps between position fixes in the training windows.
    """

    speed: tuple[float, float]
    steering: tuple[float, float]
    alpha: tuple[float, float] | None
    fix_period: tuple[float, float]

    def __post_init__(self) -> None:
        for field in FIELDS:
            value = getattr(self, field)
            if value is None and field == "alpha":
                continue
            ok = (isinstance(value, (tuple, list)) and len(value) == 2
                  and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                          and math.isfinite(v) for v in value) and value[0] <= value[1])
            if not ok:
                raise LboError(f"envelope.{field}: expected [low, high], two finite numbers "
                               f"with low <= high, got {value!r}")
            object.__setattr__(self, field, (float(value[0]), float(value[1])))

    @classmethod
    def from_training(cls, u: np.ndarray, alpha: tuple[float, float] | None,
                      fix_period: tuple[float, float]) -> Envelope:
        """The envelope of training rows ``u`` (R, 2) ``[V, delta]`` (NaN rows ignored)."""
        u = np.asarray(u, dtype=float)
        u = u[np.isfinite(u).all(1)]
        if not len(u):
            raise LboError("envelope: no finite training input to take the envelope of")
        return cls(speed=(float(u[:, 0].min()), float(u[:, 0].max())),
                   steering=(float(u[:, 1].min()), float(u[:, 1].max())), alpha=alpha,
                   fix_period=fix_period)

    def union(self, other: Envelope) -> Envelope:
        """The envelope of both training sets; alpha where either knows it (a real log's
        is unknown, None)."""
        def both(a, b):
            return None if a is None or b is None else (min(a[0], b[0]), max(a[1], b[1]))

        alpha = both(self.alpha, other.alpha) or self.alpha or other.alpha
        return Envelope(speed=both(self.speed, other.speed),
                        steering=both(self.steering, other.steering), alpha=alpha,
                        fix_period=both(self.fix_period, other.fix_period))

    def to_dict(self) -> dict[str, Any]:
        """Plain lists, as a checkpoint (``weights_only``) and a JSON sidecar store them."""
        return {k: (list(v) if v is not None else None) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: Any) -> Envelope:
        """The inverse of :meth:`to_dict`; one line naming the field for a bad entry."""
        if not isinstance(d, dict) or set(d) != set(FIELDS):
            raise LboError(f"envelope: expected the keys {', '.join(FIELDS)}, got {d!r}")
        return cls(**{k: (tuple(d[k]) if isinstance(d[k], (list, tuple)) else d[k])
                      for k in FIELDS})

    def bounds(self, field: str) -> tuple[float, float]:
        """The (low, high) outside of which a row is flagged, slack included."""
        lo, hi = getattr(self, field)
        if field == "alpha":
            return lo / (1 + ALPHA_SLACK) - 0.05, hi * (1 + ALPHA_SLACK) + 0.05
        if field == "fix_period":
            return lo / PERIOD_SLACK, hi * PERIOD_SLACK
        s = SLACK * (hi - lo) + _FLOOR[field]
        return lo - s, hi + s

    def describe(self, field: str) -> str:
        """``"speed 1..25 m/s"``: a field's trained range, for messages."""
        lo, hi = getattr(self, field)
        return f"{field} {lo:.3g}..{hi:.3g}{(' ' + UNITS[field]) if UNITS[field] else ''}"

    def check(self, m: np.ndarray, u: np.ndarray, *, dt: float, wheelbase: float,
              sigma: float, window: int) -> EnvelopeCheck:
        """Which rows of a log lie outside the envelope.

        Parameters
        ----------
        m : (T, 3) measurements, a row of NaN where there is no fix.
        u : (T, 2) inputs ``[V, delta]``.
        dt, wheelbase : the observer's step (s) and wheelbase (m), for the motion between fixes.
        sigma : the measurement sigma of x and y at alpha = 1 (m).
        window : N; the fix spacing is the mean over the last N rows.

        Returns
        -------
        :class:`EnvelopeCheck`: per-field (T,) masks of the rows outside, and the estimates.
        """
        m, u = np.asarray(m, dtype=float), np.asarray(u, dtype=float)
        t = len(u)
        fix = np.isfinite(m[:, :2]).all(1)
        spacing = fix_spacing(fix, window)
        alpha_hat = (alpha_estimates(m, u, dt, wheelbase, sigma) if self.alpha is not None
                     else np.full(t, np.nan))
        masks = {}
        for field, value in (("speed", u[:, 0]), ("steering", u[:, 1]), ("alpha", alpha_hat),
                             ("fix_period", spacing)):
            if field == "alpha" and self.alpha is None:
                masks[field] = np.zeros(t, bool)
                continue
            lo, hi = self.bounds(field)
            with np.errstate(invalid="ignore"):
                masks[field] = (value < lo) | (value > hi)  # NaN: not judged
        return EnvelopeCheck(**masks, alpha_hat=alpha_hat, fix_spacing=spacing)

    def stream(self, *, dt: float, wheelbase: float, sigma: float,
               window: int) -> EnvelopeStream:
        """The same check one sample at a time (:class:`EnvelopeStream`)."""
        return EnvelopeStream(self, dt=dt, wheelbase=wheelbase, sigma=sigma, window=window)


class EnvelopeCheck(NamedTuple):
    """The rows of a log outside an envelope: each field (T,) bool, True where outside."""

    speed: np.ndarray
    steering: np.ndarray
    alpha: np.ndarray
    fix_period: np.ndarray
    alpha_hat: np.ndarray
    """(T,) the estimated noise scale at each row, NaN where not judged yet."""
    fix_spacing: np.ndarray
    """(T,) the mean steps between fixes over the last N rows, NaN before a full window."""

    @property
    def outside(self) -> np.ndarray:
        """(T,) rows outside in any field."""
        return self.speed | self.steering | self.alpha | self.fix_period

    def reasons(self) -> np.ndarray:
        """(T,) object array: the fields a row is outside in, ``"speed,alpha"``, or ``""``."""
        out = np.full(len(self.speed), "", dtype=object)
        for field in FIELDS:
            mask = getattr(self, field)
            out[mask] = np.where(out[mask] == "", field, out[mask] + "," + field)
        return out

    def summary(self, envelope: Envelope, u: np.ndarray) -> list[str]:
        """One line per field with rows outside: how many, where the log went, the range."""
        seen = {"speed": u[:, 0], "steering": u[:, 1], "alpha": self.alpha_hat,
                "fix_period": self.fix_spacing}
        lines = []
        for field in FIELDS:
            mask = getattr(self, field)
            if mask.any():
                v = seen[field][mask]
                lines.append(f"{int(mask.sum())} of {len(mask)} rows outside the trained "
                             f"{envelope.describe(field)} (this log: {np.nanmin(v):.3g}.."
                             f"{np.nanmax(v):.3g}; first at row {int(np.flatnonzero(mask)[0])})")
        return lines


def fix_spacing(fix: np.ndarray, window: int) -> np.ndarray:
    """(T,) mean steps between fixes over the last ``window`` rows: ``window / fixes`` there,
    inf with no fix, NaN before the first full window. ``fix`` (T,) bool."""
    t = len(fix)
    c = np.concatenate([[0], np.cumsum(fix)])
    k = np.arange(t)
    count = c[k + 1] - c[np.maximum(k + 1 - window, 0)]
    with np.errstate(divide="ignore"):
        out = window / count.astype(float)
    out[k < window - 1] = np.nan
    return out


def _triple_values(p: np.ndarray, v: np.ndarray, k0, k1, k2, dt: float,
                   wheelbase: float) -> np.ndarray:
    """Per-axis noise variance from fix triples (F,) at steps k0 < k1 < k2, equally spaced:
    positions ``p`` (3, F, 2), speeds ``v`` (3, F) and the steering at k1 in ``v``'s place.

    The second difference of white noise of variance s^2 has variance 6 s^2 on each axis; the
    car's own acceleration over the spacing (longitudinal from the speeds, lateral from the
    kinematic yaw rate) is taken off in expectation."""
    h = (k1 - k0) * dt
    d2 = p[2] - 2 * p[1] + p[0]
    a_long = (v[2] - v[0]) / (2 * h)
    a_lat = v[1] ** 2 * np.tan(v[3]) / wheelbase
    return ((d2 ** 2).sum(-1) - (a_long ** 2 + a_lat ** 2) * h ** 4) / 12


def alpha_estimates(m: np.ndarray, u: np.ndarray, dt: float, wheelbase: float,
                    sigma: float) -> np.ndarray:
    """(T,) the measurement-noise scale estimated at each row from the fixes up to it.

    Over the last :data:`ALPHA_TRIPLES` triples of consecutive, equally spaced fixes, the mean
    of :func:`_triple_values` estimates the variance of the position noise; alpha is its root
    over ``sigma`` (m, at alpha = 1). NaN until :data:`ALPHA_MIN_TRIPLES` triples are in, and
    everywhere when ``sigma`` is 0. ``m`` (T, 3), ``u`` (T, 2)."""
    t = len(u)
    out = np.full(t, np.nan)
    f = np.flatnonzero(np.isfinite(m[:, :2]).all(1))
    if sigma <= 0 or len(f) < 3:
        return out
    k0, k1, k2 = f[:-2], f[1:-1], f[2:]
    equal = (k1 - k0) == (k2 - k1)
    k0, k1, k2 = k0[equal], k1[equal], k2[equal]
    if not len(k2):
        return out
    p = np.stack([m[k, :2] for k in (k0, k1, k2)])
    v = np.stack([u[k0, 0], u[k1, 0], u[k2, 0], u[k1, 1]])
    values = _triple_values(p, v, k0, k1, k2, dt, wheelbase)
    c = np.concatenate([[0.0], np.cumsum(values)])
    done = np.searchsorted(k2, np.arange(t), side="right")  # triples complete at each row
    n = np.minimum(done, ALPHA_TRIPLES)
    judged = done >= ALPHA_MIN_TRIPLES
    var = (c[done[judged]] - c[done[judged] - n[judged]]) / n[judged]
    out[judged] = np.sqrt(np.maximum(var, 0.0)) / sigma
    return out


class EnvelopeStream:
    """:meth:`Envelope.check` one sample at a time, at a constant cost per step: the same
    flags as the batch check gives row by row (tested)."""

    def __init__(self, envelope: Envelope, *, dt: float, wheelbase: float, sigma: float,
                 window: int) -> None:
        self.envelope, self.dt, self.wheelbase = envelope, dt, wheelbase
        self.sigma, self.window = sigma, window
        self.bounds = {f: envelope.bounds(f) for f in FIELDS
                       if f != "alpha" or envelope.alpha is not None}
        self.reset()

    def reset(self) -> None:
        self.k = 0
        self.fixes: deque[bool] = deque(maxlen=self.window)
        self.count = 0  # fixes in ``self.fixes``
        self.last: deque[tuple[int, np.ndarray, float, float]] = deque(maxlen=2)
        self.values: deque[float] = deque(maxlen=ALPHA_TRIPLES)
        self.done = 0

    def __call__(self, m: np.ndarray | None, u: np.ndarray) -> tuple[str, ...]:
        """The fields the sample (k-th since :meth:`reset`) lies outside of."""
        k = self.k
        self.k += 1
        fix = m is not None and bool(np.isfinite(m[:2]).all())
        if len(self.fixes) == self.window:
            self.count -= self.fixes[0]
        self.fixes.append(fix)
        self.count += fix
        spacing = self.window / self.count if self.count else math.inf
        seen = {"speed": float(u[0]), "steering": float(u[1]), "alpha": math.nan,
                "fix_period": spacing if k >= self.window - 1 else math.nan}
        if fix and m is not None:  # a fix has an m
            if len(self.last) == 2:
                (j0, p0, v0, _), (j1, p1, v1, d1) = self.last
                if j1 - j0 == k - j1:
                    p = np.stack([p0, p1, m[:2]])[:, None]
                    v = np.array([[v0], [v1], [u[0]], [d1]])
                    self.values.append(float(_triple_values(p, v, j0, j1, k, self.dt,
                                                            self.wheelbase)[0]))
                    self.done += 1
            self.last.append((k, np.array(m[:2], dtype=float), float(u[0]), float(u[1])))
        if self.sigma > 0 and self.done >= ALPHA_MIN_TRIPLES:
            seen["alpha"] = math.sqrt(max(sum(self.values) / len(self.values), 0.0)) / self.sigma
        return tuple(f for f, (lo, hi) in self.bounds.items()
                     if not math.isnan(seen[f]) and not lo <= seen[f] <= hi)
