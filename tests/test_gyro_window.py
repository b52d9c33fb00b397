"""The window filter that turns its heading with a gyro (``model.gyro=true``, issue 36): the
gyro-driven model psi' = r_m - b with the bias b a fourth state, checked against an EKF written
out by hand; a car at rest holds its heading whatever the gyro reads; without a gyro in its
window it is the filter without one; what cannot take a gyro is refused in one line."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from helpers import compose_cfg, step_log
from lbo.core.errors import LboError
from lbo.filters import gyro as gyro_model
from lbo.logs.io import receiver
from lbo.models import receiver_window as rw
from lbo.models.filternet import WindowFilter
from lbo.models.net import WindowNet
from lbo.models.recursive import RecursiveFilter
from lbo.serve.observer import Observer
from lbo.sim.measurements import Measurements
from lbo.simulate import simulate

pytestmark = pytest.mark.usefixtures("one_torch_thread")
NAN = float("nan")
COLS = {name: i for i, name in enumerate(rw.COLUMNS)}
DT = 0.02


def _drive(n: int = 12, v: float = 5.0, rate: float = 0.3, bias: float = 0.05,
           stop: tuple[int, int] = (6, 8)) -> np.ndarray:
    """A receiver window (n, 11): a car at ``v`` m/s turning at ``rate`` rad/s, at rest over
    the rows ``stop``; a gyro reading the rate plus ``bias`` at every row; a full fix at row
    0, a position fix at row 3, a position with a course at row 5, a position fix at the last
    row, every channel's accuracy reported (so R is the receiver's alone)."""
    win = np.full((n, rw.WIDTH), NAN)
    speed = np.full(n, v)
    speed[stop[0]:stop[1]] = 0.0
    turn = np.where(speed > 0, rate, 0.0)
    psi = 0.4 + np.concatenate([[0.0], np.cumsum(turn[:-1] * DT)])
    x = 100 + np.concatenate([[0.0], np.cumsum(speed[:-1] * np.cos(psi[:-1]) * DT)])
    y = -20 + np.concatenate([[0.0], np.cumsum(speed[:-1] * np.sin(psi[:-1]) * DT)])
    win[:, COLS["V"]], win[:, COLS["delta"]] = speed, 0.0  # the bicycle would not turn
    win[:, COLS["r_m"]] = turn + bias
    for k, dx in ((0, 0.1), (3, -0.2), (5, 0.15), (n - 1, 0.05)):
        win[k, :2] = x[k] + dx, y[k] - dx
        win[k, COLS["sx_m"]] = win[k, COLS["sy_m"]] = 0.3
    win[0, COLS["psi_m"]], win[0, COLS["spsi_m"]] = psi[0] + 0.01, 0.02
    win[5, COLS["course"]], win[5, COLS["s_course"]] = psi[5] - 0.02, 0.03
    return win


def _hand_gyro_ekf(win: np.ndarray, q: np.ndarray, gyro_sigma: float, bias_sigma: float,
                   walk: float) -> np.ndarray:
    """The gyro EKF written out by hand over one receiver window (n, 11): states
    ``[x, y, psi, b]``, started at row 0's full fix with b = 0; the heading turns by the last
    gyro reading less b, except at rest; each row updates with the channels it holds, R the
    reported 1-sigmas squared. Returns the last pose (3,)."""
    w = win
    z = np.r_[w[0, :3], 0.0]
    P = np.diag([w[0, 3] ** 2, w[0, 4] ** 2, w[0, 5] ** 2, bias_sigma ** 2])
    Q = np.diag([q[0] ** 2, q[1] ** 2, gyro_sigma ** 2, walk ** 2])
    for k in range(1, len(w)):
        v, r = w[k - 1, COLS["V"]], w[k - 1, COLS["r_m"]]
        turning = abs(v) >= gyro_model.STILL_SPEED
        psi = z[2]
        F = np.eye(4)
        F[0, 2], F[1, 2] = -v * math.sin(psi) * DT, v * math.cos(psi) * DT
        F[2, 3] = -DT if turning else 0.0
        z = z + np.r_[v * math.cos(psi) * DT, v * math.sin(psi) * DT,
                      (r - z[3]) * DT if turning else 0.0, 0.0]
        P = F @ P @ F.T + Q
        sel, meas, var = [], [], []
        if np.isfinite(w[k, 0]):
            sel += [0, 1]
            meas += [w[k, 0], w[k, 1]]
            var += [w[k, 3] ** 2, w[k, 4] ** 2]
        for col, sig in (("psi_m", "spsi_m"), ("course", "s_course")):
            if np.isfinite(w[k, COLS[col]]):
                sel.append(2)
                meas.append(w[k, COLS[col]])
                var.append(w[k, COLS[sig]] ** 2)
                break
        if not sel:
            continue
        H = np.eye(4)[sel]
        y = np.array(meas) - H @ z
        S = H @ P @ H.T + np.diag(var)
        K = P @ H.T @ np.linalg.inv(S)
        z = z + K @ y
        P = (np.eye(4) - K @ H) @ P
    return z[:3]


def _gyro_net(n: int, q: tuple[float, float, float] = (0.05, 0.05, 0.002)) -> WindowNet:
    return WindowNet("filternet", n, "frame", receiver=True, gyro=True,
                     process_sigma=q).double()


def test_its_gyro_model_matches_an_ekf_written_out_by_hand():
    """A turning car whose steering says it goes straight, its gyro biased, a stop mid-window:
    the estimate is the hand-written gyro EKF's (to 1e-9), with the net's learned noise."""
    win = _drive()
    net = _gyro_net(len(win))
    wf = net.net
    with torch.no_grad():
        wf.log_gyro_sigma.fill_(math.log(0.004))
        wf.log_bias_sigma.fill_(math.log(0.08))
        wf.log_bias_walk.fill_(math.log(0.001))
        got = net(torch.from_numpy(win)[None])[0].numpy()
    want = _hand_gyro_ekf(win, np.array([0.05, 0.05]), 0.004, 0.08, 0.001)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    # the bicycle (no gyro) would have driven straight: a heading off by the turn it missed
    plain = WindowNet("filternet", len(win), "frame", receiver=True,
                      process_sigma=(0.05, 0.05, 0.002)).double()
    with torch.no_grad():
        straight = plain(torch.from_numpy(win)[None])[0].numpy()
    assert abs(straight[2] - want[2]) > 0.01


def test_its_recursive_form_is_the_same_ekf_carried_from_step_to_step():
    """The recursive form over the window's rows (every channel's accuracy reported, so its
    start and R are the receiver's) ends at the hand-written EKF's estimate; without the
    gyro's column (u (T, 2)) the bicycle turns its heading."""
    win = _drive()
    net = _gyro_net(len(win))
    with torch.no_grad():
        net.net.log_gyro_sigma.fill_(math.log(0.004))
        net.net.log_bias_sigma.fill_(math.log(0.08))
        net.net.log_bias_walk.fill_(math.log(0.001))
    rec = RecursiveFilter(net.net)
    assert rec.n == 4 and rec.inputs == ("V", "delta", "r_m")
    m, u = torch.from_numpy(win[None, :, :8]), torch.from_numpy(win[None, :, 8:])
    with torch.no_grad():
        est = rec.run(m, u).pose[0, -1].numpy()
        plain = rec.run(m, u[..., :2]).pose[0, -1].numpy()
    want = _hand_gyro_ekf(win, np.array([0.05, 0.05]), 0.004, 0.08, 0.001)
    np.testing.assert_allclose(est, want, rtol=0, atol=1e-9)
    assert abs(plain[2] - want[2]) > 0.01


