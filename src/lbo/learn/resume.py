"""What ``resume=true`` may trust, and which folders a training may write into.

A run is known by the hash of what it computes (:func:`config_hash`, version
:data:`HASH_VERSION`, :mod:`lbo.learn.identity`): the same config, on the same data, finds the
same run. The hash reads today's config layout only: a setting added later (or a group moved,
a class renamed) goes with a version bump and a migration step in :mod:`lbo.learn.migrate`,
never with old layouts replayed at every hash, as version 1 did. The first search of a store
whose runs carry an older version's hash migrates them, once
(:func:`lbo.learn.migrate.migrate_experiments`).

A tracking store without authentication (an MLflow server, a shared database) lets anyone
add a run with a given config hash, naming any ``output_dir``. So a run's own folder, not the
store, says which run it holds: a training writes :data:`MARKER` there when it creates its
run (run id, config hash, the folder, finished or not), and every checkpoint carries the
same identity (:data:`IDENTITY_KEY`, :class:`lbo.learn.callbacks.RunIdentity`). A killed run is
continued, a finished one reused, and a stale one deleted only where these agree and belong to
this user. A new run never starts in a folder that holds another run's (or anyone's) files.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, cast

from omegaconf import DictConfig

from lbo.core.errors import LboError
from lbo.core.paths import sqlite_path
from lbo.core.runfolder import LOCK_NAME
from lbo.learn.identity import HASH_VERSION, older_hashes, owned, read_marker
from lbo.learn.layouts import OLDER_HASHES
from lbo.learn.migrate import mend_markers, migrate_experiments

EXPERIMENT_BEFORE = "lbo"
"""The one MLflow experiment every run went to before each data set had its own
(``lbo-<data>``): its runs are still found, reused and continued."""


LAST = "last.ckpt"
"""The checkpoint written at the end of every epoch (``save_last``), from which ``resume=true``
continues a killed run."""


def finished_run(cfg: DictConfig, digest: str, clean: bool = True) -> dict[str, Any] | None:
    """With ``resume=true``: the metrics of a FINISHED MLflow run of the same config, if any.

    Runs of the same config that never finished (killed, crashed) are deleted (unless
    ``clean`` is False), so a rerun replaces them instead of adding a duplicate.
    """
    return prior_runs(cfg, digest, clean)[0]


def prior_runs(cfg: DictConfig, digest: str, clean: bool = True, keep_resumable: bool = False
               ) -> tuple[dict[str, Any] | None, tuple[str | None, Path | None]]:
    """The MLflow runs of the same config, in one search: the metrics of the latest FINISHED
    one (or None), and, when none finished and ``keep_resumable``, the killed run to continue
    (run id, its output folder holding ``checkpoints/last.ckpt``) or (None, None). With
    ``clean``, every other unfinished run of this user's is deleted (and said so).

    A run found in the store is continued only from a folder that this user created for that
    very run (:func:`resumable_folder`): a store without authentication lets anyone add a run
    with this config hash and any ``output_dir``. In a store that others can write (a server,
    or a SQLite file not this user's alone, :func:`own_store`), a finished run is reused, and
    an unfinished one deleted, only where its folder's :data:`MARKER` shows it is this user's
    run; in this user's own SQLite file every run is.

    The first search of a store whose experiments hold runs of an older config-hash version
    migrates them (:func:`lbo.learn.migrate.migrate_experiments`), once; a run's marker that
    someone else's migration left naming the old hash is rewritten where ``cfg`` gives that
    hash (:func:`lbo.learn.migrate.mend_markers`)."""
    import mlflow

    uri = cfg.logger.tracking_uri
    store = sqlite_path(uri)
    if store is not None and not store.exists():  # MLflow would build the file only to look
        return None, (None, None)
    client = mlflow.MlflowClient(uri)
    exps = [e for e in (client.get_experiment_by_name(n) for n in dict.fromkeys(
        (cfg.logger.experiment_name, EXPERIMENT_BEFORE))) if e is not None]
    if not exps:
        return None, (None, None)
    migrate_experiments(client, exps)  # once: then no more than a look at their tags
    found = client.search_runs([e.experiment_id for e in exps],
                               f"tags.config_hash = '{digest}'")
    mend_markers(cfg, found, digest)
    own = own_store(uri)
    done = []
    for r in (r for r in found if r.info.status == "FINISHED"):
        why = None if own else _not_mine(r, digest, finished=True)
        if why is None:
            done.append(r)
        else:
            print(f"not reusing the finished run {r.info.run_id} of the same config in the "
                  f"shared store: {why}")
    resumable = _resumable(found, digest) if keep_resumable and not done else (None, None)
    for r in found:
        if clean and r.info.status != "FINISHED" and r.info.run_id != resumable[0] and (
                own or _not_mine(r, digest) is None):
            client.delete_run(r.info.run_id)
            print(f"deleted the unfinished run {r.info.run_id} ({r.info.status}) of the same "
                  "config; this run replaces it")
    if not done:
        return None, resumable
    run = max(done, key=lambda r: r.info.end_time or 0)
    history = client.get_metric_history(run.info.run_id, "val_loss")
    # the observer's name, as a training returns it (the run's may carry a study's prefix:
    # robust-filternet-N100), which the report looks the observer's scores up by
    return {"name": f"{cfg.model.name}-N{cfg.model.window}", "run_id": run.info.run_id,
            "reused": True,
            "val_loss": min((m.value for m in history), default=float("nan")),
            "checkpoint": f"{run.info.artifact_uri}/checkpoints/best.ckpt",
            **{k: v for k, v in run.data.metrics.items() if k.startswith("test_")}}, resumable


def own_store(uri: str) -> bool:
    """Whether tracking store ``uri`` is this user's alone: a SQLite file (or, not yet made, a
    folder) owned by this user that no one else can write. A server or a shared database is
    not: anyone who reaches it can add runs."""
    path = sqlite_path(uri) if uri.startswith("sqlite:") else None
    if path is None:
        return False
    for p in (path, path.parent):
        try:
            st = p.stat()
        except FileNotFoundError:
            continue
        except OSError:
            return False
        if st.st_uid != os.getuid() or st.st_mode & 0o022:
            return False
    return True


def _not_mine(run: Any, digest: str, finished: bool = False) -> str | None:
    """Why MLflow run ``run`` of config ``digest`` is not shown to be this user's by its
    output folder's :data:`MARKER` (a run made elsewhere, or planted), or None when it is."""
    folder = run.data.params.get("output_dir")
    if not folder:
        return "it names no output folder"
    marker, why = read_marker(Path(folder))
    if marker is None:
        return f"its output folder {folder} is not this user's run ({why})"
    if marker.get("run_id") != run.info.run_id or marker.get("config_hash") != digest:
        return f"its output folder {folder} belongs to run {marker.get('run_id')}"
    if finished and not marker.get("finished"):
        return f"its output folder {folder} records no finished training"
    return None


