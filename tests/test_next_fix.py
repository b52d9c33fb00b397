"""Training without the truth (issue 70): ``loss=next_fix`` teaches each window's estimate by
the fix of the step after it, which the window never read. Its batches hold no truth, the
fix's noise is its own, and the loss ranks estimators as their error against the truth does."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from helpers import cli, one_line_error
from lbo.learn.datamodule import WindowDataset, rows, window_ends
from lbo.learn.draws import AlphaDraw
from lbo.models.motion import bicycle_step
from lbo.models.net import WindowNet
from lbo.models.poses import wrap_angle_torch

SIGMA = torch.tensor([1.0, 1.0, 0.0174], dtype=torch.float64)
N, DT, L = 20, 0.02, 2.7


@pytest.fixture(scope="module")
def windows(smoke_data):
    df = pd.read_parquet(smoke_data / "train.parquet")
    x, y = rows(df)
    k = df["k"].to_numpy()
    ends = window_ends(k, N, next_step=True)
    ds = WindowDataset(x, y, ends, N, draw=AlphaDraw("uniform", low=0.5, high=3.0),
                       sigma=SIGMA, seed=0, next_fix=True)
    return ds, k


def test_no_window_ends_on_the_last_step_of_its_trajectory(windows):
    ds, k = windows
    e = ds.ends.numpy()
    assert len(e) and (k[e + 1] == k[e] + 1).all()
    last = np.flatnonzero(np.append(k[1:] != k[:-1] + 1, True))
    assert not np.isin(last, e).any() and np.isin(last - 1, e).any()


def test_a_batch_holds_the_next_fix_and_the_last_inputs_not_the_truth(windows):
    ds, _ = windows
    idx = torch.arange(len(ds))
    win, after, weight = ds[idx]
    e = ds.ends
    assert after.shape == (len(ds), 5) and weight.shape == (len(ds),)
    torch.testing.assert_close(after[:, 3:], ds.x[e, 3:5], rtol=0, atol=0)
    # the next fix is the next true state plus noise at the window's own alpha
    d = after[:, :3] - ds.y[e + 1]
    d = torch.cat([d[:, :2], wrap_angle_torch(d[:, 2:])], 1) / SIGMA
    last = win[:, -1, :3] - ds.y[e]
    last = torch.cat([last[:, :2], wrap_angle_torch(last[:, 2:])], 1) / SIGMA
    alpha = last.std(1)  # a crude per-window scale would be noisy: compare the spreads
    assert 0.9 < float(d.std() / last.std()) < 1.1
    # ... drawn apart from the window's: uncorrelated with its last fix's noise
    for c in range(3):
        r = np.corrcoef(d[:, c].numpy(), last[:, c].numpy())[0, 1]
        assert abs(r) < 0.05, (c, r)
    # ... and scaled with it: windows of larger alpha have larger next-fix errors
    big = alpha > alpha.median()
    assert float(d[big].abs().mean()) > 1.2 * float(d[~big].abs().mean())


class _Estimator:
    """Stands in for a WindowNet whose estimates are given (unit target scales)."""

    out_std = torch.ones(3, dtype=torch.float64)
    _weighted = staticmethod(WindowNet._weighted)

    def __init__(self, estimate: torch.Tensor) -> None:
        self.estimate = estimate

    def __call__(self, win: torch.Tensor) -> torch.Tensor:
        return self.estimate


def _loss_of(estimate: torch.Tensor, win, after):
    """:meth:`WindowNet.next_fix_loss` of an estimator whose outputs are ``estimate``."""
    return WindowNet.next_fix_loss(_Estimator(estimate), win, after, None, DT, L)  # type: ignore[arg-type]


def test_the_loss_ranks_estimators_as_the_truth_does_and_its_excess_is_their_error(windows):
    """The next fix's noise is independent of the window: the loss of any estimate is its
    one-step prediction's mean square error against the truth plus the same constant (the
    fix's noise, and the truth's own step), so a better estimate scores lower, by its
    error."""
    ds, _ = windows
    idx = torch.arange(len(ds))
    win, after, _ = ds[idx]
    truth = ds.y[ds.ends]
    base = float(_loss_of(truth, win, after))
    for off in (0.1, 0.3, 0.6):
        shifted = truth + torch.tensor([off, -off, 0.0], dtype=torch.float64)
        excess = float(_loss_of(shifted, win, after)) - base
        # (x and y each off by `off` m; the loss is the mean over the three channels)
        assert excess == pytest.approx(2 * off**2 / 3, rel=0.1, abs=3e-3), off
    noisy = float(_loss_of(win[:, -1, :3], win, after))
    assert noisy > base  # the raw last fix is a worse estimate than the truth
    # a fix without a heading (a single antenna): that channel is left out, not NaN
    blind = after.clone()
    blind[:, 2] = float("nan")
    assert torch.isfinite(_loss_of(truth, win, blind))


def test_the_kinematic_step_moves_the_estimate_as_the_simulator_does(windows):
    ds, _ = windows
    e = ds.ends[:500]
    moved = bicycle_step(ds.y[e], ds.x[e, 3], ds.x[e, 4], DT, L)
    # u_k moves z_k to z_{k+1}: what is left is the smoke set's process noise (0.067 m a
    # step), a fraction of the step itself
    rms = lambda d: float(d[:, :2].pow(2).mean().sqrt())  # noqa: E731
    assert rms(moved - ds.y[e + 1]) < 0.09 < 0.5 * rms(ds.y[e] - ds.y[e + 1])


@pytest.mark.parametrize(("args", "words"), [
    (("loss=nll",), ("loss must be one of ['truth', 'next_fix']",)),
    (("loss=next_fix", "model=filternet", "features=frame", "tbptt=10"),
     ("loss=next_fix: expected tbptt=null",)),
    (("loss=next_fix", "experiment=receiver"), ("loss=next_fix: expected receiver=null",)),
    (("loss=next_fix", "sensors=drift"), ("loss=next_fix: expected sensors.gnss_sigma=null",)),
])
def test_settings_it_cannot_train_are_one_line(tmp_path, args, words):
    res = cli("lbo.train", "experiment=smoke", *args, f"output_dir={tmp_path / 'out'}",
              f"hydra.run.dir={tmp_path / 'h'}",
              env={"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"})
    one_line_error(res, *words)


@pytest.mark.slow
def test_kalmannet_trains_without_truth_as_unsupervised_kalmannet(tmp_path, smoke_data):
    """KalmanNet's window form learns from the next fixes alone (its unsupervised form): the
    run says so, its weights move from their start, and the test grid's truth scores it."""
    import mlflow

    from helpers import train_in_own_store
    from lbo.learn.builders import build_net
    from lbo.tracking.artifacts import load_net

    cfg, metrics, uri = train_in_own_store(tmp_path, smoke_data, "experiment=smoke",
                                           "model=kalmannet", "features=frame", "loss=next_fix")
    run = mlflow.MlflowClient(uri).get_run(metrics["run_id"])
    assert run.data.params["loss"] == "next_fix" and run.info.status == "FINISHED"
    assert np.isfinite(metrics["test_nrmse_alpha_1"])
    trained, _ = load_net(metrics["checkpoint"])
    start = build_net(cfg).state_dict()
    moved = [k for k, v in trained.state_dict().items()
             if k in start and v.dtype.is_floating_point and not torch.equal(v, start[k])
             and not k.startswith(("in_", "out_"))]
    assert moved  # the gain network learned something from the next fixes