def test_a_gyro_filter_runs_a_single_antenna_log_alike_streamed_and_on_every_engine():
    torch.manual_seed(0)
    net = WindowNet("filternet", 60, "frame", fixes=True, receiver=True, gyro=True)
    log = simulate(compose_cfg("simulate", ["manoeuvre=free_drive", "duration=4",
                                            "receiver=single_antenna", "seed=1"]))
    m, u = log[["x_m", "y_m", "psi_m"]].to_numpy(float), log[["V", "delta"]].to_numpy(float)
    r = receiver(log)
    assert np.isfinite(r[:, -1]).all()  # a gyro at every row
    est = {}
    for engine in ("torch", "torchscript", "onnx"):
        obs = Observer.from_net(net, engine=engine, form="recursive")
        assert obs.reads_gyro
        est[engine] = obs.run(m, u, receiver=r)[0]
    first = int(np.argmax(np.isfinite(est["torch"]).all(1)))
    assert first < 60
    for engine in ("torchscript", "onnx"):
        np.testing.assert_allclose(est[engine][first:], est["torch"][first:], rtol=0,
                                   atol=1e-6, err_msg=engine)
    obs = Observer.from_net(net, form="recursive")
    said = [s.state for s in step_log(obs, m, u, r, first + 40)]
    np.testing.assert_allclose(np.array(said)[first:], est["torch"][first:first + 40],
                               rtol=0, atol=1e-9)
    no_gyro = r.copy()
    no_gyro[:, -1] = np.nan
    plain = obs.run(m, u, receiver=no_gyro)[0]
    assert np.abs(plain[first:, 2] - est["torch"][first:, 2]).max() > 1e-4


