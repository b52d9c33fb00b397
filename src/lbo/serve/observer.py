"""Run an observer, learned or classical, on a log: step by step in a control loop, or over a
whole log at once, with the same numbers either way.

    from lbo import Observer

    obs = Observer.load("outputs/.../checkpoints/best.ckpt")   # or a run id, models:/..., "ekf"
    for m_k, u_k in log:                   # m_k = [x_m, y_m, psi_m], u_k = [V, delta]
        est, valid = obs.step(m_k, u_k)    # est = [x, y, psi] at step k

Each kind of observer makes its estimates through a runner (:mod:`lbo.serve.runners`): a
classical observer's stepper, a net over the last N samples (the paper's EKF standing in, not
valid, for a CNN's or LSTM's first N-1 steps), or a filter carried from step to step
(``form="recursive"``: the robust observer's, a KalmanNet's). The classical observers and the
robust one give their estimates' covariance (``Estimate.cov``, ``Estimates.cov``); a learned
observer with a single-track body, carried, its lateral states (``Estimate.lateral``:
the side slip, lateral speed and yaw rate).

Conventions as in :mod:`lbo.filters.start`: ``u_k`` moves ``z_k`` to ``z_{k+1}``, so the
estimate at step k uses ``m_0 .. m_k`` and ``u_0 .. u_{k-1}`` (the filters) or the window of
``[m_j, u_j]``, j = k-N+1 .. k (the networks). Estimated headings are wrapped to (-pi, pi].
"""

from __future__ import annotations

import os
import warnings
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters import classical
from lbo.filters.gyro_noise import GyroNoise
from lbo.filters.inputs import InputTerms
from lbo.logs.checks import check_device
from lbo.models import checkpoint
from lbo.models.envelope import Envelope, EnvelopeCheck, EnvelopeWarning, check_mode, observer_terms
from lbo.serve import exported
from lbo.serve.estimate import Estimate, Estimates, lateral_variance
from lbo.serve.refusals import checked_log, checked_sample
from lbo.serve.rows import bicycle_rows, sampled
from lbo.serve.runners import (
    FORMS,
    ClassicalRunner,
    RecursiveRunner,
    WindowRunner,
    check_form,
    is_window_filter,
    learned_runner,
)
from lbo.sim.measurements import Measurements
from lbo.sim.noise import Noise, check_alpha
from lbo.sim.vehicle import Vehicle
from lbo.tracking.artifacts import checkpoint_file, learned_noise

if TYPE_CHECKING:  # torch, which importing lbo does not load
    from lbo.serve.carried_runner import CarriedRunner

__all__ = ["Estimate", "Estimates", "EnvelopeWarning", "Observer"]


