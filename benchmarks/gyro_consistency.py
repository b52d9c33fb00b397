"""The gyro EKF's consistency test (lbo.filters.consistency) on lbo's simulated receiver logs.

    python benchmarks/gyro_consistency.py [--bias 0.5] [--seeds 3] [--manoeuvres slalom,...]
        [--course-unbiased]

Logs: ``lbo.simulate receiver=single_antenna`` (fixes without heading at 1 Hz, velocities,
a gyro at 50 Hz) of every test manoeuvre (each starts moving) and the stop-and-go drive (it
starts standing), seeds 0 .. seeds-1, the gyro reading ``--bias`` rad/s more (0 and the
given one). The gyro EKF (default noise, as ``lbo.observe observer=gyro`` runs it) runs with
its remedy off (``relearn=False``: rows flagged only) and on (the default: the heading's and
bias's variances widened where the test fails). Per group of logs, pooled over their rows:
the heading RMSE, the mean of z^2 = error^2 / the filter's variance (every row's own, flagged
or not), the share beyond 3 sigma, the share flagged, the share beyond 3 sigma yet valid
(all rows, and from each log's first update on: before it no innovation can tell, with the
valid rows' mean z^2 there), and the logs with any row flagged. ``--course-unbiased``: the
course's variance made from the gyro less its bias (the allowance for the antenna's lever,
:func:`lbo.filters.measure.rows`), to measure what the raw, biased rate costs there.
"""

from __future__ import annotations

import argparse

import numpy as np
from hydra import compose, initialize_config_dir

from lbo.core.angles import wrap_angle
from lbo.core.paths import CONF_DIR
from lbo.filters import classical
from lbo.filters.gyro import gyro_ekf_batch
from lbo.logs.io import receiver
from lbo.serve.runners import ClassicalRunner
from lbo.sim.manoeuvres import MANOEUVRES
from lbo.sim.measurements import Measurements
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle
from lbo.simulate import STOP_AND_GO, simulate


def run_log(df, bias: float, relearn: bool, course_unbiased: bool) -> dict[str, np.ndarray]:
    """One log through the gyro EKF: per row (T,) its heading z^2, error and flag, and the
    rows from its first update on."""
    vehicle, noise = Vehicle(), Noise.preset("paper")
    m = df[["x_m", "y_m", "psi_m"]].to_numpy(float)
    u = df[["V", "delta"]].to_numpy(float)
    r = receiver(df)
    r[:, 6] += bias
    runner = ClassicalRunner("gyro", vehicle, noise)
    rows, uu = runner.log_rows(Measurements.of(m, r), u, None)
    if course_unbiased:
        r[:, 6] -= bias
        rows[:, 7] = runner.log_rows(Measurements.of(m, r), u, None)[0][:, 7]
    R = classical.measurement_cov("gyro", noise, 1.0, 1)
    post = gyro_ekf_batch(rows[None], uu[None], vehicle, noise.Q, R, relearn=relearn)
    err = wrap_angle(post.mean[0, :, 2] - df["psi"].to_numpy(float))
    held = np.isfinite(rows[1:, :2]).all(1) | np.isfinite(rows[1:, 6])
    first = 1 + int(np.argmax(held))  # the first update after the start
    assert post.checks is not None  # the gyro EKF tests its innovations
    return {"err": err, "z2": err**2 / post.cov[0, :, 2, 2],
            "flag": post.checks.inconsistent[0], "after": np.arange(len(err)) >= first}


def summary(logs: list[dict[str, np.ndarray]]) -> str:
    """The pooled numbers of a group of logs (see the module's docstring)."""
    cat = {k: np.concatenate([g[k] for g in logs]) for k in logs[0]}
    far, flag, after = cat["z2"] > 9, cat["flag"], cat["after"]
    return (f"heading RMSE {np.sqrt(np.mean(cat['err'] ** 2)):.4f} rad, mean z^2 "
            f"{cat['z2'].mean():6.2f}, beyond 3 sd {far.mean():6.1%}, flagged "
            f"{flag.mean():6.1%}, beyond 3 sd and valid {np.mean(far & ~flag):5.1%} "
            f"({np.mean((far & ~flag)[after]):5.1%} from the first update, where the valid "
            f"rows' mean z^2 is {cat['z2'][after & ~flag].mean():5.2f}), logs flagged "
            f"{sum(bool(g['flag'].any()) for g in logs)} of {len(logs)}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--bias", type=float, default=0.5)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--manoeuvres", default=",".join([*MANOEUVRES, STOP_AND_GO]))
    p.add_argument("--course-unbiased", action="store_true")
    a = p.parse_args()
    groups: dict[tuple[str, float, bool], list] = {}
    for name in a.manoeuvres.split(","):
        start = "starts standing" if name == STOP_AND_GO else "starts moving"
        for seed in range(a.seeds):
            with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
                cfg = compose("simulate", [f"manoeuvre={name}", "receiver=single_antenna",
                                           f"seed={seed}"])
            df = simulate(cfg)
            for bias in (0.0, a.bias):
                for relearn in (False, True):
                    groups.setdefault((start, bias, relearn), []).append(
                        run_log(df, bias, relearn, a.course_unbiased))
    for (start, bias, relearn), logs in sorted(groups.items()):
        print(f"{start}, bias {bias:g} rad/s, relearn {'on ' if relearn else 'off'}: "
              + summary(logs))


if __name__ == "__main__":
    main()
