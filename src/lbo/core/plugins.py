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

A name two distributions register is resolved by one rule, for every kind, in
:func:`_resolve` (the one lookup path): lbo's own names (:data:`OWN`) always belong to lbo,
and another distribution's entry point of one of them is ignored, with a one-line warning
naming it when that name is used; a name two other distributions register is refused in one
line naming both, when that name is used (nothing of either is imported). The same
distribution seen twice (an editable install found through two ``sys.path`` entries) is one.
"""

from __future__ import annotations

import re
import shlex
import sys
from functools import cache
from importlib import metadata
from typing import Any

from lbo.core.errors import LboError

GROUPS = {"model": "lbo.models", "observer": "lbo.observers", "truth": "lbo.truths"}
"""The entry-point group of each kind of part."""
FIELDS = {"model": "model.name", "observer": "observer", "truth": "car.name"}
"""The setting that names a part of each kind, for errors raised outside :func:`load`."""
OWN = {"model": ("cnn", "lstm", "filternet", "kalmannet", "split_kalmannet"),
       "observer": ("ekf", "adaptive", "ukf", "gyro"),
       "truth": ("kinematic", "dynamic")}
"""lbo's own parts of each kind (registered in its pyproject.toml): without them the
installation is stale, which is said as such."""
NAME = re.compile(r"[a-z][a-z0-9_]*")
"""A part's name: lower case, digits and underscores, starting with a letter."""
PACKAGE = re.compile(r"[A-Z0-9]|[A-Z0-9][A-Z0-9._-]*[A-Z0-9]", re.IGNORECASE)
"""A distribution's name (PEP 508): what a checkpoint's recorded provider must be before it
is put in a ``pip install`` line."""
VERSION = re.compile(r"[A-Za-z0-9][A-Za-z0-9.+!_-]{0,63}")
"""A recorded version worth repeating (PEP 440's characters); any other is left out."""
LBO = "lbo"
"""lbo's own distribution (normalised name)."""

_warned: set[tuple[str, str]] = set()
"""The (group, name) pairs whose ignored entry points were already said (once a process)."""


def _group(kind: str) -> str:
    if kind not in GROUPS:
        raise LboError(f"plug-in kind {kind!r}: expected one of {', '.join(GROUPS)}")
    return GROUPS[kind]


def _distribution(ep: metadata.EntryPoint) -> str:
    """The normalised name (PEP 503) of the distribution that registers ``ep``; "" if none."""
    dist = getattr(ep, "dist", None)
    return "" if dist is None else re.sub(r"[-_.]+", "-", str(dist.metadata["Name"])).lower()


def _shown(ep: metadata.EntryPoint) -> str:
    """``lbo-plugin-example 0.1.0 (lbo_plugin_example.gru:WindowGRU)``: who registers ``ep``."""
    dist = getattr(ep, "dist", None)
    who = ("a package without metadata" if dist is None
           else f"{dist.metadata['Name']} {dist.version}")
    return f"{who} ({ep.value})"


@cache
def _entry_points(group: str) -> dict[str, tuple[metadata.EntryPoint, ...]]:
    """The installed entry points of ``group`` by name, one for each distribution that
    registers it, in the order they are found (read once per process: the set of installed
    packages does not change under a running command). A distribution found twice (two
    ``sys.path`` entries) counts once: its first, the one Python imports."""
    found: dict[str, dict[str, metadata.EntryPoint]] = {}
    for ep in metadata.entry_points(group=group):
        found.setdefault(ep.name, {}).setdefault(_distribution(ep), ep)
    return {name: tuple(by_dist.values()) for name, by_dist in found.items()}


def _stale(kind: str) -> LboError:
    return LboError(f"lbo's own {kind}s are not registered (entry-point group "
                    f"{GROUPS[kind]}): the installation is stale; reinstall lbo "
                    "(make install, or pip install -e .)")


