"""A net that reads a receiver, trained on logs with truth (issue 36: a real drive's train
span): the windows cut from the logs, fine-tuned and from scratch, the epoch kept by the
validation logs, and the checkpoint written that every lbo command loads."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest
import torch

from helpers import compose_cfg, train_in_own_store
from lbo.core.errors import LboError
from lbo.learn import net_fit
from lbo.logs.io import receiver
from lbo.models.envelope import Envelope
from lbo.models.net import WindowNet
from lbo.serve.observer import Observer
from lbo.simulate import simulate

pytestmark = pytest.mark.usefixtures("one_torch_thread")
N = 30


def _logs(*seeds: int, duration: float = 6.0) -> list[pd.DataFrame]:
    return [simulate(compose_cfg("simulate", ["manoeuvre=free_drive", f"duration={duration}",
                                              "receiver=single_antenna", f"seed={s}"]))
            for s in seeds]


@pytest.fixture(scope="module")
def logs() -> list[pd.DataFrame]:
    return _logs(1, 2, 3)


def _net(seed: int = 0) -> WindowNet:
    torch.manual_seed(seed)
    return WindowNet("cnn", N, "frame", fixes=True, receiver=True).eval()


def test_the_windows_hold_a_fix_and_never_cross_from_one_log_to_the_next(logs):
    got = net_fit.log_windows(logs[:2], N, 2.7)
    lengths = [len(log) for log in logs[:2]]
    starts = np.cumsum([0, *lengths])
    ends = got.ends.numpy()
    first = ends - N + 1
    log_of = np.searchsorted(starts, ends, side="right") - 1
    assert (first >= starts[log_of]).all()  # a window's rows are all one log's
    win, truth = got.batch(torch.arange(len(got)))
    assert win.shape == (len(got), N, 11) and win.dtype == torch.float64
    assert torch.isfinite(win[..., 0]).any(1).all()  # every window holds a fix
    # every window of N rows that holds a fix is there: with 1 Hz fixes (50 rows apart) and
    # N = 30, some are not
    fixes = [np.flatnonzero(np.isfinite(log["x_m"].to_numpy())) for log in logs[:2]]
    expected = sum(sum(bool(((f >= e - N + 1) & (f <= e)).any()) for e in range(N - 1, n))
                   for f, n in zip(fixes, lengths))
    assert len(got) == expected < sum(n - N + 1 for n in lengths)
    # the rows are the log's as an observer reads them, the truth at each window's end
    log = logs[0]
    k = int(ends[0])
    assert np.isclose(float(win[0, -1, 8]), log["V"].iloc[k])
    assert np.isclose(float(win[0, -1, 10]), log["r_m"].iloc[k], equal_nan=True)
    np.testing.assert_allclose(truth[0].numpy(), log[["x", "y", "psi"]].iloc[k].to_numpy())


def test_fine_tuning_keeps_the_best_validation_epoch_and_is_repeatable(logs):
    train, val = (net_fit.log_windows(p, N, 2.7) for p in (logs[:2], logs[2:]))
    net = _net()
    before = {k: v.clone() for k, v in net.state_dict().items()}
    lines = []
    fitted = net_fit.fit(net, train, val, epochs=3, lr=3e-3, batch=64, seed=5,
                         progress=lines.append)
    h = fitted.history
    # a line per epoch, and after the first how long the other two will take
    assert list(h["epoch"]) == [0, 1, 2, 3] and len(lines) == 4
    assert lines[0].startswith("epoch 1/3: ") and lines[2].startswith("epoch 2/3: ")
    assert re.fullmatch(r"estimate: 2 more epochs x [0-9.]+ s \(epoch 1's time\): about \d+ s",
                        lines[1]), lines[1]
    assert fitted.best_epoch == int(h["val"].idxmin())
    assert h["val"].iloc[1:].min() < h["val"].iloc[0]  # it learns from these logs
    assert net_fit._val_loss(fitted.net, val) == pytest.approx(h["val"].min(), rel=1e-6)
    # the source is not touched; the same seed gives the same net
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())
    again = net_fit.fit(net, train, val, epochs=3, lr=3e-3, batch=64, seed=5)
    assert all(torch.equal(v, again.net.state_dict()[k])
               for k, v in fitted.net.state_dict().items())
    # the normalisation is the source's when fine-tuned
    assert torch.equal(fitted.net.in_mean, net.in_mean)


def test_from_scratch_draws_new_parameters_and_the_train_windows_normalisation(logs):
    train, val = (net_fit.log_windows(p, N, 2.7) for p in (logs[:2], logs[2:]))
    net = _net()
    fresh = net_fit.fit(net, train, val, epochs=0, lr=1e-3, seed=7, fresh=True).net
    weight = next(n for n, _ in net.named_parameters())
    assert not torch.equal(dict(net.named_parameters())[weight],
                           dict(fresh.named_parameters())[weight])
    win, state = train.batch(torch.arange(len(train)))
    stats = net.statistics(win, state)
    np.testing.assert_allclose(fresh.in_mean.numpy(), stats["in_mean"].numpy(), rtol=1e-12)
    assert fresh.in_mean.dtype == torch.float64
    assert next(fresh.parameters()).dtype == torch.float32


def test_from_scratch_a_window_filter_starts_as_its_constructor_draws_it(logs):
    """Every parameter anew, the filter's own scalars (its process noise's scale, the gyro's
    noises) included: none is the trained net's."""
    def gyro_filter() -> WindowNet:
        return WindowNet("filternet", N, "frame", fixes=True, receiver=True, gyro=True)

    trained = gyro_filter()
    with torch.no_grad():
        for p in trained.parameters():  # as if trained
            p.add_(0.5)
    train, val = (net_fit.log_windows(p, N, 2.7) for p in (logs[:2], logs[2:]))
    fresh = net_fit.fit(trained, train, val, epochs=0, lr=1e-3, seed=7, fresh=True).net
    torch.manual_seed(7)
    drawn = dict(gyro_filter().named_parameters())
    assert {"net.log_q_scale", "net.log_gyro_sigma", "net.log_bias_walk"} <= set(drawn)
    for name, p in fresh.named_parameters():
        assert torch.equal(p, drawn[name]), name


