"""Simulated single-antenna logs beside an oracle (issue 36): the gyro's true bias in a
simulated log, the oracle gyro EKF told the true noise and bias (or the bias's statistics
only; or also the fixes' drift and latency), pooling scores over drives,
and ``python -m lbo.receiver_study`` end to end at smoke scale."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from helpers import compose_cfg
from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters.gyro_noise import FixDrift
from lbo.scoring import receiver as scoring
from lbo.scoring.metrics import rmse
from lbo.sim.noise import Noise
from lbo.sim.receiver import ReceiverSpec
from lbo.sim.vehicle import Vehicle
from lbo.simulate import simulate


@pytest.fixture(scope="module")
def free_drive() -> pd.DataFrame:
    return simulate(compose_cfg("simulate", ["manoeuvre=free_drive", "duration=60",
                                             "receiver=single_antenna", "seed=3"]))


def test_a_simulated_receivers_log_holds_the_gyros_true_bias(free_drive):
    """r_m less b is the true yaw rate plus the gyro's white noise (0.005 rad/s), and b is
    a bias: it starts away from 0 and walks slowly."""
    rate = wrap_angle(np.diff(free_drive["psi"].to_numpy())) / Vehicle().dt
    noise = free_drive["r_m"].to_numpy()[:-1] - free_drive["b"].to_numpy()[:-1] - rate
    assert abs(noise.std() - ReceiverSpec().gyro.white) < 5e-4
    assert abs(noise.mean()) < 5e-4
    b = free_drive["b"].to_numpy()
    assert abs(b[0]) > 1e-4 and np.abs(np.diff(b)).max() < 1e-4


def test_the_oracle_gyro_ekf_heads_closer_than_the_gyro_ekf_with_its_defaults(free_drive):
    """Every estimate finite. Measured (60 s, alpha 1): heading RMSE 3.2 mrad told the noise
    and bias, 7.0 with the gyro EKF's defaults."""
    vehicle, noise = Vehicle(), Noise.preset("paper")
    spec = ReceiverSpec()
    oracle = scoring.oracle_gyro(free_drive, vehicle, spec.position.sigma,
                                 noise.process_sigma[0], spec.gyro.sigma)
    assert np.isfinite(oracle).all()
    table, _ = scoring.score(free_drive, ["gyro"], vehicle, noise, None,
                             {scoring.ORACLE: oracle})
    rows = table.set_index("estimator")
    gyro = rows.loc["gyro, receiver's accuracy and velocity"]
    assert rows.loc[scoring.ORACLE, "psi_mrad"] < 0.6 * gyro["psi_mrad"]
    assert scoring.ratio_to(table, scoring.ORACLE)[-1] == 1.0
    with pytest.raises(LboError, match=r"^oracle_gyro: the log has no 'b' column"):
        scoring.oracle_gyro(free_drive.drop(columns="b"), vehicle, 1.0, 0.1, 0.005)


def test_the_noise_oracle_learns_the_bias_from_the_log(free_drive):
    """Told the bias's statistics, not its value, the oracle runs on the gyro as logged (no
    ``b`` column needed): its heading is worse than the oracle told the bias, better than
    the gyro EKF's defaults, and its bias state is what moves it (a bias told to be 0
    with no walk is the oracle on an uncorrected gyro: measured (60 s, alpha 1), 9.3 mrad
    against 6.1)."""
    vehicle, spec = Vehicle(), ReceiverSpec()
    told = (vehicle, spec.position.sigma, Noise.preset("paper").process_sigma[0],
            spec.gyro.sigma)
    oracle = scoring.oracle_gyro(free_drive, *told)
    blind = free_drive.drop(columns="b")
    fair = scoring.oracle_gyro(blind, *told, bias=(spec.gyro_bias, spec.gyro_walk))
    frozen = scoring.oracle_gyro(blind, *told, bias=(1e-6, 1e-12))
    rows = scoring.scored_rows(free_drive)
    truth = free_drive[["x", "y", "psi"]].to_numpy()

    def heading(est):
        return float(np.sqrt(np.mean(wrap_angle(est[rows, 2] - truth[rows, 2]) ** 2)))

    table, _ = scoring.score(free_drive, ["gyro"], Vehicle(), Noise.preset("paper"))
    defaults = table.set_index("estimator").loc["gyro, receiver's accuracy and velocity"]
    assert heading(oracle) < heading(fair) < 1e-3 * defaults["psi_mrad"]
    assert heading(frozen) > 1.3 * heading(fair)


