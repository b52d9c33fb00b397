"""Position fixes without a heading (issue 36): the one masked Joseph update, the classical
observers on position-only logs, and each channel rule's one-line error."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from helpers import compose_cfg, observe
from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters import classical
from lbo.filters.start import HEADING_VAR0
from lbo.filters.update import joseph_update
from lbo.logs.checks import check_fixes, check_sample, check_samples
from lbo.models.net import WindowNet
from lbo.serve.observer import Observer
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle
from lbo.simulate import simulate

LOG = ["t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]
RULE = r"a row holds x_m and y_m \(a position fix\), with or without psi_m, or none of them"


def _spd(rng: np.random.Generator, g: int, n: int) -> np.ndarray:
    a = rng.normal(size=(g, n, n))
    return a @ a.swapaxes(-1, -2) + n * np.eye(n)


def _subset_update(x, P, y, H, R, held):
    """The textbook update of one trajectory with its held channels only."""
    h, r, yy = H[held], R[np.ix_(held, held)], y[held]
    if not held.any():
        return x, P
    S = h @ P @ h.T + r
    K = P @ h.T @ np.linalg.inv(S)
    A = np.eye(len(x)) - K @ h
    return x + K @ yy, A @ P @ A.T + K @ r @ K.T


def test_a_channel_not_held_adds_nothing_the_subset_update_to_rounding():
    rng = np.random.default_rng(3)
    g, n, p = 8, 5, 3
    x, P = rng.normal(size=(g, n)), _spd(rng, g, n)
    H, R = rng.normal(size=(g, p, n)), _spd(rng, g, p)
    y = rng.normal(size=(g, p))
    held = np.array([[1, 1, 1], [1, 1, 0], [0, 0, 0], [0, 1, 0], [1, 0, 1], [0, 1, 1],
                     [1, 0, 0], [0, 0, 1]], bool)
    y[~held] = np.nan  # what is not held may be anything
    xs, Ps, *_ = joseph_update(x, P, y, H, R, held)
    for i in range(g):
        xe, Pe = _subset_update(x[i], P[i], y[i], H[i], R[i], held[i])
        np.testing.assert_allclose(xs[i], xe, rtol=0, atol=1e-12)
        np.testing.assert_allclose(Ps[i], Pe, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(xs[2], x[2])  # nothing held: the prior, exactly
    np.testing.assert_allclose(Ps[2], P[2], rtol=0, atol=1e-15)


def test_per_step_h_and_r_match_a_hand_written_constant_velocity_filter():
    """A 2-D constant-velocity model [px, py, vx, vy]: position and velocity measured at some
    steps, position only at others, nothing at the rest; the masked update against a
    standard-form filter written out by hand, one trajectory at a time."""
    rng = np.random.default_rng(7)
    g, t, dt = 3, 60, 0.1
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt
    Q = np.diag([1e-3, 1e-3, 1e-2, 1e-2])
    H, R = np.eye(4), np.diag([0.5, 0.4, 0.05, 0.06])
    z = np.zeros((g, t, 4))
    z[:, 0] = rng.normal(size=(g, 4))
    for k in range(1, t):
        z[:, k] = z[:, k - 1] @ F.T + rng.normal(size=(g, 4)) * np.sqrt(np.diag(Q))
    m = z + rng.normal(size=z.shape) * np.sqrt(np.diag(R))
    kind = rng.integers(0, 3, size=(g, t))  # 0 nothing, 1 position only, 2 all four
    m[kind == 0] = np.nan
    m[..., 2:][kind == 1] = np.nan
    m[:, 0] = z[:, 0]
    x, P = m[:, 0].copy(), np.broadcast_to(R, (g, 4, 4)).copy()
    xh, Ph = x.copy(), P.copy()
    for k in range(1, t):
        x, P = x @ F.T, F @ P @ F.T + Q
        held = np.isfinite(m[:, k])
        x, P, *_ = joseph_update(x, P, m[:, k] - x, H, R, held)
        for i in range(g):  # by hand: predict, then K = P H^T S^-1, P = (I - K H) P
            xi, Pi = F @ xh[i], F @ Ph[i] @ F.T + Q
            h = np.eye(4)[held[i]]
            if h.size:
                S = h @ Pi @ h.T + h @ R @ h.T
                K = Pi @ h.T @ np.linalg.inv(S)
                xi = xi + K @ (m[i, k, held[i]] - h @ xi)
                Pi = (np.eye(4) - K @ h) @ Pi
            xh[i], Ph[i] = xi, Pi
        np.testing.assert_allclose(x, xh, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(P, Ph, rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------- on a drive


@pytest.fixture(scope="module")
def drive():
    """Four simulated slaloms (alpha = 1, inputs at 50 Hz) with position fixes at 10 Hz and
    no heading: m (4, T, 3) position-only, z (4, T, 3) truth, u (4, T, 2), and the full
    fixes at the same rows."""
    frames = [simulate(compose_cfg("simulate", ["manoeuvre=slalom"]), seed=s)[LOG]
              for s in range(4)]
    t = min(len(f) for f in frames)
    arr = np.stack([f.to_numpy(float)[:t] for f in frames])
    full = np.full((4, t, 3), np.nan)
    full[:, ::5] = arr[:, ::5, 1:4]
    m = full.copy()
    m[..., 2] = np.nan
    return {"m": m, "full": full, "u": arr[..., 4:6], "z": arr[..., 6:9]}


def _rmse(est: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(3,) RMSE of x, y (m) and wrapped psi (rad) over every row of every trajectory."""
    e = est - z
    e[..., 2] = wrap_angle(e[..., 2])
    return np.sqrt(np.mean(e.reshape(-1, 3) ** 2, axis=0))


