"""A receiver's channels (issue 36): the accuracy it reports per fix as the R of that step,
a GNSS velocity as the course over ground, their one-line errors, and their way through
``lbo.observe``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from helpers import compose_cfg, observe
from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters import classical, measure
from lbo.logs.checks import check_receiver
from lbo.logs.io import resample
from lbo.serve.observer import Observer
from lbo.sim.columns import RECEIVER
from lbo.sim.measurements import Measurements
from lbo.sim.noise import Noise
from lbo.sim.schema import Trajectories
from lbo.sim.vehicle import Vehicle
from lbo.simulate import simulate

LOG = ["t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]


# --------------------------------------------------------------------------- the model


@pytest.mark.parametrize("name", ["ekf", "ukf"])
def test_per_step_h_and_r_match_a_filter_written_out_by_hand(name):
    """At standstill (V = 0) the bicycle does not move: x_{k+1} = x_k, P grows by Q, and the
    filters are linear. Rows hold random subsets of the fix, the heading, their reported
    accuracies and the course; a textbook Kalman filter, its H and R built by hand from what
    each row holds, must give the same estimates and covariances."""
    rng = np.random.default_rng(11)
    g, t = 3, 80
    vehicle, noise = Vehicle(), Noise.preset("paper")
    R1 = classical.measurement_cov(name, noise, 1.0, g)[0]
    m = np.full((g, t, measure.WIDTH), np.nan)
    m[..., :3] = rng.normal(scale=[1.0, 1.0, 0.05], size=(g, t, 3))
    m[..., 3:6] = rng.uniform(0.2, 2.0, size=(g, t, 3)) * [1.0, 1.0, 0.02]
    m[..., 6] = rng.normal(scale=0.05, size=(g, t))
    m[..., 7] = rng.uniform(0.01, 0.1, size=(g, t))
    pos, head, told, told_psi, course = (rng.random((5, g, t)) < 0.5)
    m[..., 0:2][~pos] = np.nan
    m[..., 2][~(pos & head)] = np.nan
    m[..., 3:5][~(pos & told)] = np.nan
    m[..., 5][~(pos & head & told_psi)] = np.nan
    m[..., 6:8][~course] = np.nan
    m[:, 0, :6] = [0.1, -0.2, 0.01, 0.5, 0.7, 0.01]  # a full fix to start from
    u = np.zeros((g, t, 2))
    est, cov = classical.estimate(name, m, u, vehicle, noise)
    for i in range(g):
        x = m[i, 0, :3].copy()
        P = np.diag(m[i, 0, 3:6] ** 2)
        for k in range(1, t):
            P = P + noise.Q
            row = m[i, k]
            zs, hs, rs = [], [], []
            for c in range(3):
                if np.isfinite(row[c]):
                    zs.append(row[c])
                    hs.append(np.eye(3)[c])
                    rs.append(row[3 + c] ** 2 if np.isfinite(row[3 + c]) else R1[c, c])
            if np.isfinite(row[6]):
                zs.append(row[6])
                hs.append([0.0, 0.0, 1.0])
                rs.append(row[7] ** 2)
            if zs:
                h, r = np.array(hs), np.diag(rs)
                K = P @ h.T @ np.linalg.inv(h @ P @ h.T + r)
                x = x + K @ (np.array(zs) - h @ x)
                P = (np.eye(3) - K @ h) @ P
            np.testing.assert_allclose(est[i, k], x, rtol=0, atol=1e-9)
            np.testing.assert_allclose(cov[i, k], P, rtol=0, atol=1e-9)


def test_the_course_is_the_direction_of_travel_and_nothing_at_standstill():
    ve = np.array([10.0, 0.0, 0.05, np.nan, -3.0, 0.3])
    vn = np.array([0.0, 5.0, 0.0, np.nan, 0.0, 0.0])
    sv = np.array([0.1, np.nan, 0.1, 0.1, 0.1, 0.1])
    V = np.array([10.0, 5.0, 0.05, 0.0, -3.0, 0.3])
    course, s = measure.course_over_ground(ve, vn, sv, V)
    np.testing.assert_allclose(course[[0, 1]], [0.0, np.pi / 2])
    np.testing.assert_allclose(s[[0, 1]], [0.1 / 10, measure.SV_DEFAULT / 5])
    assert np.isnan(course[[2, 3, 5]]).all() and np.isnan(s[[2, 3, 5]]).all()
    assert wrap_angle(course[4]) == pytest.approx(0.0)  # reversing west: heading east


def test_a_reported_accuracy_replaces_r_and_its_correlations():
    R = np.array([[[4.0, 1.0, 0.1], [1.0, 4.0, 0.1], [0.1, 0.1, 0.01]]])
    m = measure.widen(np.zeros((1, 3)))
    assert measure.step_cov(m, R) is R
    m[0, 3:5] = [0.5, 3.0]
    out = measure.step_cov(m, R)
    np.testing.assert_allclose(out[0], [[0.25, 0.0, 0.0], [0.0, 9.0, 0.0], [0.0, 0.0, 0.01]])


# --------------------------------------------------------------------------- on a drive


@pytest.fixture(scope="module")
def drive():
    """Four simulated slaloms at 50 Hz: single-antenna fixes (no heading) at 1 Hz, and GNSS
    velocities (truth plus 0.1 m/s noise) with them."""
    frames = [simulate(compose_cfg("simulate", ["manoeuvre=slalom"]), seed=s)[LOG]
              for s in range(4)]
    t = min(len(f) for f in frames)
    arr = np.stack([f.to_numpy(float)[:t] for f in frames])
    rng = np.random.default_rng(5)
    z, u = arr[..., 6:9], arr[..., 4:6]
    m = np.full((4, t, 3), np.nan)
    m[:, ::50, :2] = arr[:, ::50, 1:3]
    vel = np.full((4, t, 2), np.nan)
    heading = z[:, ::50, 2]
    vel[:, ::50] = (u[:, ::50, :1] * np.stack([np.cos(heading), np.sin(heading)], -1)
                    + rng.normal(scale=0.1, size=(4, heading.shape[1], 2)))
    return {"m": m, "vel": vel, "u": u, "z": z}


def _psi_rmse(est: np.ndarray, z: np.ndarray) -> float:
    return float(np.sqrt(np.mean(wrap_angle(est[..., 2] - z[..., 2]) ** 2)))


@pytest.mark.parametrize("name", classical.OBSERVERS)
def test_a_gnss_velocity_gives_the_heading_that_a_single_antenna_lacks(drive, name):
    """Measured (seeds 0-3): 1 Hz position fixes alone leave the heading to the motion
    (0.040 rad for the EKF, oracle and UKF, 0.065 adaptive); their GNSS velocities bring it
    to 0.0085 rad."""
    vehicle, noise = Vehicle(), Noise.preset("paper")
    meas = dataclasses.replace(Measurements.of(drive["m"]), velocity=drive["vel"])
    rows = measure.rows(meas, drive["u"][..., 0])
    blind = classical.estimate(name, drive["m"], drive["u"], vehicle, noise).mean
    seen = classical.estimate(name, rows, drive["u"], vehicle, noise).mean
    print(name, _psi_rmse(blind, drive["z"]), _psi_rmse(seen, drive["z"]))
    assert _psi_rmse(seen, drive["z"]) < 0.6 * _psi_rmse(blind, drive["z"])


# --------------------------------------------------------------------------- the channel rules


def _log(t: int = 6) -> tuple[np.ndarray, np.ndarray]:
    m = np.column_stack([np.arange(t) * 0.2, np.zeros(t), np.zeros(t)])
    m[1] = np.nan
    m[2, 2] = np.nan
    return m, np.full((t, len(RECEIVER)), np.nan)


@pytest.mark.parametrize("row, column, value, message", [
    (0, "sx_m", 1.0, "row 0 has sx_m without sy_m"),
    (0, "sy_m", 1.0, "row 0 has sy_m without sx_m"),
    (1, "sx_m sy_m", 1.0, r"row 1 has an accuracy \(sx_m, sy_m\) without a position fix"),
    (2, "spsi_m", 0.01, "row 2 has spsi_m without a heading psi_m"),
    (3, "ve_m", 1.0, "row 3 has ve_m without vn_m"),
    (3, "vn_m", 1.0, "row 3 has vn_m without ve_m"),
    (4, "sv_m", 0.1, r"row 4 has sv_m without a velocity \(ve_m, vn_m\)"),
    (0, "sx_m sy_m", -1.0, r"row 0 has sx_m=-1 m, not a 1-sigma in \(0, 10000\] m"),
    (0, "spsi_m", 0.0, r"row 0 has spsi_m=0 rad, not a 1-sigma in \(0, 1\] rad"),
    # a sigma too large to be a receiver's squares towards inf: NaN estimates (issue 68)
    (0, "sx_m sy_m", 1e160, r"row 0 has sx_m=1e\+160 m, not a 1-sigma in \(0, 10000\] m"),
    (2, "sx_m sy_m", 2e4, r"row 2 has sx_m=20000 m, not a 1-sigma in \(0, 10000\] m"),
    (0, "spsi_m", 1.5, r"row 0 has spsi_m=1.5 rad, not a 1-sigma in \(0, 1\] rad"),
    (5, "ve_m vn_m", 400.0, "row 5 has ve_m=400 m/s, beyond 100 m/s"),
])
def test_each_channel_rule_is_one_line_naming_the_row(row, column, value, message):
    m, r = _log()
    for c in column.split():
        r[row, RECEIVER.index(c)] = value
    with pytest.raises(LboError, match=message) as e:
        check_receiver(m, r, "input log.csv")
    assert "\n" not in str(e.value) and str(e.value).startswith("input log.csv: ")
    assert "an accuracy comes with what it is the accuracy of" in str(e.value)


def test_every_accuracy_channel_is_bounded_at_its_limit():
    """Each reported 1-sigma is taken up to its limit and refused past it, naming the row,
    the column and the range (issue 68: sx_m=1e160 passed and the filters wrote NaN)."""
    m, r = _log()
    r[0, :3] = [1e4, 1e4, 1.0]
    r[3, 3:6] = [20.0, 0.0, 100.0]  # a velocity between fixes, at the largest sigma
    check_receiver(m, r)
    for c, value, line in ((1, 1e4 * 1.01, r"row 0 has sy_m=10100 m, not a 1-sigma in "
                                           r"\(0, 10000\] m; "),
                           (5, 101.0, r"row 3 has sv_m=101 m/s, not a 1-sigma in "
                                      r"\(0, 100\] m/s; ")):
        bad = r.copy()
        bad[0 if c < 3 else 3, c] = value
        with pytest.raises(LboError, match=r"^input log.csv: " + line
                           + r"an accuracy comes with .* sv_m in \(0, 100\] m/s$"):
            check_receiver(m, bad, "input log.csv")


def test_a_full_receiver_row_and_an_inf_one():
    m, r = _log()
    r[0] = [1.0, 1.0, 0.01, 3.0, 4.0, 0.1, 0.2]
    r[1, 3:5] = [3.0, 4.0]  # a velocity between fixes
    check_receiver(m, r)
    r[4, 5] = np.inf
    with pytest.raises(LboError, match="column 'sv_m' has NaN or inf"):
        check_receiver(m, r)


def test_a_learned_observer_refuses_a_receivers_channels_in_one_line():
    from lbo.models.net import WindowNet

    obs = Observer.from_net(WindowNet("cnn", 20, "relative"))
    m = np.column_stack([np.arange(30) * 0.2, np.zeros(30), np.zeros(30)])
    r = np.full((30, len(RECEIVER)), np.nan)
    r[0, :2] = 1.0
    with pytest.raises(LboError, match=r"^receiver: cnn-N20 does not take a receiver's "
                                       r"channels; the classical observers \(ekf, oracle, "
                                       r"adaptive, ukf\) do, the robust observer "
                                       r"\(filternet\) in its recursive form, and a CNN, "
                                       r"LSTM or window filter trained on a receiver "
                                       r"\(experiment=receiver\)$"):
        obs.run(m, np.tile([10.0, 0.0], (30, 1)), receiver=r)


# --------------------------------------------------------------------------- through the CLI


def test_resample_lands_velocities_and_accuracies_never_interpolated():
    df = pd.DataFrame({"t": [0.0, 0.011, 0.055, 0.1], "x_m": [0.0, np.nan, 1.0, np.nan],
                       "y_m": [0.0, np.nan, 0.0, np.nan], "psi_m": np.nan, "V": 10.0,
                       "delta": 0.0, "sx_m": [0.5, np.nan, 0.7, np.nan],
                       "sy_m": [0.6, np.nan, 0.8, np.nan], "ve_m": [np.nan, 9.0, np.nan, 8.0],
                       "vn_m": [np.nan, 1.0, np.nan, 2.0]})
    out = resample(df, 0.02, ("x_m", "y_m", "psi_m", "V", "delta", "sx_m", "sy_m", "ve_m",
                              "vn_m"), None)
    np.testing.assert_array_equal(out["sx_m"].to_numpy(), [0.5, np.nan, np.nan, 0.7, np.nan,
                                                           np.nan])
    np.testing.assert_array_equal(out["ve_m"].to_numpy(), [np.nan, 9.0, np.nan, np.nan, np.nan,
                                                           8.0])
    np.testing.assert_array_equal(out["x_m"].to_numpy(), [0.0, np.nan, np.nan, 1.0, np.nan,
                                                          np.nan])
    np.testing.assert_allclose(out["V"].to_numpy(), 10.0)


def test_lbo_observe_takes_reported_accuracies_and_velocities(tmp_path):
    """A single-antenna log through the CLI: the accuracy is taken as R (a fix reported ten
    times worse moves the estimate less) and the velocity as the heading."""
    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom"]))[LOG].head(600).copy()
    fix = df.index % 50 == 0
    df.loc[:, "psi_m"] = np.nan
    df.loc[~fix, ["x_m", "y_m"]] = np.nan
    df["sx_m"] = np.where(fix, 0.2, np.nan)
    df["sy_m"] = np.where(fix, 0.2, np.nan)
    df["ve_m"] = np.where(fix, df["V"] * np.cos(df["psi"]), np.nan)
    df["vn_m"] = np.where(fix, df["V"] * np.sin(df["psi"]), np.nan)
    outs = {}
    for label, scale in (("tight", 1.0), ("loose", 10.0)):
        log = df.assign(sx_m=df["sx_m"] * scale, sy_m=df["sy_m"] * scale)
        log.to_csv(tmp_path / f"{label}.csv", index=False)
        res = observe("observer=ekf", f"input={tmp_path / label}.csv",
                      f"output={tmp_path / label}.out.csv", cwd=tmp_path)
        assert res.returncode == 0, res.stderr
        assert "receiver: sx_m, sy_m, ve_m, vn_m taken" in res.stdout
        outs[label] = pd.read_csv(tmp_path / f"{label}.out.csv")
    at = np.flatnonzero(fix)[1:]
    pull = {k: np.abs(o["x"].to_numpy()[at] - df["x_m"].to_numpy()[at]).mean()
            for k, o in outs.items()}
    assert pull["tight"] < 0.5 * pull["loose"]
    err = wrap_angle(outs["tight"]["psi"].to_numpy() - df["psi"].to_numpy())[100:]
    assert np.sqrt(np.mean(err**2)) < 0.02
    bad = df.assign(sx_m=np.where(fix, -1.0, np.nan))
    bad.to_csv(tmp_path / "bad.csv", index=False)
    res = observe("observer=ekf", f"input={tmp_path / 'bad.csv'}",
                  f"output={tmp_path / 'bad.out.csv'}", cwd=tmp_path)
    assert res.returncode != 0 and not (tmp_path / "bad.out.csv").exists()
    assert "row 0 has sx_m=-1 m, not a 1-sigma in (0, 10000] m" in res.stderr


@pytest.mark.parametrize("observer", ["ekf", "ukf"])
def test_lbo_observe_refuses_an_accuracy_no_receiver_reports(tmp_path, observer):
    """Issue 68: sx_m = sy_m = 1e160 passed the check; the filters then wrote NaN after the
    second fix with RuntimeWarnings, exit 0 (with smooth=true every row invalid). Now one
    line naming the row, the column and the range, before anything is written."""
    from lbo.observe import observe

    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom"]))[LOG].head(300).copy()
    fix = df.index % 50 == 0
    df.loc[:, "psi_m"] = np.nan
    df.loc[~fix, ["x_m", "y_m"]] = np.nan
    df["sx_m"] = df["sy_m"] = np.where(fix, 1e160, np.nan)
    df.to_csv(tmp_path / "log.csv", index=False)
    out = tmp_path / "est.csv"
    cfg = compose_cfg("observe", [f"observer={observer}", f"input={tmp_path / 'log.csv'}",
                                  f"output={out}", "smooth=true"])
    with pytest.raises(LboError, match=r"^input .*log\.csv: row 0 has sx_m=1e\+160 m, not a "
                                       r"1-sigma in \(0, 10000\] m; an accuracy comes with"):
        observe(cfg)
    assert not out.exists()


# --------------------------------------------------------------------------- starting between fixes


@pytest.mark.parametrize("name", [*classical.OBSERVERS, "gyro"])
def test_a_log_that_starts_between_fixes_is_filtered_from_its_first_fix(name):
    """Three trajectories in one batch: one starting on a fix, one 13 rows before its first,
    one without any. Each gives what it gives alone from its first fix, NaN before."""
    vehicle, noise = Vehicle(), Noise.preset("paper")
    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom", "fix_rate=5"]))[LOG].head(300)
    m = df[["x_m", "y_m", "psi_m"]].to_numpy(float)
    u = df[["V", "delta"]].to_numpy(float)
    if name == "gyro":
        u = np.column_stack([u[:, 0], u[:, 0] * np.tan(u[:, 1]) / vehicle.wheelbase])
    ms = np.stack([m, np.roll(m, 3, axis=0), np.full_like(m, np.nan)])
    ms[1, :13] = np.nan  # fixes every 10 rows from row 3: the first one left is row 13
    us = np.stack([u, np.roll(u, 3, axis=0), u])
    est, cov = classical.estimate(name, ms, us, vehicle, noise)
    alone = classical.estimate(name, ms[1:2, 13:], us[1:2, 13:], vehicle, noise).mean
    # (batched against alone: rounding differs by 1e-12)
    np.testing.assert_allclose(est[1, 13:], alone[0], rtol=0, atol=1e-9)
    assert np.isnan(est[1, :13]).all() and np.isnan(est[2]).all() and np.isnan(cov[2]).all()
    np.testing.assert_allclose(est[0], classical.estimate(name, ms[:1], us[:1], vehicle,
                                                          noise).mean[0], rtol=0, atol=1e-9)


def test_logs_scored_from_each_segments_first_fix():
    from lbo.scoring import logscore

    vehicle, noise = Vehicle(), Noise.preset("paper")
    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom", "fix_rate=5"]))[LOG].head(300)
    m = df[["x_m", "y_m", "psi_m"]].to_numpy(float)[None].repeat(2, 0)
    m[1, :25] = np.nan
    arr = Trajectories(z=df[["x", "y", "psi"]].to_numpy(float)[None].repeat(2, 0),
                       u=df[["V", "delta"]].to_numpy(float)[None].repeat(2, 0), m=m,
                       mask=np.arange(300) >= classical.first_fixes(m)[:, None],
                       lengths=np.full(2, 300), traj=np.arange(2), alpha=np.ones(2),
                       file=np.array([0, 1]))
    est = logscore.peer_estimates(arr, vehicle, noise)
    scores = logscore.table(est, arr, ["a.csv", "b.csv"])
    assert np.isfinite(scores[["rmse_x", "rmse_y", "rmse_psi", "nrmse"]].to_numpy()).all()


# --------------------------------------------------------------------------- streaming


@pytest.mark.parametrize("name", [*classical.OBSERVERS, "gyro"])
def test_step_with_a_receivers_channels_gives_what_run_gives(name):
    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom", "receiver=single_antenna",
                                           "receiver.position.rate=5"])).head(400)
    m = df[["x_m", "y_m", "psi_m"]].to_numpy(float)
    u = df[["V", "delta"]].to_numpy(float)
    r = df.reindex(columns=list(RECEIVER)).to_numpy(float)
    r[1::2, RECEIVER.index("r_m")] = np.nan  # a 25 Hz gyro
    obs = Observer.load(name)
    est, valid = obs.run(m, u, receiver=r)
    assert valid.all()
    stepped = np.array([obs.step(mk, uk, receiver=rk).state for mk, uk, rk in zip(m, u, r)])
    np.testing.assert_allclose(stepped[:, :2], est[:, :2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(wrap_angle(stepped[:, 2] - est[:, 2]), 0, atol=1e-9)
    obs.reset()
    bad = r[0].copy()
    bad[0] = -1.0
    with pytest.raises(LboError, match=r"^step 0: row 0 has sx_m=-1 m, not a 1-sigma in "
                                       r"\(0, 10000\] m"):
        obs.step(m[0], u[0], receiver=bad)


def test_step_refuses_what_it_cannot_take_in_one_line():
    gyro = Observer.load("gyro")
    with pytest.raises(LboError, match=r"^step 0: gyro needs a gyro's yaw rate r_m at its "
                                       r"first step \(receiver\[6\]\)$"):
        gyro.step([0.0, 0.0, np.nan], [10.0, 0.0])
    with pytest.raises(LboError, match=r"^step 0: receiver must be 7 numbers"):
        Observer.load("ekf").step([0.0, 0.0, 0.0], [10.0, 0.0], receiver=[1.0, 1.0])
    from lbo.models.net import WindowNet

    learned = Observer.from_net(WindowNet("cnn", 20, "relative"))
    with pytest.raises(LboError, match=r"^step 0: cnn-N20 does not take a receiver's channels"):
        learned.step([0.0, 0.0, 0.0], [10.0, 0.0], receiver=np.full(7, np.nan))


def _stepped(kf, m: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The stepper's poses and covariances, one update() per row (no coasting)."""
    est, cov = [kf.x.copy()], [kf.P.copy()]
    for k in range(1, m.shape[1]):
        kf.update(m[:, k], u[:, k - 1])
        est.append(kf.x.copy())
        cov.append(kf.P.copy())
    return np.stack(est, 1), np.stack(cov, 1)