def test_rows_without_a_fix_coast_to_the_numbers_of_one_step_each():
    """A log's run takes each stretch of rows without a fix or a course in one coast, the
    gyro turning the heading through it: the poses and covariances of one step per row (a
    stretch of 79 rows at N=60, in two chunks), on every engine. The net is the test's
    before, whose ONNX step that test kept: an export costs seconds, and is not the point."""
    torch.manual_seed(0)
    net = WindowNet("filternet", 60, "frame", fixes=True, receiver=True, gyro=True)
    log = simulate(compose_cfg("simulate", ["manoeuvre=free_drive", "duration=4",
                                            "receiver=single_antenna", "seed=3",
                                            "receiver.position.rate=5"]))
    m, u = log[["x_m", "y_m", "psi_m"]].to_numpy(float), log[["V", "delta"]].to_numpy(float)
    r = receiver(log)
    r[100:170, :2] = m[100:170] = np.nan  # a 70-row gap
    r[100:170, 3:6] = np.nan
    rec = RecursiveFilter(net.net)
    assert rec.coasts
    rows, u3 = Observer.from_net(net)._runner.log_rows(Measurements.of(m, r), u, None)
    with torch.no_grad():
        est, cov = (t[0].numpy() for t in rec.run(torch.from_numpy(rows[None]),
                                                   torch.from_numpy(u3[None]))[:2])
    for engine in ("torch", "onnx"):
        obs = Observer.from_net(net, form="recursive", engine=engine)
        coasted, coast = [], obs._runner.coast
        obs._runner.coast = (lambda u, state, seen=coasted, inner=coast:
                             seen.append(len(u)) or inner(u, state))
        got, valid = found = obs.run(m, u, receiver=r)
        got_cov = found.cov
        assert max(coasted) > rec.coast_limit and sum(coasted) > len(m) // 2
        atol = 1e-12 if engine == "torch" else 1e-5
        np.testing.assert_allclose(got, est, rtol=0, atol=atol, equal_nan=True)
        np.testing.assert_allclose(got_cov, cov, rtol=0, atol=atol, equal_nan=True)


