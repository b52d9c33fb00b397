"""Training noise drawn on the fly (lbo.learn.draws, the ``draw=`` of lbo.learn.datamodule and
``train_noise``)."""

import numpy as np
import pandas as pd
import pytest
import torch
from scipy import stats

from helpers import store_client, train_cfg
from lbo.core.errors import LboError
from lbo.learn.builders import noise_settings
from lbo.learn.datamodule import FixedDataset, WindowDataModule, WindowDataset, rows, window_ends
from lbo.learn.draws import AlphaDraw, loss_weights
from lbo.models.poses import wrap_angle_torch
from lbo.train import check, train

SIGMA = torch.tensor([1.0, 1.0, 0.0174], dtype=torch.float64)  # the paper preset at alpha=1
N = 80  # long windows, so that one window's noise std is a usable estimate of its alpha


@pytest.fixture(scope="module")
def train_rows(smoke_data):
    df = pd.read_parquet(smoke_data / "train.parquet")
    x, y = rows(df)
    return x, y, window_ends(df["k"].to_numpy(), N)


def dataset(train_rows, draw, seed=0, offset=None):
    """Drawn-noise windows of N=80 steps over the smoke training set."""
    x, y, ends = train_rows
    return WindowDataset(x, y, ends, N, draw=draw, sigma=SIGMA, seed=seed, weight_offset=offset)


def scaled_noise(ds, idx):
    """(m - z) / sigma of windows ``idx`` (heading difference wrapped), and the batch."""
    win, state, weight = ds[idx]
    s = ds.ends[torch.as_tensor(idx)] - ds.window + 1
    z = ds.truth[s]  # (B, N, 3) true states of the windows
    torch.testing.assert_close(state, z[:, -1], rtol=0, atol=0)  # the truth the noise is drawn on
    d = win[..., :3] - z
    d = torch.cat([d[..., :2], wrap_angle_torch(d[..., 2:])], dim=-1)
    return d / SIGMA, win, weight


def all_windows(ds):
    return list(range(len(ds)))


# --- the stream of draws ----------------------------------------------------------------


def first_batch(dm):
    dm.setup()
    return next(iter(dm.train_dataloader()))


def module(smoke_data, seed, **kw):
    kw = {"draw": AlphaDraw("uniform", low=0.0, high=6.5), "sigma": SIGMA,
          "weight_offset": 0.25, **kw}
    return WindowDataModule(smoke_data, window=20, batch_size=64, seed=seed, **kw)


@pytest.mark.parametrize("workers", [0, 2])
def test_same_seed_same_draws_another_seed_others(smoke_data, workers):
    """``seed`` alone fixes the stream, with or without loader workers (torch's global RNG,
    which the two loaders below find in different states, must not matter)."""
    a = first_batch(module(smoke_data, 3, num_workers=workers))
    b = first_batch(module(smoke_data, 3, num_workers=workers))
    for ta, tb in zip(a, b):
        assert ta.dtype == tb.dtype and ta.shape == tb.shape
        assert ta.numpy().tobytes() == tb.numpy().tobytes()  # byte-identical
    c = first_batch(module(smoke_data, 4, num_workers=workers))
    assert not torch.equal(a[0][..., :3], c[0][..., :3])
    assert not torch.equal(a[2], c[2])  # other alphas, so other loss weights


def test_every_epoch_draws_new_noise_on_the_same_states(smoke_data):
    dm = module(smoke_data, 0, draw=AlphaDraw("fixed", alpha=1.0), weight_offset=None)
    dm.setup()
    # a new loader restarts the shuffling (the same windows), not the noise stream
    first = [b for _, b in zip(range(3), dm.train_dataloader())]
    again = [b for _, b in zip(range(3), dm.train_dataloader())]
    for (w1, s1, _), (w2, s2, _) in zip(first, again):
        torch.testing.assert_close(s2, s1, rtol=0, atol=0)  # the same windows
        torch.testing.assert_close(w2[..., 3:], w1[..., 3:], rtol=0, atol=0)  # inputs as stored
        assert (w2[..., :3] != w1[..., :3]).all()  # every measurement drawn afresh
    # one loader iterated twice (what Lightning does every epoch): other windows, other noise
    loader = dm.train_dataloader()
    e1, e2 = next(iter(loader)), next(iter(loader))
    assert not torch.equal(e1[1], e2[1]) and not torch.equal(e1[0][..., :3], e2[0][..., :3])


