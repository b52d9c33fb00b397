"""Where the variogram's receiver noise misses on the simulated receivers, and what closes
the gap (docs/logs.md, section 8): the receiver study's gyro EKF learned without truth
(``learn.objective=innovations learn.receiver_noise=variogram``), its receiver factors read
from the fixes' variogram over longer lags, or with noises held at their priors
(``learn.hold``), each against the supervised fit (lbo's measure, as
``learned_vs_supervised.py`` gives it), with the noise each learned.

    python benchmarks/variogram_lags.py [out_folder] [override ...]   # about 6 min on a 2-core CPU

The longer lags are no setting: they go through the name the fit reads its factors by
(``gyro_fit.receiver_scales``), a study no one would run, measured to say where the miss lies.
Overrides (``seed=1 drives=10``) go to every study.
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
VARIANTS: dict[str, tuple[list[str], Sequence[float] | None]] = {
    "supervised": ([], None),
    "variogram over 10-30 s (lbo's)": (SELF_SUPERVISED, None),
    "variogram over 30-60 s": (SELF_SUPERVISED, (30.0, 45.0, 60.0)),
    "variogram over 60-100 s": (SELF_SUPERVISED, (60.0, 80.0, 100.0)),
    "learn.hold=[q_position]": ([*SELF_SUPERVISED, "learn.hold=[q_position]"], None),
    "learn.hold=[course_lever]": ([*SELF_SUPERVISED, "learn.hold=[course_lever]"], None),
    "learn.hold=[q_position,course_lever]": (
        [*SELF_SUPERVISED, "learn.hold=[q_position,course_lever]"], None),
    "learn.hold=[q_position,course_lever,q_heading]": (
        [*SELF_SUPERVISED, "learn.hold=[q_position,course_lever,q_heading]"], None),
}


def run(out: Path, overrides: list[str], lags: Sequence[float] | None
        ) -> tuple[pd.DataFrame, dict[str, float]]:
    """One receiver study (``observers=[ekf,gyro]``) into ``out``: its results and the noise
    it learned."""
    def scales(logs):  # the study's factors, the fixes' sill over ``lags`` where given
        fixes = variogram.fix_errors(logs, *([lags] if lags is not None else []))
        return fixes.accuracy_scale, variogram.course_errors(logs).widening

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("receiver_study", ["observers=[ekf,gyro]", f"output_dir={out}",
                                         *overrides])
    with mock.patch.object(gyro_fit, "receiver_scales", scales):
        results = receiver_study(cfg)["table"]
    return results, json.loads((out / "gyro_noise.json").read_text())


def learned_row(table: pd.DataFrame, alpha: float) -> np.ndarray:
    return table[(table["alpha"] == alpha) & (table["estimator"] == LEARNED)][
        list(RMSE)].to_numpy(float)[0]


def main(folder: Path, extra: Sequence[str] = ()) -> pd.DataFrame:
    rows, base = [], None
    for i, (name, (overrides, lags)) in enumerate(VARIANTS.items()):
        results, noise = run(folder / str(i), [*overrides, *extra], lags)
        base = results if base is None else base
        row = {"fit": name}
        for alpha in sorted(results["alpha"].unique()):
            ratio = learned_row(results, alpha) / learned_row(base, alpha)
            row[f"alpha {alpha:g}"] = round(float(np.sqrt(np.mean(ratio**2))), 3)
        row |= {k: float(f"{noise[k]:.4g}") for k in ("accuracy_scale", "velocity_scale",
                                                 "q_position", "course_lever", "q_heading")}
        rows.append(row)
    table = pd.DataFrame(rows)
    print("| " + " | ".join(table.columns) + " |")
    print("|" + "---|" * len(table.columns))
    for values in table.itertuples(index=False):
        print("| " + " | ".join(str(v) for v in values) + " |")
    return table


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp()), sys.argv[2:])
