"""Config hash version 1, and the one-time migration of a tracking store's runs to version 2.

Version 1 of :func:`lbo.learn.identity.config_hash` replayed every older layout of the
training config at each call (:func:`hash_v1`), so that a run stored before a change kept its
hash: settings added later hashed as absent at their old value (:data:`LATER_DEFAULTS`), the
``car`` and ``sensors`` groups as the one ``truth`` group they were, the model's own settings
back at the top, lbo's classes without their layer, the epoch bar as Lightning's. Version 2
hashes today's layout only. A store's runs are brought to it once (:func:`migrate_experiment`):
the config each run logged (its ``config.yaml`` artifact, written by every lbo training since
the first) is read as data, brought to today's layout (:func:`upgraded`) and checked against
the hash the run carries (:func:`hash_v1`); the run is then tagged with its version-2 hash
(``config_hash``), the old one (``config_hash_v1``) and ``hash_version``, and its folder's
run-identity file, where it is this user's, rewritten to match. A run whose stored config does
not give its tag is left as it was, with a line saying why.

Nothing read from a store or a file is run: a config is YAML read as data, never instantiated,
and the layer of an old class name is found in its module's source text, not by importing it.

    python -m lbo.learn.migrate [<tracking uri>]   # every experiment's runs (default: lbo's)
"""

from __future__ import annotations

import ast
import copy
import hashlib
import sys
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException

from lbo.core import LAYERS
from lbo.core.cli import MODEL_SHORT
from lbo.core.errors import LboError
from lbo.learn.identity import HASH_VERSION, config_hash, read_marker, write_marker
from lbo.logs.sets import is_logs

V1_TAG = "config_hash_v1"
"""The run tag (and run-identity field) that keeps a migrated run's version-1 hash."""
MIGRATED = "lbo.hash_version"
"""The experiment tag set once every run of the experiment carries the current hash version:
``resume=true`` then looks no further (one look at the experiment it fetches anyway)."""
MAX_CONFIG = 1 << 20
"""The largest ``config.yaml`` (bytes) a migration reads: a config is a few kB."""

# --- version 1 -----------------------------------------------------------------------------

LATER_DEFAULTS: dict[str, Any] = {"model.normalisation": "standard", "receiver": None,
                  "receiver_training": {"heading_share": 0.25, "gyro_share": 0.75},
                  "model.gyro": False, "tbptt": None,
                  "sequence_length": None, "nll": 0.0, "train_noise.changes": 0,
                  "loss": "truth", "data.source": "files",
                  "train_outages": {"share": 0.0, "max_s": 10.0}}
"""Settings added after runs were stored (a dotted key: one inside a group), with the value
those runs had: version 1 hashed a config holding that value as if it did not have the key."""
LATER_MODEL_DEFAULTS: dict[str, dict[str, Any]] = {
    **{name: {"body": "kinematic", "body_lr": 1.0} for name in ("kalmannet", "split_kalmannet")},
    "filternet": {"empty_statistic": "net", "drift_tau": None},
    "gyro_ekf": {"drift": False, "scales": False}}
"""As :data:`LATER_DEFAULTS`, for the settings added to one model's config (``model.body`` of
the KalmanNet peers, which the robust observer's config has had from the start, and its
``model.empty_statistic`` and ``model.drift_tau``; the gyro EKF's ``model.drift`` and
``model.scales``)."""
WAS = {"lbo.learn.progress.EpochBar": "lightning.pytorch.callbacks.TQDMProgressBar"}
"""Callbacks that replaced another in ``conf/``, by what they replaced (version 1 hashed them
as it)."""
BAR_REFRESH_V1 = 20
"""The progress bar's refresh rate version 1 hashed every config with."""


