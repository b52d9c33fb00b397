"""Plain helpers the tests import (``from helpers import compose_cfg``); pytest's fixtures and
hooks stay in ``tests/conftest.py``.

- :mod:`helpers.config`: composing configs from conf/ (``compose_cfg``, ``train_cfg``,
  ``ROBUST_SMOKE``, ``SWEEP_BUDGET``)
- :mod:`helpers.training`: training runs at smoke size (``train_in_own_store``), and a client
  on a store made as lbo makes one (``store_client``)
- :mod:`helpers.processes`: faults injected into running processes (``kill_when_written``)
- :mod:`helpers.commands`: lbo's commands as a user types them (``cli``, ``observe``), in the
  test's process unless ``process=True``, ``lbo.observe``'s result on a log (``observed``),
  and their one-line refusals (``one_line_error``)
- :mod:`helpers.stepping`: an observer stepped through a log (``step_log``)
- :mod:`helpers.servers`: real PostgreSQL, MLflow and model servers (import it by name:
  ``from helpers.servers import postgres``)
- :mod:`helpers.scripts`: the repository's scripts in the test's process (``from
  helpers.scripts import run_script``)
- :mod:`helpers.slurm`: a real one-node SLURM cluster (``from helpers.slurm import
  slurm_cluster``)
- :mod:`helpers.hydra_cache`: Hydra's config files read, and each shape of command line built,
  once per version for the session
  (``tests/conftest.py`` installs it)
"""

from helpers.commands import cli, observe, observed, one_line_error
from helpers.config import ROBUST_SMOKE, SWEEP_BUDGET, compose_cfg, train_cfg
from helpers.processes import kill_when_written
from helpers.stepping import step_log
from helpers.training import store_client, train_in_own_store

__all__ = ["ROBUST_SMOKE", "SWEEP_BUDGET", "cli", "compose_cfg", "kill_when_written", "observe",
           "observed", "one_line_error", "step_log", "store_client", "train_cfg",
           "train_in_own_store"]
