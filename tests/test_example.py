"""The example log of the README's quickstart: what it is, and that it is reproducible."""

from __future__ import annotations

import numpy as np
import pandas as pd

from helpers import compose_cfg
from lbo.core.paths import EXAMPLE_LOG


def test_the_example_log_is_what_lbo_simulate_writes(tmp_path):
    """The shipped log is what ``lbo.simulate`` writes: the same rows, columns and missing
    fixes, every number to 1e-12. Not byte for byte across machines: numpy's SIMD sin, cos and
    tan differ in the last bit between CPUs (AVX-512 or AVX2 kernels), and a CSV prints every
    bit. On one machine the same command writes the same bytes."""
    from lbo.simulate import write_logs

    outs = [tmp_path / "again.csv", tmp_path / "once_more.csv"]
    for out in outs:
        # python -m lbo.simulate manoeuvre=stop_and_go fix_rate=10 alpha=1 seed=0 output=...
        write_logs(compose_cfg("simulate", ["manoeuvre=stop_and_go", "fix_rate=10", "alpha=1",
                                            "seed=0", f"output={out}"]))
    assert outs[0].read_bytes() == outs[1].read_bytes()
    again, shipped = pd.read_csv(outs[0]), pd.read_csv(EXAMPLE_LOG)
    assert list(again.columns) == list(shipped.columns) and len(again) == len(shipped)
    pd.testing.assert_frame_equal(again, shipped, check_exact=False, rtol=1e-12, atol=1e-12)


def test_the_example_log_is_a_stop_and_go_drive_with_10_hz_fixes():
    df = pd.read_csv(EXAMPLE_LOG)
    assert {"t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"} <= set(df.columns)
    fix = np.isfinite(df[["x_m", "y_m", "psi_m"]].to_numpy()).all(1)
    assert np.allclose(np.diff(df["t"]), 0.02)
    assert np.isclose(fix.sum() / (len(df) * 0.02), 10.0, rtol=0.01)
    assert (df["V"] == 0).mean() > 0.2  # it stands still a fifth of the time or more


def test_the_quickstart_observes_it_with_a_plot(tmp_path):
    from lbo.observe import observe

    result = observe(compose_cfg("observe", ["observer=ekf", f"input={EXAMPLE_LOG}",
                                         f"output={tmp_path / 'estimates.csv'}", "plot=true"]))
    assert (tmp_path / "estimates.png").stat().st_size > 20_000
    assert np.all(result["rmse"][:2] < 0.6) and result["valid"] == result["rows"]