def test_the_full_oracle_told_the_drift_and_latency_too_tracks_closer(free_drive):
    """Told the fixes' drift (two more states, R the white part) and the channels' latency
    (fixes and velocities brought forward to their row), the oracle's position and heading
    come closer to the truth; the same filter told only the bias's statistics is further
    from it in heading. Measured (60 s, alpha 1): x 0.61 m against 0.84 (the 50 ms latency
    is most of it), heading 3.0 mrad against 3.2, and 4.8 with the bias estimated."""
    vehicle, spec = Vehicle(), ReceiverSpec()
    q = Noise.preset("paper").process_sigma[0]
    timing = {"drift": FixDrift(spec.position.drift, spec.position.tau),
              "latency": (spec.position.latency, spec.velocity.latency)}
    oracle = scoring.oracle_gyro(free_drive, vehicle, spec.position.sigma, q, spec.gyro.sigma)
    told = (vehicle, spec.position.white, q, spec.gyro.sigma)
    full = scoring.oracle_gyro(free_drive, *told, **timing)
    fair = scoring.oracle_gyro(free_drive.drop(columns="b"), *told,
                               bias=(spec.gyro_bias, spec.gyro_walk), **timing)
    rows = scoring.scored_rows(free_drive)
    truth = free_drive[["x", "y", "psi"]].to_numpy()
    e_oracle, e_full, e_fair = (rmse(e, truth, rows) for e in (oracle, full, fair))
    assert e_full[0] < 0.8 * e_oracle[0] and e_full[2] < e_oracle[2]
    assert e_fair[2] > 1.3 * e_full[2]


def test_pooled_scores_are_those_of_the_drives_rows_as_one():
    a = pd.DataFrame({"estimator": ["p", "q"], "x_m": [1.0, 2.0], "y_m": [0.0, 1.0],
                      "psi_mrad": [3.0, 4.0], "rows": [100, 100]})
    b = a.assign(x_m=[2.0, 2.0], rows=[300, 100])
    out = scoring.pool([a, b])
    assert out["x_m"].tolist() == pytest.approx([np.sqrt((100 + 4 * 300) / 400), 2.0])
    assert out["rows"].tolist() == [400, 200]
    with pytest.raises(LboError, match=r"^pool: expected score tables of the same estimators"):
        scoring.pool([a, b.iloc[::-1]])


def test_receiver_study_scores_every_observer_against_the_oracle(tmp_path, robust_smoke):
    from lbo.receiver_study import LEARNED, receiver_study

    cfg = compose_cfg("receiver_study", [f"output_dir={tmp_path}", "alphas=[1,6]", "drives=1",
                                         "duration=30", "learn.drives=2", "learn.epochs=1",
                                         "observers=[ekf,gyro]",
                                         f"nets=[{robust_smoke['out']['checkpoint']}]"])
    table = receiver_study(cfg)["table"]
    written = pd.read_csv(tmp_path / "results.csv")
    assert written["estimator"].tolist() == table["estimator"].tolist()
    assert set(written["alpha"]) == {1.0, 6.0}
    assert LEARNED in set(written["estimator"])
    # the robust observer, in its recursive form, reads the receiver's channels too
    assert f"filternet-N40 (recursive), {scoring.NET_ROW}" in set(written["estimator"])
    oracle = written[written["estimator"] == scoring.ORACLE]
    assert (oracle["vs_oracle"] == 1.0).all()
    fair = written[written["estimator"] == scoring.NOISE_ORACLE]
    assert (fair["vs_noise_oracle"] == 1.0).all() and (fair["vs_oracle"] > 1.0).all()
    full = written[written["estimator"] == scoring.FULL_ORACLE]
    assert (full["vs_full_oracle"] == 1.0).all()
    assert scoring.FULL_NOISE_ORACLE in set(written["estimator"])
    # alpha scales the receiver's errors: the raw fixes' position error grows with it
    raw = written[written["estimator"] == scoring.RAW].set_index("alpha")
    assert raw.loc[6.0, "x_m"] > 3 * raw.loc[1.0, "x_m"]
    assert np.isfinite(written[["x_m", "y_m", "psi_mrad", "vs_oracle", "vs_noise_oracle",
                                "vs_full_oracle"]]).all().all()
    for name in ("results.md", "ratios.png", "gyro_noise.json", "gyro_noise_history.csv"):
        assert (tmp_path / name).stat().st_size > 0


