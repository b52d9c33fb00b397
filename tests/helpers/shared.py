"""Fixtures made once per test session, whichever xdist worker asks first.

``make test`` runs two pytest-xdist workers, each with its own session: a session fixture
(the smoke data sets, a trained smoke observer) would be made by each of them, and a module's
by every worker that runs a test of that module. :func:`once` makes it once for the whole run,
under a file lock in the folder the workers share (the parent of each worker's base temp
folder; a run without xdist uses its own), and hands the others what it returned. Only for
what the tests read and never change: a test that changes a file it was given changes it for
every worker.
"""

from __future__ import annotations

import pickle
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from filelock import FileLock


def shared_root(tmp_path_factory: Any, worker_id: str) -> Path:
    """The folder every worker of this run shares (``worker_id``: xdist's, ``master``
    without it)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if worker_id != "master" else base


def once(tmp_path_factory: Any, worker_id: str, name: str,
         make: Callable[[Path], Any]) -> Any:
    """``make(folder)``'s value, made by the first worker to ask in a folder of its own
    (``<shared root>/<name>``) and read back by the others; the value must pickle. A ``make``
    that raises leaves nothing behind, so the next to ask makes it again (and fails the same
    way, in its own test)."""
    root = shared_root(tmp_path_factory, worker_id)
    folder, done = root / name, root / f"{name}.pickle"
    with FileLock(str(root / f"{name}.lock")):
        if done.is_file():
            return pickle.loads(done.read_bytes())
        shutil.rmtree(folder, ignore_errors=True)  # what a failed make left
        folder.mkdir()
        value = make(folder)
        tmp = done.with_suffix(".tmp")
        tmp.write_bytes(pickle.dumps(value))
        tmp.replace(done)
        return value
