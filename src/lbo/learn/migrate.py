"""The one-time migration of a tracking store's runs to the current config hash version.

A store's runs are brought to the current version once (:func:`migrate_experiment`): the config
each run logged (its ``config.yaml`` artifact, written by every lbo training since the first)
is read as data, brought to today's layout (:func:`lbo.learn.layouts.upgraded`) and checked
against the hash the run carries, in the version it is tagged with
(:data:`lbo.learn.layouts.OLDER_HASHES`: ``hash_version``, none for version 1); the run is
then tagged with today's hash (``config_hash``), the old one (``config_hash_v1``,
``config_hash_v2``: :func:`lbo.learn.identity.was_key`) and ``hash_version``, and its folder's
run-identity file, where it is this user's, rewritten to match. A run whose stored config
does not give its tag is left as it was, with a line saying why. Nothing read from a store or
a file is run: a config is YAML read as data, never instantiated.

    python -m lbo.learn.migrate [<tracking uri>]   # every experiment's runs (default: lbo's)
"""

from __future__ import annotations

import sys
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from lbo.core.errors import LboError
from lbo.learn.identity import (
    HASH_VERSION,
    config_hash,
    older_hashes,
    read_marker,
    was_key,
    write_marker,
)
from lbo.learn.layouts import OLDER_HASHES, upgraded

V1_TAG = was_key(1)
"""The run tag (and run-identity field) that keeps a migrated run's version-1 hash."""
MIGRATED = "lbo.hash_version"
"""The experiment tag set once every run of the experiment carries the current hash version:
``resume=true`` then looks no further (one look at the experiment it fetches anyway)."""
MAX_CONFIG = 1 << 20
"""The largest ``config.yaml`` (bytes) a migration reads: a config is a few kB."""


# --- a store's runs ----------------------------------------------------------------------------


def migrate_experiments(client: Any, experiments: Iterable[Any]) -> None:
    """Migrate each of ``experiments`` (MLflow experiments) not yet marked :data:`MIGRATED`:
    what ``resume=true`` asks before its search, at no cost once they are."""
    for exp in experiments:
        if exp.tags.get(MIGRATED) != str(HASH_VERSION):
            migrate_experiment(client, exp)


def migrate_experiment(client: Any, exp: Any, mark: bool = True) -> int:
    """Bring every run of ``exp`` that carries a config hash of an older version to the current
    one (:func:`migrate_run`), mark the experiment :data:`MIGRATED` (unless not ``mark``), and
    say what was done (a line per run left as it was, then one for the experiment). Returns
    the runs migrated."""
    done = left = 0
    for run in list(_unmigrated(client, exp.experiment_id)):  # every page before a change
        why = migrate_run(client, run)
        if why is None:
            done += 1
        else:
            left += 1
            print(f"left run {run.info.run_id} of {exp.name} as it was: {why}")
    if mark:
        _mark(client, exp.experiment_id)
    if done or left:
        print(f"migrated {done} run{'s' * (done != 1)} of {exp.name} to config hash version "
              f"{HASH_VERSION}" + (f" ({left} left as they were)" if left else ""))
    return done


def _mark(client: Any, experiment_id: str) -> None:
    """Mark the experiment :data:`MIGRATED`. Jobs started together (a sweep's, through SLURM
    or joblib) mark a new experiment at once, and the store refuses the second insert of the
    tag: the one that finds the mark there has nothing left to do."""
    from mlflow.exceptions import MlflowException

    try:
        client.set_experiment_tag(experiment_id, MIGRATED, str(HASH_VERSION))
    except MlflowException:
        if client.get_experiment(experiment_id).tags.get(MIGRATED) != str(HASH_VERSION):
            raise


def _unmigrated(client: Any, experiment_id: str) -> Iterator[Any]:
    """The active runs of the experiment with a ``config_hash`` tag of an older version than
    :data:`HASH_VERSION` (or none), page by page."""
    token = None
    while True:
        page = client.search_runs([experiment_id], max_results=1000, page_token=token)
        yield from (r for r in page if "config_hash" in r.data.tags
                    and r.data.tags.get("hash_version") != str(HASH_VERSION))
        token = page.token
        if not token:
            return