def test_the_new_settings_keep_the_hashes_of_runs_made_before_them(tmp_path, smoke_data):
    """``loss`` (and ``data.source`` of data=logs) came after runs were stored: at their
    defaults a config's version-1 hash is one's without them (the hash those runs carry),
    and those runs, migrated, are the config's, so resume=true still finds them."""
    from omegaconf import open_dict

    from helpers import compose_cfg, train_cfg
    from lbo.learn.layouts import hash_v1, upgraded
    from lbo.train import config_hash

    now = train_cfg(tmp_path, smoke_data)
    before = now.copy()
    with open_dict(before):
        before.pop("loss")
    assert hash_v1(now) == hash_v1(before)
    assert config_hash(upgraded(before)) == config_hash(now)
    assert config_hash(train_cfg(tmp_path, smoke_data, "loss=next_fix")) != config_hash(now)
    logs = compose_cfg("train", ["experiment=logs"] + [
        f"data.{part}=[{smoke_data / part}.parquet]" for part in ("train", "val", "test")])
    old = logs.copy()
    with open_dict(old):
        assert old.data.pop("source") == "files"
    assert hash_v1(logs) == hash_v1(old)
    assert config_hash(upgraded(old)) == config_hash(logs)


# --- a user's logs without the truth (data=logs) ------------------------------------------------

