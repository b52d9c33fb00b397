"""What ``resume=true`` may trust, and which folders a training may write into.

A run is known by the hash of what it computes (:func:`config_hash`): the same config, on the
same data, finds the same run.

A tracking store without authentication (an MLflow server, a shared database) lets anyone
add a run with a given config hash, naming any ``output_dir``. So a run's own folder, not the
store, says which run it holds: a training writes :data:`MARKER` there when it creates its
run (run id, config hash, the folder, finished or not), and every checkpoint carries the
same identity (:data:`IDENTITY_KEY`, :class:`lbo.learn.callbacks.RunIdentity`). A killed run is
continued, a finished one reused, and a stale one deleted only where these agree and belong to
this user. A new run never starts in a folder that holds another run's (or anyone's) files.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
from pathlib import Path
from typing import Any, cast

from omegaconf import DictConfig, OmegaConf, open_dict

from lbo.core import LAYERS
from lbo.core.atomic import write_text
from lbo.core.cli import MODEL_SHORT
from lbo.core.errors import LboError
from lbo.core.paths import sqlite_path
from lbo.core.runfolder import LOCK_NAME
from lbo.logs.sets import is_logs

LATER_DEFAULTS: dict[str, Any] = {"model.normalisation": "standard", "receiver": None,
                  "receiver_training": {"heading_share": 0.25, "gyro_share": 0.75},
                  "model.gyro": False, "tbptt": None,
                  "sequence_length": None, "nll": 0.0, "train_noise.changes": 0,
                  "loss": "truth", "data.source": "files",
                  "train_outages": {"share": 0.0, "max_s": 10.0}}
"""Settings added after runs were stored (a dotted key: one inside a group), with the value
those runs had: a config holding that value hashes as if it did not have the key, so
resume=true still finds the old runs."""
LATER_MODEL_DEFAULTS: dict[str, dict[str, Any]] = {
    **{name: {"body": "kinematic", "body_lr": 1.0} for name in ("kalmannet", "split_kalmannet")},
    "filternet": {"empty_statistic": "net", "drift_tau": None},
    "gyro_ekf": {"drift": False, "scales": False}}
"""As :data:`LATER_DEFAULTS`, for the settings added to one model's config (``model.body`` of
the KalmanNet peers, which the robust observer's config has had from the start, and its
``model.empty_statistic`` and ``model.drift_tau``; the gyro EKF's ``model.drift`` and
``model.scales``)."""


WAS = {"lbo.learn.progress.EpochBar": "lightning.pytorch.callbacks.TQDMProgressBar"}
"""Callbacks that replaced another in ``conf/``, by what they replaced: a config hash reads
them as it, so that the runs of a store made before still resume and are reused."""


EXPERIMENT_BEFORE = "lbo"
"""The one MLflow experiment every run went to before each data set had its own
(``lbo-<data>``): its runs are still found, reused and continued."""


BAR_REFRESH = 20
"""The progress bar's refresh rate every config hashes as, whatever it draws at: the default,
which the runs of a store made before hashed (``make reproduce`` hides each run's bar)."""


def config_hash(cfg: DictConfig) -> str:
    """Fingerprint of what a run computes: the resolved config without where it writes."""
    c = cfg.copy()
    with open_dict(c):
        c.output_dir, c.data.root, c.resume, c.data_dir = "-", "-", False, None
        c.pop("logger", None)
        c.pop("paths", None)  # where it reads and writes, not what
        # how fast, not what: a run on other threads, or compiled (the same numbers to
        # rounding), is reused
        c.pop("threads", None)
        c.pop("compile", None)
        c.pop("keep_onnx", None)  # what lbo.observe finds afterwards, not what is trained
        c.pop("verbose", None)  # what it prints
        bar = OmegaConf.select(c, "callbacks.progress_bar")
        if isinstance(bar, DictConfig) and bar.get("_target_") in WAS:
            bar["_target_"] = WAS[bar["_target_"]]  # how it prints, hashed as it was before
        if isinstance(bar, DictConfig) and "refresh_rate" in bar:
            bar["refresh_rate"] = BAR_REFRESH  # how often it draws (0: not at all), not what
        for key, default in LATER_DEFAULTS.items():
            *group, name = key.split(".")
            node = OmegaConf.select(c, ".".join(group)) if group else c
            if isinstance(node, DictConfig) and name in node and node.get(name) == default:
                node.pop(name)
        model = c.get("model")
        for name, default in LATER_MODEL_DEFAULTS.get(model.get("name") if model else "",
                                                      {}).items():
            if name in model and model.get(name) == default:
                model.pop(name)
    text = OmegaConf.to_yaml(OmegaConf.create(_as_before_groups_moved(
        _unlayered(OmegaConf.to_container(c, resolve=True)))))
    if is_logs(cfg):  # the same paths with other contents are other data
        from lbo.learn.builders import logs_spec

        text += f"\nlogs: {logs_spec(cfg).digest}"
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _as_before_groups_moved(tree: dict[str, Any]) -> dict[str, Any]:
    """``tree`` (a resolved training config) in the layout it had before its groups moved, in
    the same key order, so that a run's hash does not depend on either move and the runs of a
    store made before them are still found:

    - the ``car`` and ``sensors`` groups as the one ``truth`` group they were (the car's keys,
      then the sensors', where ``car`` stands);
    - the model's own settings (:data:`lbo.core.cli.MODEL_SHORT`) out of ``model``, back at
      the top (``window`` before ``seed``, the others before ``batch_size``), and ``model``
      after ``data``, where its group stood."""
    model = tree.get("model")
    moved: dict[str, Any] = {}
    if isinstance(model, dict) and any(k in model for k in MODEL_SHORT):
        model = dict(model)
        moved = {k: model.pop(k) for k in MODEL_SHORT if k in model}
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if key == "seed" and "window" in moved:
            out["window"] = moved.pop("window")
        if key == "batch_size":
            out.update({k: moved.pop(k) for k in ("features", "normalisation") if k in moved})
        if key == "car":
            out["truth"] = {**value, **(tree.get("sensors") or {})}
        elif key != "sensors" and not (key == "model" and "data" in tree):
            out[key] = value
        if key == "data" and "model" in tree:
            out["model"] = model
    return out


def _unlayered(node: Any) -> Any:
    """``node`` with every lbo ``_target_`` written without its layer (``lbo.learn.callbacks.X``
    -> ``lbo.callbacks.X``), as it was before lbo's modules moved into layers: a run's hash
    does not depend on which layer a class lives in, and the runs of a store made before the
    move are still found by ``resume=true``."""
    if isinstance(node, dict):
        out = {k: _unlayered(v) for k, v in node.items()}
        target = out.get("_target_")
        if isinstance(target, str) and target.startswith("lbo."):
            parts = target.split(".")
            if len(parts) > 3 and parts[1] in LAYERS:
                out["_target_"] = ".".join([parts[0], *parts[2:]])
        return out
    if isinstance(node, list):
        return [_unlayered(v) for v in node]
    return node


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
    run; in this user's own SQLite file every run is."""
    import mlflow

    uri = cfg.logger.tracking_uri
    client = mlflow.MlflowClient(uri)
    exps = [e for e in (client.get_experiment_by_name(n) for n in dict.fromkeys(
        (cfg.logger.experiment_name, EXPERIMENT_BEFORE))) if e is not None]
    if not exps:
        return None, (None, None)
    found = client.search_runs([e.experiment_id for e in exps],
                               f"tags.config_hash = '{digest}'")
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


MARKER = ".lbo-run.json"
"""The run-identity file a training writes into its output folder when it creates its run:
the MLflow run id, the config hash, the folder itself and whether the run finished. Owned
by the user who trained, it is what ``resume=true`` trusts, not the tracking store."""


def write_marker(folder: Path, run_id: str | None, digest: str, finished: bool = False) -> Path:
    """Write (atomically) ``folder``'s run-identity file (:data:`MARKER`)."""
    return write_text(folder / MARKER, json.dumps(
        {"run_id": run_id, "config_hash": digest, "folder": str(folder.resolve()),
         "uid": os.getuid(), "finished": finished}, indent=1) + "\n")


def _owned(path: Path, what: str) -> str | None:
    """Why ``path`` cannot be trusted as this user's own (a link, another user's), or None."""
    try:
        st = path.lstat()
    except OSError:
        return f"it has no {what}"
    if stat.S_ISLNK(st.st_mode):
        return f"its {what} {path} is a symbolic link"
    if st.st_uid != os.getuid():
        return f"its {what} {path} belongs to another user (uid {st.st_uid})"
    return None


def read_marker(folder: Path) -> tuple[dict[str, Any] | None, str]:
    """``folder``'s run-identity file, if this user wrote it for this folder: (its fields, "")
    or (None, why not)."""
    folder = folder.resolve()
    why = _owned(folder, "folder") or _owned(folder / MARKER, f"run-identity file {MARKER}")
    if why is not None:
        return None, why
    try:
        marker = json.loads((folder / MARKER).read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        return None, f"its {MARKER} cannot be read ({type(e).__name__})"
    if not isinstance(marker, dict) or marker.get("folder") != str(folder):
        return None, f"its {MARKER} was written for another folder"
    return marker, ""


def resumable_folder(folder: Path, run_id: str, digest: str) -> str | None:
    """Why run ``run_id`` of config ``digest`` may not be continued in ``folder`` (the folder
    its MLflow run names), or None when it may: the folder and its run-identity file are this
    user's, written for that run and config; ``checkpoints/last.ckpt`` is this user's, carries
    the same identity (``RunIdentity``), and the best checkpoint it names lies in that
    folder's ``checkpoints``."""
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
    why = _owned(ckpts, "checkpoint folder") or _owned(last, f"checkpoint {LAST}")
    if why is not None:
        return why
    try:  # tensors and plain containers only: a checkpoint is never code to run
        ckpt = torch.load(last, map_location="cpu", weights_only=True)
    except Exception as e:
        return f"its checkpoint {last} cannot be read ({type(e).__name__})"
    if not isinstance(ckpt, dict) or ckpt.get(IDENTITY_KEY) != {"run_id": run_id,
                                                                   "config_hash": digest}:
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
                   field: str = "output_dir", finished_ok: bool = False) -> str | None:
    """Why a training may not start afresh in ``folder``, or None when it may.

    It may when the folder is missing or holds nothing but :data:`HYDRA_RECORD`, or (with
    ``resume=true``) when it is an unfinished run of the same config (``digest``; None: any)
    that this user created there: that run is replaced, as ``resume=true`` replaces a killed
    run. ``finished_ok``: a finished run of that config there passes too (``resume=true``
    reuses it rather than train). Anything else is another run's or another program's files,
    which a typo or a copied command would otherwise delete or overwrite (``best.ckpt``,
    ``evaluation.csv``)."""
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
    same = marker is not None and (digest is None or marker.get("config_hash") == digest)
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
