"""Where a learned observer's checkpoint is: a file, an MLflow run, a run's or a registered
model's URI, resolved to a local file (downloaded into a temporary folder when it is remote).

A run id in lbo's own kind of store (a SQLite file whose runs keep their artifacts in a local
folder, as ``sqlite:///mlflow.db`` and its ``mlartifacts/`` do) is read in place: the run's
artifact folder is looked up in the database with the standard library, and its
``checkpoints/best.ckpt`` opened where it lies. MLflow's import, its store and its copy of the
file cost about 2.5 s of a 9 s ``lbo.observe``; anything else goes through MLflow."""

from __future__ import annotations

import contextlib
import json
import os
import re
import sqlite3
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlparse

from lbo.core.errors import LboError
from lbo.core.paths import sqlite_path, tracking_uri
from lbo.core.smallfile import read_small
from lbo.filters import classical
from lbo.tracking.runs import no_progress_bar

RUN_ID = re.compile(r"[0-9a-f]{32}")
"""An MLflow run id, as ``observer=<run id>`` takes it."""


def load_net(source: str, device: str = "cpu") -> tuple[Any, dict[str, Any]]:
    """The :class:`~lbo.models.net.WindowNet` and hyperparameters of a learned observer named
    as :meth:`lbo.Observer.load` takes it (a checkpoint file, an MLflow run id, a ``runs:/`` or
    ``models:/`` URI); raises LboError naming the problem."""
    from lbo.models.checkpoint import read_checkpoint

    with checkpoint_file(str(source)) as path:
        return read_checkpoint(path, device=device)


@contextlib.contextmanager
def checkpoint_file(source: str) -> Iterator[Path]:
    """The local checkpoint file for a source; one downloaded from MLflow lives in a
    temporary folder that is removed on exit."""
    src = unquote(urlparse(source).path) if source.startswith("file://") else source
    if Path(src).is_file():
        yield Path(src)
        return
    if RUN_ID.fullmatch(src):
        in_place = local_run_checkpoint(src, tracking_uri())
        if in_place is not None:
            yield in_place
            return
        uri, run_id = f"runs:/{src}/checkpoints/best.ckpt", src
    elif src.startswith(("runs:/", "models:/")):
        uri, run_id = src, None
    elif Path(src).suffix or "/" in src or os.sep in src:
        raise LboError(f"observer: checkpoint not found: {src}")
    else:
        raise LboError(f"observer: {src!r} is not a checkpoint file, an MLflow run id "
                       "(32 hex digits), a runs:/ or models:/ URI, nor one of "
                       f"{', '.join(classical.on_logs())}")
    with tempfile.TemporaryDirectory(prefix="lbo-ckpt-") as tmp:
        yield _download(uri, run_id, Path(tmp))


def local_run_checkpoint(run_id: str, store: str) -> Path | None:
    """A run's ``checkpoints/best.ckpt`` where it lies, when ``store`` is a SQLite file that
    holds the run and the run's artifacts are a local folder; None otherwise (a server, another
    database, remote artifacts, no such run or file), and MLflow is asked instead."""
    folder = local_run_folder(run_id, store)
    path = folder / "checkpoints" / "best.ckpt" if folder is not None else None
    return path if path is not None and path.is_file() else None


def local_run_folder(run_id: str, store: str) -> Path | None:
    """A run's artifact folder, when ``store`` is a SQLite file that holds the run and keeps
    its artifacts in a local folder; None otherwise."""
    db = sqlite_path(store)
    if db is None or not db.is_file():
        return None
    try:  # read-only: a command that only reads never changes the store
        with contextlib.closing(sqlite3.connect(f"{db.resolve().as_uri()}?mode=ro",
                                                uri=True)) as con:
            row = con.execute("SELECT artifact_uri FROM runs WHERE run_uuid = ?",
                              (run_id,)).fetchone()
    except sqlite3.Error:  # not MLflow's schema, locked, damaged: MLflow says what is wrong
        return None
    if not row or not isinstance(row[0], str):
        return None
    where = urlparse(row[0])
    if where.scheme == "file":
        return Path(unquote(where.path))
    if not where.scheme:
        return Path(row[0])
    return None  # mlflow-artifacts:, s3:, ...: MLflow fetches them


NOISE_FILES = ("gyro_noise.json", "conditions.json")
"""What a run of ``lbo.train model=gyro_ekf`` keeps in its ``gyro_ekf/`` artifact folder
(:mod:`lbo.learn.noise_run`) for :func:`learned_noise`."""


