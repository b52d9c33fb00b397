"""The learned side-slip filter (lbo.models.slip_filter): the linear single-track Kalman filter
whose tyres and noise small networks learn (lbo.train model=slip_filter data=sideslip)."""

import mlflow
import numpy as np
import pytest
import torch

from helpers import cli, one_line_error
from lbo.core.errors import LboError
from lbo.learn import slip_data
from lbo.models import slip, slip_filter
from lbo.sim import sideslip

GAIN = 1000.0


@pytest.fixture(scope="module")
def slice_and_prior():
    """300 rows of the validation span (a corner included), and the prior of the train span."""
    spans = slip_data.real_spans()
    prior = slip.Prior(sideslip.CAR, slip_data.noise_of([spans["train"]], GAIN), sideslip.DT)
    return spans["val"].iloc[2000:2300].reset_index(drop=True), prior


def trained_like(prior, seed=0):
    """A filter whose networks' last layers are not zero: it corrects the tyres and the noise."""
    torch.manual_seed(seed)
    net = slip_filter.LateralFilter(prior, hidden=8)
    with torch.no_grad():
        for layer in (net.tyres[-1], net.noise[-1]):
            layer.weight.normal_(0.0, 0.3)
    return net


def test_untrained_it_is_the_linear_filter_it_corrects(slice_and_prior):
    """Both networks start at zero: the same x and P as lbo.filters.lateral's linear filter,
    the JAcobians by differences and the masked update included."""
    part, prior = slice_and_prior
    vx, delta, y = sideslip.observed(part)
    y = y.copy()
    y[100:110, 0] = np.nan  # a channel not held: the update without it
    est = slip_filter.FilterObserver(slip_filter.LateralFilter(prior)).run(vx, delta, y)
    ref = prior.run(vx, delta, y)
    assert np.allclose(est.x, ref.x, rtol=0, atol=1e-9)
    assert np.allclose(est.P, ref.P, rtol=1e-7, atol=1e-14)


def test_a_stream_of_rows_gives_what_the_whole_log_gives(slice_and_prior):
    """Row by row, in PyTorch and as the ONNX step in ONNX Runtime (the first row's start
    included): the whole log's estimates, to 1e-12 (measured 1.9e-14 and 2.3e-14). With ten
    rows whose yaw rate is not held, to 1e-9: the whole log's noise network runs on every row
    at once, a row's alone differs in the last bit, and an unheld channel's growing variance
    carries that further (measured 1.0e-10 and 1.3e-10)."""
    from lbo.serve import lateral as serve

    part, prior = slice_and_prior
    observer = slip_filter.FilterObserver(trained_like(prior))
    vx, delta, y = sideslip.observed(part)
    gap = y.copy()
    gap[50:60, 1] = np.nan
    for ys, atol in ((y, 1e-12), (gap, 1e-9)):
        whole = observer.run(vx, delta, ys)
        assert not np.allclose(whole.x, prior.run(vx, delta, ys).x, atol=1e-4)  # it corrects
        assert np.isfinite(whole.P).all() and (np.linalg.eigvalsh(whole.P) > 0).all()
        for engine in ("torch", "onnx"):
            stream = serve.stream(observer, engine)
            rows = np.array([stream.step(*r) for r in zip(vx, delta, ys[:, 0], ys[:, 1])])
            assert np.allclose(rows, whole.x, rtol=0, atol=atol), (engine, atol)


def test_the_filter_reads_no_truth_and_learns_through_both_networks(slice_and_prior):
    """A planted check: the training sequences' inputs are what the car measures, the INS's
    beta only their target; the loss's gradient reaches the tyres and the noise."""
    part, prior = slice_and_prior
    cols = slip_data.columns(part)
    vx, delta, y = sideslip.observed(part)
    assert np.array_equal(cols[:, :4], np.column_stack([vx, delta, y]))
    assert np.array_equal(cols[:, 4], part["beta"].to_numpy())
    planted = part.assign(beta=np.random.default_rng(0).normal(size=len(part)),
                          vy=np.random.default_rng(1).normal(size=len(part)))
    net = trained_like(prior)
    rows = torch.from_numpy(cols)[None]
    x, _ = net(rows[..., 0], rows[..., 1], rows[..., 2:4])
    x_planted, _ = net(*(torch.from_numpy(np.array(a))[None]
                         for a in sideslip.observed(planted)))
    assert torch.equal(x, x_planted)
    loss = torch.mean((x[0, 20:, 0] - rows[0, 20:, 4]) ** 2)
    loss.backward()
    for layer in (net.tyres[0], net.noise[0]):
        assert layer.weight.grad is not None and layer.weight.grad.abs().sum() > 0