LOG_COLUMNS = ["t", "x_m", "y_m", "psi_m", "V", "delta"]


@pytest.fixture(scope="module")
def fleet(smoke_data, tmp_path_factory):
    """The smoke test set's manoeuvres as logs, twice: ``truth/`` with the reference's x, y,
    psi and ``blind/`` the same logs without them, but for the test logs (scored by it)."""
    root = tmp_path_factory.mktemp("fleet")
    test = pd.read_parquet(smoke_data / "test.parquet")
    for (traj, alpha), g in test.groupby(["traj", "alpha"]):
        part = "val" if alpha == 1.0 else "test" if alpha == 3.0 else "train"
        log = g.sort_values("k")[[*LOG_COLUMNS, "x", "y", "psi"]]
        for kind in ("truth", "blind"):
            (root / kind / part).mkdir(parents=True, exist_ok=True)
            kept = log if kind == "truth" or part == "test" else log[LOG_COLUMNS]
            kept.to_csv(root / kind / part / f"m{traj}_a{alpha:g}.csv", index=False)
    return root


def fleet_cfg(logs, tmp, *overrides: str):
    from helpers import compose_cfg

    return compose_cfg("train", [
        "experiment=smoke", "data=logs", "train_noise=stored", "data.run_in=100",
        "keep_onnx=false", *(f"data.{p}=[{logs}/{p}]" for p in ("train", "val", "test")),
        f"data.root={tmp}/data", f"output_dir={tmp}/out", *overrides])


def test_logs_without_the_truth_make_sets_that_say_so(fleet, tmp_path):
    import json

    from lbo.logs import sets as log_sets

    spec = log_sets.spec_from_cfg(fleet_cfg(fleet / "blind", tmp_path, "loss=next_fix"))
    folder, sets, _ = log_sets.build(spec, progress=False)
    for part in ("train", "val"):
        assert sets[part][["x", "y", "psi"]].isna().all(axis=None)
        assert sets[part][["x_m", "y_m", "V", "delta"]].notna().all(axis=None)
    assert sets["val"]["alpha"].isna().all()  # the noise level needs the truth too
    assert sets["test"][["x", "y", "psi"]].notna().all(axis=None)
    facts = json.loads((folder / "manifest.json").read_text())["files"]
    assert {f["truth"] for f in facts["train"] + facts["val"]} == {False}
    assert {f["truth"] for f in facts["test"]} == {True}
    said = log_sets.summary(folder, sets, 0.02)
    assert "15 log(s) without the truth" in said[0] and "without" not in said[2]


