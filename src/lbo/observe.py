"""`python -m lbo.observe`: run an observer on your own vehicle log, write the estimates.

    python -m lbo.observe observer=<checkpoint | run id | models:/name/version | ekf | oracle |
        adaptive | ukf | gyro> input=my_log.csv output=estimates.csv [resample=true] [max_gap=0.5]

The log (CSV or Parquet) holds one row per sample with the columns ``t`` (s), ``x_m``,
``y_m`` (m), ``psi_m`` (rad), ``V`` (m/s) and ``delta`` (rad), and optionally the true ``x,
y, psi``. A row with ``x_m, y_m, psi_m`` all empty is a step without a position fix (GNSS
slower than the inputs); the classical observers predict through it, and learned ones
trained with ``fix_rates`` take it. A receiver's log may add, row by row, the accuracy it
reports for each fix (``sx_m, sy_m`` m, ``spsi_m`` rad: the classical filters' R of that
step), a GNSS velocity (``ve_m, vn_m`` m/s, ``sv_m``: the course over ground, while the car
moves; :mod:`lbo.filters.measure`) and a gyro's yaw rate ``r_m`` (rad/s), which
``observer=gyro`` turns the heading with in place of the steering (:mod:`lbo.filters.gyro`);
``gyro_noise=<file.json>`` gives it a noise learned on a drive (:mod:`lbo.learn.gyro_fit`);
``adapt=true`` fits that noise to the log itself first, by its innovations (offline); with
any other observer (``ekf``, a learned one, ...) it fits the inputs' terms, a factor on the
speed and an offset and a factor on the steering, by the kinematic EKF's prediction errors
(:mod:`lbo.learn.input_fit`), and the observer reads the inputs they undo.
The whole log is checked before anything is written (:mod:`lbo.logs.checks`, the checks
:class:`lbo.Observer` applies too); a failed run writes no output file. The output has ``t,
x, y, psi, valid``: ``valid`` is false before the first fix, and on the first N-1 rows of a
CNN or LSTM, whose window is not full yet (those rows hold the EKF's estimate). An observer
that knows how sure it is (every classical one, and the robust observer) adds ``var_x,
var_y`` (m^2), ``var_psi`` (rad^2) and ``cov_xy`` (m^2), its covariance's entries; the CNN
and the LSTM have none. A learned observer with a single-track body (``experiment=dynamic``,
KalmanNet's peers with ``model.body=single_track``), run with ``form=recursive``, adds the
lateral states no sensor gives: ``beta`` (rad, the side slip at the centre of gravity),
``v_y`` (m/s) and ``r`` (rad/s), and where its checkpoint holds its body's error on the
validation set (trained on data with them), their variances ``var_beta, var_v_y, var_r``.

``smooth=true`` runs a Rauch-Tung-Striebel smoother after the filter (:mod:`lbo.filters.smoother`),
for the best estimate of an offline log from every sample before and after each row: the
classical observers and the robust observer (in its recursive form) only. ``form=recursive``
runs the robust observer's filter from step to step instead of over a window per estimate.
``engine=torchscript|onnx`` runs a learned observer in TorchScript or ONNX Runtime in place of
PyTorch (:mod:`lbo.serve.engines`); a long log through the robust observer's recursive form
runs fastest in ONNX Runtime (``benchmarks/bench_receiver_log.py``). ``engine=auto`` (the
default) runs the robust observer's recursive form from the ONNX graphs ``lbo.train`` kept of
it, without loading torch (:mod:`lbo.serve.exported`), and PyTorch otherwise.

``resample=true`` puts a log sampled at another (or an uneven) period onto the observer's
grid ``t0, t0 + dt, ...``: V and delta (and the true state) are interpolated linearly, but
never across a gap in ``t`` longer than ``max_gap`` seconds (0.5 s by default; such a log is
refused). Fixes are never interpolated: each lands on the grid row nearest to it (if within
dt/2), and every other row is a step without a fix, so an upsampled log has sparse fixes.
With the true state in the log, the RMSE per variable (over the valid rows) and the NRMSE
are printed; E_ref is lbo's EKF (R at alpha=1) on the same rows, as on a user's test logs
(:mod:`lbo.scoring.logscore`): a log's noise level is unknown, so the EKF scores 1 and a number
below 1 is better than it.

A learned observer's checkpoint stores the envelope of its training inputs (speed, steering,
noise scale alpha, steps between fixes; :mod:`lbo.models.envelope`). Rows outside it are
named in a warning line per field and in the output's ``outside`` column; ``envelope=mark``
also sets their ``valid`` to false, ``envelope=off`` skips the check.
"""