def test_runs_without_a_measurement_coast_in_one_call_as_the_steps_would_go():
    """Between 2 Hz fixes (position only, some with an accuracy, courses) at 50 Hz, the EKF
    takes each run of rows that hold nothing in closed form (KalmanStepper.coast):
    the numbers of one update per row, to rounding; the adaptive EKF and a trajectory that
    has no heading yet step row by row."""
    from lbo.filters.kalman import AdaptiveStepper, KalmanStepper
    from lbo.filters.stepper import run_stepper
    from lbo.sim.vehicle import simulate as roll

    vehicle, rng = Vehicle(), np.random.default_rng(0)
    g, t = 3, 1500
    k = np.arange(t)
    u = np.broadcast_to(np.stack([10 + 3 * np.sin(k / 300), 0.1 * np.sin(k / 200)], 1),
                        (g, t, 2)).copy()
    u[1, :, 0] *= -0.5  # one reverses
    z = roll(np.zeros((g, 3)), u, vehicle.dt, vehicle.wheelbase, np.zeros(3), rng)
    m = measure.widen(z + rng.standard_normal(z.shape) * [0.5, 0.5, 0.02]).copy()
    m[:, k % 25 != 0] = np.nan
    m[:, :, 2] = np.nan
    m[0, k % 50 == 0, 3:5] = 0.4
    m[:, k % 25 == 0, 6] = wrap_angle(z[:, k % 25 == 0, 2] + np.where(u[:, :1, 0] < 0, np.pi, 0))
    m[:, k % 25 == 0, 7] = 0.02
    Q = np.diag([0.0667**2, 0.0667**2, 0.00113**2])
    R = np.broadcast_to(np.diag([1.0, 1.0, 0.0174**2]), (g, 3, 3))
    kf = KalmanStepper(m[:, 0], vehicle, Q, R)
    calls = []
    update = kf.update
    kf.update = lambda *a: calls.append(1) or update(*a)
    est, cov = run_stepper(kf, m, u)
    assert len(calls) == len(range(25, t, 25))  # only the fix rows step one by one
    ref, ref_cov = _stepped(KalmanStepper(m[:, 0], vehicle, Q, R), m, u)
    assert np.abs(est - ref).max() < 1e-9 and np.abs(cov - ref_cov).max() < 1e-12
    adaptive = AdaptiveStepper(m[:, 0], vehicle, Q, R, forgetting=0.99,
                               r_floor=np.full((g, 3), 1e-6))
    blind = KalmanStepper(measure.widen(np.array([[0.0, 0.0, np.nan]])), vehicle, Q, R[:1])
    assert not adaptive.coasts and not blind.coasts


