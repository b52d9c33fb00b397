"""The MBDS side-slip run shipped with lbo, and the single-track filters of side slip."""

import dataclasses

import numpy as np
import pandas as pd
import pytest

from lbo.core.errors import LboError
from lbo.filters.lateral import (
    LateralNoise,
    kinematic_beta,
    linear_single_track,
    nonlinear_single_track,
)
from lbo.sim import sideslip

NOISE = LateralNoise(delta=0.8, ay=1.0, r=0.005)


@pytest.fixture(scope="module")
def run():
    return sideslip.example()


def test_the_run_reads_in_si_units_with_lbos_names(run):
    assert list(run.columns) == list(sideslip.COLUMNS.values())
    assert len(run) == 55001 and (run.dtypes == np.float64).all()
    assert np.allclose(np.diff(run["t"]), sideslip.DT, atol=1e-9)
    # every angle in rad, every rate in rad/s (the repository's yawRateFilt, in deg/s, is not
    # shipped): a car's yaw rate stays under 1 rad/s, its road wheels under 0.5 rad
    assert 0.5 < run["r_m"].abs().max() < 1.0
    assert run["delta"].abs().max() < 0.5 and run["beta"].abs().max() < 0.1
    # the INS's side slip is the direction of its velocity: vy is truth too
    assert np.allclose(run["beta"], np.arctan2(run["vy"], run["vx"]), atol=1e-6)
    assert 16 < run["vx"].min() and run["vx"].max() < 62
    assert np.rad2deg(np.sqrt(np.mean(run["beta"] ** 2))) == pytest.approx(1.69, abs=0.01)


def test_the_spans_cut_the_run_by_time_sixty_twenty_twenty(run):
    spans = sideslip.split(run)
    assert list(spans) == ["train", "val", "test"]
    assert [len(s) for s in spans.values()] == [33001, 11000, 11000]
    joined = np.concatenate([s["t"].to_numpy() for s in spans.values()])
    assert np.array_equal(joined, run["t"].to_numpy())  # contiguous, in order, all of it
    assert all(s.index[0] == 0 for s in spans.values())


def _by_hand(vx, delta, y, car, noise, dt):
    """The reference filter (the repository's BetaStanfordLinear.m and LinearKF.m) written
    out one row at a time: the Euler-stepped model, Q = B q^2 B^T, P = (I - K C) P."""
    m, iz, lf, lr, cf, cr = car.mass, car.yaw_inertia, car.l_f, car.l_r, car.c_f, car.c_r
    x, P = np.zeros(2), np.eye(2) * 1e4
    R = np.diag([noise.ay**2, noise.r**2])
    out = [x]
    for i in range(1, len(vx)):
        v = vx[i - 1]
        A = np.array([[1 - dt * (cf + cr) / (m * v),
                       -dt * (1 + (lf * cf - lr * cr) / (m * v**2))],
                      [-dt * (lf * cf - lr * cr) / iz,
                       1 - dt * (lf**2 * cf + lr**2 * cr) / (iz * v)]])
        B = dt * np.array([cf / (m * v), lf * cf / iz])
        C = np.array([[-(cf + cr) / m, -(lf * cf - lr * cr) / (m * vx[i])], [0.0, 1.0]])
        D = np.array([cf / m, 0.0])
        xp = A @ x + B * delta[i - 1]
        Pp = A @ P @ A.T + np.outer(B, B) * noise.delta**2
        K = Pp @ C.T @ np.linalg.inv(C @ Pp @ C.T + R)
        x = xp + K @ (y[i] - C @ xp - D * delta[i])
        P = (np.eye(2) - K @ C) @ Pp
        out.append(x)
    return np.array(out)


def test_the_filter_is_the_reference_one_written_out_by_hand(run):
    part = run.iloc[20000:20400]  # a corner at 30-40 m/s
    vx, delta, y = sideslip.observed(part)
    est = linear_single_track(vx, delta, y, sideslip.CAR, NOISE, sideslip.DT)
    assert est.x.shape == (400, 2) and est.P.shape == (400, 2, 2)
    np.testing.assert_allclose(est.x, _by_hand(vx, delta, y, sideslip.CAR, NOISE, sideslip.DT),
                               rtol=0, atol=1e-9)
    assert np.allclose(est.P, est.P.transpose(0, 2, 1)) and (np.linalg.eigvalsh(est.P) > 0).all()
    np.testing.assert_allclose(est.vy(vx), vx * np.tan(est.beta))
    # it follows the INS's side slip far closer than straight ahead does
    beta = part["beta"].to_numpy()[100:]
    assert np.sqrt(np.mean((est.beta[100:] - beta) ** 2)) < 0.6 * np.sqrt(np.mean(beta**2))