def test_indexing_twice_redraws_only_the_measurements(train_rows):
    ds = dataset(train_rows, AlphaDraw("fixed", alpha=1.0))
    idx = [0, 5, 17, 400, len(ds) - 1]
    w1, s1, _ = ds[idx]
    w2, s2, _ = ds[idx]
    torch.testing.assert_close(s2, s1, rtol=0, atol=0)
    torch.testing.assert_close(w2[..., 3:], w1[..., 3:], rtol=0, atol=0)
    e = ds.ends[idx]
    stored = ds.windows[e - N + 1]  # (B, N, 5): the stored rows of those windows
    torch.testing.assert_close(w1[..., 3:], stored[..., 3:], rtol=0, atol=0)
    assert (w1[..., :3] != w2[..., :3]).all()
    assert not torch.equal(w1[..., :3], stored[..., :3])  # not the stored draw either


@pytest.mark.parametrize("workers", [0, 2])
def test_epochs_do_not_repeat_a_draw_with_loader_workers(smoke_data, workers):
    """The same windows in two epochs (no shuffling) must get new noise, with or without
    worker processes; and two batches must not share one noise draw."""
    dm = module(smoke_data, 0, draw=AlphaDraw("fixed", alpha=1.0), weight_offset=None,
                num_workers=workers)
    dm.setup()
    ds = dm.train_set
    loader = dm._loader(ds, 64, shuffle=False)
    epoch1 = [b for _, b in zip(range(2), loader)]
    epoch2 = [b for _, b in zip(range(2), loader)]
    assert not torch.equal(epoch1[0][0][..., :3], epoch2[0][0][..., :3]), \
        "the second epoch repeats the first epoch's noise"
    noise = [scaled_noise_of_batch(ds, b, j * 64) for j, b in enumerate(epoch1)]
    assert not torch.allclose(noise[0], noise[1]), "two batches share one noise draw"


def scaled_noise_of_batch(ds, batch, start):
    s = ds.ends[start:start + len(batch[1])] - ds.window + 1
    z = ds.truth[s]  # (B, N, 3) true states of the windows
    torch.testing.assert_close(batch[1], z[:, -1], rtol=0, atol=0)
    d = batch[0][..., :3] - z
    return torch.cat([d[..., :2], wrap_angle_torch(d[..., 2:])], dim=-1) / SIGMA


# --- the distribution of the noise ----------------------------------------------------------


def test_fixed_alpha_has_the_configured_std_per_channel(train_rows):
    ds = dataset(train_rows, AlphaDraw("fixed", alpha=2.0))
    eps, win, weight = scaled_noise(ds, all_windows(ds))
    flat = eps.reshape(-1, 3)
    assert len(flat) > 400_000
    np.testing.assert_allclose(flat.std(0).numpy(), 2.0, rtol=0.03)
    np.testing.assert_allclose(flat.mean(0).numpy(), 0.0, atol=0.02)
    # Gaussian: the excess kurtosis of a normal is 0
    np.testing.assert_allclose(stats.kurtosis(flat.numpy(), axis=0), 0.0, atol=0.05)
    assert torch.all(weight == 1)  # no offset: equal loss weights
    assert torch.all(win[..., 2].abs() <= np.pi)  # headings wrapped like the stored ones


def test_alpha_zero_measures_the_true_states(train_rows):
    ds = dataset(train_rows, AlphaDraw("fixed", alpha=0.0))
    eps, win, _ = scaled_noise(ds, all_windows(ds)[:500])
    assert torch.all(eps == 0)


