"""One run per folder, and the record Hydra keeps of it without credentials.

Two commands started in the same second, or given the same ``hydra.run.dir`` or
``output_dir``, would otherwise write into one folder: checkpoints ``best.ckpt`` and
``best-v1.ckpt`` of two runs, and one run's ``.hydra`` files over the other's. A run holds an
exclusive lock on its folder (``.lbo-run.lock``) from before its first file until it ends; a
second run there stops with one line and writes nothing. The kernel drops the lock of a
killed run, so a rerun after a crash is never locked out.

Hydra's own ``.hydra/{config,hydra,overrides}.yaml`` would hold every command-line override
as typed, passwords included (``hydra.output_subdir`` is null in ``conf/hydra/default.yaml``):
:func:`save_hydra_files` writes the same three files with every password as ``***``.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from lbo.core.errors import LboError
from lbo.core.redact import scrub, scrub_file

LOCK_NAME = ".lbo-run.lock"

_held: dict[Path, list] = {}  # folder -> [FileLock, depth]: re-entrant within one process
_guard = threading.Lock()


@contextlib.contextmanager
def claim(folder: str | os.PathLike, what: str = "output folder") -> Iterator[Path]:
    """Hold the exclusive lock of run folder ``folder`` (created) for the ``with`` block.

    Re-entrant in one process (the entry shell and ``train`` may both claim one folder).
    Raises LboError, with nothing written in the folder but the lock file, when another
    process holds it.
    """
    from filelock import FileLock, Timeout

    path = Path(folder).resolve()
    with _guard:
        entry = _held.get(path)
        if entry is None:
            try:
                path.mkdir(parents=True, exist_ok=True)
                lock = FileLock(path / LOCK_NAME, timeout=0)
                lock.acquire()
            except Timeout:
                raise LboError(f"{what} {path} is in use by another run (it holds "
                               f"{LOCK_NAME}); give each run its own folder "
                               "(hydra.run.dir=... or output_dir=...)") from None
            except OSError as e:
                raise LboError(f"{what} {path}: cannot write there ({e.strerror or e})") \
                    from None
            entry = _held[path] = [lock, 0]
        entry[1] += 1
    try:
        yield path
    finally:
        with _guard:
            entry[1] -= 1
            if entry[1] == 0:
                entry[0].release()
                del _held[path]


def save_hydra_files(task_cfg: DictConfig) -> Path | None:
    """Write ``<run dir>/.hydra/{config,hydra,overrides}.yaml`` for the running Hydra job, with
    every password as ``***``; also mask those in a sweep's ``multirun.yaml``, which Hydra's
    sweeper wrote. Returns the folder, or None outside a Hydra job."""
    from hydra.core.hydra_config import HydraConfig

    from lbo.core.atomic import write_text

    if not HydraConfig.initialized():
        return None
    hc = HydraConfig.get()
    folder = Path(hc.runtime.output_dir) / ".hydra"
    hydra_node = OmegaConf.create({"hydra": OmegaConf.to_container(hc, resolve=False)})
    for name, node in (("config.yaml", task_cfg), ("hydra.yaml", hydra_node),
                       ("overrides.yaml", OmegaConf.create(list(hc.overrides.task)))):
        write_text(folder / name, scrub(OmegaConf.to_yaml(node)))
    if str(hc.mode) == "RunMode.MULTIRUN":
        scrub_file(Path(hc.sweep.dir) / "multirun.yaml")
    return folder