# measured (seeds 0-3, alpha 1, slalom, every row from the first fix): position RMSE
# 0.45-0.48 m (x, y) for the EKF, oracle and UKF, 0.45-0.66 m for the adaptive EKF, 0.29 m
# smoothed, against 1.0 m for the raw fixes; heading 0.056-0.057 rad (EKF, oracle, UKF),
# 0.077 rad (adaptive), 0.024-0.025 rad smoothed, the first metres (heading not yet known) in
POSITION_BOUND, HEADING_BOUND = 0.8, 0.15


@pytest.mark.parametrize("name, smooth", [(n, False) for n in classical.OBSERVERS]
                         + [("ekf", True), ("ukf", True)])
def test_position_only_fixes_beat_the_raw_fixes_and_find_the_heading(drive, name, smooth):
    vehicle, noise = Vehicle(), Noise.preset("paper")
    est, cov = classical.estimate(name, drive["m"], drive["u"], vehicle, noise, alpha=1.0,
                                  smooth=smooth)
    assert np.isfinite(est).all() and np.isfinite(cov).all()
    fixes = drive["full"][:, ::5, :2] - drive["z"][:, ::5, :2]
    raw = np.sqrt(np.mean(fixes.reshape(-1, 2) ** 2, axis=0))
    rmse = _rmse(est, drive["z"])
    print(f"{name}{' smoothed' if smooth else ''}: rmse {rmse}, raw fixes {raw}")
    assert (rmse[:2] < POSITION_BOUND * raw).all()
    assert rmse[2] < HEADING_BOUND
    # the heading starts unknown (variance 1 rad^2) and is learned from the motion
    if not smooth:  # (the smoother carries what the motion showed back to the start)
        assert cov[:, 0, 2, 2] == pytest.approx(HEADING_VAR0)
    assert (cov[:, -1, 2, 2] < 0.01).all()


def test_full_fixes_still_win_on_the_heading(drive):
    """The heading from motion alone is worse than with a heading sensor, as it must be."""
    vehicle, noise = Vehicle(), Noise.preset("paper")
    blind = _rmse(classical.estimate("ekf", drive["m"], drive["u"], vehicle, noise).mean,
                  drive["z"])
    seen = _rmse(classical.estimate("ekf", drive["full"], drive["u"], vehicle, noise).mean,
                 drive["z"])
    assert seen[2] < blind[2]


def test_the_observer_runs_and_steps_a_position_only_log_alike(drive):
    m, u = drive["m"][0, :400], drive["u"][0, :400]
    m = m.copy()
    m[::10, 2] = np.nan  # mixed: some fixes with, some without a heading
    m[5::10] = drive["full"][0, 5:400:10]
    for name in classical.OBSERVERS:
        obs = Observer.load(name)
        est, valid = obs.run(m, u)
        assert valid.all()
        stepped = np.array([obs.step(None if np.isnan(mk).all() else mk, uk).state
                            for mk, uk in zip(m, u)])
        np.testing.assert_allclose(stepped[:, :2], est[:, :2], rtol=0, atol=1e-9)
        np.testing.assert_allclose(wrap_angle(stepped[:, 2] - est[:, 2]), 0, atol=1e-9)


