"""The older config hash versions, and a config a run stored in an older layout brought to
today's.

Version 1 of :func:`lbo.learn.identity.config_hash` replayed every older layout of the
training config at each call (:func:`hash_v1`), so that a run stored before a change kept its
hash: settings added later hashed as absent at their old value (:data:`LATER_DEFAULTS`), the
``car`` and ``sensors`` groups as the one ``truth`` group they were, the model's own settings
back at the top, lbo's classes without their layer, the epoch bar as Lightning's. Versions
2 on hash today's layout only; :func:`upgraded` brings a stored config to it, so that the
one-time migration of a store (:mod:`lbo.learn.migrate`) can check a run's older tag and give
it today's hash. Versions 2 on hashed today's layout less the settings added since, which
:func:`hash_before` leaves out at the value runs had (:data:`ADDED`). Nothing here runs what a
config names: the layer of an old class name is found in its module's source text, not by
importing it.
"""

from __future__ import annotations

import ast
import copy
import hashlib
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from lbo.core import LAYERS
from lbo.core.cli import MODEL_SHORT
from lbo.core.errors import LboError
from lbo.learn.identity import HASH_VERSION, computed, tree_hash
from lbo.logs.sets import is_logs

# --- version 1 -----------------------------------------------------------------------------

LATER_DEFAULTS: dict[str, Any] = {"model.normalisation": "standard", "receiver": None,
                  "receiver_training": {"heading_share": 0.25, "gyro_share": 0.75},
                  "model.gyro": False, "tbptt": None,
                  "sequence_length": None, "nll": 0.0, "train_noise.changes": 0,
                  "loss": "truth", "data.source": "files",
                  "train_outages": {"share": 0.0, "max_s": 10.0}}
"""Settings added after runs were stored (a dotted key: one inside a group), with the value
those runs had: version 1 hashed a config holding that value as if it did not have the key."""
ADDED: dict[int, dict[str, dict[str, Any]]] = {
    3: {"filternet": {"input_terms": False}},
    4: {name: {"body_rear": None} for name in ("filternet", "kalmannet", "split_kalmannet")}}
"""The settings added to a model's config with each version from 3 on, by the version and the
model's name, with the value the runs stored before had: an older version hashed today's
config without them (:func:`hash_before`), and version 1 too (:data:`LATER_MODEL_DEFAULTS`
holds them)."""


def added_after(version: int) -> dict[str, dict[str, Any]]:
    """The settings of :data:`ADDED` that versions after ``version`` added, by model name."""
    out: dict[str, dict[str, Any]] = {}
    for v, models in ADDED.items():
        if v > version:
            for name, settings in models.items():
                out.setdefault(name, {}).update(settings)
    return out


LATER_MODEL_DEFAULTS: dict[str, dict[str, Any]] = {
    **{name: {"body": "kinematic", "body_lr": 1.0, **added_after(2)[name]}
       for name in ("kalmannet", "split_kalmannet")},
    "filternet": {"empty_statistic": "net", "drift_tau": None, **added_after(2)["filternet"]},
    "gyro_ekf": {"drift": False, "scales": False, "receiver_noise": "learned", "hold": []}}
"""As :data:`LATER_DEFAULTS`, for the settings added to one model's config (``model.body`` of
the KalmanNet peers, which the robust observer's config has had from the start, and their
``model.body_rear``; the robust observer's ``model.empty_statistic``, ``model.drift_tau``,
``model.input_terms`` and ``model.body_rear``; the gyro EKF's ``model.drift``,
``model.scales``, ``model.receiver_noise`` and ``model.hold``)."""
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


# --- versions 2 on ---------------------------------------------------------------------------

def hash_before(version: int, cfg: DictConfig) -> str:
    """The config hash of ``cfg`` (today's layout) under ``version`` (2 or more): the hash a
    run stored under that version carries, where ``cfg`` holds the settings added since
    (:data:`ADDED`) at their old values (another value is a config no such run had, and
    hashes apart)."""
    tree = computed(cfg)
    model = tree.get("model")
    if isinstance(model, dict):
        for name, default in added_after(version).get(str(model.get("name")), {}).items():
            if name in model and model[name] == default:
                model.pop(name)
    return tree_hash(tree, cfg)


OLDER_HASHES: dict[int, Callable[[DictConfig], str]] = {
    1: hash_v1, **{v: partial(hash_before, v) for v in range(2, HASH_VERSION)}}
"""Each older version's hash of today's config, by version: what a run tagged with that
``hash_version`` (none: 1) carries, which its migration checks before it retags the run.
Versions 2 on are :func:`hash_before` theirs, so a new version adds only its settings to
:data:`ADDED`."""


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
