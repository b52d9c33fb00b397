"""The learned side-slip observer (lbo.models.slip) and its training on the real run
(lbo.train model=slip_gru data=sideslip)."""

import mlflow
import numpy as np
import pytest
import torch

from helpers import cli, one_line_error
from lbo.core.errors import LboError
from lbo.filters.lateral import LateralEstimate, linear_single_track
from lbo.learn import slip_data
from lbo.models import slip
from lbo.sim import lateral, sideslip

GAIN = 1000.0


@pytest.fixture(scope="module")
def shipped():
    """The real run's spans, the prior the training reads off its train span, its estimates."""
    spans = slip_data.real_spans()
    prior = slip.Prior(sideslip.CAR, slip_data.noise_of([spans["train"]], GAIN), sideslip.DT)
    return spans, prior, slip_data.real_estimates(prior)


@pytest.fixture(scope="module")
def observer(shipped):
    """An untrained observer (seeded weights), standardised by the training span's rows."""
    spans, prior, priors = shipped
    torch.manual_seed(0)
    net = slip.SlipNet(hidden=8)
    net.set_normalisation(slip.features(*sideslip.observed(spans["train"]), priors["train"].x))
    return slip.SlipObserver(net, 12, prior)


def test_windows_end_at_their_row_and_start_with_copies_of_the_first():
    rows = np.arange(15, dtype=np.float32).reshape(5, 3)
    w = slip.windows(rows, 3)
    assert w.shape == (5, 3, 3)
    assert np.array_equal(w[4], rows[2:5]) and np.array_equal(w[2], rows[0:3])
    assert np.array_equal(w[0], np.repeat(rows[:1], 3, axis=0))
    assert np.array_equal(w[1], rows[[0, 0, 1]])


def test_the_linear_filter_carried_on_from_a_start_is_the_same_filter(shipped):
    vx, delta, y = sideslip.observed(shipped[0]["val"].iloc[:200])
    whole = linear_single_track(vx, delta, y, sideslip.CAR, shipped[1].noise, sideslip.DT)
    first = linear_single_track(vx[:100], delta[:100], y[:100], sideslip.CAR, shipped[1].noise,
                                sideslip.DT)
    rest = linear_single_track(vx[99:], delta[99:], y[99:], sideslip.CAR, shipped[1].noise,
                               sideslip.DT, start=LateralEstimate(first.x[-1], first.P[-1]))
    assert np.allclose(rest.x, whole.x[99:], rtol=0, atol=1e-12)
    assert np.allclose(rest.P, whole.P[99:], rtol=1e-10, atol=0)


def test_the_observer_reads_no_truth_a_planted_check(shipped):
    """The windows and the estimate are the same when the INS's vy and beta are replaced by
    noise: only the training target reads them."""
    spans, _, priors = shipped
    span = spans["val"].iloc[:300].copy()
    planted = span.copy()
    rng = np.random.default_rng(0)
    planted["vy"], planted["beta"] = rng.normal(size=(2, len(span)))
    est = LateralEstimate(priors["val"].x[:300], priors["val"].P[:300])
    w, target = slip_data._windows([span], est, 12, 1)
    w2, target2 = slip_data._windows([planted], est, 12, 1)
    assert np.array_equal(w, w2) and not np.allclose(target, target2)
    assert not set(sideslip.TRUTH) & set(slip.FEATURES)


def test_a_stream_of_rows_gives_what_the_whole_log_gives(shipped, observer):
    span = shipped[0]["test"].iloc[:80]
    vx, delta, y = sideslip.observed(span)
    whole = observer.run(vx, delta, y)
    assert whole.x.shape == (80, 2) and np.isnan(whole.P).all()  # no covariance: none claimed
    stream = observer.stream()
    rows = np.array([stream.step(*row) for row in zip(vx, delta, y[:, 0], y[:, 1])])
    assert rows.shape == (80, 2)
    assert np.allclose(rows, whole.x, rtol=0, atol=1e-6)
    assert np.array_equal(whole.x[:, 1], observer.prior.run(vx, delta, y).r)  # the prior's r


def test_the_onnx_network_and_stream_give_pytorchs_numbers(shipped, observer):
    from lbo.serve import lateral as serve
    from lbo.serve.engines import onnx_session

    session = onnx_session(serve.onnx_bytes(observer), threads=1)
    for batch in (1, 7):
        w = np.random.default_rng(batch).normal(size=(batch, 12, 6)).astype(np.float32)
        with torch.no_grad():
            expected = observer.net(torch.from_numpy(w)).numpy()
        assert np.allclose(session.run(None, {"window": w})[0], expected, rtol=0, atol=1e-7)
    vx, delta, y = sideslip.observed(shipped[0]["test"].iloc[:30])
    rows = list(zip(vx, delta, y[:, 0], y[:, 1]))
    torch_stream, onnx_stream = serve.stream(observer), serve.stream(observer, "onnx")
    a = np.array([torch_stream.step(*r) for r in rows])
    b = np.array([onnx_stream.step(*r) for r in rows])
    assert np.allclose(a, b, rtol=0, atol=1e-7)
    with pytest.raises(LboError, match=r"engine: expected one of \['torch', 'onnx'\]"):
        serve.stream(observer, "tensorrt")


