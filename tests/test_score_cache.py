"""The classical observers' rows kept beside a test set (lbo.scoring.score_cache)."""

import dataclasses
import shutil

import numpy as np
import pandas as pd
import pytest

from lbo.core import sources
from lbo.scoring import grid, score_cache
from lbo.scoring.grid import classical_table, load_test, reference
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

VEHICLE, NOISE = Vehicle(), Noise.preset("paper")


@pytest.fixture
def test_file(smoke_data, tmp_path):
    """A private copy of the smoke test set: the session's folder gets no ``scores/``."""
    path = tmp_path / "set" / "test.parquet"
    path.parent.mkdir()
    shutil.copyfile(smoke_data / "test.parquet", path)
    return path


def _refuse(*args, **kwargs):
    raise AssertionError("scored again, though its rows are kept")


def test_kept_rows_are_read_back_equal_and_not_scored_again(test_file, monkeypatch):
    arr = load_test(test_file)
    ref = reference(arr, VEHICLE, NOISE)
    first = classical_table(arr, VEHICLE, NOISE, ["ekf", "oracle"], ref, keep=test_file)
    kept = sorted(p.name for p in (test_file.parent / score_cache.FOLDER).iterdir())
    assert [n.split("-")[0] for n in kept] == ["ekf", "oracle"]
    assert all(n.endswith(".parquet") for n in kept)
    monkeypatch.setattr(grid, "classical", _refuse)
    again = classical_table(arr, VEHICLE, NOISE, ["ekf", "oracle"], ref, keep=test_file)
    pd.testing.assert_frame_equal(again, first)  # exact: Parquet keeps every bit of a float
    # not kept: always scored (the refusing stand-in is reached)
    with pytest.raises(AssertionError, match="scored again"):
        classical_table(arr, VEHICLE, NOISE, ["ekf"], ref)


def test_the_tuned_oracle_is_kept_too(test_file, monkeypatch):
    arr = load_test(test_file)
    ref = reference(arr, VEHICLE, NOISE)
    first = classical_table(arr, VEHICLE, NOISE, ["oracle_tuned"], ref, keep=test_file)
    monkeypatch.setattr(grid, "tuned_oracle", _refuse)
    pd.testing.assert_frame_equal(
        classical_table(arr, VEHICLE, NOISE, ["oracle_tuned"], ref, keep=test_file), first)


def test_rows_of_other_conditions_are_scored_afresh(test_file):
    arr = load_test(test_file)
    ref = reference(arr, VEHICLE, NOISE)
    paper = classical_table(arr, VEHICLE, NOISE, ["ekf"], ref, keep=test_file)
    other = dataclasses.replace(NOISE, process_sigma=tuple(2 * np.asarray(NOISE.process_sigma)))
    changed = classical_table(arr, VEHICLE, other, ["ekf"], ref, keep=test_file)
    assert not np.allclose(changed["nrmse"], paper["nrmse"])
    assert len(list((test_file.parent / score_cache.FOLDER).iterdir())) == 2
    # and the first conditions' rows are still there, unchanged
    pd.testing.assert_frame_equal(
        classical_table(arr, VEHICLE, NOISE, ["ekf"], ref, keep=test_file), paper)


def test_the_key_follows_every_input(test_file, tmp_path, monkeypatch):
    ref = np.array([0.2, 0.2, 0.004])
    conditions = (VEHICLE, NOISE, None, 0)
    base = score_cache.key(test_file, "ekf", conditions, ref)
    assert score_cache.key(test_file, "ekf", conditions, ref) == base
    assert score_cache.key(test_file, "oracle", conditions, ref) != base
    assert score_cache.key(test_file, "ekf", (VEHICLE, NOISE, None, 1), ref) != base
    assert score_cache.key(test_file, "ekf", conditions, ref * 1.001) != base
    other = tmp_path / "other.parquet"
    other.write_bytes(test_file.read_bytes() + b"\0")
    assert score_cache.key(other, "ekf", conditions, ref) != base
    # a change to the filters' source: another digest, so another key
    monkeypatch.setattr(score_cache, "source_digest", lambda: "changed")
    assert score_cache.key(test_file, "ekf", conditions, ref) != base


def test_the_source_digest_follows_the_filters_source(tmp_path):
    src = sources.PACKAGE
    assert score_cache.source_digest() == sources.tree_digest(src, score_cache._SOURCES)
    for package in score_cache._SOURCES:
        shutil.copytree(src / package, tmp_path / package,
                        ignore=shutil.ignore_patterns("__pycache__"))
    copy = sources.tree_digest(tmp_path, score_cache._SOURCES)
    assert copy == score_cache.source_digest()
    kalman = tmp_path / "filters" / "kalman.py"
    kalman.write_text(kalman.read_text() + "\n# a change\n")
    changed = sources.tree_digest(tmp_path, score_cache._SOURCES)
    assert changed != copy
    (tmp_path / "sim" / "new.py").write_text("")  # a new module counts too
    assert sources.tree_digest(tmp_path, score_cache._SOURCES) not in (copy, changed)


def test_an_unreadable_kept_file_is_scored_afresh_and_replaced(test_file):
    arr = load_test(test_file)
    ref = reference(arr, VEHICLE, NOISE)
    first = classical_table(arr, VEHICLE, NOISE, ["ekf"], ref, keep=test_file)
    (path,) = (test_file.parent / score_cache.FOLDER).iterdir()
    path.write_bytes(b"not parquet")
    pd.testing.assert_frame_equal(
        classical_table(arr, VEHICLE, NOISE, ["ekf"], ref, keep=test_file), first)
    pd.testing.assert_frame_equal(pd.read_parquet(path), first)


def test_a_data_set_that_takes_no_scores_folder_is_scored_without_keeping(test_file):
    arr = load_test(test_file)
    ref = reference(arr, VEHICLE, NOISE)
    blocker = test_file.parent / score_cache.FOLDER
    blocker.write_text("a file where the folder would go")  # as a read-only folder refuses it
    table = classical_table(arr, VEHICLE, NOISE, ["ekf"], ref, keep=test_file)
    assert set(table["observer"]) == {"ekf"}
    assert blocker.read_text() == "a file where the folder would go"
    assert sorted(p.name for p in test_file.parent.iterdir()) == [score_cache.FOLDER,
                                                                   "test.parquet"]
