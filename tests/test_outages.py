"""GNSS outages (issue 74): the windows are placed where the car moves, the receiver's columns
are blanked there and nothing else is, no blanked fix reaches an observer, and the errors
through them are read as the protocol says."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from helpers import compose_cfg, store_client
from lbo.core.errors import LboError
from lbo.core.paths import CONF_DIR
from lbo.scoring import outages
from lbo.scoring.outages import BLANKED, Outages
from lbo.scoring.receiver import score
from lbo.sim import gyro_drive
from lbo.sim.columns import RECEIVER, STATE
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

VEHICLE = Vehicle()


def test_outages_fall_every_so_often_where_the_car_moves_throughout():
    """Each at the first row 25 s or more after the last began from which the car moves for
    10 s: at 25 s, then not at 50 s (the car stands from 40 to 52 s) but at 52 s, then at
    77 s; the last must fit in the log."""
    dt = 0.1
    t = np.arange(0, 100, dt)
    log = pd.DataFrame({"V": np.where((t >= 40) & (t < 52), 0.0, 10.0)})
    spans = outages.windows(log["V"], Outages(10.0, 25.0), dt)
    np.testing.assert_array_equal(spans, [[250, 350], [520, 620], [770, 870]])
    assert outages.windows(log["V"], Outages(10.0, 25.0), dt, first=300).tolist() == \
        [[550, 650], [800, 900]]
    assert outages.windows(log["V"].iloc[:860], Outages(10.0, 25.0), dt).tolist() == \
        [[250, 350], [520, 620]]
    assert outages.windows(log.assign(V=0.5)["V"], Outages(10.0, 25.0), dt).shape == (0, 2)
    slow = gyro_drive.draw(0).assign(V=0.5)
    with pytest.raises(LboError, match=r"^outages: no window of 10 s fits where the car moves "
                                       r"\(at least 1 m/s throughout\); shorten "
                                       r"outages\.length_s$"):
        outages.place(slow, Outages(10.0, 25.0), VEHICLE.dt)


def test_only_the_receivers_columns_are_blanked_and_only_inside_the_outages():
    log = gyro_drive.draw(0)
    spans = outages.windows(log["V"], Outages(5.0, 15.0), VEHICLE.dt)
    assert len(spans) == 3
    out = outages.blank(log, spans)
    inside = outages.inside(len(log), spans)
    assert inside.sum() == 3 * round(5.0 / VEHICLE.dt)
    assert set(BLANKED) == {"x_m", "y_m", "psi_m", *RECEIVER} - {"r_m"}
    assert out.loc[inside, list(BLANKED)].isna().all().all()
    pd.testing.assert_frame_equal(out[~inside], log[~inside])  # outside: as it was
    kept = [c for c in log.columns if c not in BLANKED]  # the truth, the gyro, the inputs
    pd.testing.assert_frame_equal(out[kept], log[kept])
    assert log.loc[inside, "x_m"].notna().any()  # the log given is not changed


def test_no_fix_inside_an_outage_reaches_an_observer():
    """Planted: the fixes inside the outages moved by kilometres, their velocities by 30 m/s;
    once blanked, every observer's estimate is the same to the bit as on the log as drawn
    (and without the blanking the planted values do change them: the check can fail)."""
    log = gyro_drive.draw(1)
    spans = outages.windows(log["V"], Outages(5.0, 15.0), VEHICLE.dt)
    planted = log.copy()
    rows = outages.inside(len(log), spans)
    planted.loc[rows, ["x_m", "y_m"]] += 3000.0
    planted.loc[rows, ["ve_m", "vn_m"]] += 30.0
    noise = Noise.from_cfg(OmegaConf.load(CONF_DIR / "noise" / "paper.yaml"))
    observers = ["ekf", "ukf", "gyro"]
    _, drawn = score(outages.blank(log, spans), observers, VEHICLE, noise)
    _, moved = score(outages.blank(planted, spans), observers, VEHICLE, noise)
    assert drawn.keys() == moved.keys() and len(drawn) == 5
    for label in drawn:
        np.testing.assert_array_equal(drawn[label], moved[label], err_msg=label)
    _, unblanked = score(planted, ["ekf"], VEHICLE, noise)
    label = "ekf, receiver's accuracy and velocity"
    assert np.nanmax(np.abs(unblanked[label] - drawn[label])) > 100.0


def test_the_errors_through_the_outages_are_read_as_the_protocol_says():
    """Two outages of 1 s at dt 0.5 (rows 2-3 and 6-7), at 2 m/s then 4 m/s (2 m and 4 m
    driven): the estimate is off by (3, 4) m at each end and by 0.1 rad in heading inside."""
    t = 10
    log = pd.DataFrame({"x": np.zeros(t), "y": 0.0, "psi": 0.0,
                        "V": [2.0] * 5 + [4.0] * 5})
    spans = np.array([[2, 4], [6, 8]])
    est = np.zeros((t, 3))
    est[[3, 7], :2] = [3.0, 4.0]  # the ends
    est[[2, 3, 6, 7], 2] = 0.1
    other = np.zeros((t, 3))
    other[[3, 7], 0] = 2.5
    table = outages.score({"a": est, "b": other}, log, spans, 0.5, reference="b")
    a = table.set_index("estimator").loc["a"]
    assert a["outages"] == 2 and a["end_m"] == 5.0 and a["end_worst_m"] == 5.0
    assert a["position_m"] == pytest.approx(np.sqrt(2 * 25 / 4))
    assert a["psi_mrad"] == pytest.approx(100.0)
    assert a["drift_pct"] == pytest.approx(100 * (5 / 2 + 5 / 4) / 2)
    assert a["end_vs_b"] == 2.0
    assert "| a | 3.54 | 100.0 | 5.00 | 5.00 | 187.50 | 2.00 |" in outages.markdown(table)
    curves = outages.curves(est, log[list(STATE)].to_numpy(float), spans)
    np.testing.assert_array_equal(curves, [[0.0, 5.0], [0.0, 5.0]])
    with pytest.raises(LboError, match=r"^outages: no window to score$"):
        outages.score({"a": est}, log, np.zeros((0, 2), int), 0.5)


@pytest.mark.parametrize("length, every, line", [
    (10.0, 10.0, r"^outages\.every_s must be longer than outages\.length_s \(one outage ends "
                 r"before the next begins\), got 10 <= 10$"),
    (-1.0, 25.0, r"^outages\.length_s must be a number of seconds > 0, got -1\.0$"),
    (10.0, True, r"^outages\.every_s must be a number of seconds > 0, got True$"),
    (10.0, "25", r"^outages\.every_s must be a number of seconds > 0, got '25'$"),
])
def test_bad_outages_are_one_line(length, every, line):
    with pytest.raises(LboError, match=line):
        Outages(length, every)


def test_no_length_means_no_outages():
    assert Outages.from_cfg(None) is None
    assert Outages.from_cfg(OmegaConf.create({"length_s": 0, "every_s": 25.0})) is None
    assert Outages.from_cfg(OmegaConf.create({"length_s": 10, "every_s": 25.0})) == \
        Outages(10.0, 25.0)


def test_observe_scores_a_users_log_through_outages_it_cuts(tmp_path):
    """``lbo.observe ... outages.length_s=5 outages.every_s=15``: the log is blanked before
    any observer reads it, the output holds the estimates on the blanked log, and the main
    observer and each compared one are scored through the outages; a log without truth is
    one line."""
    from helpers import observe

    log = gyro_drive.draw(2)
    log.to_csv(tmp_path / "log.csv", index=False)
    res = observe("observer=gyro", f"input={tmp_path / 'log.csv'}", "compare=[ekf]",
                  f"plot={tmp_path / 'est.png'}",
                  f"output={tmp_path / 'est.csv'}", "outages.length_s=5", "outages.every_s=15",
                  cwd=tmp_path, check=True)
    assert "through 3 GNSS outages of 5 s (every 15 s while moving)" in res.stdout
    rows = [line for line in res.stdout.splitlines() if line.startswith(("| gyro", "| ekf"))]
    assert len(rows) == 2, res.stdout
    spans = outages.place(log, Outages(5.0, 15.0), VEHICLE.dt)
    _, alone = score(outages.blank(log, spans), ["gyro"], VEHICLE, Noise.from_cfg(
        OmegaConf.load(CONF_DIR / "noise" / "paper.yaml")))
    est = pd.read_csv(tmp_path / "est.csv")[["x", "y", "psi"]].to_numpy()
    inside = outages.inside(len(log), spans)
    np.testing.assert_allclose(est[inside], alone["gyro, receiver's accuracy and velocity"][
        inside], atol=1e-9)  # the output is the blanked log's
    log.drop(columns=list(STATE)).to_csv(tmp_path / "blind.csv", index=False)
    bad = observe("observer=gyro", f"input={tmp_path / 'blind.csv'}",
                  f"output={tmp_path / 'bad.csv'}", "outages.length_s=5", cwd=tmp_path)
    assert bad.returncode == 2 and bad.stderr.strip().splitlines()[-1] == (
        f"error: outages: scored against the log's truth (x, y, psi); input "
        f"{tmp_path / 'blind.csv'} has none")
    assert not (tmp_path / "bad.csv").exists()


def test_the_simulator_drops_the_fixes_in_the_outages_and_keeps_the_truth(tmp_path):
    """``lbo.simulate ... outages.length_s=10 outages.every_s=25``: the same log as without
    outages but for the receiver's columns, blank on the rows of the windows the protocol
    places (so ``lbo.observe outages=`` with the same settings scores through exactly them),
    and the line it prints counts them."""
    from helpers import cli

    args = ["manoeuvre=stop_and_go", "receiver=single_antenna", "seed=3"]
    plain, cut = tmp_path / "plain.csv", tmp_path / "cut.csv"
    assert cli("lbo.simulate", *args, f"output={plain}").returncode == 0
    res = cli("lbo.simulate", *args, f"output={cut}", "outages.length_s=10",
              "outages.every_s=25")
    assert res.returncode == 0, res.stderr[-2000:]
    before, after = pd.read_csv(plain), pd.read_csv(cut)
    spans = outages.place(before, Outages(10.0, 25.0), VEHICLE.dt)
    assert f", {len(spans)} GNSS outages of 10 s (receiver columns blanked, truth kept)" \
        in res.stdout
    rows = outages.inside(len(before), spans)
    assert len(spans) >= 2 and rows.sum() == 500 * len(spans)  # 10 s at 50 Hz each
    blanked = [c for c in BLANKED if c in before]
    assert after.loc[rows, blanked].isna().all(axis=None)
    pd.testing.assert_frame_equal(after.loc[~rows], before.loc[~rows])
    kept = [c for c in before if c not in blanked]  # the truth, the inputs, the gyro
    pd.testing.assert_frame_equal(after[kept], before[kept])
    assert (before.loc[rows, ["x_m", "y_m"]].notna().any(axis=None))  # there were fixes


def grid(alpha=(1.0, 3.0), t=40, dt=0.5):
    """Two trajectories of ``t`` rows at 2 m/s, the second 10 rows shorter (padded), fixes on
    every row; their truth at rest at the origin."""
    from lbo.sim.schema import Trajectories

    g = len(alpha)
    lengths = np.array([t, t - 10])
    u = np.zeros((g, t, 2))
    u[..., 0] = 2.0
    m = np.ones((g, t, 3))
    return Trajectories(z=np.zeros((g, t, 3)), u=u, m=m,
                        mask=np.arange(t) < lengths[:, None], lengths=lengths,
                        traj=np.arange(g), alpha=np.array(alpha), file=np.full(g, -1))


def test_outages_on_the_test_grid_blank_their_rows_and_are_read_per_noise_level():
    """Outages of 2 s every 5 s at dt 0.5 from the first fix: rows [10, 14) and [20, 24) of
    the 20 s trajectory (a third, [30, 34), also fits), two in the 15 s one (its padding is
    not driven); only the fixes of those rows blanked; the errors read per alpha."""
    arr = grid()
    spans = outages.grid_windows(arr, Outages(2.0, 5.0), 0.5)
    assert spans.tolist() == [[0, 10, 14], [0, 20, 24], [0, 30, 34], [1, 10, 14], [1, 20, 24]]
    blanked = outages.blank_grid(arr, spans)
    inside = outages.grid_inside(arr.m.shape[:2], spans)
    assert inside.sum() == 5 * 4 and inside[0, 10:14].all() and not inside[0, 14]
    assert np.isnan(blanked.m[inside]).all() and np.isfinite(blanked.m[~inside]).all()
    np.testing.assert_array_equal(blanked.z, arr.z)
    np.testing.assert_array_equal(blanked.u, arr.u)
    assert np.isfinite(arr.m).all()  # the grid given is left as it was
    # "a" ends each outage (3, 4) m off at alpha 1 and twice that at alpha 3; "b" 1 m off
    a, b = np.zeros_like(arr.z), np.zeros_like(arr.z)
    a[0, [13, 23, 33], :2] = [3.0, 4.0]
    a[1, [13, 23], :2] = [6.0, 8.0]
    b[:, :, 0] = np.where(inside, 1.0, 0.0)
    eye = np.broadcast_to(np.eye(3), (*arr.m.shape[:2], 3, 3))
    table = outages.score_grid({"a": a, "b": b}, arr, spans, 0.5, reference="b",
                               covariances={"a": eye})
    got = table.set_index(["estimator", "alpha"])
    # NEES over the outages' rows only, P = I: 3 ends of 25 m^2 in 12 rows at alpha 1
    assert got.loc[("a", 1.0), "nees"] == pytest.approx(3 * 25 / 12)
    assert got.loc[("a", 3.0), "nees"] == pytest.approx(2 * 100 / 8)
    assert got.loc[("a", 1.0), "nees_low"] < 3 < got.loc[("a", 1.0), "nees_high"]
    assert np.isnan(got.loc[("b", 1.0), "nees"])  # no covariance given
    assert got.loc[("a", 1.0), "outages"] == 3 and got.loc[("a", 3.0), "outages"] == 2
    assert got.loc[("a", 1.0), "end_m"] == 5.0 and got.loc[("a", 3.0), "end_m"] == 10.0
    assert got.loc[("b", 3.0), "end_m"] == 1.0 and got.loc[("a", 3.0), "end_vs_b"] == 10.0
    assert got.loc[("a", 1.0), "drift_pct"] == pytest.approx(100 * 5.0 / 4.0)  # 4 m driven
    assert got.loc[("a", 1.0), "position_m"] == pytest.approx(np.sqrt(3 * 25 / 12))
    none = grid(t=12)  # 6 s: no 2 s outage fits 5 s after the first fix and before the end
    with pytest.raises(LboError, match=r"^outages: no window of 2 s fits in a test trajectory "
                                       r"\(one every 5 s from its first fix"):
        outages.grid_windows(none, Outages(2.0, 5.0), 0.5)


def test_no_fix_inside_a_grid_outage_reaches_an_observer(smoke_data):
    """Planted: the fixes inside the outages moved 1 km before blanking; every classical
    observer's estimates on the blanked grid are the same to the bit."""
    from lbo.scoring.grid import classical, load_test

    arr = load_test(smoke_data / "test.parquet")
    spans = outages.grid_windows(arr, Outages(3.0, 6.0), VEHICLE.dt)
    inside = outages.grid_inside(arr.m.shape[:2], spans)
    planted = dataclasses.replace(arr, m=np.where(inside[..., None], arr.m + 1000.0, arr.m))
    noise = Noise.from_cfg(OmegaConf.load(CONF_DIR / "noise" / "paper.yaml"))
    for name in ("ekf", "oracle", "adaptive", "ukf"):
        np.testing.assert_array_equal(
            classical(name, outages.blank_grid(arr, spans), VEHICLE, noise),
            classical(name, outages.blank_grid(planted, spans), VEHICLE, noise), err_msg=name)


