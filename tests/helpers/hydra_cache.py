"""Hydra's config files read, and each shape of command line built, once per test run, not
once per compose.

The tests compose about 1,600 configs in-process (:func:`helpers.compose_cfg`, and the commands
they run through Hydra's main), and each compose re-reads and re-parses every YAML file of
``conf/`` it uses (``FileConfigSource.load_config`` -> ``OmegaConf.load`` -> PyYAML): about
40% of a compose, for files that do not change while the tests run. Hydra's own
``CachingConfigRepository`` caches only within one compose.

:func:`install` (``tests/conftest.py``, for the whole session) wraps
``FileConfigSource.load_config`` so that it keeps what Hydra read from each file (its config and
``# @package`` header), keyed by the file's real path, ``st_mtime_ns`` and ``st_size``: a file
a test writes or changes is read afresh. Each call returns a copy, as Hydra mutates what it is
given (it pops ``defaults``, merges into the config): the config is kept pickled and each copy
unpickled, nine times faster than ``copy.deepcopy`` of an OmegaConf config, which walks every
node in Python (0.52 against 4.63 ms for ``experiment=smoke``'s: docs/design.md, "Measured on
2026-12-03, night"), and faster than ``OmegaConf.create`` from the parsed YAML. A missing
file, or one that does not parse, is Hydra's own read, which raises what it always raised;
failures are not kept.
:func:`uninstall` puts Hydra's methods back.

The class patched is the one Hydra's ``SourcesRegistry`` resolves ``file://`` to, not the one
``from hydra._internal.core_plugins.file_config_source import FileConfigSource`` gives: Hydra's
plugin scan (on its first compose) executes that module again and registers the class made then.

It also keeps what Hydra builds from those files for each shape of command line: the defaults
list (``create_defaults_list``) and the configs merged along it
(``ConfigLoaderImpl._compose_config_from_defaults_list``): most of what a compose costs once
the files are kept (``benchmarks/compose_cache.py``: 97-110 ms a compose, 17-21 ms with the
builds kept). Neither reads the overrides that set values (``data.root=...``, ``seed=3``):
Hydra applies those to a copy of the merged config afterwards, as it always does. So the key is
the config's name, the config sources, and the overrides Hydra reads as group choices (told
apart from values exactly as ``defaults_list.Overrides`` tells them: a dict, or a key that is
no config group, is a value); a command line with other values takes the kept list and a copy
of the kept config. The files the first build read (the primary config included) are checked
unchanged before the kept build is used, as above.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pickle
from collections.abc import Callable
from typing import Any

from hydra._internal import config_loader_impl
from hydra._internal.config_loader_impl import ConfigLoaderImpl
from hydra._internal.defaults_list import DefaultsList
from hydra._internal.sources_registry import SourcesRegistry
from hydra.core.override_parser.types import Override
from hydra.core.plugins import Plugins
from hydra.plugins.config_source import ConfigResult

LoadConfig = Callable[[Any, str], ConfigResult]

_wrapped: dict[tuple[Any, str], Callable[..., Any]] = {}
"""(owner, name) -> Hydra's own, for each function or method :func:`install` wrapped."""

FileKey = tuple[str, int, int]
"""A version of a file: its real path, ``st_mtime_ns`` and ``st_size``."""

_read: dict[FileKey, tuple[dict[str, str | None], bytes]] = {}
"""A file's version -> the header and config (:func:`_kept`) Hydra read from it."""


def _kept(config: Any) -> bytes:
    """An OmegaConf config as the caches keep it: pickled, so that :func:`_copy` is cheap."""
    return pickle.dumps(config, protocol=pickle.HIGHEST_PROTOCOL)


def _copy(kept: bytes) -> Any:
    """A new config from what :func:`_kept` made, shared with no other copy."""
    return pickle.loads(kept)


_reading: list[set[FileKey]] = []
"""The file versions read by the compose under way (one set per ``_load_configuration_impl``
entered): what a kept build depends on."""


@dataclasses.dataclass
class _Built:
    """What Hydra built for one shape of command line."""

    files: frozenset[FileKey]
    defaults: DefaultsList
    merged: bytes | None = None  # the config merged along the defaults (:func:`_kept`), before
    # any value is set
    merged_once: bool = False  # the merge is kept from its second time on


_built: dict[tuple[Any, ...], _Built] = {}
"""shape of a command line (see the module's docstring) -> what Hydra built for it."""

_by_list: dict[int, _Built] = {}
"""id of a kept defaults list -> its build (kept builds hold their lists, so ids are unique)."""


def _key(path: str) -> FileKey:
    st = os.stat(path)
    return path, st.st_mtime_ns, st.st_size


def _unchanged(key: FileKey) -> bool:
    try:
        return _key(key[0]) == key
    except OSError:
        return False


