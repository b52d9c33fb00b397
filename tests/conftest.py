"""pytest fixtures and hooks; the plain helpers the tests import are in ``tests/helpers``."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from helpers import compose_cfg, hydra_cache
from helpers.shared import once, shared_root


def pytest_configure(config) -> None:
    """Split the cores between xdist's workers (``make test`` runs two): each worker, and every
    command it starts (through OMP_NUM_THREADS), takes its share of intra-op threads. Two torch
    processes that each take every core spin against each other, many times slower a step."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if not workers:
        return
    share = max(1, (os.cpu_count() or 1) // int(workers))
    os.environ.setdefault("OMP_NUM_THREADS", str(share))
    import torch

    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


@pytest.fixture(scope="session", autouse=True)
def conf_read_once():
    """Hydra reads each version of a config file once for the session, not once per compose,
    and builds each shape of command line once (:mod:`helpers.hydra_cache`): conf/ is composed
    about 1,600 times a run, unchanged, most of them the same choices with other values
    (``benchmarks/compose_cache.py``: 132-178 ms a compose with Hydra's own reads, 97-110 ms
    with the files kept, 17-21 ms with the builds kept too). A file a test writes or changes is read
    afresh. Hydra's own methods are back at the session's end."""
    hydra_cache.install()
    yield
    hydra_cache.uninstall()


@pytest.fixture(scope="session", autouse=True)
def own_cache_dir(tmp_path_factory, worker_id):
    """lbo's cache folder (kept ONNX exports, the empty MLflow store) in the run's temp folder
    that every worker shares, for this process and the commands it starts: the tests never
    write into the user's ~/.cache, and an observer both workers run (``robust_smoke``) is
    exported once, as two sessions of a user share it (lbo writes each kept file atomically)."""
    folder = shared_root(tmp_path_factory, worker_id) / "lbo-cache"
    folder.mkdir(exist_ok=True)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("LBO_CACHE_DIR", str(folder))
        yield


@pytest.fixture(scope="session")
def smoke_data(tmp_path_factory, worker_id) -> Path:
    """The smoke data sets, generated once per test run and shared by its workers (their
    data root too: a set a training draws on demand is drawn once, under lbo's data lock)."""
    from lbo.datagen import generate

    return once(tmp_path_factory, worker_id, "data", lambda root: Path(
        generate(compose_cfg("datagen", ["data=smoke", f"data.root={root}"]))))


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch thread, in the test process and in the CLIs it starts: on a busy 2-core
    machine, intra-op threads make small batches 10-100x slower (measured), and these tests
    check numbers, not speed."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("OMP_NUM_THREADS", "1")
        yield
    torch.set_num_threads(threads)


@pytest.fixture
def tracking(tmp_path, monkeypatch):
    """A fresh MLflow SQLite store for one test, through MLFLOW_TRACKING_URI."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    return uri


@pytest.fixture(scope="module")
def manoeuvre(smoke_data):
    """One simulated manoeuvre of the smoke test set at alpha=1, as a user's log would be."""
    import pandas as pd

    test = pd.read_parquet(smoke_data / "test.parquet")
    return test[(test["traj"] == 0) & (test["alpha"] == 1.0)].sort_values("k")


@pytest.fixture(scope="session")
def robust_smoke(tmp_path_factory, worker_id, smoke_data):
    """The robust observer trained once at smoke scale for the whole run, in an MLflow store
    of its own (``cfg``, training's ``out``, ``uri``, ``dir``, ``run_id``): the tests read
    it, and none changes it."""
    from helpers import ROBUST_SMOKE, train_in_own_store

    def make(tmp: Path) -> dict:
        cfg, out, uri = train_in_own_store(tmp, smoke_data, *ROBUST_SMOKE,
                                           "trainer.limit_train_batches=5", "window=40",
                                           "batch_size=64")
        return {"cfg": cfg, "out": out, "uri": uri, "dir": tmp / "out",
                "run_id": out["run_id"]}

    return once(tmp_path_factory, worker_id, "robust", make)


@pytest.fixture(scope="session")
def smoke_cnn(tmp_path_factory, worker_id, smoke_data):
    """One smoke CNN (N=20, one epoch of 5 batches on the smoke friction circle at alpha = 1),
    trained once for the whole run in an MLflow store of its own (``checkpoint``, ``run_id``,
    ``uri``), for the tests that only read a trained observer."""
    from helpers import train_in_own_store

    def make(tmp: Path) -> dict:
        _, out, uri = train_in_own_store(tmp, smoke_data, "experiment=smoke",
                                         "trainer.max_epochs=1", "trainer.limit_train_batches=5")
        return {"checkpoint": out["checkpoint"], "run_id": out["run_id"], "uri": uri}

    return once(tmp_path_factory, worker_id, "smoke_cnn", make)


@pytest.fixture(scope="session")
def paper_sweep(tmp_path_factory, worker_id, smoke_data):
    """The paper's sweep at smoke size, ``python -m lbo.train -m model=cnn,lstm
    window=20,40,60,80 experiment=smoke`` with :data:`helpers.SWEEP_BUDGET`, run once for the
    whole run in a process of its own (one torch thread) into an MLflow store of its own:
    ``uri``, ``sweep`` (its folder), ``returncode``, ``stdout``, ``stderr``. test_train reads
    the sweep; test_scaling's joblib sweep is compared with its runs."""
    import subprocess
    import sys

    from helpers import SWEEP_BUDGET

    def make(tmp: Path) -> dict:
        uri = f"sqlite:///{tmp / 'mlflow.db'}"
        res = subprocess.run(
            [sys.executable, "-m", "lbo.train", "-m", "model=cnn,lstm", "window=20,40,60,80",
             "experiment=smoke", *SWEEP_BUDGET, f"data.root={smoke_data.parent}",
             f"hydra.sweep.dir={tmp / 'sweep'}"], capture_output=True, text=True,
            env={**os.environ, "MLFLOW_TRACKING_URI": uri, "OMP_NUM_THREADS": "1"})
        return {"uri": uri, "sweep": tmp / "sweep", "returncode": res.returncode,
                "stdout": res.stdout, "stderr": res.stderr}

    return once(tmp_path_factory, worker_id, "paper_sweep", make)


SLOW_S = 1.0
"""A test that took this many seconds or more in the run ``tests/durations.json`` was written
from is marked ``slow`` (``make test-fast`` skips it), as are those marked by hand."""


@pytest.hookimpl(tryfirst=True)  # before -m deselects by marker
def pytest_collection_modifyitems(config, items) -> None:
    """The longest test files first (``tests/durations.json``, which
    ``benchmarks/test_durations.py`` writes from a run's report; a file not listed there first
    of all), each file's tests in their own order: xdist hands files to whichever worker is
    free in this order, so no long file starts when the other worker is nearly done. Each test
    that took :data:`SLOW_S` or more in that run is marked ``slow``."""
    listed = Path(__file__).with_name("durations.json")
    durations = json.loads(listed.read_text()) if listed.is_file() else {}
    files, tests = durations.get("files", {}), durations.get("tests", {})
    root = Path(str(config.rootpath))

    def cost(item) -> float:
        return files.get(Path(str(item.path)).relative_to(root).as_posix(), float("inf"))

    for item in items:
        if tests.get(item.nodeid, 0.0) >= SLOW_S:
            item.add_marker(pytest.mark.slow)
    items.sort(key=cost, reverse=True)  # stable: a file's tests keep their order