def test_logs_filtered_together_give_what_each_gives_alone(run):
    parts = [run.iloc[a:a + 200] for a in (5000, 30000, 50000)]
    arrays = [sideslip.observed(p) for p in parts]
    together = linear_single_track(*(np.stack(a) for a in zip(*arrays, strict=True)),
                                   sideslip.CAR, NOISE, sideslip.DT)
    assert together.x.shape == (3, 200, 2)
    for g, a in enumerate(arrays):
        alone = linear_single_track(*a, sideslip.CAR, NOISE, sideslip.DT)
        np.testing.assert_allclose(together.x[g], alone.x, rtol=0, atol=1e-12)


def test_no_observer_reads_the_ins_truth(run):
    """Planted: the truth columns replaced by nonsense change nothing an observer gives."""
    part = run.iloc[10000:10300].copy()
    clean = linear_single_track(*sideslip.observed(part), sideslip.CAR, NOISE, sideslip.DT)
    part[list(sideslip.TRUTH)] = 1e9
    planted = linear_single_track(*sideslip.observed(part), sideslip.CAR, NOISE, sideslip.DT)
    np.testing.assert_array_equal(planted.x, clean.x)
    assert not set(sideslip.TRUTH) & {*sideslip.INPUTS, *sideslip.MEASURED}
    noise = LateralNoise.of(*sideslip.observed(part))
    assert noise.ay > 0 and noise.r > 0 and noise.delta > 0


def test_a_missing_measurement_is_a_prediction_step(run):
    vx, delta, y = sideslip.observed(run.iloc[1000:1100])
    y = y.copy()
    y[50:60] = np.nan
    est = linear_single_track(vx, delta, y, sideslip.CAR, NOISE, sideslip.DT)
    assert np.isfinite(est.x).all()
    assert np.trace(est.P[59]) > np.trace(est.P[49])  # it grew uncertain while blind


def test_tyres_that_never_saturate_make_the_ekf_the_linear_filter(run):
    """The EKF's tyres are linear at small slip: with a friction no tyre reaches, it gives
    the linear filter's side slip (up to the small-angle steps the linear model takes)."""
    vx, delta, y = sideslip.observed(run.iloc[20000:20300])
    linear = linear_single_track(vx, delta, y, sideslip.CAR, NOISE, sideslip.DT)
    grippy = dataclasses.replace(sideslip.CAR, mu=1e6)
    ekf = nonlinear_single_track(vx, delta, y, grippy, NOISE, sideslip.DT)
    assert np.abs(ekf.beta - linear.beta).max() < 0.02 * np.abs(linear.beta).max()
    assert np.abs(ekf.r - linear.r).max() < 0.02 * np.abs(linear.r).max()
    # at the car's own friction it departs from it where the tyres saturate
    real = nonlinear_single_track(vx, delta, y, dataclasses.replace(grippy, mu=1.0), NOISE,
                                  sideslip.DT)
    assert np.abs(real.beta - linear.beta).max() > 0.1 * np.abs(linear.beta).max()
    assert np.allclose(real.P, real.P.transpose(0, 2, 1)) and np.isfinite(real.x).all()


def test_the_friction_is_read_off_a_span_of_lateral_acceleration():
    span = pd.DataFrame({"ay_m": np.r_[np.full(999, 9.81), 30.0]})
    assert sideslip.friction(span) == pytest.approx(1.0, abs=0.03)  # the spike left out
    assert sideslip.friction(span, share=100) == pytest.approx(30.0 / 9.81)


def test_the_kinematic_side_slip_needs_only_the_axles():
    car = sideslip.CAR
    assert kinematic_beta(0.0, car) == 0.0
    assert kinematic_beta(0.1, car) == pytest.approx(np.arctan(1.07 * np.tan(0.1) / 2.4))


def test_bad_input_is_one_line():
    with pytest.raises(LboError, match=r"^vx: expected speeds above 0 m/s"):
        linear_single_track(np.zeros(5), np.zeros(5), np.zeros((5, 2)), sideslip.CAR, NOISE, 0.01)
    with pytest.raises(LboError, match=r"^linear_single_track needs vx and delta \(G, T\)"):
        linear_single_track(np.ones(5), np.zeros(4), np.zeros((5, 2)), sideslip.CAR, NOISE, 0.01)
    with pytest.raises(LboError, match=r"^noise.ay must be a number > 0, got 0.0$"):
        LateralNoise(delta=1.0, ay=0.0, r=1.0)