@pytest.mark.parametrize(("kind", "drop", "words"), [
    ("test", ["x", "y", "psi"], "data=logs scores the test logs against the reference"),
    ("train", ["psi"], "missing true-state column psi"),
])
def test_a_test_log_without_the_truth_or_a_log_with_part_of_it_is_one_line(
        fleet, tmp_path, kind, drop, words):
    import shutil

    from lbo.core.errors import LboError
    from lbo.logs import sets as log_sets

    logs = tmp_path / "logs"
    shutil.copytree(fleet / "truth", logs)
    bad = sorted((logs / kind).iterdir())[0]
    pd.read_csv(bad).drop(columns=drop).to_csv(bad, index=False)
    spec = log_sets.spec_from_cfg(fleet_cfg(logs, tmp_path))
    with pytest.raises(LboError, match=f"^log {bad}: .*{words}"):
        log_sets.build(spec, progress=False)
    assert not (tmp_path / "data").exists() or not any((tmp_path / "data").rglob("*.parquet"))


@pytest.mark.parametrize(("overrides", "words"), [
    ((), "train on them with loss=next_fix, or give logs that have it"),
    (("loss=next_fix", "train_noise=paper"),
     "train on the logs' own fixes \\(train_noise=stored\\)"),
])
def test_the_truth_or_noise_drawn_around_it_on_logs_without_it_is_one_line(
        fleet, tmp_path, overrides, words):
    from lbo.core.errors import LboError
    from lbo.learn.builders import datamodule, prepare_data

    cfg = fleet_cfg(fleet / "blind", tmp_path, *overrides)
    with pytest.raises(LboError, match=f"^the training set holds logs without the truth.*{words}$"):
        datamodule(cfg, prepare_data(cfg)[0])


@pytest.mark.slow
def test_logs_without_the_truth_train_as_the_same_logs_with_it(fleet, tmp_path, tracking,
                                                               one_torch_thread):
    """loss=next_fix never reads the truth: the same logs with and without it train to the
    same weights and the same validation losses, scored on the test logs' truth alike."""
    from lbo.tracking.artifacts import load_net
    from lbo.train import train

    done = {kind: train(fleet_cfg(fleet / kind, tmp_path / kind, "loss=next_fix"))
            for kind in ("truth", "blind")}
    for key in ("val_loss", "test_nrmse"):
        assert np.isfinite(done["blind"][key]) and done["blind"][key] == done["truth"][key], key
    nets = {kind: load_net(d["checkpoint"])[0].state_dict() for kind, d in done.items()}
    for name, value in nets["truth"].items():
        assert torch.equal(value, nets["blind"][name]), name


@pytest.mark.slow
def test_a_fleet_without_any_truth_trains_and_is_scored_later_where_there_is_some(
        fleet, tmp_path, tracking, one_torch_thread, capsys):
    """No test logs at all (data.test=[]): the training runs to a finished run that says it
    is not scored; lbo.evaluate observer=<that run> scores it on logs with the truth, into
    the same run."""
    import mlflow

    from helpers import cli
    from lbo.train import train

    done = train(fleet_cfg(fleet / "blind", tmp_path, "loss=next_fix", "data.test=[]"))
    said = capsys.readouterr().out
    assert "no test logs (data.test=[]): cnn-N20 is not scored" in said
    assert not any(k.startswith("test_") for k in done) and np.isfinite(done["val_loss"])
    client = mlflow.MlflowClient(tracking)
    run = client.get_run(done["run_id"])
    assert run.info.status == "FINISHED" and not (tmp_path / "out" / "evaluation.csv").exists()
    res = cli("lbo.evaluate", "data=logs", f"data.test=[{fleet}/truth/test]", "data.run_in=100",
              f"data.root={tmp_path}/data", f"observer={done['run_id']}",
              f"hydra.run.dir={tmp_path}/eval", env={"MLFLOW_TRACKING_URI": tracking})
    assert res.returncode == 0, res.stderr[-3000:]
    scored = client.get_run(done["run_id"]).data.metrics
    assert any(k.startswith("eval_logs_") for k in scored), scored
