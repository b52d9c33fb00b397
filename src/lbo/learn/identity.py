"""A run's identity: the hash of what it computes, and the file in its folder that carries it.

A training run is known by :func:`config_hash` of its config: the same config, on the same
data, finds the same run (``resume=true``, ``make reproduce``). The hash is versioned
(:data:`HASH_VERSION`, the MLflow tag ``hash_version`` beside ``config_hash``): it hashes the
config in today's layout only, and a change that would give a stored run's config another hash
(a key added later, a group moved, a class renamed) goes with a version bump and a migration
step that rewrites the runs of a store once (:mod:`lbo.learn.migrate`), never with a table of
old layouts replayed at every hash. Version 1 did that (:func:`lbo.learn.layouts.hash_v1`);
its runs are migrated the first time ``resume=true`` searches their store.

A run's own folder, not the tracking store, says which run it holds (a store without
authentication lets anyone add a run with any hash and folder): :data:`MARKER`, written by the
user who trained, with the run id, the config hash and whether the run finished.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
from enum import Enum
from pathlib import Path
from typing import Any, cast

import yaml  # type: ignore[import-untyped]  # no stubs installed; OmegaConf dumps with it
from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf._utils import get_omega_conf_dumper

from lbo.core.atomic import write_text
from lbo.logs.sets import is_logs

HASH_VERSION = 4
"""The version of :func:`config_hash` a run is tagged with (``hash_version``). A change to
what the hash reads, or to the layout of the config it reads, bumps it, beside a migration
step in :mod:`lbo.learn.migrate` that brings the stored runs to it, and the older version's
hash of today's config in :data:`lbo.learn.layouts.OLDER_HASHES`. Version 3 added
``model.input_terms`` to the window filter's config, version 4 ``model.body_rear``."""


BAR_REFRESH = 20
"""The progress bar's refresh rate every config hashes as, whatever it draws at (``make
reproduce`` hides each run's bar)."""


NOT_COMPUTED = ("logger", "paths", "threads", "compile", "keep_onnx", "verbose")
"""Top-level settings that say where a run reads and writes (``logger``, ``paths``), how fast
it runs (``threads``; ``compile``, the same numbers to rounding), what ``lbo.observe`` finds
afterwards (``keep_onnx``) or what it prints (``verbose``): none is in the hash, so a run made
otherwise in these is reused."""


def config_hash(cfg: DictConfig) -> str:
    """Fingerprint (version :data:`HASH_VERSION`) of what a run computes: the resolved config,
    keys sorted, without where it writes (:func:`computed`); for ``data=logs``, also the
    digest of the logs' bytes (the same paths with other contents are other data)."""
    return tree_hash(computed(cfg), cfg)


def tree_hash(tree: dict[str, Any], cfg: DictConfig) -> str:
    """The hash of ``tree``, the config ``cfg`` as :func:`computed` gives it (or an older
    version's reading of it, :data:`lbo.learn.layouts.OLDER_HASHES`): its YAML, keys sorted,
    and for ``data=logs`` the digest of the logs' bytes."""
    text = yaml_text(tree)
    if is_logs(cfg):
        from lbo.learn.builders import logs_spec

        text += f"\nlogs: {logs_spec(cfg).digest}"
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def yaml_text(tree: dict[str, Any]) -> str:
    """``OmegaConf.to_yaml(OmegaConf.create(tree), sort_keys=True)`` of a plain ``tree`` (what
    :func:`computed` gives), without building the config, which took 40% of a
    :func:`config_hash`: OmegaConf's own YAML dumper (which quotes a string that reads as a
    number or a bool) on the tree itself. Enums are written by name and tuples as lists, as
    ``to_yaml`` writes them."""
    return yaml.dump(_enum_names(tree), Dumper=get_omega_conf_dumper(), default_flow_style=False,
                     allow_unicode=True, sort_keys=True)


def _enum_names(tree: Any) -> Any:
    if isinstance(tree, dict):
        return {k: _enum_names(v) for k, v in tree.items()}
    if isinstance(tree, list | tuple):
        return [_enum_names(v) for v in tree]
    return tree.name if isinstance(tree, Enum) else tree


def computed(cfg: DictConfig) -> dict[str, Any]:
    """``cfg`` resolved, as :func:`config_hash` reads it: its output folder, data root and
    data-set folder blanked (before the interpolations that name them resolve), ``resume``
    false, :data:`NOT_COMPUTED` left out and the bar's refresh rate :data:`BAR_REFRESH`."""
    c = cfg.copy()
    with open_dict(c):
        c.output_dir, c.data.root, c.resume, c.data_dir = "-", "-", False, None
        for key in NOT_COMPUTED:
            c.pop(key, None)
        bar = OmegaConf.select(c, "callbacks.progress_bar")
        if isinstance(bar, DictConfig) and "refresh_rate" in bar:
            bar["refresh_rate"] = BAR_REFRESH  # how often it draws (0: not at all), not what
    return cast(dict[str, Any], OmegaConf.to_container(c, resolve=True))


def run_tags(digest: str) -> dict[str, str]:
    """The MLflow tags a run is known by: its config hash ``digest`` and the hash's version."""
    return {"config_hash": digest, "hash_version": str(HASH_VERSION)}


MARKER = ".lbo-run.json"
"""The run-identity file a training writes into its output folder when it creates its run:
the MLflow run id, the config hash (and its version), the folder itself and whether the run
finished. Owned by the user who trained, it is what ``resume=true`` trusts, not the store."""


WAS_PREFIX = "config_hash_v"
"""The start of the run tags and run-identity fields that keep a migrated run's older hashes
(:func:`was_key`)."""


def was_key(version: int) -> str:
    """The run tag and run-identity field that keep a migrated run's hash of an older
    ``version``: ``config_hash_v<version>``."""
    return f"{WAS_PREFIX}{version}"


def older_hashes(fields: dict[str, Any]) -> dict[str, str]:
    """The older versions' hashes that a run's tags or run-identity file (``fields``) keep,
    by their key (:func:`was_key`)."""
    return {k: v for k, v in fields.items() if k.startswith(WAS_PREFIX)
            and k.removeprefix(WAS_PREFIX).isdigit() and isinstance(v, str)}


def write_marker(folder: Path, run_id: str | None, digest: str, finished: bool = False,
                 was: dict[str, str] | None = None) -> Path:
    """Write (atomically) ``folder``'s run-identity file (:data:`MARKER`). ``was``: the run's
    hashes of older versions by :func:`was_key`, which a checkpoint written before a migration
    still carries."""
    fields: dict[str, Any] = {"run_id": run_id, "config_hash": digest,
                              "hash_version": HASH_VERSION, **(was or {})}
    fields |= {"folder": str(folder.resolve()), "uid": os.getuid(), "finished": finished}
    return write_text(folder / MARKER, json.dumps(fields, indent=1) + "\n")


def owned(path: Path, what: str) -> str | None:
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
    why = owned(folder, "folder") or owned(folder / MARKER, f"run-identity file {MARKER}")
    if why is not None:
        return None, why
    try:
        marker = json.loads((folder / MARKER).read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        return None, f"its {MARKER} cannot be read ({type(e).__name__})"
    if not isinstance(marker, dict) or marker.get("folder") != str(folder):
        return None, f"its {MARKER} was written for another folder"
    return marker, ""
