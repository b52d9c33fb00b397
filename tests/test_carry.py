"""A receiver net's window form through a stop (issue 36): where a window holds no heading,
the window filter carries its own estimate of N-1 steps before, so it estimates every row from
the first course over ground on and holds the heading a standing car keeps; a CNN gives none
there."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from helpers import compose_cfg, step_log
from lbo.logs.io import receiver
from lbo.models.net import WindowNet
from lbo.serve import carry
from lbo.serve.observer import Observer
from lbo.sim.measurements import Measurements
from lbo.simulate import simulate

pytestmark = pytest.mark.usefixtures("one_torch_thread")
NAN = float("nan")


def test_the_estimate_goes_in_as_a_course_and_as_a_fix_where_the_first_row_has_none():
    windows = np.full((2, 4, 11), NAN)
    windows[:, :, 8:10] = 0.0  # V, delta
    windows[0, 2, [0, 1, 3, 4]] = [5.0, 6.0, 0.3, 0.4]  # window 0: a fix at row 2, reported
    windows[1, 0, [0, 1]] = [7.0, 8.0]  # window 1: a fix of its own at row 0, none reported
    prior = np.array([[1.0, 2.0, 0.5], [3.0, 4.0, -1.0]])
    out = carry.carried(windows, prior)
    np.testing.assert_array_equal(out[0, 0, :8], [1.0, 2.0, NAN, 0.3, 0.4, NAN, 0.5,
                                                  carry.CARRIED_SIGMA_PSI])
    np.testing.assert_array_equal(out[1, 0, :8], [7.0, 8.0, NAN, NAN, NAN, NAN, -1.0,
                                                  carry.CARRIED_SIGMA_PSI])
    np.testing.assert_array_equal(out[:, 1:], windows[:, 1:])  # the other rows as they were
    assert np.isnan(windows[:, 0, 6]).all()  # a copy: the caller's windows are untouched


def _stop() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A single-antenna stop-and-go slice (rows 900-1500 of seed 3's log, fixes at 10 Hz):
    the car drives, stands about 7 s (no course over ground) and drives off. m (T, 3), u (T,
    2), receiver channels (T, 7)."""
    log = simulate(compose_cfg("simulate", ["receiver=single_antenna", "seed=3",
                                            "receiver.position.rate=10"])).iloc[900:1500]
    return (log[["x_m", "y_m", "psi_m"]].to_numpy(float), log[["V", "delta"]].to_numpy(float),
            receiver(log))


def _blind(obs: Observer, m: np.ndarray, u: np.ndarray, r: np.ndarray, n: int
           ) -> tuple[int, np.ndarray, np.ndarray]:
    """The slice's first row with a heading, and (T,) bool: the rows whose window of n holds
    none, and those whose window the car stood still for."""
    rows, _ = obs._runner.log_rows(Measurements.of(m, r), u, None)
    heading = np.isfinite(rows[:, 2]) | np.isfinite(rows[:, 6])
    blind = np.array([k >= n - 1 and not heading[k - n + 1:k + 1].any() for k in range(len(m))])
    still = np.array([k >= n - 1 and (u[k - n + 1:k + 1, 0] == 0).all() for k in range(len(m))])
    first = int(np.argmax(heading))
    assert blind[first:].sum() > 200 and (blind & still).sum() > 200  # a long stop
    return first, blind, still


def test_through_a_stop_the_window_filter_holds_the_heading_the_car_stopped_with():
    m, u, r = _stop()
    n = 20
    torch.manual_seed(0)
    net = WindowNet("filternet", n, "frame", fixes=True, receiver=True).eval()
    obs = Observer.from_net(net, form="window")
    est, valid = obs.run(m, u, receiver=r)
    first, blind, still = _blind(obs, m, u, r, n)
    assert valid[first:].all() and np.isfinite(est[first:]).all()
    k = np.flatnonzero(blind & still)  # a standing car does not turn
    np.testing.assert_allclose(est[k, 2], est[k - n + 1, 2], rtol=0, atol=1e-9)
    obs.reset()
    stepped = step_log(obs, m, u, r)
    np.testing.assert_allclose(np.array([s.state for s in stepped])[first:], est[first:],
                               rtol=0, atol=1e-9)
    assert [s.valid for s in stepped] == list(valid)


def test_a_cnn_gives_none_where_its_window_holds_no_heading_and_names_the_filter_that_does():
    m, u, r = _stop()
    n = 20
    torch.manual_seed(0)
    obs = Observer.from_net(WindowNet("cnn", n, "frame", fixes=True, receiver=True).eval())
    est, valid = obs.run(m, u, receiver=r)
    first, blind, _ = _blind(obs, m, u, r, n)
    assert not valid[blind].any() and np.isnan(est[blind]).all()
    assert valid[max(first, n - 1):][~blind[max(first, n - 1):]].all()
    obs.reset()
    said = step_log(obs, m, u, r)
    k = int(np.flatnonzero(blind)[0])
    assert said[k].reason == (
        "no heading in the last 20 steps (0.4 s): cnn-N20 reads the heading from its window's "
        "psi_m or course over ground, and a car that stood or crept that long gave none (the "
        "window filter, model=filternet, carries its own through a stop)")
