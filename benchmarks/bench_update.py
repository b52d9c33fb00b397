"""The window filter's update in its training loop: Joseph's form as lbo computes it
(:func:`lbo.models.update.joseph`, factored: ``A P - (A P H^T - K R) K^T``, S inverted by
LAPACK) against the same form as written in textbooks (``A P A^T + K R K^T``), and against
what the window filter took until 2026-12-01: the short form ``A P`` (not Joseph's) with S
inverted by cofactors. On one forward and backward pass of a batch of 256 windows of N = 40,
float64, one thread; the median of 10 passes after 2 warm-ups, each form timed twice in turn,
plain and with the drift states. Also each form's largest difference from lbo's in the
estimates.

    OMP_NUM_THREADS=1 python benchmarks/bench_update.py
"""

import statistics
import time

import torch

from lbo.models import update
from lbo.models.net import WindowNet

torch.set_num_threads(1)
mm = update.mm


def _ends(P, K, z, y):
    """``z + K y`` and P symmetrised, as lbo's update ends."""
    return z + mm(K, y.unsqueeze(-1)).squeeze(-1), 0.5 * (P + P.transpose(-1, -2))


def textbook(z, P, PHt, K, y, R, H=None):
    """Joseph's form as written: ``(I - K H) P (I - K H)^T + K R K^T``."""
    eye = torch.eye(P.shape[-1], dtype=P.dtype)
    A = eye - (K if H is None else mm(K, H))
    P = mm(mm(A, P), A.transpose(-1, -2)) + mm(mm(K, R), K.transpose(-1, -2))
    return _ends(P, K, z, y)


def short(z, P, PHt, K, y, R, H=None):
    """The short form ``(I - K H) P``: exact only for the optimal gain."""
    P = P - mm(K, PHt.transpose(-1, -2))
    return _ends(P, K, z, y)


def cofactors(s):
    """S inverted by cofactors, as a trace records it."""
    return update.inverse_sym3(s) if s.shape[-1] == 3 else update.inverse_sym2(s)


# the covariance's form and S's inverse
FORMS = {"lbo": (update.joseph, update.inverse_sym), "textbook": (textbook, update.inverse_sym),
         "short, cofactors": (short, cofactors)}

torch.manual_seed(0)
x = torch.randn(256, 40, 5, dtype=torch.float64)
for drift in (False, True):
    net = WindowNet("filternet", 40, "frame", drift=drift).double()
    times: dict[str, list[float]] = {name: [] for name in FORMS}
    outs = {}
    for _ in range(2):
        for name, (form, inverse) in FORMS.items():
            update.joseph, update.inverse_sym = form, inverse
            ts = []
            for _ in range(12):
                start = time.perf_counter()
                out = net(x)
                out.sum().backward()
                ts.append(time.perf_counter() - start)
            times[name].append(statistics.median(ts[2:]))
            outs[name] = out.detach()
    update.joseph, update.inverse_sym = FORMS["lbo"]
    base = statistics.median(times["lbo"])
    parts = [f"{name} {1e3 * statistics.median(t):.1f} ms ({statistics.median(t) / base:.2f}x, "
             f"{float((outs[name] - outs['lbo']).abs().max()):.0e})"
             for name, t in times.items()]
    print(f"drift={drift}: " + "; ".join(parts))