def hash_v1(cfg: DictConfig) -> str:
    """The version-1 config hash of ``cfg``, as lbo computed it before version 2 (the hash a
    run stored before carries in its ``config_hash`` tag)."""
    c = cfg.copy()
    with open_dict(c):
        c.output_dir, c.data.root, c.resume, c.data_dir = "-", "-", False, None
        for key in ("logger", "paths", "threads", "compile", "keep_onnx", "verbose"):
            c.pop(key, None)
        bar = OmegaConf.select(c, "callbacks.progress_bar")
        if isinstance(bar, DictConfig) and bar.get("_target_") in WAS:
            bar["_target_"] = WAS[bar["_target_"]]
        if isinstance(bar, DictConfig) and "refresh_rate" in bar:
            bar["refresh_rate"] = BAR_REFRESH_V1
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
    text = OmegaConf.to_yaml(OmegaConf.create(as_before_groups_moved(
        unlayered(OmegaConf.to_container(c, resolve=True)))))
    if is_logs(cfg):
        from lbo.learn.builders import logs_spec

        text += f"\nlogs: {logs_spec(cfg).digest}"
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def as_before_groups_moved(tree: dict[str, Any]) -> dict[str, Any]:
    """``tree`` (a resolved training config) in the layout it had before its groups moved, in
    the same key order, as version 1 hashed it:

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


def unlayered(node: Any) -> Any:
    """``node`` with every lbo ``_target_`` written without its layer (``lbo.learn.callbacks.X``
    -> ``lbo.callbacks.X``), as it was before lbo's modules moved into layers."""
    if isinstance(node, dict):
        out = {k: unlayered(v) for k, v in node.items()}
        target = out.get("_target_")
        if isinstance(target, str) and target.startswith("lbo."):
            parts = target.split(".")
            if len(parts) > 3 and parts[1] in LAYERS:
                out["_target_"] = ".".join([parts[0], *parts[2:]])
        return out
    if isinstance(node, list):
        return [unlayered(v) for v in node]
    return node


# --- an old layout brought to today's ----------------------------------------------------------

CAR_KEYS = ("name", "mass", "yaw_inertia", "l_f", "l_r", "c_f", "c_r", "mu", "v_kinematic",
            "substeps", "process_scale")
"""The keys of the ``truth`` group that went to ``car`` when it was split (``conf/car/``)."""
SENSOR_KEYS = ("gnss_sigma", "gnss_tau", "steering_offset", "speed_scale")
"""... and those that went to ``sensors`` (``conf/sensors/``)."""
FILLED_WHERE = {"model.gyro": ("model.name", "filternet"), "data.source": ("data.kind", "logs")}
"""The settings of :data:`LATER_DEFAULTS` that today's config holds only where another has a
value: ``model.gyro`` the window filter's, ``data.source`` a user's logs'."""
NOT_FILLED = ("receiver",)
"""... and those it never holds at their old value: ``receiver`` is a group, absent (not
null) when none is chosen."""
SRC = Path(__file__).resolve().parents[1]
"""lbo's source folder, where the module of an old class name is looked for."""


def upgraded(cfg: DictConfig) -> DictConfig:
    """``cfg`` (a training config as a run stored it, resolved, in any older layout) in
    today's layout: lbo's classes in their layer, the epoch bar for Lightning's, ``truth``
    split into ``car`` and ``sensors``, the model's own settings under ``model``, the settings
    added later at the value the run had (:data:`LATER_DEFAULTS`), and the paths under the
    run's output folder written as under ``-`` (what the hash resolves ``output_dir`` to).
    Keys keep their order, as :func:`hash_v1` reads it. An LboError says why it cannot be."""
    tree = _layered(OmegaConf.to_container(cfg, resolve=False))
    bar = (tree.get("callbacks") or {}).get("progress_bar")
    if isinstance(bar, dict) and bar.get("_target_") in WAS.values():
        bar["_target_"] = next(k for k, v in WAS.items() if v == bar["_target_"])
    tree = _car_and_sensors(tree)
    _model_keys(tree)
    _fill_later(tree)
    folder = tree.get("output_dir")
    if isinstance(folder, str) and folder.strip("/.") and "$" not in folder:
        tree = _blank_folder(tree, folder.rstrip("/"))
    return OmegaConf.create(tree)


