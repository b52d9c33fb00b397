"""One validation path for logs (lbo.logs.checks): the CLI `lbo.observe` and the library API
(`Observer.run`, `Observer.step`) refuse the same bad input with the same one line."""

from __future__ import annotations

import re
import socket
import time

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from helpers import compose_cfg, observe, observed, one_line_error, train_in_own_store
from helpers.shared import once
from lbo.core.errors import LboError
from lbo.logs.io import resample
from lbo.models.features import window_view
from lbo.models.net import WindowNet
from lbo.observe import observe as observe_cfg
from lbo.serve.observer import Observer
from lbo.simulate import simulate

pytestmark = pytest.mark.usefixtures("one_torch_thread")
LOG = ["t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]
MEAS, INPUTS = ["x_m", "y_m", "psi_m"], ["V", "delta"]


@pytest.fixture(scope="module")
def fix_rates_cnn(tmp_path_factory, worker_id, smoke_data):
    """One smoke CNN (N=20) trained with missing fixes (fix_rates=[50,10]), shared here (made
    once for the run: the tests only read it)."""
    return once(tmp_path_factory, worker_id, "fix_rates_cnn", lambda tmp: train_in_own_store(
        tmp, smoke_data, "experiment=smoke", "model=cnn", "window=20", "fix_rates=[50,10]",
        "trainer.max_epochs=1", "trainer.limit_train_batches=3")[1]["checkpoint"])


def assert_refused(res, message, out):
    """Exit 2, one line `error: ...` matching ``message``, no traceback, no output file."""
    line = one_line_error(res)
    assert re.search(message, line), line
    assert not out.exists()


def refused_in_process(overrides, message, out):
    with pytest.raises(LboError) as err:
        observe_cfg(compose_cfg("observe", overrides))
    assert "\n" not in str(err.value)
    assert re.search(message, str(err.value)), str(err.value)
    assert not out.exists()
    return str(err.value)


def arrays(df):
    return df[MEAS].to_numpy(dtype=float), df[INPUTS].to_numpy(dtype=float)


# --- 1. resample never invents a fix, and refuses a gap it would interpolate across -----------


def test_resample_puts_each_fix_on_its_nearest_row_and_invents_none(manoeuvre):
    log = manoeuvre[LOG].reset_index(drop=True)
    fine = resample(log, 0.01, tuple(LOG[1:]))
    # a fix on every row of the log: on the 0.01 s grid, every other row has none
    fix = fine[MEAS].notna().all(axis=1).to_numpy()
    np.testing.assert_array_equal(fix, np.arange(len(fine)) % 2 == 0)
    assert fine[MEAS].isna().all(axis=1).sum() == len(fine) - len(log)
    np.testing.assert_array_equal(fine.loc[fix, MEAS].to_numpy(), log[MEAS].to_numpy())
    # inputs and the true state are interpolated
    assert np.isfinite(fine[INPUTS + ["x", "y", "psi"]].to_numpy()).all()
    # jittered times: a fix goes to its nearest grid row, of two on one row the nearer wins
    df = pd.DataFrame({"t": [0.0, 0.013, 0.021, 0.06], "x_m": [1.0, 2.0, 3.0, 4.0],
                       "y_m": 0.0, "psi_m": 0.0, "V": 1.0, "delta": 0.0})
    out = resample(df, 0.02, ("x_m", "y_m", "psi_m", "V", "delta"))
    np.testing.assert_array_equal(out["x_m"], [1.0, 3.0, np.nan, 4.0])


def _gap_log(manoeuvre, every=1):
    """The manoeuvre with a 10 s gap in t between rows 120 and 121 (t=2.4 s to 12.4 s)."""
    log = manoeuvre[LOG].reset_index(drop=True).copy()
    log.loc[121:, "t"] += 10.0 - 0.02
    if every > 1:
        log.loc[log.index % every != 0, MEAS] = np.nan
    return log


@pytest.mark.parametrize("every", [1, 5])  # a fix on every row, or on one in five
def test_resample_refuses_a_gap_longer_than_max_gap(tmp_path, manoeuvre, every):
    log, out = tmp_path / "log.csv", tmp_path / "est.csv"
    _gap_log(manoeuvre, every).to_csv(log, index=False)
    res = observe("observer=ekf", f"input={log}", f"output={out}", "resample=true")
    assert_refused(res, re.escape(
        f"input {log}: rows 120 and 121 are 10 s apart (t=2.4 s to 12.4 s), longer than "
        "max_gap=0.5 s: V and delta cannot be interpolated across it; split the log there, "
        "or raise max_gap"), out)


def test_a_raised_max_gap_interpolates_inputs_but_never_fixes(tmp_path, manoeuvre, capsys):
    log, out = tmp_path / "log.csv", tmp_path / "est.csv"
    _gap_log(manoeuvre).to_csv(log, index=False)
    result = observed(log, out, "resample=true", "max_gap=20")
    rows = len(manoeuvre) + 499  # the 10 s gap is 499 more rows of 0.02 s
    assert result["rows"] == rows
    assert f"fixes: {len(manoeuvre)} of {rows} rows" in capsys.readouterr().out
    est = pd.read_csv(out)
    assert est["valid"].all()  # the EKF predicts through the gap (from interpolated inputs)
    with pytest.raises(LboError, match=r"^max_gap must be a time in seconds > 0, got -1$"):
        observed(log, tmp_path / "b.csv", "max_gap=-1")


def test_a_gap_no_longer_than_the_observer_dt_is_not_refused(tmp_path, manoeuvre):
    log, out = tmp_path / "log.csv", tmp_path / "est.csv"
    manoeuvre[LOG].iloc[::50].to_csv(log, index=False)  # 1 s steps, above max_gap=0.5 s
    result = observed(log, out, "resample=true", "vehicle.dt=1.0")
    assert result["rows"] == len(manoeuvre[::50])


def test_an_upsampled_log_has_sparse_fixes_that_an_every_fix_observer_refuses(manoeuvre):
    fine = resample(manoeuvre[LOG].reset_index(drop=True), 0.01, tuple(LOG[1:]))
    obs = Observer.from_net(WindowNet("cnn", 20, "relative"))
    with pytest.raises(LboError, match=r"^row 1: no fix, but cnn-N20 was trained with a fix"):
        obs.run(*arrays(fine))


# --- 2. column names ------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_a_column_given_twice_is_refused(tmp_path, manoeuvre, suffix):
    log, out = tmp_path / f"log{suffix}", tmp_path / "est.csv"
    df = manoeuvre[LOG].reset_index(drop=True)
    columns = [df[c] for c in LOG] + [df["x_m"] + 1.0]
    names = LOG + ["x_m"]
    if suffix == ".csv":
        log.write_text(pd.concat(columns, axis=1).to_csv(index=False, header=names))
    else:
        pq.write_table(pa.table([pa.array(c.to_numpy()) for c in columns], names=names), log)
    refused_in_process(["observer=ekf", f"input={log}", f"output={out}"],
                       re.escape(f"input {log}: column 'x_m' appears more than once in the "
                                 "header; keep one column of each name"), out)


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_spaces_after_the_commas_are_stripped(tmp_path, manoeuvre, suffix):
    log, out = tmp_path / f"log{suffix}", tmp_path / "est.csv"
    if suffix == ".csv":
        text = manoeuvre[LOG].to_csv(index=False)
        log.write_text(text.replace(",", ", "))  # `t, x_m, y_m, ...` and `0.0, 1.2, ...`
    else:  # names with spaces, and an index that pandas keeps as a column of the file
        df = manoeuvre[LOG].rename(columns=lambda c: f" {c}").set_axis(
            np.arange(len(manoeuvre))[::-1] * 3)
        df.to_parquet(log)
        assert "__index_level_0__" in pq.read_schema(log).names
    result = observed(log, out)
    assert result["rows"] == len(manoeuvre) and "rmse" in result


def test_missing_columns_name_the_columns_found(tmp_path, manoeuvre):
    log, out = tmp_path / "log.csv", tmp_path / "est.csv"
    manoeuvre[LOG].rename(columns={"V": "speed"}).to_csv(log, index=False)
    refused_in_process(["observer=ekf", f"input={log}", f"output={out}"],
                       r"missing column V \(a log needs .*; found t, x_m, y_m, psi_m, speed, "
                       r"delta, x, y, psi\)$", out)


# --- 3. t in milliseconds -----------------------------------------------------------------------


@pytest.mark.parametrize("unit, factor, median, resampled", [
    ("milliseconds", 1e3, "20", False), ("milliseconds", 1e3, "20", True),
    ("microseconds", 1e6, "20000", False), ("nanoseconds", 1e9, "2e+07", False)])
def test_t_in_milliseconds_is_refused(tmp_path, manoeuvre, unit, factor, median, resampled):
    log, out = tmp_path / "log.csv", tmp_path / "est.csv"
    manoeuvre[LOG].assign(t=manoeuvre["t"] * factor).to_csv(log, index=False)
    refused_in_process(["observer=ekf", f"input={log}", f"output={out}",
                        f"resample={str(resampled).lower()}"],
                       re.escape(f"input {log}: column 't' looks like {unit} (median step "
                                 f"{median} for dt=0.02 s); give t in seconds"), out)


def test_a_log_in_seconds_at_10hz_is_not_taken_for_milliseconds(tmp_path, manoeuvre):
    log, out = tmp_path / "log.csv", tmp_path / "est.csv"
    manoeuvre[LOG].iloc[::5].to_csv(log, index=False)  # 0.1 s steps
    result = observed(log, out, "resample=true")
    assert result["rows"] == len(manoeuvre) - 4  # up to the log's last t


# --- 4. one validation path: Observer.run refuses what the CLI refuses, with the same line -----


def _with(df, row, column, value):
    d = df.copy()
    d.loc[d.index[row], column] = value
    return d


API_CASES = {  # case: (log from the good one, what the line says after `input <path>: `)
    "inf_fix": (lambda d: _with(d, 5, "x_m", np.inf),
                "column 'x_m' has NaN or inf (first at row 5)"),
    "x_without_y": (lambda d: _with(d, 5, "y_m", np.nan),
                    "row 5 has x_m without y_m; a row holds x_m and y_m (a position fix), with "
                    "or without psi_m, or none of them (a step without a fix)"),
    "heading_without_position": (lambda d: _with(_with(d, 5, "y_m", np.nan), 5, "x_m", np.nan),
                                 "row 5 has a heading without a position (psi_m without x_m, "
                                 "y_m); a row holds x_m and y_m (a position fix), with or "
                                 "without psi_m, or none of them (a step without a fix)"),
    "nan_speed": (lambda d: _with(d, 9, "V", np.nan), "column 'V' has NaN or inf (first at row 9)"),
    "absurd_position": (lambda d: _with(d, 3, "y_m", 1e12),
                        "row 3: y_m=1e+12 m is beyond 1e+07 m (positions are metres in a "
                        "local frame)"),
    "absurd_speed": (lambda d: _with(d, 8, "V", 400.0),
                     "row 8: V=400 m/s is beyond 100 m/s (no road vehicle is that fast; "
                     "speeds are in m/s)"),
    "absurd_steering": (lambda d: _with(d, 4, "delta", 10.0),
                        "row 4: delta=10 rad is beyond the vehicle's steering limit "
                        "delta_max=0.5 rad (steering in rad, at the wheels; or set "
                        "vehicle.delta_max; a steering-wheel angle needs steering_ratio=, one "
                        "in degrees units.delta=deg)"),
    # 7 rad is a heading in rad on another branch (issue 41, 15): only an absurd one is out
    "heading_outlier": (lambda d: _with(d, 6, "psi_m", 1e7),
                        "row 6: psi_m=1e+07 rad is beyond 1e+06 rad (a heading in rad, on any "
                        "branch)"),
    "degrees": (lambda d: d.assign(psi_m=np.degrees(d["psi_m"]) + 90.0),
                "column 'psi_m' looks like degrees"),
    "no_fix": (lambda d: d.assign(x_m=np.nan, y_m=np.nan, psi_m=np.nan),
               "no position fix in any row (x_m and y_m are empty everywhere)"),
}


@pytest.mark.parametrize("case", list(API_CASES))
def test_observer_run_refuses_what_the_cli_refuses_with_the_same_line(tmp_path, manoeuvre,
                                                                       case):
    make, message = API_CASES[case]
    bad = make(manoeuvre[LOG].reset_index(drop=True))
    log, out = tmp_path / "log.csv", tmp_path / "est.csv"
    bad.to_csv(log, index=False)
    cli = refused_in_process(["observer=ekf", f"input={log}", f"output={out}"],
                             re.escape(message), out)
    with pytest.raises(LboError) as err:
        Observer.load("ekf").run(*arrays(bad), source=f"input {log}")
    assert str(err.value) == cli
    assert str(err.value).startswith(f"input {log}: {message}")


@pytest.mark.parametrize("source", ["ekf", "learned"])
def test_step_refuses_a_bad_sample_and_the_next_good_one_goes_on(manoeuvre, source):
    m, u = arrays(manoeuvre)
    if source == "learned":
        torch.manual_seed(0)
        obs = Observer.from_net(WindowNet("cnn", 20, "relative").double())
    else:
        obs = Observer.load("ekf")
    ref, ref_valid = obs.run(m, u)
    bad_samples = [
        ((m[40], [1e300, u[40, 1]]), r"^step 40: V=1e\+300 m/s is beyond 100 m/s"),
        (([1e12, m[40, 1], m[40, 2]], u[40]), r"^step 40: x_m=1e\+12 m is beyond 1e\+07 m"),
        (([m[40, 0], np.nan, m[40, 2]], u[40]),
         r"^step 40: measurement \[.*\] has x_m without y_m; a sample holds x_m and y_m"),
        (([np.nan, np.nan, m[40, 2]], u[40]),
         r"^step 40: measurement \[nan, nan, .*\] has a heading without a position"),
        (([np.inf, m[40, 1], m[40, 2]], u[40]),
         r"^step 40: measurement .* has inf \(x_m\); pass measurement=None"),
        ((m[40], [np.nan, 0.0]), r"^step 40: input \[V, delta\] = \[nan, 0\] has NaN or inf"),
        ((m[40], [u[40, 0], 0.9]), r"^step 40: delta=0.9 rad is beyond the vehicle's steering"),
        (([m[40, 0], m[40, 1], 400.0], u[40]), r"^step 40: psi_m=400 rad is outside"),
    ]
    states, valid = [], []
    for k in range(len(m)):
        if k == 40:
            for (mk, uk), message in bad_samples:
                with pytest.raises(LboError, match=message) as err:
                    obs.step(mk, uk)
                assert "\n" not in str(err.value)
        e = obs.step(m[k], u[k])
        states.append(e.state)
        valid.append(e.valid)
    # the refused samples left no trace: the same numbers as the batch run without them
    np.testing.assert_allclose(np.array(states), ref, atol=1e-9)
    np.testing.assert_array_equal(valid, ref_valid)


def test_step_takes_an_all_nan_measurement_as_no_fix():
    a, b = Observer.load("ekf"), Observer.load("ekf")
    a.step([1.0, 2.0, 0.1], [5.0, 0.0])
    b.step([1.0, 2.0, 0.1], [5.0, 0.0])
    np.testing.assert_array_equal(a.step([np.nan] * 3, [5.0, 0.0]).state,
                                  b.step(None, [5.0, 0.0]).state)


# --- 5. alpha ---------------------------------------------------------------------------------


def test_alpha_must_be_in_0_to_100(tmp_path, manoeuvre):
    from lbo.sim.noise import check_alpha

    log, out = tmp_path / "log.csv", tmp_path / "est.csv"
    manoeuvre[LOG].to_csv(log, index=False)
    res = observe("observer=oracle", f"input={log}", f"output={out}", "alpha=1e300")
    assert_refused(res, r"^error: alpha must be a number in \[0, 100\], got 1e\+300$", out)
    assert "Warning" not in res.stderr
    for bad, shown in ((1e300, "1e+300"), (-1, "-1"), (float("nan"), "nan"), ("x", "'x'"),
                       (True, "True")):
        with pytest.raises(LboError, match=re.escape(f"alpha must be a number in [0, 100], "
                                                     f"got {shown}")):
            Observer("oracle", alpha=bad)
    assert check_alpha(100) == 100.0 and check_alpha(0) == 0.0


@pytest.mark.parametrize(("field", "bad"), [("data.train.alpha", 101), ("data.val.alpha", -1),
                                            ("data.test.alpha_max", 1001),
                                            ("train_noise.alpha", 101), ("alpha", -0.5)])
def test_every_alpha_lbo_is_given_is_checked_by_one_rule(field, bad):
    """A data set's levels, a training draw's and a simulated log's: the noise scale an
    observer is told, the same range and the same line (lbo.sim.noise.check_alpha)."""
    from helpers import compose_cfg
    from lbo.learn.draws import AlphaDraw
    from lbo.sim.datasets import spec_from_cfg
    from lbo.simulate import simulate

    line = rf"^{re.escape(field)} must be a number in \[0, 100\], got {re.escape(f'{bad:g}')}$"
    with pytest.raises(LboError, match=line):
        if field.startswith("data."):
            spec_from_cfg(compose_cfg("datagen", [f"{field}={bad}"]))
        elif field.startswith("train_noise."):
            AlphaDraw(alpha=bad)
        else:
            simulate(compose_cfg("simulate", [f"alpha={bad}"]))


# --- 6. a learned observer that takes missing fixes needs one in every window ----------------


def _thinned(every, drop_last=0):
    df = simulate(compose_cfg("simulate", ["manoeuvre=slalom", f"fix_rate={50 / every}"]))
    df = df[LOG].reset_index(drop=True)
    if drop_last:
        df.loc[len(df) - drop_last:, MEAS] = np.nan
    return df


def test_a_1hz_log_is_refused_for_a_cnn_whose_window_is_shorter(tmp_path, fix_rates_cnn):
    log, out = tmp_path / "log.csv", tmp_path / "est.csv"
    _thinned(50).to_csv(log, index=False)
    res = observe(f"observer={fix_rates_cnn}", f"input={log}", f"output={out}")
    assert_refused(res, re.escape(
        f"error: input {log}: fixes are up to 50 steps (1 s) apart (rows 0 and 50), but "
        "cnn-N20 needs a fix in every window of 20 steps (0.4 s); use an observer with a "
        "longer window, the robust one (experiment=robust), or a classical one"), out)
    # at 5 Hz (a fix every 10 steps) every window holds a fix: every estimate from row 19 on
    _thinned(10).to_csv(log, index=False)
    result = observed(log, out, observer=fix_rates_cnn)
    assert result["valid"] == result["rows"] - 19


def test_the_window_rule_refuses_exactly_the_logs_with_nan_estimates(fix_rates_cnn):
    """A gap of N steps between fixes is fine, N+1 gives a NaN estimate (refused); so does a
    log ending with N steps without a fix; for the CNN and the window filter's window form
    alike."""
    torch.manual_seed(0)
    observers = [Observer.load(fix_rates_cnn),
                 Observer.from_net(WindowNet("filternet", 20, "frame", fixes=True).double(),
                                   form="window")]
    u = np.tile([8.0, 0.05], (120, 1))
    for obs in observers:
        n = obs.window
        for gap, ends_without in ((n, 0), (n + 1, 0), (5, n - 1), (5, n)):
            last = 119 - ends_without  # the last fix
            at = np.unique(np.r_[np.arange(0, last + 1, gap), last])
            m = np.full((120, 3), np.nan)
            m[at] = np.stack([0.16 * at, np.zeros(len(at)), np.zeros(len(at))], 1)
            series = np.concatenate([m, u], 1)
            if obs._runner.pads:
                series = np.concatenate([np.full((n - 1, 5), np.nan), series])
                series[: n - 1, 3:] = 0.0
            direct = obs._runner.predict(np.ascontiguousarray(window_view(series, n)))
            first = 0 if obs._runner.pads else n - 1
            nan_rows = ~np.isfinite(direct).all(1)
            if gap <= n and ends_without < n:
                assert not nan_rows.any(), (obs.name, gap, ends_without)
                est, valid = obs.run(m, u)
                assert valid[first:].all()
            else:
                assert nan_rows.any(), (obs.name, gap, ends_without)
                message = (f"fixes are up to {gap} steps" if ends_without == 0 else
                           f"the last {ends_without} rows (after row {last}) have no fix")
                with pytest.raises(LboError, match=re.escape(message)):
                    obs.run(m, u)


def test_a_log_starting_without_a_fix_is_not_refused():
    torch.manual_seed(0)
    obs = Observer.from_net(WindowNet("filternet", 20, "frame", fixes=True).double())
    m = np.full((100, 3), np.nan)
    m[30::10] = [[1.0, 2.0, 0.3]]
    est, valid = obs.run(m, np.tile([8.0, 0.05], (100, 1)))
    assert not valid[:30].any() and valid[30:].all()


def test_step_returns_nan_with_a_reason_when_the_window_holds_no_fix():
    torch.manual_seed(0)
    obs = Observer.from_net(WindowNet("cnn", 20, "relative", fixes=True).double())
    u = [8.0, 0.05]
    first = obs.step([0.0, 0.0, 0.0], u)
    assert not first.valid and first.reason.startswith("window not yet full (1 of 20 steps)")
    for _ in range(19):
        e = obs.step(None, u)
    assert e.valid and e.reason is None  # step 19: the window holds the fix of step 0
    e = obs.step(None, u)  # step 20: no fix in steps 1 .. 20
    assert not e.valid and np.isnan(e.state).all()
    assert e.reason == ("no fix in the last 20 steps (0.4 s): cnn-N20 needs a fix in every "
                        "window of 20 steps")
    state, valid = obs.step([3.0, 0.0, 0.0], u)  # a fix: estimates resume
    assert valid and np.isfinite(state).all()


# --- 7. checkpoints with bad stored values ---------------------------------------------------


def _edited(path, tmp_path, edit):
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    edit(ckpt)
    out = tmp_path / "best.ckpt"
    torch.save(ckpt, out)
    return out


def _nan_weight(ckpt):
    key = next(k for k, v in ckpt["state_dict"].items()
               if k.startswith("observer.net.") and v.is_floating_point())
    ckpt["state_dict"][key].view(-1)[0] = float("nan")


@pytest.mark.parametrize("edit, message", [
    (lambda c: c["hyper_parameters"]["meta"]["noise"].update(measurement_sigma=[-1.0, 1, 1]),
     "its stored noise.measurement_sigma must be three finite sigmas >= 0"),
    (_nan_weight, r"its weights hold NaN or inf \(net\..*: training diverged\?\); "
                  r"retrain it, e\.g\. with a smaller optimizer\.lr$"),
])
def test_a_checkpoint_with_bad_stored_values_is_named(fix_rates_cnn, tmp_path, edit, message):
    path = _edited(fix_rates_cnn, tmp_path, edit)
    with pytest.raises(LboError, match=f"^checkpoint {re.escape(str(path))}: {message}") as err:
        Observer.load(path)
    assert "\n" not in str(err.value)


# --- 8. device --------------------------------------------------------------------------------


def test_a_bogus_device_is_refused_before_the_checkpoint_is_read(tmp_path, manoeuvre):
    log, out, ckpt = tmp_path / "log.csv", tmp_path / "est.csv", tmp_path / "broken.ckpt"
    manoeuvre[LOG].to_csv(log, index=False)
    ckpt.write_bytes(b"not a checkpoint")
    res = observe(f"observer={ckpt}", f"input={log}", f"output={out}", "device=bogus")
    assert_refused(res, r"^error: device=bogus: expected cpu, cuda or cuda:<n>$", out)
    with pytest.raises(LboError, match=r"^device=gpu: expected cpu, cuda or cuda:<n>$"):
        Observer.load(ckpt, device="gpu")


def test_cuda_without_cuda_is_refused_before_the_checkpoint_is_read(tmp_path, manoeuvre,
                                                                      monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    log, out, ckpt = tmp_path / "log.csv", tmp_path / "est.csv", tmp_path / "broken.ckpt"
    manoeuvre[LOG].to_csv(log, index=False)
    ckpt.write_bytes(b"not a checkpoint")
    message = "device=cuda needs CUDA, which torch does not see here; use device=cpu"
    refused_in_process([f"observer={ckpt}", f"input={log}", f"output={out}", "device=cuda"],
                       f"^{re.escape(message)}$", out)
    with pytest.raises(LboError, match=f"^{re.escape(message)}$"):
        Observer.load(ckpt, device="cuda")
    with pytest.raises(LboError, match=r"^device=cuda:1 needs CUDA"):
        Observer.from_net(WindowNet("cnn", 20, "relative"), device="cuda:1")


# --- 9. a tracking server that is down --------------------------------------------------------


def test_a_run_id_with_the_tracking_server_down_fails_fast(tmp_path, manoeuvre, monkeypatch):
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"http://127.0.0.1:{port}")
    log, out = tmp_path / "log.csv", tmp_path / "est.csv"
    manoeuvre[LOG].to_csv(log, index=False)
    start = time.monotonic()
    res = observe(f"observer={'ab' * 16}", f"input={log}", f"output={out}", timeout=60)
    assert time.monotonic() - start < 15
    assert_refused(res, re.escape(f"error: MLFLOW_TRACKING_URI: no MLflow tracking server "
                                  f"answers at http://127.0.0.1:{port} ("), out)


def test_the_recursive_form_predicts_through_a_gap_longer_than_its_window():
    # its filter carries from step to step: a gap of 3 N steps is prediction only, no NaN
    torch.manual_seed(0)
    obs = Observer.from_net(WindowNet("filternet", 20, "frame", fixes=True))
    assert obs.form == "recursive"
    m = np.full((200, 3), np.nan)
    at = np.r_[0:40:5, 100:200:5]
    m[at] = np.stack([0.16 * at, np.zeros(len(at)), np.zeros(len(at))], 1)
    est, valid = found = obs.run(m, np.tile([8.0, 0.0], (200, 1)))
    cov = found.cov
    assert valid.all() and np.isfinite(est).all()
    # the covariance grows through the gap and shrinks at the next fix
    assert cov[99, 0, 0] > 5 * cov[39, 0, 0] and cov[100, 0, 0] < cov[99, 0, 0]
