"""One training pass of the learned window filter (``model=filternet``) in its window form:
forward and backward over a batch of 256 windows of N = 40, float32, one thread, for the
paper's windows, the same with half their fixes missing, and a receiver's windows (fixes
only). Prints the median of 11 passes after 3 warm-ups, in ms.

    OMP_NUM_THREADS=1 python benchmarks/bench_window_pass.py

To compare two versions of lbo, run it in turn with each on the path, several times
(``PYTHONPATH=<checkout>/src``), and compare the medians: these machines are noisy.
"""

import statistics
import time

import torch

from lbo.models.net import WindowNet

torch.set_num_threads(1)
torch.manual_seed(0)
BATCH, N = 256, 40
times = []
for label, kw, width in (("paper", {}, 5), ("missing fixes", {"fixes": True}, 5),
                         ("receiver", {"receiver": True}, 11)):
    net = WindowNet("filternet", N, "frame", **kw)
    x = torch.randn(BATCH, N, width)
    x[..., 3] = 10 + x[..., 3]  # speeds near 10 m/s
    if kw.get("fixes"):
        x[..., :3] = torch.where(torch.rand(BATCH, N, 1) < 0.5, x[..., :3], float("nan"))
        x[:, -1, :3] = 1.0
    if kw.get("receiver"):  # fixes and headings alone: no accuracy, course or gyro
        x[..., 3:8] = float("nan")
        x[..., 10] = float("nan")
    ts = []
    for _ in range(14):
        start = time.perf_counter()
        net(x).sum().backward()
        ts.append(time.perf_counter() - start)
    times.append(f"{label} {1e3 * statistics.median(ts[3:]):.1f} ms")
print("a training pass: " + ", ".join(times))
