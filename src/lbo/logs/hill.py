"""The hill drive as a data set of logs, split by drive (``data=hill``).

The onavdata hill drive (:mod:`lbo.logs.hguide`) holds three drives, the car standing still
30 s or more between them (:func:`lbo.logs.hguide.drives`: 254 s, 132 s and 284 s). ``data=hill``
names them by number in each set (``data.train=[1] data.val=[2] data.test=[3]`` by default), so
that every command that reads ``data=logs`` (``lbo.train``, ``lbo.evaluate``, ``lbo.tune``)
reads the real car too, split by drive rather than by time: what is scored is a drive that
training never saw.

:func:`drive_files` writes the drives once as lbo logs (``<root>/hill-drives-<digest>/
drive<k>.parquet``, each with the receiver's channels and the INS/GNSS truth at the antenna,
as ``lbo.observe`` reads them) and returns their paths; the digest is the vehicle's settings
and :data:`VERSION`, so another ``dt`` or a new alignment writes a new folder.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path

from lbo.core.atomic import data_lock
from lbo.core.errors import LboError
from lbo.logs.io import write_table
from lbo.sim.vehicle import Vehicle

__all__ = ["DRIVES", "VERSION", "check_numbers", "check_split", "drive_files"]

DRIVES = 3
"""The hill drive's drives (cut in its standstills of 30 s or more)."""
VERSION = 1
"""Raised when the drives' logs change (the importer, the alignment, the cut)."""


def check_numbers(value: object, field: str) -> list[int]:
    """The drive numbers of one set (a list of integers from 1 to :data:`DRIVES`, each once);
    one line naming ``field`` otherwise."""
    items = [value] if isinstance(value, int) else value
    numbers = (list(items) if isinstance(items, Sequence) and not isinstance(items, str)
               else [None])
    if not numbers or len(set(numbers)) < len(numbers) or not all(
            isinstance(k, int) and not isinstance(k, bool) and 1 <= k <= DRIVES
            for k in numbers):
        raise LboError(f"{field}: expected a list of the hill drive's drive numbers, each once, "
                       f"from 1 to {DRIVES} (e.g. [1, 2]), got {value!r}")
    return [int(k) for k in numbers if k is not None]


def check_split(sets: Mapping[str, Sequence[int]]) -> None:
    """One line naming the set when a drive is in two sets (the split is by drive)."""
    seen: dict[int, str] = {}
    for part, numbers in sets.items():
        for k in numbers:
            if k in seen:
                raise LboError(f"data.{part}: drive {k} is also in data.{seen[k]}; the sets "
                               "are split by drive, so a drive belongs to one of them")
            seen[k] = part


def drive_files(root: str | Path, vehicle: Vehicle,
                sets: Mapping[str, Sequence[int]]) -> dict[str, list[Path]]:
    """The log files of the drives each set names (``{"train": [1], ...}``), written under
    ``root`` the first time (a parallel sweep's jobs wait for the first). Raises LboError
    when onavdata is missing (``pip install 'lbo[real]'``)."""
    settings = {"version": VERSION, "vehicle": vehicle.__dict__}
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:12]
    folder = Path(root) / f"hill-drives-{digest}"
    paths = [folder / f"drive{k}.parquet" for k in range(1, DRIVES + 1)]
    with data_lock(folder):
        if not all(p.is_file() for p in paths):
            from lbo.logs import hguide

            df = hguide.read()
            log = hguide.to_log(df, vehicle, hguide.fit_alignment(df))
            drives = hguide.drives(log)
            if len(drives) != DRIVES:  # the cut's rule changed without VERSION
                raise LboError(f"the hill drive cut into {len(drives)} drives, expected "
                               f"{DRIVES}")
            for drive, path in zip(drives, paths):
                write_table(drive, path)  # each atomic: a killed run leaves whole files
    return {part: [paths[k - 1] for k in numbers] for part, numbers in sets.items()}