def _resumable(found: list, digest: str) -> tuple[str | None, Path | None]:
    """The latest unfinished run among ``found`` whose output folder still holds its last
    checkpoint and is that run's own (:func:`resumable_folder`): (run id, output folder), or
    (None, None). A run whose folder fails the checks is not continued, with a line why."""
    for r in sorted(found, key=lambda r: r.info.start_time or 0, reverse=True):
        folder = r.data.params.get("output_dir")
        if r.info.status == "FINISHED" or not folder or \
                not (Path(folder) / "checkpoints" / LAST).is_file():
            continue
        why = resumable_folder(Path(folder), r.info.run_id, digest)
        if why is None:
            return r.info.run_id, Path(folder)
        print(f"not resuming the unfinished run {r.info.run_id} of the same config: {why}; "
              "this run starts afresh")
    return None, None


def resumable_folder(folder: Path, run_id: str, digest: str) -> str | None:
    """Why run ``run_id`` of config ``digest`` may not be continued in ``folder`` (the folder
    its MLflow run names), or None when it may: the folder and its run-identity file are this
    user's, written for that run and config; ``checkpoints/last.ckpt`` is this user's, carries
    the same identity (``RunIdentity``; or, written before the run was migrated, an older
    version's hash its marker keeps), and the best checkpoint it names lies in that folder's
    ``checkpoints``."""
    import torch

    why: str | None
    marker, why = read_marker(folder)
    if marker is None:
        return f"its output folder {folder} was not created for it here ({why})"
    if marker.get("run_id") != run_id or marker.get("config_hash") != digest:
        return (f"its output folder {folder} belongs to run {marker.get('run_id')} of config "
                f"{marker.get('config_hash')}")
    ckpts = folder.resolve() / "checkpoints"
    last = ckpts / LAST
    why = owned(ckpts, "checkpoint folder") or owned(last, f"checkpoint {LAST}")
    if why is not None:
        return why
    try:  # tensors and plain containers only: a checkpoint is never code to run
        ckpt = torch.load(last, map_location="cpu", weights_only=True)
    except Exception as e:
        return f"its checkpoint {last} cannot be read ({type(e).__name__})"
    # a run killed before its store was migrated: its last checkpoint carries an older
    # version's hash, which the marker keeps beside the new one (lbo.learn.migrate)
    ids = [{"run_id": run_id, "config_hash": h}
           for h in (digest, *older_hashes(marker).values())]
    if not isinstance(ckpt, dict) or ckpt.get(IDENTITY_KEY) not in ids:
        return f"its checkpoint {last} was not written by that run"
    for key, state in (ckpt.get("callbacks") or {}).items():
        if str(key).startswith("ModelCheckpoint") and isinstance(state, dict):
            best = state.get("best_model_path") or ""
            if best and Path(best).resolve().parent != ckpts:
                return f"its checkpoint {last} names a best checkpoint outside {ckpts}: {best}"
    return None


