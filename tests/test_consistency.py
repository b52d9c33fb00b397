"""The consistency test of the gyro EKF's innovations (issue 68, item 7): a gyro biased by
0.5 rad/s (25 sigma of the filter's prior on it) on a log that starts moving left every row
valid while 78% of them lay beyond 3 sigma (mean heading z^2 55). The windowed NIS test
(:mod:`lbo.filters.consistency`) flags such rows and the filter's variances are widened to
learn the bias again; a healthy filter's rows are not flagged."""

from __future__ import annotations

import numpy as np
import pytest

from helpers import compose_cfg, step_log
from helpers.commands import observe
from lbo.core.angles import wrap_angle
from lbo.filters import classical
from lbo.filters.consistency import (
    SIGNIFICANCE,
    WINDOW,
    NisWindow,
    chi2_bounds,
    widen,
)
from lbo.filters.gyro import gyro_ekf_batch
from lbo.filters.update import joseph_update
from lbo.filters.update import nis as normalised
from lbo.logs.io import receiver
from lbo.serve.observer import Observer
from lbo.serve.runners import ClassicalRunner
from lbo.sim.measurements import Measurements
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle
from lbo.simulate import simulate as simulate_log

BIAS = 0.5
"""rad/s added to the gyro: the audit's, 25 times the filter's prior sigma (0.02)."""


def _log(manoeuvre: str, seed: int = 0, bias: float = 0.0) -> dict:
    """lbo's own simulated single-antenna log (fixes at 1 Hz, a gyro at 50 Hz), its gyro
    reading ``bias`` rad/s more."""
    df = simulate_log(compose_cfg("simulate", [f"manoeuvre={manoeuvre}",
                                               "receiver=single_antenna", f"seed={seed}"]))
    df["r_m"] += bias
    return {"df": df, "m": df[["x_m", "y_m", "psi_m"]].to_numpy(float),
            "u": df[["V", "delta"]].to_numpy(float), "r": receiver(df),
            "psi": df["psi"].to_numpy(float)}


