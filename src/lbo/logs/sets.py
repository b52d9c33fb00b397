"""Training, validation and test sets from a user's own vehicle logs (``data=logs``).

Each set is a list of paths, folders or globs of CSV/Parquet logs with the columns that
``python -m lbo.observe`` reads (``t, x_m, y_m, psi_m, V, delta``) plus the reference
system's true ``x, y, psi``. The training and validation logs may go without the truth (a
fleet's logs have none): their sets hold NaN there, and only ``loss=next_fix`` trains on them;
the test logs are scored against it, so they need it. Every file is checked with the same
one-line errors as ``lbo.observe`` (:mod:`lbo.logs.checks`), then cut into segments at every
gap in time and every jump in dt, so that no window crosses a gap or a file boundary (each
segment is a trajectory of its own, its step ``k`` restarting at 0), and put onto the
vehicle's dt with ``resample=true``. The split is by file: a file belongs to one set only.

The sets are written in the simulated sets' schema to ``<root>/logs-<digest>/`` (``digest``:
the settings and the bytes of every file), so that training, tuning and evaluation read them
as they read a generated data set. A validation or test row is scored from step ``run_in`` of
its segment on, the same rows for every observer; its ``alpha`` is the noise level the
reference measures in that file (its RMS measurement error over the noise preset's sigma),
which no observer is told.
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from lbo.core.angles import wrap_angle
from lbo.core.atomic import data_lock, remove_stale_temps, write_text
from lbo.core.checks import integer, require
from lbo.core.errors import LboError
from lbo.logs.formats import LogFormat
from lbo.logs.units import check_max_gap, check_time_unit
from lbo.sim import schema
from lbo.sim.columns import INPUT, LOG, MEAS, STATE
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

KIND = "logs"
SETS = ("train", "val", "test")
LOGS_VERSION = 1
FORMATS = (".csv", ".parquet")


@dataclass(frozen=True, kw_only=True)
class LogSpec:
    """A checked ``data=logs`` config: the files of each set and how they are read."""

    name: str
    root: Path
    files: dict[str, list[Path]]
    resample: bool
    max_gap: float
    run_in: int
    vehicle: Vehicle
    noise: Noise
    digest: str
    log_format: LogFormat = LogFormat()

    @property
    def folder(self) -> Path:
        return self.root / f"{self.name}-{self.digest}"


def is_logs(cfg: DictConfig) -> bool:
    """Whether the config's data group is a user's logs (``data=logs``)."""
    data = cfg.get("data")
    return data is not None and data.get("kind") == KIND


def is_log_folder(folder: str | Path) -> bool:
    """Whether a data-set folder was built from logs (its manifest says so)."""
    manifest = Path(folder) / "manifest.json"
    return manifest.is_file() and json.loads(manifest.read_text()).get("kind") == KIND


def expand(patterns, field: str) -> list[Path]:
    """The files a list of paths, folders (their .csv and .parquet files) or globs names,
    sorted within each entry, each once. Raises one line naming ``field`` for an empty list, a
    pattern that matches nothing, or a file that is neither CSV nor Parquet."""
    if isinstance(patterns, str):
        patterns = [patterns]
    require(patterns is not None and len(patterns) > 0, field,
            "a list of log files, folders or globs, e.g. [runs/day1/*.csv]", patterns)
    out: list[Path] = []
    for p in patterns:
        text = os.path.expanduser(str(p))
        if Path(text).is_dir():
            found = sorted(q for q in Path(text).iterdir() if q.suffix.lower() in FORMATS)
            if not found:
                raise LboError(f"{field}: folder {text} holds no .csv or .parquet log")
        elif glob.has_magic(text):
            found = sorted(Path(q) for q in glob.glob(text, recursive=True) if Path(q).is_file())
            if not found:
                raise LboError(f"{field}: no file matches {text!r}")
        else:
            if not Path(text).is_file():
                raise LboError(f"{field}: log not found: {text}")
            found = [Path(text)]
        for q in found:
            if q.suffix.lower() not in FORMATS:
                raise LboError(f"{field}: {q} is not a .csv or .parquet log")
            if q not in out:
                out.append(q)
    return out


def _digest(settings: dict, files: dict[str, list[Path]]) -> str:
    h = hashlib.sha256(json.dumps(settings, sort_keys=True).encode())
    for part in SETS:
        for path in files[part]:
            h.update(f"{part}:{path.name}:".encode())
            with open(path, "rb") as f:
                for chunk in iter(lambda: f.read(1 << 20), b""):
                    h.update(chunk)
    return h.hexdigest()[:12]


def _listed(value):
    return OmegaConf.to_container(value) if OmegaConf.is_list(value) else value


def spec_from_cfg(cfg: DictConfig, need: tuple[str, ...] = SETS) -> LogSpec:
    """Check a ``data=logs`` config and find its files; one line naming the first bad field.

    ``need``: the sets that must be given (``lbo.evaluate`` needs only the test logs); the
    others may be empty. Nothing is read but the files' bytes (for the digest); their contents
    are checked by :func:`build`.
    """
    vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
    d = cfg.data
    require(isinstance(d.get("resample"), bool), "data.resample", "true or false",
            d.get("resample"))
    max_gap = check_max_gap(d.get("max_gap"), "data.max_gap")
    run_in = integer(d.get("run_in"), "data.run_in", 1, form="an integer >= 1 (steps of each "
                     "validation and test segment before it is scored)")
    if d.get("source") == "hill":  # data=hill: the hill drive's drives, named by number
        from lbo.logs import hill

        numbers = {part: hill.check_numbers(_listed(d.get(part)), f"data.{part}")
                   for part in SETS if part in need or d.get(part)}
        hill.check_split(numbers)
        files: dict[str, list[Path]] = {part: [] for part in SETS}
        files |= hill.drive_files(Path(d.root), vehicle, numbers)
    else:
        require(d.get("source") in (None, "files"), "data.source", "files or hill",
                d.get("source"))
        files = {part: expand(_listed(d.get(part)), f"data.{part}")
                 if part in need or d.get(part) else [] for part in SETS}
    seen: dict[Path, str] = {}
    for part in SETS:
        for path in files[part]:
            key = path.resolve()
            if key in seen:
                raise LboError(f"data.{part}: {path} is also in data.{seen[key]}; the sets are "
                               "split by file, so a log belongs to one of them")
            seen[key] = part
    try:
        fmt = LogFormat.from_cfg(d)
    except LboError as e:
        raise LboError(f"data.{e}") from None
    settings = {"version": LOGS_VERSION, "resample": d.resample, "max_gap": max_gap,
                "run_in": run_in, "vehicle": vehicle.__dict__,
                "noise": [noise.process_sigma, noise.measurement_sigma]}
    if not fmt.is_plain:  # (logs in lbo's form keep the folders they were cached in)
        settings["format"] = [dict(fmt.columns), dict(fmt.units), fmt.steering_ratio,
                              fmt.heading]
    return LogSpec(name=str(d.name), root=Path(d.root), files=files, resample=bool(d.resample),
                   max_gap=max_gap, run_in=run_in, vehicle=vehicle, noise=noise,
                   digest=_digest(settings, files), log_format=fmt)


# --------------------------------------------------------------------------- reading


def segments(path: Path, spec: LogSpec, part: str = "test") -> list[pd.DataFrame]:
    """The checked segments of one log of set ``part``: ``t``, the measurements, the inputs
    and the truth (NaN where a training or validation log has none), on the vehicle's dt, cut
    at every gap in ``t`` (with ``resample``: longer than ``max_gap``; without: any step more
    than 1% off dt). Segments shorter than two steps or without a fix are left out.

    Raises
    ------
    LboError
        The checks of ``lbo.observe`` (columns, NaN, units, ranges, steering limit), some but
        not all true-state columns, a test log without them, or a period that is not dt
        without ``resample``.
    """
    from lbo.logs.io import (
        DT_TOLERANCE,
        check_log,
        check_steering,
        read_log,
        resample,
    )

    source = f"log {path}"
    df, _ = spec.log_format.apply(read_log(path), source)
    missing = [c for c in STATE if c not in df.columns]
    if missing and all(c in df.columns for c in LOG):
        if part == "test" or len(missing) < len(STATE):
            raise LboError(
                f"{source}: missing true-state column{'s' if len(missing) > 1 else ''} "
                f"{', '.join(missing)} (data=logs scores the test logs against the reference "
                "system's x, y in m and psi in rad; the training and validation logs may go "
                "without all three, for loss=next_fix)")
    # the learned observers train on full fixes (x_m, y_m and psi_m) only
    check_log(df, source, spec.log_format.heading, position_only=False)
    check_steering(df, spec.vehicle, source)
    if missing:  # no truth: its NaN columns keep the sets' schema; loss=next_fix reads none
        df = df.assign(**dict.fromkeys(STATE, np.nan))
    dt = spec.vehicle.dt
    t = df["t"].to_numpy(dtype=float)
    check_time_unit(t, dt, source)
    steps = np.diff(t)
    if spec.resample:
        cuts = np.flatnonzero(steps > max(spec.max_gap, dt)) + 1
    else:
        if len(steps) and abs(np.median(steps) - dt) / dt > DT_TOLERANCE:
            raise LboError(f"{source}: the sampling period ({np.median(steps):.6g} s median) "
                           f"is not the vehicle's dt={dt:g} s; pass data.resample=true to "
                           f"interpolate the logs to dt={dt:g} s")
        cuts = np.flatnonzero(np.abs(steps - dt) / dt > DT_TOLERANCE) + 1
    columns = (*LOG[1:], *STATE)
    out = []
    for rows in np.split(np.arange(len(df)), cuts):
        seg = df.iloc[rows]
        if spec.resample and len(seg) > 1:
            seg = resample(seg, dt, columns, None, source)
        seg = seg[["t", *columns]].reset_index(drop=True)
        if len(seg) >= 2 and np.isfinite(seg[list(MEAS)].to_numpy(float)).all(1).any():
            out.append(seg)
    if not out:
        raise LboError(f"{source}: no stretch of at least two steps at dt={dt:g} s with a "
                       "position fix")
    left = len(df) - sum(len(s) for s in out) if not spec.resample else 0
    if left > 0:
        print(f"note: {source}: {left} of {len(df)} rows left out (a period other than "
              f"dt={dt:g} s, or a stretch without a fix); data.resample=true uses them")
    return out


def noise_level(m: np.ndarray, z: np.ndarray, sigma) -> float:
    """The alpha of a log's own noise: the RMS of its measurement errors over ``sigma`` (3,),
    the noise preset's at alpha=1, over the rows with a fix (NaN for a log without the truth).
    m, z: (R, 3)."""
    fix = np.isfinite(m).all(1) & np.isfinite(z).all(1)
    if not fix.any():
        return float("nan")
    err = m[fix] - z[fix]
    err[:, 2] = wrap_angle(err[:, 2])
    return float(np.sqrt(np.mean(np.square(err / np.asarray(sigma)))))


def make_set(part: str, spec: LogSpec) -> tuple[pd.DataFrame, list[dict]]:
    """One set's rows in the data-set schema (plus ``file``, the index of its log), and a
    line of facts per file (rows, segments, seconds, noise level)."""
    frames: list[pd.DataFrame] = []
    facts: list[dict[str, Any]] = []
    traj = 0
    for i, path in enumerate(spec.files[part]):
        segs = segments(path, spec, part)
        z = np.concatenate([s[list(STATE)].to_numpy(float) for s in segs])
        m = np.concatenate([s[list(MEAS)].to_numpy(float) for s in segs])
        level = noise_level(m, z, spec.noise.measurement_sigma)
        for seg in segs:
            n = len(seg)
            k = np.arange(n)
            extra: dict[str, np.ndarray] = {"file": np.full(n, i, np.int32)}
            if part != "train":
                extra.update(alpha=np.full(n, level), scored=k >= spec.run_in)
            f = schema.frame(np.full(n, traj), k, spec.vehicle.dt,
                             seg[list(STATE)].to_numpy(float),
                             seg[list(INPUT)].to_numpy(float),
                             seg[list(MEAS)].to_numpy(float), **extra)
            f["t"] = seg["t"].to_numpy(float)
            frames.append(f)
            traj += 1
        kept = int(sum(len(s) for s in segs))
        facts.append({"file": str(path), "rows": kept, "segments": len(segs), "alpha": level,
                      "truth": bool(np.isfinite(z).all())})
    df = pd.concat(frames, ignore_index=True)
    if part != "train" and not df["scored"].any():
        longest = max(f["rows"] for f in facts)
        raise LboError(f"data.{part}: no segment is longer than data.run_in={spec.run_in} "
                       f"steps (the longest has {longest}); give longer logs or a smaller "
                       "data.run_in")
    return df, facts


def build(spec: LogSpec, progress: bool = True) -> tuple[Path, dict[str, pd.DataFrame], bool]:
    """Check every log, then write the three sets and ``manifest.json`` under
    ``spec.folder`` (or reuse them). Every file is read and checked before anything is
    written, so a bad log leaves no folder behind. Returns the folder, the frames and whether
    they were reused."""
    folder = spec.folder
    parts = [p for p in SETS if spec.files[p]]
    paths = {p: folder / f"{p}.parquet" for p in parts}
    with data_lock(folder):
        cached = _cached(folder, paths)
        if cached is not None:
            return folder, cached, True
        sets, facts = {}, {}
        for part in parts:
            if progress:
                print(f"reading {len(spec.files[part])} {part} log(s) ...", flush=True)
            sets[part], facts[part] = make_set(part, spec)
        folder.mkdir(parents=True, exist_ok=True)
        stale = remove_stale_temps(folder)
        if stale:
            print(f"removed {len(stale)} temp file(s) a killed run left in {folder}")
        for part in parts:
            schema.write_set(sets[part], paths[part])
        manifest = {"kind": KIND, "name": spec.name, "digest": spec.digest,
                    "version": LOGS_VERSION, "vehicle": spec.vehicle.__dict__,
                    "noise": {"name": spec.noise.name,
                              "process_sigma": spec.noise.process_sigma,
                              "measurement_sigma": spec.noise.measurement_sigma},
                    "resample": spec.resample, "max_gap": spec.max_gap,
                    "run_in": spec.run_in, "files": facts,
                    "sets": {p.name: schema.fingerprint(p) for p in paths.values()}}
        write_text(folder / "manifest.json", json.dumps(manifest, indent=1))
    return folder, sets, False


def _cached(folder: Path, paths: dict[str, Path]) -> dict[str, pd.DataFrame] | None:
    """The sets of a logs cache, each checked as the simulated sets are
    (:func:`lbo.sim.schema.cached_set`: against the sizes and sha256 its manifest records,
    then as Parquet); None when there is none to reuse, or one is damaged (said in one line:
    the caller reads the logs again)."""
    manifest = folder / "manifest.json"
    if not manifest.is_file() or not all(p.is_file() for p in paths.values()):
        return None
    try:
        recorded = json.loads(manifest.read_text()).get("sets") or {}
    except (OSError, ValueError, AttributeError):
        recorded = {}
    sets: dict[str, pd.DataFrame | None] = {}
    for part, path in paths.items():
        sets[part], problem = schema.cached_set(path, recorded.get(path.name), part)
        if problem is not None:
            print(f"{path}: {problem}; reading the logs again", flush=True)
            return None
    return cast(dict[str, pd.DataFrame], sets)  # each a set: cached_set found no problem


def test_files(folder: str | Path) -> list[str]:
    """The test logs of a folder built from logs, in the order of the ``file`` column."""
    manifest = json.loads((Path(folder) / "manifest.json").read_text())
    return [f["file"] for f in manifest["files"]["test"]]


def summary(folder: Path, sets: dict[str, pd.DataFrame], dt: float) -> list[str]:
    """Lines that say what each set holds."""
    manifest = json.loads((folder / "manifest.json").read_text())
    lines = []
    for part in sets:
        df, facts = sets[part], manifest["files"][part]
        minutes = len(df) * dt / 60
        line = (f"  {part:5s} {len(facts)} log(s), {df['traj'].nunique()} segment(s), "
                f"{len(df):,} rows ({minutes:.1f} min)")
        if part != "train":
            levels = [f["alpha"] for f in facts if np.isfinite(f["alpha"])]
            line += f", {int(df['scored'].sum()):,} scored"
            if levels:
                line += f"; noise level {min(levels):.2f}-{max(levels):.2f} x the preset"
        blind = sum(not f.get("truth", True) for f in facts)
        if blind:
            line += f"; {blind} log(s) without the truth (loss=next_fix trains on them)"
        lines.append(line)
    return lines
