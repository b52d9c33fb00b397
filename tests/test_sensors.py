"""Simulated real sensors (issue 36) against their specifications: the gyro bias random
walk's variance, the latency, the Gauss-Markov correlation time, the rates, the reported
accuracy; and the classical filters on simulated single-antenna logs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters import classical
from lbo.serve.observer import Observer
from lbo.sim.columns import RECEIVER
from lbo.sim.noise import Noise
from lbo.sim.receiver import Channel, ReceiverSpec, gyro_bias, sense
from lbo.sim.vehicle import Vehicle, simulate

DT = 0.02


def _drive(g: int, t: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """G smooth drives of T steps, without process noise (the truth's rate is its own)."""
    vehicle = Vehicle()
    k = np.arange(t)
    u = np.stack([12.0 + 3.0 * np.sin(2 * np.pi * k / 900), 0.1 * np.sin(2 * np.pi * k / 400)],
                 axis=1)
    u = np.broadcast_to(u, (g, t, 2)).copy()
    z = simulate(np.zeros((g, 3)), u, vehicle.dt, vehicle.wheelbase, np.zeros(3),
                 np.random.default_rng(seed))
    return z, u


def _quiet(**changes) -> ReceiverSpec:
    """A spec without any error, but for ``changes``."""
    spec = ReceiverSpec(position=Channel(rate=1.0), velocity=Channel(rate=1.0),
                        gyro=Channel(), gyro_bias=0.0, gyro_walk=0.0,
                        reported_spread=0.0)
    return dataclasses.replace(spec, **changes)


def test_the_gyro_bias_random_walk_has_the_variance_it_is_told():
    spec = _quiet(gyro_walk=2e-3, gyro_bias=0.01)
    b = gyro_bias((4000, 501), DT, spec, np.random.default_rng(0))
    seconds = 500 * DT
    walk = b[:, -1] - b[:, 0]
    # 4000 samples: the variance's relative standard error is sqrt(2 / 4000) = 2.2%
    assert np.var(walk) == pytest.approx(spec.gyro_walk**2 * seconds, rel=0.08)
    assert np.std(b[:, 0]) == pytest.approx(0.01, rel=0.06)
    half = b[:, 250] - b[:, 0]  # independent increments: variance linear in time
    assert np.var(half) == pytest.approx(spec.gyro_walk**2 * seconds / 2, rel=0.08)


def test_a_late_channel_holds_the_truth_of_latency_seconds_before():
    z, u = _drive(2, 600)
    spec = _quiet(position=Channel(rate=10.0, latency=0.13),
                  velocity=Channel(rate=10.0, latency=0.13))
    out = sense(z, u, DT, spec, 1.0, np.random.default_rng(0))
    fix = np.isfinite(out["x_m"][0])
    assert np.array_equal(np.flatnonzero(fix), np.arange(0, 600, 5))  # 10 Hz at 50 Hz

    def lag_of(measured: np.ndarray, truth: np.ndarray) -> float:
        """The shift (s, 1 ms grid) of ``truth`` that best matches ``measured`` at fixes."""
        rows = np.flatnonzero(fix)[10:]
        lags = np.arange(0.0, 0.3, 0.001)
        errs = [np.sum((measured[rows] - np.interp(rows * DT - lag, np.arange(600) * DT,
                                                  truth)) ** 2) for lag in lags]
        return float(lags[int(np.argmin(errs))])

    assert lag_of(out["x_m"][0], z[0, :, 0]) == pytest.approx(0.13, abs=0.0015)
    speed_east = u[0, :, 0] * np.cos(z[0, :, 2])
    assert lag_of(out["ve_m"][0], speed_east) == pytest.approx(0.13, abs=0.0015)


def test_the_drift_has_its_variance_and_correlation_time():
    z, u = _drive(200, 3000)
    tau, sigma = 4.0, 0.8
    spec = _quiet(position=Channel(drift=sigma, tau=tau))
    out = sense(z, u, DT, spec, 1.0, np.random.default_rng(1))
    e = out["x_m"] - z[..., 0]
    lag = int(round(tau / DT))
    assert np.var(e) == pytest.approx(sigma**2, rel=0.1)
    corr = np.mean(e[:, :-lag] * e[:, lag:]) / np.mean(e**2)
    assert corr == pytest.approx(np.exp(-1), abs=0.05)


def test_alpha_scales_the_receiver_and_the_reported_accuracy_tracks_it():
    z, u = _drive(50, 1000)
    spec = ReceiverSpec(position=Channel(rate=1.0, latency=0.0, white=0.3, drift=0.5, tau=5.0))
    for alpha in (1.0, 3.0):
        out = sense(z, u, DT, spec, alpha, np.random.default_rng(2))
        fix = np.isfinite(out["x_m"])
        err = np.concatenate([(out["x_m"] - z[..., 0])[fix], (out["y_m"] - z[..., 1])[fix]])
        true = np.sqrt(np.mean(err**2))
        assert true == pytest.approx(alpha * spec.position.sigma, rel=0.15)
        reported = np.sqrt(np.mean(out["sx_m"][fix] ** 2))
        assert reported == pytest.approx(true, rel=0.15)
        assert np.isnan(out["psi_m"]).all()  # one antenna


def test_the_gyro_reads_the_yaw_rate_plus_its_bias():
    z, u = _drive(3, 500)
    spec = _quiet(gyro_bias=0.02)
    out = sense(z, u, DT, spec, 1.0, np.random.default_rng(3))
    rate = u[..., 0] * np.tan(u[..., 1]) / Vehicle().wheelbase
    np.testing.assert_allclose((out["r_m"] - out["gyro_bias"])[:, :-1], rate[:, :-1],
                               rtol=0, atol=1e-9)
    assert np.ptp(out["gyro_bias"], axis=1).max() == 0.0  # no walk told: a constant bias


def test_same_seed_same_channels_and_a_bad_setting_is_one_line():
    z, u = _drive(2, 300)
    a = sense(z, u, DT, ReceiverSpec(), 2.0, np.random.default_rng(9))
    b = sense(z, u, DT, ReceiverSpec(), 2.0, np.random.default_rng(9))
    for k in a:
        assert np.array_equal(a[k], b[k], equal_nan=True)
    with pytest.raises(LboError, match=r"^receiver.position.rate must be null \(every step\) or a "
                                       r"rate in Hz in \(0, 50\], got 100.0$"):
        ReceiverSpec.from_cfg({"position": {"rate": 100.0}}, DT)
    with pytest.raises(LboError, match=r"^receiver.velocity.speed: not a field; accepted: "):
        ReceiverSpec.from_cfg({"velocity": {"speed": 1.0}}, DT)


@pytest.mark.parametrize("alpha", [1.0, 3.0, 6.0])
def test_every_classical_filter_takes_a_simulated_single_antenna_log(alpha):
    """Position at 1 Hz without heading, its accuracy and velocity: every classical observer
    runs it and beats the raw fixes on position."""
    vehicle, noise = Vehicle(), Noise.preset("paper")
    z, u = _drive(2, 3000, seed=4)
    out = sense(z, u, DT, ReceiverSpec(), alpha, np.random.default_rng(5))
    for i in range(2):
        m = np.column_stack([out["x_m"][i], out["y_m"][i], out["psi_m"][i]])
        r = np.column_stack([out[c][i] if c in out else np.full(3000, np.nan)
                             for c in RECEIVER])
        fix = np.isfinite(m[:, 0])
        raw = np.sqrt(np.mean((m[fix, :2] - z[i, fix, :2]) ** 2))
        for name in classical.OBSERVERS:
            est, valid = Observer.load(name, vehicle, noise).run(m, u[i], receiver=r)
            assert valid.all() and np.isfinite(est).all()
            e = np.sqrt(np.mean((est[1000:, :2] - z[i, 1000:, :2]) ** 2))
            assert e < raw, (name, alpha, e, raw)


def test_lbo_simulate_writes_a_receivers_log_that_the_filters_take():
    from helpers import compose_cfg
    from lbo.simulate import simulate as simulate_log

    plain = simulate_log(compose_cfg("simulate", ["manoeuvre=slalom"]))
    df = simulate_log(compose_cfg("simulate", ["manoeuvre=slalom", "receiver=single_antenna",
                                               "receiver.position.rate=5"]))
    # the truth and inputs are those drawn without a receiver; the fixes are the receiver's
    for c in ("t", "x", "y", "psi", "V", "delta"):
        assert np.array_equal(plain[c].to_numpy(), df[c].to_numpy())
    fix = df["x_m"].notna()
    assert np.array_equal(np.flatnonzero(fix), np.arange(0, len(df), 10))
    assert df["psi_m"].isna().all() and df["r_m"].notna().all()
    r = df.reindex(columns=list(RECEIVER)).to_numpy(dtype=float)  # no spsi_m: no heading
    est, valid = Observer.load("ukf").run(df[["x_m", "y_m", "psi_m"]].to_numpy(),
                                          df[["V", "delta"]].to_numpy(), receiver=r)
    assert valid.all() and np.isfinite(est).all()
    with pytest.raises(LboError, match=r"^fix_rate: a receiver sets its own rate"):
        simulate_log(compose_cfg("simulate", ["manoeuvre=slalom", "receiver=single_antenna",
                                              "fix_rate=10"]))


def test_the_velocity_leans_by_the_rear_slip_it_is_given():
    """Without errors, a receiver's velocity is V / cos(slip) along psi + slip; no slip: V
    along psi."""
    z, u = _drive(1, 200)
    slip = 0.03 * np.sin(np.arange(200) / 20.0)[None]
    for given, lean in ((slip, slip), (None, np.zeros_like(slip))):
        out = sense(z, u, DT, _quiet(velocity=Channel()), 1.0,
                    np.random.default_rng(0), slip=given)
        course = np.arctan2(out["vn_m"], out["ve_m"])
        assert np.abs(wrap_angle(course - z[..., 2] - lean)).max() < 1e-12
        assert np.allclose(np.hypot(out["ve_m"], out["vn_m"]), u[..., 0] / np.cos(lean),
                           rtol=1e-12)


def test_lbo_simulate_gives_the_car_that_slips_a_velocity_along_its_rear_axle():
    """On a slalom without velocity errors: the kinematic bicycle's course is its heading;
    the car that slips' course leaves it by its rear slip. A free drive of the car that slips
    has no slip to give: refused in one line."""
    from helpers import compose_cfg
    from lbo.simulate import simulate as simulate_log

    quiet = ["manoeuvre=slalom", "receiver=single_antenna", "receiver.velocity.rate=null",
             "receiver.velocity.latency=0", "receiver.velocity.white=0"]
    kinematic = simulate_log(compose_cfg("simulate", quiet))
    dynamic = simulate_log(compose_cfg("simulate", [*quiet, "data=dynamic"]))
    lean = {}
    for name, df in (("kinematic", kinematic), ("dynamic", dynamic)):
        moving = df["V"].to_numpy() > 2.0
        course = np.arctan2(df["vn_m"], df["ve_m"]).to_numpy()
        lean[name] = np.abs(wrap_angle(course - df["psi"].to_numpy()))[moving]
    assert lean["kinematic"].max() < 1e-9
    assert 0.005 < lean["dynamic"].max() < 0.1
    with pytest.raises(LboError, match=r"^receiver: a free_drive of the car that slips"):
        simulate_log(compose_cfg("simulate", ["manoeuvre=free_drive", "data=dynamic",
                                              "receiver=single_antenna"]))
