"""Real logs: steps without a position fix, standstill, and the robust observer on them."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from helpers import ROBUST_SMOKE, compose_cfg, observe, train_in_own_store
from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters import classical
from lbo.filters.kalman import KalmanStepper
from lbo.learn.draws import draw_fixes, fix_periods
from lbo.models.net import WindowNet
from lbo.serve.observer import Observer
from lbo.sim.noise import Noise
from lbo.sim.stopgo import stop_and_go_speed
from lbo.sim.vehicle import Vehicle
from lbo.simulate import simulate, thin

pytestmark = pytest.mark.usefixtures("one_torch_thread")
LOG = ["t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]


@pytest.mark.parametrize("name", classical.OBSERVERS)
def test_prediction_only_steps_follow_the_straight_line_closed_form(name):
    vehicle, noise = Vehicle(), Noise.preset("paper")
    t, v, psi0 = 200, 12.0, 0.7
    m = np.full((1, t, 3), np.nan)
    m[0, 0] = [3.0, -2.0, psi0]
    u = np.tile([v, 0.0], (1, t, 1))
    est = classical.estimate(name, m, u, vehicle, noise, alpha=2.0).mean[0]
    k = np.arange(t)
    expected = np.stack([3.0 + k * v * vehicle.dt * np.cos(psi0),
                         -2.0 + k * v * vehicle.dt * np.sin(psi0), np.full(t, psi0)], -1)
    if name != "ukf":
        np.testing.assert_allclose(est, expected, atol=1e-9)
        return
    # the UKF predicts the mean over its heading uncertainty eps: along the heading, by
    # E[cos eps] < 1 of the distance (a symmetric eps leaves no cross-track offset)
    np.testing.assert_allclose(est[:, 2], psi0, atol=1e-12)
    d = est[:, :2] - [3.0, -2.0]
    cross = -d[:, 0] * np.sin(psi0) + d[:, 1] * np.cos(psi0)
    along = d[:, 0] * np.cos(psi0) + d[:, 1] * np.sin(psi0)
    np.testing.assert_allclose(cross, 0.0, atol=1e-9)
    shrink = 1 - along[1:] / (k[1:] * v * vehicle.dt)
    assert (shrink > 0).all() and (shrink < 0.5 * (2 * noise.measurement_sigma[2]) ** 2
                                    + t * noise.process_sigma[2] ** 2).all()


def test_a_missing_fix_skips_the_update_and_keeps_the_prior_covariance():
    vehicle, noise = Vehicle(), Noise.preset("paper")
    rng = np.random.default_rng(0)
    m0 = rng.normal(size=(4, 3))
    u = np.tile([10.0, 0.05], (4, 1))
    a = KalmanStepper(m0, vehicle, noise.Q, np.broadcast_to(noise.R(1.0), (4, 3, 3)))
    b = KalmanStepper(m0, vehicle, noise.Q, np.broadcast_to(noise.R(1.0), (4, 3, 3)))
    m1 = rng.normal(size=(4, 3))
    m1[[1, 3]] = np.nan
    a.update(m1, u)
    full = b.update(np.where(np.isnan(m1), 0.0, m1), u)
    np.testing.assert_allclose(a.x[[0, 2]], full[[0, 2]])  # fixes: the usual update
    P0 = noise.R(1.0)
    from lbo.sim.vehicle import jacobian, step
    F = jacobian(m0[[1, 3]], u[[1, 3]], vehicle.dt)
    np.testing.assert_allclose(a.x[[1, 3]], step(m0[[1, 3]], u[[1, 3]], vehicle.dt,
                                                 vehicle.wheelbase))
    np.testing.assert_allclose(a.P[[1, 3]], F @ P0 @ F.swapaxes(-1, -2) + noise.Q)


def test_the_window_filter_with_missing_fixes_is_the_kalman_stepper():
    torch.manual_seed(0)
    net = WindowNet("filternet", 30, "frame", fixes=True).net.double()
    sigma = torch.rand(8, 3, dtype=torch.float64) + 0.5
    net.measurement_sigma = lambda x: sigma
    x = torch.randn(8, 30, 6, dtype=torch.float64) * 0.1
    x[..., 3] += 10.0
    x[..., 5] = 1.0
    x[:, 5:25:2, 5] = 0.0
    x[:, :3, 5] = 0.0  # the filter starts at the first fix, step 3
    x[..., :3] *= x[..., 5:]
    out = net(x).detach().numpy()
    m = x[..., :3].numpy().copy()
    m[x[..., 5].numpy() < 0.5] = np.nan
    u = x[..., 3:5].numpy()
    R = np.einsum("gi,ij->gij", sigma.numpy() ** 2, np.eye(3))
    kf = KalmanStepper(m[:, 3], Vehicle(), np.diag(np.exp(2 * net.log_q0.numpy())), R)
    for k in range(4, 30):
        kf.update(m[:, k], u[:, k - 1])
    np.testing.assert_allclose(out, kf.x, atol=1e-9)


def test_fix_dropout_keeps_the_drawn_periods_and_at_least_one_fix():
    assert fix_periods([50, 10, 5, 1], 0.02) == (1, 5, 10, 50)
    with pytest.raises(LboError, match=r"^fix_rates: expected null or a list"):
        fix_periods([10, -1], 0.02)
    g = torch.Generator().manual_seed(0)
    mask = draw_fixes(4000, 20, (1, 50), g)
    assert mask.any(1).all()
    share = mask.float().mean(1)
    # every step (period 1), or about 1 in 50 (0.05 at most in 20 steps, besides the forced one)
    assert ((share == 1.0) | (share <= 0.15)).all()
    assert 0.4 < (share == 1.0).float().mean() < 0.6


def test_streaming_with_none_equals_batch_inference():
    torch.manual_seed(1)
    net = WindowNet("filternet", 40, "frame", fixes=True).double()
    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom", "fix_rate=5", "alpha=2"]))
    m = df[["x_m", "y_m", "psi_m"]].to_numpy()
    u = df[["V", "delta"]].to_numpy()
    for obs in (Observer.from_net(net), Observer("ekf"), Observer("adaptive")):
        est, valid = obs.run(m, u)
        obs.reset()
        steps = [obs.step(None if np.isnan(mk).any() else mk, uk) for mk, uk in zip(m, u)]
        np.testing.assert_allclose(np.stack([s.state for s in steps]), est, atol=1e-6)
        assert [s.valid for s in steps] == valid.tolist()
        assert valid.all()  # the log starts with a fix; the window filter starts there


def test_an_observer_trained_with_every_fix_refuses_a_missing_one():
    obs = Observer.from_net(WindowNet("cnn", 20, "relative"))
    m = np.zeros((30, 3))
    m[7] = np.nan
    u = np.tile([1.0, 0.1], (30, 1))  # within the steering limit, which run checks first
    with pytest.raises(LboError, match=r"^row 7: no fix, but cnn-N20 was trained with a fix"):
        obs.run(m, u)
    with pytest.raises(LboError, match=r"^step 0: no fix"):
        obs.step(None, u[0])


def test_the_stop_and_go_log_stands_still_a_third_of_the_time():
    speed = stop_and_go_speed(0.02)
    assert (speed == 0).mean() >= 0.30
    df = simulate(compose_cfg("simulate", ["fix_rate=1"]))
    assert (df["V"] == 0).mean() >= 0.30
    fix = df["x_m"].notna().to_numpy()
    assert fix[0] and np.flatnonzero(fix)[1] == 50  # 1 Hz at 50 Hz inputs
    np.testing.assert_array_equal(thin(np.ones((7, 3)), 3)[:, 0],
                                  [1, np.nan, np.nan, 1, np.nan, np.nan, 1])


def test_training_data_with_stop_and_go_has_standstill(tmp_path):
    from lbo.sim.datasets import make_train, spec_from_cfg

    cfg = compose_cfg("datagen", ["data=smoke", f"data.root={tmp_path}",
                                  "+data.train.stop_and_go=0.5"])
    train = make_train(spec_from_cfg(cfg))
    V = train["V"].to_numpy().reshape(cfg.data.train.n_traj, -1)
    half = cfg.data.train.n_traj // 2
    assert (V[:half] >= cfg.vehicle.v_min).all()   # friction circle, as the paper's
    assert (V[half:] == 0).mean() > 0.1            # stop-and-go: standstill
    with pytest.raises(LboError, match=r"^data.train.stop_and_go must be a share of the "
                                       r"trajectories in \[0, 1\], got 2$"):
        spec_from_cfg(compose_cfg("datagen", ["data=smoke", "+data.train.stop_and_go=2"]))


@pytest.mark.parametrize("blank, message", [
    ({"x_m": [4], "y_m": [4]}, r"row 4 has a heading without a position \(psi_m without x_m, "
                               r"y_m\); a row holds x_m and y_m \(a position fix\), with or "
                               r"without psi_m, or none of them"),
    ({"x_m": "all", "y_m": "all", "psi_m": "all"},
     r"no position fix in any row \(x_m and y_m are empty everywhere\)"),
])
def test_a_heading_without_a_position_or_no_fix_is_one_line_and_no_output(tmp_path, blank, message):
    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom"]))[LOG].head(50)
    for col, rows in blank.items():
        df.loc[df.index if rows == "all" else df.index[rows], col] = np.nan
    df.to_csv(tmp_path / "log.csv", index=False)
    res = observe("observer=ekf", f"input={tmp_path / 'log.csv'}",
                   f"output={tmp_path / 'est.csv'}", cwd=tmp_path)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: input {tmp_path / 'log.csv'}: ")
    import re
    assert re.search(message, lines[0]), lines[0]
    assert not (tmp_path / "est.csv").exists()


@pytest.mark.slow
def test_a_smoke_robust_checkpoint_runs_on_a_thinned_log(tmp_path, smoke_data):
    cfg, out, _ = train_in_own_store(tmp_path, smoke_data, *ROBUST_SMOKE, "window=60",
                                     "fix_rates=[50,10,1]", "trainer.limit_train_batches=5",
                                     "batch_size=64")
    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom", "fix_rate=10", "alpha=1"]))
    log = tmp_path / "log.csv"
    df[LOG].to_csv(log, index=False)
    res = observe(f"observer={out['checkpoint']}", f"input={log}",
                   f"output={tmp_path / 'est.csv'}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "fixes: 190 of 950 rows (10 Hz; inputs at 50 Hz)" in res.stdout
    est = pd.read_csv(tmp_path / "est.csv")
    assert est["valid"].all() and np.isfinite(est[["x", "y", "psi"]].to_numpy()).all()
    e = est[["x", "y", "psi"]].to_numpy() - df[["x", "y", "psi"]].to_numpy()
    e[:, 2] = wrap_angle(e[:, 2])
    # thinned to 10 Hz the raw fixes are 1 m off; the observer must not be far off that
    assert np.sqrt(np.mean(e[:, :2] ** 2)) < 1.5


def test_a_cnn_trained_with_fix_rates_takes_a_log_with_missing_fixes(tmp_path, smoke_data):
    cfg, out, _ = train_in_own_store(tmp_path, smoke_data, "experiment=smoke", "model=cnn",
                                     "window=20", "fix_rates=[50,5]", "trainer.max_epochs=1",
                                     "trainer.limit_train_batches=3")
    obs = Observer.load(out["checkpoint"])
    assert obs.takes_missing_fixes and obs.net.in_mean.shape == (6,)
    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom", "fix_rate=10"]))
    m, u = df[["x_m", "y_m", "psi_m"]].to_numpy(), df[["V", "delta"]].to_numpy()
    est, valid = obs.run(m, u)
    assert valid[19:].all() and not valid[:19].any()  # the CNN needs a full window
    assert np.isfinite(est[19:]).all()
    # its estimate is anchored at the latest fix, 0 to 4 steps back, not at a missing one
    assert np.abs(est[19:, :2] - df[["x", "y"]].to_numpy()[19:]).mean() < 5.0


def test_the_export_of_an_observer_with_missing_fixes_matches_pytorch(tmp_path):
    from lbo.export import export
    from lbo.serve.engines import onnx_session

    torch.manual_seed(2)
    # N = 20: the window form's export unrolls its N steps (twice as long at N = 40)
    net = WindowNet("filternet", 20, "frame", fixes=True)  # float32 weights, as trained
    # the window form; the recursive form's step export is tested in test_recursive.py
    paths = export(Observer.from_net(net, form="window"), tmp_path)
    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom", "fix_rate=5"]))
    series = df[["x_m", "y_m", "psi_m", "V", "delta"]].to_numpy()
    win = np.stack([series[e - 20:e] for e in (20, 333, 700)])  # fixes every 10 steps
    assert np.isnan(win[..., 0]).mean() == pytest.approx(0.9)
    with torch.inference_mode():
        ref = net(torch.from_numpy(win)).numpy()
    got = onnx_session(paths["onnx"]).run(None, {"window": win})[0]
    with torch.inference_mode():
        scripted = torch.jit.load(str(paths["torchscript"]))(torch.from_numpy(win)).numpy()
    assert np.isfinite(ref).all()
    np.testing.assert_allclose(got, ref, atol=1e-5)
    np.testing.assert_allclose(scripted, ref, atol=1e-5)