def test_along_a_sequence_the_level_changes_where_drawn_and_the_weights_follow_it(train_rows):
    """train_noise.changes=2 on sequences: each window's alpha holds three drawn levels in
    turn (no more), the noise of each step is its level's (alpha 0: the true state exactly),
    and the weights are per step; without sequences a window keeps one level."""
    x, y, ends = train_rows
    draw = AlphaDraw("levels", levels=(0.0, 4.0), changes=2)
    ds = WindowDataset(x, y, ends, N, draw=draw, sigma=SIGMA, seed=3, weight_offset=0.25,
                       sequences=True)
    win, z, weight = ds[list(range(200))]
    assert weight.shape == (200, N)
    alpha = alpha_of_weight(weight, 0.25)
    switches = (alpha[:, 1:] != alpha[:, :-1]).sum(1)
    assert switches.max() <= 2 and (switches > 0).float().mean() > 0.5
    exact = (win[..., :3] == z).all(-1)
    torch.testing.assert_close(exact, torch.isclose(alpha, torch.zeros_like(alpha)),
                               rtol=0, atol=0)
    levels = draw.along(1000, 50, torch.Generator().manual_seed(0))
    assert levels.shape == (1000, 50) and set(levels.unique().tolist()) == {0.0, 4.0}
    one = WindowDataset(x, y, ends, N, draw=draw, sigma=SIGMA, seed=3, weight_offset=0.25)
    assert one[list(range(10))][2].shape == (10,)


def per_window_alpha(eps):
    """Root mean square of the scaled noise over a window's steps and channels: ~alpha."""
    return eps.pow(2).mean(dim=(1, 2)).sqrt()


def alpha_of_weight(weight, offset):
    return weight.rsqrt() - offset


def test_uniform_alpha_is_uniform_and_sets_each_window_noise(train_rows):
    ds = dataset(train_rows, AlphaDraw("uniform", low=0.0, high=6.5), offset=0.25)
    eps, _, weight = scaled_noise(ds, all_windows(ds))
    est = per_window_alpha(eps).numpy()
    assert len(est) > 6000
    # the estimates alone: uniform on [0, 6.5]
    assert est.mean() == pytest.approx(3.25, abs=0.08)
    q = [0.1, 0.25, 0.5, 0.75, 0.9]
    np.testing.assert_allclose(np.quantile(est, q), 6.5 * np.array(q), atol=0.15)
    assert est.min() >= 0 and est.max() <= 6.5 * 1.15
    # the alphas behind the loss weights: in range, uniform, and the ones that scaled the noise
    alpha = alpha_of_weight(weight, 0.25).numpy()
    assert alpha.min() >= 0 and alpha.max() <= 6.5
    assert stats.kstest(alpha, "uniform", args=(0.0, 6.5)).pvalue > 1e-3
    big = alpha > 0.5
    ratio = est[big] / alpha[big]
    assert np.median(np.abs(ratio - 1)) < 0.05
    assert np.quantile(np.abs(ratio - 1), 0.99) < 0.15
    assert np.abs(est[~big] - alpha[~big]).max() < 0.1
    # across channels too: x, y and psi of a window share its alpha
    per_channel = eps.pow(2).mean(dim=1).sqrt().numpy()[big] / alpha[big, None]
    np.testing.assert_allclose(np.median(per_channel, axis=0), 1.0, atol=0.03)


@pytest.mark.parametrize("levels", [(1.0, 3.0), (0.5, 2.0, 5.0)])
def test_levels_draw_only_those_levels_equally_often(train_rows, levels):
    ds = dataset(train_rows, AlphaDraw("levels", levels=levels), offset=0.5)
    eps, _, weight = scaled_noise(ds, all_windows(ds))
    est = per_window_alpha(eps).numpy()
    alpha = alpha_of_weight(weight, 0.5).numpy()
    level = np.abs(alpha[:, None] - np.array(levels)).argmin(1)
    np.testing.assert_allclose(alpha, np.array(levels)[level], rtol=0, atol=1e-9)  # only those
    np.testing.assert_allclose(np.bincount(level, minlength=len(levels)) / len(alpha),
                               1 / len(levels), atol=0.03)
    # the noise alone tells the levels apart (nearest in log), and agrees with the weights
    nearest = np.abs(np.log(est[:, None]) - np.log(levels)).argmin(1)
    np.testing.assert_array_equal(nearest, level)
    assert np.quantile(np.abs(est / alpha - 1), 0.99) < 0.15


