"""Kalman baselines and the PCRB on simulated bicycle trajectories (paper noise preset)."""

from __future__ import annotations

import numpy as np
import pytest

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters import kalman as filters
from lbo.filters.pcrb import pcrb
from lbo.filters.reference import run_filterpy_ekf, ukf_filterpy_batch
from lbo.filters.unscented import ukf_batch
from lbo.scoring.metrics import nrmse, rmse
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle, measure, simulate

VEHICLE = Vehicle()
NOISE = Noise.preset("paper")
REF = (0.27, 0.27, 4.7e-3)  # about the EKF at alpha=1 under this preset; weights only


def smooth_inputs(g: int, t: int, rng: np.random.Generator) -> np.ndarray:
    """(G, T, 2): V in 5..15 m/s and delta within +-0.1 rad, slow random sinusoids."""
    time = np.arange(t) * VEHICLE.dt
    freq = rng.uniform(0.05, 0.3, (g, 2, 1))
    phase = rng.uniform(0, 2 * np.pi, (g, 2, 1))
    v = 10 + 5 * np.sin(2 * np.pi * freq[:, 0] * time + phase[:, 0])
    delta = 0.1 * np.sin(2 * np.pi * freq[:, 1] * time + phase[:, 1])
    return np.stack([v, delta], axis=-1)


def make_batch(g: int, t: int, alpha: float | np.ndarray, seed: int):
    """True states z, inputs u and measurements m, each (G, T, .), at noise level alpha."""
    rng = np.random.default_rng(seed)
    u = smooth_inputs(g, t, rng)
    z0 = np.column_stack([rng.normal(0, 50, g), rng.normal(0, 50, g),
                          rng.uniform(-np.pi, np.pi, g)])
    z = simulate(z0, u, VEHICLE.dt, VEHICLE.wheelbase, np.array(NOISE.process_sigma), rng)
    sigma = NOISE.meas(np.broadcast_to(np.asarray(alpha, float), (g,)))[:, None, :]
    return z, u, measure(z, sigma, rng)