@pytest.mark.parametrize("override, line", [
    ("alphas=[]", r"^alphas must be a list of noise scales >= 0, got \[\]$"),
    ("learn.alpha_range=[6,1]", r"^learn.alpha_range must be \[low, high\] with high >= low"),
    ("observers=[kalman]", r"^observers"),
])
def test_receiver_study_refuses_bad_settings_in_one_line(tmp_path, override, line):
    from lbo.receiver_study import receiver_study

    cfg = compose_cfg("receiver_study", [f"output_dir={tmp_path}", override])
    with pytest.raises(LboError, match=line):
        receiver_study(cfg)
    assert not any(tmp_path.iterdir())  # refused before anything is written


def test_the_plot_draws_every_estimator_however_many_nets_it_scores(tmp_path):
    from lbo.receiver_study import plot

    names = [f"net {i} (window), receiver's accuracy and velocity" for i in range(14)]
    results = pd.DataFrame([{"estimator": n, "alpha": a, "vs_oracle": 1.0 + i / 10}
                            for i, n in enumerate(names) for a in (1.0, 3.0)])
    plot(results, tmp_path / "ratios.png")
    assert (tmp_path / "ratios.png").stat().st_size > 10_000


def test_the_ratio_on_the_same_rows_leaves_out_the_rows_one_has_none_for():
    """An estimator without estimates on some rows is measured against the reference on the
    rows both hold; the raw fixes (no estimates) get none, printed as a dash."""
    g = np.random.default_rng(3)
    truth = g.normal(size=(100, 3))
    ref = truth + g.normal(scale=[1.0, 2.0, 0.1], size=(100, 3))
    est = truth + g.normal(scale=[0.5, 1.0, 0.05], size=(100, 3))
    ref[:60] *= 10.0  # the reference is far worse on the rows est has none for
    est[:60] = np.nan
    table = pd.DataFrame({"estimator": ["raw", "ref", "est"], "x_m": 1.0, "y_m": 1.0,
                          "psi_mrad": 1.0})
    got = scoring.ratio_on_same_rows(table, {"ref": ref, "est": est}, truth, "ref")
    rows = np.arange(100) >= 60
    assert np.isnan(got[0]) and got[1] == 1.0
    assert got[2] == pytest.approx(scoring.measure_ratio(est, ref, truth, rows), rel=1e-12)
    assert 0.4 < got[2] < 0.6  # about half, as drawn; over every row it would be far less
    assert np.isnan(scoring.ratio_on_same_rows(table, {"est": est}, truth, "ref")).all()
    assert scoring.markdown(table.assign(v=got), "v").splitlines()[2] == \
        "| raw | 1.00 | 1.00 | 1.0 | - |"


def test_moving_rows_are_those_with_a_course_in_their_last_seconds():
    """A car that drives, stands 3 s and drives off: the first 9 rows of the stop are moving
    (their last 10 rows, 1 s, hold a course), the rest of the stop is not; the ratio can be
    taken over the moving rows alone."""
    dt, t = 0.1, 100
    v = np.full(t, 10.0)
    v[40:70] = 0.0
    log = pd.DataFrame({"x_m": np.nan, "y_m": np.nan, "psi_m": np.nan, "V": v,
                        "ve_m": v, "vn_m": 0.0, "sv_m": 0.1}, index=range(t))
    moving = scoring.moving_rows(log, dt, seconds=1.0)
    np.testing.assert_array_equal(np.flatnonzero(~moving), np.arange(49, 70))  # 10 rows
    truth = np.zeros((t, 3))
    ref, est = np.ones((t, 3)), np.ones((t, 3))
    est[~moving] = 3.0  # worse where the car stands only
    table = pd.DataFrame({"estimator": ["ref", "est"], "x_m": 1.0, "y_m": 1.0,
                          "psi_mrad": 1.0})
    got = scoring.ratio_on_same_rows(table, {"ref": ref, "est": est}, truth, "ref", moving)
    np.testing.assert_allclose(got, [1.0, 1.0])
    assert scoring.ratio_on_same_rows(table, {"ref": ref, "est": est}, truth, "ref")[1] > 1.5