def _heading_z2(est: np.ndarray, cov: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """(T,) the squared heading error over the filter's own variance of it."""
    return wrap_angle(est[:, 2] - psi) ** 2 / cov[:, 2, 2]


@pytest.fixture(scope="module")
def biased() -> dict:
    """The audit's case: the slalom (it starts at 11 m/s), its gyro biased by 0.5 rad/s."""
    return _log("slalom", 0, BIAS)


def test_a_gyro_biased_far_beyond_its_prior_is_flagged_and_learned_again(biased):
    """Before: every row valid, 78% beyond 3 sigma, mean z^2 55, heading RMSE 0.24 rad.
    Measured now (the covariance of every row, flagged or not): heading RMSE 0.146 rad, mean
    z^2 4.9; from the first update on (1 s: before it no innovation can tell), 5.6% of the
    rows are valid and beyond 3 sigma, and the valid rows' mean z^2 is 2.8."""
    obs = Observer.load("gyro")
    est, valid = obs.run(biased["m"], biased["u"], receiver=biased["r"])
    runner = ClassicalRunner("gyro", obs.vehicle, obs.noise)
    rows, u = runner.log_rows(Measurements.of(biased["m"], biased["r"]), biased["u"], None)
    _, cov, _ = runner.run(rows, u, np.ones(len(rows), bool))  # every row's, flagged or not
    z2 = _heading_z2(est, cov, biased["psi"])
    first = 50  # the first update after the start: the second fix (1 Hz)
    far = z2 > 9
    assert (~valid).sum() > 40  # the rows from each failed test to the next update
    assert np.mean((far & valid)[first:]) < 0.1   # before: 0.78
    assert z2[first:][valid[first:]].mean() < 5.0  # before: 55
    rmse = float(np.sqrt(np.mean(wrap_angle(est[:, 2] - biased["psi"]) ** 2)))
    assert rmse < 0.18  # before: 0.24


def test_without_relearning_every_row_beyond_3_sigma_after_the_first_update_is_flagged(biased):
    """``relearn=False``: the filter is left sure of its wrong bias, and the test flags what
    it cannot explain: 90% of the rows, every one beyond 3 sigma from the first update on."""
    vehicle, noise = Vehicle(), Noise.preset("paper")
    rows, u = ClassicalRunner("gyro", vehicle, noise).log_rows(
        Measurements.of(biased["m"], biased["r"]), biased["u"], None)
    R = classical.measurement_cov("gyro", noise, 1.0, 1)
    post = gyro_ekf_batch(rows[None], u[None], vehicle, noise.Q, R, relearn=False)
    assert post.checks is not None
    flagged = post.checks.inconsistent[0]
    z2 = _heading_z2(post.mean[0], post.cov[0], biased["psi"])
    assert not (z2 > 9)[50:][~flagged[50:]].any()
    assert flagged.mean() > 0.8
    assert post.checks.reason(0, 0) is None
    why = post.checks.reason(0, int(np.argmax(flagged)))
    assert why is not None and why.startswith("innovations inconsistent with the covariance: "
                                              "NIS ")
    assert f"beyond the {SIGNIFICANCE:.1%} chi-square bound" in why


def test_stepping_flags_the_rows_that_a_run_flags_and_says_why(biased):
    obs = Observer.load("gyro")
    _, valid = obs.run(biased["m"], biased["u"], receiver=biased["r"])
    steps = step_log(obs, biased["m"], biased["u"], biased["r"])
    assert [e.valid for e in steps] == valid.tolist()
    reasons = {e.reason.split(":")[0] for e in steps if not e.valid}
    assert reasons == {"innovations inconsistent with the covariance"}
    assert any("widened" in e.reason for e in steps if not e.valid)


@pytest.mark.parametrize("manoeuvre, seed, bias", [
    ("slalom", 0, 0.0), ("slalom", 1, 0.0), ("hairpin", 0, 0.0), ("figure_eight", 2, 0.0),
    ("stop_and_go", 0, 0.0), ("stop_and_go", 1, 0.0),
    ("stop_and_go", 0, BIAS),  # starts standing: the bias is learned there, honestly
])
def test_a_healthy_filter_has_no_flagged_row(manoeuvre, seed, bias):
    """Measured on every test manoeuvre and the stop-and-go drive, seeds 0, 1, 2 (48 logs):
    no row flagged; the stop-and-go drive with the 0.5 rad/s bias neither (mean z^2 0.79)."""
    log = _log(manoeuvre, seed, bias)
    est, valid = Observer.load("gyro").run(log["m"], log["u"], receiver=log["r"])
    assert valid.all()
    runner = ClassicalRunner("gyro", Vehicle(), Noise.preset("paper"))
    _, cov, _ = runner.run(*runner.log_rows(Measurements.of(log["m"], log["r"]), log["u"], None),
                        np.ones(len(log["m"]), bool))
    assert _heading_z2(est, cov, log["psi"]).mean() < 2.0


def test_lbo_observe_says_how_many_rows_it_flagged(biased, tmp_path):
    biased["df"].to_csv(tmp_path / "log.csv", index=False)
    res = observe("observer=gyro", f"input={tmp_path / 'log.csv'}",
                  f"output={tmp_path / 'est.csv'}", cwd=tmp_path, check=True)
    import pandas as pd

    out = pd.read_csv(tmp_path / "est.csv")
    flagged = int((~out["valid"]).sum())
    assert flagged > 40
    assert (f"consistency: {flagged} rows flagged valid=false: innovations inconsistent with "
            f"the covariance (the NIS of the last {WINDOW} updates beyond its 99.9% "
            "chi-square bound") in res.stdout


def test_the_nis_is_the_textbook_one_of_the_tested_channels():
    """y^T S^-1 y with S the tested channels' block of H P H^T + R, whatever the others."""
    rng = np.random.default_rng(3)
    g, n, p = 5, 4, 5
    A = rng.normal(size=(g, n, n))
    P = A @ A.swapaxes(1, 2) + 0.1 * np.eye(n)
    H = rng.normal(size=(p, n))
    R = np.diag(rng.uniform(0.1, 1.0, p))
    y = rng.normal(size=(g, p))
    held = rng.random((g, p)) < 0.7
    tested = np.array([True, True, False, True, True])
    x = rng.normal(size=(g, n))
    update = joseph_update(x, P, y, H, R, held)
    nis = normalised(update, held, tested)
    assert np.array_equal(normalised(update, held), normalised(update, held, np.ones(p, bool)))
    for i in range(g):
        t = held[i] & tested
        S = H[t] @ P[i] @ H[t].T + R[np.ix_(t, t)]
        want = y[i, t] @ np.linalg.solve(S, y[i, t]) if t.any() else 0.0
        assert nis[i] == pytest.approx(want, rel=1e-12, abs=1e-15)


def test_a_consistent_filter_fails_the_window_test_at_its_significance():
    """NIS drawn as a consistent filter's (chi-square, 1-3 degrees of freedom an update,
    some steps without one): the share of failed tests is 1 - SIGNIFICANCE (0.1%)."""
    rng = np.random.default_rng(0)
    g, steps = 20000, 60
    win = NisWindow(g, 4)
    failed = tested = 0
    for _ in range(steps):
        dof = rng.integers(0, 4, g)
        nis = rng.chisquare(np.maximum(dof, 1)) * (dof > 0)
        win.push(nis, dof)
        failed += int((win.inconsistent & (dof > 0)).sum())
        tested += int((dof > 0).sum())
    assert failed / tested == pytest.approx(1 - SIGNIFICANCE, rel=0.15)
    assert chi2_bounds(3)[0] == np.inf and chi2_bounds(3)[3] == pytest.approx(16.266, abs=1e-3)
    # twice the innovations' variance is found within a window
    win = NisWindow(1, 4)
    for _ in range(WINDOW):
        win.push(np.array([4.0 * 3]), np.array([3]))
    assert win.inconsistent[0] and win.excess()[0] == pytest.approx(4.0)


def test_widening_scales_the_states_variances_and_keeps_p_a_covariance():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(3, 4, 4))
    P = A @ A.swapaxes(1, 2)
    rows = np.array([True, False, True])
    out = widen(P, (2, 3), np.array([9.0, 9.0, 0.5]), rows)
    np.testing.assert_allclose(out[0, 2:, 2:], 9.0 * P[0, 2:, 2:])
    np.testing.assert_allclose(out[0, :2, 2:], 3.0 * P[0, :2, 2:])
    np.testing.assert_array_equal(out[0, :2, :2], P[0, :2, :2])
    np.testing.assert_array_equal(out[1], P[1])  # not a row that failed
    np.testing.assert_array_equal(out[2], P[2])  # never narrowed
    assert (np.linalg.eigvalsh(out) > -1e-12).all()