def _layered(node: Any) -> Any:
    """``node`` with every lbo ``_target_`` written without a layer given the one layer whose
    module of that name defines it (read as text, not imported)."""
    if isinstance(node, dict):
        out = {k: _layered(v) for k, v in node.items()}
        target = out.get("_target_")
        parts = target.split(".") if isinstance(target, str) else []
        if len(parts) > 2 and parts[0] == "lbo" and parts[1] not in LAYERS:
            found = [layer for layer in LAYERS if _defines(SRC / layer, parts[1:-1], parts[-1])]
            if len(found) != 1:
                raise LboError(f"_target_: {target}: {len(found)} layers of lbo define it, "
                               "not one")
            out["_target_"] = ".".join(["lbo", found[0], *parts[1:]])
        return out
    if isinstance(node, list):
        return [_layered(v) for v in node]
    return node


def _defines(folder: Path, module: list[str], name: str) -> bool:
    """Whether module ``module`` (its path's parts) under ``folder`` defines class or function
    ``name`` at its top, read from its source."""
    path = folder.joinpath(*module)
    path = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
    try:
        body = ast.parse(path.read_text()).body
    except (OSError, SyntaxError, ValueError):
        return False
    return any(isinstance(n, (ast.ClassDef, ast.FunctionDef)) and n.name == name for n in body)


def _car_and_sensors(tree: dict[str, Any]) -> dict[str, Any]:
    """``tree`` with a ``truth`` group as the ``car`` and ``sensors`` groups it was split
    into, where it stood."""
    truth = tree.get("truth")
    if not isinstance(truth, dict) or "car" in tree:
        return tree
    stray = [k for k in truth if k not in CAR_KEYS + SENSOR_KEYS]
    if stray:
        raise LboError(f"truth.{stray[0]}: neither the car's setting nor the sensors'")
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if key == "truth":
            out["car"] = {k: v for k, v in truth.items() if k in CAR_KEYS}
            out["sensors"] = {k: v for k, v in truth.items() if k in SENSOR_KEYS}
        else:
            out[key] = value
    return out


def _model_keys(tree: dict[str, Any]) -> None:
    """Move the model's own settings (``window``, ``features``, ``normalisation``) from the
    top of ``tree`` under ``model``, first, as today's config holds them."""
    model = tree.get("model")
    top = [k for k in MODEL_SHORT if k in tree]
    if not top or not isinstance(model, dict):
        return
    if any(k in model for k in top):
        raise LboError(f"{top[0]}: both at the top and under model")
    tree["model"] = {**{k: tree.pop(k) for k in top}, **model}


def _fill_later(tree: dict[str, Any]) -> None:
    """Add each setting added after the run was stored (:data:`LATER_DEFAULTS`,
    :data:`LATER_MODEL_DEFAULTS`) where today's config holds it and the run's does not, at
    the value the run had."""
    def at(path: list[str]) -> Any:  # the node itself, to add to
        node: Any = tree
        for part in path:
            node = node.get(part) if isinstance(node, dict) else None
        return node

    for key, default in LATER_DEFAULTS.items():
        *group, name = key.split(".")
        node = at(group)
        where = FILLED_WHERE.get(key)
        if isinstance(node, dict) and name not in node and key not in NOT_FILLED and (
                where is None or at(where[0].split(".")) == where[1]):
            node[name] = copy.deepcopy(default)
    model = tree.get("model")
    if isinstance(model, dict):
        for name, default in LATER_MODEL_DEFAULTS.get(str(model.get("name")), {}).items():
            model.setdefault(name, copy.deepcopy(default))


