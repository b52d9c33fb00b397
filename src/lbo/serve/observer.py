"""Run an observer, learned or classical, on a log: step by step in a control loop, or over a
whole log at once, with the same numbers either way.

    from lbo import Observer

    obs = Observer.load("outputs/.../checkpoints/best.ckpt")   # or a run id, models:/..., "ekf"
    for m_k, u_k in log:                   # m_k = [x_m, y_m, psi_m], u_k = [V, delta]
        est, valid = obs.step(m_k, u_k)    # est = [x, y, psi] at step k

A CNN or LSTM needs N samples before its window is full. Until then (the first N-1 steps) it
returns the estimate of the paper's EKF (noise preset of the checkpoint, R at alpha=1), which
runs beside the window, and flags it ``valid=False``. Classical observers are valid from the
first fix, and so is the robust observer (``filternet``) in its recursive form
(``form="recursive"``, :mod:`lbo.models.recursive`), which carries its filter from step to
step at a constant cost; its window form re-runs the filter over the last N samples for every
estimate, as it was trained.

Every classical observer and the robust observer also give the covariance of their estimate
(``Estimate.cov``, ``run(..., cov=True)``); the CNN and the LSTM have none (NaN).

Conventions as in :mod:`lbo.filters.start`: ``u_k`` moves ``z_k`` to ``z_{k+1}``, so the
estimate at step k uses ``m_0 .. m_k`` and ``u_0 .. u_{k-1}`` (the filters) or the window of
``[m_j, u_j]``, j = k-N+1 .. k (the networks). Estimated headings are wrapped to (-pi, pi].
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple
from urllib.parse import unquote, urlparse

import numpy as np

from lbo.core.errors import LboError
from lbo.core.paths import tracking_uri
from lbo.filters import classical, measure
from lbo.filters.classical import OBSERVERS as CLASSICAL
from lbo.filters.gyro import GyroNoise
from lbo.models.envelope import Envelope, EnvelopeCheck, check_mode
from lbo.models.features import window_view
from lbo.sim.columns import RECEIVER
from lbo.sim.logcheck import (
    check_alpha,
    check_device,
    check_fix_windows,
    check_receiver,
    check_sample,
    check_samples,
)
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle, wrap_angle

ENGINES = ("torch", "torchscript", "onnx")
"""Inference engines for learned observers."""

FORMS = ("window", "recursive")
"""How a window filter (``filternet``) runs: over the last N samples for every estimate, as it
was trained, or recursively, its filter carried from step to step."""

def default_form(net: Any) -> str:
    """The form a learned observer runs in unless asked for another: ``recursive`` for the
    robust observer's window filter, ``window`` for every other net.

    The recursive form estimates as well as the window form (``docs/serving.md`` has the
    measurement), at a constant cost per step and with a covariance. A window filter with a
    learned process model (``residual``, a single-track body) or drift states (the car that
    slips, ``experiment=dynamic``) stays in its window form: its noise model learned to
    inflate R at high noise as the window's memory, which a filter carried from step to step
    does not forget, so its heading would drift (``docs/dynamic.md``)."""
    inner = getattr(net, "net", None)
    if not has_recursive_form(net) or getattr(inner, "residual", 0) or \
            getattr(inner, "drift", False) or getattr(inner, "single_track", False):
        return "window"
    return "recursive"


def has_recursive_form(net: Any) -> bool:
    """Whether the net's model is the window filter, whose filter can carry from step to
    step (:class:`lbo.models.recursive.RecursiveFilter`); any other model, a plug-in's that
    reads metres and radians too, runs as a window."""
    from lbo.models.filternet import WindowFilter

    return isinstance(getattr(net, "net", None), WindowFilter)

NET_KINDS = {"WindowCNN": "cnn", "WindowLSTM": "lstm", "WindowFilter": "filter",
             "KalmanNet": "kalmannet"}
"""The name an untrained or unnamed net goes by (``<kind>-N<window>``), per net class."""


RUN_ID = re.compile(r"[0-9a-f]{32}")
"""An MLflow run id, as ``observer=<run id>`` takes it."""


class _Pair(NamedTuple):
    state: np.ndarray
    valid: bool


def _engine_device(engine: str, device: Any) -> Any:
    """The checked device of ``engine``: one of :data:`ENGINES`, and ONNX on the CPU only."""
    if engine not in ENGINES:
        raise LboError(f"engine must be one of {list(ENGINES)}, got {engine!r}")
    device = check_device(device)
    if engine == "onnx" and str(device) != "cpu":
        raise LboError(f"engine=onnx runs on the CPU (ONNX Runtime's CPU provider), "
                       f"got device={device}")
    return device


class Estimate(_Pair):
    """One step's result: ``state`` (3,) ``[x, y, psi]`` (m, m, rad; psi in (-pi, pi]) and
    ``valid``; unpacks as ``state, valid``. ``reason`` (not unpacked) says why an estimate is
    not valid, None when it is:

    - ``"no position fix yet"``: before the first fix (state NaN);
    - ``"window not yet full (k of N steps): the EKF's estimate"``: a CNN's or LSTM's first
      N-1 steps;
    - ``"no fix in the last N steps (... s): ..."``: a learned observer trained with
      ``fix_rates`` whose window holds no fix has nothing to anchor its estimate to (state
      NaN); estimates resume with the next fix;
    - ``"the network's estimate is not finite ..."``: a net with NaN or inf weights;
    - ``"outside the training envelope: ..."``: with ``envelope_mode="mark"``, a sample beyond
      what a learned observer was trained on (:mod:`lbo.models.envelope`).
    """

    reason: str | None = None
    cov: np.ndarray
    """(3, 3) covariance of ``state`` (m^2, m rad, rad^2): the filter's own P; NaN for an
    observer that gives none (the CNN and the LSTM)."""
    outside: tuple[str, ...] = ()
    """The fields of the training envelope this sample lies outside (``("speed",)``), in
    every envelope mode but ``"off"``; () inside, or without an envelope."""

    def __new__(cls, state: np.ndarray, valid: bool, reason: str | None = None,
                cov: np.ndarray | None = None, outside: tuple[str, ...] = ()) -> Estimate:
        self = super().__new__(cls, state, valid)
        self.reason = None if valid else (reason or "the estimate is not finite")
        self.cov = np.full((3, 3), np.nan) if cov is None else cov
        self.outside = outside
        return self


class EnvelopeWarning(UserWarning):
    """A learned observer was given samples outside the envelope of its training inputs."""


# --------------------------------------------------------------------------- streaming filters


class _Stream:
    """Classical observer ``name`` of :mod:`lbo.filters.classical`, one sample per call: its batch
    filter's stepper, so stepping and :meth:`Observer.run` give the same numbers."""

    def __init__(self, name: str, vehicle: Vehicle, noise: Noise, alpha: float,
                 gyro: GyroNoise | None = None) -> None:
        self.name, self.vehicle, self.noise, self.alpha = name, vehicle, noise, alpha
        self.gyro = gyro
        self.reset()

    def reset(self) -> None:
        self.flt: Any = None

    def __call__(self, m: np.ndarray, u_prev: np.ndarray | None) -> np.ndarray:
        """The estimate after measurement m (3,) (NaN: not held); NaN until the first
        position fix (one without a heading starts the filter too)."""
        if self.flt is None:
            if not np.isfinite(m[:2]).all():
                return np.full(3, np.nan)
            self.flt = classical.stepper(self.name, m[None], self.vehicle, self.noise,
                                         self.alpha, gyro=self.gyro)
            return self.flt.x[0, :3].copy()
        return self.flt.update(m[None], np.asarray(u_prev, float)[None])[0].copy()

    @property
    def cov(self) -> np.ndarray:
        """(3, 3) covariance of the last estimate (NaN before the first fix)."""
        return np.full((3, 3), np.nan) if self.flt is None else self.flt.P[0, :3, :3].copy()


