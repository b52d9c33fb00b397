"""Why the variogram's receiver noise misses on the simulated receivers (docs/logs.md, section
8): the receiver study's gyro EKF learned without truth, its receiver factors read from the
fixes' variogram over longer lags, and with the position's process noise held at its prior,
each against the supervised fit (lbo's measure, as ``learned_vs_supervised.py`` gives it).

    python benchmarks/variogram_lags.py [out_folder]      # about 3 min on a 2-core CPU

The variants are the study's ``learn.objective=innovations learn.receiver_noise=variogram``
with one thing changed, through the two names the fit reads (``gyro_fit.receiver_scales``, the
factors; ``gyro_fit.GyroFilter``, the filter whose noises it learns), not through settings: a
study no one would run, measured to say where the miss lies.
"""

from __future__ import annotations

import json
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from unittest import mock

import numpy as np
import pandas as pd
from hydra import compose, initialize_config_dir

from lbo.core.paths import CONF_DIR
from lbo.learn import gyro_fit, variogram
from lbo.receiver_study import LEARNED, receiver_study
from lbo.scoring.receiver import RMSE

SELF_SUPERVISED = ["learn.objective=innovations", "learn.receiver_noise=variogram"]
VARIANTS: dict[str, tuple[list[str], Sequence[float] | None, bool]] = {
    "supervised": ([], None, False),
    "variogram over 10-30 s (lbo's)": (SELF_SUPERVISED, None, False),
    "variogram over 30-60 s": (SELF_SUPERVISED, (30.0, 45.0, 60.0), False),
    "variogram over 60-100 s": (SELF_SUPERVISED, (60.0, 80.0, 100.0), False),
    "variogram over 10-30 s, q_position held at its prior": (SELF_SUPERVISED, None, True),
}


def run(out: Path, overrides: list[str], lags: Sequence[float] | None, hold: bool
        ) -> tuple[pd.DataFrame, dict[str, float]]:
    """One receiver study (``observers=[ekf,gyro]``) into ``out``: its results and the noise
    it learned."""
    def scales(logs):  # the study's factors, the fixes' sill over ``lags`` where given
        fixes = variogram.fix_errors(logs, *([lags] if lags is not None else []))
        return fixes.accuracy_scale, variogram.course_errors(logs).widening

    class Filter(gyro_fit.GyroFilter):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            if hold:
                self.log["q_position"].requires_grad_(False)

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("receiver_study", ["observers=[ekf,gyro]", f"output_dir={out}",
                                         *overrides])
    with mock.patch.object(gyro_fit, "receiver_scales", scales), \
            mock.patch.object(gyro_fit, "GyroFilter", Filter):
        results = receiver_study(cfg)["table"]
    return results, json.loads((out / "gyro_noise.json").read_text())


def learned_row(table: pd.DataFrame, alpha: float) -> np.ndarray:
    return table[(table["alpha"] == alpha) & (table["estimator"] == LEARNED)][
        list(RMSE)].to_numpy(float)[0]


def main(folder: Path) -> pd.DataFrame:
    rows, base = [], None
    for i, (name, (overrides, lags, hold)) in enumerate(VARIANTS.items()):
        results, noise = run(folder / str(i), overrides, lags, hold)
        base = results if base is None else base
        row = {"fit": name}
        for alpha in sorted(results["alpha"].unique()):
            ratio = learned_row(results, alpha) / learned_row(base, alpha)
            row[f"alpha {alpha:g}"] = round(float(np.sqrt(np.mean(ratio**2))), 3)
        row |= {k: round(noise[k], 3) for k in ("accuracy_scale", "velocity_scale",
                                                 "q_position", "course_lever")}
        rows.append(row)
    table = pd.DataFrame(rows)
    print("| " + " | ".join(table.columns) + " |")
    print("|" + "---|" * len(table.columns))
    for values in table.itertuples(index=False):
        print("| " + " | ".join(str(v) for v in values) + " |")
    return table


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp()))
