"""Time the batched EKF against the filterpy loop on the paper's test grid.

    python benchmarks/bench_filters.py

The grid is the paper-scale test set: 15 manoeuvres x 25 alpha levels (0 to 6 by 0.25) =
375 trajectories, run-ins included, padded to the longest. Targets: batched < 5 s for the
whole grid, >= 20x faster than the filterpy loop, same numbers.
"""

from __future__ import annotations

import time

import numpy as np

from lbo.filters import ekf_batch, run_filterpy_ekf
from lbo.noise import Noise
from lbo.vehicle import Vehicle


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def bench(m: np.ndarray, u: np.ndarray, vehicle: Vehicle, Q: np.ndarray, R: np.ndarray,
          repeats: int = 3, n_reference: int | None = 25) -> dict[str, float]:
    """Time :func:`ekf_batch` and the filterpy loop on the same trajectories and compare them.

    Parameters
    ----------
    m : (G, T, 3) measurements.
    u : (G, T, 2) inputs.
    vehicle : Vehicle
    Q : (3, 3) process covariance.
    R : (3, 3) shared or (G, 3, 3) per trajectory.
    repeats : timings per method; the median is reported.
    n_reference : the filterpy loop runs on the first ``n_reference`` trajectories only and
        its time is scaled linearly to G (it is per-trajectory and sequential); None runs all.

    Returns
    -------
    dict with ``batched_s``, ``filterpy_s`` (for all G, extrapolated if subset),
    ``filterpy_measured_s``, ``n_reference``, ``speedup`` and ``max_abs_diff``.
    """
    g = m.shape[0]
    R = np.broadcast_to(R, (g, 3, 3))
    n_ref = g if n_reference is None else min(n_reference, g)

    est = ekf_batch(m, u, vehicle, Q, R)  # warm-up, and the numbers to compare
    batched_s = _median_time(lambda: ekf_batch(m, u, vehicle, Q, R), repeats)

    def reference() -> np.ndarray:
        return np.stack([run_filterpy_ekf(m[i], u[i], vehicle, Q, R[i]) for i in range(n_ref)])

    ref = reference()
    measured_s = _median_time(reference, repeats)
    filterpy_s = measured_s * g / n_ref
    return {
        "batched_s": batched_s,
        "filterpy_s": filterpy_s,
        "filterpy_measured_s": measured_s,
        "n_reference": n_ref,
        "speedup": filterpy_s / batched_s,
        "max_abs_diff": float(np.abs(est[:n_ref] - ref).max()),
    }


def paper_test_grid():
    """The real paper-scale test set (generated on first use, then cached under data/)."""
    from hydra import compose, initialize_config_dir

    from lbo.datagen.build import build, spec_from_cfg
    from lbo.evaluate import load_test
    from lbo.paths import CONF_DIR

    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("datagen", ["data=paper"])
    folder, _, _ = build(spec_from_cfg(cfg), progress=False)
    return load_test(folder / "test.parquet")


def main() -> None:
    vehicle, noise = Vehicle(), Noise.preset("paper")
    arr = paper_test_grid()
    m, u = arr["m"], arr["u"]
    g, t = m.shape[:2]
    print(f"paper test grid: {g} trajectories (15 manoeuvres x 25 alpha levels) x {t} steps, "
          f"run-ins and padding included = {g * t:,} filter steps (paper EKF, alpha=1 R)")
    r = bench(m, u, vehicle, noise.Q, noise.R(1.0))
    print(f"ekf_batch      : {r['batched_s']:8.3f} s  (median of 3, all {g} trajectories)")
    print(f"filterpy loop  : {r['filterpy_s']:8.3f} s  (median of 3 on {r['n_reference']} "
          f"trajectories = {r['filterpy_measured_s']:.3f} s, scaled linearly to {g})")
    print(f"speed-up       : {r['speedup']:8.1f} x")
    print(f"max |diff|     : {r['max_abs_diff']:.2e}  (on the {r['n_reference']} compared)")
    ok = r["batched_s"] < 5.0 and r["speedup"] >= 20.0 and r["max_abs_diff"] < 1e-9
    print("targets (< 5 s, >= 20x, diff < 1e-9):", "met" if ok else "NOT met")


if __name__ == "__main__":
    main()
