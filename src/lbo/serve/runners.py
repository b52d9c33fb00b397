"""How an observer turns samples into estimates: one runner per path, each both streaming and
over a whole log, with the same numbers either way.

- :class:`ClassicalRunner`: a classical observer's stepper (:mod:`lbo.filters.stepper`), one
  sample per call; its batch filter over a log.
- :class:`WindowRunner`: a learned net over the last N samples (a CNN, an LSTM, the window
  filter in its window form, a plug-in's model); the paper's EKF stands in for the first N-1
  steps of a net that needs a full window.
- :class:`RecursiveRunner`: the robust observer's window filter carried from step to step
  (:mod:`lbo.models.recursive`).
- :class:`~lbo.serve.carried_runner.CarriedRunner`: KalmanNet's peers carried likewise.

:class:`lbo.Observer` checks every sample and hands it to its runner, which keeps the runner's
state between steps. Each runner has ``reset()``, ``take(k, m, u, fix)`` (one checked sample
-> :class:`Estimate`) and ``run(m, u, fix, smooth, batch_size)`` (a checked log -> estimates
(T, 3), covariances (T, 3, 3) and lateral states (T, 3), :func:`lbo.serve.estimate.side_slip`,
NaN where none are carried), ``first_valid``: the first row whose estimate is the observer's
own, and ``carries_lateral``: whether it carries a single-track body's lateral states.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters import classical, measure
from lbo.filters.gyro_noise import GyroNoise
from lbo.models.features import held_within, window_view
from lbo.serve import carry, refusals
from lbo.serve.engines import make_predictor, make_recursive_step
from lbo.serve.estimate import Estimate, side_slip
from lbo.serve.exported import ExportedNet
from lbo.serve.rows import bicycle_rows, receiver_rows, window_series
from lbo.sim.columns import RECEIVER
from lbo.sim.measurements import Measurements
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

if TYPE_CHECKING:  # torch, which importing lbo does not load
    from lbo.serve.carried_runner import CarriedRunner

FORMS = ("window", "recursive")
"""How a window filter (``filternet``) runs: over the last N samples for every estimate, as it
was trained, or recursively, its filter carried from step to step."""


def is_window_filter(net: Any) -> bool:
    """Whether the net's model is the window filter, whose recursive form is a Kalman filter
    with a covariance (:class:`lbo.models.recursive.RecursiveFilter`); one kept as ONNX graphs
    (:class:`lbo.serve.exported.ExportedNet`) is one, read without torch."""
    if isinstance(net, ExportedNet):
        return True
    from lbo.models.filternet import WindowFilter

    return isinstance(getattr(net, "net", None), WindowFilter)


def has_recursive_form(net: Any) -> bool:
    """Whether the net's model can be carried from step to step: the window filter, or one
    that keeps :class:`lbo.models.carried.SequenceModel` (KalmanNet's peers, a plug-in's)."""
    if is_window_filter(net):
        return True
    from lbo.models.carried import is_sequence_model  # torch: loaded with a net already

    return is_sequence_model(getattr(net, "net", None))


def default_form(net: Any) -> str:
    """The form a learned observer runs in unless asked for another: ``recursive`` for the
    robust observer's window filter (as good as its window form, at a constant cost per step
    and with a covariance: ``docs/serving.md``) and for a model trained carried (``tbptt``),
    ``window`` for every other net. A window filter with a learned process model or drift
    states stays a window: its noise model learned to inflate R at high noise as the window's
    memory, which a filter carried from step to step never forgets (``docs/dynamic.md``)."""
    if getattr(net, "carried", False):
        return "recursive"
    inner = getattr(net, "net", None)
    if not is_window_filter(net) or bool(getattr(inner, "residual", 0)) or \
            getattr(inner, "drift", False) or getattr(inner, "single_track", False):
        return "window"
    return "recursive"


def check_form(form: str | None, net: Any) -> str | None:
    """The form an observer runs in (None for a classical one), or one line: ``recursive``
    needs a model that can be carried from step to step (:func:`has_recursive_form`)."""
    if net is None:
        if form not in (None, "window"):
            raise LboError(f"form={form}: a classical observer is recursive already; "
                           "leave form unset")
        return None
    if form is None:
        return default_form(net)
    if form not in FORMS:
        raise LboError(f"form must be one of {list(FORMS)} or null, got {form!r}")
    if form == "recursive" and not has_recursive_form(net):
        raise LboError(f"form=recursive: a {type(net.net).__name__} has no filter to carry "
                       "from step to step; the window filter (filternet), kalmannet and "
                       "split_kalmannet have a recursive form")
    return form


def learned_runner(name: str, net: Any, form: str, vehicle: Vehicle, noise: Noise,
                   engine: str, device: str) -> WindowRunner | RecursiveRunner | CarriedRunner:
    """The runner of learned observer ``name`` in ``form`` (checked by :func:`check_form`)."""
    if form == "window":
        return WindowRunner(name, net, vehicle=vehicle, noise=noise, engine=engine,
                            device=device)
    if is_window_filter(net):
        return RecursiveRunner(net, vehicle, engine=engine, device=device)
    from lbo.serve.carried_runner import CarriedRunner  # torch: loaded with the net already

    return CarriedRunner(name, net, engine=engine, device=device)


def from_first_fix(name: str, m: np.ndarray, u: np.ndarray, vehicle: Vehicle, noise: Noise,
                   smooth: bool = False, gyro: GyroNoise | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Classical observer ``name`` over one log (T, 3) or (T, 8) (a receiver's rows,
    :mod:`lbo.filters.measure`), (T, 2), started at its first fix: (T, 3) estimates and
    (T, 3, 3) covariances, NaN before that fix (``smooth``: the RTS smoother's; ``gyro``:
    the gyro EKF's noise), and (T,) bool: the rows its consistency test flags (the gyro
    EKF's, :mod:`lbo.filters.consistency`; none for the others)."""
    post = classical.estimate(name, m[None], u[None], vehicle, noise, smooth=smooth,
                              gyro=gyro)
    flagged = np.zeros(len(m), bool) if post.checks is None else post.checks.inconsistent[0]
    return post.mean[0], post.cov[0], flagged


