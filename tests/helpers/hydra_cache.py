"""Hydra's config files read once per test run, not once per compose.

The tests compose about 1,600 configs in-process (:func:`helpers.compose_cfg`, and the commands
they run through Hydra's main), and each compose re-reads and re-parses every YAML file of
``conf/`` it uses (``FileConfigSource.load_config`` -> ``OmegaConf.load`` -> PyYAML): about
40% of a compose, for files that do not change while the tests run. Hydra's own
``CachingConfigRepository`` caches only within one compose.

:func:`install` (``tests/conftest.py``, for the whole session) wraps
``FileConfigSource.load_config`` so that it keeps what Hydra read from each file (its config and
``# @package`` header), keyed by the file's real path, ``st_mtime_ns`` and ``st_size``: a file
a test writes or changes is read afresh. Each call returns a deep copy, as Hydra mutates what
it is given (it pops ``defaults``, merges into the config); a copy is faster than
``OmegaConf.create`` from the parsed YAML (measured). A missing file, or one that does not
parse, is Hydra's own read, which raises what it always raised; failures are not kept.
:func:`uninstall` puts Hydra's method back.

The class patched is the one Hydra's ``SourcesRegistry`` resolves ``file://`` to, not the one
``from hydra._internal.core_plugins.file_config_source import FileConfigSource`` gives: Hydra's
plugin scan (on its first compose) executes that module again and registers the class made then.
"""

from __future__ import annotations

import contextlib
import copy
import os
from collections.abc import Callable
from typing import Any

from hydra._internal.sources_registry import SourcesRegistry
from hydra.core.plugins import Plugins
from hydra.plugins.config_source import ConfigResult

LoadConfig = Callable[[Any, str], ConfigResult]

_patched: dict[Any, LoadConfig] = {}
"""The class patched -> Hydra's own ``load_config``."""

_read: dict[tuple[str, int, int], tuple[dict[str, str | None], Any]] = {}
"""(real path, mtime_ns, size) -> the header and config Hydra read from that file."""


def _key(path: str) -> tuple[str, int, int]:
    st = os.stat(path)
    return path, st.st_mtime_ns, st.st_size


def _caching(hydras: LoadConfig) -> LoadConfig:
    """``FileConfigSource.load_config`` that reads each version of a file once, through
    Hydra's own (``hydras``)."""

    def load_config(self: Any, config_path: str) -> ConfigResult:
        path = os.path.realpath(os.path.join(self.path, self._normalize_file_name(config_path)))
        try:
            key = _key(path)
        except OSError:  # missing: Hydra raises its ConfigLoadError
            return hydras(self, config_path)
        kept = _read.get(key)
        if kept is None:
            loaded = hydras(self, config_path)  # raises as it did; nothing kept then
            with contextlib.suppress(OSError):
                if _key(path) == key:  # not changed while Hydra read it
                    _read[key] = (dict(loaded.header), copy.deepcopy(loaded.config))
            return loaded
        header, config = kept
        return ConfigResult(config=copy.deepcopy(config), header=dict(header),
                            path=f"{self.scheme()}://{self.path}", provider=self.provider)

    return load_config


def install() -> None:
    """Hydra's file configs read once per version of each file, from now on."""
    Plugins.instance()  # Hydra's plugin scan, which makes the class it uses
    cls: Any = SourcesRegistry.instance().resolve("file")
    if cls not in _patched:
        _patched[cls] = cls.__dict__["load_config"]
        cls.load_config = _caching(_patched[cls])


def uninstall() -> None:
    """Hydra's own ``load_config`` back, and what was read dropped."""
    while _patched:
        cls, hydras = _patched.popitem()
        cls.load_config = hydras
    _read.clear()
