"""Parts found by name among the installed packages: lbo's own and a user's, by one path.

A part is a class that lbo builds by name: a learned model (group ``lbo.models``), a
classical observer's stepper (group ``lbo.observers``) or a truth model, the car a simulated
log is drawn from (group ``lbo.truths``). A package offers one through a Python
entry point in its ``pyproject.toml``::

    [project.entry-points."lbo.models"]
    my_gru = "my_package.gru:WindowGRU"

and lbo's own parts are registered the same way (lbo's ``pyproject.toml``), so a config's
``model.name`` and a checkpoint's both go through :func:`load`. The contract a model keeps is
in docs/plugins.md.

Why entry points and not import paths: a checkpoint or an MLflow run names its part, and lbo
never imports a module that a file it loads names. A name is looked up among the entry
points of the installed packages only; a name no installed package registers is a one-line
error (naming the package that provided it when the checkpoint recorded one), and nothing
is imported.
"""

from __future__ import annotations

import re
from functools import cache
from importlib import metadata
from typing import Any

from lbo.core.errors import LboError

GROUPS = {"model": "lbo.models", "observer": "lbo.observers", "truth": "lbo.truths"}
"""The entry-point group of each kind of part."""
OWN = {"model": ("cnn", "lstm", "filternet", "kalmannet", "split_kalmannet"),
       "observer": ("ekf", "adaptive", "ukf", "gyro"),
       "truth": ("kinematic", "dynamic")}
"""lbo's own parts of each kind (registered in its pyproject.toml): without them the
installation is stale, which is said as such."""
NAME = re.compile(r"[a-z][a-z0-9_]*")
"""A part's name: lower case, digits and underscores, starting with a letter."""


def _group(kind: str) -> str:
    if kind not in GROUPS:
        raise LboError(f"plug-in kind {kind!r}: expected one of {', '.join(GROUPS)}")
    return GROUPS[kind]


@cache
def _entry_points(group: str) -> dict[str, metadata.EntryPoint]:
    """The installed entry points of ``group`` by name (read once per process: the set of
    installed packages does not change under a running command)."""
    return {ep.name: ep for ep in metadata.entry_points(group=group)}


def names(kind: str) -> tuple[str, ...]:
    """The registered names of ``kind``, lbo's own first, then the others sorted."""
    found = _entry_points(_group(kind))
    own = [n for n in OWN[kind] if n in found]
    if len(own) < len(OWN[kind]):
        raise LboError(f"lbo's own {kind}s are not registered (entry-point group "
                       f"{GROUPS[kind]}): the installation is stale; reinstall lbo "
                       "(make install, or pip install -e .)")
    return (*own, *sorted(n for n in found if n not in OWN[kind]))


def provider(kind: str, name: str) -> dict[str, str]:
    """``{"package": ..., "version": ...}`` of the installed distribution that registers
    ``name`` (what a checkpoint records, so that a missing part's error can say what to
    install); empty where the entry point has no distribution."""
    ep = _entry_points(_group(kind)).get(name)
    dist = getattr(ep, "dist", None)
    if dist is None:
        return {}
    return {"package": str(dist.metadata["Name"]), "version": str(dist.version)}


def load(kind: str, name: Any, field: str, recorded: dict[str, Any] | None = None) -> Any:
    """The class registered as ``name`` for ``kind``, imported from its installed package.

    field : the setting named in errors (e.g. ``model.name``).
    recorded : the provider a checkpoint recorded (:func:`provider`), for the error when the
        name is not installed.

    Raises LboError, in one line, for a name that is not a part's name, one that no installed
    package registers (nothing is imported then), or a registered part that fails to import.
    """
    group = _group(kind)
    known = names(kind)
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise LboError(f"{field}: expected the name of a registered {kind} ({', '.join(known)}),"
                       f" got {name!r}")
    if name not in known:
        got = recorded or {}
        hint = (f"it was provided by {got['package']} {got.get('version', '')}".rstrip()
                + f": pip install {got['package']}" if got.get("package") else
                f"install the package that registers it under the entry-point group {group}")
        raise LboError(f"{field}: {kind} {name!r} is not installed ({hint}); installed: "
                       f"{', '.join(known)}")
    ep = _entry_points(group)[name]
    try:
        return ep.load()
    except Exception as e:  # the plug-in's own import failed: say which, in one line
        raise LboError(f"{field}: {kind} {name!r} is registered ({ep.value}) but does not "
                       f"import: {type(e).__name__}: {e}") from None
