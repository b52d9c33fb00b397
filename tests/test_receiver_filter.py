"""The window filter (filternet) in its window form over a receiver's windows (issue 36): each
row updates with the channels it holds, the reported accuracies as their R (turned from world
axes into the window's frame), checked against a Kalman filter written out by hand; a window
of full fixes gives the paper window form's estimate; ``experiment=receiver model=filternet``
trains end to end and its checkpoint runs in both forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from helpers import compose_cfg, step_log, train_in_own_store
from lbo.core.errors import LboError
from lbo.logs.io import receiver
from lbo.models import receiver_window as rw
from lbo.models.filternet import WindowFilter
from lbo.models.net import WindowNet
from lbo.scoring.receiver import net_rows
from lbo.serve.observer import Observer
from lbo.simulate import simulate

pytestmark = pytest.mark.usefixtures("one_torch_thread")
NAN = float("nan")


def _paper_windows(batch: int = 4, n: int = 20, seed: int = 1) -> torch.Tensor:
    """Paper windows (B, n, 5) of a car at 10 m/s, full fixes at every third step and the
    last, NaN between."""
    g = torch.Generator().manual_seed(seed)
    f = dict(generator=g, dtype=torch.float64)
    t = torch.arange(n, dtype=torch.float64) * 0.02
    win = torch.stack([10 * t + torch.randn(batch, n, **f), 3 + 0.5 * torch.randn(batch, n, **f),
                       0.3 + 0.01 * torch.randn(batch, n, **f),
                       torch.full((batch, n), 10.0, dtype=torch.float64),
                       torch.full((batch, n), 0.01, dtype=torch.float64)], -1)
    held = torch.zeros(n, dtype=torch.bool)
    held[::3] = True
    held[-1] = True
    win[:, ~held, :3] = NAN
    return win


def test_a_window_of_full_fixes_gives_the_paper_window_forms_estimate():
    torch.manual_seed(0)
    rec = WindowNet("filternet", 20, "frame", receiver=True).double()
    paper = WindowNet("filternet", 20, "frame", fixes=True).double()
    for p in rec.net.noise.parameters():  # a noise model that is not the identity
        torch.nn.init.normal_(p, std=0.3)
    paper.net.load_state_dict(rec.net.state_dict())
    win = _paper_windows()
    with torch.no_grad():
        want, got = paper(win), rec(win)
    assert torch.allclose(got, want, rtol=0, atol=1e-9)
    assert torch.allclose(rec(rw.widen(win)), want, rtol=0, atol=1e-9)  # the same window


def _hand_filter(rows: list[dict], q: np.ndarray, r: np.ndarray, h: float) -> np.ndarray:
    """A Kalman filter written out by hand for a car at standstill (F = I) in world axes:
    rows of ``z`` (3,) and ``held`` (3,) bool with their R (3, 3), the model's frame R
    ``r`` and Q ``q`` (3,) turned by the heading h. Returns the final state (3,)."""
    c, s = math.cos(h), math.sin(h)
    T = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    Q = T @ np.diag(q) @ T.T
    z, P = rows[0]["z"].copy(), rows[0]["R"].copy()
    for row in rows[1:]:
        P = P + Q
        sel = np.flatnonzero(row["held"])
        if len(sel) == 0:
            continue
        H = np.eye(3)[sel]
        S = H @ P @ H.T + row["R"][np.ix_(sel, sel)]
        K = P @ H.T @ np.linalg.inv(S)
        y = row["z"][sel] - H @ z
        z = z + K @ y
        P = (np.eye(3) - K @ H) @ P
    return z


def test_per_step_h_and_r_match_a_filter_written_out_by_hand():
    """A window of six rows at standstill: a position and a course; nothing; a position with sx, sy
    reported; a position and a course; nothing; a full fix with sx and spsi reported. The
    model's R and Q are not isotropic, so turning them between the world and the anchor's
    frame (its heading 0.7 rad) shows."""
    r_sig, q_sig, h = np.array([1.0, 0.5, 0.02]), np.array([0.1, 0.05, 0.001]), 0.7
    net = WindowNet("filternet", 6, "frame", receiver=True, measurement_sigma=tuple(r_sig),
                    process_sigma=tuple(q_sig)).double()
    cols = {name: i for i, name in enumerate(rw.COLUMNS)}
    win = np.full((6, rw.WIDTH), NAN)
    win[:, cols["V"]], win[:, cols["delta"]] = 0.0, 0.0
    win[0, :2], win[0, cols["course"]], win[0, cols["s_course"]] = [1.0, 2.0], 0.6, 0.05
    win[2, :2], win[2, 3:5] = [1.5, 1.6], [0.3, 0.8]
    win[3, :2], win[3, cols["course"]], win[3, cols["s_course"]] = [0.8, 2.3], 0.75, 0.05
    win[5, :3], win[5, cols["sx_m"]], win[5, cols["spsi_m"]] = [1.2, 2.1, h], 0.4, 0.01
    c, s = math.cos(h), math.sin(h)
    T = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    # the noise model's R in world axes: alpha = 1's, as the window holds one full fix (the
    # last), so its statistic holds no residual
    model = T @ np.diag(r_sig**2) @ T.T

    def told(x2: float | None, y2: float | None, head: float) -> np.ndarray:
        R = model.copy()
        if x2 is not None or y2 is not None:
            R[0, 1] = R[1, 0] = 0.0
        R[0, 0] = x2 if x2 is not None else R[0, 0]
        R[1, 1] = y2 if y2 is not None else R[1, 1]
        R[2, 2] = head
        return R

    none = np.zeros(3, bool)
    rows = [{"z": np.r_[win[0, :2], 0.6], "held": np.ones(3, bool),
             "R": told(None, None, 0.05**2)},
            {"z": np.zeros(3), "held": none, "R": model},
            {"z": np.r_[win[2, :2], 0.0], "held": np.array([1, 1, 0], bool),
             "R": told(0.09, 0.64, model[2, 2])},
            {"z": np.r_[win[3, :2], 0.75], "held": np.ones(3, bool),
             "R": told(None, None, 0.05**2)},
            {"z": np.zeros(3), "held": none, "R": model},
            {"z": win[5, :3], "held": np.ones(3, bool), "R": told(0.16, None, 0.01**2)}]
    want = _hand_filter(rows, q_sig**2, r_sig**2, h)
    with torch.no_grad():
        got = net(torch.from_numpy(win)[None])[0].numpy()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_a_window_with_nothing_to_start_at_gives_its_anchor():
    """Position fixes without any heading: the filter never starts, and the estimate is the
    window's anchor (its latest fix, carried by the bicycle)."""
    net = WindowNet("filternet", 10, "frame", receiver=True).double()
    win = np.full((1, 10, rw.WIDTH), NAN)
    win[..., 8], win[..., 9] = 5.0, 0.0  # V, delta
    win[0, 2, :2], win[0, 6, :2] = [0.0, 0.0], [0.6, 0.0]
    win = torch.from_numpy(win)
    with torch.no_grad():
        assert torch.allclose(net(win), net.anchor(win), rtol=0, atol=1e-12)


