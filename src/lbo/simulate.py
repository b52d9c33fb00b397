"""`python -m lbo.simulate`: write a simulated vehicle log, to check an observer on the
conditions of your own car before trusting it, or a fleet of drives to train one on.

    python -m lbo.simulate manoeuvre=stop_and_go alpha=1 [fix_rate=10] output=log.csv
    python -m lbo.simulate manoeuvre=free_drive duration=60 drives=20 data=dynamic \
        fix_rate=10 output=fleet/train/drive.csv

``manoeuvre`` is ``stop_and_go`` (an urban drive that stands still more than 30% of the time,
with starts from rest and creeping), ``free_drive`` (``duration`` seconds of one
friction-circle trajectory, as a training trajectory of the data sets, seeded by ``seed``) or
any test manoeuvre of the data sets. The ``car`` group (``data=dynamic`` picks ``car=dynamic``)
decides whether the car slips, the ``sensors`` group what its sensors' errors are. ``fix_rate``
thins the position fixes to that rate (Hz; the inputs stay at 1/dt): the rows between fixes
have empty ``x_m, y_m, psi_m``. The log has the test-set columns (``traj, k, t``, the true
``x, y, psi``, ``V, delta``, ``x_m, y_m, psi_m``, ``alpha``, ``scored``), so both
``lbo.observe input=<log>`` and ``lbo.evaluate test_file=<log>.parquet`` score it.

``drives=N`` (N > 1) writes N logs ``<stem>_000<suffix>`` ... ``<stem>_<N-1><suffix>`` beside
``output`` (its folder is created), drive i simulated with ``seed + i``: a fleet of varied
drives for ``data=logs``. Every file is written atomically.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import cast

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from lbo.core.angles import wrap_angle
from lbo.core.checks import integer, number, require
from lbo.core.cli import entry
from lbo.core.errors import LboError
from lbo.logs.checks import fix_period
from lbo.scoring import outages as outage
from lbo.scoring.outages import Outages
from lbo.sim import schema
from lbo.sim.columns import INPUT, MEAS, STATE
from lbo.sim.manoeuvres import MANOEUVRES
from lbo.sim.noise import check_alpha
from lbo.sim.stopgo import drive_stop_and_go
from lbo.sim.vehicle import Vehicle, measure

STOP_AND_GO = "stop_and_go"
FREE_DRIVE = "free_drive"


def thin(m: np.ndarray, every: int) -> np.ndarray:
    """Keep the fixes of rows 0, every, 2 every, ...; the others become NaN. (T, 3) -> (T, 3)."""
    out = np.full_like(m, np.nan)
    out[::every] = m[::every]
    return out


def free_drive(spec, duration: float, alpha: float, seed: int) -> dict[str, np.ndarray]:
    """``duration`` seconds of one friction-circle trajectory: a training trajectory of the
    data set ``spec`` describes (:func:`lbo.sim.datasets.make_train`, its truth model and
    sensors included), drawn from ``seed`` and measured at ``alpha``. Nothing is written to
    the data cache. Returns ``z`` (T, 3), ``u`` (T, 2), ``m`` (T, 3)."""
    from lbo.sim.datasets import make_train

    train = {**spec.train, "n_traj": 1, "duration": float(duration), "stop_and_go": 0.0,
             "alpha": float(alpha)}
    df = make_train(dataclasses.replace(spec, seed=int(seed), train=train))
    return {"z": df[list(STATE)].to_numpy(), "u": df[list(INPUT)].to_numpy(),
            "m": df[list(MEAS)].to_numpy()}


def check_duration(cfg: DictConfig, dt: float) -> float:
    """``cfg.duration`` (s) of a free drive: a number > 0 of at least two steps."""
    duration = number(cfg.get("duration"), "duration", low=0.0, low_open=True)
    require(round(duration / dt) >= 2, "duration", f"at least two steps ({2 * dt:g} s)",
            cfg.get("duration"))
    return duration


def check(cfg: DictConfig):
    """The data set's spec (:func:`lbo.sim.datasets.spec_from_cfg`), its data, noise, vehicle
    car and sensors groups checked; one line for a user's logs, which have nothing to simulate."""
    from lbo.logs.sets import is_logs
    from lbo.sim.datasets import spec_from_cfg

    if is_logs(cfg):
        raise LboError(f"data={cfg.data.name}: lbo.simulate drives a simulated data set's "
                       "manoeuvres, not a vehicle's logs; pick another data= (e.g. data=paper)")
    return spec_from_cfg(cfg)