from __future__ import annotations

import dataclasses
import sys
import warnings
from typing import Any, cast

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from lbo.core.checks import boolean, integer, one_of
from lbo.core.cli import entry
from lbo.core.errors import LboError
from lbo.filters.consistency import SIGNIFICANCE, WINDOW
from lbo.learn.variogram import RECEIVER_NOISES
from lbo.logs.checks import check_device
from lbo.logs.formats import LogFormat
from lbo.logs.io import (
    check_log,
    check_output_path,
    check_period,
    check_steering,
    plot_path,
    read_log,
    resample,
    write_table,
)
from lbo.logs.units import MAX_GAP, check_max_gap, check_time_unit
from lbo.models.envelope import check_mode
from lbo.scoring import outages as outage
from lbo.scoring.metrics import nrmse
from lbo.scoring.outages import Outages
from lbo.sim.columns import COVARIANCE, LATERAL_ESTIMATE, LATERAL_VARIANCE, LOG, RECEIVER, STATE
from lbo.sim.measurements import Measurements

__all__ = ["main", "observe"]


def observe(cfg: DictConfig) -> dict[str, Any]:
    """Observe the log ``cfg.input`` with ``cfg.observer`` and write ``cfg.output``.

    Returns
    -------
    ``output`` (Path), ``observer`` (name), ``rows``, ``valid`` (rows with a full window),
    ``inconsistent`` (rows a classical observer's consistency test flagged), and, when the
    log holds the true state, ``rmse`` (3,) (m, m, rad), ``e_ref`` (3,) (the EKF's RMSE on
    the same rows) and ``nrmse``.
    """
    from lbo.filters.classical import check_gyro_noise, on_logs
    from lbo.filters.gyro_noise import GyroNoise
    from lbo.scoring.unscored import (
        heading_rows,
        heading_unseen,
        psi_text,
        scored_rmse,
        taken,
        unscored,
    )
    from lbo.serve.engines import engine_device
    from lbo.serve.observer import EnvelopeWarning, Observer
    from lbo.serve.refusals import no_receiver
    from lbo.serve.runners import is_window_filter
    from lbo.sim.noise import Noise, check_alpha
    from lbo.sim.vehicle import Vehicle

    for field in ("observer", "input", "output"):
        if cfg.get(field) is None or str(cfg.get(field)) == "":
            raise LboError(f"{field} must be given: python -m lbo.observe observer=<checkpoint "
                           "| run id | models:/name/version | ekf | oracle | adaptive | ukf> "
                           "input=<log.csv|.parquet> output=<estimates.csv|.parquet>")
    if not isinstance(cfg.observer, str):  # e.g. a run id of digits only
        raise LboError(f"observer: Hydra read {cfg.observer!r} as a number; quote it: "
                       "observer=\"'<run id>'\"")
    source = str(cfg.input)
    name = str(cfg.observer)
    classical = name in on_logs()  # lbo's own and the installed plug-ins'
    # the settings first: no log nor checkpoint is read for a run that cannot go on
    alpha = check_alpha(cfg.alpha)
    threads = integer(cfg.get("threads", 1), "threads", 1)
    device = check_device(cfg.get("device", "cpu"), probe=not classical)
    engine = cfg.get("engine", "auto")
    if not classical:
        engine_device(engine, device)  # before any checkpoint is read
    max_gap = check_max_gap(cfg.get("max_gap", MAX_GAP))
    output = check_output_path(str(cfg.output), source)
    plot = plot_path(cfg.get("plot"), output)
    smooth = boolean(cfg.get("smooth", False), "smooth")
    form = cfg.get("form")
    compare = _compared(cfg.get("compare"), plot)
    gyro_noise = cfg.get("gyro_noise")
    if gyro_noise is not None:
        check_gyro_noise(name, gyro_noise)  # before the file is read
        gyro_noise = GyroNoise.load(str(gyro_noise))
    adapt = boolean(cfg.get("adapt", False), "adapt")
    adapt_epochs = integer(cfg.get("adapt_epochs", 12), "adapt_epochs", 1)
    adapt_scales = boolean(cfg.get("adapt_scales", False), "adapt_scales")
    receiver_noise = one_of(cfg.get("adapt_receiver_noise", "learned"), RECEIVER_NOISES,
                            "adapt_receiver_noise")
    outages = Outages.from_cfg(cfg.get("outages"))
    if adapt_scales and not (adapt and name == "gyro"):
        raise LboError("adapt_scales: the factors on the speed and the gyro are learned by "
                       "the fit adapt=true makes for observer=gyro; pass both with it")
    if receiver_noise != "learned" and not (adapt and name == "gyro"):
        raise LboError("adapt_receiver_noise: how the fit adapt=true makes for observer=gyro "
                       "finds the receiver's factors; pass both with it")
    fmt = LogFormat.from_cfg(cfg)
    where = f"input {source}"
    df, origin = fmt.apply(read_log(source), where)
    truth = check_log(df, where, fmt.heading)

    vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
    mode = check_mode(cfg.get("envelope", "warn"))
    if smooth and engine == "auto":  # the smoother runs in PyTorch
        engine = "torch"
    kw = {"alpha": alpha, "features": cfg.get("features"), "device": device,
          "envelope_mode": mode, "engine": "torch" if classical else engine}
    obs = Observer.load(name, vehicle if classical else None, noise if classical else None,
                        form=form, gyro_noise=gyro_noise, **kw)
    # each loaded as the main one, before any work: a bad one fails before the output is
    # written; the envelope is the main observer's to say
    compared = {other: Observer.load(other, *((vehicle, noise) if other in on_logs()
                                               else (None, None)),
                                      **{**kw, "envelope_mode": "off",
                                         "engine": "torch" if other in on_logs() else engine})
                for other in compare}
    if sys.modules.get("torch") is not None:  # loaded for a learned observer: its small
        import torch  # batches and steps gain nothing from more threads (none: ONNX Runtime)

        torch.set_num_threads(threads)
    if obs.kind == "learned" and vehicle.delta_max > obs.vehicle.delta_max:
        # the steering limit the log is checked against (a car whose lock is past the
        # checkpoint's): the model stays the checkpoint's, and rows beyond the steering it was
        # trained on are flagged by its envelope
        obs.vehicle = dataclasses.replace(obs.vehicle, delta_max=vehicle.delta_max)
    if smooth and form is None and obs.form == "window" and is_window_filter(obs.net):
        # the form that has a filter to smooth, from the net already read
        obs = Observer(obs.name, obs.vehicle, obs.noise, net=obs.net, alpha=alpha,
                       engine=cast(str, obs.engine), device=device, meta=obs.meta,
                       form="recursive", envelope_mode=mode)  # a learned one's engine: a str
    check_steering(df, obs.vehicle, where)
    check_time_unit(df["t"].to_numpy(dtype=float), obs.dt, where)
    columns = (LOG[1:] + (STATE if truth else ())
               + tuple(c for c in RECEIVER if c in df.columns))
    if cfg.resample:
        df = resample(df, obs.dt, columns, max_gap, where)
    check_period(df["t"].to_numpy(dtype=float), obs.dt, where)
    spans = None
    if outages is not None:  # blanked before anything reads the log, the adapting fit too
        if not truth:
            raise LboError(f"outages: scored against the log's truth (x, y, psi); {where} "
                           "has none")
        spans, df = outage.cut(df, outages, obs.dt)

    if adapt and name == "gyro":
        start = gyro_noise or GyroNoise.from_q(noise.Q)
        if adapt_scales and start.speed_scale is None:
            start = start.with_scales()
        obs = _adapted(df, start, vehicle, noise, adapt_epochs, receiver_noise, kw)
    meas = Measurements.from_frame(df)  # read once: every observer below takes it
    m, u = meas.pose, df[["V", "delta"]].to_numpy(dtype=float)
    if adapt and name != "gyro":  # every other observer takes the inputs' terms
        obs.inputs = _fitted_inputs(meas, u, vehicle, noise)
    given = taken(obs, meas)  # what obs reads of the log: its run and its heading rows
    with warnings.catch_warnings():  # said below, one line per field
        warnings.simplefilter("ignore", EnvelopeWarning)
        found = obs.run(given, u, source=where, smooth=smooth)
    est, valid, cov = found.state, found.valid, found.cov
    envelope = obs.check_envelope(m, u) if mode != "off" else None
    result: dict[str, Any] = {"output": output, "observer": obs.name, "rows": len(df),
                              "valid": int(valid.sum())}
    if obs.inputs is not None:
        result["input_terms"] = dataclasses.asdict(obs.inputs)
    # a classical filter's heading before its first one is 0 rad, sd 1 rad, and valid: left
    # out of the heading's RMSE (it is scored for the observers, not for their start)
    unseen = heading_unseen(obs, meas, u) if truth else np.zeros(len(df), bool)
    if truth:
        z = df[list(STATE)].to_numpy(dtype=float)
        result["rmse"] = scored_rmse(est, z, valid, unseen)
        result["heading_unseen"] = int((valid & unseen).sum())
        result["e_ref"] = _ekf_reference(obs, meas, u, z, valid, unseen, where)
        result["nrmse"] = (nrmse(result["rmse"], result["e_ref"])
                           if valid.any() and np.isfinite(result["e_ref"]).all()
                           else float("nan"))
    out = pd.DataFrame({"t": df["t"].to_numpy(dtype=float), "x": est[:, 0], "y": est[:, 1],
                        "psi": est[:, 2], "valid": valid})
    if obs.gives_covariance:
        for name_, (i, j) in zip(COVARIANCE, ((0, 0), (1, 1), (2, 2), (0, 1))):
            out[name_] = cov[:, i, j]
    if obs.carries_lateral:
        for i, name_ in enumerate(LATERAL_ESTIMATE):
            out[name_] = found.lateral[:, i]
    if obs.lateral_error is not None:
        for i, name_ in enumerate(LATERAL_VARIANCE):
            out[name_] = found.lateral_var[:, i]
    if envelope is not None:  # the fields of the training envelope each row is outside of
        out["outside"] = envelope.reasons()
    if origin is not None:  # the estimate where the log's positions were: degrees
        out["lat"], out["lon"] = origin.to_geodetic(est[:, 0], est[:, 1])
    write_table(out, output)
    others = {}
    for other, o in compared.items():
        e, ok = o.run(taken(o, meas), u, source=where)
        others[o.name if o.name not in others and o.name != obs.name else other] = \
            np.where(ok[:, None], e, np.nan)
        if truth:
            blind = heading_unseen(o, meas, u)
            r = scored_rmse(e, df[list(STATE)].to_numpy(dtype=float), ok, blind)
            print(f"compare {other}: rmse x {r[0]:.6g} m, y {r[1]:.6g} m, "
                  f"{psi_text(o.name, r[2], ok, blind)} ({int(ok.sum())} valid rows)")
    if spans is not None and outages is not None:
        through = outage.score({obs.name: np.where(valid[:, None], est, np.nan), **others},
                               df, spans, obs.dt)
        result["outages"] = through
        print(f"through {len(spans)} GNSS outages of {outages.length_s:g} s (every "
              f"{outages.every_s:g} s while moving), every receiver column blanked (so in "
              f"{output} too):")
        print(outage.markdown(through), end="")
    if plot is not None:
        from lbo.core import plots

        plots.save(plots.observed_log(out["t"].to_numpy(), m, np.where(valid[:, None], est, np.nan),
                                      obs.name, df[list(STATE)].to_numpy(dtype=float)
                                      if truth else None, cov if obs.gives_covariance else None,
                                      others),
                   plot)

    what = (f"learned, window {obs.window}, features {obs.features}" if obs.kind == "learned"
            else f"classical, noise {obs.noise.name}, wheelbase {obs.vehicle.wheelbase:g} m"
            + (f", its noise learned by run {name}" if obs.meta.get("source") == name else ""))
    print(f"observer {obs.name} ({what}, dt {obs.dt:g} s) on {len(df)} rows"
          + (f" (resampled from {source})" if cfg.resample else "")
          + (", smoothed (RTS)" if smooth else ""))
    if not fmt.is_plain or origin is not None:
        print("read as: " + ", ".join(filter(None, [fmt.describe(), (
            f"lat/lon -> metres east/north of {origin.lat:.7f}, {origin.lon:.7f}"
            if origin is not None else None)])))
    fix = np.isfinite(m[:, :2]).all(1)  # a position, with or without a heading
    duration = len(df) * obs.dt
    print(f"fixes: {int(fix.sum())} of {len(df)} rows ({fix.sum() / duration:.3g} Hz; inputs "
          f"at {1 / obs.dt:g} Hz)")
    if any(c in df.columns for c in RECEIVER):
        told = [c for c, held in zip(RECEIVER, np.isfinite(meas.receiver).any(0)) if held]
        idle = "r_m" in told and obs.takes_receiver and not obs.reads_gyro
        read = [c for c in told if not (idle and c == "r_m")]
        print(f"receiver: {', '.join(read) or 'no value'} "
              + ("taken (reported accuracy as R, velocity as course over ground)"
                 if obs.takes_receiver else f"not read: {no_receiver(obs.name)}")
              + (f"; r_m not read by {name} (observer=gyro reads it, and a net trained "
                 "with experiment=receiver, the window filter with model.gyro=true)"
                 if idle else ""))
    if obs.kind == "learned":
        asked = (vehicle, noise.process_sigma, noise.measurement_sigma)
        if asked != (obs.vehicle, obs.noise.process_sigma, obs.noise.measurement_sigma):
            print("note: a learned observer keeps its checkpoint's vehicle and noise "
                  f"(noise {obs.noise.name}, wheelbase {obs.vehicle.wheelbase:g} m); "
                  "vehicle= and noise= apply to the classical observers (a larger "
                  "vehicle.delta_max widens the steering check)")
        if obs.envelope is None:
            print(f"envelope: not checked ({obs.name}'s checkpoint predates lbo storing the "
                  "range of its training inputs)")
        elif envelope is not None and envelope.outside.any():
            flag = ("marked valid=false" if mode == "mark" else
                    "still valid: envelope=mark marks them invalid")
            for line in envelope.summary(obs.envelope, u):
                print(f"warning: {line}")
            print(f"envelope: {int(envelope.outside.sum())} rows outside what {obs.name} was "
                  f"trained on ({flag}; column outside names the fields)")
    # the reasons that apply, each with its count: a log of position fixes without psi_m nor a
    # velocity never gives the robust observer a heading, not a window or a first fix
    reasons = unscored(obs, est, valid, fix, heading_rows(given, u, obs.vehicle.wheelbase),
        envelope.outside if envelope is not None and mode == "mark" else None)
    if result["valid"] < len(df):
        print(f"valid: {result['valid']} of {len(df)} rows; not scored: {'; '.join(reasons)}")
    # a classical observer's estimate is finite from its first fix on: a finite one not valid
    # is one its consistency test flagged (the gyro EKF's, lbo.filters.consistency)
    flagged = int((np.isfinite(est).all(1) & ~valid).sum()) if obs.kind == "classical" else 0
    result["inconsistent"] = flagged
    if flagged:
        print(f"consistency: {flagged} rows flagged valid=false: innovations inconsistent with "
              f"the covariance (the NIS of the last {WINDOW} updates beyond its "
              f"{SIGNIFICANCE:.1%} chi-square bound; lbo.filters.consistency)"
              + ("; the heading's and the gyro bias's variances widened to learn the bias "
                 "again" if name == "gyro" else ""))
    if truth and not valid.any():
        short = obs.kind == "learned" and obs.form == "window" and len(df) < obs.window
        print("rmse: no valid row to score (" + (f"the log is shorter than the window, "
                                                 f"N={obs.window}" if short else
                                                 "; ".join(reasons)) + ")")
    elif truth:
        e = result["rmse"]
        print(f"rmse x {e[0]:.6g} m, y {e[1]:.6g} m, {psi_text(obs.name, e[2], valid, unseen)} "
              f"({result['valid']} valid rows)")
        ref = result["e_ref"]
        print(f"nrmse {result['nrmse']:.6g} (E_ref: the EKF on the same rows, x {ref[0]:.4g} m, "
              f"y {ref[1]:.4g} m, psi {ref[2]:.4g} rad; below 1 is better than the EKF)"
              if np.isfinite(result["nrmse"]) else
              "nrmse: not scored (" + ("the EKF, its reference, never observed its heading on "
                                       "these rows)" if np.isfinite(e[2]) else
                                       "no heading was observed to score)"))
    print(f"observed: {output}" + (f"; plot: {plot}" if plot is not None else ""))
    return result