def test_evaluate_scores_every_observer_through_outages_on_the_test_grid(
        smoke_data, robust_smoke, tmp_path, capsys):
    """``lbo.evaluate outages.length_s=3 outages.every_s=6``: outages.csv holds every observer
    at every noise level, the robust observer (its recursive form coasts) and the classical
    ones with an estimate at each outage's end; a window CNN has none, and says so."""
    from lbo.evaluate import evaluate

    robust = robust_smoke["out"]["checkpoint"]
    evaluate(compose_cfg("evaluate", [
        "data=smoke", f"data.root={smoke_data.parent}", f"output_dir={tmp_path}",
        "observers=[ekf,oracle,pcrb]", f"learned=[{robust}]", "outages.length_s=3",
        "outages.every_s=6"]))
    printed = capsys.readouterr().out
    assert re.search(r"through GNSS outages of 3 s \(every 6 s while moving, \d+ in 21 test "
                     r"trajectories", printed)
    table = pd.read_csv(tmp_path / "outages.csv")
    assert set(table["estimator"]) == {"filternet-N40", "ekf", "oracle"}  # no bound
    assert table.groupby("estimator")["alpha"].nunique().eq(7).all()
    assert table[["end_m", "position_m", "psi_mrad", "drift_pct"]].notna().all().all()
    assert (table.loc[table["estimator"] == "ekf", "end_vs_ekf"] == 1.0).all()
    assert (table["end_m"] > 0.1).all()  # coasting 3 s drifts, fixes or not
    # the covariance through the outages: every filter that gives one has its NEES
    assert table[["nees", "nees_low", "nees_high"]].notna().all().all()
    assert "NEES inside the outages (3 for an honest covariance" in printed