def _blank_folder(node: Any, folder: str) -> Any:
    """``node`` with ``folder`` (the run's output folder, which the stored config holds
    resolved) as ``-`` wherever a value is it or under it (``<folder>/checkpoints``)."""
    if isinstance(node, dict):
        return {k: _blank_folder(v, folder) for k, v in node.items()}
    if isinstance(node, list):
        return [_blank_folder(v, folder) for v in node]
    if isinstance(node, str) and (node == folder or node.startswith(folder + "/")):
        return "-" + node[len(folder):]
    return node


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
        client.set_experiment_tag(exp.experiment_id, MIGRATED, str(HASH_VERSION))
    if done or left:
        print(f"migrated {done} run{'s' * (done != 1)} of {exp.name} to config hash version "
              f"{HASH_VERSION}" + (f" ({left} left as they were)" if left else ""))
    return done


def _unmigrated(client: Any, experiment_id: str) -> Iterator[Any]:
    """The active runs of the experiment with a ``config_hash`` tag and no ``hash_version``,
    page by page."""
    token = None
    while True:
        page = client.search_runs([experiment_id], max_results=1000, page_token=token)
        yield from (r for r in page if "config_hash" in r.data.tags
                    and "hash_version" not in r.data.tags)
        token = page.token
        if not token:
            return


def migrate_run(client: Any, run: Any) -> str | None:
    """Tag ``run`` (carrying a version-1 ``config_hash``) with its version-2 hash, worked out
    from the config it logged, and rewrite its folder's run-identity file where that is this
    user's and names the run; or say why not (and change nothing)."""
    from mlflow.entities import RunTag
    from mlflow.exceptions import MlflowException

    old = run.data.tags["config_hash"]
    try:
        stored = _stored_config(client, run.info.run_id)
        if stored is None:
            return "it logged no config.yaml"
        cfg = upgraded(stored)
        v1 = hash_v1(cfg)
        if v1 != old:
            return f"its config.yaml hashes as {v1}, not as its tag {old}"
        new = config_hash(cfg)
    except LboError as e:
        return str(e)
    except (OSError, ValueError, OmegaConfBaseException, MlflowException) as e:
        return f"its config.yaml cannot be read ({type(e).__name__})"
    folder = run.data.params.get("output_dir")
    marker, _ = read_marker(Path(folder)) if folder else (None, "")
    if marker is not None and marker.get("run_id") == run.info.run_id and (
            marker.get("config_hash") == old or marker.get(V1_TAG) == old):
        write_marker(Path(folder), run.info.run_id, new, bool(marker.get("finished")), was=old)
    client.log_batch(run.info.run_id, tags=[RunTag("config_hash", new), RunTag(V1_TAG, old),
                                            RunTag("hash_version", str(HASH_VERSION))])
    return None


def _stored_config(client: Any, run_id: str) -> DictConfig | None:
    """The ``config.yaml`` artifact of run ``run_id``, read as data only (a YAML mapping: the
    safe loader, under OmegaConf's float rules), or None without one."""
    logged = {a.path: a for a in client.list_artifacts(run_id)}
    if "config.yaml" not in logged:
        return None
    if (logged["config.yaml"].file_size or 0) > MAX_CONFIG:
        raise LboError(f"its config.yaml is over {MAX_CONFIG} bytes")
    with tempfile.TemporaryDirectory() as tmp:
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
    ``digest``, the hash of ``cfg``) by its version-1 hash, which someone else's migration of
    a shared store could not: where the file names the run, and ``cfg``'s own version-1 hash
    is the one it holds (so the store's word is not taken for it)."""
    v1 = None
    for run in runs:
        was, folder = run.data.tags.get(V1_TAG), run.data.params.get("output_dir")
        marker, _ = read_marker(Path(folder)) if was and folder else (None, "")
        if marker is None or marker.get("run_id") != run.info.run_id or \
                marker.get("config_hash") != was:
            continue
        v1 = v1 or hash_v1(cfg)
        if v1 == was:
            write_marker(Path(folder), run.info.run_id, digest, bool(marker.get("finished")),
                         was=was)


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
