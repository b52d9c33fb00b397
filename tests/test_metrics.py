"""RMSE, NRMSE and the per-alpha score table."""

from __future__ import annotations

import numpy as np
import pytest

from lbo.core.errors import LboError
from lbo.scoring.metrics import PAPER_REFERENCE, SCORE_COLUMNS, nrmse, rmse, score_table


def test_rmse_of_known_errors():
    truth = np.zeros((4, 3))
    est = np.array([[1.0, 2.0, 0.1], [-1.0, 2.0, -0.1], [1.0, -2.0, 0.1], [-1.0, -2.0, 0.1]])
    np.testing.assert_allclose(rmse(est, truth), [1.0, 2.0, 0.1])


def test_heading_error_is_wrapped():
    truth = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -3.1]])
    est = np.array([[0.0, 0.0, 2 * np.pi - 0.01], [0.0, 0.0, 3.1]])  # 0.01 and 2pi - 6.2
    expected = np.sqrt((0.01**2 + (2 * np.pi - 6.2) ** 2) / 2)
    np.testing.assert_allclose(rmse(est, truth)[2], expected)


def test_mask_and_batch_dims():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(2, 5, 6, 3))
    est = truth + 1.0
    est[..., :2, :] = np.nan  # unscored steps may hold anything
    mask = np.ones((2, 5, 6), dtype=bool)
    mask[..., :2] = False
    out = rmse(est, truth, mask)
    assert out.shape == (2, 5, 3)
    np.testing.assert_allclose(out, 1.0)
    mask[0, 0] = False  # nothing scored: NaN, not an error
    assert np.all(np.isnan(rmse(est, truth, mask)[0, 0]))
    with pytest.raises(LboError, match="mask"):
        rmse(est, truth, mask[..., 1:])


def test_nrmse():
    assert nrmse(np.array(PAPER_REFERENCE)) == pytest.approx(1.0, abs=1e-15)
    assert nrmse(2 * np.array(PAPER_REFERENCE), PAPER_REFERENCE) == pytest.approx(2.0)
    assert nrmse([0.24, 0, 0]) == pytest.approx(np.sqrt(1 / 3))
    batch = nrmse(np.array([[1.0, 1.0, 1.0], [2.0, 2.0, 2.0]]), (1.0, 1.0, 1.0))
    np.testing.assert_allclose(batch, [1.0, 2.0])


def test_score_table_pools_points_per_alpha():
    # alpha 1: trajectory 0 has 4 scored errors of 1, trajectory 2 has 1 scored error of 3;
    # pooled RMSE is sqrt((4 + 9) / 5), not the mean of per-trajectory RMSEs (2.0).
    truth = np.zeros((3, 4, 3))
    est = np.zeros((3, 4, 3))
    est[0, :, 0] = 1.0
    est[1, :, 1] = 0.5
    est[2, :, 0] = 3.0
    mask = np.ones((3, 4), dtype=bool)
    mask[2, 1:] = False
    alpha = np.array([1.0, 0.0, 1.0])
    table = score_table("ekf", est, truth, mask, alpha, ref=(1.0, 1.0, 1.0))
    assert list(table.columns) == SCORE_COLUMNS
    assert table["alpha"].tolist() == [0.0, 1.0]  # sorted
    assert set(table["observer"]) == {"ekf"}
    a0, a1 = table.iloc[0], table.iloc[1]
    np.testing.assert_allclose([a0.rmse_x, a0.rmse_y, a0.rmse_psi], [0.0, 0.5, 0.0])
    np.testing.assert_allclose([a1.rmse_x, a1.rmse_y, a1.rmse_psi], [np.sqrt(13 / 5), 0, 0])
    np.testing.assert_allclose(table["nrmse"], [0.5 / np.sqrt(3), np.sqrt(13 / 15)])


def test_score_table_matches_rmse_on_each_level():
    rng = np.random.default_rng(1)
    alpha = np.repeat([0.0, 0.25, 6.0], 4)
    truth = rng.normal(size=(12, 50, 3))
    est = truth + rng.normal(size=truth.shape) * (1 + alpha)[:, None, None]
    mask = rng.random((12, 50)) > 0.2
    table = score_table("cnn", est, truth, mask, alpha)
    for row in table.itertuples():
        sel = alpha == row.alpha
        expected = rmse(est[sel].reshape(-1, 3), truth[sel].reshape(-1, 3), mask[sel].ravel())
        np.testing.assert_allclose([row.rmse_x, row.rmse_y, row.rmse_psi], expected)
        assert row.nrmse == pytest.approx(nrmse(expected))