def simulate(cfg: DictConfig, seed: int | None = None) -> pd.DataFrame:
    """The log ``cfg`` describes, as a frame with the test-set columns; ``seed`` (default
    ``cfg.seed``) draws its noise (and a free drive's trajectory)."""
    from lbo.sim.datasets import drive_within_grip, slower_steps
    from lbo.sim.noise import Noise

    name = cfg.manoeuvre
    require(name in (STOP_AND_GO, FREE_DRIVE) or name in MANOEUVRES, "manoeuvre",
            f"{STOP_AND_GO}, {FREE_DRIVE} or one of {sorted(MANOEUVRES)}", name)
    alpha = cfg.alpha
    check_alpha(alpha)
    vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
    rate = cfg.get("fix_rate")
    if rate is not None:
        number(rate, "fix_rate", low=0.0, high=1 / vehicle.dt, low_open=True,
               form=f"null (a fix at every step) or a rate in Hz in (0, {1 / vehicle.dt:g}]")
    seed = integer(cfg.seed if seed is None else seed, "seed", 0)
    duration = check_duration(cfg, vehicle.dt) if name == FREE_DRIVE else None
    rng = np.random.default_rng([seed, 7])
    spec = check(cfg)
    truth = spec.truth
    if name == FREE_DRIVE:  # the truth model and the sensors' errors come with make_train
        if truth.car is not None and cfg.get("receiver") is not None:
            raise LboError("receiver: a free_drive of the car that slips does not keep the rear "
                           "slip its velocity needs; use stop_and_go or a test manoeuvre")
        out = free_drive(spec, cast(float, duration), alpha, seed)  # checked for a free drive
        z, u, m, run_in, slip = out["z"], out["u"], out["m"], 0, None
    else:
        if name == STOP_AND_GO:
            out = drive_stop_and_go(vehicle, spec.motion_noise.process_sigma, rng, truth.car)
            z, u, slip, run_in = out["z"], out["u"], out["slip"], 0
        else:
            man = MANOEUVRES[name]
            run_in = spec.test["run_in"]
            steps = slower_steps(np.array([man.steps]), spec.test)
            out, steps, rng = drive_within_grip(spec, [man.build()], steps,
                                                np.array([man.speed_shape]), run_in, spec.test,
                                                lambda: np.random.default_rng([seed, 7]))
            z, u = out["z"][0, :run_in + steps[0]], out["u"][0, :run_in + steps[0]]
            slip = out["slip"][0, :run_in + steps[0]]
        m = measure(z, noise.meas(alpha), rng)
        if truth.sensors.gnss_sigma > 0:
            m += truth.sensors.drift((1, len(z)), vehicle.dt, alpha, rng)[0]
        u = truth.sensors.logged_inputs(u)
        m[:, 2] = wrap_angle(m[:, 2])
    if rate is not None:
        m = thin(m, fix_period(rate, vehicle.dt))
    k = np.arange(len(z))
    df = schema.frame(np.zeros(len(z)), k, vehicle.dt, z, u, m,
                      alpha=np.full(len(z), float(alpha)), scored=k >= run_in)
    if cfg.get("receiver") is not None:
        df = with_receiver(df, z, u, cfg, vehicle.dt, alpha, seed, slip)
    outages = Outages.from_cfg(cfg.get("outages"))
    if outages is not None:  # the receiver silent in windows while the car moves; truth kept
        df = outage.cut(df, outages, vehicle.dt)[1]
    return df