def _no_heading(name: str) -> str:
    """Why a learned observer refuses a position fix without a heading."""
    return (f"a position fix without a heading (psi_m empty), but {name} takes full fixes "
            f"only (x_m, y_m and psi_m); the classical observers ({', '.join(CLASSICAL)}) "
            "take it")


def _gyro_inputs(u: np.ndarray, receiver: np.ndarray | None, source: str | None
                 ) -> np.ndarray:
    """The ``gyro`` observer's inputs (T, 2) ``[V, r_m]``: the gyro's yaw rate held from each
    reading to the next (the first reading back to the log's start); one line where the log
    has no gyro."""
    rate = None if receiver is None else receiver[:, RECEIVER.index("r_m")]
    if rate is None or not np.isfinite(rate).any():
        raise LboError(f"{source + ': ' if source else ''}gyro needs a gyro's yaw rate: a "
                       "column r_m (rad/s, counter-clockwise); use ekf or ukf for a log "
                       "without one")
    held = np.isfinite(rate)
    last = np.maximum.accumulate(np.where(held, np.arange(len(rate)), -1))
    return np.column_stack([u[:, 0], rate[np.where(last < 0, np.argmax(held), last)]])


def _from_first_fix(name: str, m: np.ndarray, u: np.ndarray, vehicle: Vehicle, noise: Noise,
                    alpha: float, smooth: bool = False, gyro: GyroNoise | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Classical observer ``name`` over one log (T, 3) or (T, 8) (a receiver's rows,
    :mod:`lbo.filters.measure`), (T, 2), started at its first fix: (T, 3) estimates and
    (T, 3, 3) covariances, NaN before that fix (``smooth``: the RTS smoother's; ``gyro``:
    the gyro EKF's noise)."""
    est, cov = classical.estimate(name, m[None], u[None], vehicle, noise, alpha,
                                  return_cov=True, smooth=smooth, gyro=gyro)
    return est[0], cov[0]


# --------------------------------------------------------------------------- inference engines


Predictor = Callable[[np.ndarray], np.ndarray]
"""Windows (B, N, 5) float64 ``[x_m, y_m, psi_m, V, delta]`` -> states (B, 3) float64."""


def make_predictor(net: Any, engine: str = "torch", device: str = "cpu") -> Predictor:
    """Wrap an :class:`~lbo.models.net.WindowNet` as a numpy-in, numpy-out predictor.

    ``torchscript`` traces the net; ``onnx`` exports it in memory and runs it in ONNX Runtime
    on one thread (one window per step gains nothing from more). The torch engines use
    torch's threads: in a control loop call ``torch.set_num_threads(1)``, as intra-op threads
    slow a single window down, by 10x on a busy 2-core machine (measured).
    """
    import torch

    device = _engine_device(engine, device)
    net = net.to(device).eval()
    if engine == "onnx":
        from lbo.serve.engines import onnx_bytes, onnx_session

        session = onnx_session(onnx_bytes(net.cpu()), threads=1)
        return lambda win: session.run(None, {"window": win})[0]
    if engine == "torchscript":
        from lbo.serve.engines import trace

        net = trace(net)

    def predict(win: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return net(torch.from_numpy(win).to(device)).cpu().numpy()

    return predict


def check_form(form: str | None, net: Any) -> str | None:
    """The form an observer runs in (None for a classical one), or one line: ``recursive``
    needs a window filter (``filternet``), whose filter can carry from step to step."""
    if net is None:
        if form not in (None, "window"):
            raise LboError(f"form={form}: a classical observer is recursive already; "
                           "leave form unset")
        return None
    filt = has_recursive_form(net)
    if form is None:
        return default_form(net)
    if form not in FORMS:
        raise LboError(f"form must be one of {list(FORMS)} or null, got {form!r}")
    if form == "recursive" and not filt:
        raise LboError(f"form=recursive: a {type(net.net).__name__} has no filter to carry "
                       "from step to step; only the window filter (filternet) has a recursive "
                       "form")
    return form


Stepper = Callable[[np.ndarray, np.ndarray, list], tuple[np.ndarray, np.ndarray, list]]
"""The recursive form's step: measurement (1, 3), input (1, 2), state -> pose (1, 3),
covariance (1, 3, 3), new state (float64 numpy arrays in, out)."""


def make_stepper(net: Any, engine: str = "torch", device: str = "cpu") -> tuple[Stepper, list]:
    """The recursive form (:class:`~lbo.models.recursive.RecursiveFilter`) of a window filter
    ``net`` (an :class:`~lbo.models.net.WindowNet` of ``filternet``) as a numpy step function on
    ``engine``, and its initial state. ``onnx`` runs on one thread, as in a control loop."""
    import torch

    from lbo.models.recursive import RecursiveFilter

    device = _engine_device(engine, device)
    rec = RecursiveFilter(net.net.cpu() if engine == "onnx" else net.net).to(device)
    state = [s.cpu().numpy() for s in rec.initial_state(1)]
    if engine == "onnx":
        from lbo.serve.engines import onnx_session, onnx_step, recursive_onnx_bytes

        return onnx_step(onnx_session(recursive_onnx_bytes(rec), threads=1)), state
    module = rec
    if engine == "torchscript":
        from lbo.serve.engines import trace_recursive

        module = trace_recursive(rec)

    def torch_step(m: np.ndarray, u: np.ndarray, st: list) -> tuple:
        with torch.inference_mode():
            out = module(*(torch.from_numpy(np.require(x, requirements="W")).to(device)
                           for x in (m, u, *st)))  # a read-only frame's rows are copied
        out = [o.cpu().numpy() for o in out]
        return out[0], out[1], out[2:]

    return torch_step, state


# --------------------------------------------------------------------------- the observer


class Observer:
    """A state observer for the kinematic bicycle, learned or classical, for logs and loops.

    Build one with :meth:`load` (checkpoint, MLflow run, registered model or classical name)
    or :meth:`from_net`. Then either :meth:`step` through a log sample by sample (O(1) per
    step: a ring buffer of the last N samples, no history kept) or :meth:`run` it over a
    whole log at once; both give the same numbers (to 1e-6, tested).

    Attributes
    ----------
    name : ``"cnn-N60"``, ``"ekf"``, ...
    kind : ``"learned"`` or ``"classical"``.
    window : N, samples per window (1 for the classical observers).
    dt : the sampling period (s) the observer expects.
    features : feature mode of a learned observer (``"relative"``, ``"frame"``,
        ``"absolute"``), else None.
    vehicle, noise : the model the filters use (for a learned observer: its checkpoint's,
        used by the fallback EKF).
    alpha : measurement-noise scale the ``oracle`` is told (R = noise.R(alpha)).
    engine : ``"torch"``, ``"torchscript"`` or ``"onnx"`` (learned observers).
    form : ``"window"`` or ``"recursive"`` for a window filter (``filternet``), see
        :data:`FORMS`; ``"window"`` for the CNN and the LSTM; None for classical observers.
    meta : the checkpoint's metadata (data set, data hash, seed, ...), {} for classical.
    net : the :class:`~lbo.models.net.WindowNet`, or None.
    envelope : the :class:`~lbo.models.envelope.Envelope` of the inputs a learned observer was
        trained on (its checkpoint's), or None (classical, or a checkpoint from before lbo
        stored it).
    envelope_mode : what :meth:`step` and :meth:`run` do with samples outside ``envelope``
        (:data:`lbo.models.envelope.MODES`): ``"warn"`` (an :class:`EnvelopeWarning`),
        ``"mark"`` (also ``valid=False`` there) or ``"off"``.
    """

    def __init__(self, name: str, vehicle: Vehicle | None = None, noise: Noise | None = None,
                 *, net: Any = None, alpha: float = 1.0, engine: str = "torch",
                 device: str = "cpu", meta: dict[str, Any] | None = None,
                 form: str | None = None, envelope_mode: str = "warn",
                 gyro_noise: GyroNoise | None = None) -> None:
        self.name = name
        self.vehicle = vehicle or Vehicle()
        self.noise = noise or Noise.preset("paper")
        self.alpha = check_alpha(alpha)
        self.meta = dict(meta or {})
        self.net = net
        self.device = device
        self.form = check_form(form, net)
        classical.check_gyro_noise(name, gyro_noise)
        self.gyro_noise = gyro_noise
        if net is None:
            classical.check(name)
            self.kind, self.window, self.features, self.engine = "classical", 1, None, None
            self._filter = _Stream(name, self.vehicle, self.noise, self.alpha, gyro_noise)
        else:
            self.kind, self.window, self.features = "learned", int(net.window), net.features
            self.engine = engine
            self._filter = _Stream("ekf", self.vehicle, self.noise, 1.0)  # the fallback
            if self.form == "recursive":
                self._step_fn, self._state0 = make_stepper(net, engine, device)
            else:
                self._predict = make_predictor(net, engine, device)
            # Ring buffer written twice (rows i and i+N): the last N samples are always the
            # contiguous rows i+1 .. i+N, so a window is a view, never a copy or a roll.
            self._ring = np.zeros((2 * self.window, 5))
        self.envelope = _stored_envelope(name, self.meta) if net is not None else None
        self.envelope_mode = check_mode(envelope_mode)
        self._envelope = (self.envelope.stream(**self._envelope_terms())
                          if self.envelope is not None and self.envelope_mode != "off" else None)
        self.reset()

    def _envelope_terms(self) -> dict[str, float]:
        sx, sy = self.noise.measurement_sigma[:2]
        return {"dt": self.vehicle.dt, "wheelbase": self.vehicle.wheelbase,
                "sigma": float(np.sqrt((sx ** 2 + sy ** 2) / 2)), "window": self.window}

    def check_envelope(self, m: np.ndarray, u: np.ndarray) -> EnvelopeCheck | None:
        """Which rows of a log (``m`` (T, 3), ``u`` (T, 2)) lie outside the envelope of the
        observer's training inputs; None where there is no envelope to check."""
        if self.envelope is None:
            return None
        return self.envelope.check(np.asarray(m, dtype=float), np.asarray(u, dtype=float),
                                   **self._envelope_terms())

    @property
    def takes_missing_fixes(self) -> bool:
        """Whether steps without a position fix are allowed (classical, or trained for it)."""
        return self.net is None or bool(getattr(self.net, "fixes", False))

    @property
    def gives_covariance(self) -> bool:
        """Whether the estimates come with a covariance: the classical observers' and the
        window filter's (its recursive form's P; the window form's is NaN), not a CNN's or
        an LSTM's."""
        return self.net is None or self.form == "recursive"

    @property
    def _pads(self) -> bool:
        # a window filter that starts at its first fix reads a window reaching back before
        # the log as steps with no fix and no motion: estimates from the first fix on
        return bool(getattr(self.net, "fixes", False) and getattr(self.net, "physical", False))

    # ----------------------------------------------------------------------- construction

    @classmethod
    def load(cls, source: str | os.PathLike, vehicle: Vehicle | None = None,
             noise: Noise | None = None, *, alpha: float = 1.0, features: str | None = None,
             engine: str = "torch", device: str = "cpu", form: str | None = None,
             envelope_mode: str = "warn", gyro_noise: GyroNoise | None = None) -> Observer:
        """Load an observer.

        Parameters
        ----------
        source : one of
            - a checkpoint file (``.ckpt``, as ``lbo.train`` writes) or a ``file://`` URI;
            - an MLflow run id (32 hex digits): its ``checkpoints/best.ckpt``;
            - ``runs:/<run id>/<path>``, ``models:/<name>/<version>`` or
              ``models:/<name>@<alias>``: the checkpoint there, in the store that
              :func:`tracking_uri` names;
            - ``"ekf"`` (R at alpha=1, the paper's), ``"oracle"`` (R at ``alpha``),
              ``"adaptive"`` (learns R, starts at alpha=1) or ``"ukf"``.
        vehicle, noise : for classical observers (defaults: ``Vehicle()``, the ``paper``
            preset). For a learned one they replace its checkpoint's in the fallback EKF;
            ``vehicle.dt`` must then be the dt it was trained at.
        alpha : measurement-noise scale told to the ``oracle``, in [0, 100].
        features : refuse a checkpoint trained with another feature mode (None: any).
        engine : ``"torch"``, ``"torchscript"`` or ``"onnx"`` for learned observers.
        device : torch device of a learned observer (``"cpu"``, ``"cuda"``, ``"cuda:<n>"``),
            checked (and CUDA asked for) before any checkpoint is read.
        form : how a window filter runs (:data:`FORMS`); None: :func:`default_form`.
        envelope_mode : ``"warn"``, ``"mark"`` or ``"off"``: what to do with samples outside
            the envelope of a learned observer's training inputs (see :class:`Observer`).
        gyro_noise : the noise of ``"gyro"`` (:class:`lbo.filters.gyro.GyroNoise`, e.g. as
            :mod:`lbo.learn.gyro_fit` learns it from a drive); None: its defaults.

        Raises
        ------
        LboError
            One line naming the problem: unknown source, unreadable or foreign checkpoint,
            checkpoint format or feature mode this lbo does not read, MLflow run without a
            checkpoint, ...
        """
        source = os.fspath(source)
        alpha = check_alpha(alpha)
        if form is not None and form not in FORMS:
            raise LboError(f"form must be one of {list(FORMS)} or null, got {form!r}")
        check_mode(envelope_mode)
        classical.check_gyro_noise(source, gyro_noise)
        named = source in classical.NAMES or source in classical.on_logs()
        device = check_device(device, probe=not named)
        if named:
            classical.check(source)  # pcrb: a bound, not an observer
            return cls(source, vehicle, noise, alpha=alpha, gyro_noise=gyro_noise)
        with _checkpoint_file(source) as path:
            net, hp = read_checkpoint(path, features=features, device=device)
        meta = dict(hp.get("meta") or {})
        trained, trained_noise = trained_conditions(hp, path)
        if vehicle is not None and not np.isclose(vehicle.dt, trained.dt, rtol=1e-9):
            raise LboError(f"vehicle.dt={vehicle.dt:g} s, but the observer was trained at "
                           f"dt={trained.dt:g} s; resample the data to {trained.dt:g} s")
        return cls(f"{hp['model']['name']}-N{hp['window']}", vehicle or trained,
                   noise or trained_noise, net=net, alpha=alpha,
                   engine=engine, device=device, meta={**meta, "source": source}, form=form,
                   envelope_mode=envelope_mode)

    @classmethod
    def from_net(cls, net: Any, vehicle: Vehicle | None = None, noise: Noise | None = None,
                 *, name: str | None = None, engine: str = "torch",
                 device: str = "cpu", form: str | None = None) -> Observer:
        """Wrap an :class:`~lbo.models.net.WindowNet` (trained or not) as an observer."""
        name = name or f"{NET_KINDS.get(type(net.net).__name__, 'net')}-N{net.window}"
        return cls(name, vehicle, noise, net=net, engine=engine, device=device, form=form)

    # ----------------------------------------------------------------------- streaming

    @property
    def dt(self) -> float:
        return self.vehicle.dt

    def reset(self) -> None:
        """Forget the history: the next :meth:`step` is the first of a new log."""
        self._count = 0
        self._last_fix: int | None = None
        self._u_prev: np.ndarray | None = None
        self._gyro: float | None = None  # the gyro's last reading (observer gyro)
        self._filter.reset()
        self._warned: set[str] = set()
        if self._envelope is not None:
            self._envelope.reset()
        if self.net is not None:
            self._ring[:] = 0.0
            if self._pads:
                self._ring[:, :3] = np.nan
        if self.form == "recursive":
            self._state = [x.copy() for x in self._state0]

    def step(self, measurement: np.ndarray | None, input: np.ndarray,
             receiver: np.ndarray | None = None) -> Estimate:
        """Take one sample and return the estimate at this step.

        Parameters
        ----------
        measurement : (3,) ``[x_m, y_m, psi_m]`` (m, m, rad), or None (or all NaN) when this
            step has no position fix (classical observers, and learned ones trained with
            ``fix_rates``); ``psi_m`` NaN alone: a position fix without a heading (classical
            observers only).
        input : (2,) ``[V, delta]`` (m/s, rad) applied from this step to the next.
        receiver : (7,) this sample's receiver channels, as a row of :meth:`run`'s
            ``receiver`` (NaN where not held), or None; classical observers only. ``gyro``
            needs it, with ``r_m`` at its first step (each reading is held to the next).

        Returns
        -------
        :class:`Estimate` ``(state (3,), valid)``; unpacks as ``est, valid = obs.step(m, u)``;
        its ``reason`` says why an estimate is not valid. A learned observer trained with
        ``fix_rates`` whose last N steps hold no fix returns NaN, valid False, and a reason
        naming the gap (where :meth:`run` refuses such a log): in a control loop the gap is
        not the sample's fault, and the estimates resume with the next fix.

        Raises
        ------
        LboError
            One line naming the step and the value, for a sample :meth:`run` would refuse in
            a log: inf, a heading without a position, x_m without y_m (or the reverse), a
            position fix without a heading for a learned observer, |x_m| or
            |y_m| beyond 1e7 m, |psi_m| beyond 2 pi, |V| beyond 100 m/s, |delta| beyond the
            vehicle's ``delta_max``; or no fix for an observer trained with a fix at every
            step. A refused sample changes nothing: the next :meth:`step` goes on as if it
            had never been given.

        Notes
        -----
        Cost per call: scalar checks of the five numbers, one ring-buffer write and one
        network call on a (1, N, 5) view (or one filter step), whatever the length of the
        log; in the recursive form, one step of the filter, whatever N is. For a control
        loop, run torch on one thread (``torch.set_num_threads(1)``) or use ``engine="onnx"``
        (one thread already).
        """
        k = self._count
        try:
            u = np.asarray(input, dtype=float).reshape(2)
            m = (None if measurement is None
                 else np.asarray(measurement, dtype=float).reshape(3))
        except (TypeError, ValueError):
            raise LboError(f"step {k}: expected measurement [x_m, y_m, psi_m] (3 numbers, or "
                           f"None) and input [V, delta] (2 numbers), got {measurement!r} and "
                           f"{input!r}") from None
        fix = check_sample(None if m is None else tuple(m.tolist()), tuple(u.tolist()), k,
                           self.vehicle.delta_max)
        if fix and self.net is not None and np.isnan(m[2]):
            raise LboError(f"step {k}: {_no_heading(self.name)}")
        if not fix:
            if not self.takes_missing_fixes:
                raise LboError(f"step {k}: no fix, but {self.name} was trained with a fix at "
                               "every step; use an observer trained with fix_rates "
                               "(experiment=robust) or a classical one")
            m = np.full(3, np.nan)
        else:  # one branch for every observer (absolute features read the angle itself)
            m = m.copy()  # never the caller's array
            m[2] = wrap_angle(m[2])
        if receiver is not None or self.name == classical.GYRO:
            m, u = self._receiver_sample(k, m, u, receiver)
        # checked: from here on the sample is taken
        outside = self._envelope(m, u) if self._envelope is not None else ()
        est = self._take(k, m, u, fix)
        if not outside:
            return est
        why = "outside the training envelope: " + ", ".join(
            self.envelope.describe(f) for f in outside)
        if self.envelope_mode == "mark":
            return Estimate(est.state, False, why if est.valid else est.reason, est.cov, outside)
        new = [f for f in outside if f not in self._warned]
        if new:  # once per field until reset: a control loop is not flooded
            self._warned.update(new)
            warnings.warn(f"{self.name}: step {k}: {why}", EnvelopeWarning, stacklevel=2)
        return Estimate(est.state, est.valid, est.reason, est.cov, outside)

    def _receiver_sample(self, k: int, m: np.ndarray, u: np.ndarray,
                         receiver: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Sample ``k``'s filter row (8,) and inputs (2,) with its receiver channels (7,),
        checked as :meth:`run` checks a row; for ``gyro``, ``[V, r_m]`` with the last
        reading held. Nothing is kept unless the sample passes."""
        if receiver is not None:
            try:
                r = np.asarray(receiver, dtype=float).reshape(len(RECEIVER))
            except (TypeError, ValueError):
                raise LboError(f"step {k}: receiver must be {len(RECEIVER)} numbers "
                               f"[{', '.join(RECEIVER)}] (NaN where not held), got "
                               f"{receiver!r}") from None
            if self.net is not None:
                raise LboError(f"step {k}: {self.name} does not take a receiver's channels "
                               f"yet; the classical observers ({', '.join(CLASSICAL)}) do")
            check_receiver(m[None], r[None], f"step {k}")
        else:
            r = np.full(len(RECEIVER), np.nan)
        if self.name == classical.GYRO:
            rate = r[RECEIVER.index("r_m")]
            gyro = float(rate) if np.isfinite(rate) else self._gyro
            if gyro is None:
                raise LboError(f"step {k}: gyro needs a gyro's yaw rate r_m at its first step "
                               f"(receiver[{RECEIVER.index('r_m')}])")
            self._gyro = gyro
            u = np.array([u[0], gyro])
        return self._receiver_rows(m[None], u[None], r[None])[0], u

    def _receiver_rows(self, m: np.ndarray, u: np.ndarray, receiver: np.ndarray) -> np.ndarray:
        """The filters' rows (T, 8) of measurements m (T, 3) and a receiver's channels (T, 7)
        at inputs u (T, 2) (``[V, r_m]`` for ``gyro``): the turn rate the course's variance
        allows for is the gyro's, or the bicycle's ``V tan(delta) / L``."""
        if self.gyro_noise is not None:
            return self.gyro_noise.rows(m, receiver, u)
        turn = (u[:, 1] if self.name == classical.GYRO else
                u[:, 0] * np.tan(u[:, 1]) / self.vehicle.wheelbase)
        return measure.rows(m, receiver[:, :3], receiver[:, 3:5], receiver[:, 5], u[:, 0], turn)

    def _take(self, k: int, m: np.ndarray, u: np.ndarray, fix: bool) -> Estimate:
        """The estimate at step ``k`` of a checked sample (``m`` (3,), NaN without a fix)."""
        n = self.window
        if self.form == "recursive":
            self._count += 1
            pose, cov, self._state = self._step_fn(m[None], u[None], self._state)
            state, cov = pose[0], cov[0]
            state[2] = wrap_angle(state[2])
            valid = bool(np.isfinite(state).all())
            return Estimate(state, valid, "no position fix yet", cov if valid else None)
        if self.net is not None:
            i = k % n
            self._ring[i, :3] = self._ring[i + n, :3] = m
            self._ring[i, 3:] = self._ring[i + n, 3:] = u
        self._count += 1
        if fix:
            self._last_fix = k
        if self.net is not None and (self._count >= n or self._pads):
            if self._last_fix is None:
                return Estimate(np.full(3, np.nan), False, "no position fix yet")
            if k - self._last_fix >= n:
                return Estimate(np.full(3, np.nan), False,
                                f"no fix in the last {n} steps ({n * self.dt:g} s): {self.name} "
                                f"needs a fix in every window of {n} steps")
            state = self._predict(self._ring[None, i + 1:i + 1 + n])[0]
            state[2] = wrap_angle(state[2])
            valid = bool(np.isfinite(state).all())
            return Estimate(state, valid, "the network's estimate is not finite (NaN or inf "
                                          "weights?)")
        state = self._filter(m, self._u_prev)
        self._u_prev = u
        state[2] = wrap_angle(state[2])
        finite = bool(np.isfinite(state).all())
        if self.net is None:
            return Estimate(state, finite, "no position fix yet", self._filter.cov)
        return Estimate(state, False, f"window not yet full ({self._count} of {n} steps): the "
                                      "EKF's estimate" if finite else "no position fix yet")

    # ----------------------------------------------------------------------- batch

    def run(self, m: np.ndarray, u: np.ndarray, batch_size: int = 4096, *,
            source: str | None = None, cov: bool = False, smooth: bool = False,
            receiver: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Estimates over a whole log at once (vectorised; the streaming state is untouched).

        Parameters
        ----------
        m : (T, 3) measurements ``[x_m, y_m, psi_m]``; a row of NaN is a step without a
            position fix, a NaN psi_m alone a position fix without a heading (classical
            observers only: a learned one refuses it in one line).
        u : (T, 2) inputs ``[V, delta]``.
        batch_size : windows per network call.
        source : what to call the log in messages (``"input log.csv"``); None: nothing.
        cov : also return the covariances.
        smooth : the Rauch-Tung-Striebel smoother's estimates (and covariances) after the
            filter (:mod:`lbo.filters.smoother`): every row drawn on the whole log, for offline
            logs. Classical observers and a window filter in its recursive form only.
        receiver : (T, 7) a receiver's channels, :data:`lbo.sim.columns.RECEIVER`
            ``[sx_m, sy_m, spsi_m, ve_m, vn_m, sv_m, r_m]``, NaN where a row holds none: the
            accuracy it reports per fix (the R of that step), a GNSS velocity (its course
            over ground, :mod:`lbo.filters.measure`) and a gyro's yaw rate (the ``gyro``
            observer's input, held from one reading to the next). Classical observers only;
            the adaptive one learns its own R and takes the velocity alone.

        Returns
        -------
        est : (T, 3) ``[x, y, psi]``, psi in (-pi, pi]; the same numbers as T calls of
            :meth:`step` after :meth:`reset`.
        valid : (T,) bool, False on the first N-1 rows of a CNN or LSTM (EKF fallback),
            where the estimate is not finite (before the first fix), and with
            ``envelope_mode="mark"`` on the rows outside the training envelope (see
            :meth:`check_envelope`; ``"warn"`` gives one :class:`EnvelopeWarning` instead).
        covariance : (T, 3, 3), only with ``cov=True``: each estimate's covariance (the
            filter's P), NaN where the observer gives none (a CNN's or LSTM's windows).

        Raises
        ------
        LboError
            One line naming the row: the checks of ``python -m lbo.observe``
            (:func:`lbo.sim.logcheck.check_samples`: NaN or inf other than a missing fix or
            heading, a heading without a position, x_m without y_m, no fix at all, headings
            in degrees, positions, speeds or steering beyond a vehicle's); a position fix
            without a heading for a learned observer; a step without a fix for an observer
            trained with a fix at every step; for a learned observer trained with ``fix_rates``
            in its window form, a window of N steps after the first fix without any fix (its
            estimate there would be NaN).
        """
        try:
            m = np.asarray(m, dtype=float)
            u = np.asarray(u, dtype=float)
        except (TypeError, ValueError):
            raise LboError(f"{source + ': ' if source else ''}run needs m (T, 3) and u (T, 2) "
                           "of numbers") from None
        if m.ndim != 2 or m.shape[1] != 3 or u.shape != (len(m), 2):
            raise LboError(f"run needs m (T, 3) and u (T, 2), got {m.shape} and {u.shape}")
        if smooth and not self.gives_covariance:
            raise LboError(f"smooth: {self.name} has no filter to smooth"
                           + (" in its window form; use form=recursive" if self.form == "window"
                              and has_recursive_form(self.net) else
                              "; smoothing takes a classical observer or the robust one"))
        fix = check_samples(m, u, delta_max=self.vehicle.delta_max, source=source)
        if receiver is not None:
            receiver = np.asarray(receiver, dtype=float)
            if receiver.shape != (len(m), len(RECEIVER)):
                raise LboError(f"run needs receiver ({len(m)}, {len(RECEIVER)}) "
                               f"[{', '.join(RECEIVER)}], got {receiver.shape}")
            if self.net is not None:
                raise LboError(f"receiver: {self.name} does not take a receiver's channels "
                               f"({', '.join(RECEIVER)}) yet; the classical observers "
                               f"({', '.join(CLASSICAL)}) do")
            check_receiver(m, receiver, source)
        if self.net is not None and (fix & np.isnan(m[:, 2])).any():
            raise LboError(f"{source + ': ' if source else ''}row "
                           f"{int(np.argmax(fix & np.isnan(m[:, 2])))}: "
                           + _no_heading(self.name))
        if not fix.all() and not self.takes_missing_fixes:
            raise LboError(f"{source + ': ' if source else ''}row "
                           f"{int(np.flatnonzero(~fix)[0])}: no fix, but {self.name} was "
                           "trained with a fix at every step; use an observer trained with "
                           "fix_rates (experiment=robust) or a classical one")
        if self.net is not None and self.form == "window":
            check_fix_windows(fix, self.window, self.name, self.dt, source)
        # a log may hold its headings on any branch (accumulated rad): one branch for every
        # observer, as step() takes them (absolute features read the angle itself)
        m = m.copy()
        m[:, 2] = wrap_angle(m[:, 2])
        t = len(m)
        covs = np.full((t, 3, 3), np.nan)
        if self.net is None:
            if self.name == classical.GYRO:
                u = _gyro_inputs(u, receiver, source)
            if receiver is not None:
                m = self._receiver_rows(m, u, receiver)
            est, covs = _from_first_fix(self.name, m, u, self.vehicle, self.noise,
                                        self.alpha, smooth, self.gyro_noise)
        elif self.form == "recursive" and smooth:
            from lbo.models.recursive import run_arrays

            mm = np.where(fix[:, None], m, np.nan)
            est, covs = run_arrays(self.net.net, mm[None], u[None], smooth=True,
                                   device=self.device)
            est, covs = est[0], covs[0]
        elif self.form == "recursive":  # through the engine's step, as step() runs it
            est = np.full((t, 3), np.nan)
            state = [x.copy() for x in self._state0]
            mm = np.where(fix[:, None], m, np.nan)
            for k in range(t):
                pose, c, state = self._step_fn(mm[k:k + 1], u[k:k + 1], state)
                est[k], covs[k] = pose[0], c[0]
        else:
            n = self.window
            est = np.full((t, 3), np.nan)
            head = 0 if self._pads else min(n - 1, t)
            if head:
                est[:head] = _from_first_fix("ekf", m[:head], u[:head], self.vehicle,
                                             self.noise, 1.0)[0]
            series = np.concatenate([m, u], axis=1)
            if self._pads:  # no fix and no motion before the log
                pad = np.zeros((n - 1, 5))
                pad[:, :3] = np.nan
                series = np.concatenate([pad, series])
            if len(series) >= n:
                windows = window_view(np.ascontiguousarray(series), n)  # a view
                for s in range(0, len(windows), batch_size):
                    chunk = np.ascontiguousarray(windows[s:s + batch_size])
                    est[head + s:head + s + len(chunk)] = self._predict(chunk)
        est[:, 2] = wrap_angle(est[:, 2])
        valid = np.isfinite(est).all(1)
        if self.form == "window" and not self._pads:
            valid &= np.arange(t) >= self.window - 1
        if self._envelope is not None:  # an envelope, and a mode other than off
            check = self.check_envelope(m, u)
            if self.envelope_mode == "mark":
                valid &= ~check.outside
            elif check.outside.any():
                warnings.warn(f"{self.name}{' on ' + source if source else ''}: "
                              + "; ".join(check.summary(self.envelope, u)), EnvelopeWarning,
                              stacklevel=2)
        covs[~valid] = np.nan
        return (est, valid, covs) if cov else (est, valid)

    def __repr__(self) -> str:
        extra = (f", window={self.window}, features={self.features!r}, engine={self.engine!r}"
                 f", form={self.form!r}" if self.kind == "learned" else
                 (f", alpha={self.alpha:g}" if self.name == "oracle" else ""))
        return f"Observer({self.name!r}, dt={self.dt:g}{extra})"


# --------------------------------------------------------------------------- checkpoints


def read_checkpoint(path: str | os.PathLike, features: str | None = None,
                    device: str = "cpu") -> tuple[Any, dict[str, Any]]:
    """Rebuild the :class:`~lbo.models.net.WindowNet` of an ``lbo.train`` checkpoint.

    The checkpoint's hyperparameters name the architecture, window and feature mode, its
    buffers hold the normalisation statistics and ``meta`` the vehicle (dt) and noise preset.
    Only tensors and plain containers are unpickled (``weights_only``).

    Returns
    -------
    (net in eval mode, hyperparameters dict).

    Raises
    ------
    LboError
        Unreadable file, not an lbo checkpoint, another checkpoint format, an unknown
        feature mode or not the ``features`` asked for, weights that do not fit, weights
        that hold NaN or inf (a diverged training).
    """
    import torch

    from lbo.models import model_class
    from lbo.models.features import FEATURE_MODES
    from lbo.models.net import CHECKPOINT_FORMAT, WindowNet

    path = Path(path)
    if features is not None and features not in FEATURE_MODES:
        raise LboError(f"features: unknown mode {features!r}; expected one of "
                       f"{', '.join(FEATURE_MODES)}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except PermissionError as e:
        raise LboError(f"checkpoint {path}: cannot read it ({e.strerror})") from None
    except Exception as e:  # zip, pickle, EOF: not a file lbo wrote
        # torch's own message suggests weights_only=False: unsafe advice for a foreign file
        what = ("it holds pickled objects beyond tensors and plain containers, which lbo "
                "never unpickles" if "weights_only" in str(e).lower() or
                "weights only" in str(e).lower() else "damaged, or another kind of file")
        raise LboError(f"checkpoint {path}: not a readable lbo checkpoint ({what})") from None
    hp = ckpt.get("hyper_parameters") if isinstance(ckpt, dict) else None
    if not isinstance(hp, dict) or "state_dict" not in ckpt:
        raise LboError(f"checkpoint {path}: not an lbo observer checkpoint "
                       "(no hyper_parameters and state_dict)")
    fmt = hp.get("format")
    if fmt != CHECKPOINT_FORMAT:
        raise LboError(f"checkpoint {path}: checkpoint format {fmt}, this lbo reads format "
                       f"{CHECKPOINT_FORMAT}; retrain it, or use the lbo version that wrote it")
    mode = hp.get("features")
    if mode not in FEATURE_MODES:
        raise LboError(f"checkpoint {path}: feature mode {mode!r} is unknown to this lbo "
                       f"(it knows {', '.join(FEATURE_MODES)})")
    if features is not None and features != mode:
        raise LboError(f"checkpoint {path}: trained with features={mode}, "
                       f"but features={features} was asked for")
    try:
        model = dict(hp["model"])
        # the name is looked up among the installed plug-ins only (nothing the file names is
        # imported); one that is missing says which package provided it
        model_class(model.get("name"), hp.get("provider"))
        net = WindowNet(model.pop("name"), hp["window"], mode, bool(hp.get("fixes", False)),
                          **model)
        state = {k.removeprefix("observer."): v for k, v in ckpt["state_dict"].items()
                 if k.startswith("observer.")}
        net.load_state_dict(state)
    except LboError as e:
        raise LboError(f"checkpoint {path}: {e}") from None
    except (KeyError, TypeError, RuntimeError) as e:
        reason = str(e).strip().splitlines()[0]
        raise LboError(f"checkpoint {path}: its weights do not fit the architecture it "
                       f"names ({reason})") from None
    bad = next((k for k, v in state.items() if torch.is_tensor(v) and v.is_floating_point()
                and not bool(torch.isfinite(v).all())), None)
    if bad is not None:
        raise LboError(f"checkpoint {path}: its weights hold NaN or inf ({bad}: training "
                       "diverged?); retrain it, e.g. with a smaller optimizer.lr")
    return net.to(device).eval(), hp


def load_net(source: str, device: str = "cpu") -> tuple[Any, dict[str, Any]]:
    """The :class:`~lbo.models.net.WindowNet` and hyperparameters of a learned observer named
    as :meth:`Observer.load` takes it (a checkpoint file, an MLflow run id, a ``runs:/`` or
    ``models:/`` URI); raises LboError naming the problem."""
    with _checkpoint_file(str(source)) as path:
        return read_checkpoint(path, device=device)


def trained_conditions(hp: dict[str, Any], path: str | os.PathLike) -> tuple[Vehicle, Noise]:
    """The vehicle and noise preset a checkpoint was trained with (``hp["meta"]``), for the
    reference filters and the streaming fallback; raises LboError naming the file."""
    meta = hp.get("meta") or {}
    try:
        vehicle = Vehicle(**meta["vehicle"])
    except (KeyError, TypeError) as e:
        raise LboError(f"checkpoint {path}: no usable meta.vehicle ({e})") from None
    except LboError as e:
        raise LboError(f"checkpoint {path}: its stored {e}") from None
    try:
        n = meta["noise"]
        noise = Noise(n["process_sigma"], n["measurement_sigma"], n.get("name", "custom"))
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, LboError):  # a bad value stored in the checkpoint: its fault
            raise LboError(f"checkpoint {path}: its stored {e}") from None
        raise LboError(f"checkpoint {path}: no usable meta.noise ({e})") from None
    return vehicle, noise


def _stored_envelope(name: str, meta: dict[str, Any]) -> Envelope | None:
    """The training envelope in a checkpoint's metadata, None for one written before lbo
    stored it; one line naming the observer for a damaged one."""
    stored = meta.get("envelope")
    if stored is None:
        return None
    try:
        return Envelope.from_dict(stored)
    except LboError as e:
        raise LboError(f"observer {name}: its stored {e}") from None


@contextlib.contextmanager
def _checkpoint_file(source: str) -> Iterator[Path]:
    """The local checkpoint file for a source; one downloaded from MLflow lives in a
    temporary folder that is removed on exit."""
    src = unquote(urlparse(source).path) if source.startswith("file://") else source
    if Path(src).is_file():
        yield Path(src)
        return
    if RUN_ID.fullmatch(src):
        uri, run_id = f"runs:/{src}/checkpoints/best.ckpt", src
    elif src.startswith(("runs:/", "models:/")):
        uri, run_id = src, None
    elif Path(src).suffix or "/" in src or os.sep in src:
        raise LboError(f"observer: checkpoint not found: {src}")
    else:
        raise LboError(f"observer: {src!r} is not a checkpoint file, an MLflow run id "
                       "(32 hex digits), a runs:/ or models:/ URI, nor one of "
                       f"{', '.join(classical.on_logs())}")
    with tempfile.TemporaryDirectory(prefix="lbo-ckpt-") as tmp:
        yield _download(uri, run_id, Path(tmp))


def _download(uri: str, run_id: str | None, folder: Path) -> Path:
    """Download ``uri`` (runs:/ or models:/) into ``folder``; return the .ckpt in it."""
    import mlflow
    from mlflow.exceptions import MlflowException

    from lbo.tracking.runs import check_server

    store = tracking_uri()
    # a dead server: one line in seconds, not MLflow's retries for minutes
    check_server(store, field="MLFLOW_TRACKING_URI")
    client = mlflow.MlflowClient(store, registry_uri=store)
    if run_id is not None:
        try:
            client.get_run(run_id)
        except MlflowException:
            raise LboError(f"observer: MLflow run {run_id} not found in {store}") from None
    try:
        where = _model_version_uri(client, uri) if uri.startswith("models:/") else uri
        local = Path(mlflow.artifacts.download_artifacts(artifact_uri=where, dst_path=str(folder),
                                                         tracking_uri=store))
    except MlflowException as e:
        reason = str(e.message).strip().splitlines()[0]
        if run_id is not None:
            raise LboError(f"observer: MLflow run {run_id} has no checkpoints/best.ckpt "
                           f"(did it finish training?): {reason}") from None
        raise LboError(f"observer: {uri} not found in {store}: {reason}") from None
    if local.is_file():
        return local
    found = sorted(local.rglob("*.ckpt"))
    best = [p for p in found if p.name == "best.ckpt"]
    if len(best) == 1 or len(found) == 1:
        return (best or found)[0]
    raise LboError(f"observer: {uri} holds {len(found)} .ckpt files, "
                   "expected one (or one best.ckpt)")


def _model_version_uri(client: Any, uri: str) -> str:
    """``models:/name/version`` or ``models:/name@alias`` -> where that version's files are."""
    ref = uri[len("models:/"):].strip("/")
    if "@" in ref:
        name, alias = ref.split("@", 1)
        version = client.get_model_version_by_alias(name, alias).version
    elif "/" in ref:
        name, version = ref.rsplit("/", 1)
    else:
        raise LboError(f"observer: {uri}: give models:/<name>/<version> or models:/<name>@<alias>")
    return client.get_model_version_download_uri(name, version)