HYDRA_RECORD = (LOCK_NAME, ".hydra")
"""What a folder may hold and still be a new run's: its lock, Hydra's record of the job
(``.hydra/``, rewritten by each job) and the job's log (``train.log``)."""


def folder_refusal(folder: Path, digest: str | None, resume: bool,
                   field: str = "output_dir", finished_ok: bool = False,
                   cfg: DictConfig | None = None) -> str | None:
    """Why a training may not start afresh in ``folder``, or None when it may.

    It may when the folder is missing or holds nothing but :data:`HYDRA_RECORD`, or (with
    ``resume=true``) when it is an unfinished run of the same config (``digest``; None: any)
    that this user created there: that run is replaced, as ``resume=true`` replaces a killed
    run. ``finished_ok``: a finished run of that config there passes too (``resume=true``
    reuses it rather than train). Anything else is another run's or another program's files,
    which a typo or a copied command would otherwise delete or overwrite (``best.ckpt``,
    ``evaluation.csv``). With ``cfg`` (whose hash ``digest`` is), a run-identity file written
    under an older config-hash version is the same config's where it names ``cfg``'s hash of
    that version (:data:`lbo.learn.layouts.OLDER_HASHES`)."""
    from hydra.core.hydra_config import HydraConfig

    job = HydraConfig.get().job.name if HydraConfig.initialized() else "train"
    try:
        held = sorted(p.name for p in folder.iterdir()
                      if p.name not in HYDRA_RECORD and p.name != f"{job}.log")
    except FileNotFoundError:
        return None
    except NotADirectoryError:
        return f"{field}: {folder} is a file, not a folder; give a folder"
    if not held:
        return None
    marker, _ = read_marker(folder)
    same = marker is not None and (digest is None or marker.get("config_hash") == digest or (
        cfg is not None and _older_hash(marker, cfg)))
    # same: there is a marker
    if same and resume and (finished_ok or not cast(dict, marker).get("finished")):
        return None
    if marker is not None and marker.get("finished"):
        what = f"the files of the finished run {marker.get('run_id')}"
    elif same:
        what = (f"the files of the unfinished run {cast(dict, marker).get('run_id')} of this "
                "config (add resume=true to continue or replace it)")
    elif marker is not None:
        what = f"the files of run {marker.get('run_id')} of another config"
    else:
        shown = ", ".join(held[:4]) + (", ..." if len(held) > 4 else "")
        what = f"files that are not this run's ({shown})"
    return (f"{field}: {folder} already holds {what}; nothing there was changed: give "
            f"{field}=<a new or empty folder> (or remove that folder)")


def _older_hash(marker: dict[str, Any], cfg: DictConfig) -> bool:
    """Whether run-identity file ``marker``, written under an older config-hash version (none
    named: 1), holds ``cfg``'s hash of that version."""
    version = marker.get("hash_version", 1)
    then = OLDER_HASHES.get(version) if version != HASH_VERSION else None
    return then is not None and marker.get("config_hash") == then(cfg)


def check_folder(cfg: DictConfig) -> None:
    """Refuse (one line) a run folder that holds another run's files, before lbo's shell
    writes its ``.hydra`` record there (``hydra.run.dir=<a finished run's folder>``)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return
    folder = Path(HydraConfig.get().runtime.output_dir).resolve()
    if Path(cfg.output_dir).resolve() == folder:
        resume = bool(cfg.get("resume"))
        refusal = folder_refusal(folder, None, resume, "hydra.run.dir", finished_ok=resume)
        if refusal is not None:
            raise LboError(refusal)


IDENTITY_KEY = "lbo_run"
"""Where a checkpoint carries the identity of the run that wrote it
(:class:`lbo.learn.callbacks.RunIdentity`): ``{"run_id": ..., "config_hash": ...}``."""


def clear_stale_checkpoints(folder: Path) -> list[Path]:
    """Remove the ``.ckpt`` files an earlier run left in ``folder`` (killed, or trained into
    the same output folder), so this run's best checkpoint is ``best.ckpt`` and never a
    ``best-v1.ckpt`` beside a stale one. Returns what it removed (and says so)."""
    stale = sorted(folder.glob("*.ckpt")) if folder.is_dir() else []
    for path in stale:
        path.unlink()
    if stale:
        print(f"removed {len(stale)} stale checkpoint(s) of an earlier run from {folder}: "
              f"{', '.join(p.name for p in stale)}")
    return stale
