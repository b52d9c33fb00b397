"""Where a learned observer's checkpoint is: a file, an MLflow run, a run's or a registered
model's URI, resolved to a local file (downloaded into a temporary folder when it is remote)."""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlparse

from lbo.core.errors import LboError
from lbo.core.paths import tracking_uri
from lbo.filters import classical

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


PROGRESS_BAR = "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR"


@contextlib.contextmanager
def _no_progress_bar() -> Iterator[None]:
    """MLflow's download bars off (a checkpoint of a few MB comes in a blink, and the bars
    would sit between a command's own lines), unless the user set :data:`PROGRESS_BAR`."""
    if PROGRESS_BAR in os.environ:
        yield
        return
    os.environ[PROGRESS_BAR] = "false"
    try:
        yield
    finally:
        os.environ.pop(PROGRESS_BAR, None)


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
        with _no_progress_bar():
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
