"""Atomic file writes: a killed writer never leaves a half-written file under the real name.

A write goes to a temp file beside its target, ``.<target name>.<random>.lbo-tmp``, which is
renamed over the target once complete. The name says whose temp it is (lbo's) and for which
file, so that :func:`remove_stale_temps` clears only the temps of the files a command is about
to write, never another program's hidden files in a folder it shares. Files are created with
the mode the user's umask gives (``0o666 & ~umask``), as ``open()`` would.
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from lbo.core.errors import LboError

TEMP_SUFFIX = ".lbo-tmp"
"""The suffix of lbo's temp files (``.<target name>.<random>.lbo-tmp``)."""

# the random part mkstemp puts in a name (and the shorter ones older tests and versions used)
_RANDOM = r"[A-Za-z0-9_]+"
_umask_guard = threading.Lock()


def umask() -> int:
    """The process's umask, read without changing it where Linux tells it
    (``/proc/self/status``); elsewhere set and restored at once, under a lock (a file another
    thread creates in between would get the mode of umask 0)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _umask_guard:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def file_mode() -> int:
    """The mode a new file gets from the user's umask: 0o644 under the usual 022, 0o600 under
    077 (a user who keeps drive traces private)."""
    return 0o666 & ~umask()


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
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.",
                                   suffix=TEMP_SUFFIX)
        os.close(fd)
    except OSError as e:
        raise LboError(f"cannot write {path}: {e.strerror or e}") from None
    try:
        yield Path(tmp)
        os.chmod(tmp, file_mode())  # mkstemp makes 0600; the user's umask decides
        os.replace(tmp, path)
    except OSError as e:
        raise LboError(f"cannot write {path}: {e.strerror or e}") from None
    finally:
        Path(tmp).unlink(missing_ok=True)


def remove_stale_temps(folder: str | Path, names: Iterable[str] | None = None) -> list[Path]:
    """Delete the temp files that killed writers of :func:`atomic_path` left in ``folder``.

    ``names``: the file names about to be written there; only their temps go
    (``.<name>.<random>.lbo-tmp``, and the ``.<name>.<random>.tmp`` of older lbo versions). None:
    every ``.lbo-tmp`` file, for a folder only lbo writes to (a data-set cache). Another
    program's hidden files are never touched. Call it only while no other lbo process writes
    there (under the folder's lock)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    if names is None:
        pattern = re.compile(rf"\..+\.{_RANDOM}{re.escape(TEMP_SUFFIX)}")
    else:
        targets = "|".join(re.escape(n) for n in names)
        if not targets:
            return []
        pattern = re.compile(rf"\.(?:{targets})\.{_RANDOM}(?:{re.escape(TEMP_SUFFIX)}|\.tmp)")
    stale = sorted(p for p in folder.iterdir() if pattern.fullmatch(p.name) and p.is_file())
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (:func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def data_lock(folder: Path) -> Any:
    """The lock of a data-set folder: jobs of a parallel sweep share one data set, the first
    generates it and the others wait; whoever writes into the folder holds it."""
    from filelock import FileLock

    folder.parent.mkdir(parents=True, exist_ok=True)
    return FileLock(folder.parent / f".{folder.name}.lock", timeout=-1)