def test_loguniform_alpha_is_uniform_in_log(train_rows):
    ds = dataset(train_rows, AlphaDraw("loguniform", low=0.1, high=6.5), offset=0.25)
    _, _, weight = scaled_noise(ds, all_windows(ds)[:3000])
    alpha = alpha_of_weight(weight, 0.25).numpy()
    assert alpha.min() >= 0.1 - 1e-9 and alpha.max() <= 6.5 + 1e-9
    lo, hi = np.log(0.1), np.log(6.5)
    assert stats.kstest(np.log(alpha), "uniform", args=(lo, hi - lo)).pvalue > 1e-3


# --- loss weights -----------------------------------------------------------------------------


def test_loss_weights_are_inverse_squares_or_ones():
    alpha = torch.tensor([0.0, 0.5, 1.0, 3.0, 6.5], dtype=torch.float64)
    torch.testing.assert_close(loss_weights(alpha, 0.25), 1.0 / (alpha + 0.25) ** 2,
                               rtol=1e-15, atol=0)
    assert loss_weights(alpha, 0.25)[0].item() == pytest.approx(16.0)
    ones = loss_weights(alpha, None)
    assert ones.dtype == alpha.dtype and ones.shape == alpha.shape and torch.all(ones == 1)


def test_loss_weights_follow_the_noise_of_each_window(train_rows):
    """Weights from the per-window noise std: 1/(alpha_hat + offset)^2, within the estimate's
    error (about 5 % on alpha for 240 noise samples)."""
    ds = dataset(train_rows, AlphaDraw("uniform", low=1.0, high=6.0), offset=1.0)
    eps, _, weight = scaled_noise(ds, all_windows(ds)[:2000])
    from_noise = loss_weights(per_window_alpha(eps), 1.0)
    ratio = (weight / from_noise).numpy()
    assert np.median(np.abs(ratio - 1)) < 0.08
    assert np.quantile(np.abs(ratio - 1), 0.99) < 0.25


# --- validation: one fixed draw ---------------------------------------------------------------


def val_tensors(dm):
    dm.setup()
    assert isinstance(dm.val_set, FixedDataset)
    return dm.val_set[list(range(len(dm.val_set)))]


def test_validation_is_one_fixed_draw(smoke_data):
    dm = module(smoke_data, 7, val_repeats=3)
    a = val_tensors(dm)
    assert len(dm.val_set) == 3 * 995
    b = val_tensors(dm)
    c = val_tensors(module(smoke_data, 7, val_repeats=3))
    for ta, tb, tc in zip(a, b, c):
        assert ta.numpy().tobytes() == tb.numpy().tobytes() == tc.numpy().tobytes()
    # the val loader (every epoch) yields that same draw
    loader = dm.val_dataloader()
    for _ in range(2):
        got = [torch.cat(t) for t in zip(*loader)]
        for g, t in zip(got, a):
            assert torch.equal(g, t)
    # training draws do not move it
    next(iter(dm.train_dataloader()))
    assert torch.equal(val_tensors(dm)[0], a[0])
    win, state, weight = a
    # each repeat: the same 995 windows and inputs, its own noise and alpha
    for r in (1, 2):
        torch.testing.assert_close(state[r * 995:(r + 1) * 995], state[:995], rtol=0, atol=0)
        torch.testing.assert_close(win[r * 995:(r + 1) * 995, :, 3:], win[:995, :, 3:],
                                   rtol=0, atol=0)
        assert (win[r * 995:(r + 1) * 995, :, :3] != win[:995, :, :3]).all()
    # over the training distribution of alpha (uniform on [0, 6.5], weights 1/(alpha+0.25)^2)
    alpha = alpha_of_weight(weight, 0.25)
    assert alpha.min() >= 0 and alpha.max() <= 6.5 and alpha.std() > 1.5
    # another seed: another draw on the same windows
    d = val_tensors(module(smoke_data, 8, val_repeats=3))
    assert torch.equal(d[1], state) and not torch.equal(d[0], win)


