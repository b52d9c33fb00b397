import re
import sqlite3
import subprocess
import sys
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from helpers import compose_cfg, train_in_own_store
from helpers import observe as run_observe
from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.export import register
from lbo.filters.classical import estimate as run_classical
from lbo.filters.kalman import ekf_batch
from lbo.filters.reference import run_filterpy_ekf
from lbo.logs.io import resample
from lbo.observe import observe as observe_cfg
from lbo.scoring.grid import classical, predict_grid
from lbo.scoring.metrics import nrmse, rmse
from lbo.serve.engines import TOLERANCE
from lbo.serve.observer import Observer
from lbo.sim import schema
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

VEHICLE, NOISE = Vehicle(), Noise.preset("paper")
LOG = ["t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]


# one torch thread, here and in the CLIs: see the one_torch_thread fixture in conftest.py
pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def trained(tmp_path_factory, smoke_data):
    """One smoke CNN (N=20), logged to its own MLflow store, shared by this module."""
    _, out, uri = train_in_own_store(tmp_path_factory.mktemp("observe"), smoke_data,
                                     "experiment=smoke", "trainer.max_epochs=1",
                                     "trainer.limit_train_batches=5")
    return {"checkpoint": out["checkpoint"], "run_id": out["run_id"], "uri": uri}


@pytest.fixture
def log_csv(tmp_path, manoeuvre):
    path = tmp_path / "log.csv"
    manoeuvre[LOG].to_csv(path, index=False)
    return path


def arrays(frame, window=1):
    """Padded arrays of one trajectory with every row from the window's end on scored."""
    arr = schema.to_arrays(frame.drop(columns=["scored"]))
    return replace(arr, mask=arr.mask & (np.arange(arr.mask.shape[1]) >= window - 1))


observe = partial(run_observe, check=True)


def classical_cov(name, arr):
    """(T, 3, 3) covariances of a classical filter on one log's arrays."""
    from lbo.filters.classical import estimate as run_classical

    return run_classical(name, arr.m, arr.u, VEHICLE, NOISE).cov[0]


def printed_rmse(stdout):
    found = re.search(r"rmse x (\S+) m, y (\S+) m, psi (\S+) rad", stdout)
    assert found, stdout
    return np.array([float(v) for v in found.groups()])


# --- the CLI on a simulated log --------------------------------------------------------------


@pytest.mark.parametrize("which", ["learned", "ekf"])
def test_observe_prints_the_evaluation_rmse(tmp_path, trained, manoeuvre, log_csv, which):
    out = tmp_path / "est.csv"
    if which == "learned":
        net = Observer.load(trained["checkpoint"]).net
        arr = arrays(manoeuvre, net.window)
        expected = rmse(predict_grid(net, arr, net.window), arr.z, arr.mask)[0]
        res = observe(f"observer={trained['checkpoint']}", f"input={log_csv}", f"output={out}")
        valid = len(manoeuvre) - net.window + 1
    else:
        arr = arrays(manoeuvre)
        expected = rmse(classical("ekf", arr, VEHICLE, NOISE), arr.z)[0]
        res = observe("observer=ekf", f"input={log_csv}", f"output={out}")
        valid = len(manoeuvre)
    np.testing.assert_allclose(printed_rmse(res.stdout), expected, rtol=1e-5)
    # the NRMSE's E_ref: the EKF's RMSE on the rows scored (the EKF itself scores 1)
    e_ref = rmse(classical("ekf", arr, VEHICLE, NOISE), arr.z, arr.mask)[0]
    found = re.search(r"nrmse (\S+) \(E_ref: the EKF on the same rows, x (\S+) m, y (\S+) m, "
                      r"psi (\S+) rad", res.stdout)
    assert found, res.stdout
    np.testing.assert_allclose([float(v) for v in found.groups()[1:]], e_ref, rtol=1e-3)
    np.testing.assert_allclose(float(found.group(1)), nrmse(expected, e_ref), rtol=1e-5)
    if which == "ekf":
        assert found.group(1) == "1"
    assert f"observed: {out}" in res.stdout
    est = pd.read_csv(out)
    # the EKF gives its covariance's entries; the CNN has none to give, but names the rows
    # outside its training envelope (none in this manoeuvre)
    covariance = ["var_x", "var_y", "var_psi", "cov_xy"] if which == "ekf" else []
    envelope = ["outside"] if which == "learned" else []
    assert list(est.columns) == ["t", "x", "y", "psi", "valid", *covariance, *envelope]
    if which == "learned":
        assert est["outside"].isna().all()  # empty strings: inside everywhere
    assert len(est) == len(manoeuvre) and int(est["valid"].sum()) == valid
    if which == "ekf":
        P = classical_cov("ekf", arr)
        np.testing.assert_allclose(est[covariance].to_numpy(),
                                   P[:, [0, 1, 2, 0], [0, 1, 2, 1]], rtol=1e-9)
    np.testing.assert_array_equal(est["t"], manoeuvre["t"])
    assert not est["valid"].iloc[:len(est) - valid].any()


def test_ekf_output_matches_filterpys_ekf(tmp_path, manoeuvre, log_csv):
    out = tmp_path / "est.parquet"  # Parquet by extension
    cfg = compose_cfg("observe", ["observer=ekf", f"input={log_csv}", f"output={out}",
                                  "vehicle.wheelbase=3.1", "noise=literal"])
    result = observe_cfg(cfg)
    m, u = manoeuvre[["x_m", "y_m", "psi_m"]].to_numpy(), manoeuvre[["V", "delta"]].to_numpy()
    noise = Noise.from_cfg(cfg.noise)
    # the expected values come from filterpy's EKF, an implementation independent of lbo's
    ref = run_filterpy_ekf(m, u, Vehicle(wheelbase=3.1), noise.Q, noise.R(1.0))
    est = pd.read_parquet(out)
    np.testing.assert_allclose(est[["x", "y"]], ref[:, :2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(est["psi"], wrap_angle(ref[:, 2]), rtol=0, atol=1e-9)
    z = manoeuvre[["x", "y", "psi"]].to_numpy()
    np.testing.assert_allclose(result["rmse"], rmse(ref, z), rtol=1e-12)
    np.testing.assert_array_equal(result["e_ref"], result["rmse"])  # the EKF is its reference
    assert result["nrmse"] == pytest.approx(1.0, abs=1e-12)


def test_smooth_true_writes_the_rts_smoothers_estimates(tmp_path, manoeuvre, log_csv, trained):
    from lbo.filters.classical import estimate as run_classical

    out = tmp_path / "est.csv"
    result = observe_cfg(compose_cfg("observe", ["observer=oracle", "alpha=1", f"input={log_csv}",
                                         f"output={out}", "smooth=true"]))
    m, u = manoeuvre[["x_m", "y_m", "psi_m"]].to_numpy(), manoeuvre[["V", "delta"]].to_numpy()
    want, P = run_classical("oracle", m[None], u[None], VEHICLE, NOISE, smooth=True)
    est = pd.read_csv(out)
    np.testing.assert_allclose(est[["x", "y"]], want[0, :, :2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(est["var_x"], P[0, :, 0, 0], rtol=1e-9)
    filtered = observe_cfg(compose_cfg("observe", ["observer=oracle", "alpha=1", f"input={log_csv}",
                                           f"output={tmp_path / 'f.csv'}"]))
    assert (result["rmse"][:2] < 0.9 * filtered["rmse"][:2]).all()
    # scored against the same EKF (R at alpha=1, filtering), which the smoother beats
    ekf = run_classical("ekf", m[None], u[None], VEHICLE, NOISE).mean[0]
    np.testing.assert_allclose(result["e_ref"], rmse(ekf, manoeuvre[["x", "y", "psi"]].to_numpy()),
                               rtol=1e-12)
    assert result["nrmse"] == pytest.approx(nrmse(result["rmse"], result["e_ref"]))
    assert result["nrmse"] < 1
    with pytest.raises(LboError, match="has no filter to smooth"):
        observe_cfg(compose_cfg("observe", [f"observer={trained['checkpoint']}", f"input={log_csv}",
                                    f"output={tmp_path / 'cnn.csv'}", "smooth=true"]))
    assert not (tmp_path / "cnn.csv").exists()


def test_observe_writes_only_its_output(tmp_path, log_csv):
    res = run_observe("observer=ekf", f"input={log_csv}", "output=est.csv", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["est.csv", "log.csv"]


# --- bad input: one line, exit 2, no output ---------------------------------------------------


def _set(df, row, column, value):
    d = df.copy()
    d.loc[d.index[row], column] = value
    return d


BAD_LOGS = {  # case: (log from the good one, what the message must say)
    "missing": (lambda d: d.drop(columns=["V", "delta"]), "missing columns V, delta"),
    "nan": (lambda d: _set(d, 5, "V", np.nan), "column 'V' has NaN or inf"),
    "x_without_y": (lambda d: _set(d, 5, "y_m", np.nan), r"row 5 has x_m without y_m"),
    "inf_fix": (lambda d: _set(d, 5, "x_m", np.inf), "column 'x_m' has NaN or inf"),
    "absurd_position": (lambda d: _set(d, 3, "x_m", 1e300),
                        r"row 3: x_m=1e\+300 m is beyond 1e\+07 m \(positions are metres"),
    "absurd_speed": (lambda d: _set(d, 8, "V", 400.0),
                     r"row 8: V=400 m/s is beyond 100 m/s \(no road vehicle is that fast"),
    "absurd_steering": (lambda d: _set(d, 4, "delta", 10.0),
                        r"row 4: delta=10 rad is beyond the vehicle's steering limit "
                        r"delta_max=0.5 rad"),
    # 7 rad is a heading in rad on another branch (issue 41, 15): only an absurd one is out
    "heading_outlier": (lambda d: _set(d, 6, "psi_m", 1e7),
                        r"row 6: psi_m=1e\+07 rad is beyond 1e\+06 rad \(a heading in rad"),
    "inf": (lambda d: _set(d, 9, "V", np.inf), "column 'V' has NaN or inf"),
    "repeated_t": (lambda d: _set(d, 7, "t", d["t"].iloc[6]), "'t' is not strictly increasing"),
    "backwards_t": (lambda d: d.iloc[::-1], "'t' is not strictly increasing"),
    "dt": (lambda d: d.assign(t=d["t"] * 1.5),
           r"sampling period .* differs from the observer's dt=0.02 s by more than 1%; "
           r"pass resample=true"),
    "degrees": (lambda d: d.assign(psi_m=np.degrees(d["psi_m"]) + 90.0),
                "'psi_m' looks like degrees"),
    "header_only": (lambda d: d.iloc[:0], "empty file"),
    "empty": (None, "empty file"),
}


@pytest.mark.parametrize("case", list(BAD_LOGS))
def test_bad_log_is_refused_before_any_output(tmp_path, manoeuvre, case):
    make, message = BAD_LOGS[case]
    log = tmp_path / "log.csv"
    if make is None:
        log.write_text("")
    else:
        make(manoeuvre[LOG]).to_csv(log, index=False)
    out = tmp_path / "est.csv"
    res = observe("observer=ekf", f"input={log}", f"output={out}", check=False)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: input "), res.stderr
    assert re.search(message, lines[0]), lines[0]
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["log.csv"]  # no temp file left either


@pytest.mark.parametrize("override, message", [
    ("observer=kalman", "not a checkpoint file, an MLflow run id"),
    ("observer=missing.ckpt", "checkpoint not found: missing.ckpt"),
    ("observer=pcrb", "pcrb is a bound"),
    ("observer=oracle_tuned", "oracle_tuned is told the true states"),
    ("observer=oracle_dynamic", "oracle_dynamic is told the simulated car's parameters"),
    ("output=est.txt", "output must be a .csv or .parquet file"),
    ("input=log.json", "input must be a .csv or .parquet file"),
    ("input=nowhere.csv", "file not found"),
    ("output=LOG", "output must not be the input log"),
    ("smooth=maybe", "smooth must be true or false"),
    ("threads=0", "threads must be an integer >= 1, got 0"),
])
def test_bad_arguments_are_refused(tmp_path, log_csv, override, message):
    overrides = {"observer": "ekf", "input": str(log_csv), "output": str(tmp_path / "est.csv")}
    key, value = override.replace("LOG", str(log_csv)).split("=", 1)
    overrides[key] = value
    before = log_csv.read_bytes()
    with pytest.raises(LboError, match=re.escape(message)):
        observe_cfg(compose_cfg("observe", [f"{k}={v}" for k, v in overrides.items()]))
    assert not (tmp_path / "est.csv").exists()
    assert log_csv.read_bytes() == before


def test_a_log_shorter_than_the_window_is_all_fallback(tmp_path, trained, manoeuvre, capsys):
    path, out = tmp_path / "short.parquet", tmp_path / "est.csv"
    manoeuvre[LOG].iloc[:12].to_parquet(path)
    result = observe_cfg(compose_cfg("observe", [f"observer={trained['checkpoint']}",
                                         f"input={path}", f"output={out}"]))
    assert result["valid"] == 0 and not pd.read_csv(out)["valid"].any()
    assert "no valid row to score" in capsys.readouterr().out


def test_resample_interpolates_to_the_observer_dt(tmp_path, manoeuvre):
    # the log at 0.01 s (midpoints interpolated): refused, then resampled back to 0.02 s
    fine_t = np.arange(2 * len(manoeuvre) - 1) * 0.01
    fine = resample(manoeuvre[LOG], 0.01, tuple(LOG[1:]))
    np.testing.assert_allclose(fine["t"], fine_t, atol=1e-12)
    path, out = tmp_path / "fine.csv", tmp_path / "est.csv"
    fine.to_csv(path, index=False)
    base = [f"input={path}", f"output={out}", "observer=ekf"]
    with pytest.raises(LboError, match="resample=true"):
        observe_cfg(compose_cfg("observe", base))
    result = observe_cfg(compose_cfg("observe", [*base, "resample=true"]))
    m, u = manoeuvre[["x_m", "y_m", "psi_m"]].to_numpy(), manoeuvre[["V", "delta"]].to_numpy()
    ref = ekf_batch(m[None], u[None], VEHICLE, NOISE.Q, NOISE.R(1.0)).mean[0]
    est = pd.read_csv(out)
    assert result["rows"] == len(manoeuvre)
    np.testing.assert_allclose(est[["x", "y"]], ref[:, :2], atol=1e-6)
    # a vehicle.dt override changes what the classical observers accept: the 0.01 s log as is
    fine_out = observe_cfg(compose_cfg("observe", [*base, "vehicle.dt=0.01"]))
    assert fine_out["rows"] == len(fine)
    np.testing.assert_allclose(pd.read_csv(out)["t"], fine_t, atol=1e-12)


def test_resample_takes_the_short_way_round_for_headings():
    # the true heading is interpolated (fixes never are: see test_log_checks)
    df = pd.DataFrame({"t": [0.0, 0.04], "psi": [3.1, -3.1], "x": [0.0, 4.0]})
    out = resample(df, 0.02, ("psi", "x"))
    np.testing.assert_allclose(out["x"], [0.0, 2.0, 4.0])
    assert abs(abs(out["psi"][1]) - np.pi) < 1e-12
    np.testing.assert_allclose(out["psi"][[0, 2]], [3.1, -3.1])


# --- streaming --------------------------------------------------------------------------------


@pytest.mark.parametrize("source", ["learned", "ekf", "oracle", "adaptive", "ukf"])
def test_streaming_equals_batch(trained, smoke_data, source):
    test = pd.read_parquet(smoke_data / "test.parquet")
    frame = test[(test["traj"] == 1) & (test["alpha"] == 3.0)].sort_values("k")
    m, u = frame[["x_m", "y_m", "psi_m"]].to_numpy(), frame[["V", "delta"]].to_numpy()
    obs = Observer.load(trained["checkpoint"] if source == "learned" else source, alpha=3.0)
    est, valid = obs.run(m, u)
    for _ in range(2):  # reset() starts a new log
        obs.reset()
        steps = [obs.step(mk, uk) for mk, uk in zip(m, u)]
        streamed = np.array([s.state for s in steps])
        err = streamed - est
        err[:, 2] = wrap_angle(err[:, 2])
        assert np.abs(err).max() < 1e-6
        np.testing.assert_array_equal([s.valid for s in steps], valid)
    n = obs.window
    assert valid.sum() == len(m) - n + 1
    if source == "learned":
        # the first N-1 rows are the paper's EKF; from row N-1 on, the network's windows
        ekf = ekf_batch(m[None], u[None], obs.vehicle, obs.noise.Q, obs.noise.R(1.0)).mean[0]
        np.testing.assert_allclose(est[:n - 1, :2], ekf[:n - 1, :2], atol=1e-12)
        win = torch.from_numpy(np.concatenate([m, u], axis=1)[None, -n:])
        with torch.no_grad():
            np.testing.assert_allclose(est[-1], obs.net(win)[0].numpy(), atol=1e-6)
        assert obs._runner.ring.shape == (2 * n, 5)  # the history is never kept


def test_step_refuses_x_without_y_and_inf():
    obs = Observer.load("ekf")
    with pytest.raises(LboError, match=r"^step 0: measurement \[0, nan, 0\] has x_m without y_m"):
        obs.step([0.0, np.nan, 0.0], [1.0, 0.0])
    with pytest.raises(LboError, match=r"^step 0: measurement \[0, inf, 0\] has inf \(y_m\)"):
        obs.step([0.0, np.inf, 0.0], [1.0, 0.0])


# --- checkpoints and where they come from -----------------------------------------------------


def _edited(trained, tmp_path, edit):
    ckpt = torch.load(trained["checkpoint"], map_location="cpu", weights_only=True)
    edit(ckpt)
    path = tmp_path / "edited.ckpt"
    torch.save(ckpt, path)
    return path


@pytest.mark.parametrize("edit, kwargs, message", [
    (lambda c: c["hyper_parameters"].update(format=99), {},
     "checkpoint format 99, this lbo reads format 1"),
    (lambda c: c["hyper_parameters"].pop("format"), {}, "checkpoint format None"),
    (lambda c: c["hyper_parameters"].update(features="polar"), {},
     "feature mode 'polar' is unknown to this lbo"),
    (lambda c: None, {"features": "absolute"},
     "trained with features=relative, but features=absolute was asked for"),
    (lambda c: c["state_dict"].pop("observer.in_mean"), {}, "weights do not fit"),
    (lambda c: c.pop("hyper_parameters"), {}, "not an lbo observer checkpoint"),
    # a bad value stored in the checkpoint is the checkpoint's fault, not a setting's
    (lambda c: c["hyper_parameters"]["meta"]["vehicle"].update(dt=-0.02), {},
     "edited.ckpt: its stored vehicle.dt must be a period in seconds > 0, got -0.02"),
])
def test_foreign_checkpoints_are_refused(trained, tmp_path, edit, kwargs, message):
    with pytest.raises(LboError, match=re.escape(message)) as err:
        Observer.load(_edited(trained, tmp_path, edit), **kwargs)
    assert "\n" not in str(err.value)


def test_corrupt_checkpoint_is_one_line(trained, tmp_path):
    path = tmp_path / "cut.ckpt"
    path.write_bytes(open(trained["checkpoint"], "rb").read()[:5000])
    with pytest.raises(LboError, match="not a readable lbo checkpoint \\(damaged, or another "
                                       "kind of file\\)$") as err:
        Observer.load(path)
    assert "\n" not in str(err.value)


class Foreign:
    """An arbitrary class: torch's safe loader refuses to unpickle it."""


@pytest.mark.parametrize("content, reason", [
    (b"just some bytes, not a checkpoint" * 10, "damaged, or another kind of file"),
    (None, "it holds pickled objects beyond tensors and plain containers, which lbo never "
           "unpickles"),
])
def test_a_foreign_file_named_ckpt_is_not_an_lbo_checkpoint(tmp_path, content, reason):
    path = tmp_path / "model.ckpt"
    if content is None:  # a real torch file, but with an arbitrary pickled object inside
        torch.save({"state_dict": {}, "obj": Foreign()}, path)
    else:
        path.write_bytes(content)
    with pytest.raises(LboError) as err:
        Observer.load(path)
    assert str(err.value) == f"checkpoint {path}: not a readable lbo checkpoint ({reason})"
    assert "weights_only" not in str(err.value)


def test_an_unknown_feature_mode_is_named_as_such(trained):
    with pytest.raises(LboError, match=r"^features: unknown mode 'foo'; expected one of "
                                       r"relative, frame, absolute$"):
        Observer.load(trained["checkpoint"], features="foo")


def test_checkpoint_carries_the_observer(trained):
    obs = Observer.load(trained["checkpoint"], features="relative")
    assert (obs.name, obs.window, obs.dt, obs.features) == ("cnn-N20", 20, 0.02, "relative")
    assert obs.noise.name == "paper" and obs.vehicle == VEHICLE
    assert torch.all(obs.net.in_std != 1.0)  # normalisation statistics of the training set


def test_a_run_in_a_local_store_is_read_in_place_and_others_through_mlflow(trained,
                                                                           monkeypatch):
    import mlflow

    from lbo.tracking.artifacts import checkpoint_file, local_run_checkpoint

    run = mlflow.MlflowClient(trained["uri"]).get_run(trained["run_id"])
    folder = Path(run.info.artifact_uri.removeprefix("file://"))
    in_place = local_run_checkpoint(trained["run_id"], trained["uri"])
    assert in_place == folder / "checkpoints" / "best.ckpt"
    assert in_place.read_bytes() == Path(trained["checkpoint"]).read_bytes()
    # not in place: no such run, no such store, a server, a run whose checkpoint is gone
    assert local_run_checkpoint("0" * 32, trained["uri"]) is None
    assert local_run_checkpoint(trained["run_id"], trained["uri"] + ".missing") is None
    assert local_run_checkpoint(trained["run_id"], "http://127.0.0.1:1") is None
    not_mlflow = Path(trained["checkpoint"]).parent / "other.db"
    sqlite3.connect(not_mlflow).close()  # an empty database: no runs table
    assert local_run_checkpoint(trained["run_id"], f"sqlite:///{not_mlflow}") is None
    moved = in_place.with_name("moved.ckpt")
    in_place.rename(moved)
    try:
        assert local_run_checkpoint(trained["run_id"], trained["uri"]) is None
    finally:
        moved.rename(in_place)
    # the store is only read: its bytes are the same after
    store = Path(trained["uri"].removeprefix("sqlite:///"))
    before = store.read_bytes()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", trained["uri"])
    with checkpoint_file(trained["run_id"]) as path:
        assert path == in_place
    assert store.read_bytes() == before


def test_run_id_and_registered_model_load_the_same_observer(trained, manoeuvre, monkeypatch,
                                                            capfd):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", trained["uri"])
    m, u = manoeuvre[["x_m", "y_m", "psi_m"]].to_numpy(), manoeuvre[["V", "delta"]].to_numpy()
    ref, _ = Observer.load(trained["checkpoint"]).run(m, u)
    capfd.readouterr()
    by_run = Observer.load(trained["run_id"])
    assert "Downloading artifacts" not in capfd.readouterr().err  # no progress bars
    np.testing.assert_array_equal(by_run.run(m, u)[0], ref)
    uri = register(trained["run_id"], "lbo-test")
    assert uri == "models:/lbo-test/1"
    np.testing.assert_array_equal(Observer.load(uri).run(m, u)[0], ref)
    # a second version, promoted: the alias follows it
    assert register(trained["run_id"], "lbo-test", alias="champion") == "models:/lbo-test/2"
    np.testing.assert_array_equal(Observer.load("models:/lbo-test@champion").run(m, u)[0], ref)
    import mlflow

    client = mlflow.MlflowClient(trained["uri"], registry_uri=trained["uri"])
    assert str(client.get_model_version_by_alias("lbo-test", "champion").version) == "2"
    with pytest.raises(LboError, match=f"MLflow run {'0' * 31}1 not found"):
        Observer.load("0" * 31 + "1")
    with pytest.raises(LboError, match="models:/lbo-test/7 not found"):
        Observer.load("models:/lbo-test/7")


def test_import_lbo_stays_light():
    code = ("import sys, lbo; assert 'torch' not in sys.modules; "
            "assert lbo.Observer.load('ekf').name == 'ekf'; print(sorted(lbo.__all__))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "Observer" in res.stdout
    # a classical observer over a log, as lbo.observe runs it, needs no torch (2 s of imports)
    code = ("import sys, numpy as np, lbo.observe; from lbo import Observer; "
            "m = np.c_[np.arange(50.0), np.zeros(50), np.zeros(50)]; "
            "est, valid = Observer.load('ekf').run(m, np.tile([10.0, 0.0], (50, 1))); "
            "assert valid.all(); assert 'torch' not in sys.modules, 'torch imported'")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


def test_plot_draws_the_estimate_over_the_log(tmp_path, log_csv):
    from matplotlib.image import imread

    res = observe("observer=ekf", f"input={log_csv}", f"output={tmp_path / 'est.csv'}",
                  f"plot={tmp_path / 'fig.png'}")
    assert "plot:" in res.stdout
    image = imread(tmp_path / "fig.png")
    assert image.shape[0] > 200 and image.std() > 0.01  # a figure, not a blank
    bad = observe("observer=ekf", f"input={log_csv}", f"output={tmp_path / 'b.csv'}",
                  f"plot={tmp_path / 'b.jpg'}", check=False)
    assert bad.returncode != 0
    assert "plot must be true, false or a .png file" in bad.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "b.csv").exists()


def test_plot_true_writes_a_png_beside_the_output(tmp_path, log_csv):
    from matplotlib.image import imread

    res = observe("observer=ekf", f"input={log_csv}", f"output={tmp_path / 'est.parquet'}",
                  "plot=true")
    assert f"plot: {tmp_path / 'est.png'}" in res.stdout
    assert imread(tmp_path / "est.png").std() > 0.01


def test_compare_draws_more_observers_in_the_plot_and_prints_their_rmse(tmp_path, log_csv):
    from matplotlib.image import imread

    res = observe("observer=ekf", f"input={log_csv}", f"output={tmp_path / 'est.csv'}",
                  "plot=true", "compare=[ukf,adaptive]")
    said = [line for line in res.stdout.splitlines() if line.startswith("compare ")]
    assert [line.split(":")[0] for line in said] == ["compare ukf", "compare adaptive"]
    assert all(re.search(r"rmse x [\d.e-]+ m, y [\d.e-]+ m, psi [\d.e-]+ rad", line)
               for line in said)
    assert imread(tmp_path / "est.png").std() > 0.01
    assert list(pd.read_csv(tmp_path / "est.csv").columns[:5]) == ["t", "x", "y", "psi", "valid"]
    for extra, line in ((["compare=[ukf]"], "compare: draws more observers in the plot; give "
                         "plot=true (or a .png)"),
                        (["plot=true", "compare=ukf"], "compare: expected a list of observers, "
                         "e.g. compare=[ekf,gyro], got 'ukf'"),
                        (["plot=true", f"compare=[{tmp_path / 'none.ckpt'}]"],
                         f"observer: checkpoint not found: {tmp_path / 'none.ckpt'}")):
        bad = observe("observer=ekf", f"input={log_csv}", f"output={tmp_path / 'b.csv'}",
                      *extra, check=False)
        assert bad.returncode == 2 and bad.stderr.strip() == f"error: {line}"
        assert not (tmp_path / "b.csv").exists()


def test_the_plot_shows_errors_against_the_truth_or_the_uncertainty(manoeuvre):
    from lbo.core import plots

    t = manoeuvre["t"].to_numpy()
    m = manoeuvre[["x_m", "y_m", "psi_m"]].to_numpy()
    z = manoeuvre[["x", "y", "psi"]].to_numpy()
    est, cov = run_classical("ekf", m[None], manoeuvre[["V", "delta"]].to_numpy()[None], VEHICLE,
                             NOISE)
    est, cov = est[0], cov[0]

    def panels(fig):
        labels = [[t.get_text() for t in ax.get_legend().get_texts()] for ax in fig.axes]
        plots.plt.close(fig)
        return labels

    # the path, then a panel each for x, y and psi: its error and its own sigma band
    both = panels(plots.observed_log(t, m, est, "ekf", z, cov))
    assert len(both) == 4 and both[0] == ["fixes", "ekf", "truth"]
    assert both[1] == both[2] == both[3] == ["ekf: +-2 sigma", "ekf: error"]
    assert panels(plots.observed_log(t, m, est, "ekf", None, cov))[1:] == \
        [["ekf: +-2 sigma"]] * 3
    assert panels(plots.observed_log(t, m, est, "cnn", z, None))[3] == ["cnn: error"]
    assert len(panels(plots.observed_log(t, m, est, "cnn", None, np.full((len(t), 3, 3),
                                                                          np.nan)))) == 1
    # another observer beside it: its path, and its errors in each panel
    beside = panels(plots.observed_log(t, m, est, "ekf", z, None, {"ukf": est + 0.1}))
    assert beside[0] == ["fixes", "ekf", "ukf", "truth"]
    assert beside[1] == beside[2] == beside[3] == ["ekf: error", "ukf: error"]


def test_evaluate_scores_an_existing_observer_and_logs_to_its_run(trained, smoke_data, tmp_path,
                                                                   monkeypatch, capsys):
    import mlflow

    from lbo.evaluate import evaluate

    monkeypatch.setenv("MLFLOW_TRACKING_URI", trained["uri"])
    csv = evaluate(compose_cfg("evaluate", ["data=smoke", f"data.root={smoke_data.parent}",
                                            f"output_dir={tmp_path / 'ev'}", "observers=[ekf]",
                                            f"observer={trained['run_id']}"]))
    assert f"logged to MLflow run {trained['run_id']}" in capsys.readouterr().out
    table = pd.read_csv(csv)
    mine = table[table["observer"] == "cnn-N20"].set_index("alpha")["nrmse"]
    assert len(mine) == 7
    client = mlflow.MlflowClient(trained["uri"])
    logged = client.get_run(trained["run_id"]).data.metrics
    assert {a: logged[f"eval_smoke_nrmse_alpha_{a:g}"] for a in mine.index} == mine.to_dict()
    files = [a.path for a in client.list_artifacts(trained["run_id"], "evaluations/smoke")]
    assert "evaluations/smoke/evaluation.csv" in files
    # a checkpoint file has no run to log to: scored, and said so
    evaluate(compose_cfg("evaluate", ["data=smoke", f"data.root={smoke_data.parent}",
                                      f"output_dir={tmp_path / 'ck'}", "observers=[ekf]",
                                      f"observer={trained['checkpoint']}"]))
    assert "is a checkpoint file, not an MLflow run" in capsys.readouterr().out
    with pytest.raises(LboError, match=f"observer: MLflow run {'0' * 31}1 not found"):
        evaluate(compose_cfg("evaluate", ["data=smoke", f"data.root={smoke_data.parent}",
                                          f"output_dir={tmp_path / 'no'}", "observers=[ekf]",
                                          "observer=" + "0" * 31 + "1"]))
    assert not (tmp_path / "no" / "evaluation.csv").exists()


def test_a_learned_observer_runs_on_the_threads_it_is_given(trained, tmp_path, log_csv):
    """One thread by default: a learned observer's windows are small, and more threads mostly
    spin (under one other job, 17-19 s against 32-82 s with two on this machine)."""
    try:
        observe_cfg(compose_cfg("observe", [f"observer={trained['checkpoint']}",
                                            f"input={log_csv}", f"output={tmp_path / 'a.csv'}",
                                            "threads=2"]))
        assert torch.get_num_threads() == 2
        observe_cfg(compose_cfg("observe", [f"observer={trained['checkpoint']}",
                                            f"input={log_csv}", f"output={tmp_path / 'b.csv'}"]))
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(1)  # as this module's fixture has it


def test_engine_runs_a_learned_observer_in_torchscript_or_onnx_runtime(trained, tmp_path,
                                                                       log_csv):
    def run(*extra):
        out = tmp_path / f"est{len(list(tmp_path.iterdir()))}.csv"
        observe_cfg(compose_cfg("observe", [f"observer={trained['checkpoint']}",
                                            f"input={log_csv}", f"output={out}", *extra]))
        return pd.read_csv(out)

    want = run()
    for engine in ("torchscript", "onnx"):
        got = run(f"engine={engine}")
        np.testing.assert_allclose(got[["x", "y", "psi"]], want[["x", "y", "psi"]], rtol=0,
                                   atol=TOLERANCE, err_msg=engine)
    # checked before any checkpoint is read
    with pytest.raises(LboError, match=r"^engine must be one of \['torch', 'torchscript', "
                                       r"'onnx', 'auto'\], got 'tensorrt'$"):
        observe_cfg(compose_cfg("observe", ["observer=missing.ckpt", f"input={log_csv}",
                                            f"output={tmp_path / 'x.csv'}", "engine=tensorrt"]))


@pytest.mark.parametrize("alpha", [0.0, 0.5, 3.0, 6.0])
def test_the_oracle_told_alpha_runs_and_steps_as_the_grids_oracle(manoeuvre, alpha):
    """lbo.Observer builds the oracle with its R at alpha when it is made: run and stepped, it
    gives the grid's oracle told the same alpha (lbo.filters.classical.estimate), estimates
    and covariances."""
    m = manoeuvre[["x_m", "y_m", "psi_m"]].to_numpy()
    u = manoeuvre[["V", "delta"]].to_numpy()
    ref = run_classical("oracle", m[None], u[None], Vehicle(), Noise.preset("paper"), alpha)
    obs = Observer.load("oracle", alpha=alpha)
    run = obs.run(m, u)
    np.testing.assert_allclose(run.state, ref.mean[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(run.cov, ref.cov[0], rtol=1e-9, atol=1e-12)
    obs.reset()
    steps = np.array([obs.step(m[k], u[k]).state for k in range(len(m))])
    np.testing.assert_allclose(steps, ref.mean[0], rtol=0, atol=1e-9)
    assert repr(obs).endswith(f"alpha={alpha:g})") and obs.noise == Noise.preset("paper")