def test_load_refuses_what_is_not_its_checkpoint(tmp_path):
    other = tmp_path / "other.ckpt"
    torch.save({"hyper_parameters": {"name": "cnn"}, "state_dict": {}}, other)
    with pytest.raises(LboError, match=r"not a slip_gru checkpoint"):
        slip.load(other)
    (tmp_path / "junk.ckpt").write_text("not a checkpoint")
    with pytest.raises(LboError, match=r"not a checkpoint lbo can read"):
        slip.load(tmp_path / "junk.ckpt")
    with pytest.raises(LboError, match=r"no such file"):
        slip.load(tmp_path / "none.ckpt")


@pytest.mark.parametrize(("args", "words"), [
    (["data=paper"], ["data: model=slip_gru learns on the side-slip run", "data=paper"]),
    (["data=sideslip_sim", "data.spread=0.9"], ["data.spread", "a share in [0, 0.5]"]),
    (["init_from=nowhere.ckpt"], ["init_from: expected the path of a model=slip_gru checkpoint"]),
    (["model.window=1"], ["model.window", "an integer >= 2"]),
    (["+model.body=single_track"], ["model.body: not a parameter of model 'slip_gru'"]),
    (["fix_rates=[10]"], ["fix_rates: expected None", "reads no position fixes"]),
    (["lr_schedule=cosine"], ["lr_schedule: expected constant"]),
])
def test_bad_settings_are_refused_in_one_line(args, words, tmp_path):
    res = cli("lbo.train", "model=slip_gru", "data=sideslip", *args,
              f"hydra.run.dir={tmp_path / 'run'}", f"logger.tracking_uri=sqlite:///{tmp_path}/m.db")
    one_line_error(res, *words)


def test_pose_observers_refuse_the_side_slip_run(tmp_path):
    res = cli("lbo.train", "model=cnn", "data=sideslip", f"hydra.run.dir={tmp_path / 'run'}")
    one_line_error(res, "data: data=sideslip is the real side-slip run", "model=slip_gru")


def test_simulated_runs_are_cars_at_the_limit_like_the_real_one():
    runs = lateral.simulate(lateral.Settings(n=6, duration=20.0), seed=3)
    again = lateral.simulate(lateral.Settings(n=6, duration=20.0), seed=3)
    assert all(a.equals(b) for a, b in zip(runs, again))  # the seed decides
    assert [len(r) for r in runs] == [2000] * 6
    assert list(runs[0].columns) == ["t", "vx", "delta", "ay_m", "r_m", "vy", "beta"]
    cars = [r.attrs["car"] for r in runs]
    assert len({c["mass"] for c in cars}) == 6  # each car its own
    for r in runs:
        assert np.allclose(r["beta"], np.arctan2(r["vy"], r["vx"]))
        assert 15.9 < r["vx"].min() and r["vx"].max() < 61.1
        # the tyres' limit is reached, and no car spins: beta stays within a road car's
        assert np.abs(r["beta"]).max() < np.deg2rad(15)
    assert max(np.abs(r["ay_m"]).max() for r in runs) > 0.8 * 9.81
    with pytest.raises(LboError, match=r"data\.mu must be \[low, high\]"):
        lateral.Settings(mu=(1.4, 0.9))


SMOKE = ["model=slip_gru", "data=sideslip", "model.window=12", "model.hidden=8",
         "trainer.max_epochs=2", "+trainer.limit_train_batches=3", "+trainer.limit_val_batches=4",
         "callbacks.progress_bar.refresh_rate=0"]


