"""Atomic file writes: a killed writer never leaves a half-written file under the real name."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from lbo.core.errors import LboError


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temp path beside ``path``; on success rename it over ``path``, else delete it.

    A folder at ``path``, a folder that cannot be written (read-only, full disk) or a failed
    write are one :class:`LboError` naming ``path``; nothing is left behind.
    """
    path = Path(path)
    if path.is_dir():
        raise LboError(f"{path} is a folder; give a file path to write to")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.close(fd)
    except OSError as e:
        raise LboError(f"cannot write {path}: {e.strerror or e}") from None
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; these are ordinary shared outputs
        os.replace(tmp, path)
    except OSError as e:
        raise LboError(f"cannot write {path}: {e.strerror or e}") from None
    finally:
        Path(tmp).unlink(missing_ok=True)


def remove_stale_temps(folder: str | Path) -> list[Path]:
    """Delete the temp files that killed writers of :func:`atomic_path` left in ``folder``.

    Call it only while no other process writes there (under the folder's lock)."""
    folder = Path(folder)
    stale = sorted(folder.glob(".*.tmp")) if folder.is_dir() else []
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


def write_text(path: str | Path, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def data_lock(folder: Path) -> Any:
    """The lock of a data-set folder: jobs of a parallel sweep share one data set, the first
    generates it and the others wait; whoever writes into the folder holds it."""
    from filelock import FileLock

    folder.parent.mkdir(parents=True, exist_ok=True)
    return FileLock(folder.parent / f".{folder.name}.lock", timeout=-1)
