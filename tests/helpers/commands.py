"""lbo's commands run as a user runs them (``python -m lbo.<command>`` in a subprocess), and
their refusals read."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def cli(module: str, *args: str, env: dict[str, str] | None = None, cwd: Path | None = None,
        timeout: float = 600) -> subprocess.CompletedProcess:
    """``python -m <module> <args>``, its output captured; ``env`` is added to os.environ."""
    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True,
                          env={**os.environ, **(env or {})}, cwd=cwd, timeout=timeout)


def observe(*args: str, cwd: Path | None = None, timeout: float = 600,
            check: bool = False) -> subprocess.CompletedProcess:
    """``python -m lbo.observe <args>``; ``check``: assert it succeeded."""
    res = cli("lbo.observe", *args, cwd=cwd, timeout=timeout)
    if check:
        assert res.returncode == 0, res.stderr[-3000:]
    return res


def one_line_error(res: subprocess.CompletedProcess, *words: str) -> str:
    """The single ``error:`` line of a refused command (exit 2, no traceback), which holds
    each of ``words``."""
    assert res.returncode == 2, res.stdout[-2000:] + res.stderr[-3000:]
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr[-3000:]
    assert "Traceback" not in res.stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]