def test_what_cannot_read_a_receiver_is_refused_in_one_line():
    with pytest.raises(LboError, match=r"^model.drift: expected false for a window filter that "
                                       r"reads a receiver \(in_features=15\), got True$"):
        WindowFilter(20, in_features=15, drift=True)
    with pytest.raises(LboError, match=r"^model.in_features: expected 5, or 6 with the fix "
                                       r"channel, or 15 \(a receiver\), got 9$"):
        WindowFilter(20, in_features=9)
    with pytest.raises(LboError, match=r"^receiver: model 'kalmannet' does not read a "
                                       r"receiver's windows \(model.in_features: expected 5, or "
                                       r"6 with the fix channel, got 15\); the CNN, the LSTM "
                                       r"and the window filter \(filternet\) do$"):
        WindowNet("kalmannet", 20, "frame", receiver=True)


def test_the_single_track_body_reads_a_receiver_too():
    net = WindowNet("filternet", 20, "frame", receiver=True, body="single_track").double()
    win = _paper_windows()
    with torch.no_grad():
        est = net(win)
    assert torch.isfinite(est).all() and net.net.receiver


@pytest.mark.slow
def test_its_window_form_runs_a_single_antenna_log_alike_on_every_engine():
    """At N = 20 on fixes at 5 Hz (10 rows apart): the ONNX export unrolls the window's N
    steps, 7 s here where N = 60 on the receiver's default 1 Hz took 34 s, for the same
    graph of the same step."""
    torch.manual_seed(0)
    net = WindowNet("filternet", 20, "frame", fixes=True, receiver=True)
    for p in net.net.noise.parameters():  # a noise model that is not the identity
        torch.nn.init.normal_(p, std=0.3)
    log = simulate(compose_cfg("simulate", ["manoeuvre=free_drive", "duration=4",
                                            "receiver=single_antenna", "seed=1",
                                            "receiver.position.rate=5",
                                            "receiver.velocity.rate=5"]))
    m, u = log[["x_m", "y_m", "psi_m"]].to_numpy(float), log[["V", "delta"]].to_numpy(float)
    est = {engine: Observer.from_net(net, engine=engine, form="window").run(
        m, u, receiver=receiver(log))[0] for engine in ("torch", "torchscript", "onnx")}
    held = np.isfinite(est["torch"]).all(1)
    assert held.sum() > 100
    for engine in ("torchscript", "onnx"):
        np.testing.assert_allclose(est[engine][held], est["torch"][held], rtol=0, atol=1e-4,
                                   err_msg=engine)