def migrate_run(client: Any, run: Any) -> str | None:
    """Tag ``run`` (carrying a ``config_hash`` of an older version) with today's hash, worked
    out from the config it logged, and rewrite its folder's run-identity file where that is
    this user's and names the run; or say why not (and change nothing)."""
    from mlflow.entities import RunTag
    from mlflow.exceptions import MlflowException

    old, tagged = run.data.tags["config_hash"], run.data.tags.get("hash_version", "1")
    version = int(tagged) if tagged.isdigit() else 0
    if version not in OLDER_HASHES:
        return f"its hash_version {tagged!r} is none of {sorted(OLDER_HASHES)}"
    try:
        stored = _stored_config(client, run.info.run_id)
        if stored is None:
            return "it logged no config.yaml"
        cfg = upgraded(stored)
        then = OLDER_HASHES[version](cfg)
        if then != old:
            return f"its config.yaml hashes as {then}, not as its tag {old}"
        new = config_hash(cfg)
    except LboError as e:
        return str(e)
    except (OSError, ValueError, OmegaConfBaseException, MlflowException) as e:
        return f"its config.yaml cannot be read ({type(e).__name__})"
    folder = run.data.params.get("output_dir")
    marker, _ = read_marker(Path(folder)) if folder else (None, "")
    was = {was_key(version): old}
    if marker is not None and marker.get("run_id") == run.info.run_id and (
            marker.get("config_hash") == old or old in older_hashes(marker).values()):
        write_marker(Path(folder), run.info.run_id, new, bool(marker.get("finished")),
                     was=older_hashes(marker) | was)
    tags = {"config_hash": new, **was, "hash_version": str(HASH_VERSION)}
    try:
        client.log_batch(run.info.run_id, tags=[RunTag(k, v) for k, v in tags.items()])
    except MlflowException:
        # jobs started together (a sweep's, through SLURM or joblib) migrate the same runs at
        # once, and the store refuses the second insert of a tag: the first one's stand
        if {k: client.get_run(run.info.run_id).data.tags.get(k) for k in tags} != tags:
            raise
    return None


def _stored_config(client: Any, run_id: str) -> DictConfig | None:
    """The ``config.yaml`` artifact of run ``run_id``, read as data only (a YAML mapping: the
    safe loader, under OmegaConf's float rules), or None without one."""
    logged = {a.path: a for a in client.list_artifacts(run_id)}
    if "config.yaml" not in logged:
        return None
    if (logged["config.yaml"].file_size or 0) > MAX_CONFIG:
        raise LboError(f"its config.yaml is over {MAX_CONFIG} bytes")
    from lbo.tracking.runs import no_progress_bar

    with tempfile.TemporaryDirectory() as tmp, no_progress_bar():
        text = Path(client.download_artifacts(run_id, "config.yaml", tmp)).read_text()
    try:
        cfg = OmegaConf.create(text)
    except Exception as e:  # PyYAML's errors, OmegaConf's
        raise LboError(f"its config.yaml is not YAML ({type(e).__name__})") from e
    if not isinstance(cfg, DictConfig):
        raise LboError("its config.yaml is not a mapping")
    return cfg


def mend_markers(cfg: DictConfig, runs: Iterable[Any], digest: str) -> None:
    """Rewrite this user's run-identity files that still name a run (among ``runs``, found by
    ``digest``, the hash of ``cfg``) by an older version's hash, which someone else's migration
    of a shared store could not: where the file names the run, and ``cfg``'s own hash of that
    version is the one it holds (so the store's word is not taken for it)."""
    for run in runs:
        folder = run.data.params.get("output_dir")
        kept = older_hashes(run.data.tags)
        marker, _ = read_marker(Path(folder)) if kept and folder else (None, "")
        if marker is None or marker.get("run_id") != run.info.run_id:
            continue
        for version, then in OLDER_HASHES.items():
            was = kept.get(was_key(version))
            if was is not None and marker.get("config_hash") == was and then(cfg) == was:
                write_marker(Path(folder), run.info.run_id, digest,
                             bool(marker.get("finished")), was=older_hashes(marker) | {
                                 was_key(version): was})
                break


def migrate(uri: str) -> int:
    """Migrate the runs of every experiment of the store at ``uri`` that carry an older
    version's hash, marked or not (a run an older lbo added since is migrated too). No
    experiment is marked: some may not be lbo's (``resume=true`` marks its own). Returns the
    runs migrated."""
    import mlflow

    from lbo.tracking.runs import check_store

    check_store(uri, "tracking_uri")
    client = mlflow.MlflowClient(uri)
    return sum(migrate_experiment(client, e, mark=False)
               for e in client.search_experiments())


def main(argv: list[str] | None = None) -> int:
    """``python -m lbo.learn.migrate [<tracking uri>]``: :func:`migrate`, in one line an
    error."""
    import argparse

    from lbo.core.cli import scrubbed_output
    from lbo.core.paths import sqlite_path, tracking_uri

    parser = argparse.ArgumentParser(prog="python -m lbo.learn.migrate", description=(
        f"Bring the runs of an MLflow store to config hash version {HASH_VERSION}, once."))
    parser.add_argument("tracking_uri", nargs="?", help="the store (default: "
                        "MLFLOW_TRACKING_URI, else mlflow.db at the repository)")
    uri = parser.parse_args(argv).tracking_uri or tracking_uri()
    with scrubbed_output():
        path = sqlite_path(uri)
        if path is not None and not path.is_file():
            print(f"no store at {uri}: nothing to migrate")
            return 0
        try:
            n = migrate(uri)
        except (LboError, OSError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"{uri}: {n} run{'s' * (n != 1)} migrated to config hash version {HASH_VERSION}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