def test_what_cannot_be_trained_on_a_log_is_one_line(logs):
    windows = net_fit.log_windows(logs[:1], N, 2.7)
    paper = WindowNet("cnn", N, "frame", fixes=True)
    with pytest.raises(LboError, match=r"^training on a log: cnn-N30 does not read a receiver "
                                       r"\(train one with experiment=receiver\)$"):
        net_fit.fit(paper, windows, windows, epochs=1, lr=1e-3)
    bare = logs[0].drop(columns=[c for c in logs[0].columns if c in
                                 ("sx_m", "sy_m", "spsi_m", "ve_m", "vn_m", "sv_m", "r_m")])
    with pytest.raises(LboError, match=r"^training on a log: a net that reads a receiver needs "
                                       r"its channels"):
        net_fit.log_windows([bare], N, 2.7)
    with pytest.raises(LboError, match=r"^training on a log: no window of 400 rows holds"):
        net_fit.log_windows([logs[0].iloc[:100]], 400, 2.7)


def test_an_envelope_union_covers_both_and_keeps_a_known_alpha():
    a = Envelope(speed=(1.0, 20.0), steering=(-0.2, 0.2), alpha=(0.0, 6.5), fix_period=(5.0, 50.0))
    b = Envelope(speed=(-2.0, 15.0), steering=(-0.5, 0.1), alpha=None, fix_period=(50.0, 50.0))
    u = a.union(b)
    assert (u.speed, u.steering, u.alpha, u.fix_period) == (
        (-2.0, 20.0), (-0.5, 0.2), (0.0, 6.5), (5.0, 50.0))
    assert b.union(b).alpha is None


@pytest.mark.slow
def test_a_trained_receiver_net_fine_tuned_on_logs_is_a_checkpoint_lbo_loads(tmp_path,
                                                                            smoke_data):
    _, out, uri = train_in_own_store(tmp_path, smoke_data, "experiment=receiver", "data=smoke",
                                     "trainer.max_epochs=1", "trainer.limit_train_batches=2",
                                     "window=60", "batch_size=64", "~callbacks.evaluation")
    with pytest.MonkeyPatch.context() as mp:  # without the evaluation, its run has the weights
        mp.setenv("MLFLOW_TRACKING_URI", uri)
        assert Observer.load(out["run_id"]).name == "cnn-N60"
    train, val = _logs(4, 5, duration=8.0), _logs(6, duration=8.0)
    for fresh, name in ((False, "tuned.ckpt"), (True, "scratch.ckpt")):
        path = net_fit.fit_and_write(tmp_path / name, out["checkpoint"], train, val,
                                     "on simulated logs", fresh=fresh, epochs=1, lr=1e-3,
                                     batch=128)
        obs = Observer.load(path)
        assert obs.net.receiver and obs.name == "cnn-N60"
        assert obs.meta["trained_on"].startswith("on simulated logs, " + (
            "from scratch" if fresh else f"fine-tuned from {out['checkpoint']}"))
        history = pd.read_csv(tmp_path / f"{path.stem}_history.csv")
        assert list(history["epoch"]) == [0, 1]
        envelope = Envelope.from_dict(obs.meta["envelope"])
        speeds = np.concatenate([log["V"].to_numpy() for log in train])
        assert envelope.speed[0] <= speeds.min() and envelope.speed[1] >= speeds.max()
        assert (envelope.alpha is None) == fresh  # fine-tuned: the simulated alphas it knew
        log = val[0]
        est, valid = obs.run(log[["x_m", "y_m", "psi_m"]].to_numpy(float),
                             log[["V", "delta"]].to_numpy(float), receiver=receiver(log))
        assert valid[59:].any() and np.isfinite(est[valid]).all()
    assert sorted(p.name for p in tmp_path.glob("*.ckpt*")) == ["scratch.ckpt", "tuned.ckpt"]