def test_the_scores_give_a_window_filter_that_reads_a_receiver_in_both_forms():
    net = WindowNet("filternet", 20, "frame", receiver=True)
    rows = net_rows([Observer.from_net(net), Observer.from_net(WindowNet("cnn", 20, "frame",
                                                                         receiver=True))])
    assert [(label.split(",")[0], obs.form) for label, obs in rows.items()] == [
        ("filternet-N20 (recursive)", "recursive"), ("filternet-N20 (window)", "window"),
        ("cnn-N20 (window)", "window")]


@pytest.mark.slow
def test_experiment_receiver_trains_a_window_filter_that_runs_in_both_forms(tmp_path,
                                                                             smoke_data):
    cfg, out, _ = train_in_own_store(tmp_path, smoke_data, "experiment=receiver", "data=smoke",
                                     "model=filternet", "trainer.max_epochs=1",
                                     "trainer.limit_train_batches=3", "window=60",
                                     "batch_size=64")
    assert math.isfinite(out["val_loss"]) and math.isfinite(out["test_nrmse_alpha_1"])
    log = simulate(compose_cfg("simulate", ["manoeuvre=free_drive", "duration=4",
                                            "receiver=single_antenna", "seed=1"]))
    m, u = log[["x_m", "y_m", "psi_m"]].to_numpy(float), log[["V", "delta"]].to_numpy(float)
    for form in ("window", "recursive"):
        obs = Observer.load(out["checkpoint"], form=form)
        assert obs.net.receiver and obs.takes_receiver and obs.name == "filternet-N60"
        est, valid = obs.run(m, u, receiver=receiver(log))
        first = int(np.argmax(valid))
        assert valid[first:].all() and np.isfinite(est[first:]).all(), form
        z = log[["x", "y"]].to_numpy(float)
        assert np.sqrt(np.mean((est[first:, :2] - z[first:]) ** 2)) < 5.0, form
        obs.reset()  # streamed, the same numbers
        r = receiver(log)
        said = [s.state for s in step_log(obs, m, u, r, first + 80)]
        np.testing.assert_allclose(np.array(said)[first:], est[first:first + 80], rtol=0,
                                   atol=1e-6, err_msg=form)
