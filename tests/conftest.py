from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from lbo.paths import CONF_DIR


def compose_cfg(name: str, overrides: list[str] | None = None):
    """Compose a config from conf/ the way the entry points do, without running Hydra."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose(config_name=name, overrides=overrides or [])


@pytest.fixture(scope="session")
def smoke_data(tmp_path_factory) -> Path:
    """The smoke data sets, generated once per test session."""
    from lbo.datagen.__main__ import run

    root = tmp_path_factory.mktemp("data")
    return Path(run(compose_cfg("datagen", ["data=smoke", f"data.root={root}"])))


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


def train_cfg(tmp_path, smoke_data, *overrides):
    """The training config at smoke scale, writing under ``tmp_path / 'out'``."""
    return compose_cfg("train", ["experiment=smoke", f"data.root={smoke_data.parent}",
                                 f"output_dir={tmp_path / 'out'}", *overrides])


ROBUST_SMOKE = ("experiment=robust", "data=smoke", "trainer.max_epochs=1")
"""The robust experiment cut to one short epoch on the smoke sets (add the batches, the
window and the batch size)."""


def train_in_own_store(tmp: Path, smoke_data: Path, *overrides: str):
    """Train at smoke size into ``tmp / 'out'``, logged to an MLflow store of its own.

    Returns ``(cfg, metrics, tracking_uri)``; ``overrides`` choose the experiment and sizes.
    """
    from lbo.train import train

    uri = f"sqlite:///{tmp / 'mlflow.db'}"
    cfg = compose_cfg("train", [*overrides, f"data.root={smoke_data.parent}",
                                f"output_dir={tmp / 'out'}"])
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", uri)
        return cfg, train(cfg), uri


@pytest.fixture(scope="module")
def manoeuvre(smoke_data):
    """One simulated manoeuvre of the smoke test set at alpha=1, as a user's log would be."""
    import pandas as pd

    test = pd.read_parquet(smoke_data / "test.parquet")
    return test[(test["traj"] == 0) & (test["alpha"] == 1.0)].sort_values("k")


def kill_when_written(proc, path: Path, times: int = 1, delay: float = 0.0):
    """A started thread that SIGKILLs the process group of ``proc`` once ``path`` has been
    written ``times`` times (e.g. a run's first checkpoint; ``last.ckpt`` once per epoch), and
    ``delay`` seconds more; join it after ``proc`` ends."""
    import os
    import signal
    import threading
    import time

    def watch() -> None:
        seen, stamp = 0, None
        while proc.poll() is None:
            if path.exists() and path.stat().st_mtime_ns != stamp:
                stamp, seen = path.stat().st_mtime_ns, seen + 1
                if seen >= times:
                    time.sleep(delay)
                    os.killpg(proc.pid, signal.SIGKILL)
                    return
            time.sleep(0.005)

    thread = threading.Thread(target=watch)
    thread.start()
    return thread
