"""The learned filters' one step (lbo.models.filter_step): every number as it was before the
window form's three loops and the recursive form's step became that one step.

``tests/data/filter_step/before.npz`` holds the numbers of the code before that change (made by
running :func:`outputs` on it): the window form of each kind of window filter, and its
recursive form run and smoothed over a log, in float64, with weights drawn away from their
initial values. The same numbers to 1e-9 (they were bit for bit where they were written).

The recursive form runs its nets in float32 (as trained, and as ONNX exports them); here
they run in float64 as well. A float32 kernel's last bit differs from one CPU to another
(AVX2 against AVX-512), and the recursion carried that to 1e-7 of the poses and
covariances: numbers written on one machine failed at 1e-9 on the next.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from lbo.models import recursive
from lbo.models.net import WindowNet
from lbo.models.recursive import RecursiveFilter

pytestmark = pytest.mark.usefixtures("one_torch_thread")
BEFORE = Path(__file__).parent / "data" / "filter_step" / "before.npz"
NAN = float("nan")
N = 20
KINDS = {
    "plain": dict(),
    "residual": dict(residual=8),
    "single_track": dict(body="single_track"),
    "fixes": dict(fixes=True),
    "fixes_single_track": dict(fixes=True, body="single_track"),
    "drift": dict(drift=True),
    "drift_fixes": dict(drift=True, fixes=True),
    "receiver": dict(receiver=True),
    "receiver_gyro": dict(receiver=True, gyro=True),
    "receiver_learned_empty": dict(receiver=True, empty_statistic="learned"),
}


def _paper(batch: int, fixes: bool, seed: int) -> torch.Tensor:
    """Paper windows (B, N, 5) of a car near 10 m/s; with ``fixes``, 40% of the rows hold
    one (the last always; the first in some windows only), NaN elsewhere."""
    g = torch.Generator().manual_seed(seed)
    f = dict(generator=g, dtype=torch.float64)
    t = torch.arange(N, dtype=torch.float64) * 0.02
    win = torch.stack([10 * t + 0.5 * torch.randn(batch, N, **f),
                       3 + 0.5 * torch.randn(batch, N, **f),
                       0.3 + 0.05 * torch.randn(batch, N, **f),
                       10 + torch.randn(batch, N, **f), 0.05 * torch.randn(batch, N, **f)], -1)
    if fixes:
        held = torch.rand(batch, N, generator=g) < 0.4
        held[:, -1] = True
        held[0, 0], held[1, 0] = False, True
        win[..., :3] = torch.where(held[..., None], win[..., :3], NAN)
    return win


def _receiver(batch: int, seed: int, gyro: bool) -> torch.Tensor:
    """Receiver windows (B, N, 11): the paper's fixes, half with reported accuracies, a third
    without a heading (the course in its place, half of those with its sigma), and with
    ``gyro`` a reading at half the rows."""
    g = torch.Generator().manual_seed(seed)
    p = _paper(batch, True, seed)
    sig = torch.where(torch.rand(batch, N, 3, generator=g) < 0.5,
                      0.3 + torch.rand(batch, N, 3, generator=g), NAN)
    sig[..., 2] = sig[..., 2] * 0.05
    course = p[..., 2] + 0.02 * torch.randn(batch, N, generator=g, dtype=torch.float64)
    s_course = torch.where(torch.rand(batch, N, generator=g) < 0.5, 0.03, NAN)
    no_heading = torch.rand(batch, N, generator=g) < 0.3
    psi = torch.where(no_heading, NAN, p[..., 2])
    course = torch.where(no_heading & (p[..., 0] == p[..., 0]), course, NAN)
    r = 0.2 + 0.05 * torch.randn(batch, N, generator=g, dtype=torch.float64)
    r = torch.where(torch.rand(batch, N, generator=g) < 0.5, r, NAN) if gyro \
        else torch.full_like(r, NAN)
    return torch.cat([p[..., :2], psi[..., None], sig, course[..., None], s_course[..., None],
                      p[..., 3:5], r[..., None]], -1)


class _Double(torch.nn.Module):
    """The recursive form's nets in float64 (in place of its float32 ``_Single``)."""

    def __init__(self, net: torch.nn.Module) -> None:
        super().__init__()
        self.net = net.double()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


def outputs() -> dict[str, np.ndarray]:
    """Each kind's window estimates (6, 3), and its recursive form's poses and covariances
    over three windows' rows end to end, 1 km from the origin (2, 60, 3), smoothed where
    fixes are missing; every net in float64."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(recursive, "_Single", _Double)
        return _outputs()


def _outputs() -> dict[str, np.ndarray]:
    out = {}
    for name, kw in KINDS.items():
        kw = dict(kw)
        fixes, receiver = kw.pop("fixes", False), kw.pop("receiver", False)
        torch.manual_seed(0)
        net = WindowNet("filternet", N, "frame", fixes=fixes, receiver=receiver, **kw).double()
        g = torch.Generator().manual_seed(5)
        with torch.no_grad():
            for p in net.net.parameters():
                p.add_(0.1 * torch.randn(p.shape, generator=g, dtype=p.dtype))
        gyro = kw.get("gyro", False)
        seeds = (3, 4, 5)
        if receiver:
            win = _receiver(6, 2, gyro)
            log = torch.cat([_receiver(2, s, gyro) for s in seeds], 1)
            m, u = log[..., :8], log[..., 8:11] if gyro else log[..., 8:10]
        else:
            win = _paper(6, fixes, 1)
            log = torch.cat([_paper(2, fixes, s) for s in seeds], 1)
            m, u = log[..., :3], log[..., 3:5]
        m = m.clone()
        m[..., 0] += 1000.0
        rec = RecursiveFilter(net.net)
        with torch.inference_mode():
            out[f"{name}/window"] = net(win).numpy()
            run = rec.run(m, u)
            out[f"{name}/pose"], out[f"{name}/cov"] = run.pose.numpy(), run.cov.numpy()
            if fixes or receiver:
                out[f"{name}/smoothed"] = rec.run(m, u, smooth=True).pose.numpy()
    return out


def test_every_kind_of_window_filter_gives_the_numbers_it_gave_before_the_one_step():
    before = np.load(BEFORE)
    now = outputs()
    assert sorted(now) == sorted(before.files)
    for key, value in now.items():
        np.testing.assert_allclose(value, before[key], rtol=0, atol=1e-9, err_msg=key)
        assert np.isfinite(value).mean() > 0.9, key  # numbers, not NaN to NaN