def test_stored_measurements_stay_the_validation_set(smoke_data):
    dm = WindowDataModule(smoke_data, window=20, seed=0)
    dm.setup()
    assert isinstance(dm.val_set, WindowDataset) and len(dm.val_set) == 995
    win, _, weight = dm.val_set[[0, 1, 2]]
    assert torch.all(weight == 1)
    np.testing.assert_array_equal(win[:, -1].numpy(), dm.val_set.x[dm.val_set.ends[:3]].numpy())


def test_drawn_noise_without_sigmas_is_refused(smoke_data):
    with pytest.raises(LboError, match="sigma"):
        WindowDataModule(smoke_data, window=20, draw=AlphaDraw("fixed"))


# --- the train_noise group: presets and bad input ------------------------------------------


def test_presets_compose_to_their_settings(tmp_path, smoke_data):
    paper = noise_settings(train_cfg(tmp_path, smoke_data))
    assert paper["draw"] == AlphaDraw("fixed", alpha=1.0)
    assert paper["weight_offset"] is None and paper["val_repeats"] == 4
    assert paper["sigma"] == (1.0, 1.0, 0.0174)
    diverse = noise_settings(train_cfg(tmp_path, smoke_data, "train_noise=diverse"))
    assert diverse["draw"] == AlphaDraw("uniform", low=0.0, high=6.5)
    assert diverse["weight_offset"] == 0.25
    assert noise_settings(train_cfg(tmp_path, smoke_data, "train_noise=stored")) == {}
    levels = noise_settings(train_cfg(tmp_path, smoke_data, "train_noise.distribution=levels",
                                      "train_noise.levels=[1,3]"))
    assert levels["draw"].levels == (1, 3)


BAD = [  # overrides, the field the one line must start with
    (["train_noise.alpha=-1"], "train_noise.alpha"),
    (["train_noise.alpha=inf"], "train_noise.alpha"),
    (["train_noise.alpha=abc"], "train_noise.alpha"),
    (["train_noise.alpha=true"], "train_noise.alpha"),
    (["train_noise.distribution=uniform", "train_noise.low=3", "train_noise.high=3"],
     "train_noise.high"),
    (["train_noise.distribution=uniform", "train_noise.low=4", "train_noise.high=1"],
     "train_noise.high"),
    (["train_noise.distribution=uniform", "train_noise.low=-1"], "train_noise.low"),
    (["train_noise.distribution=loguniform", "train_noise.low=0"], "train_noise.low"),
    (["train_noise.distribution=gamma"], "train_noise.distribution"),
    (["train_noise.distribution=levels"], "train_noise.levels"),
    (["train_noise.distribution=levels", "train_noise.levels=[1,-2]"], "train_noise.levels"),
    (["train_noise.distribution=levels", "train_noise.levels=abc"], "train_noise.levels"),
    (["train_noise.source=disk"], "train_noise.source"),
    (["train_noise.loss_weight_offset=0"], "train_noise.loss_weight_offset"),
    (["train_noise.val_repeats=0"], "train_noise.val_repeats"),
    (["train_noise.changes=-1"], "train_noise.changes"),
    (["train_noise.changes=1.5"], "train_noise.changes"),
]


@pytest.mark.parametrize("overrides, field", BAD, ids=[" ".join(o) for o, _ in BAD])
def test_bad_train_noise_is_one_line_naming_the_field(tmp_path, smoke_data, overrides, field):
    cfg = train_cfg(tmp_path, smoke_data, *overrides)
    for call in (noise_settings, check):
        with pytest.raises(LboError) as err:
            call(cfg)
        message = str(err.value)
        assert message.startswith(field + " ") or message.startswith(field + ":"), message
        assert "\n" not in message


@pytest.mark.parametrize("overrides", [["train_noise.alpha=-1"],
                                       ["train_noise.distribution=gamma"]])
def test_bad_train_noise_is_refused_before_anything_is_written(tmp_path, smoke_data, tracking,
                                                               overrides):

    with pytest.raises(LboError, match="^train_noise"):
        train(train_cfg(tmp_path, smoke_data, *overrides))
    assert not (tmp_path / "out").exists()  # no checkpoint folder, no config.yaml
    exp = store_client(tracking).get_experiment_by_name("lbo-smoke")
    assert exp is None or store_client(tracking).search_runs([exp.experiment_id]) == []
