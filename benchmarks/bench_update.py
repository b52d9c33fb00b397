"""The window filter's update in its training loop: the short form it uses
(:func:`lbo.models.update.full_update`, ``(I - K H) P``) against Joseph's
(:func:`lbo.models.update.joseph`, every other torch filter's update), on one forward and
backward pass of a batch of 256 windows of N = 40, float64, one thread; the median of 10
passes after 2 warm-ups, each form timed twice in turn, plain and with the drift states.

    OMP_NUM_THREADS=1 python benchmarks/bench_update.py
"""

import statistics
import time

import torch

from lbo.models import filter_step, update
from lbo.models.net import WindowNet

torch.set_num_threads(1)
short = update.full_update


def joseph(z, P, y, R, eye, H=None):
    """full_update's gain, then Joseph's covariance."""
    Hm = eye if H is None else H
    PH = P if H is None else P @ H.T
    return update.joseph(z, P, PH @ update.inverse_sym3(Hm @ PH + R), y, Hm, R)


torch.manual_seed(0)
x = torch.randn(256, 40, 5, dtype=torch.float64)
for drift in (False, True):
    net = WindowNet("filternet", 40, "frame", drift=drift).double()
    times: dict[str, list[float]] = {"short": [], "joseph": []}
    outs = {}
    for name, form in (("short", short), ("joseph", joseph)) * 2:
        filter_step.full_update = form
        ts = []
        for _ in range(12):
            start = time.perf_counter()
            out = net(x)
            out.sum().backward()
            ts.append(time.perf_counter() - start)
        times[name].append(statistics.median(ts[2:]))
        outs[name] = out.detach()
    filter_step.full_update = short
    s, j = statistics.median(times["short"]), statistics.median(times["joseph"])
    print(f"drift={drift}: short form {1e3 * s:.1f} ms, Joseph {1e3 * j:.1f} ms a pass "
          f"({j / s:.2f}x); largest difference of the estimates "
          f"{float((outs['short'] - outs['joseph']).abs().max()):.1e}")
