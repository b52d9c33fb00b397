"""The gyro-driven EKF (issue 36): heading turned by a yaw-rate gyro, its bias a state; on
simulated single-antenna logs with a biased gyro, through Observer.run and lbo.observe."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from helpers import compose_cfg
from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters import classical
from lbo.filters.gyro import gyro_ekf_batch
from lbo.filters.measure import rows
from lbo.serve.observer import Observer
from lbo.sim.columns import RECEIVER
from lbo.sim.logcheck import check_receiver
from lbo.sim.noise import Noise
from lbo.sim.receiver import Channel, ReceiverSpec, sense
from lbo.sim.vehicle import Vehicle, simulate
from lbo.simulate import simulate as simulate_log

DT = 0.02


@pytest.fixture(scope="module")
def drive():
    """Four 2-minute drives, single-antenna fixes at 1 Hz with velocities, and a gyro biased
    by 0.03 rad/s (1.7 deg/s) that walks slowly."""
    vehicle = Vehicle()
    t, g = 6000, 4
    k = np.arange(t)
    u = np.stack([12.0 + 3.0 * np.sin(2 * np.pi * k / 900), 0.1 * np.sin(2 * np.pi * k / 400)],
                 axis=1)
    u = np.broadcast_to(u, (g, t, 2)).copy()
    z = simulate(np.zeros((g, 3)), u, DT, vehicle.wheelbase, np.zeros(3),
                 np.random.default_rng(0))
    spec = ReceiverSpec(gyro=Channel(None, 0.0, 0.005), gyro_bias=0.0, gyro_walk=1e-4)
    out = sense(z, u, DT, spec, 1.0, np.random.default_rng(1))
    out["r_m"] = out["r_m"] + 0.03
    out["gyro_bias"] = out["gyro_bias"] + 0.03
    m = np.stack([rows(np.column_stack([out["x_m"][i], out["y_m"][i], out["psi_m"][i]]),
                       np.column_stack([out["sx_m"][i], out["sy_m"][i], np.full(t, np.nan)]),
                       np.column_stack([out["ve_m"][i], out["vn_m"][i]]), out["sv_m"][i],
                       u[i, :, 0]) for i in range(g)])
    return {"m": m, "u": u, "z": z, "gyro": np.stack([u[..., 0], out["r_m"]], -1), "out": out}


def _psi_rmse(est: np.ndarray, z: np.ndarray) -> float:
    return float(np.sqrt(np.mean(wrap_angle(est[:, 1500:, 2] - z[:, 1500:, 2]) ** 2)))


def test_the_gyro_ekf_learns_the_bias_and_holds_the_heading_between_fixes(drive):
    """Measured (4 drives): the bias estimates end 0.6-1.9 mrad/s from the true ~30 mrad/s;
    heading RMSE after 30 s: 16 mrad with the bias a state, 28 mrad told it is 0 (bias
    sigma 1e-6), the 1 Hz course over ground pulling that one back at every fix."""
    vehicle, noise = Vehicle(), Noise.preset("paper")
    R = classical.measurement_cov("ekf", noise, 1.0, 4)
    est, bias = gyro_ekf_batch(drive["m"], drive["gyro"], vehicle, noise.Q, R,
                               return_bias=True)
    blind = gyro_ekf_batch(drive["m"], drive["gyro"], vehicle, noise.Q, R, bias_sigma=1e-6,
                           bias_walk=0.0)
    true_bias = drive["out"]["gyro_bias"][:, -1]
    np.testing.assert_allclose(bias, true_bias, atol=0.003)
    assert _psi_rmse(est, drive["z"]) < 0.7 * _psi_rmse(blind, drive["z"])


def test_observer_run_takes_the_gyro_from_a_receivers_channels(drive):
    out, u, z = drive["out"], drive["u"][0], drive["z"][0]
    m = np.column_stack([out["x_m"][0], out["y_m"][0], out["psi_m"][0]])
    r = np.full((len(m), len(RECEIVER)), np.nan)
    for j, c in enumerate(RECEIVER):
        if c in out:
            r[:, j] = out[c][0]
    r[1::2, RECEIVER.index("r_m")] = np.nan  # a gyro at 25 Hz: each reading held to the next
    check_receiver(m, r)
    obs = Observer.load("gyro")
    est, valid, cov = obs.run(m, u, receiver=r, cov=True)
    assert valid.all() and np.isfinite(est).all() and np.isfinite(cov).all()
    assert np.sqrt(np.mean(wrap_angle(est[1500:, 2] - z[1500:, 2]) ** 2)) < 0.02
    with pytest.raises(LboError, match=r"^gyro needs a gyro's yaw rate: a column r_m"):
        obs.run(m, u, receiver=np.where(np.arange(len(RECEIVER)) == 6, np.nan, r))
    with pytest.raises(LboError, match=r"^step 0: gyro needs a gyro's yaw rate r_m"):
        obs.step(m[0], u[0])
    bad = r.copy()
    bad[5, 6] = 30.0  # deg/s read as rad/s
    with pytest.raises(LboError, match=r"row 5 has r_m=30 rad/s, beyond 10 rad/s"):
        check_receiver(m, bad)


def test_lbo_observe_runs_the_gyro_ekf_on_a_simulated_receivers_log(tmp_path):
    df = simulate_log(compose_cfg("simulate", ["manoeuvre=slalom", "receiver=single_antenna"]))
    df.to_csv(tmp_path / "log.csv", index=False)
    res = subprocess.run([sys.executable, "-m", "lbo.observe", "observer=gyro",
                          f"input={tmp_path / 'log.csv'}", f"output={tmp_path / 'est.csv'}"],
                         capture_output=True, text=True, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "receiver: sx_m, sy_m, ve_m, vn_m, sv_m, r_m taken" in res.stdout
    assert "rmse x" in res.stdout


def test_at_standstill_the_heading_is_held_and_the_gyro_reads_its_bias():
    """A car standing for 60 s after a fix with a heading: its gyro reads 0.02 rad/s of bias
    and noise. The heading does not drift and the bias is learned from the gyro alone."""
    vehicle, noise = Vehicle(), Noise.preset("paper")
    t = 3000
    rng = np.random.default_rng(4)
    m = np.full((1, t, 3), np.nan)
    m[0, 0] = [0.0, 0.0, 0.7]
    u = np.zeros((1, t, 2))
    u[0, :, 1] = 0.02 + 0.01 * rng.standard_normal(t)
    R = classical.measurement_cov("ekf", noise, 1.0, 1)
    est, bias = gyro_ekf_batch(m, u, vehicle, noise.Q, R, return_bias=True)
    assert np.abs(est[0, :, 2] - 0.7).max() < 1e-12
    assert bias[0] == pytest.approx(0.02, abs=0.002)
