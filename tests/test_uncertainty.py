"""Covariances, their calibration (NEES) and RTS smoothing of the classical observers."""

import numpy as np
import pandas as pd
import pytest

from helpers import compose_cfg
from lbo.core.angles import wrap_angle
from lbo.evaluate import evaluate
from lbo.filters.classical import estimate as run_classical
from lbo.filters.smoother import rts
from lbo.scoring.grid import load_test
from lbo.scoring.metrics import nees_table
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

VEHICLE, NOISE = Vehicle(), Noise.preset("paper")


# ------------------------------------------------------------------ RTS == filterpy, linear


def test_rts_matches_filterpys_rts_smoother_on_a_linear_system():
    from filterpy.kalman import KalmanFilter

    rng = np.random.default_rng(3)
    n, T = 3, 120
    F = np.eye(n) + 0.1 * rng.standard_normal((n, n))
    F *= 0.97 / np.abs(np.linalg.eigvals(F)).max()
    Q, R = np.diag([0.1, 0.2, 0.05]), np.diag([1.0, 2.0, 0.5])
    xs = np.zeros((T, n))
    for k in range(1, T):
        xs[k] = F @ xs[k - 1] + rng.multivariate_normal(np.zeros(n), Q)
    zs = xs + rng.multivariate_normal(np.zeros(n), R, size=T)
    kf = KalmanFilter(dim_x=n, dim_z=n)
    kf.F, kf.H, kf.Q, kf.R, kf.P = F, np.eye(n), Q, R, 4.0 * np.eye(n)
    kf.x = np.zeros((n, 1))
    x_f, P_f, x_p, P_p = kf.batch_filter(zs[..., None])
    want, P_want, _, _ = kf.rts_smoother(x_f, P_f)
    x_f, x_p, want = x_f[..., 0], x_p[..., 0], want[..., 0]
    cross = P_f @ F.T  # C_{k+1} = P_{k|k} F^T, stored at k+1
    cross = np.concatenate([np.zeros((1, n, n)), cross[:-1]])
    got, P_got = rts(x_f[None], P_f[None], x_p[None], P_p[None], cross[None], angles=())
    np.testing.assert_allclose(got[0], want, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(P_got[0], P_want, rtol=1e-10, atol=1e-12)
    # padding after a trajectory's end does not flow back into it
    pad = lambda a: np.concatenate([a, np.repeat(a[-1:] * 0 + a[:1], 30, axis=0)])  # noqa: E731
    got_pad, _ = rts(*(pad(a)[None] for a in (x_f, P_f, x_p, P_p, cross)), angles=(),
                     lengths=np.array([T]))
    np.testing.assert_allclose(got_pad[0, :T], want, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------------ NEES: the metric itself


def test_nees_table_puts_a_consistent_covariance_inside_the_band_and_a_bold_one_outside():
    rng = np.random.default_rng(0)
    G, T = 30, 200
    L = np.array([[0.3, 0, 0], [0.1, 0.2, 0], [0, 0.01, 0.02]])
    cov = np.broadcast_to(L @ L.T, (G, T, 3, 3))
    err = rng.standard_normal((G, T, 3)) @ L.T
    truth = np.zeros((G, T, 3))
    mask, alpha = np.ones((G, T), bool), np.repeat([1.0, 2.0], G // 2)
    good = nees_table("good", err, cov, truth, mask, alpha)
    assert list(good["alpha"]) == [1.0, 2.0]
    assert good["inside"].all() and np.allclose(good["nees"], 3.0, atol=0.15)
    # the band of the mean over G/2 = 15 runs: chi-square with 45 dof, over 15
    assert good["low"].iloc[0] == pytest.approx(28.366 / 15, abs=1e-3)
    assert good["high"].iloc[0] == pytest.approx(65.410 / 15, abs=1e-3)
    bold = nees_table("bold", err, cov / 4, truth, mask, alpha)
    assert not bold["inside"].any() and np.allclose(bold["nees"], 12.0, rtol=0.1)
    timid = nees_table("timid", err, cov * 4, truth, mask, alpha)
    assert not timid["inside"].any()
    # heading errors wrap: an error of 2 pi is none
    wrapped = err.copy()
    wrapped[..., 2] += 2 * np.pi
    np.testing.assert_allclose(nees_table("w", wrapped, cov, truth, mask, alpha)["nees"],
                               good["nees"])


# ------------------------------------------------------------ the classical filters' NEES


@pytest.fixture(scope="module")
def test_grid(smoke_data):
    return load_test(smoke_data / "test.parquet")


def _nees(name, arr):
    est, cov = run_classical(name, arr.m, arr.u, VEHICLE, NOISE, alpha=arr.alpha)
    return nees_table(name, est, cov, arr.z, arr.mask, arr.alpha).set_index("alpha")


@pytest.mark.parametrize("name", ["oracle", "adaptive"])
def test_filters_told_or_estimating_the_noise_are_calibrated_at_every_alpha(test_grid, name):
    table = _nees(name, test_grid)
    scored = table.loc[table.index > 0]  # at alpha = 0 the oracle's R is zero: no NEES
    assert len(scored) == 6 and scored["inside"].all(), scored


def test_the_ekf_at_r_alpha_1_is_overconfident_at_high_noise(test_grid):
    table = _nees("ekf", test_grid)
    assert table.loc[1.0, "inside"]
    assert not table.loc[[4.0, 5.0, 6.0], "inside"].any()
    assert table.loc[6.0, "nees"] > 5 * table.loc[6.0, "high"]


def test_the_ukf_covariance_is_near_the_ekfs(test_grid):
    ekf, ukf = _nees("ekf", test_grid), _nees("ukf", test_grid)
    np.testing.assert_allclose(ukf["nees"], ekf["nees"], rtol=0.15)


# ---------------------------------------------------------------------------- smoothing


def _rmse(est, arr):
    e = est - arr.z
    e[..., 2] = wrap_angle(e[..., 2])
    return np.sqrt((e[arr.mask] ** 2).mean(0))


@pytest.mark.parametrize("name", ["ekf", "oracle", "adaptive", "ukf"])
def test_smoothing_beats_filtering_and_narrows_the_covariance(test_grid, name):
    arr = test_grid
    kw = {"alpha": arr.alpha, "lengths": arr.lengths}
    filt, P_f = run_classical(name, arr.m, arr.u, VEHICLE, NOISE, **kw)
    smooth, P_s = run_classical(name, arr.m, arr.u, VEHICLE, NOISE, smooth=True, **kw)
    noisy = arr.alpha >= 1
    gain = 1 - _rmse(smooth[noisy], _sel(arr, noisy)) / _rmse(filt[noisy], _sel(arr, noisy))
    assert (gain[:2] > 0.1).all(), gain
    ok = arr.mask[noisy]
    assert (np.trace(P_s[noisy][ok], axis1=-2, axis2=-1)
            <= np.trace(P_f[noisy][ok], axis1=-2, axis2=-1) + 1e-12).all()


def _sel(arr, which):
    return arr.take(which)


# ------------------------------------------------------------------- lbo.evaluate options


def test_evaluate_writes_calibration_and_smoothed_scores(tmp_path, smoke_data):
    cfg = compose_cfg("evaluate", ["data=smoke", f"data.root={smoke_data.parent}",
                                   f"output_dir={tmp_path}", "observers=[ekf,oracle]",
                                   "calibration=true", "smooth=true"])
    table = pd.read_csv(evaluate(cfg))
    assert {"ekf-smoothed", "oracle-smoothed"} <= set(table["observer"])
    both = table[table["alpha"] == 6.0].set_index("observer")["nrmse"]
    assert both["oracle-smoothed"] < 0.9 * both["oracle"]
    nees = pd.read_csv(tmp_path / "nees.csv")
    assert {"observer", "alpha", "nees", "low", "high", "inside"} <= set(nees.columns)
    oracle = nees[(nees["observer"] == "oracle") & (nees["alpha"] > 0)]
    assert oracle["inside"].all()
    assert (tmp_path / "nees.png").stat().st_size > 10_000
