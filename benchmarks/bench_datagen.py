"""Paper-scale data generation: wall time and peak RSS, median of 3 fresh processes.

    python benchmarks/bench_datagen.py [--scale paper] [--repeats 3]

Each run is a new process that generates the sets into an empty temp folder (no cache),
so the figures include imports-free generation plus the Parquet writes.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile

CHILD = r"""
import json, resource, sys, time
from lbo.sim.datasets import make_train, make_val, make_test, spec_from_cfg
from lbo import schema
from hydra import compose, initialize_config_dir
from lbo.core.paths import CONF_DIR
with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
    cfg = compose("datagen", [f"data={sys.argv[1]}", f"data.root={sys.argv[2]}"])
spec = spec_from_cfg(cfg)
out = {}
for name, make in (("train", make_train), ("val", make_val), ("test", make_test)):
    t = time.perf_counter()
    df = make(spec)
    schema.write_set(df, spec.folder / f"{name}.parquet")
    out[name] = time.perf_counter() - t
    out[f"rows_{name}"] = len(df)
    del df
out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(out))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", default="paper")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    runs = []
    for i in range(args.repeats):
        with tempfile.TemporaryDirectory() as root:
            res = subprocess.run([sys.executable, "-c", CHILD, args.scale, root],
                                 capture_output=True, text=True, check=True)
            runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
            print(f"run {i + 1}: " + ", ".join(f"{k} {runs[-1][k]:.2f} s"
                                               for k in ("train", "val", "test"))
                  + f", peak RSS {runs[-1]['peak_rss_mb']:.0f} MB", flush=True)
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    print(f"\ndatagen {args.scale} (median of {args.repeats}): "
          f"train set {med['train']:.2f} s for {int(med['rows_train']):,} steps "
          f"(target < 60 s), val {med['val']:.2f} s, test {med['test']:.2f} s "
          f"for {int(med['rows_test']):,} rows; peak RSS {med['peak_rss_mb']:.0f} MB "
          f"(target < 2048 MB)")


if __name__ == "__main__":
    main()