def pooled(est: np.ndarray, z: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(3,) RMSE over every step of every trajectory."""
    return rmse(est.reshape(1, -1, 3), z.reshape(1, -1, 3),
                None if mask is None else mask.reshape(1, -1))[0]


# ----------------------------------------------------------------- batched EKF == filterpy


def test_ekf_batch_matches_filterpy_loop():
    z, u, m = make_batch(3, 300, [0.5, 1.0, 4.0], seed=1)
    m[..., 2] = wrap_angle(m[..., 2])  # headings given wrapped: residuals must handle it
    R = np.stack([NOISE.R(a) for a in (0.5, 1.0, 4.0)])
    ref = np.stack([run_filterpy_ekf(m[i], u[i], VEHICLE, NOISE.Q, R[i])
                    for i in range(3)])
    np.testing.assert_allclose(filters.ekf_batch(m, u, VEHICLE, NOISE.Q, R).mean, ref,
                               rtol=0, atol=1e-9)


def test_shared_R_equals_broadcast_R():
    z, u, m = make_batch(4, 200, 2.0, seed=2)
    shared = filters.ekf_batch(m, u, VEHICLE, NOISE.Q, NOISE.R(2.0))
    per_traj = filters.ekf_batch(m, u, VEHICLE, NOISE.Q, np.tile(NOISE.R(2.0), (4, 1, 1)))
    np.testing.assert_array_equal(shared.mean, per_traj.mean)
    np.testing.assert_array_equal(shared.cov, per_traj.cov)


def test_the_covariances_and_the_start():
    z, u, m = make_batch(2, 50, 1.0, seed=3)
    est, P = filters.ekf_batch(m, u, VEHICLE, NOISE.Q, NOISE.R(1.0))
    assert est.shape == (2, 50, 3) and P.shape == (2, 50, 3, 3)
    np.testing.assert_array_equal(est[:, 0], m[:, 0])
    np.testing.assert_allclose(P[:, 0], np.broadcast_to(NOISE.R(1.0), (2, 3, 3)))
    np.testing.assert_allclose(P, P.swapaxes(-1, -2), atol=1e-15)
    assert np.all(np.linalg.eigvalsh(P) > 0)


def test_with_their_covariances_the_filters_give_a_typed_posterior():
    """Every classical observer's result is a Posterior (mean, cov), started at
    the first row or at the first fix (a log whose first rows hold none)."""
    from lbo.filters.classical import estimate
    from lbo.filters.stepper import Posterior

    z, u, m = make_batch(2, 50, 1.0, seed=3)
    late = m.copy()
    late[:, :5] = np.nan
    for name in ("ekf", "ukf", "adaptive", "oracle"):
        for rows in (m, late):
            post = estimate(name, rows, u, VEHICLE, NOISE)
            assert isinstance(post, Posterior), name
            assert post.mean.shape == (2, 50, 3) and post.cov.shape == (2, 50, 3, 3)
            # the same run twice gives the same numbers
            again = estimate(name, rows, u, VEHICLE, NOISE)
            np.testing.assert_array_equal(post.mean, again.mean)


def test_heading_branch_does_not_matter():
    """Wrapped and continuous heading measurements give the same (wrapped) estimates."""
    z, u, m = make_batch(3, 300, 1.0, seed=4)
    assert np.ptp(z[..., 2]) > np.pi  # the trajectories cross +-pi somewhere
    wrapped = m.copy()
    wrapped[..., 2] = wrap_angle(m[..., 2])
    for run in (lambda mm: filters.ekf_batch(mm, u, VEHICLE, NOISE.Q, NOISE.R(1.0)).mean,
                lambda mm: filters.adaptive_ekf_batch(mm, u, VEHICLE, NOISE.Q,
                                                      NOISE.R(1.0)).mean):
        a, b = run(m), run(wrapped)
        np.testing.assert_allclose(a[..., :2], b[..., :2], atol=1e-9)
        np.testing.assert_allclose(wrap_angle(a[..., 2] - b[..., 2]), 0, atol=1e-9)


def test_bad_shapes_raise():
    z, u, m = make_batch(2, 20, 1.0, seed=5)
    with pytest.raises(LboError, match="R must be"):
        filters.ekf_batch(m, u, VEHICLE, NOISE.Q, np.eye(2))
    with pytest.raises(LboError, match="inputs u"):
        filters.ekf_batch(m, u[:, :-1], VEHICLE, NOISE.Q, NOISE.R())
    with pytest.raises(LboError, match="forgetting"):
        filters.adaptive_ekf_batch(m, u, VEHICLE, NOISE.Q, NOISE.R(), forgetting=1.5)


# ----------------------------------------------------------------- who beats whom

ALPHAS = (1.0, 3.0, 6.0)
PER_ALPHA = 160  # 160 x 600 steps: pooled RMSEs move by about 1 % between seeds


@pytest.fixture(scope="module")
def grid():
    """Per alpha: RMSE (3,) of the PCRB, oracle, fixed (alpha=1 R) and adaptive EKFs."""
    out = {}
    for i, alpha in enumerate(ALPHAS):
        z, u, m = make_batch(PER_ALPHA, 600, alpha, seed=10 + i)
        settled = np.zeros(z.shape[:2], dtype=bool)
        settled[:, 150:] = True
        adaptive = filters.adaptive_ekf_batch(m, u, VEHICLE, NOISE.Q, NOISE.R(1.0)).mean
        oracle = filters.ekf_batch(m, u, VEHICLE, NOISE.Q, NOISE.R(alpha)).mean
        bound = pcrb(z, u, VEHICLE, NOISE.Q, NOISE.R(alpha), n_mc=20, rng=i)
        out[alpha] = {
            "pcrb": np.sqrt(bound.reshape(-1, 3).mean(axis=0)),
            "oracle": pooled(oracle, z),
            "fixed": pooled(filters.ekf_batch(m, u, VEHICLE, NOISE.Q, NOISE.R(1.0)).mean, z),
            "adaptive": pooled(adaptive, z),
            "oracle_settled": pooled(oracle, z, settled),
            "adaptive_settled": pooled(adaptive, z, settled),
        }
    return out


@pytest.mark.parametrize("alpha", ALPHAS)
def test_oracle_reaches_pcrb(grid, alpha):
    """The near-linear oracle EKF is efficient: its RMSE equals the bound up to sampling
    noise of the RMSE (about 1 % on the NRMSE, 2 % per variable at this size)."""
    r = grid[alpha]
    assert nrmse(r["pcrb"], REF) <= 1.03 * nrmse(r["oracle"], REF)
    assert nrmse(r["pcrb"], REF) >= 0.97 * nrmse(r["oracle"], REF)
    assert np.all(r["pcrb"] <= 1.06 * r["oracle"])


@pytest.mark.parametrize("alpha", [a for a in ALPHAS if a != 1.0])
def test_oracle_beats_fixed_ekf(grid, alpha):
    assert np.all(grid[alpha]["oracle"] < 0.9 * grid[alpha]["fixed"])


def test_fixed_ekf_is_efficient_at_its_design_point(grid):
    """At alpha=1 the paper's EKF has the right R: its NRMSE is the bound's, to sampling noise."""
    r = grid[1.0]
    assert nrmse(r["fixed"], REF) <= 1.03 * nrmse(r["pcrb"], REF)


@pytest.mark.parametrize("alpha", ALPHAS)
def test_adaptive_close_to_oracle(grid, alpha):
    """Adaptive within 10 % of the oracle; all of the gap is the first second or so, while
    R is being learnt: from step 150 on it is within 2 %."""
    r = grid[alpha]
    ratio = nrmse(r["adaptive"], REF) / nrmse(r["oracle"], REF)
    assert 0.99 <= ratio <= 1.10
    settled = nrmse(r["adaptive_settled"], REF) / nrmse(r["oracle_settled"], REF)
    assert 0.99 <= settled <= 1.02


def test_adaptive_beats_fixed_at_alpha6(grid):
    r = grid[6.0]
    assert nrmse(r["adaptive"], REF) < 0.85 * nrmse(r["fixed"], REF)
    assert np.all(r["adaptive"] < 0.9 * r["fixed"])


# ----------------------------------------------------------------- UKF and alpha = 0


def test_ukf_close_to_ekf_at_alpha1():
    z, u, m = make_batch(4, 500, 1.0, seed=6)
    est_ukf = ukf_batch(m, u, VEHICLE, NOISE.Q, NOISE.R(1.0)).mean
    est_ekf = filters.ekf_batch(m, u, VEHICLE, NOISE.Q, NOISE.R(1.0)).mean
    r_ukf, r_ekf = pooled(est_ukf, z), pooled(est_ekf, z)
    assert np.all(np.abs(r_ukf / r_ekf - 1) < 0.05)  # brief allows 15 %; it is ~0.1 %
    np.testing.assert_array_equal(est_ukf[:, 0], m[:, 0])


def test_alpha0_is_exact_and_finite():
    alpha = np.array([0.0, 0.0, 1.0, 6.0])
    z, u, m = make_batch(4, 200, alpha, seed=7)
    R = NOISE.R(1.0) * (alpha**2)[:, None, None]
    bound = pcrb(z, u, VEHICLE, NOISE.Q, R, n_mc=10, rng=0)
    assert bound.shape == (4, 200, 3) and np.all(np.isfinite(bound))
    np.testing.assert_array_equal(bound[:2], 0.0)
    assert np.all(bound[2:] > 0)
    np.testing.assert_allclose(filters.ekf_batch(m, u, VEHICLE, NOISE.Q, R).mean[:2], z[:2],
                               atol=1e-9)
    for est in (filters.adaptive_ekf_batch(m, u, VEHICLE, NOISE.Q, NOISE.R(1.0)).mean,
                ukf_batch(m, u, VEHICLE, NOISE.Q, R).mean):
        assert np.all(np.isfinite(est))
        assert np.all(pooled(est[:2], z[:2]) < 0.1 * np.array(REF))


def test_batched_ukf_gives_filterpy_numbers_on_the_smoke_grid(smoke_data):
    """The vectorised UKF against filterpy's loop on every trajectory and alpha level of the
    smoke test grid (R at alpha=1, and R at each level's own alpha)."""
    from lbo.filters.classical import measurement_cov
    from lbo.scoring.grid import load_test

    arr = load_test(smoke_data / "test.parquet")
    for R in (NOISE.R(1.0), measurement_cov("oracle", NOISE, arr.alpha, len(arr.alpha))):
        ref = ukf_filterpy_batch(arr.m, arr.u, VEHICLE, NOISE.Q, R)
        new = ukf_batch(arr.m, arr.u, VEHICLE, NOISE.Q, R).mean
        assert np.isfinite(new[arr.mask]).all()
        assert np.abs(new - ref)[arr.mask].max() <= 1e-9


def test_compose_covariance_equals_the_steps_one_by_one():
    """The scan's maps, applied to any P0, give the covariance of K sequential predictions
    (K = 13: not a power of two), in NumPy and in torch."""
    import torch

    from lbo.filters.kalman import compose_covariance

    rng = np.random.default_rng(4)
    K, n = 13, 4
    F = np.eye(n) + 0.1 * rng.standard_normal((K, n, n))
    L = 0.1 * rng.standard_normal((K, n, n))
    Q = L @ L.swapaxes(1, 2)
    P0 = np.eye(n) + 0.05 * np.ones((n, n))
    want, P = [], P0
    for j in range(K):
        P = F[j] @ P @ F[j].T + Q[j]
        want.append(P)
    for to in (np.asarray, torch.from_numpy):
        A, B = compose_covariance(to(F), to(Q))
        got = A @ to(P0) @ A.swapaxes(1, 2) + B
        np.testing.assert_allclose(np.asarray(got), np.array(want), rtol=1e-12, atol=1e-14)
