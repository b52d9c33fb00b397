"""What the tests' Hydra caches save a compose (``tests/helpers/hydra_cache.py``): the median
time of composing ``train`` with Hydra's own reads, with the config files kept, and with the
files and each command line's build kept, for two kinds of command line the suite composes:

- the same choices with other values (``experiment=smoke seed=<i> data.root=<folder i>``), as
  the tests that train, observe or evaluate compose;
- other choices each time (``experiment=<e> <group>=<option>``), as ``test_config_groups``
  composes, where only the files are kept.

    .venv/bin/python benchmarks/compose_cache.py [--repeats 30]
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from helpers import compose_cfg, hydra_cache  # noqa: E402
from lbo.core.paths import CONF_DIR  # noqa: E402


def median_ms(lines: list[list[str]]) -> float:
    times = []
    for overrides in lines:
        start = time.perf_counter()
        compose_cfg("train", overrides)
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=30)
    n = parser.parse_args().repeats
    values = [["experiment=smoke", f"seed={i}", f"data.root=/tmp/lbo-bench-{i}"]
              for i in range(n)]
    options = sorted(p.stem for p in (CONF_DIR / "model").glob("*.yaml"))
    experiments = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))
    shapes = [[f"experiment={e}", f"model={m}"]
              for e, m in itertools.islice(itertools.product(experiments, options), n)]
    compose_cfg("train", values[0])  # Hydra's plugin scan and lbo's imports, once
    print(f"median ms a compose of train, {n} composes each")
    print("                          same choices, other values   other choices")
    for name, setup in (("Hydra's own reads", hydra_cache.uninstall),
                        ("files kept", lambda: hydra_cache.install(builds=False)),
                        ("files and builds kept", hydra_cache.install)):
        hydra_cache.uninstall()
        setup()
        compose_cfg("train", values[0])
        compose_cfg("train", shapes[0])  # the first of each kind builds and keeps
        print(f"{name:<26}{median_ms(values):>14.1f}{median_ms(shapes):>28.1f}")
    hydra_cache.uninstall()


if __name__ == "__main__":
    main()
