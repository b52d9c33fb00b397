"""Time the batched EKF and UKF against filterpy's loops, and the whole classical stage, on
the paper's test grid.

    python benchmarks/bench_filters.py

The grid is the paper-scale test set: 15 manoeuvres x 25 alpha levels (0 to 6 by 0.25) =
375 trajectories, run-ins included, padded to the longest. Targets: the batched EKF < 5 s
for the whole grid and >= 20x faster than filterpy; the batched UKF >= 50x faster than
filterpy; both with the same numbers (max difference <= 1e-9); and every classical observer
of ``lbo.evaluate`` (EKF, oracle, adaptive EKF, UKF, PCRB) in under 15 s together.
"""

from __future__ import annotations

import time

import numpy as np

from lbo.filters.classical import NAMES
from lbo.filters.kalman import ekf_batch
from lbo.filters.reference import run_filterpy_ekf, ukf
from lbo.filters.unscented import ukf_batch
from lbo.scoring.grid import classical
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def bench(batched, reference, m: np.ndarray, u: np.ndarray, R: np.ndarray, repeats: int = 3,
          n_reference: int | None = 25) -> dict[str, float]:
    """Time a batched filter and filterpy's loop on the same trajectories and compare them.

    Parameters
    ----------
    batched : ``(m, u, R) -> est`` over all G trajectories at once.
    reference : ``(m_i, u_i, R_i) -> est_i`` over one trajectory (filterpy).
    m : (G, T, 3) measurements.
    u : (G, T, 2) inputs.
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

    est = batched(m, u, R)  # warm-up, and the numbers to compare
    batched_s = _median_time(lambda: batched(m, u, R), repeats)

    def loop() -> np.ndarray:
        return np.stack([reference(m[i], u[i], R[i]) for i in range(n_ref)])

    ref = loop()
    measured_s = _median_time(loop, repeats)
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

    from lbo.core.paths import CONF_DIR
    from lbo.scoring.grid import load_test
    from lbo.sim.datasets import build, spec_from_cfg

    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("datagen", ["data=paper"])
    folder, _, _ = build(spec_from_cfg(cfg), progress=False)
    return load_test(folder / "test.parquet")


def main() -> None:
    vehicle, noise = Vehicle(), Noise.preset("paper")
    arr = paper_test_grid()
    m, u, Q = arr["m"], arr["u"], noise.Q
    g, t = m.shape[:2]
    print(f"paper test grid: {g} trajectories (15 manoeuvres x 25 alpha levels) x {t} steps, "
          f"run-ins and padding included = {g * t:,} filter steps (alpha=1 R)\n")
    filters = {
        "EKF": (lambda m_, u_, R_: ekf_batch(m_, u_, vehicle, Q, R_).mean,
                lambda m_, u_, R_: run_filterpy_ekf(m_, u_, vehicle, Q, R_), 25, 20.0),
        "UKF": (lambda m_, u_, R_: ukf_batch(m_, u_, vehicle, Q, R_).mean,
                lambda m_, u_, R_: ukf(m_, u_, vehicle, Q, R_), 10, 50.0),
    }
    ok = True
    print(f"{'filter':<6}{'batched s':>11}{'filterpy s':>12}{'speed-up':>10}{'max |diff|':>12}"
          "   filterpy timed on")
    for name, (batched, reference, n_ref, target) in filters.items():
        r = bench(batched, reference, m, u, noise.R(1.0), n_reference=n_ref)
        print(f"{name:<6}{r['batched_s']:>11.3f}{r['filterpy_s']:>12.1f}{r['speedup']:>9.0f}x"
              f"{r['max_abs_diff']:>12.1e}   {r['n_reference']} trajectories "
              f"({r['filterpy_measured_s']:.2f} s), scaled to {g}")
        ok &= r["speedup"] >= target and r["max_abs_diff"] <= 1e-9

    print("\nthe classical stage (lbo.evaluate's observers on the whole grid, once each):")
    total = 0.0
    for name in NAMES:
        start = time.perf_counter()
        classical(name, arr, vehicle, noise)
        seconds = time.perf_counter() - start
        total += seconds
        print(f"  {name:<9}{seconds:7.2f} s")
    print(f"  {'total':<9}{total:7.2f} s")
    ok &= total < 15.0
    print("\ntargets (EKF >= 20x, UKF >= 50x, diff <= 1e-9, classical stage < 15 s):",
          "met" if ok else "NOT met")


if __name__ == "__main__":
    main()