def test_load_and_stream_refuse_what_they_cannot_take(tmp_path, slice_and_prior):
    other = tmp_path / "other.ckpt"
    torch.save({"hyper_parameters": {"name": "slip_gru"}, "state_dict": {}}, other)
    with pytest.raises(LboError, match=r"not a slip_filter checkpoint"):
        slip_filter.load(other)
    from lbo.serve import lateral as serve

    observer = slip_filter.FilterObserver(slip_filter.LateralFilter(slice_and_prior[1]))
    with pytest.raises(LboError, match=r"^engine: expected one of \['torch', 'onnx'\], got "
                                       r"'tensorrt'$"):
        serve.stream(observer, "tensorrt")


@pytest.mark.parametrize(("args", "words"), [
    (["model.warmup=200"], ["model.warmup: expected fewer rows than model.sequence (200)"]),
    (["model.sequence=1"], ["model.sequence", "an integer >= 2"]),
    (["+model.layers=2"], ["model.layers: not a parameter of model 'slip_filter'",
                           "hidden, prior_gain, sequence, warmup"]),
    (["data=dynamic"], ["data: model=slip_filter learns on the side-slip run"]),
    (["tbptt=10"], ["tbptt: expected None with model=slip_filter", "model.sequence"]),
    (["nll=-1"], ["nll must be a number >= 0, got -1"]),
])
def test_bad_settings_are_refused_in_one_line(args, words, tmp_path):
    res = cli("lbo.train", "model=slip_filter", "data=sideslip", *args,
              f"hydra.run.dir={tmp_path / 'run'}", f"logger.tracking_uri=sqlite:///{tmp_path}/m.db")
    one_line_error(res, *words)


def test_its_loss_adds_the_nll_of_beta_under_its_own_variance(slice_and_prior):
    """With nll > 0 the loss is the squared error plus nll times the Gaussian NLL of beta's
    error under the filter's variance of it (both in degrees), so the noise network learns
    to say how far off beta is; slip_gru refuses nll (it gives no covariance)."""
    from lbo.learn.slip_models import _filter_module

    part, prior = slice_and_prior
    rows = torch.from_numpy(slip_data.columns(part))[None]
    net = trained_like(prior)
    batch = [rows, rows[..., 4]]
    plain = _filter_module(net, 20, 0.0, torch.optim.Adam).training_step(batch, 0)
    weighed = _filter_module(net, 20, 0.3, torch.optim.Adam).training_step(batch, 0)
    x, P = net(rows[..., 0], rows[..., 1], rows[..., 2:4])
    err = (x[0, 20:, 0] - rows[0, 20:, 4]) / slip.UNIT
    var = P[0, 20:, 0, 0] / slip.UNIT**2
    assert plain.item() == pytest.approx(torch.mean(err**2).item(), rel=1e-12)
    nll = torch.mean(0.5 * (torch.log(var) + err**2 / var))
    assert weighed.item() == pytest.approx((torch.mean(err**2) + 0.3 * nll).item(), rel=1e-12)


SMOKE = ["model=slip_filter", "data=sideslip_sim", "data.train=2", "data.val=1",
         "data.duration=4", "model.sequence=100", "model.warmup=20", "model.hidden=4",
         "batch_size=8", "trainer.max_epochs=2", "nll=0.3", "callbacks.progress_bar.refresh_rate=0"]


@pytest.mark.slow
def test_train_fits_it_on_sequences_logs_a_run_and_refuses_another_kinds_start(
        tmp_path, tracking):
    # the evaluation callback off: the real spans, 55,000 rows of filtering, are not scored
    res = cli("lbo.train", *SMOKE, "~callbacks.evaluation", f"logger.tracking_uri={tracking}",
              f"hydra.run.dir={tmp_path / 'a'}")
    assert res.returncode == 0, res.stderr[-3000:]
    client = mlflow.MlflowClient(tracking)
    (run,) = client.search_runs(client.get_experiment_by_name("lbo-sideslip_sim").experiment_id)
    assert run.info.status == "FINISHED" and run.data.tags["model"] == "slip_filter"
    assert len(client.get_metric_history(run.info.run_id, "val_loss")) == 2
    ckpt = tmp_path / "a" / "checkpoints" / "best.ckpt"
    observer = slip_filter.load(ckpt)
    assert observer.net.hidden == 4
    from lbo.serve import lateral as serve

    by_run = serve.load(run.info.run_id)  # the run's logged checkpoint: the same filter
    assert isinstance(by_run, slip_filter.FilterObserver)
    assert all(torch.equal(a, b) for a, b in zip(by_run.net.state_dict().values(),
                                                 observer.net.state_dict().values()))
    moved = [not torch.equal(p, torch.zeros_like(p))
             for p in (observer.net.tyres[-1].weight, observer.net.noise[-1].weight)]
    assert all(moved)  # both networks learned from their zero start
    other = cli("lbo.train", "model=slip_gru", "data=sideslip", f"init_from={ckpt}",
                f"hydra.run.dir={tmp_path / 'b'}", f"logger.tracking_uri={tracking}")
    one_line_error(other, f"init_from: {ckpt} is model=slip_filter with hidden 4; expected "
                   "model=slip_gru with window 50")
