"""Where the project lives: the project root holds data/, mlflow.db and optuna.db; conf/ is
the repository's, or the copy shipped inside the package when lbo is not installed editable."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf


def _find_root() -> Path:
    if "LBO_ROOT" in os.environ:
        return Path(os.environ["LBO_ROOT"]).resolve()
    here = Path(__file__).resolve().parents[3]  # src/lbo/core/paths.py -> the repository
    if (here / "conf").is_dir():
        return here
    return Path.cwd().resolve()


def _find_conf(root: Path) -> Path:
    if (root / "conf" / "train.yaml").is_file():
        return root / "conf"
    return Path(__file__).resolve().parents[1] / "conf"  # an installed wheel: lbo/conf


REPO_ROOT: Path = _find_root()
CONF_DIR: Path = _find_conf(REPO_ROOT)
EXAMPLE_LOG: Path = CONF_DIR.parent / "examples" / "stop_and_go_10hz.csv"
"""The example log of the README's quickstart (``examples/`` of the repository, or the copy in
the package): ``python -m lbo.simulate manoeuvre=stop_and_go fix_rate=10 output=...`` writes it
again, byte for byte."""



def cache_dir() -> Path:
    """Where lbo keeps what it can make again (ONNX exports of in-memory sessions):
    ``LBO_CACHE_DIR``, else ``$XDG_CACHE_HOME/lbo``, else ``~/.cache/lbo``."""
    if os.environ.get("LBO_CACHE_DIR"):
        return Path(os.environ["LBO_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "lbo"


# `${lbo.root:}` in any config resolves to the repo root, whatever the working directory.
if not OmegaConf.has_resolver("lbo.root"):
    OmegaConf.register_new_resolver("lbo.root", lambda: str(REPO_ROOT))


def tracking_uri() -> str:
    """The MLflow store every entry point uses: ``MLFLOW_TRACKING_URI``, else the SQLite
    file at the repo root. The configs read it too, as ``${lbo.tracking_uri:}``."""
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{REPO_ROOT / 'mlflow.db'}"


def store_overrides(uri: str) -> list[str]:
    """The override a training run composed by a command needs to log to the store ``uri``
    (``logger.tracking_uri=...``); none where the run finds that store itself
    (:func:`tracking_uri`), so that a URI, which may hold a password, is not passed on
    where it need not be."""
    return [] if str(uri) == tracking_uri() else [f"logger.tracking_uri={uri}"]


if not OmegaConf.has_resolver("lbo.tracking_uri"):
    OmegaConf.register_new_resolver("lbo.tracking_uri", tracking_uri)


def sqlite_path(uri: str) -> Path | None:
    """The database file behind a ``sqlite:///`` URL, or None for anything else."""
    prefix = "sqlite:///"
    if not uri.startswith(prefix):
        return None
    path = uri[len(prefix):].split("?")[0]
    return None if path in ("", ":memory:") else Path(path)


def artifact_location(tracking_uri: str) -> str | None:
    """Where a new MLflow experiment keeps its artifacts: beside a SQLite store, or None to
    let a tracking server decide. Without this, MLflow writes ./mlruns wherever it is run."""
    path = sqlite_path(tracking_uri)
    return None if path is None else (path.resolve().parent / "mlartifacts").as_uri()


if not OmegaConf.has_resolver("lbo.artifacts"):
    OmegaConf.register_new_resolver("lbo.artifacts", artifact_location)


def shipped(folder: str, name: str) -> dict[str, np.ndarray]:
    """The arrays of a real run lbo ships with its licence, ``data/<folder>/<name>`` in
    lbo.sim's package data (a ``numpy.savez_compressed`` file, no pickles), keyed as saved."""
    from importlib import resources

    source = resources.files("lbo.sim").joinpath("data", folder, name)
    with resources.as_file(source) as path, np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}
