"""GNSS outages drawn into training windows (``train_outages``): a share of the windows loses
every fix in one stretch, as a log does under a bridge, so a learned filter meets outages in
training (lbo.learn.draws.OutageDraw)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from helpers import ROBUST_SMOKE, train_cfg, train_in_own_store
from lbo.core.errors import LboError
from lbo.learn.builders import datamodule
from lbo.learn.draws import OutageDraw
from lbo.learn.identity import config_hash
from lbo.learn.layouts import hash_v1, upgraded
from lbo.train import check


def _stretches(row: torch.Tensor) -> list[tuple[int, int]]:
    """The (first step, length) of each run of False in a (N,) bool row."""
    out, start = [], None
    for k, held in enumerate(row.tolist() + [True]):
        if not held and start is None:
            start = k
        elif held and start is not None:
            out.append((start, k - start))
            start = None
    return out


def test_a_drawn_outage_is_one_stretch_of_the_window_half_of_them_to_its_last_step():
    g = torch.Generator().manual_seed(0)
    fix = torch.ones(4000, 50, dtype=torch.bool)
    cut = OutageDraw(share=1.0, max_steps=20).cut(fix, g)
    stretches = [_stretches(row) for row in cut]
    assert all(len(s) == 1 for s in stretches)  # one stretch in every window
    lengths = np.array([s[0][1] for s in stretches])
    ends = np.array([s[0][0] + s[0][1] for s in stretches])
    assert lengths.min() == 1 and lengths.max() == 20  # 1 to max_steps steps
    assert 0.48 < np.mean(ends == 50) < 0.55  # half to the last step, and 1 in 31-50 by chance
    assert (ends < 50).mean() > 0.4  # the rest: recoveries, fixes after the outage


def test_a_share_of_the_windows_and_a_cap_of_the_window_less_one_step():
    g = torch.Generator().manual_seed(1)
    fix = torch.ones(4000, 12, dtype=torch.bool)
    cut = OutageDraw(share=0.3, max_steps=500).cut(fix, g)
    hit = ~cut.all(1)
    assert 0.27 < hit.float().mean() < 0.33
    assert cut.any(1).all() and (~cut).sum(1).max() == 11  # at most N - 1 steps


def test_a_window_whose_fixes_all_fall_in_its_outage_keeps_the_one_beside_it():
    g = torch.Generator().manual_seed(2)
    fix = torch.zeros(3000, 30, dtype=torch.bool)
    fix[:, 29] = True  # one fix, at the last step: an outage to the end takes it
    cut = OutageDraw(share=1.0, max_steps=10).cut(fix, g)
    assert cut.any(1).all()
    lost = ~cut[:, 29]
    assert lost.any() and (cut[lost].sum(1) == 1).all()  # one fix kept, just before it
    kept_at = cut[lost].float().argmax(1)
    assert (kept_at < 29).all()


def test_no_outage_draws_nothing_and_leaves_the_stream_of_draws_as_it_was():
    g, h = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    fix = torch.rand(8, 20, generator=torch.Generator().manual_seed(4)) < 0.5
    assert torch.equal(OutageDraw(share=0.0).cut(fix, g), fix)
    assert torch.equal(torch.rand(5, generator=g), torch.rand(5, generator=h))


BAD = [
    (["train_outages.share=0.5"], "train_outages.share: outages need a net that reads the fix "
                                  "channel (fix_rates, e.g. experiment=robust), got 0.5 with "
                                  "fix_rates=null"),
    (["fix_rates=[10]", "train_outages.share=2"],
     "train_outages.share must be a share in [0, 1], got 2"),
    (["fix_rates=[10]", "train_outages.share=0.5", "train_outages.max_s=0"],
     "train_outages.max_s must be a number of seconds > 0, got 0"),
    (["fix_rates=[10]", "+train_outages.length=3"],
     "train_outages.length: not a field; accepted: share, max_s"),
]


@pytest.mark.parametrize("overrides, line", BAD, ids=[" ".join(o) for o, _ in BAD])
def test_a_bad_outage_setting_is_one_line_before_any_data(tmp_path, smoke_data, overrides,
                                                           line):
    with pytest.raises(LboError) as err:
        check(train_cfg(tmp_path, smoke_data, *overrides))
    assert str(err.value) == line


def test_the_default_hashes_as_the_runs_stored_before_it(tmp_path, smoke_data):
    cfg = train_cfg(tmp_path, smoke_data, "experiment=robust")
    stored = cfg.copy()
    with __import__("omegaconf").open_dict(stored):
        stored.pop("train_outages")
    assert hash_v1(cfg) == hash_v1(stored)  # the hash those runs carry (version 1)...
    assert config_hash(upgraded(stored)) == config_hash(cfg)  # ...migrated: the default's
    drawn = train_cfg(tmp_path, smoke_data, "experiment=robust", "train_outages.share=0.5")
    assert config_hash(drawn) != config_hash(cfg)


def test_training_and_validation_windows_lose_their_fixes_in_the_outages(tmp_path, smoke_data):
    """The robust observer's windows (drawn noise), their fixes kept at every step
    (``fix_rates=[50]``) but for the outages, of up to 0.4 s (20 steps) in half of them: the
    blanked rows are NaN in x_m, y_m and psi_m, one stretch a window, and every window keeps
    a fix; the validation set's one fixed draw has them too."""
    cfg = train_cfg(tmp_path, smoke_data, *ROBUST_SMOKE, "window=40", "fix_rates=[50]",
                    "train_outages.share=0.5", "train_outages.max_s=0.4")
    dm = datamodule(cfg, smoke_data)
    assert dm.outages == OutageDraw(share=0.5, max_steps=20)
    for windows in (dm.train_set[list(range(2000))][0], dm.val_set.tensors[0]):
        held = torch.isfinite(windows[..., 0])
        assert torch.equal(torch.isfinite(windows[..., 2]), held)
        gaps = [_stretches(row) for row in held]
        assert all(len(g) <= 1 and sum(n for _, n in g) <= 20 for g in gaps)
        hit = np.array([len(g) == 1 for g in gaps])
        assert 0.4 < hit.mean() < 0.6 and held.any(1).all()
        to_end = np.array([len(g) == 1 and sum(g[0]) == 40 for g in gaps])
        assert 0.4 < to_end.sum() / hit.sum() < 0.65  # half, and some by chance


@pytest.mark.slow
def test_the_robust_observer_trains_through_drawn_outages(tmp_path, smoke_data):
    _, out, _ = train_in_own_store(tmp_path, smoke_data, *ROBUST_SMOKE, "window=40",
                                   "trainer.limit_train_batches=3", "batch_size=64",
                                   "train_outages.share=0.5", "train_outages.max_s=0.4")
    assert math.isfinite(out["val_loss"]) and math.isfinite(out["test_nrmse_alpha_1"])
