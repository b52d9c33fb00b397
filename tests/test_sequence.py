"""The sequence trainer (issue 37): a filter carried from step to step and trained by
truncated back-propagation through time: carried in chunks as in one run, its steps those of
its window form, and on a linear case (straight drives) it learns to match the EKF."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lbo.core.errors import LboError
from lbo.filters.kalman import ekf_batch
from lbo.learn import sequence
from lbo.models import KalmanNet, SplitKalmanNet
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

NOISE = Noise.preset("paper")
SIGMA = np.array(NOISE.measurement_sigma)
PEERS = [KalmanNet, SplitKalmanNet]


def straight(b: int, t: int, seed: int, every: int = 1) -> sequence.Sequences:
    """b straight drives of t steps at 5-15 m/s in any direction, fixes at alpha 1."""
    rng = np.random.default_rng(seed)
    psi = rng.uniform(-np.pi, np.pi, b)
    v = rng.uniform(5, 15, b)
    time = np.arange(t) * Vehicle().dt
    z = np.stack([v[:, None] * np.cos(psi)[:, None] * time,
                  v[:, None] * np.sin(psi)[:, None] * time,
                  np.broadcast_to(psi[:, None], (b, t))], -1)
    z[..., :2] += rng.normal(scale=100.0, size=(b, 1, 2))
    u = np.stack([np.broadcast_to(v[:, None], (b, t)), np.zeros((b, t))], -1)
    return sequence.draw(z, u, SIGMA, np.ones(b), np.full(b, every), rng)


@pytest.mark.parametrize("cls", PEERS)
def test_carried_in_chunks_it_runs_as_in_one_pass_and_as_its_window_form(cls):
    """Untrained (a gain of 0.3), fixes every third step: the filter carried through chunks
    of 7 steps gives what one pass gives, and the last estimate of a pass over N steps is
    what the window form returns for those N steps."""
    torch.manual_seed(0)
    net = cls(40, gain=0.3, in_features=6).eval()
    seq = straight(5, 40, 1, every=3).centred()
    m, u = (torch.as_tensor(a, dtype=torch.float32) for a in (seq.m, seq.u))
    with torch.no_grad():
        whole, _ = sequence.run(net, m, u)
        parts, state, u_prev = [], None, None
        for k in range(0, 40, 7):
            est, state = sequence.run(net, m[:, k:k + 7], u[:, k:k + 7], state, u_prev)
            parts.append(est)
            u_prev = u[:, min(k + 7, 40) - 1]
        window = torch.cat([torch.nan_to_num(m), u, torch.isfinite(m).all(-1, keepdim=True)
                            .float()], -1)
        torch.testing.assert_close(torch.cat(parts, 1), whole)
        torch.testing.assert_close(whole[:, -1], net(window))
    assert torch.isfinite(whole).all()


@pytest.mark.parametrize("cls", PEERS)
def test_trained_by_truncated_backpropagation_it_learns_to_match_the_ekf(cls,
                                                                        one_torch_thread):
    """The linear case: straight drives, white fixes at alpha 1, where the EKF is near
    optimal. Started at a gain of 0.3, 3 epochs over 48 sequences of 200 steps, 8 a batch, in
    chunks of 50 (about 10 s) bring each peer to the EKF's mean square error over steps 50 on
    of 200 held-out sequences: measured 0.89, 0.75 and 1.03 of the EKF's on x, y and psi for
    KalmanNet, 0.61, 0.73 and 0.58 for Split-KalmanNet; within 1.2. Their validation loss
    falls to 0.27 and 0.21 of the untrained one. (From the default gain of 0.05 an untrained
    peer is already 0.8-0.9 of the EKF here: the EKF's Q allows for process noise these
    drives do not have.)"""
    torch.manual_seed(0)
    net = cls(20, gain=0.3)
    train, val, test = straight(48, 200, 10), straight(16, 200, 11), straight(200, 200, 12)
    fit = sequence.fit(net, train, val, epochs=3, chunk=50, batch=8, lr=1e-3,
                       progress=None)
    assert len(fit.train) == 3 and len(fit.validation) == 4
    c = test.centred()
    with torch.no_grad():
        est, _ = sequence.run(net, *(torch.as_tensor(a, dtype=torch.float32)
                                     for a in (c.m, c.u)))
    ekf = ekf_batch(c.m, c.u, Vehicle(), NOISE.Q, np.diag(SIGMA**2))

    def mse(e):
        d = e[:, 50:] - c.z[:, 50:]
        d[..., 2] = np.angle(np.exp(1j * d[..., 2]))
        return (d**2).mean((0, 1))

    ratio = mse(est.numpy().astype(float)) / mse(ekf)
    assert ratio.max() < 1.2, ratio
    assert fit.validation[fit.best_epoch] < 0.4 * fit.validation[0]


def test_bad_sequences_and_settings_are_one_line():
    seq = straight(2, 10, 0)
    with pytest.raises(LboError, match=r"^sequences: expected m \(B, T, 3\), u \(B, T, 2\)"):
        sequence.Sequences(seq.m[:, :, :2], seq.u, seq.z)
    m = seq.m.copy()
    m[1, 0] = np.nan
    with pytest.raises(LboError, match=r"^sequences: every sequence must start with a "
                                       r"position fix$"):
        sequence.Sequences(m, seq.u, seq.z)
    with pytest.raises(LboError, match=r"^sequence.chunk must be an integer >= 2"):
        sequence.fit(KalmanNet(20), seq, seq, epochs=1, chunk=1, batch=2, lr=1e-3)
