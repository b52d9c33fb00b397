"""The classical observers scored ahead in a process of their own, on the core a training
leaves idle (:mod:`lbo.scoring.peers_ahead`), kept as the evaluation scores them."""

from __future__ import annotations

import os
import shutil

import pandas as pd
import pytest

from helpers import train_cfg
from lbo.filters.classical import GRID_PEERS
from lbo.scoring import peers_ahead, score_cache
from lbo.scoring.grid import classical_table, load_test, reference
from lbo.train import meta


def unscored_copy(smoke_data, folder):
    """A copy of the smoke data set in ``folder``, without the classical rows kept in it."""
    shutil.copytree(smoke_data, folder)
    shutil.rmtree(folder / score_cache.FOLDER, ignore_errors=True)
    return folder


def conditions(tmp_path, smoke_data):
    from lbo.models.checkpoint import trained_conditions

    info = meta(train_cfg(tmp_path, smoke_data), "-")
    return info, *trained_conditions({"meta": info}, "-")


def test_peers_scored_ahead_are_kept_as_the_evaluation_scores_them(tmp_path, smoke_data):
    folder = unscored_copy(smoke_data, tmp_path / "set")
    info, vehicle, noise = conditions(tmp_path, smoke_data)
    ahead = peers_ahead.start(folder, info, GRID_PEERS, "ekf")
    assert ahead.wait() is None
    kept = sorted(p.name.split("-")[0] for p in (folder / score_cache.FOLDER).iterdir())
    assert kept == sorted(GRID_PEERS)
    arr = load_test(folder / "test.parquet")
    ref = reference(arr, vehicle, noise)
    fresh = classical_table(arr, vehicle, noise, GRID_PEERS, ref)  # scored here, not kept
    read = classical_table(arr, vehicle, noise, GRID_PEERS, ref, keep=folder / "test.parquet")
    pd.testing.assert_frame_equal(read, fresh)


def test_a_failed_scoring_says_why_in_one_line_and_keeps_nothing(tmp_path, smoke_data):
    info, _, _ = conditions(tmp_path, smoke_data)
    (tmp_path / "empty").mkdir()
    failed = peers_ahead.start(tmp_path / "empty", info, GRID_PEERS, "ekf").wait()
    assert failed is not None and failed.startswith("exit 1: lbo.scoring.peers_ahead: ")
    assert "test.parquet" in failed and "\n" not in failed
    assert not (tmp_path / "empty" / score_cache.FOLDER).exists()


def test_a_stopped_scoring_ends_and_leaves_no_partial_file(tmp_path, smoke_data):
    folder = unscored_copy(smoke_data, tmp_path / "set")
    info, _, _ = conditions(tmp_path, smoke_data)
    ahead = peers_ahead.start(folder, info, GRID_PEERS, "ekf")
    ahead.stop()
    assert not ahead.running()
    kept = folder / score_cache.FOLDER
    assert all(p.suffix == ".parquet" for p in kept.iterdir()) if kept.exists() else True
    assert ahead.process.returncode in (143, -15)  # its own exit, or killed before it set it


def test_a_spare_core_is_one_no_launcher_shares_out(monkeypatch):
    cores = len(os.sched_getaffinity(0))
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert peers_ahead.spare_core(cores - 1) == (cores > 1)
    assert not peers_ahead.spare_core(cores)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # xdist's workers, joblib's jobs: cores shared
    assert not peers_ahead.spare_core(1)


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs a core the training leaves")
def test_a_training_on_one_thread_scores_its_peers_on_the_idle_core(tmp_path, smoke_data,
                                                                   tracking, monkeypatch):
    """``threads=1`` with a core to spare: the evaluation's classical rows are the ones the
    process beside the training kept, and the same as a training scoring them itself."""
    from lbo.train import train

    root = tmp_path / "data"
    unscored_copy(smoke_data, root / smoke_data.name)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    started, waited = [], []
    real_start = peers_ahead.start

    def start(*args):
        ahead = real_start(*args)
        real_wait = ahead.wait
        ahead.wait = lambda: waited.append(real_wait()) or waited[-1]
        started.append(args)
        return ahead

    monkeypatch.setattr(peers_ahead, "start", start)
    torch_threads = __import__("torch").get_num_threads()
    try:
        train(train_cfg(tmp_path / "a", smoke_data, f"data.root={root}", "threads=1"))
    finally:
        __import__("torch").set_num_threads(torch_threads)
    assert len(started) == 1 and waited == [None]
    kept = sorted(p.name.split("-")[0] for p in (root / smoke_data.name / score_cache.FOLDER)
                  .iterdir())
    assert kept == sorted(GRID_PEERS)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # no core to spare: scored in the evaluation
    train(train_cfg(tmp_path / "b", smoke_data))  # the shared set, its peers scored here
    assert len(started) == 1

    def peer_rows(run: str) -> pd.DataFrame:
        table = pd.read_csv(tmp_path / run / "out" / "evaluation.csv")
        return table[table["observer"].isin(GRID_PEERS)].reset_index(drop=True)

    pd.testing.assert_frame_equal(peer_rows("a"), peer_rows("b"))
