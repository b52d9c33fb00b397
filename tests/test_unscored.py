"""What ``lbo.observe``'s summary leaves out of its scores, and why (issue 68): a classical
filter's heading before it first observes one leaves the heading's RMSE, and the ``valid:``
and ``rmse:`` lines name the reasons that apply, not a fixed list."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from helpers import compose_cfg
from lbo.filters.start import CourseStart
from lbo.observe import observe
from lbo.scoring.metrics import rmse
from lbo.scoring.unscored import heading_unseen, unscored
from lbo.serve.observer import Observer
from lbo.sim.columns import RECEIVER
from lbo.sim.measurements import Measurements
from lbo.simulate import simulate

LOG = ["t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]


def _standstill_then_drive(still: int, seed: int = 0) -> pd.DataFrame:
    """A car standing ``still`` rows (50 Hz) at a heading of 2 rad, then a slalom from there;
    position fixes without a heading at 10 Hz, a gyro ``r_m`` (the true turn), no velocity."""
    drive = simulate(compose_cfg("simulate", ["manoeuvre=slalom"]), seed=seed)[LOG]
    drive = drive.head(1500).reset_index(drop=True)
    turn = 2.0 - drive["psi"].iloc[0]  # the drive turned to start at the standstill's heading
    c, s = np.cos(turn), np.sin(turn)
    for a, b in (("x", "y"), ("x_m", "y_m")):
        drive[a], drive[b] = c * drive[a] - s * drive[b], s * drive[a] + c * drive[b]
    drive["psi"] += turn
    start = drive.iloc[[0] * still].assign(V=0.0, delta=0.0)
    log = pd.concat([start, drive], ignore_index=True)
    log["t"] = np.arange(len(log)) * 0.02
    rng = np.random.default_rng(seed)
    log["x_m"] = log["x"] + rng.normal(scale=0.5, size=len(log))
    log["y_m"] = log["y"] + rng.normal(scale=0.5, size=len(log))
    log["psi_m"] = np.nan
    log.loc[log.index % 5 != 0, ["x_m", "y_m"]] = np.nan
    log["r_m"] = np.gradient(np.unwrap(log["psi"].to_numpy()), 0.02)
    return log


@pytest.mark.parametrize("name", ["ekf", "ukf", "adaptive", "gyro"])
@pytest.mark.parametrize("still", [0, 600])
def test_heading_unseen_is_the_rows_the_filter_itself_ran_blind(monkeypatch, name, still):
    """Recorded inside the filter as it runs the log (each step's CourseStart.blind), the rows
    before its first heading are the rows heading_unseen finds by stepping it again."""
    log = _standstill_then_drive(still)
    m = log[["x_m", "y_m", "psi_m"]].to_numpy()
    u = log[["V", "delta"]].to_numpy()
    r = log.reindex(columns=list(RECEIVER)).to_numpy(dtype=float)
    seen: list[bool] = []
    take = CourseStart.take

    def record(self, *args):
        out = take(self, *args)
        seen.append(bool(self.blind[0]))
        return out

    obs = Observer.load(name)
    monkeypatch.setattr(CourseStart, "take", record)
    obs.run(m, u, receiver=r)
    monkeypatch.undo()
    # the first fix (row 0) holds no heading; each later step takes one, in row order, and
    # no step coasts past a row while the heading is unknown
    ran_blind = 1 + int(np.argmin(seen))
    assert 0 < ran_blind < len(seen)
    unseen = heading_unseen(obs, Measurements.of(m, r), u)
    assert unseen.sum() == ran_blind and unseen[:ran_blind].all()
    assert still < ran_blind < still + 400  # the first metres of the drive
    # a heading with the first fix: nothing unseen, nothing stepped again
    full = m.copy()
    full[0, 2] = log["psi"].iloc[0]
    assert not heading_unseen(obs, Measurements.of(full, r), u).any()


def _observe(tmp_path, log: pd.DataFrame, observer: str = "ekf") -> dict:
    path = tmp_path / "log.csv"
    log.to_csv(path, index=False)
    return observe(compose_cfg("observe", [f"observer={observer}", f"input={path}",
                                           f"output={tmp_path / 'est.csv'}"]))


def test_a_heading_never_observed_leaves_the_rmse_and_says_so(tmp_path, capsys):
    """60 s at standstill from the start, position fixes only: the EKF's heading is 0 rad,
    sd 1 rad, valid, all along; its 2 rad error was the printed psi RMSE."""
    log = _standstill_then_drive(3000).head(3000)
    result = _observe(tmp_path, log)
    out = capsys.readouterr().out
    assert result["valid"] == 3000 and result["heading_unseen"] == 3000
    assert np.isnan(result["rmse"][2]) and np.isfinite(result["rmse"][:2]).all()
    assert ("psi not scored (ekf never observed its heading: no psi_m, no course over ground "
            "from ve_m, vn_m at |v| >= 1 m/s, and the car never moved far enough from its "
            "first fix to take the course of its fixes) (3000 valid rows)") in out
    assert "nrmse: not scored (no heading was observed to score)" in out
    est = pd.read_csv(tmp_path / "est.csv")
    assert est["valid"].all() and (est["psi"] == 0).all()  # the output itself is as it was


def test_rows_before_the_first_heading_leave_only_the_headings_rmse(tmp_path, capsys):
    log = _standstill_then_drive(1000)
    result = _observe(tmp_path, log)
    out = capsys.readouterr().out
    est = pd.read_csv(tmp_path / "est.csv")
    z = log[["x", "y", "psi"]].to_numpy()
    e = est[["x", "y", "psi"]].to_numpy()
    valid = est["valid"].to_numpy()
    n = result["heading_unseen"]
    assert 1000 < n < 1400 and valid.all()
    seen = np.arange(len(log)) >= n
    np.testing.assert_allclose(result["rmse"][:2], rmse(e, z, valid)[:2])
    np.testing.assert_allclose(result["rmse"][2], rmse(e, z, seen)[2])
    assert rmse(e, z, valid)[2] > 1.0 > 10 * result["rmse"][2]  # what the line said before
    assert (f"psi {result['rmse'][2]:.6g} rad over {len(log) - n} rows (the {n} before ekf "
            "first observed its heading left out: it starts there from 0 rad, sd 1 rad) "
            f"({len(log)} valid rows)") in out
    # a full fix on every fix row: every row's heading is scored, as before
    full = log.assign(psi_m=np.where(log["x_m"].notna(), log["psi"], np.nan))
    result = _observe(tmp_path, full)
    assert result["heading_unseen"] == 0 and "left out" not in capsys.readouterr().out


def test_each_reason_is_named_only_where_it_applies():
    """The valid line's reasons, each with its count, in row order; a classical filter is
    never said to wait for a heading (it starts at its first fix)."""
    t = 10
    fix = np.arange(t) >= 2
    est = np.zeros((t, 3))
    est[:2] = np.nan
    classical = SimpleNamespace(kind="classical", name="ekf", form=None, window=1)
    valid = np.isfinite(est).all(1)
    assert unscored(classical, est, valid, fix, np.zeros(t, bool), None) == [
        "2 before the first fix (row 2)"]
    est[7:] = np.nan
    valid = np.isfinite(est).all(1)
    valid[5] = False  # finite, not valid: its consistency test
    assert unscored(classical, est, valid, fix, np.zeros(t, bool), None) == [
        "2 before the first fix (row 2)", "1 flagged by its consistency test",
        "3 with an estimate that is not finite (the filter's numbers overflowed: check the "
        "log's values and units)"]
    cnn = SimpleNamespace(kind="learned", name="cnn-N4", form="window", window=4)
    est = np.zeros((t, 3))
    est[:1] = np.nan
    est[8:] = np.nan  # a window without a fix
    valid = np.isfinite(est).all(1) & (np.arange(t) >= 3)
    outside = np.arange(t) == 5
    valid &= ~outside
    assert unscored(cnn, est, valid, np.arange(t) >= 1, np.arange(t) >= 1, outside) == [
        "1 before the first fix (row 1)", "1 outside its training envelope (envelope=mark)",
        "2 while its window of 4 steps fills (the EKF's estimate)",
        "2 without an estimate (its window held no fix or no heading)"]


@pytest.mark.slow
@pytest.mark.usefixtures("one_torch_thread")
def test_the_robust_observer_without_a_heading_names_that_reason(tmp_path, robust_smoke,
                                                                 capsys, monkeypatch):
    """Position fixes without psi_m and no velocity: the robust observer never starts. Its
    `valid: 0 of N` line gave three reasons, none of which applied, and the rmse line blamed
    a log shorter than the window."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", robust_smoke["uri"])
    log = _standstill_then_drive(0).drop(columns="r_m")
    result = _observe(tmp_path, log, str(robust_smoke["out"]["checkpoint"]))
    out = capsys.readouterr().out
    assert result["valid"] == 0
    why = (f"{len(log)} with no heading yet: filternet-N40 starts at the first row that holds a "
           "position and a heading (psi_m, or a course over ground from ve_m, vn_m at |v| >= "
           "1 m/s); this log holds none")
    assert f"valid: 0 of {len(log)} rows; not scored: {why}\n" in out
    assert f"rmse: no valid row to score ({why})\n" in out
    assert "shorter than the window" not in out and "before the first fix" not in out
