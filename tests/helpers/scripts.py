"""The repository's scripts (``benchmarks/*.py``) in the test's process: loaded as modules,
their ``main`` run with a command line, where a test is about what a script reads and
prints, not its process (an interpreter and lbo's imports saved a call)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import Any


def load_script(path: Path, monkeypatch: Any) -> ModuleType:
    """The script at ``path`` as a module ``<stem>_script`` (not a test module's name), in
    ``sys.modules`` (its dataclasses look their module up by name) and with its folder on
    ``sys.path`` (its imports of the scripts beside it), as ``python <path>`` would have them;
    both put back when the test ends."""
    monkeypatch.syspath_prepend(str(path.parent))
    name = f"{path.stem}_script"
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None, path
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, name, module)
    spec.loader.exec_module(module)
    return module


def run_script(path: Path, args: list[str], monkeypatch: Any, capsys: Any) -> str:
    """What ``python <path> <args>`` prints, its ``main`` run in this process (in the
    current folder and environment); an error fails the test (argparse's by SystemExit)."""
    module = load_script(path, monkeypatch)
    with monkeypatch.context() as mp:
        mp.setattr(sys, "argv", [str(path), *args])
        capsys.readouterr()
        module.main()
        return capsys.readouterr().out
