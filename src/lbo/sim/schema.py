"""The one data schema shared by simulated sets and users' own logs, and its Parquet I/O.

One row per time step: ``traj, k, t, x, y, psi, V, delta, x_m, y_m, psi_m`` (m, rad, m/s),
plus ``alpha`` and ``scored`` for the validation and test sets.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from lbo.core.atomic import atomic_path
from lbo.core.errors import LboError, located
from lbo.sim.columns import INPUT, LATERAL, MEAS, SCORED_SET, SET, STATE

_INT = ("traj", "k")
MANIFEST = "manifest.json"
"""The file a data-set folder (generated, or a user's logs) records itself in."""
FIX_RULE = ("a row holds x_m and y_m (a position fix), with or without psi_m, or none of "
            "them (a step without a fix)")
"""What a row of a log may hold, as the checks say it."""


def check_values(df: pd.DataFrame, columns: tuple[str, ...], source: str = "data",
                 kinds: str = "iufb") -> None:
    """Raise LboError naming the first of ``columns`` that is not numeric (dtype kind outside
    ``kinds``) or holds NaN or inf."""
    for c in columns:
        values = df[c].to_numpy()
        if values.dtype.kind not in kinds:
            raise LboError(f"{source}: column {c!r} is not numeric (dtype {df[c].dtype})")
        if values.dtype.kind == "f" and not np.isfinite(values).all():
            bad = int(np.flatnonzero(~np.isfinite(values))[0])
            raise LboError(f"{source}: column {c!r} has NaN or inf (first at row {bad})")


def check_frame(df: pd.DataFrame, required: tuple[str, ...], source: str = "data",
                missing_fixes: bool = False, missing_truth: bool = False) -> None:
    """Raise LboError naming the first missing column, or the first column with NaN/inf.

    With ``missing_fixes``, rows whose ``x_m, y_m, psi_m`` are all NaN (steps without a
    position fix) are allowed, partial ones are not (see :func:`fix_rows`). With
    ``missing_truth``, the true ``x, y, psi`` and the noise level ``alpha`` may be NaN (logs
    without the truth, :mod:`lbo.logs.sets`).
    """
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise LboError(f"{source}: missing column {missing[0]!r} (expected columns: "
                       f"{', '.join(required)})")
    if len(df) == 0:
        raise LboError(f"{source}: the file holds no rows")
    fixes = missing_fixes and all(c in required for c in MEAS)
    if fixes:
        fix_rows(df, source)
    # without the truth, a log's noise level (``alpha``) is unknown too
    blank = (MEAS if fixes else ()) + ((*STATE, "alpha") if missing_truth else ())
    check_values(df.fillna(dict.fromkeys(blank, 0.0)) if blank else df, required, source)


def check_fixes(m: np.ndarray, source: str | None = None,
                position_only: bool = False) -> np.ndarray:
    """The rows of a log's measurements m (T, 3) that hold a position fix, (T,) bool, checked.

    Each row holds x_m and y_m (a fix) with psi_m, or none of the three; with
    ``position_only`` (a log for the classical observers) a fix may also lack psi_m. A heading
    without a position, x_m without y_m (or the reverse), a fix without a heading where one is
    needed, or a log without any fix, is one :class:`LboError` naming the first such row."""
    empty = np.isnan(m)
    pos = ~empty[:, 0] & ~empty[:, 1]
    rules = [
        (empty[:, 0] & empty[:, 1] & ~empty[:, 2], "has a heading without a position "
                                                    "(psi_m without x_m, y_m)"),
        (empty[:, 0] ^ empty[:, 1], None),
    ]
    if not position_only:
        rules.append((pos & empty[:, 2], "has a position without a heading (psi_m empty)"))
    firsts = [(int(np.argmax(bad)), i) for i, (bad, _) in enumerate(rules) if bad.any()]
    if firsts:
        r, i = min(firsts)
        what = rules[i][1]
        if what is None:
            have, lack = ("x_m", "y_m") if empty[r, 1] else ("y_m", "x_m")
            what = f"has {have} without {lack}"
        allowed = FIX_RULE if position_only else (
            "here a row holds x_m, y_m and psi_m (a fix) or none of them (a step without a "
            "fix)")
        raise LboError(located(source, f"row {r} {what}; {allowed}"))
    if not pos.any():
        raise LboError(located(source, "no position fix in any row (x_m and y_m are empty "
                                   "everywhere)"))
    return pos


def fix_rows(df: pd.DataFrame, source: str = "input") -> np.ndarray:
    """(T,) bool, the rows that hold a position fix; a row with only some of ``x_m, y_m,
    psi_m`` empty, or a log without any fix, is one :class:`LboError` (the check of
    :func:`check_fixes`, which users' logs go through too)."""
    empty = df[list(MEAS)].isna().to_numpy()  # whatever the dtype: only the gaps count here
    return check_fixes(np.where(empty, np.nan, 0.0), source)


def read_set(path: str | Path, required: tuple[str, ...] = SET,
             missing_fixes: bool = False, missing_truth: bool = False) -> pd.DataFrame:
    """Read a Parquet set and check its columns (see :func:`check_frame`). Raises LboError
    for missing or unreadable files (cut short, not Parquet) or missing columns."""
    path = Path(path)
    if not path.is_file():
        raise LboError(f"data set not found: {path} (run `python -m lbo.datagen data=...` first)")
    try:
        df = pd.read_parquet(path)
    except Exception as e:  # noqa: BLE001 - pyarrow's errors are many; each means unreadable
        advice = (f"; delete {path.parent} and run the command again to rebuild the data set"
                  if is_data_set_folder(path.parent) else "")
        raise LboError(f"{path}: not a readable Parquet file (cut short, or not Parquet: "
                       f"{first_line(e)}){advice}") from None
    check_frame(df, required, source=str(path), missing_fixes=missing_fixes,
                missing_truth=missing_truth)
    return df


def write_set(df: pd.DataFrame, path: str | Path) -> Path:
    """Write a frame to Parquet atomically: a temp file in the same folder, then rename.

    A killed writer leaves at most a ``.tmp`` file, never a half-written ``path``.
    """
    with atomic_path(path) as tmp:
        pq.write_table(pa.Table.from_pandas(df, preserve_index=False), tmp, compression="zstd")
    return Path(path)


def frame(traj: np.ndarray, k: np.ndarray, dt: float, z: np.ndarray, u: np.ndarray,
          m: np.ndarray, **extra: np.ndarray) -> pd.DataFrame:
    """Build a schema frame from flat arrays. traj, k: (R,); z, m: (R, 3); u: (R, 2)."""
    cols = {"traj": traj.astype(np.int32), "k": k.astype(np.int32), "t": k * dt}
    cols.update({name: z[:, i] for i, name in enumerate(STATE)})
    cols.update({name: u[:, i] for i, name in enumerate(INPUT)})
    cols.update({name: m[:, i] for i, name in enumerate(MEAS)})
    cols.update(extra)
    return pd.DataFrame(cols)


@dataclass(frozen=True, kw_only=True)
class Trajectories:
    """A schema frame's trajectories as padded arrays (:func:`to_arrays`): G trajectories of
    up to T steps, the shorter padded by repeating their last row, so that filters can run
    over the padding harmlessly."""

    z: np.ndarray
    """(G, T, 3) the truth ``x, y, psi``."""
    u: np.ndarray
    """(G, T, 2) the inputs ``V, delta``."""
    m: np.ndarray
    """(G, T, 3) the measurements ``x_m, y_m, psi_m`` (NaN: no fix at that step)."""
    mask: np.ndarray
    """(G, T) bool: the real rows (and the scored ones, where the frame has ``scored``)."""
    lengths: np.ndarray
    """(G,) each trajectory's number of real rows."""
    traj: np.ndarray
    """(G,) each trajectory's ``traj`` id."""
    alpha: np.ndarray
    """(G,) each trajectory's noise scale (NaN where the frame has no ``alpha``)."""
    file: np.ndarray
    """(G,) each trajectory's index in its set's list of log files (-1: not a user's log)."""
    lateral: np.ndarray | None = None
    """(G, T, 2) the true ``v_y, r`` of a car that slips (:data:`LATERAL`), None where the
    frame has none (a kinematic set, or a car-that-slips set made before lbo kept them: its
    folder keeps its name, so that stored runs still find it; delete it to make it again)."""

    def take(self, pick: np.ndarray) -> Trajectories:
        """The trajectories ``pick`` (a (G,) mask or indices)."""
        picked: dict[str, Any] = {f.name: None if getattr(self, f.name) is None
                                  else getattr(self, f.name)[pick] for f in fields(self)}
        return Trajectories(**picked)


def to_arrays(df: pd.DataFrame) -> Trajectories:
    """Split a schema frame (sorted by traj, k) into padded per-trajectory arrays."""
    keys = ["traj", "alpha"] if "alpha" in df.columns else ["traj"]
    df = df.sort_values(keys + ["k"], kind="stable")
    group = df.groupby(keys, sort=False).ngroup().to_numpy()
    starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    lengths = np.diff(np.r_[starts, len(df)])
    g, t_max = len(starts), int(lengths.max())
    pos = np.arange(len(df)) - np.repeat(starts, lengths)
    # index of the source row for every padded cell: real rows, then the last row repeated
    idx = np.minimum(np.arange(t_max)[None, :], (lengths - 1)[:, None]) + starts[:, None]
    real = np.zeros((g, t_max), bool)
    real[group, pos] = True
    return Trajectories(
        z=df[list(STATE)].to_numpy()[idx], u=df[list(INPUT)].to_numpy()[idx],
        m=df[list(MEAS)].to_numpy()[idx], lengths=lengths, traj=df["traj"].to_numpy()[starts],
        mask=real & (df["scored"].to_numpy()[idx] if "scored" in df.columns else True),
        alpha=df["alpha"].to_numpy(float)[starts] if "alpha" in df.columns else np.full(g, np.nan),
        file=np.full(g, -1),
        lateral=(df[list(LATERAL)].to_numpy()[idx] if set(LATERAL) <= set(df.columns) else None))


_CACHE_NAME = re.compile(r".+-[0-9a-f]{12}")


def is_data_set_folder(folder: Path) -> bool:
    """Whether ``folder`` is a data-set cache, whose files lbo reuses as they are: it holds
    the ``manifest.json`` of a generated data set or of a user's logs (``data=logs``), or it is
    named ``<name>-<12 hex digits>`` and holds a set (a generation stopped before its
    manifest)."""
    manifest = folder / MANIFEST
    try:
        record = json.loads(manifest.read_text()) if manifest.is_file() else None
    except (OSError, ValueError):
        record = None
    if isinstance(record, dict) and "digest" in record and "version" in record:
        return True
    return bool(_CACHE_NAME.fullmatch(folder.name)) and (
        manifest.is_file() or any((folder / f"{n}.parquet").is_file()
                                  for n in ("train", "val", "test")))


def check_outside_data_sets(**paths: Path | str | None) -> None:
    """Refuse an output path (given by its field name, ``output=path``) that lies in a
    data-set cache (:func:`is_data_set_folder`): a file written there would replace a set that
    training and evaluation then reuse. None is skipped."""
    for field, path in paths.items():
        if path is None:
            continue
        folder = Path(path).resolve().parent
        if is_data_set_folder(folder):
            raise LboError(f"{field}: {path} is in the data-set cache {folder}, whose files lbo "
                           "reuses as they are; give a path outside that folder")


def fingerprint(path: Path) -> dict[str, int | str]:
    """``{"bytes": size, "sha256": hex digest}`` of a file, read in 1 MiB blocks: what a
    data-set cache's manifest records of each set, to tell a set cut short or replaced."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return {"bytes": path.stat().st_size, "sha256": digest.hexdigest()}


def cached_set(path: Path, recorded: dict | None, name: str
               ) -> tuple[pd.DataFrame | None, str | None]:
    """The cached set ``name`` (``train``, ``val``, ``test``) at ``path`` and None, or None and
    what is wrong with it: a size or sha256 other than the manifest records (``recorded``, a
    :func:`fingerprint`; a cache written before lbo recorded them has none), a file that does
    not read as Parquet, or a set's column missing (an observer's estimates written over it)."""
    if recorded:
        size = path.stat().st_size
        if size != recorded.get("bytes"):
            return None, (f"{size} bytes where this data set's {MANIFEST} records "
                          f"{recorded.get('bytes')} (cut short, or replaced by another file)")
        if fingerprint(path)["sha256"] != recorded.get("sha256"):
            return None, (f"its sha256 differs from the one this data set's {MANIFEST} "
                          "records (the file was replaced or damaged)")
    try:
        df = pd.read_parquet(path)
    except Exception as e:  # noqa: BLE001 - pyarrow's errors are many; each means unreadable
        return None, f"not a readable Parquet file ({first_line(e)})"
    required = SET if name == "train" else SCORED_SET
    missing = [c for c in required if c not in df.columns]
    if missing:
        return None, (f"not a {name} set: it lacks column {missing[0]!r} (another program's "
                      "file written over it?)")
    return df, None


def first_line(e: BaseException) -> str:
    """The first line of an exception's message (pyarrow's run to pages), or its type."""
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__
