"""lbo's commands run as a user types them (``python -m lbo.<command> <args>``), and their
refusals read.

A command runs in the test's own process unless the test is about the process itself
(``process=True``: exit by signal, a kill, a lock another process holds, what a fresh
interpreter imports, a child's environment at start-up), or starts processes that outlive it
(a joblib sweep: its workers write to the process's own stderr, and joblib keeps them, with
the environment they started with, for the next sweep). In-process it is the same ``main``
that ``python -m`` calls, with the same arguments, environment and folder, its output
captured and its exit code read from
``SystemExit``; what it changes in the process (the environment, the folder, logging, warning
filters, torch's threads and random state, Hydra's global state, signal handlers) is put back
afterwards. This saves the interpreter's start-up, torch, Lightning, Hydra and MLflow imported
afresh: 1.5-4 s a command on a 2-core machine.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import logging
import os
import signal
import subprocess
import sys
import traceback
import warnings
from pathlib import Path


def cli(module: str, *args: str, env: dict[str, str] | None = None, cwd: Path | None = None,
        timeout: float = 600, process: bool = False) -> subprocess.CompletedProcess:
    """``python -m <module> <args>``, its output captured; ``env`` is added to os.environ.

    In this process unless ``process`` (a subprocess, stopped after ``timeout`` seconds)."""
    if process:
        return subprocess.run([sys.executable, "-m", module, *args], capture_output=True,
                              text=True, env={**os.environ, **(env or {})}, cwd=cwd,
                              timeout=timeout)
    return _in_process(module, list(args), env or {}, cwd)


def observe(*args: str, cwd: Path | None = None, timeout: float = 600, check: bool = False,
            process: bool = False) -> subprocess.CompletedProcess:
    """``python -m lbo.observe <args>``; ``check``: assert it succeeded."""
    res = cli("lbo.observe", *args, cwd=cwd, timeout=timeout, process=process)
    if check:
        assert res.returncode == 0, res.stderr[-3000:]
    return res


def observed(log: Path, output: Path, *overrides: str, observer: str = "ekf") -> dict:
    """:func:`lbo.observe.observe`'s result for the log file ``log``, its estimates written to
    ``output``: the command's config composed with ``overrides``, called in this process."""
    from helpers.config import compose_cfg
    from lbo.observe import observe as run

    return run(compose_cfg("observe", [f"observer={observer}", f"input={log}",
                                       f"output={output}", *overrides]))


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


def _exit_code(code: object, err: io.StringIO) -> int:
    """The exit status ``sys.exit(code)`` gives a process (a message goes to stderr, as 1)."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=err)
    return 1


def _in_process(module: str, args: list[str], env: dict[str, str],
                cwd: Path | None) -> subprocess.CompletedProcess:
    out, err = io.StringIO(), io.StringIO()
    argv = [module, *args]
    with _kept_state():
        os.environ.update(env)
        if cwd is not None:
            os.chdir(cwd)
        sys.argv = list(argv)
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                try:
                    main = importlib.import_module(module).main
                    code = _exit_code(main(), err)
                except SystemExit as e:
                    code = _exit_code(e.code, err)
                except Exception:  # noqa: BLE001 - what an uncaught error does to a process
                    traceback.print_exc(file=err)
                    code = 1
        finally:
            for stream in (out, err):
                stream.flush()
        _drop_handlers_on((out, err))
    return subprocess.CompletedProcess(argv, code, out.getvalue(), err.getvalue())


def _drop_handlers_on(streams: tuple[io.StringIO, ...]) -> None:
    """Take off every logging handler left writing into a command's captured output (one a
    library made when first imported by the command): later records would vanish there."""
    every = [logging.getLogger(), *(lg for lg in logging.Logger.manager.loggerDict.values()
                                    if isinstance(lg, logging.Logger))]
    for lg in every:
        for h in lg.handlers[:]:
            stream = getattr(h, "stream", None)
            if stream in streams or getattr(stream, "_stream", None) in streams:
                lg.removeHandler(h)


@contextlib.contextmanager
def _kept_state():
    """Put back what a command changes in the process that runs it."""
    import numpy as np
    import torch
    from hydra.core.global_hydra import GlobalHydra

    environ, folder, argv = dict(os.environ), os.getcwd(), list(sys.argv)
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    loggers = {name: (lg.level, lg.disabled, lg.propagate, list(lg.handlers))
               for name, lg in logging.Logger.manager.loggerDict.items()
               if isinstance(lg, logging.Logger)}
    threads, dtype = torch.get_num_threads(), torch.get_default_dtype()
    deterministic = torch.are_deterministic_algorithms_enabled()
    rng = (torch.get_rng_state(), np.random.get_state())
    handlers_by_signal = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    GlobalHydra.instance().clear()
    try:
        with warnings.catch_warnings():
            yield
    finally:
        GlobalHydra.instance().clear()
        for s, h in handlers_by_signal.items():
            signal.signal(s, h)
        torch.set_rng_state(rng[0])
        np.random.set_state(rng[1])
        torch.use_deterministic_algorithms(deterministic)
        torch.set_default_dtype(dtype)
        torch.set_num_threads(threads)
        for name, lg in list(logging.Logger.manager.loggerDict.items()):
            if isinstance(lg, logging.Logger) and name in loggers:
                lg.level, lg.disabled, lg.propagate, lg.handlers[:] = (
                    loggers[name][0], loggers[name][1], loggers[name][2], loggers[name][3])
        for h in root.handlers[:]:
            if h not in handlers:
                root.removeHandler(h)
                with contextlib.suppress(Exception):
                    h.close()
        root.handlers[:] = handlers
        root.setLevel(level)
        sys.argv = argv
        os.chdir(folder)
        os.environ.clear()
        os.environ.update(environ)
