"""The robust experiment (filternet, frame features, drawn noise) end to end at smoke scale:
train, then observe a log with its checkpoint."""

import re

import mlflow
import numpy as np
import pandas as pd
import pytest
import torch

from helpers import compose_cfg, observe, store_client
from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.learn.lightning_module import TrainingModule
from lbo.serve.observer import Observer
from lbo.train import train

LOG = ["t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def robust(robust_smoke):
    return robust_smoke


@pytest.fixture(scope="module")
def noisy(smoke_data):
    """The smoke test set's first manoeuvre at alpha = 3 (conftest's ``manoeuvre`` is at 1)."""
    test = pd.read_parquet(smoke_data / "test.parquet")
    return test[(test["traj"] == 0) & (test["alpha"] == 3.0)].sort_values("k")


def test_robust_experiment_trains_and_scores(robust):
    out = robust["out"]
    assert out["name"] == "filternet-N40"
    assert np.isfinite(out["val_loss"])
    for a in (1, 3, 6):
        assert np.isfinite(out[f"test_nrmse_alpha_{a}"])
    table = pd.read_csv(robust["dir"] / "evaluation.csv")
    assert set(table["observer"]) == {"filternet-N40", "ekf", "oracle"}
    client = mlflow.MlflowClient(robust["uri"])
    run = client.get_run(out["run_id"])
    assert run.info.status == "FINISHED"
    assert run.data.tags["train_noise"] == "uniform [0, 6.5]"
    assert run.data.tags["features"] == "frame" and run.data.tags["model"] == "filternet"
    module = TrainingModule.load_from_checkpoint(out["checkpoint"], map_location="cpu")
    hp = module.hparams
    assert hp["features"] == "frame" and hp["window"] == 40 and hp["model"]["name"] == "filternet"
    # the filter's model comes from the run's vehicle and noise preset, resolved
    assert hp["model"]["dt"] == 0.02 and list(hp["model"]["measurement_sigma"]) == [1.0, 1.0,
                                                                                     0.0174]
    # five steps of training moved the learned parts off their initial values
    net = module.observer.net
    assert net.noise[-1].weight.abs().max() > 0 or net.log_q_scale.abs().max() > 0


def test_observe_cli_runs_the_robust_checkpoint(robust, noisy, tmp_path):
    log, est_path = tmp_path / "log.csv", tmp_path / "est.csv"
    noisy[LOG].to_csv(log, index=False)
    res = observe(f"observer={robust['out']['checkpoint']}", f"input={log}",
                  f"output={est_path}")
    assert res.returncode == 0, res.stderr[-3000:]
    assert "features frame" in res.stdout
    found = re.search(r"rmse x (\S+) m, y (\S+) m, psi (\S+) rad", res.stdout)
    assert found, res.stdout
    assert np.all(np.isfinite([float(v) for v in found.groups()]))
    est = pd.read_csv(est_path)
    # the robust observer knows how sure it is: its covariance's entries come with it, and
    # which rows lie outside what it was trained on
    assert list(est.columns) == ["t", "x", "y", "psi", "valid", "var_x", "var_y", "var_psi",
                                 "cov_xy", "outside"]
    assert (est[["var_x", "var_y", "var_psi"]] > 0).all(axis=None)
    # a window filter that starts at its first fix: valid from the log's first row
    assert len(est) == len(noisy) and est["valid"].all()
    assert np.isfinite(est[["x", "y", "psi"]].to_numpy()).all()
    # the same numbers as the Python API
    m, u = noisy[["x_m", "y_m", "psi_m"]].to_numpy(), noisy[["V", "delta"]].to_numpy()
    ref, valid = Observer.load(robust["out"]["checkpoint"]).run(m, u)
    np.testing.assert_array_equal(est["valid"].to_numpy(), valid)
    np.testing.assert_allclose(est[["x", "y"]].to_numpy(), ref[:, :2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(wrap_angle(est["psi"].to_numpy() - ref[:, 2]), 0, atol=1e-9)


def test_observe_smooths_the_robust_observer(robust, noisy, tmp_path):
    from lbo.observe import observe

    log = tmp_path / "log.csv"
    noisy[LOG].to_csv(log, index=False)
    ckpt = robust["out"]["checkpoint"]
    res = {s: observe(compose_cfg("observe", [f"observer={ckpt}", f"input={log}", f"smooth={s}",
                                          f"output={tmp_path / f'{s}.csv'}"]))
           for s in ("false", "true")}
    assert (res["true"]["rmse"][:2] < 0.95 * res["false"]["rmse"][:2]).all(), res
    m, u = noisy[["x_m", "y_m", "psi_m"]].to_numpy(), noisy[["V", "delta"]].to_numpy()
    smoothed = Observer.load(ckpt, form="recursive").run(m, u, smooth=True)
    ref, cov = smoothed.state, smoothed.cov
    est = pd.read_csv(tmp_path / "true.csv")
    np.testing.assert_allclose(est[["x", "y"]].to_numpy(), ref[:, :2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(est["var_y"].to_numpy(), cov[:, 1, 1], rtol=1e-9)


def test_observer_load_runs_and_streams_the_robust_checkpoint(robust, noisy):
    obs = Observer.load(robust["out"]["checkpoint"])
    assert (obs.name, obs.kind, obs.window, obs.features) == ("filternet-N40", "learned", 40,
                                                              "frame")
    m, u = noisy[["x_m", "y_m", "psi_m"]].to_numpy(), noisy[["V", "delta"]].to_numpy()
    est, valid = obs.run(m, u)
    assert est.shape == (len(m), 3) and np.isfinite(est).all()
    assert valid.all()  # it starts at the first fix, so a window reaching back is no loss
    z = noisy[["x", "y", "psi"]].to_numpy()
    err = np.abs(est[valid, :2] - z[valid, :2])
    assert err.mean() < 3.0  # a filter at alpha=3 (sigma 3 m), not garbage
    # step by step: the same estimates
    n = 120
    obs.reset()
    streamed = np.array([obs.step(mk, uk).state for mk, uk in zip(m[:n], u[:n])])
    gap = streamed - est[:n]
    gap[:, 2] = wrap_angle(gap[:, 2])
    assert np.abs(gap).max() < 1e-6
    # rotate and shift the whole log: the estimates rotate and shift with it
    theta, shift = 0.8, np.array([500.0, -250.0])
    c, s = np.cos(theta), np.sin(theta)
    rot = np.array([[c, -s], [s, c]])
    moved = np.column_stack([m[:, :2] @ rot.T + shift, wrap_angle(m[:, 2] + theta)])
    est_moved, _ = obs.run(moved, u)
    np.testing.assert_allclose(est_moved[valid, :2], est[valid, :2] @ rot.T + shift, atol=1e-6)
    np.testing.assert_allclose(wrap_angle(est_moved[valid, 2] - est[valid, 2] - theta), 0,
                               atol=1e-6)


def test_robust_checkpoint_refuses_another_feature_mode(robust):
    for mode in ("relative", "absolute"):
        with pytest.raises(LboError, match=re.escape(
                f"trained with features=frame, but features={mode} was asked for")) as err:
            Observer.load(robust["out"]["checkpoint"], features=mode)
        assert "\n" not in str(err.value)
    assert Observer.load(robust["out"]["checkpoint"], features="frame").features == "frame"


# --- filternet needs frame features --------------------------------------------------------


def _filternet_relative(tmp_path, root):
    """The window filter told to read relative features (its own default is frame)."""
    return compose_cfg("train", ["experiment=smoke", f"data.root={root}",
                                 f"output_dir={tmp_path / 'out'}", "model=filternet",
                                 "model.features=relative"])


def test_filternet_with_relative_features_is_refused_before_training(tmp_path, smoke_data,
                                                                      monkeypatch):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    cfg = _filternet_relative(tmp_path, smoke_data.parent)
    assert cfg.model.features == "relative"
    with pytest.raises(LboError, match=r"^features: model 'filternet' needs features in "
                                       r"\['frame'\], got 'relative'$") as err:
        train(cfg)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "out").exists()
    exp = store_client(uri).get_experiment_by_name("lbo-smoke")
    assert exp is None or store_client(uri).search_runs([exp.experiment_id]) == []


def test_filternet_with_relative_features_is_refused_before_the_data_is_generated(
        tmp_path, monkeypatch):
    """Bad settings are refused "before any work" (lbo.train.check): a data set that is not
    cached yet (at paper scale, a long job) must not be generated first."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    root = tmp_path / "data"
    with pytest.raises(LboError, match="^features: model 'filternet' needs features"):
        train(_filternet_relative(tmp_path, root))
    assert not root.exists() or not any(root.iterdir()), "a data set was generated first"
    assert not (tmp_path / "out").exists()


# --- the checkpoint's stored window and envelope ------------------------------------------------


def test_a_checkpoint_naming_a_huge_window_is_one_line(robust, tmp_path):
    """A window of 10**10 steps (tensors only, so weights_only loads it) sized the recursive
    form's state and the ring buffer: hundreds of GB, a RuntimeError traceback. Refused in one
    line before anything is allocated."""
    ckpt = torch.load(robust["out"]["checkpoint"], map_location="cpu", weights_only=True)
    ckpt["hyper_parameters"]["window"] = 10 ** 10
    path = tmp_path / "huge.ckpt"
    torch.save(ckpt, path)
    with pytest.raises(LboError, match=re.escape(
            f"checkpoint {path}: window: expected an integer number of steps in [1, 10000], "
            "got 10000000000")) as err:
        Observer.load(path)
    assert "\n" not in str(err.value)


def test_the_robust_envelope_spans_its_drawn_noise_and_fix_rates(robust):
    env = Observer.load(robust["out"]["checkpoint"]).envelope
    assert env.alpha == (0.0, 6.5)  # train_noise=diverse
    assert env.fix_period == (1.0, 50.0)  # fix_rates [50, 10, 5, 1] at 50 Hz


@pytest.mark.parametrize("model", ["filternet", "kalmannet", "split_kalmannet"])
def test_a_frame_model_brings_its_feature_mode_unless_told_otherwise(model):
    """experiment=smoke (or none) leaves features relative for the CNN and the LSTM; the
    models that read the latest fix's frame only set it themselves (issue 73)."""
    for experiment in ([], ["experiment=smoke"]):
        assert compose_cfg("train", [*experiment, f"model={model}"]).model.features == "frame"
    assert compose_cfg("train", ["experiment=smoke"]).model.features == "relative"
    told = compose_cfg("train", [f"model={model}", "model.features=absolute"])
    assert told.model.features == "absolute"  # the user's word wins (and is refused)