def _ekf_reference(obs: Any, meas: Measurements, u: np.ndarray, z: np.ndarray,
                   valid: np.ndarray, unseen: np.ndarray, where: str) -> np.ndarray:
    """E_ref (3,) of the NRMSE on a log: the RMSE of lbo's EKF (R at alpha=1, ``obs``'s
    vehicle and noise) over the rows scored for ``obs`` (``valid`` (T,), the heading without
    ``unseen`` (T,) ones nor those before the EKF's own first heading). As on a user's test
    logs, where the noise level is unknown: the EKF scores 1, below 1 is better than it."""
    from lbo.scoring.unscored import heading_unseen, scored_rmse, taken
    from lbo.serve.observer import Observer

    ekf = Observer.load("ekf", obs.vehicle, obs.noise)
    est, ok = ekf.run(taken(ekf, meas), u, source=where)
    return scored_rmse(est, z, valid & ok, unseen | heading_unseen(ekf, meas, u))


def _adapted(df: pd.DataFrame, start: Any, vehicle: Any, noise: Any, epochs: int,
             receiver_noise: str, kw: dict[str, Any]) -> Any:
    """The gyro EKF with its noise fitted on the log ``df`` by its innovations, from
    ``start``, the receiver's factors as ``receiver_noise`` says
    (:func:`lbo.learn.gyro_fit.adapt`), said in one line with the time it took."""
    import time

    from lbo.learn.gyro_fit import adapt
    from lbo.serve.observer import Observer

    how = (", the receiver's noise by its variogram" if receiver_noise == "variogram" else "")
    print(f"adapting: the gyro EKF's noise to this log's innovations{how}, {epochs} epochs",
          flush=True)
    began = time.perf_counter()
    # only epoch 0's estimate of the rest: the epochs' losses are the fit's business
    fitted = adapt(df, start, vehicle, noise, epochs=epochs, progress=lambda line: print(
        "  " + line, flush=True) if line.startswith("estimate:") else None,
        receiver_noise=receiver_noise)
    print(f"adapted: the gyro EKF's noise fitted to this log's innovations (offline: it read "
          f"the whole log first; no truth read), {epochs} epochs in "
          f"{time.perf_counter() - began:.1f} s, kept epoch {fitted.best_epoch}: {fitted.noise}")
    return Observer.load("gyro", vehicle, noise, gyro_noise=fitted.noise, **kw)


