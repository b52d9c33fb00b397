"""The Hydra shell every entry point shares: bad input is one line on stderr, exit code 2."""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any, NoReturn

import hydra
from omegaconf import DictConfig

from lbo.errors import LboError
from lbo.paths import CONF_DIR, REPO_ROOT
from lbo.tracking import check_launcher, launcher_from_argv


def fail(err: Exception) -> NoReturn:
    print(f"error: {err}", file=sys.stderr, flush=True)
    sys.exit(2)


def entry(config_name: str, run: Callable[[DictConfig], Any]) -> Callable[[], Any]:
    """A ``@hydra.main`` around ``run(cfg)`` composing ``conf/<config_name>.yaml``.

    ``run``'s return value goes back to Hydra (a sweeper's objective); an LboError becomes
    ``error: <message>`` on stderr and exit code 2. A launcher plugin named on the command
    line that is not installed is reported the same way, before Hydra composes anything.
    """

    @hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=config_name)
    def main(cfg: DictConfig) -> Any:
        try:
            return run(cfg)
        except LboError as e:
            fail(e)

    def checked() -> Any:
        try:
            if not (CONF_DIR / f"{config_name}.yaml").is_file():
                raise LboError(f"lbo's configs are neither in {REPO_ROOT / 'conf'} nor in the "
                               "installed package: reinstall lbo (pip install <repo>), or set "
                               "LBO_ROOT=<repo>")
            check_launcher(launcher_from_argv(sys.argv[1:]))
        except LboError as e:
            fail(e)
        return main()

    return checked