def with_receiver(df: pd.DataFrame, z: np.ndarray, u: np.ndarray, cfg: DictConfig, dt: float,
                  alpha: float, seed: int, slip: np.ndarray | None = None) -> pd.DataFrame:
    """The log ``df`` with its fixes replaced by the channels of ``cfg.receiver``
    (:mod:`lbo.sim.receiver`) of the truth z (T, 3) and inputs u (T, 2), drawn from their own
    generator (``[seed, 11]``: the log's other columns are those drawn without a receiver),
    and the gyro's true bias as a truth column ``b`` (rad/s), which an oracle is told; ``V``
    as the receiver's speed sensor reads it (``receiver.speed_scale``).
    slip : (T,) the rear axle's side slip (rad) that turns its velocity, or None (none)."""
    from lbo.sim.receiver import COLUMNS, ReceiverSpec, sense

    if cfg.get("fix_rate") is not None:
        raise LboError("fix_rate: a receiver sets its own rate (receiver.position.rate); "
                       "leave fix_rate null")
    spec = ReceiverSpec.from_cfg(cfg.receiver, dt)
    out = sense(z[None], u[None], dt, spec, alpha, np.random.default_rng([seed, 11]),
                None if slip is None else slip[None])
    df = df.copy()
    for c in COLUMNS:
        df[c] = out[c][0]
    df["b"] = out["gyro_bias"][0]
    df["V"] = df["V"] * spec.speed_scale  # what the speed sensor reads (the truth moved at V)
    return df


def fleet_paths(output: Path, drives: int) -> list[Path]:
    """``output`` itself for one drive, else ``<stem>_000<suffix>`` ... beside it."""
    if drives == 1:
        return [output]
    return [output.with_name(f"{output.stem}_{i:03d}{output.suffix}") for i in range(drives)]


def describe(cfg: DictConfig, df: pd.DataFrame) -> tuple[str, float]:
    """One line on what the log ``df`` holds, and its duration (s)."""
    fix = np.isfinite(df[["x_m", "y_m"]].to_numpy()).all(1)  # a position, with or without psi_m
    still = float((df["V"] == 0).mean())
    duration = len(df) * float(cfg.vehicle.dt)
    outages = Outages.from_cfg(cfg.get("outages"))
    # placed again on the blanked log: the same rows (the rule reads the speed and the first fix)
    gaps = len(outage.place(df, outages, float(cfg.vehicle.dt))) if outages else 0
    return (f"{cfg.manoeuvre}: {len(df)} rows ({duration:.1f} s at {1 / cfg.vehicle.dt:g} Hz), "
            f"{fix.sum()} fixes ({fix.sum() / duration:.3g} Hz), standing still "
            f"{still:.0%} of the time, alpha {cfg.alpha:g}"
            + (f", {gaps} GNSS outages of {outages.length_s:g} s (receiver columns blanked, "
               "truth kept)" if outages else "")), duration


def write_logs(cfg: DictConfig) -> Path:
    """Simulate and write ``cfg.output`` (.csv or .parquet), or ``cfg.drives`` logs beside it;
    print what they hold. Returns the path written (the first one of a fleet)."""
    from lbo.logs.io import check_output_path, write_table

    if not cfg.get("output"):
        raise LboError("output must be given: python -m lbo.simulate manoeuvre=stop_and_go "
                       "alpha=1 [fix_rate=10] output=<log.csv|.parquet>")
    drives = integer(cfg.get("drives", 1), "drives", 1)
    output = check_output_path(str(cfg.output))
    seed = integer(cfg.seed, "seed", 0)
    paths = fleet_paths(output, drives)
    if drives == 1:
        df = simulate(cfg)
        write_table(df, output)
        print(describe(cfg, df)[0])
        print(f"simulated: {output}")
        return output
    rows, seconds = 0, 0.0
    for i, path in enumerate(paths):
        df = simulate(cfg, seed=seed + i)
        write_table(df, path)
        line, duration = describe(cfg, df)
        rows, seconds = rows + len(df), seconds + duration
        print(f"{line}, seed {seed + i}: {path}", flush=True)
    print(f"simulated {drives} drives ({rows} rows, {seconds:.1f} s): {paths[0]} ... "
          f"{paths[-1].name}")
    return paths[0]


main = entry("simulate", write_logs)


if __name__ == "__main__":
    sys.exit(main())