def _resolve(kind: str, name: str, field: str) -> metadata.EntryPoint | None:
    """The entry point ``name`` of ``kind`` resolves to (None: none registers it).

    lbo's own name: lbo's entry point, and any other distribution's is ignored, said once a
    process in one line on stderr. Another name that two distributions register: LboError
    naming both. Nothing is imported here."""
    group = _group(kind)
    claims = _entry_points(group).get(name, ())
    if name in OWN[kind]:
        own = [ep for ep in claims if _distribution(ep) == LBO]
        if not own:
            raise _stale(kind)
        others = [ep for ep in claims if _distribution(ep) != LBO]
        if others and (group, name) not in _warned:
            _warned.add((group, name))
            print(f"warning: {field}: {kind} {name!r} is lbo's own; the entry point of "
                  f"{' and '.join(_shown(ep) for ep in others)} registered under that name "
                  f"in {group} is ignored (lbo's own names always belong to lbo; rename it "
                  "there)", file=sys.stderr, flush=True)
        return own[0]
    if len(claims) > 1:
        shown = ", ".join(_shown(ep) for ep in claims[:-1]) + f" and {_shown(claims[-1])}"
        raise LboError(f"{field}: {kind} {name!r} is registered by {len(claims)} packages, "
                       f"{shown}, under the entry-point group {group}; uninstall all but one "
                       "(none of them was imported)")
    return claims[0] if claims else None


def names(kind: str) -> tuple[str, ...]:
    """The registered names of ``kind``, lbo's own first, then the others sorted."""
    found = _entry_points(_group(kind))
    own = [n for n in OWN[kind] if any(_distribution(ep) == LBO for ep in found.get(n, ()))]
    if len(own) < len(OWN[kind]):
        raise _stale(kind)
    return (*own, *sorted(n for n in found if n not in OWN[kind]))


def provider(kind: str, name: str) -> dict[str, str]:
    """``{"package": ..., "version": ...}`` of the installed distribution that registers
    ``name`` (what a checkpoint records, so that a missing part's error can say what to
    install); empty where the entry point has no distribution."""
    ep = _resolve(kind, name, FIELDS[kind])
    dist = getattr(ep, "dist", None)
    if dist is None:
        return {}
    return {"package": str(dist.metadata["Name"]), "version": str(dist.version)}


def _install_hint(recorded: Any, group: str) -> str:
    """What to install for a part that is not installed, from the provider a checkpoint
    recorded. The recorded name is data read from a file: it is put in a ``pip install``
    line only if it is a distribution's name (PEP 508), and quoted even then."""
    got = recorded if isinstance(recorded, dict) else {}
    package, version = got.get("package"), got.get("version")
    anywhere = f"install the package that registers it under the entry-point group {group}"
    if not package:
        return anywhere
    if not (isinstance(package, str) and PACKAGE.fullmatch(package)):
        shown = repr(package[:80] if isinstance(package, str) else package)[:100]
        return f"the provider its file records, {shown}, is not a package name; {anywhere}"
    if isinstance(version, str) and VERSION.fullmatch(version):
        return f"it was provided by {package} {version}: pip install {shlex.quote(package)}"
    return f"it was provided by {package}: pip install {shlex.quote(package)}"


def load(kind: str, name: Any, field: str, recorded: dict[str, Any] | None = None) -> Any:
    """The class registered as ``name`` for ``kind``, imported from its installed package.

    field : the setting named in errors (e.g. ``model.name``).
    recorded : the provider a checkpoint recorded (:func:`provider`), for the error when the
        name is not installed.

    Raises LboError, in one line, for a name that is not a part's name, one that no installed
    package registers (nothing is imported then), one that two packages other than lbo
    register (:func:`_resolve`; nothing imported either), or a registered part that fails to
    import.
    """
    group = _group(kind)
    known = names(kind)
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise LboError(f"{field}: expected the name of a registered {kind} ({', '.join(known)}),"
                       f" got {name!r}")
    ep = _resolve(kind, name, field)
    if ep is None:
        raise LboError(f"{field}: {kind} {name!r} is not installed "
                       f"({_install_hint(recorded, group)}); installed: {', '.join(known)}")
    try:
        return ep.load()
    except Exception as e:  # the plug-in's own import failed: say which, in one line
        raise LboError(f"{field}: {kind} {name!r} is registered ({ep.value}) but does not "
                       f"import: {type(e).__name__}: {e}") from None