def test_lbo_observe_takes_a_position_only_log(tmp_path):
    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom"]))[LOG].head(300)
    df.loc[:, "psi_m"] = np.nan
    df.loc[df.index % 5 != 0, ["x_m", "y_m"]] = np.nan
    df.to_csv(tmp_path / "log.csv", index=False)
    res = observe("observer=ekf", f"input={tmp_path / 'log.csv'}",
                  f"output={tmp_path / 'est.csv'}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    out = pd.read_csv(tmp_path / "est.csv")
    assert out["valid"].all() and np.isfinite(out[["x", "y", "psi"]].to_numpy()).all()
    assert "fixes: 60 of 300 rows" in res.stdout


# --------------------------------------------------------------------------- the channel rules


def _log(t: int = 20) -> tuple[np.ndarray, np.ndarray]:
    m = np.column_stack([np.arange(t) * 0.2, np.zeros(t), np.zeros(t)])
    return m, np.tile([10.0, 0.0], (t, 1))


@pytest.mark.parametrize("blank, message", [
    ([(4, 0), (4, 1)], rf"^row 4 has a heading without a position \(psi_m without x_m, y_m\); "
                       rf"{RULE} \(a step without a fix\)$"),
    ([(6, 1)], rf"^row 6 has x_m without y_m; {RULE}"),
    ([(6, 0), (6, 2)], rf"^row 6 has y_m without x_m; {RULE}"),
    ([(r, 0) for r in range(20)] + [(r, 1) for r in range(20)] + [(r, 2) for r in range(20)],
     r"^no position fix in any row \(x_m and y_m are empty everywhere\)$"),
])
def test_each_channel_rule_is_one_line_naming_the_row(blank, message):
    m, u = _log()
    for r, c in blank:
        m[r, c] = np.nan
    with pytest.raises(LboError, match=message) as err:
        check_samples(m, u)
    assert "\n" not in str(err.value)
    with pytest.raises(LboError, match=message.replace("^", "^input log.csv: ")):
        Observer.load("ekf").run(m, u, source="input log.csv")


def test_a_position_without_a_heading_is_a_fix_and_a_training_set_still_wants_headings():
    m, u = _log()
    m[3, 2] = np.nan
    np.testing.assert_array_equal(check_samples(m, u), np.ones(20, bool))
    with pytest.raises(LboError, match=r"^row 3 has a position without a heading \(psi_m "
                                       r"empty\); here a row holds x_m, y_m and psi_m"):
        check_fixes(m, position_only=False)


@pytest.mark.parametrize("m, message", [
    ((np.nan, np.nan, 0.1), r"^step 7: measurement \[nan, nan, 0.1\] has a heading without a "
                            rf"position; {RULE.replace('a row', 'a sample')}"),
    ((1.0, np.nan, 0.1), r"^step 7: measurement \[1, nan, 0.1\] has x_m without y_m"),
    ((np.inf, 2.0, np.nan), r"^step 7: measurement \[inf, 2, nan\] has inf \(x_m\)"),
])
def test_step_refuses_each_bad_subset_in_one_line_and_takes_the_next(m, message):
    with pytest.raises(LboError, match=message):
        check_sample(m, (10.0, 0.0), 7, 0.5)
    obs = Observer.load("ekf")
    obs.step([0.0, 0.0, np.nan], [10.0, 0.0])
    for _ in range(6):
        obs.step(None, [10.0, 0.0])
    with pytest.raises(LboError, match=message):
        obs.step(np.array(m), [10.0, 0.0])
    assert check_sample((1.0, 2.0, np.nan), (10.0, 0.0), 7, 0.5) is True
    assert obs.step([1.4, 0.0, np.nan], [10.0, 0.0]).valid


def test_a_learned_observer_refuses_a_position_only_log_in_one_line():
    obs = Observer.from_net(WindowNet("cnn", 20, "relative"))
    m, u = _log(40)
    m[12, 2] = np.nan
    line = (r"row 12: a position fix without a heading \(psi_m empty\), but cnn-N20 takes full "
            r"fixes only \(x_m, y_m and psi_m\); the classical observers \(ekf, oracle, "
            r"adaptive, ukf\) take it, the robust observer \(filternet\) in its recursive "
            r"form, and a CNN, LSTM or window filter trained on a receiver "
            r"\(experiment=receiver\)$")
    with pytest.raises(LboError, match="^input log.csv: " + line):
        obs.run(m, u, source="input log.csv")
    with pytest.raises(LboError, match="^step 0: " + line[len("row 12: "):]):
        obs.step(m[12], u[12])
