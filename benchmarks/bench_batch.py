"""The batched EKF and UKF on a grid of the paper test set's size (375 trajectories of 1400
steps, synthetic, seeded), one thread, the median of 3 runs each. Give another checkout's
``src`` folder to time its filters instead (e.g. one from before every batch filter kept its
covariances):

    OMP_NUM_THREADS=1 python benchmarks/bench_batch.py [<checkout>/src]
"""

import statistics
import sys
import time

if len(sys.argv) > 1:
    sys.path.insert(0, sys.argv[1])

import numpy as np  # noqa: E402  (after the path: the filters of the checkout given)

from lbo.filters.kalman import ekf_batch  # noqa: E402
from lbo.filters.unscented import ukf_batch  # noqa: E402
from lbo.sim.noise import Noise  # noqa: E402
from lbo.sim.vehicle import Vehicle  # noqa: E402

rng = np.random.default_rng(0)
G, T = 375, 1400
psi = np.cumsum(rng.normal(0, 0.002, (G, T)), 1)
x, y = np.cumsum(0.2 * np.cos(psi), 1), np.cumsum(0.2 * np.sin(psi), 1)
m = np.stack([x, y, psi], -1) + rng.normal(size=(G, T, 3)) * [1.0, 1.0, 0.0174]
u = np.stack([np.full((G, T), 10.0), np.full((G, T), 0.01)], -1)
noise, vehicle = Noise.preset("paper"), Vehicle()
for name, run in (("EKF", ekf_batch), ("UKF", ukf_batch)):
    times = []
    for _ in range(3):
        start = time.perf_counter()
        run(m, u, vehicle, noise.Q, noise.R(1.0))
        times.append(time.perf_counter() - start)
    print(f"{name}: {statistics.median(times):.3f} s for {G} x {T} steps")