def _fitted_inputs(meas: Measurements, u: np.ndarray, vehicle: Any, noise: Any) -> Any:
    """The inputs' terms of the kinematic EKF fitted on the log by its position innovations
    (:func:`lbo.learn.input_fit.fit`), said in a line with the time it took."""
    from lbo.learn import input_fit
    from lbo.serve.rows import bicycle_rows

    print("adapting: the inputs' terms (speed factor, steering offset and factor) to this "
          "log's fixes", flush=True)
    rows = (bicycle_rows(meas, u, vehicle.wheelbase) if meas.reads_receiver else meas.pose)
    fitted = input_fit.fit(rows, u, vehicle, noise)
    print(f"adapted: {fitted.terms.describe()} (offline: it read the whole log first; no truth "
          f"read), {fitted.runs} EKF runs in {fitted.seconds:.1f} s, the fixes' mean square "
          f"innovation {fitted.start_loss:.3g} -> {fitted.loss:.3g} m^2")
    return fitted.terms


def _compared(compare: Any, plot: Any) -> list[str]:
    """The observers of ``compare``, checked: a list of names or sources, drawn in the plot."""
    if compare is None or (hasattr(compare, "__len__") and not len(compare)):
        return []
    if isinstance(compare, str) or not all(isinstance(c, str) for c in compare):
        raise LboError(f"compare: expected a list of observers, e.g. compare=[ekf,gyro], got "
                       f"{compare!r}")
    if plot is None:
        raise LboError("compare: draws more observers in the plot; give plot=true (or a .png)")
    return [str(c) for c in compare]


main = entry("observe", observe)


if __name__ == "__main__":
    sys.exit(main())
