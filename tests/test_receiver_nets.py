"""A CNN or LSTM that reads a receiver (issue 36): its windows' features, each channel with a
mask (lbo.models.receiver_window); the receiver drawn afresh per training window
(lbo.learn.draws.ReceiverDraw); the observer over a single-antenna log, stepped and run, on
every engine; and ``experiment=receiver`` trained end to end."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from helpers import cli, compose_cfg, step_log, train_in_own_store
from lbo.core.errors import LboError
from lbo.learn.builders import noise_settings
from lbo.learn.draws import ReceiverDraw, draw_fixes
from lbo.logs.io import receiver
from lbo.models import receiver_window as rw
from lbo.models.net import WindowNet
from lbo.serve.observer import Observer
from lbo.sim.receiver import Channel, ReceiverSpec
from lbo.sim.vehicle import step
from lbo.simulate import simulate

pytestmark = pytest.mark.usefixtures("one_torch_thread")
NAN = float("nan")


DT, WHEELBASE = 0.02, 2.7


def _window(rows: list[list[float]], v: float = 0.0) -> torch.Tensor:
    """A receiver window (1, N, 11) of rows [x_m, y_m, psi_m, course, r_m] (NaN: none), the
    accuracies 0.5 m where there is a fix, V = v and delta = 0."""
    out = []
    for x, y, psi, course, rate in rows:
        fix = math.isfinite(x)
        out.append([x, y, psi, 0.5 if fix else NAN, 0.5 if fix else NAN,
                    0.01 if math.isfinite(psi) else NAN, course,
                    0.05 if math.isfinite(course) else NAN, v, 0.0, rate])
    return torch.tensor([out], dtype=torch.float64)


def _anchor(win: torch.Tensor) -> torch.Tensor:
    return rw.anchor(win, DT, WHEELBASE)


def test_the_anchor_is_the_latest_fix_turned_by_the_latest_heading():
    win = _window([[0.0, 0.0, 0.3, NAN, 0.0], [NAN, NAN, NAN, NAN, 0.0],
                   [1.0, 2.0, NAN, 0.5, NAN], [NAN, NAN, NAN, NAN, 0.1]])
    np.testing.assert_allclose(_anchor(win)[0], [1.0, 2.0, 0.5])  # the course came last
    win[0, 2, 6] = NAN  # no course: the heading measured before
    np.testing.assert_allclose(_anchor(win)[0], [1.0, 2.0, 0.3])
    win[0, 0, 2] = NAN  # no heading at all: the world's axes, and every heading mask 0
    np.testing.assert_allclose(_anchor(win)[0], [1.0, 2.0, 0.0])
    f = rw.features(win, _anchor(win))[0]
    assert f[:, rw.FEATURES.index("heading")].sum() == 0
    assert f[:, rw.FEATURES.index("course_held")].sum() == 0
    win[0, :, 0:2] = NAN  # no fix: no anchor
    assert torch.isnan(_anchor(win)[0, :2]).all()


def test_the_anchor_is_carried_from_the_latest_fix_by_the_kinematic_bicycle():
    """The latest fix 30 steps back and the latest heading 10 steps before it: the anchor is
    that fix stepped on by lbo.sim.vehicle.step from that heading (the heading stepped from
    its own row on)."""
    n, j, h = 40, 9, 0
    u = np.column_stack([np.linspace(8.0, 12.0, n), 0.1 * np.sin(np.arange(n) / 5.0)])
    rows = [[NAN, NAN, NAN, NAN, NAN] for _ in range(n)]
    rows[h] = [NAN, NAN, 0.4, NAN, NAN]  # a heading alone (as a course would be)
    rows[h][3] = 0.4
    rows[j] = [5.0, -3.0, NAN, NAN, NAN]
    win = _window(rows)
    win[0, :, 8:10] = torch.from_numpy(u)
    z = np.array([0.0, 0.0, 0.4])
    for k in range(h, j):
        z = step(z, u[k], DT, WHEELBASE)
    z = np.array([5.0, -3.0, z[2]])
    for k in range(j, n - 1):
        z = step(z, u[k], DT, WHEELBASE)
    np.testing.assert_allclose(_anchor(win)[0].numpy(), z, atol=1e-9)


def test_features_hold_each_channel_with_its_mask_in_the_anchors_frame():
    win = _window([[0.0, 0.0, NAN, NAN, 0.02], [NAN, NAN, NAN, NAN, NAN],
                   [0.0, 1.0, NAN, math.pi / 2, 0.03]])
    f = rw.features(win, _anchor(win))[0]
    col = {name: f[:, i].tolist() for i, name in enumerate(rw.FEATURES)}
    # the anchor is (0, 1) heading north: the first fix lies 1 m behind it
    np.testing.assert_allclose(col["dx"], [-1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(col["dy"], [0.0, 0.0, 0.0], atol=1e-12)
    assert col["fix"] == [1.0, 0.0, 1.0] and col["course_held"] == [0.0, 0.0, 1.0]
    assert col["sx"] == [0.5, 0.0, 0.5] and col["s_course"] == [0.0, 0.0, 0.05]
    assert col["r_m"] == [0.02, 0.0, 0.03] and col["gyro"] == [1.0, 0.0, 1.0]
    assert torch.isfinite(f).all()


def test_features_do_not_change_when_the_whole_window_moves_and_turns():
    g = torch.Generator().manual_seed(0)
    z = torch.cumsum(torch.randn(4, 30, 3, generator=g, dtype=torch.float64) * 0.1, 1)
    u = torch.tensor([8.0, 0.02], dtype=torch.float64).expand(4, 30, 2).clone()
    fix = draw_fixes(4, 30, (5,), g)
    spec = ReceiverSpec()
    draw = ReceiverDraw(spec, heading_share=0.5)
    win = draw.windows(z, u, torch.full((4,), 1.0, dtype=torch.float64), fix,
                       torch.Generator().manual_seed(1))
    turn, shift = 1.1, torch.tensor([30.0, -20.0], dtype=torch.float64)
    moved = win.clone()
    c, s = math.cos(turn), math.sin(turn)
    moved[..., 0] = c * win[..., 0] - s * win[..., 1] + shift[0]
    moved[..., 1] = s * win[..., 0] + c * win[..., 1] + shift[1]
    moved[..., 2] = win[..., 2] + turn
    moved[..., 6] = win[..., 6] + turn
    torch.testing.assert_close(rw.features(moved, _anchor(moved)), rw.features(win, _anchor(win)),
                               atol=1e-9, rtol=0)


def test_a_window_without_any_heading_teaches_no_heading():
    """Its anchor's heading is 0, not the car's: the loss leaves the heading out there, and
    keeps it where the window holds a course."""
    torch.manual_seed(0)
    net = WindowNet("cnn", 8, "frame", fixes=True, receiver=True)
    blind = _window([[float(k), 0.0, NAN, NAN, NAN] for k in range(8)], v=0.5)
    assert not rw.heading_known(blind).any()
    state = torch.tensor([[7.0, 0.0, 0.0]], dtype=torch.float64)
    turned = torch.tensor([[7.0, 0.0, 2.0]], dtype=torch.float64)
    assert net.loss(blind, state) == net.loss(blind, turned)
    seen = blind.clone()
    seen[0, 3, 6] = 0.0
    assert rw.heading_known(seen).all() and net.loss(seen, state) != net.loss(seen, turned)


def test_a_paper_window_is_a_receiver_window_without_its_channels():
    torch.manual_seed(0)
    net = WindowNet("lstm", 12, "frame", fixes=True, receiver=True)
    paper = torch.randn(3, 12, 5, dtype=torch.float64)
    wide = rw.widen(paper)
    assert wide.shape == (3, 12, rw.WIDTH)
    assert torch.isnan(wide[..., 3:8]).all() and torch.isnan(wide[..., 10]).all()
    torch.testing.assert_close(net(paper), net(wide))
    with pytest.raises(LboError, match=r"^features: an observer that reads a receiver takes "
                                       r"features=frame"):
        WindowNet("cnn", 12, "relative", fixes=True, receiver=True)


def _drawn(spec: ReceiverSpec, n: int = 400, steps: int = 50, alpha: float = 1.0,
           heading_share: float = 0.0, gyro_share: float = 1.0, period: int = 5):
    """Receiver windows drawn along a straight drive east at 10 m/s (psi = 0)."""
    t = torch.arange(steps, dtype=torch.float64) * 0.02
    z = torch.stack([10 * t, torch.zeros_like(t), torch.zeros_like(t)], -1).expand(n, steps, 3)
    u = torch.tensor([10.0, 0.0], dtype=torch.float64).expand(n, steps, 2)
    g = torch.Generator().manual_seed(0)
    fix = draw_fixes(n, steps, (period,), g)
    draw = ReceiverDraw(spec, heading_share=heading_share, gyro_share=gyro_share)
    alphas = torch.full((n,), alpha, dtype=torch.float64)
    return z, fix, draw.windows(z, u, alphas, fix, g)


def test_the_drawn_receiver_holds_its_channels_where_its_specification_says():
    spec = ReceiverSpec()
    z, fix, win = _drawn(spec, alpha=2.0)
    held = torch.isfinite(win)
    assert torch.equal(held[..., 0], fix) and torch.equal(held[..., 3], fix)
    assert not held[..., 2].any() and not held[..., 5].any()  # one antenna: no heading
    assert torch.equal(held[..., 6], fix)  # 10 m/s: a course at every fix
    assert held[..., 10].all()  # the gyro at every step
    told = win[..., 3][fix]
    assert abs(float(told.median()) / (2.0 * spec.position.sigma) - 1.0) < 0.05
    # on a straight drive the gyro reads its bias, N(0, gyro_bias^2) per window and nearly
    # constant within one, plus its white noise
    bias = win[..., 10]
    assert abs(float(bias.mean(1).std()) / spec.gyro_bias - 1.0) < 0.15
    within = float((bias - bias.mean(1, keepdim=True)).std())
    assert abs(within / spec.gyro.white - 1.0) < 0.1
    _, _, some = _drawn(spec, heading_share=0.5, gyro_share=0.5)
    with_heading = torch.isfinite(some[..., 2]).any(1).double().mean()
    with_gyro = torch.isfinite(some[..., 10]).any(1).double().mean()
    assert abs(float(with_heading) - 0.5) < 0.1 and abs(float(with_gyro) - 0.5) < 0.1


def test_a_still_receiver_gives_no_course_and_an_exact_one_gives_the_truth():
    exact = ReceiverSpec(position=Channel(), velocity=Channel())  # every step, no error
    z, fix, win = _drawn(exact, period=1)
    torch.testing.assert_close(win[..., :2], z[..., :2])
    torch.testing.assert_close(win[..., 6], torch.zeros_like(win[..., 6]))
    late = ReceiverSpec(position=Channel(latency=0.05), velocity=Channel())
    z, fix, win = _drawn(late, period=1)  # 50 ms late at 10 m/s: 0.5 m behind
    np.testing.assert_allclose((z[..., 0] - win[..., 0])[:, 3:], 0.5, atol=1e-9)
    spec = ReceiverSpec()
    t = 20
    z = torch.zeros(8, t, 3, dtype=torch.float64)
    u = torch.zeros(8, t, 2, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    still = ReceiverDraw(spec).windows(z, u, torch.ones(8, dtype=torch.float64),
                                       torch.ones(8, t, dtype=torch.bool), g)
    assert torch.isnan(still[..., 6:8]).all()


def test_a_receiver_net_steps_and_runs_a_single_antenna_log_alike_on_every_engine():
    log = simulate(compose_cfg("simulate", ["manoeuvre=free_drive", "duration=8",
                                            "receiver=single_antenna", "seed=3"]))
    m = log[["x_m", "y_m", "psi_m"]].to_numpy(float)
    u = log[["V", "delta"]].to_numpy(float)
    r = receiver(log)
    torch.manual_seed(0)
    net = WindowNet("cnn", 60, "frame", fixes=True, receiver=True).eval()
    obs = Observer.from_net(net)
    assert obs.takes_receiver and obs.reads_gyro
    est, valid = obs.run(m, u, receiver=r)
    assert valid[59:].all() and not valid[:59].any()
    stepped = np.array([s.state for s in step_log(obs, m, u, r)])
    np.testing.assert_allclose(stepped[59:], est[59:], atol=1e-5)
    for engine in ("torchscript", "onnx"):
        other, _ = Observer.from_net(net, engine=engine).run(m, u, receiver=r)
        np.testing.assert_allclose(other[59:], est[59:], atol=1e-5)
    # without a velocity no window holds a heading (one antenna): no estimate, and why
    r_still = r.copy()
    r_still[:, 3:6] = np.nan
    none, valid = obs.run(m, u, receiver=r_still)
    assert not valid.any() and np.isnan(none[59:]).all()
    obs.reset()
    said = step_log(obs, m, u, r_still, 61)
    assert said[60].reason.startswith("no heading in the last 60 steps (1.2 s): cnn-N60 reads")
    # without the gyro (a log that has none) it still runs, and reads a different window
    r_blind = r.copy()
    r_blind[:, -1] = np.nan
    blind, _ = obs.run(m, u, receiver=r_blind)
    assert np.isfinite(blind[59:]).all() and np.abs(blind[59:] - est[59:]).max() > 0


def test_receiver_training_settings_are_checked_in_one_line():
    base = ["experiment=receiver", "data=smoke"]
    cfg = compose_cfg("train", base)
    draw = noise_settings(cfg)["receiver"]
    assert (draw.heading_share, draw.gyro_share) == (0.25, 0.75)
    assert draw.spec.position.rate == 1.0
    with pytest.raises(LboError, match=r"^fix_rates must be the rates \(Hz\) of the receiver's"):
        noise_settings(compose_cfg("train", [*base, "fix_rates=null"]))
    with pytest.raises(LboError, match=r"^receiver_training.heading_share must be a share in "
                                       r"\[0, 1\], got 2$"):
        noise_settings(compose_cfg("train", [*base, "receiver_training.heading_share=2"]))
    with pytest.raises(LboError, match=r"^receiver_training.rate: not a field"):
        noise_settings(compose_cfg("train", [*base, "+receiver_training.rate=2"]))
    with pytest.raises(LboError, match=r"^receiver.gyro.white"):
        noise_settings(compose_cfg("train", [*base, "receiver.gyro.white=-1"]))


@pytest.mark.slow
def test_experiment_receiver_trains_and_its_checkpoint_reads_a_receiver(tmp_path, smoke_data):
    cfg, out, _ = train_in_own_store(tmp_path, smoke_data, "experiment=receiver", "data=smoke",
                                     "trainer.max_epochs=1", "trainer.limit_train_batches=3",
                                     "window=60", "batch_size=64")
    assert math.isfinite(out["val_loss"]) and math.isfinite(out["test_nrmse_alpha_1"])
    obs = Observer.load(out["checkpoint"])
    assert obs.net.receiver and obs.takes_receiver and obs.name == "cnn-N60"
    # a window of 60 steps (1.2 s) holds a fix of the 1 Hz receiver
    log = simulate(compose_cfg("simulate", ["manoeuvre=free_drive", "duration=4",
                                            "receiver=single_antenna", "seed=1"]))
    est, valid = obs.run(log[["x_m", "y_m", "psi_m"]].to_numpy(float),
                         log[["V", "delta"]].to_numpy(float), receiver=receiver(log))
    assert valid[59:].all() and np.isfinite(est[59:]).all()
    # exported: the files take receiver windows (batch, 60, 11), as the JSON says
    res = cli("lbo.export", f"observer={out['checkpoint']}", "out_dir=exports", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    meta = json.loads((tmp_path / "exports" / "cnn-N60.json").read_text())
    assert meta["input"]["shape"] == ["batch", 60, rw.WIDTH]
    assert meta["input"]["columns"] == list(rw.COLUMNS)
    assert max(meta["max_abs_diff_to_pytorch"].values()) <= 1e-5  # checked before written