def test_fixes_and_velocities_late_by_a_latency_are_brought_forward_to_their_row():
    """A car on a circle at 15 m/s and 0.2 rad/s, its fixes 50 ms and its velocities 80 ms
    late: brought forward, each velocity is the one of its row (a turn is exact on a
    circle), each fix the position of its row to the third order (V r^2 l^3 / 24: 3 um, the
    arc against its chord);
    a fix before the first velocity stays as it is."""
    speed, rate, dt, t = 15.0, 0.2, 0.02, 400
    time = np.arange(t) * dt

    def state(s):
        psi = rate * s
        pos = speed / rate * np.column_stack([np.sin(psi), 1.0 - np.cos(psi)])
        return pos, speed * np.column_stack([np.cos(psi), np.sin(psi)])

    fix, _ = state(time - 0.05)
    _, velocity = state(time - 0.08)
    velocity[:3] = np.nan
    fix_now, vel_now = measure.undelayed(fix, velocity, np.full(t, rate), 0.05, 0.08)
    pos, vel = state(time)
    np.testing.assert_allclose(vel_now[3:], vel[3:], rtol=0, atol=1e-9)
    assert np.isnan(vel_now[:3]).all()
    np.testing.assert_array_equal(fix_now[:3], fix[:3])
    np.testing.assert_allclose(fix_now[3:], pos[3:], rtol=0, atol=4e-6)
    assert np.abs(fix[3:] - pos[3:]).max() > 0.7  # 0.75 m along the road, uncorrected
    with pytest.raises(LboError, match=r"^velocity_latency: expected a number of seconds >= 0"):
        measure.undelayed(fix, velocity, np.full(t, rate), 0.05, -0.1)


def test_a_speed_sensor_that_reads_off_scales_the_logs_speed_only():
    """``receiver.speed_scale=1.02``: the log's V is the car's speed times 1.02, while the
    truth, the fixes and the gyro are those of the same drive with an exact sensor (the
    learned factor that undoes it: docs/logs.md section 11); out of [0.5, 2] it is one line."""
    args = ["receiver=single_antenna", "manoeuvre=free_drive", "duration=20"]
    exact = simulate(compose_cfg("simulate", args))
    off = simulate(compose_cfg("simulate", [*args, "receiver.speed_scale=1.02"]))
    assert (exact["V"] > 1.0).mean() > 0.5
    np.testing.assert_allclose(off["V"], 1.02 * exact["V"], rtol=1e-12)
    same = [c for c in exact.columns if c != "V"]
    pd.testing.assert_frame_equal(off[same], exact[same])
    with pytest.raises(LboError, match=r"^receiver\.speed_scale must be a number in "
                                       r"\[0\.5, 2\], got 3\.0$"):
        simulate(compose_cfg("simulate", [*args, "receiver.speed_scale=3.0"]))