def learned_noise(source: str) -> tuple[Any, Any, Any] | None:
    """The gyro EKF a run of ``lbo.train model=gyro_ekf`` learned, when ``source`` is such a
    run's id: ``(GyroNoise, Vehicle, Noise)`` (its noise, and the vehicle and classical preset
    it was learned with), read as data, never run. None for any other source (a checkpoint, a
    learned observer's run), which is then loaded as a checkpoint."""
    from lbo.filters.gyro_noise import GyroNoise
    from lbo.models.checkpoint import trained_conditions

    if not RUN_ID.fullmatch(source):
        return None
    store = tracking_uri()
    folder = local_run_folder(source, store)
    if folder is None and sqlite_path(store) is not None:  # lbo's own store, not its run
        return None
    with contextlib.ExitStack() as stack:
        if folder is None:  # a server's run: its two small files fetched, if it has them
            tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="lbo-noise-")))
            found = _noise_download(source, store, tmp)
        else:
            found = folder / "gyro_ekf"
        if found is None or not (found / NOISE_FILES[0]).is_file():
            return None
        cond = found / NOISE_FILES[1]
        try:
            meta = json.loads(read_small(cond, f"run {source}: {cond.name}",
                                         "a JSON object").decode("utf-8"))
        except ValueError as e:
            raise LboError(f"observer: run {source}: {cond.name} is not JSON ({e})") from None
        vehicle, noise = trained_conditions({"meta": meta}, cond)
        return GyroNoise.load(found / NOISE_FILES[0]), vehicle, noise


def _noise_download(run_id: str, store: str, folder: Path) -> Path | None:
    """A remote run's ``gyro_ekf/`` folder downloaded into ``folder``; None when it has none."""
    import mlflow
    from mlflow.exceptions import MlflowException

    from lbo.tracking.runs import check_server

    check_server(store, field="MLFLOW_TRACKING_URI")
    client = mlflow.MlflowClient(store)
    try:
        if not [a for a in client.list_artifacts(run_id, "gyro_ekf")
                if a.path.endswith(NOISE_FILES[0])]:
            return None
        with no_progress_bar():
            for name in NOISE_FILES:
                client.download_artifacts(run_id, f"gyro_ekf/{name}", str(folder))
    except MlflowException:
        return None  # no such run: loading it as a checkpoint says so
    return folder / "gyro_ekf"


def _download(uri: str, run_id: str | None, folder: Path) -> Path:
    """Download ``uri`` (runs:/ or models:/) into ``folder``; return the .ckpt in it."""
    import mlflow
    from mlflow.exceptions import MlflowException

    from lbo.tracking.runs import check_server

    store = tracking_uri()
    # a dead server: one line in seconds, not MLflow's retries for minutes
    check_server(store, field="MLFLOW_TRACKING_URI")
    client = mlflow.MlflowClient(store, registry_uri=store)
    if run_id is not None:
        try:
            client.get_run(run_id)
        except MlflowException:
            raise LboError(f"observer: MLflow run {run_id} not found in {store}") from None
    try:
        where = _model_version_uri(client, uri) if uri.startswith("models:/") else uri
        with no_progress_bar():
            local = Path(mlflow.artifacts.download_artifacts(
                artifact_uri=where, dst_path=str(folder), tracking_uri=store))
    except MlflowException as e:
        reason = str(e.message).strip().splitlines()[0]
        if run_id is not None:
            raise LboError(f"observer: MLflow run {run_id} has no checkpoints/best.ckpt "
                           f"(did it finish training?): {reason}") from None
        raise LboError(f"observer: {uri} not found in {store}: {reason}") from None
    if local.is_file():
        return local
    found = sorted(local.rglob("*.ckpt"))
    best = [p for p in found if p.name == "best.ckpt"]
    if len(best) == 1 or len(found) == 1:
        return (best or found)[0]
    raise LboError(f"observer: {uri} holds {len(found)} .ckpt files, "
                   "expected one (or one best.ckpt)")


def _model_version_uri(client: Any, uri: str) -> str:
    """``models:/name/version`` or ``models:/name@alias`` -> where that version's files are."""
    ref = uri[len("models:/"):].strip("/")
    if "@" in ref:
        name, alias = ref.split("@", 1)
        version = client.get_model_version_by_alias(name, alias).version
    elif "/" in ref:
        name, version = ref.rsplit("/", 1)
    else:
        raise LboError(f"observer: {uri}: give models:/<name>/<version> or models:/<name>@<alias>")
    return client.get_model_version_download_uri(name, version)