def test_outages_are_for_the_test_grid_and_checked_before_any_work(tmp_path):
    from lbo.evaluate import evaluate

    with pytest.raises(LboError, match=r"^outages: scored on the simulated test grid; on a log "
                                       r"with truth, python -m lbo.observe outages"):
        evaluate(compose_cfg("evaluate", ["data=logs", f"data.test=[{tmp_path}]",
                                          "outages.length_s=10"]))
    with pytest.raises(LboError, match=r"^outages\.every_s must be longer than"):
        evaluate(compose_cfg("evaluate", ["data=smoke", f"output_dir={tmp_path}",
                                          "outages.length_s=10", "outages.every_s=5"]))
    assert not any(tmp_path.iterdir())


def test_an_observers_run_is_told_its_error_at_the_outages_end(tmp_path, monkeypatch):
    """log_to_run with an outages.csv among the files: ``eval_<data>_outage_end_m_alpha_<a>``
    for the observer's rows (a real MLflow store)."""

    from lbo.evaluate import log_to_run

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    client = store_client(uri)
    run = client.create_run(client.create_experiment("e", f"{tmp_path / 'art'}")).info.run_id
    pd.DataFrame({"observer": ["mine", "mine", "ekf"], "alpha": [1.0, 3.0, 1.0],
                  "nrmse": [0.9, 2.0, 1.0]}).to_csv(tmp_path / "evaluation.csv", index=False)
    pd.DataFrame({"estimator": ["mine", "mine", "ekf"], "alpha": [1.0, 3.0, 1.0],
                  "end_m": [1.5, 2.5, 2.0]}).to_csv(tmp_path / "outages.csv", index=False)
    log_to_run(run, run, "mine", tmp_path / "evaluation.csv", "smoke",
               [tmp_path / "evaluation.csv", tmp_path / "outages.csv"])
    logged = client.get_run(run).data.metrics
    assert logged == {"eval_smoke_nrmse_alpha_1": 0.9, "eval_smoke_nrmse_alpha_3": 2.0,
                      "eval_smoke_outage_end_m_alpha_1": 1.5,
                      "eval_smoke_outage_end_m_alpha_3": 2.5}
    assert {a.path for a in client.list_artifacts(run, "evaluations/smoke")} == {
        "evaluations/smoke/evaluation.csv", "evaluations/smoke/outages.csv"}