def _caching(hydras: LoadConfig) -> LoadConfig:
    """``FileConfigSource.load_config`` that reads each version of a file once, through
    Hydra's own (``hydras``)."""

    def load_config(self: Any, config_path: str) -> ConfigResult:
        path = os.path.realpath(os.path.join(self.path, self._normalize_file_name(config_path)))
        try:
            key = _key(path)
        except OSError:  # missing: Hydra raises its ConfigLoadError
            return hydras(self, config_path)
        if _reading:
            _reading[-1].add(key)
        kept = _read.get(key)
        if kept is None:
            loaded = hydras(self, config_path)  # raises as it did; nothing kept then
            with contextlib.suppress(OSError):
                if _key(path) == key:  # not changed while Hydra read it
                    _read[key] = (dict(loaded.header), _kept(loaded.config))
            return loaded
        header, config = kept
        return ConfigResult(config=_copy(config), header=dict(header),
                            path=f"{self.scheme()}://{self.path}", provider=self.provider)

    return load_config


def _recording(hydras: Callable[..., Any]) -> Callable[..., Any]:
    """``ConfigLoaderImpl._load_configuration_impl`` noting the files its compose reads."""

    def load_configuration_impl(self: Any, *args: Any, **kwargs: Any) -> Any:
        _reading.append(set())
        try:
            return hydras(self, *args, **kwargs)
        finally:
            _reading.pop()

    return load_configuration_impl


def _values(repo: Any, overrides: list[Override]) -> list[Override]:
    """The overrides Hydra applies as values, in their order: as ``defaults_list.Overrides``
    sorts them (sweeps are neither: the launcher expands them)."""
    return [o for o in overrides if not o.is_sweep_override()
            and (isinstance(o.value(), dict) or not repo.group_exists(o.key_or_group))]


def _defaults_kept(hydras: Callable[..., DefaultsList]) -> Callable[..., DefaultsList]:
    """``create_defaults_list`` that builds each shape of command line once."""

    def create_defaults_list(repo: Any, config_name: str | None, overrides_list: list[Override],
                             prepend_hydra: bool, skip_missing: bool) -> DefaultsList:
        def build() -> DefaultsList:
            return hydras(repo=repo, config_name=config_name, overrides_list=overrides_list,
                          prepend_hydra=prepend_hydra, skip_missing=skip_missing)

        if not _reading:  # not inside a compose (``--info defaults``): Hydra's own
            return build()
        values = _values(repo, overrides_list)
        set_values = {id(o) for o in values}
        chosen = tuple(o.input_line for o in overrides_list if id(o) not in set_values)
        shape = (config_name, chosen, prepend_hydra, skip_missing,
                 tuple((s.scheme(), s.path) for s in repo.get_sources()))
        kept = _built.get(shape)
        if kept is not None and all(_unchanged(f) for f in kept.files):
            return dataclasses.replace(kept.defaults, config_overrides=values)
        built = build()
        if [id(o) for o in built.config_overrides] == [id(o) for o in values]:
            if kept is not None:
                _by_list.pop(id(kept.defaults.defaults), None)
            _built[shape] = _by_list[id(built.defaults)] = _Built(frozenset(_reading[-1]), built)
        return built

    return create_defaults_list


def _merged_kept(hydras: Callable[..., Any]) -> Callable[..., Any]:
    """``ConfigLoaderImpl._compose_config_from_defaults_list`` that keeps the merge of a kept
    defaults list once it is asked for twice and gives a copy each time after (Hydra then sets
    values in what it is given)."""

    def compose_config_from_defaults_list(self: Any, defaults: list[Any], repo: Any) -> Any:
        kept = _by_list.get(id(defaults))
        if kept is None or kept.defaults.defaults is not defaults:
            return hydras(self, defaults, repo)
        if kept.merged is None:
            merged = hydras(self, defaults, repo)
            if kept.merged_once:  # most shapes are merged once: no copy for those
                kept.merged = _kept(merged)
            kept.merged_once = True
            return merged
        return _copy(kept.merged)

    return compose_config_from_defaults_list


_BUILDS: tuple[tuple[Any, str, Callable[[Any], Any]], ...] = (
    (ConfigLoaderImpl, "_load_configuration_impl", _recording),
    (config_loader_impl, "create_defaults_list", _defaults_kept),
    (ConfigLoaderImpl, "_compose_config_from_defaults_list", _merged_kept),
)
"""(owner, name, wrapper) of what :func:`install` wraps to keep the builds."""


def install(builds: bool = True) -> None:
    """Hydra's file configs read once per version of each file, and (``builds``) each shape of
    command line built once, from now on."""
    Plugins.instance()  # Hydra's plugin scan, which makes the class it uses
    files: Any = SourcesRegistry.instance().resolve("file")
    for owner, name, wrap in ((files, "load_config", _caching), *(_BUILDS if builds else ())):
        if (owner, name) not in _wrapped:
            _wrapped[owner, name] = getattr(owner, name)
            setattr(owner, name, wrap(_wrapped[owner, name]))


def uninstall() -> None:
    """Hydra's own functions back, and what was read and built dropped."""
    while _wrapped:
        (owner, name), hydras = _wrapped.popitem()
        setattr(owner, name, hydras)
    _read.clear()
    _built.clear()
    _by_list.clear()