class ClassicalRunner:
    """Classical observer ``name`` (:mod:`lbo.filters.classical`): its batch filter's stepper
    one sample per call, so stepping and running a log give the same numbers. The gyro EKF's
    rows that its consistency test flags (:mod:`lbo.filters.consistency`) are not valid,
    their reason the test's: ``inconsistent`` (T,) after :meth:`run`."""

    first_valid = 0
    carries_lateral = False  # oracle_dynamic's are scored on simulated sets only
    reads_receiver = False  # a receiver's channels go through rows() only where given
    inconsistent: np.ndarray | None = None  # the rows the last run()'s test flagged

    def __init__(self, name: str, vehicle: Vehicle, noise: Noise, *,
                 gyro: GyroNoise | None = None) -> None:
        self.name, self.vehicle, self.noise = name, vehicle, noise
        self.gyro = gyro
        self.reset()

    def reset(self) -> None:
        self.flt: Any = None
        self.u_prev: np.ndarray | None = None
        self.gyro_last: float | None = None  # the gyro's last reading (observer gyro)

    def rows(self, meas: Measurements, u: np.ndarray) -> np.ndarray:
        """The filters' rows (T, 8) of measurements ``meas`` (T steps) at inputs u (T, 2)
        (``[V, r_m]`` for ``gyro``): the turn rate the course's variance allows for is the
        gyro's, or the bicycle's ``V tan(delta) / L``."""
        if self.gyro is not None:
            return self.gyro.rows(meas, u)
        if self.name == classical.GYRO:
            return measure.rows(meas, u[:, 0], u[:, 1])
        return bicycle_rows(meas, u, self.vehicle.wheelbase)

    def log_rows(self, meas: Measurements, u: np.ndarray, source: str | None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """A checked log's rows of its measurements ``meas``, (T, 8), or its poses (T, 3) where
        no step holds a receiver's channel, and its inputs (T, 2): for
        ``gyro``, ``[V, r_m]``, the gyro's yaw rate held from each reading to the next (the
        first reading back to the log's start); one line where the log has no gyro."""
        if self.name == classical.GYRO:
            rate = meas.gyro
            if not np.isfinite(rate).any():
                raise LboError(f"{source + ': ' if source else ''}gyro needs a gyro's yaw "
                               "rate: a column r_m (rad/s, counter-clockwise); use ekf or ukf "
                               "for a log without one")
            held = measure.held_last(rate)
            u = np.column_stack([u[:, 0], np.where(np.isnan(held), held[np.isfinite(held)][0],
                                                   held)])
        return (self.rows(meas, u) if meas.reads_receiver else meas.pose), u

    def sample(self, k: int, meas: Measurements, u: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """Sample ``k``'s row (8,) of its checked measurements ``meas`` (one step) and its
        inputs (2,): for ``gyro``, ``[V, r_m]`` with the last reading held. Nothing is kept
        unless the sample passes."""
        if self.name == classical.GYRO:
            gyro = float(meas.gyro) if meas.has_gyro else self.gyro_last
            if gyro is None:
                raise LboError(f"step {k}: gyro needs a gyro's yaw rate r_m at its first step "
                               f"(receiver[{RECEIVER.index('r_m')}])")
            self.gyro_last = gyro
            u = np.array([u[0], gyro])
        return self.rows(meas[None], u[None])[0], u

    def take(self, k: int, m: np.ndarray, u: np.ndarray, fix: bool) -> Estimate:
        """The estimate after row m (3,) or (8,) (NaN: not held) and inputs u (2,); NaN until
        the first position fix (one without a heading starts the filter too)."""
        if self.flt is None:
            state = np.full(3, np.nan)
            if np.isfinite(m[:2]).all():
                self.flt = classical.stepper(self.name, m[None], self.vehicle, self.noise,
                                             gyro=self.gyro)
                state = self.flt.x[0, :3].copy()
        else:
            state = self.flt.update(m[None], np.asarray(self.u_prev, float)[None])[0].copy()
        self.u_prev = u
        state[2] = wrap_angle(state[2])
        cov = None if self.flt is None else self.flt.P[0, :3, :3].copy()
        # a stepper with a consistency test (the gyro EKF's) says why its estimate is flagged
        why = getattr(self.flt, "reason", lambda g: None)(0) if self.flt is not None else None
        return Estimate(state, bool(np.isfinite(state).all()) and why is None,
                        why or "no position fix yet", cov)

    def run(self, m: np.ndarray, u: np.ndarray, fix: np.ndarray, smooth: bool = False,
            batch_size: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        est, cov, self.inconsistent = from_first_fix(self.name, m, u, self.vehicle,
                                                     self.noise, smooth, self.gyro)
        return est, cov, side_slip(None, u[:, 0])


class WindowRunner:
    """A learned net over the last N samples (:class:`~lbo.models.net.WindowNet`), on
    ``engine``. Until its window is full, the paper's EKF (the vehicle's and noise's, R at
    alpha = 1) gives the estimate, flagged not valid; a window filter that starts at its first
    fix (``pads``) reads the steps before the log as steps with no fix and no motion, and
    estimates from the first fix on.

    A net that reads a receiver (``reads_receiver``) takes rows (T, 9): the filters' row
    (:data:`lbo.filters.measure.CHANNELS`) and the gyro's ``r_m``, as :meth:`log_rows` and
    :meth:`sample` make them; its windows are :data:`lbo.models.receiver_window.COLUMNS`.
    Where its window holds no heading (a stop), the window filter carries its own estimate of
    N-1 steps before (``carries``, :mod:`lbo.serve.carry`); a CNN or an LSTM gives none."""

    carries_lateral = False  # a window's single-track body starts afresh in each window

    def __init__(self, name: str, net: Any, *, vehicle: Vehicle, noise: Noise, engine: str,
                 device: str) -> None:
        self.name, self.window, self.dt = name, int(net.window), vehicle.dt
        self.vehicle, self.noise = vehicle, noise
        self.predict = make_predictor(net, engine, device)
        self.fallback = ClassicalRunner("ekf", vehicle, noise)
        self.pads = bool(getattr(net, "fixes", False) and getattr(net, "physical", False))
        self.reads_receiver = bool(getattr(net, "receiver", False))
        # the filter holds a carried heading as a standing car does; a CNN reads it as any
        # course (one trained on the hill drive's span alone, carrying, erred 0.42 rad)
        self.carries = self.reads_receiver and is_window_filter(net)
        self.first_valid = 0 if self.pads else self.window - 1
        # Ring buffer written twice (rows i and i+N): the last N samples are always the
        # contiguous rows i+1 .. i+N, so a window is a view, never a copy or a roll.
        rows = measure.WIDTH + 1 if self.reads_receiver else 3  # + r_m
        # a step before the log (pads): no measurement and no motion
        self.empty = window_series(np.full((1, rows), np.nan), np.zeros((1, 2)))[0]
        self.ring = np.zeros((2 * self.window, len(self.empty)))
        self.reset()

    def log_rows(self, meas: Measurements, u: np.ndarray, source: str | None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """A checked log's :func:`receiver_rows` (T, 9) of its measurements ``meas``."""
        return receiver_rows(meas, u, self.vehicle.wheelbase), u

    def sample(self, k: int, meas: Measurements, u: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """Sample ``k``'s row (9,) of its checked measurements ``meas`` (one step)."""
        return receiver_rows(meas[None], u[None], self.vehicle.wheelbase)[0], u

    def reset(self) -> None:
        self.fallback.reset()
        self.last_fix: int | None = None
        self.ring[:] = self.empty if self.pads else 0.0
        self.states = np.full((self.window, 3), np.nan)  # the last N states, at k % N

    def take(self, k: int, m: np.ndarray, u: np.ndarray, fix: bool) -> Estimate:
        est = self._take(k, m, u, fix)
        # its own estimates only: never the EKF's that stands in while the window fills
        self.states[k % self.window] = est.state if est.valid else np.nan
        return est

    def _take(self, k: int, m: np.ndarray, u: np.ndarray, fix: bool) -> Estimate:
        n = self.window
        i = k % n
        self.ring[i] = self.ring[i + n] = window_series(m[None], u[None])[0]
        if fix:
            self.last_fix = k
        if k + 1 >= n or self.pads:
            if self.last_fix is None:
                return Estimate(np.full(3, np.nan), False, "no position fix yet")
            if k - self.last_fix >= n:
                return Estimate(np.full(3, np.nan), False,
                                f"no fix in the last {n} steps ({n * self.dt:g} s): {self.name} "
                                f"needs a fix in every window of {n} steps")
            window = self.ring[None, i + 1:i + 1 + n]
            if self.reads_receiver and not measure.heading_held(window).any():
                prior = self.states[(k + 1) % n]  # the estimate at the window's first row
                if not self.carries or not np.isfinite(prior).all():
                    return Estimate(np.full(3, np.nan), False,
                                    refusals.blind_window(self.name, n, self.dt, self.carries))
                window = carry.carried(window, prior[None])
            state = self.predict(window)[0]
            state[2] = wrap_angle(state[2])
            return Estimate(state, bool(np.isfinite(state).all()),
                            "the network's estimate is not finite (NaN or inf weights?)")
        state = self.fallback.take(k, m[:measure.WIDTH], u, fix).state
        finite = bool(np.isfinite(state).all())
        return Estimate(state, False, f"window not yet full ({k + 1} of {n} steps): the "
                                      "EKF's estimate" if finite else "no position fix yet")

    def run(self, m: np.ndarray, u: np.ndarray, fix: np.ndarray, smooth: bool = False,
            batch_size: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n, t = self.window, len(m)
        est = np.full((t, 3), np.nan)
        head = 0 if self.pads else min(n - 1, t)
        if head:
            est[:head] = from_first_fix("ekf", m[:head, :measure.WIDTH], u[:head], self.vehicle,
                                        self.noise)[0]
        series = window_series(m, u)
        if self.pads:  # no fix and no motion before the log
            series = np.concatenate([np.tile(self.empty, (n - 1, 1)), series])
        if len(series) >= n:
            windows = window_view(np.ascontiguousarray(series), n)  # a view
            for s in range(0, len(windows), batch_size):
                chunk = np.ascontiguousarray(windows[s:s + batch_size])
                est[head + s:head + s + len(chunk)] = self.predict(chunk)
            if self.reads_receiver:  # no heading in the window: the one carried (take())
                blind = np.flatnonzero(~held_within(measure.heading_held(series), n)[n - 1:])
                est[head + blind] = np.nan
                if self.carries:
                    carry.run_blind(windows, blind, head, est, self.predict)
        return est, np.full((t, 3, 3), np.nan), side_slip(None, u[:, 0])


class RecursiveRunner:
    """The window filter of ``net`` carried from step to step on ``engine``
    (:func:`lbo.serve.engines.make_recursive_step`): one filter step per sample, with its
    covariance; over a log, the same numbers, each stretch of rows without any measurement
    in one coast (:meth:`lbo.models.recursive.RecursiveFilter.coast`, where the filter
    coasts) and every other row through the engine's step (or, with ``smooth``, the RTS
    smoother's estimates in PyTorch). A filter trained with a gyro (``reads_receiver``) takes
    inputs (T, 3) ``[V, delta, r_m]``, the gyro's last reading held (:meth:`log_rows`). One
    with a single-track body (``carries_lateral``) gives the ``[v_y, r]`` it carries (the
    state's ``body``, :data:`lbo.models.recursive.STATE_NAMES`), on every engine."""

    first_valid = 0
    gyro_last: float  # set by reset
    _BODY = 2  # the body's place in the state: lbo.models.recursive.STATE_NAMES, unimported

    def __init__(self, net: Any, vehicle: Vehicle, *, engine: str, device: str) -> None:
        self.net, self.vehicle, self.device = net, vehicle, device
        self.state0: list[np.ndarray]
        self.step, self.state0, self.coast = (
            net.recursive_step() if isinstance(net, ExportedNet)
            else make_recursive_step(net, engine, device))
        self.reads_receiver = bool(getattr(net.net, "gyro", False))
        self.carries_lateral = bool(getattr(net.net, "single_track", False))
        self.reset()

    def log_rows(self, meas: Measurements, u: np.ndarray, source: str | None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """A checked log's filters' rows (T, 8) (:func:`bicycle_rows`) of its measurements
        ``meas`` and, for a gyro filter, inputs (T, 3) ``[V, delta, r_m]``: the gyro's last
        reading (:func:`lbo.filters.measure.held_last`), NaN before the first (there the
        bicycle turns the heading)."""
        rows = bicycle_rows(meas, u, self.vehicle.wheelbase)
        if not self.reads_receiver:
            return rows, u
        return rows, np.column_stack([u, measure.held_last(meas.gyro)])

    def sample(self, k: int, meas: Measurements, u: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """Sample ``k``'s row (8,) of its checked measurements ``meas`` (one step), and its
        inputs u (2,) as they are, or for a gyro filter (3,) with the gyro's last reading
        (kept only once the sample passes)."""
        row = bicycle_rows(meas[None], u[None], self.vehicle.wheelbase)[0]
        if not self.reads_receiver:
            return row, u
        self.gyro_last = float(meas.gyro) if meas.has_gyro else self.gyro_last
        return row, np.array([u[0], u[1], self.gyro_last])

    def reset(self) -> None:
        self.state = [x.copy() for x in self.state0]
        self.gyro_last = np.nan  # the gyro's last reading

    def _body(self, body: np.ndarray) -> np.ndarray | None:
        """The carried ``[v_y, r]`` (..., 2), or None where the filter has no single-track
        body (its body state is the kinematic bicycle's, unread)."""
        return body if self.carries_lateral else None

    def take(self, k: int, m: np.ndarray, u: np.ndarray, fix: bool) -> Estimate:
        pose, cov, self.state = self.step(m[None], u[None], self.state)
        state, cov = pose[0], cov[0]
        state[2] = wrap_angle(state[2])
        valid = bool(np.isfinite(state).all())
        return Estimate(state, valid, "no position fix yet", cov if valid else None,
                        lateral=side_slip(self._body(self.state[self._BODY][0]), u[0], state))

    def run(self, m: np.ndarray, u: np.ndarray, fix: np.ndarray, smooth: bool = False,
            batch_size: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        mm = np.array(m)  # rows (T, 3), or (T, 8) with a receiver's channels
        mm[~fix, :3] = np.nan
        if smooth:
            if isinstance(self.net, ExportedNet):
                raise LboError("smooth: the robust observer's ONNX graphs run its filter "
                               "only; load it with engine=torch to smooth")
            from lbo.models.recursive import run_arrays

            out = run_arrays(self.net.net, mm[None], u[None], smooth=True, device=self.device)
            # the body is the filter's, not smoothed: the smoother runs over z = the pose
            return out.pose[0], out.cov[0], side_slip(self._body(out.body[0]), u[:, 0], out.pose[0])
        t = len(m)
        est, covs = np.full((t, 3), np.nan), np.full((t, 3, 3), np.nan)
        body = np.full((t, 2), np.nan)
        state = [x.copy() for x in self.state0]  # through the engine's step, as take() runs
        # the runs of rows without any measurement, once started, go in one coast each
        # (the same numbers: RecursiveFilter.coast): most rows of a log with slow fixes
        empty = ~np.isfinite(mm).any(1)
        # the first row at or after each that holds a measurement (t: none)
        held_next = np.minimum.accumulate(np.where(empty, t, np.arange(t))[::-1])[::-1]
        k = 0
        while k < t:
            if self.coast is not None and empty[k] and state[-1][0] > 0.5:  # started
                stop = int(held_next[k])
                est[k:stop], covs[k:stop], state = self.coast(u[k:stop], state)
                k = stop
                continue
            pose, c, state = self.step(mm[k:k + 1], u[k:k + 1], state)
            est[k], covs[k], body[k] = pose[0], c[0], state[self._BODY][0]
            k += 1
        return est, covs, side_slip(self._body(body), u[:, 0], est)