class Observer:
    """A state observer for the kinematic bicycle, learned or classical, for logs and loops.

    Build one with :meth:`load` (checkpoint, MLflow run, registered model or classical name)
    or :meth:`from_net`. Then :meth:`step` through a log sample by sample (O(1) per step) or
    :meth:`run` it over a whole log at once: the same numbers (to 1e-6, tested).

    Attributes
    ----------
    name : ``"cnn-N60"``, ``"ekf"``, ...
    kind : ``"learned"`` or ``"classical"``.
    window : N, samples per window (1 for the classical observers).
    dt : the sampling period (s) the observer expects.
    features : a learned observer's feature mode (``"relative"``, ...), else None.
    vehicle, noise : the filters' model (a learned observer's: its checkpoint's).
    alpha : measurement-noise scale the ``oracle`` is told (R = noise.R(alpha)).
    engine : ``"torch"``, ``"torchscript"`` or ``"onnx"`` (learned observers; ``"auto"``
        resolved).
    form : ``"window"`` or ``"recursive"`` (:data:`FORMS`) for a window filter, ``"window"``
        for the CNN and the LSTM, None for classical observers.
    meta : the checkpoint's metadata (data set, hash, seed, ...); classical: {} or its run.
    net : the :class:`~lbo.models.net.WindowNet` (or its recursive form's ONNX graphs,
        :class:`lbo.serve.exported.ExportedNet`), or None.
    envelope : the :class:`~lbo.models.envelope.Envelope` of a learned observer's training
        inputs, or None (classical, or a checkpoint from before lbo stored it).
    envelope_mode : what :meth:`step` and :meth:`run` do with samples outside ``envelope``:
        ``"warn"`` (an :class:`EnvelopeWarning`), ``"mark"`` (also not valid) or ``"off"``.
    inputs : the :class:`~lbo.filters.inputs.InputTerms` (a speed factor, a steering offset
        and factor) every input is undone by before the model reads it, or None (as logged);
        the samples are checked as logged. May be set (:mod:`lbo.learn.input_fit` learns them).
    """

    def __init__(self, name: str, vehicle: Vehicle | None = None, noise: Noise | None = None,
                 *, net: Any = None, alpha: float = 1.0, engine: str = "torch",
                 device: str = "cpu", meta: dict[str, Any] | None = None,
                 form: str | None = None, envelope_mode: str = "warn",
                 gyro_noise: GyroNoise | None = None, inputs: InputTerms | None = None) -> None:
        self.name, self.meta, self.inputs = name, dict(meta or {}), inputs
        self.vehicle = vehicle or Vehicle()
        self.noise = noise or Noise.preset("paper")
        self.alpha = check_alpha(alpha)
        self.net, self.device = net, device
        self.form = check_form(form, net)
        classical.check_gyro_noise(name, gyro_noise)
        self.gyro_noise = gyro_noise
        self._runner: ClassicalRunner | WindowRunner | RecursiveRunner | CarriedRunner
        if net is None:
            classical.check(name)
            self.kind, self.window, self.features, self.engine = "classical", 1, None, None
            self._runner = ClassicalRunner(name, self.vehicle,
                                           classical.told(name, self.noise, self.alpha),
                                           gyro=gyro_noise)
        else:
            self.kind, self.window, self.features = "learned", int(net.window), net.features
            if engine == "auto":  # ONNX Runtime where the recursive form is kept as graphs
                engine = "onnx" if isinstance(net, exported.ExportedNet) else "torch"
            self.engine = engine
            self._runner = learned_runner(name, net, cast(str, self.form), self.vehicle,
                                          self.noise, engine, device)  # a net's form: a str
        self.envelope = checkpoint.stored_envelope(name, self.meta) if net is not None else None
        self.envelope_mode = check_mode(envelope_mode)
        self._envelope = (self.envelope.stream(**observer_terms(self.vehicle, self.noise,
                                                                self.window))
                          if self.envelope is not None and self.envelope_mode != "off" else None)
        self.reset()

    def check_envelope(self, m: np.ndarray, u: np.ndarray) -> EnvelopeCheck | None:
        """Which rows of a log (``m`` (T, 3), ``u`` (T, 2) as logged, read as :attr:`inputs`
        undoes them) lie outside the envelope of the observer's training inputs; None where
        there is no envelope to check."""
        if self.envelope is None:
            return None
        u = np.asarray(u, dtype=float)
        return self.envelope.check(np.asarray(m, dtype=float),
                                   u if self.inputs is None else self.inputs.undo(u),
                                   **observer_terms(self.vehicle, self.noise, self.window))

    @property
    def takes_missing_fixes(self) -> bool:
        """Whether steps without a position fix are allowed (classical, or trained for it)."""
        return self.net is None or bool(getattr(self.net, "fixes", False))

    @property
    def takes_receiver(self) -> bool:
        """Whether fixes without a heading and a receiver's channels are taken: by the
        classical observers, by the robust observer's recursive form on every engine (its
        update takes the channels a row holds, :mod:`lbo.models.recursive`) where it was
        trained with missing fixes (one trained with a fix at every step reads nothing else),
        and by a window net trained on a receiver's windows (:mod:`lbo.models.receiver_window`)."""
        return (self.net is None or bool(getattr(self.net, "receiver", False))
                or (isinstance(self._runner, RecursiveRunner) and self.takes_missing_fixes))

    @property
    def reads_gyro(self) -> bool:
        """Whether a gyro's yaw rate ``r_m`` is read: by the gyro EKF, and by a window net
        trained on a receiver's windows (the window filter only with ``model.gyro``)."""
        return self.name == classical.GYRO or (bool(getattr(self.net, "receiver", False))
                                               and getattr(self.net.net, "gyro", True))

    @property
    def carries_lateral(self) -> bool:
        """Whether the estimates come with the lateral states ``[beta, v_y, r]`` of a
        single-track body (``Estimate.lateral``, ``Estimates.lateral``): a learned observer
        trained around one (``experiment=dynamic``; KalmanNet's peers with
        ``model.body=single_track``) in its recursive form. The window form starts the body
        afresh in each window, and carries none from one estimate to the next."""
        return bool(getattr(self._runner, "carries_lateral", False))

    @property
    def lateral_error(self) -> np.ndarray | None:
        """(2, 2) the error of the ``[v_y, r]`` its body carries, fitted on the validation set
        as it trained (per state, the floor and the relative part of its variance:
        :attr:`lbo.models.net.WindowNet.lateral_error`) where it :attr:`carries_lateral`: the
        lateral states then come with variances (``Estimate.lateral_var``,
        ``Estimates.lateral_var``). None: no variance."""
        return getattr(self.net, "lateral_error", None) if self.carries_lateral else None

    @property
    def gives_covariance(self) -> bool:
        """Whether the estimates come with a covariance: the classical observers' and the
        window filter's (its recursive form's P), not a CNN's, LSTM's or KalmanNet's."""
        return self.net is None or isinstance(self._runner, RecursiveRunner)

    # ----------------------------------------------------------------------- construction

    @classmethod
    def load(cls, source: str | os.PathLike, vehicle: Vehicle | None = None,
             noise: Noise | None = None, *, alpha: float = 1.0, features: str | None = None,
             engine: str = "torch", device: str = "cpu", form: str | None = None,
             envelope_mode: str = "warn", gyro_noise: GyroNoise | None = None,
             inputs: InputTerms | None = None) -> Observer:
        """Load an observer.

        Parameters
        ----------
        source : one of
            - a checkpoint file (``.ckpt``, as ``lbo.train`` writes) or a ``file://`` URI;
            - an MLflow run id (32 hex digits): its ``checkpoints/best.ckpt`` (or its gyro noise);
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
        engine : ``"torch"``, ``"torchscript"``, ``"onnx"`` or ``"auto"`` (learned observers):
            ``"auto"`` and ``"onnx"`` run the recursive form's ONNX graphs without torch where
            ``lbo.train`` kept them (:mod:`lbo.serve.exported`); else ``"auto"`` is PyTorch.
        device : torch device of a learned observer (``"cpu"``, ``"cuda"``, ``"cuda:<n>"``),
            checked (and CUDA asked for) before any checkpoint is read.
        form : how a learned filter runs (:data:`FORMS`); None: :func:`default_form`.
        envelope_mode : ``"warn"``, ``"mark"`` or ``"off"``: what to do with samples outside
            the envelope of a learned observer's training inputs (see :class:`Observer`).
        gyro_noise : the noise of ``"gyro"`` (:class:`lbo.filters.gyro_noise.GyroNoise`, e.g. as
            :mod:`lbo.learn.gyro_fit` learns it from a drive); None: its defaults.
        inputs : the terms the inputs are undone by (see :class:`Observer`); None: none.

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
            return cls(source, vehicle, noise, alpha=alpha, gyro_noise=gyro_noise, inputs=inputs)
        learned = learned_noise(source)  # a run of lbo.train model=gyro_ekf: data, no code
        if learned is not None:
            return cls(classical.GYRO, vehicle or learned[1], noise or learned[2], alpha=alpha,
                       gyro_noise=learned[0], meta={"source": source}, inputs=inputs)
        with checkpoint_file(source) as path:
            found = (exported.load(path, engine) if engine in ("auto", "onnx") and form in (
                None, "recursive") and device == "cpu" else None)  # graphs: without torch
            if found is not None:  # read_checkpoint checks the features itself
                checkpoint.check_features(path, found[0].features, features)
            net, hp = found or checkpoint.read_checkpoint(path, features=features, device=device)
        meta = dict(hp.get("meta") or {})
        trained, trained_noise = checkpoint.trained_conditions(hp, path)
        if vehicle is not None and not np.isclose(vehicle.dt, trained.dt, rtol=1e-9):
            raise LboError(f"vehicle.dt={vehicle.dt:g} s, but the observer was trained at "
                           f"dt={trained.dt:g} s; resample the data to {trained.dt:g} s")
        return cls(f"{hp['model']['name']}-N{hp['window']}", vehicle or trained,
                   noise or trained_noise, net=net, alpha=alpha,
                   engine=engine, device=device, meta={**meta, "source": source}, form=form,
                   envelope_mode=envelope_mode, inputs=inputs)

    @classmethod
    def from_net(cls, net: Any, vehicle: Vehicle | None = None, noise: Noise | None = None,
                 *, name: str | None = None, engine: str = "torch",
                 device: str = "cpu", form: str | None = None) -> Observer:
        """Wrap an :class:`~lbo.models.net.WindowNet` (trained or not) as an observer."""
        name = name or f"{net.model}-N{net.window}"  # as a checkpoint of it is named
        return cls(name, vehicle, noise, net=net, engine=engine, device=device, form=form)

    # ----------------------------------------------------------------------- streaming

    @property
    def dt(self) -> float:
        return self.vehicle.dt

    def reset(self) -> None:
        """Forget the history: the next :meth:`step` is the first of a new log."""
        self._count = 0
        self._runner.reset()
        self._warned: set[str] = set()
        if self._envelope is not None:
            self._envelope.reset()

    def step(self, measurement: np.ndarray | Measurements | None, input: np.ndarray,
             receiver: np.ndarray | None = None) -> Estimate:
        """Take one sample and return the estimate at this step.

        Parameters
        ----------
        measurement : (3,) ``[x_m, y_m, psi_m]`` (m, m, rad), or None (or all NaN) when this
            step has no position fix (classical observers, and learned ones trained with
            ``fix_rates``); ``psi_m`` NaN alone: a position fix without a heading (where
            :attr:`takes_receiver`). Or one step's :class:`lbo.Measurements`, which holds the
            receiver's channels too.
        input : (2,) ``[V, delta]`` (m/s, rad) applied from this step to the next.
        receiver : (7,) this sample's receiver channels, a row of :meth:`run`'s ``receiver``,
            or None (where :attr:`takes_receiver`). ``gyro`` needs ``r_m`` at its first step.

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
            position fix without a heading for a window net, |x_m| or |y_m| beyond 1e7 m,
            |psi_m| beyond 2 pi, |V| beyond 100 m/s, |delta| beyond ``delta_max``; or no fix
            for a net trained with a fix at every step. A refused sample changes nothing.

        Notes
        -----
        Cost per call, whatever the log's length: scalar checks, a ring-buffer write and a
        net on a (1, N, 5) view; in the recursive form, one filter step, whatever N is. In a
        control loop run torch on one thread, or ``engine="onnx"`` (one thread already).
        """
        k = self._count
        m, u, receiver, fix = checked_sample(self, measurement, input, receiver, k)
        if self.inputs is not None:  # checked as logged, read as the terms undo them
            u = self.inputs.undo(u)
        row = m
        if receiver is not None or self.name == classical.GYRO or self._runner.reads_receiver:
            row, u = self._runner.sample(k, sampled(k, m, receiver), u)
        # checked: from here on the sample is taken
        outside = self._envelope(m, u) if self._envelope is not None else ()
        est = self._runner.take(k, row, u, fix)
        self._count += 1
        valid, reason = est.valid, est.reason
        if outside:  # outside: there is an envelope
            why = "outside the training envelope: " + ", ".join(
                cast(Envelope, self.envelope).describe(f) for f in outside)
            new = [f for f in outside if f not in self._warned]
            if self.envelope_mode == "mark":
                valid, reason = False, why if est.valid else est.reason
            elif new:  # once per field until reset: a control loop is not flooded
                self._warned.update(new)
                warnings.warn(f"{self.name}: step {k}: {why}", EnvelopeWarning, stacklevel=2)
        error = self.lateral_error
        return Estimate(est.state, valid, reason, est.cov, outside, est.lateral,
                        None if error is None else lateral_variance(error, est.lateral, u[0]))

    # ----------------------------------------------------------------------- batch

    def run(self, m: np.ndarray | Measurements, u: np.ndarray, batch_size: int = 4096, *,
            source: str | None = None, smooth: bool = False,
            receiver: np.ndarray | None = None) -> Estimates:
        """Estimates over a whole log at once (vectorised; the streaming state is untouched).

        Parameters
        ----------
        m : (T, 3) measurements ``[x_m, y_m, psi_m]``; a row of NaN is a step without a
            position fix, a NaN psi_m alone a position fix without a heading (where
            :attr:`takes_receiver`; a window net refuses it in one line). Or the log's
            :class:`lbo.Measurements` (T steps), which holds the receiver's channels too.
        u : (T, 2) inputs ``[V, delta]``.
        batch_size : windows per network call.
        source : what to call the log in messages (``"input log.csv"``); None: nothing.
        smooth : the Rauch-Tung-Striebel smoother's estimates (and covariances) after the
            filter (:mod:`lbo.filters.smoother`): every row drawn on the whole log, for offline
            logs. Classical observers and a window filter in its recursive form only.
        receiver : (T, 7) a receiver's channels, :data:`lbo.sim.columns.RECEIVER`
            ``[sx_m, sy_m, spsi_m, ve_m, vn_m, sv_m, r_m]``, NaN where a row holds none: the
            accuracy it reports per fix (the R of that step), a GNSS velocity (its course
            over ground, :mod:`lbo.filters.measure`) and a gyro's yaw rate (the ``gyro``
            observer's input, held from one reading to the next). Where :attr:`takes_receiver`;
            the adaptive EKF learns its own R and takes the velocity alone.

        Returns
        -------
        :class:`Estimates`, which unpacks as ``est, valid = obs.run(m, u)``; the same numbers
        as T calls of :meth:`step` after :meth:`reset`:

        state : (T, 3) ``[x, y, psi]``, psi in (-pi, pi].
        valid : (T,) bool, False on the first N-1 rows of a CNN or LSTM (EKF fallback),
            where the estimate is not finite (before the first fix; for a net that reads a
            receiver, where its window holds no heading), on the gyro EKF's rows that fail
            its consistency test (:mod:`lbo.filters.consistency`), and with ``envelope_mode=
            "mark"`` outside the training envelope (:meth:`check_envelope`; "warn": a warning).
        cov : (T, 3, 3) each estimate's covariance (the filter's P), NaN where the observer
            gives none (a CNN's or LSTM's windows) and on rows that are not valid.
        lateral : (T, 3) ``[beta, v_y, r]`` (rad, m/s, rad/s) where :attr:`carries_lateral`
            (beta = atan2(v_y, V) on the logged speed), NaN elsewhere and on rows that are
            not valid.
        lateral_var : (T, 3) their variances where :attr:`lateral_error` is known, NaN
            elsewhere.

        Raises
        ------
        LboError
            One line naming the row: ``python -m lbo.observe``'s checks
            (:func:`lbo.logs.checks.check_samples`); a fix without a heading, or a
            receiver's channels, where not :attr:`takes_receiver`; no fix for a net trained
            with one at every step; N steps without a fix for a window net (a NaN estimate).
        """
        if smooth and not self.gives_covariance:
            raise LboError(f"smooth: {self.name} has no filter to smooth"
                           + (" in its window form; use form=recursive" if self.form == "window"
                              and is_window_filter(self.net) else
                              "; smoothing takes a classical observer or the robust one"))
        m, u, receiver, fix = checked_log(self, m, u, receiver, source)
        logged = u
        if self.inputs is not None:  # checked as logged, read as the terms undo them
            u = self.inputs.undo(u)
        read = u
        # a log may hold its headings on any branch (accumulated rad): one branch for every
        # observer, as step() takes them (absolute features read the angle itself)
        m = m.copy()
        m[:, 2] = wrap_angle(m[:, 2])
        meas = Measurements.of(m, receiver)
        rows = m
        if self.net is None or self._runner.reads_receiver:
            rows, u = self._runner.log_rows(meas, u, source)
        elif receiver is not None:
            rows = bicycle_rows(meas, u, self.vehicle.wheelbase)
        est, covs, lateral = self._runner.run(rows, u, fix, smooth, batch_size)
        est[:, 2] = wrap_angle(est[:, 2])
        valid = np.isfinite(est).all(1) & (np.arange(len(m)) >= self._runner.first_valid)
        valid &= ~getattr(self._runner, "inconsistent", np.zeros(len(m), bool))  # gyro's test
        if self._envelope is not None:  # an envelope, and a mode other than off
            check = cast(EnvelopeCheck, self.check_envelope(m, logged))  # there is an envelope
            if self.envelope_mode == "mark":
                valid &= ~check.outside
            elif check.outside.any():
                warnings.warn(f"{self.name}{' on ' + source if source else ''}: "
                              + "; ".join(check.summary(cast(Envelope, self.envelope), read)),
                              EnvelopeWarning, stacklevel=2)
        covs[~valid] = np.nan
        lateral[~valid] = np.nan
        return Estimates(est, valid, covs, lateral,
                         lateral_variance(self.lateral_error, lateral, u[:, 0]))

    def __repr__(self) -> str:
        extra = (f", window={self.window}, features={self.features!r}, engine={self.engine!r}"
                 f", form={self.form!r}" if self.kind == "learned" else
                 (f", alpha={self.alpha:g}" if self.name == "oracle" else ""))
        return f"Observer({self.name!r}, dt={self.dt:g}{extra})"
