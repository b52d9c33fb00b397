"""The training's progress bar says which epoch of how many (lbo.learn.progress)."""

from __future__ import annotations

import re

import pytest

from helpers import cli
from lbo.learn.progress import epoch_words, estimate_words


@pytest.mark.parametrize(("epoch", "most", "early", "said"), [
    (2, 10, False, "epoch 3 of 10"), (0, 100, True, "epoch 1 of at most 100"),
    (4, -1, True, "epoch 5"), (0, None, False, "epoch 1")])
def test_an_epoch_is_counted_from_one_and_of_its_total(epoch, most, early, said):
    assert epoch_words(epoch, most, early) == said


def test_the_estimate_multiplies_epochs_batches_and_the_time_of_one():
    said = estimate_words(0.73, 100, 4, 9, early_stopping=True)
    assert said.startswith("estimate: 4 epochs x 100 batches x 0.73 s (timed over 9 of its "
                           "first batches): about 4 min 52 s of training, less if early "
                           "stopping ends it;")
    assert "about 2 s of training;" in estimate_words(1.0, 2, 1, 1, early_stopping=False)
    assert "): under 1 s of training;" in estimate_words(0.01, 20, 2, 9, early_stopping=False)


@pytest.mark.slow
def test_a_training_says_epoch_k_of_n_on_its_bar(tmp_path, smoke_data):
    res = cli("lbo.train", "experiment=smoke", f"data.root={smoke_data.parent}",
              "trainer.max_epochs=2", "trainer.limit_train_batches=2", "keep_onnx=false",
              "~callbacks.evaluation", f"output_dir={tmp_path / 'out'}",
              f"hydra.run.dir={tmp_path}",
              env={"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"},
              process=True)  # a process of its own: pytest would take Lightning's warnings
    assert res.returncode == 0, res.stderr[-3000:]
    # Lightning's bar writes to stdout; the default callbacks stop early: the total is at most
    assert "epoch 1 of at most 2" in res.stdout and "epoch 2 of at most 2" in res.stdout
    # how long it will take, said once, after its first epoch's two batches (one timed)
    estimates = re.findall(r"estimate: 2 epochs x 2 batches x (\S+) s \(timed over 1 of its "
                           r"first batches\): (?:about \d+ s|under 1 s) of training", res.stdout)
    assert len(estimates) == 1 and float(estimates[0]) > 0, res.stdout[-3000:]
    # each bar's last word on its epoch is ours (Lightning's own "Epoch 0", from 0 and without
    # a total, is drawn first and overwritten at once)
    done = [f for f in res.stdout.replace("\r", "\n").splitlines()
            if "100%|" in f and not f.startswith("Validation")]
    assert done and all(f.startswith("epoch ") for f in done), done
    # lbo logs per epoch: Lightning's warning on its per-step logging interval is not shown
    assert "log_every_n_steps" not in res.stdout + res.stderr
    # nor its hint at srun where SLURM is installed (lbo's SLURM jobs come through submitit)
    assert "srun" not in res.stdout + res.stderr


def test_how_often_the_bar_draws_is_not_part_of_a_runs_identity():
    """make reproduce hides each run's bar (refresh_rate=0): its runs are the runs of the same
    config trained with the bar, and of a store made before."""
    from helpers import compose_cfg
    from lbo.learn.identity import config_hash
    from lbo.learn.layouts import hash_v1

    shown = compose_cfg("train", ["experiment=smoke"])
    hidden = compose_cfg("train", ["experiment=smoke", "callbacks.progress_bar.refresh_rate=0"])
    assert config_hash(hidden) == config_hash(shown)
    assert hash_v1(hidden) == hash_v1(shown)  # the version-1 runs, migrated, are both's
    assert config_hash(compose_cfg("train", ["experiment=smoke", "window=40"])) != \
        config_hash(shown)