def test_its_export_takes_the_gyros_reading_as_a_third_input(tmp_path):
    """The exported step (ONNX), fed u (1, 3) ``[V, delta, r_m]`` as its JSON says, gives the
    observer's estimates over a single-antenna log."""
    import json

    import onnxruntime as ort

    from lbo.export import export

    torch.manual_seed(0)
    obs = Observer.from_net(WindowNet("filternet", 60, "frame", fixes=True, receiver=True,
                                      gyro=True))
    paths = export(obs, tmp_path, "gyro")
    spec = json.loads(paths["json"].read_text())
    assert spec["input"]["u"]["columns"] == ["V", "delta", "r_m"]
    log = simulate(compose_cfg("simulate", ["manoeuvre=free_drive", "duration=2",
                                            "receiver=single_antenna", "seed=2"]))
    m, u = log[["x_m", "y_m", "psi_m"]].to_numpy(float), log[["V", "delta"]].to_numpy(float)
    est = obs.run(m, u, receiver=receiver(log))[0]
    rows, u3 = obs._runner.log_rows(Measurements.of(m, receiver(log)), u, None)
    assert u3.shape == (len(m), 3)
    session = ort.InferenceSession(str(paths["onnx"]), providers=["CPUExecutionProvider"])
    state = {s["name"]: np.zeros([1 if d == "batch" else d for d in s["shape"]])
             for s in spec["state"]}
    inputs = {s["name"] for s in spec["state"] if s["onnx_input"]}
    got = []
    for k in range(len(m)):
        out = session.run(None, {"m": rows[k:k + 1], "u": u3[k:k + 1],
                                 **{n: v for n, v in state.items() if n in inputs}})
        state = dict(zip(state, out[2:]))
        got.append(out[0][0])
    np.testing.assert_allclose(np.array(got), est, rtol=0, atol=1e-6)


def test_a_car_at_rest_holds_its_heading_whatever_the_gyro_reads():
    """At rest the gyro reads its bias (and noise): the heading does not move."""
    win = _drive(n=30, stop=(0, 30))
    win[1:-1, :2] = win[:, COLS["course"]] = NAN  # only the start and the last position
    win[:, COLS["r_m"]] = 0.5  # a gyro that reads 0.5 rad/s at rest
    net = _gyro_net(len(win))
    with torch.no_grad():
        got = net(torch.from_numpy(win)[None])[0].numpy()
    assert abs(got[2] - win[0, COLS["psi_m"]]) < 1e-12


def test_without_a_gyro_in_its_window_it_is_the_filter_without_one():
    torch.manual_seed(0)
    plain = WindowNet("filternet", 12, "frame", receiver=True).double()
    for p in plain.net.noise.parameters():
        torch.nn.init.normal_(p, std=0.3)
    gyro = _gyro_net(12, q=(0.0667, 0.0667, 0.00113))
    missing = gyro.load_state_dict(plain.state_dict(), strict=False)
    assert set(missing.missing_keys) == {"net.log_gyro_sigma", "net.log_bias_sigma",
                                         "net.log_bias_walk"}
    win = _drive()
    win[:, COLS["r_m"]] = NAN
    x = torch.from_numpy(win)[None]
    with torch.no_grad():
        np.testing.assert_allclose(gyro(x).numpy(), plain(x).numpy(), rtol=0, atol=1e-12)


def test_the_train_config_builds_it_and_refuses_it_without_a_receiver():
    from lbo.learn.builders import build_net

    base = ["experiment=receiver", "model=filternet", "window=40", "model.gyro=true"]
    net = build_net(compose_cfg("train", base))
    assert net.net.gyro and net.net.receiver and RecursiveFilter(net.net).n == 4
    with pytest.raises(LboError, match=r"^model.gyro: expected false unless the filter reads "
                                       r"a receiver"):
        build_net(compose_cfg("train", ["experiment=robust", "window=40", "model.gyro=true"]))


@pytest.mark.parametrize("kwargs", [dict(in_features=6), dict(in_features=15, residual=8),
                                    dict(in_features=15, body="single_track"),
                                    dict(in_features=15, gyro="yes")])
def test_what_cannot_take_a_gyro_is_refused_in_one_line(kwargs):
    with pytest.raises(LboError) as info:
        WindowFilter(20, gyro=kwargs.pop("gyro", True), **kwargs)
    assert str(info.value).startswith("model.gyro: expected") and "\n" not in str(info.value)
