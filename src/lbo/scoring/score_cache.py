"""The classical observers' scores on a test set, kept beside it.

Every training ends by scoring its observer beside the classical ones on the same test grid,
and the classical ones give the same rows every time: on a car that slips the five of them
(the tuned oracle runs the EKF 20 times) take about 45 s of the final evaluation. Their rows
are kept in the data set's folder, under ``scores/``, one Parquet file per observer, named by
a digest of everything the rows depend on:

- the test set's bytes,
- the vehicle, the noise preset and the truth the set was drawn from,
- the reference errors E_ref,
- the source of the lbo packages that compute them (:mod:`lbo.filters`, :mod:`lbo.sim`,
  :mod:`lbo.scoring`, :mod:`lbo.core`), so that a changed filter is scored afresh.

A plug-in's observer is never kept: its code lives outside lbo, and no digest here would see
it change. Files are written whole or not at all (:func:`lbo.core.atomic.atomic_path`), and a
file that cannot be read is scored afresh and replaced.
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from lbo.core import sources
from lbo.core.atomic import atomic_path
from lbo.core.errors import LboError
from lbo.scoring.metrics import SCORE_COLUMNS

FOLDER = "scores"
"""The subfolder of a data set that holds the kept rows."""

_SOURCES = ("filters", "sim", "scoring", "core")


def source_digest() -> str:
    """sha256 of the source of the lbo packages that score the classical observers."""
    return sources.source_digest(_SOURCES)


def file_digest(path: Path) -> str:
    """sha256 of a file's bytes, read in 1 MiB blocks; read once per process while its size
    and modification time stay (a training's five peers name the same test set)."""
    stat = path.stat()
    return _digest_of(path.resolve(), stat.st_size, stat.st_mtime_ns)


@functools.lru_cache(maxsize=8)
def _digest_of(path: Path, size: int, mtime_ns: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def key(test_file: Path, observer: str, conditions: tuple[object, ...],
        ref: np.ndarray) -> str:
    """The digest (16 hex digits) that names one observer's rows on ``test_file``:
    ``conditions`` are the vehicle, noise, truth and seed (their reprs enter the digest),
    ``ref`` (3,) is E_ref."""
    h = hashlib.sha256()
    for part in (file_digest(test_file), observer, *map(repr, conditions), source_digest()):
        h.update(str(part).encode())
        h.update(b"\0")
    h.update(np.ascontiguousarray(ref, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def cached(test_file: Path, observer: str, conditions: tuple[object, ...], ref: np.ndarray,
           compute: Callable[[], pd.DataFrame]) -> pd.DataFrame:
    """``observer``'s score rows (:data:`~lbo.scoring.metrics.SCORE_COLUMNS`) on
    ``test_file``: read from the data set's ``scores/`` folder when kept there under the same
    :func:`key`, else computed by ``compute()`` and kept there (where the folder takes it: a
    read-only data set is scored every time)."""
    name = f"{observer}-{key(test_file, observer, conditions, ref)}.parquet"
    path = test_file.parent / FOLDER / name
    if path.is_file():
        try:
            table = pd.read_parquet(path)
            if list(table.columns) == list(SCORE_COLUMNS):
                return table
        except (OSError, ValueError):  # unreadable: scored afresh below, and replaced
            pass
    table = compute()
    try:
        path.parent.mkdir(exist_ok=True)
        with atomic_path(path) as tmp:
            table.to_parquet(tmp, index=False)
    except (OSError, LboError):
        pass
    return table
