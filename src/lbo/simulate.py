"""`python -m lbo.simulate`: write a simulated vehicle log, to check an observer on the
conditions of your own car before trusting it.

    python -m lbo.simulate manoeuvre=stop_and_go alpha=1 [fix_rate=10] output=log.csv

``manoeuvre`` is ``stop_and_go`` (an urban drive that stands still more than 30% of the time,
with starts from rest and creeping) or any test manoeuvre of the data sets. ``fix_rate``
thins the position fixes to that rate (Hz; the inputs stay at 1/dt): the rows between fixes
have empty ``x_m, y_m, psi_m``. The log has the test-set columns (``traj, k, t``, the true
``x, y, psi``, ``V, delta``, ``x_m, y_m, psi_m``, ``alpha``, ``scored``), so both
``lbo.observe input=<log>`` and ``lbo.evaluate test_file=<log>.parquet`` score it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from lbo import schema
from lbo.cli import entry
from lbo.config import require
from lbo.datagen.clothoid import sample
from lbo.datagen.manoeuvres import MANOEUVRES, Chain
from lbo.datagen.pursuit import drive
from lbo.dynamic import SingleTrack
from lbo.errors import LboError
from lbo.vehicle import Vehicle, measure, wrap_angle

STOP_AND_GO = "stop_and_go"
# (kind, value, seconds): "stand" for the seconds, "go" to the speed at |a| = 2 m/s^2 and hold it
STOP_AND_GO_PROFILE = (
    ("stand", 0.0, 5.0), ("go", 10.0, 6.0), ("stand", 0.0, 8.0), ("go", 0.8, 6.0),
    ("stand", 0.0, 4.0), ("go", 13.0, 5.0), ("go", 5.0, 3.0), ("stand", 0.0, 7.0),
    ("go", 2.0, 4.0), ("go", 9.0, 6.0), ("stand", 0.0, 6.0),
)
ACCEL = 2.0  # m/s^2


def stop_and_go_speed(dt: float) -> np.ndarray:
    """(T,) speed profile of the stop-and-go drive, sampled every ``dt``."""
    v, out = 0.0, []
    for kind, target, seconds in STOP_AND_GO_PROFILE:
        if kind == "go":
            n = int(np.ceil(abs(target - v) / (ACCEL * dt)))
            out.append(v + np.sign(target - v) * np.minimum(np.arange(1, n + 1) * ACCEL * dt,
                                                            abs(target - v)))
            v = target
        else:
            n = int(np.ceil(v / (ACCEL * dt)))  # brake to a stop first
            out.append(np.maximum(v - np.arange(1, n + 1) * ACCEL * dt, 0.0))
            v = 0.0
        out.append(np.full(int(round(seconds / dt)), v))
    return np.concatenate(out)


def drive_stop_and_go(vehicle: Vehicle, process_sigma, rng: np.random.Generator,
                      car: SingleTrack | None = None) -> dict[str, np.ndarray]:
    """True states z (T, 3) and inputs u (T, 2) of the stop-and-go drive through town, by the
    kinematic bicycle or by the dynamic ``car``."""
    speed = stop_and_go_speed(vehicle.dt)
    path = Chain().straight(60).turn(10, -90, 4).straight(70).turn(12, 90, 5).straight(60) \
        .turn(9, 90, 4).straight(200).segments
    out = drive([sample(path, 0.1, lead_in=0.0, tail=100.0)], speed[None], vehicle,
                np.asarray(process_sigma), rng, ds=0.1, car=car)
    return {"z": out["z"][0], "u": out["u"][0]}


def thin(m: np.ndarray, every: int) -> np.ndarray:
    """Keep the fixes of rows 0, every, 2 every, ...; the others become NaN. (T, 3) -> (T, 3)."""
    out = np.full_like(m, np.nan)
    out[::every] = m[::every]
    return out


def simulate(cfg: DictConfig) -> pd.DataFrame:
    """The log ``cfg`` describes, as a frame with the test-set columns."""
    from lbo.datagen.build import drive_paths, slower_steps, spec_from_cfg
    from lbo.noise import Noise

    name = cfg.manoeuvre
    require(name == STOP_AND_GO or name in MANOEUVRES, "manoeuvre",
            f"{STOP_AND_GO} or one of {sorted(MANOEUVRES)}", name)
    alpha = cfg.alpha
    require(isinstance(alpha, (int, float)) and not isinstance(alpha, bool) and alpha >= 0,
            "alpha", "a noise scale >= 0", alpha)
    vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
    rate = cfg.get("fix_rate")
    require(rate is None or (isinstance(rate, (int, float)) and not isinstance(rate, bool)
                             and 0 < rate <= 1 / vehicle.dt), "fix_rate",
            f"null (a fix at every step) or a rate in Hz in (0, {1 / vehicle.dt:g}]", rate)
    require(isinstance(cfg.seed, int) and cfg.seed >= 0, "seed", "an integer >= 0", cfg.seed)
    rng = np.random.default_rng([cfg.seed, 7])
    spec = spec_from_cfg(cfg)  # checks the data, noise, vehicle and truth groups
    truth = spec.truth
    if name == STOP_AND_GO:
        out = drive_stop_and_go(vehicle, noise.process_sigma, rng, truth.car)
        z, u, run_in = out["z"], out["u"], 0
    else:
        man = MANOEUVRES[name]
        run_in = spec.test["run_in"]
        steps = slower_steps(np.array([man.steps]), spec.test)
        out = drive_paths(spec, [man.build()], steps, np.array([man.speed_shape]), run_in,
                          spec.test["speed_variation"], rng)
        z, u = out["z"][0, :run_in + steps[0]], out["u"][0, :run_in + steps[0]]
    m = measure(z, noise.meas(alpha), rng)
    if truth.sensors.gnss_sigma > 0:
        m += truth.sensors.drift((1, len(z)), vehicle.dt, alpha, rng)[0]
    u = truth.sensors.logged_inputs(u)
    m[:, 2] = wrap_angle(m[:, 2])
    if rate is not None:
        m = thin(m, max(1, int(round(1 / (rate * vehicle.dt)))))
    k = np.arange(len(z))
    return schema.frame(np.zeros(len(z)), k, vehicle.dt, z, u, m,
                        alpha=np.full(len(z), float(alpha)), scored=k >= run_in)


def run(cfg: DictConfig) -> Path:
    """Simulate and write ``cfg.output`` (.csv or .parquet); print what it holds."""
    from lbo.observe import check_output_path, write_table

    if not cfg.get("output"):
        raise LboError("output must be given: python -m lbo.simulate manoeuvre=stop_and_go "
                       "alpha=1 [fix_rate=10] output=<log.csv|.parquet>")
    output = check_output_path(str(cfg.output))
    df = simulate(cfg)
    write_table(df, output)
    fix = np.isfinite(df[list(schema.MEAS)].to_numpy()).all(1)
    still = float((df["V"] == 0).mean())
    duration = len(df) * float(cfg.vehicle.dt)
    print(f"{cfg.manoeuvre}: {len(df)} rows ({duration:.1f} s at {1 / cfg.vehicle.dt:g} Hz), "
          f"{fix.sum()} fixes ({fix.sum() / duration:.3g} Hz), standing still "
          f"{still:.0%} of the time, alpha {cfg.alpha:g}")
    print(f"simulated: {output}")
    return output


main = entry("simulate", run)


if __name__ == "__main__":
    sys.exit(main())
