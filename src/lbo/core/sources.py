"""Digests of lbo's own source, for results kept between runs: a kept result names the digest
of the code that made it, so a change to that code makes it afresh."""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

PACKAGE: Path = Path(__file__).resolve().parents[1]
"""The ``lbo`` package folder."""


def tree_digest(root: Path, packages: tuple[str, ...]) -> str:
    """sha256 of the ``.py`` files under ``root / package`` for each package: their paths
    relative to ``root`` and their bytes, in sorted order."""
    h = hashlib.sha256()
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            h.update(path.relative_to(root).as_posix().encode() + b"\0")
            h.update(path.read_bytes())
    return h.hexdigest()


@functools.cache
def source_digest(packages: tuple[str, ...]) -> str:
    """:func:`tree_digest` of lbo's own ``packages`` (e.g. ``("filters", "sim")``), once per
    process."""
    return tree_digest(PACKAGE, packages)