@pytest.mark.slow
def test_train_learns_on_the_train_span_logs_a_run_and_a_rerun_reuses_it(tmp_path, tracking):
    args = [*SMOKE, f"logger.tracking_uri={tracking}", "resume=true"]
    res = cli("lbo.train", *args, f"hydra.run.dir={tmp_path / 'a'}")
    assert res.returncode == 0, res.stderr[-3000:]
    assert "| test | slip_gru |" in res.stdout and "| test | linear single-track KF |" in res.stdout
    client = mlflow.MlflowClient(tracking)
    (run,) = client.search_runs(client.get_experiment_by_name("lbo-sideslip").experiment_id)
    assert run.info.status == "FINISHED" and run.data.tags["model"] == "slip_gru"
    m = run.data.metrics
    assert m["test_linear_beta_rmse_deg"] == pytest.approx(0.964, abs=0.001)  # the docs' KF
    assert m["test_vs_linear"] == pytest.approx(m["test_beta_rmse_deg"] / 0.964, rel=2e-3)
    assert len(client.get_metric_history(run.info.run_id, "val_loss")) == 2
    files = {f.path for f in client.list_artifacts(run.info.run_id, "checkpoints")}
    assert files == {"checkpoints/best.ckpt"}
    observer = slip.load(tmp_path / "a" / "checkpoints" / "best.ckpt")
    assert (observer.window, observer.net.gru.hidden_size) == (12, 8)
    from lbo.serve import lateral as serve

    by_run = serve.load(run.info.run_id)  # the run's logged checkpoint: the same observer
    assert all(torch.equal(a, b) for a, b in zip(by_run.net.state_dict().values(),
                                                 observer.net.state_dict().values()))
    assert observer.prior.noise == slip_data.noise_of([slip_data.real_spans()["train"]], GAIN)

    # fine-tuned from it on the real run: its prior and normalisation kept, its weights moved
    tuned = cli("lbo.train", *SMOKE, "trainer.max_epochs=1", f"logger.tracking_uri={tracking}",
                f"init_from={tmp_path / 'a' / 'checkpoints' / 'best.ckpt'}",
                f"hydra.run.dir={tmp_path / 'c'}")
    assert tuned.returncode == 0, tuned.stderr[-3000:]
    assert "init_from: starting from the weights of" in tuned.stdout
    fine = slip.load(tmp_path / "c" / "checkpoints" / "best.ckpt")
    assert fine.prior == observer.prior
    assert torch.equal(fine.net.mean, observer.net.mean)
    assert not torch.equal(fine.net.head.weight, observer.net.head.weight)

    again = cli("lbo.train", *args, f"hydra.run.dir={tmp_path / 'a'}")  # its own folder
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"reusing finished run {run.info.run_id}" in again.stdout
    other = cli("lbo.train", *args, "model.hidden=4", f"hydra.run.dir={tmp_path / 'a'}")
    one_line_error(other, f"already holds the files of the finished run {run.info.run_id}")


@pytest.mark.slow
def test_train_on_simulation_reads_nothing_of_the_real_run_but_to_score_it(tmp_path, tracking):
    res = cli("lbo.train", *SMOKE, "data=sideslip_sim", "data.train=3", "data.val=1",
              "data.duration=20", f"logger.tracking_uri={tracking}",
              f"hydra.run.dir={tmp_path / 'sim'}")
    assert res.returncode == 0, res.stderr[-3000:]
    assert "on 3 simulated runs (1500 windows of 12 rows)" in res.stdout
    observer = slip.load(tmp_path / "sim" / "checkpoints" / "best.ckpt")
    settings = lateral.Settings(n=4, duration=20.0)
    sim_train = lateral.simulate(settings, seed=0)[:3]
    assert observer.prior.noise == slip_data.noise_of(sim_train, GAIN)  # not the real run's
    client = mlflow.MlflowClient(tracking)
    (run,) = client.search_runs(client.get_experiment_by_name("lbo-sideslip_sim").experiment_id)
    assert run.data.tags["data"] == "sideslip_sim"
    assert {"test_beta_rmse_deg", "test_vs_linear"} <= set(run.data.metrics)


@pytest.mark.slow
def test_tune_studies_the_side_slip_observer_on_the_validation_span(tmp_path, tracking):
    handoff = tmp_path / "tuned" / "slip_gru.yaml"
    res = cli("lbo.tune", "hparams_search=slip_gru", *SMOKE[2:4], "trainer.max_epochs=1",
              *SMOKE[5:],
              "tune.n_trials=1", f"tune.storage=sqlite:///{tmp_path / 'optuna.db'}",
              f"tune.handoff={handoff}", f"logger.tracking_uri={tracking}",
              f"hydra.run.dir={tmp_path / 'run'}")
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.splitlines()[1].startswith("trial   0  val_loss")
    assert handoff.exists()
    client = mlflow.MlflowClient(tracking)
    runs = client.search_runs(client.get_experiment_by_name("lbo-sideslip").experiment_id,
                              "tags.optuna_trial = '0'")
    (trial,) = runs
    assert trial.data.tags["model"] == "slip_gru" and trial.info.status == "FINISHED"
    assert "val_beta_rmse_deg" in trial.data.metrics
    assert not any(k.startswith("test_") for k in trial.data.metrics)  # never the test span
