import logging

import numpy as np
import pandas as pd
import pytest
import torch

from helpers import cli, one_line_error, store_client, train_cfg
from lbo.core.cli import quiet_lightning
from lbo.core.errors import LboError
from lbo.learn.datamodule import WindowDataModule, rows, window_ends
from lbo.learn.lightning_module import TrainingModule
from lbo.models.net import WindowNet
from lbo.scoring.metrics import SCORE_COLUMNS
from lbo.train import train


def runs(uri):
    client = store_client(uri)
    exp = client.get_experiment_by_name("lbo-smoke")
    return client, client.search_runs([exp.experiment_id]) if exp else []


# --- data -------------------------------------------------------------------------------


def test_windows_are_views_that_never_cross_trajectories(smoke_data):
    dm = WindowDataModule(smoke_data, window=20)
    dm.setup()
    ds = dm.train_set
    assert ds.windows.untyped_storage().data_ptr() == ds.x.untyped_storage().data_ptr()
    train = pd.read_parquet(smoke_data / "train.parquet")
    win, state, weight = ds[list(range(len(ds)))]
    assert torch.all(weight == 1)  # stored measurements: equal loss weights
    ends = ds.ends.numpy()
    traj = train["traj"].to_numpy()
    starts = ends - 19
    assert np.all(traj[starts] == traj[ends])  # first and last row of each window: one trajectory
    np.testing.assert_array_equal(win[:, -1].numpy(), ds.x[ends].numpy())
    np.testing.assert_array_equal(win[:, 0].numpy(), ds.x[starts].numpy())
    np.testing.assert_array_equal(state.numpy(), train[["x", "y", "psi"]].to_numpy()[ends])
    per_traj = train.groupby("traj").size().to_numpy()
    assert len(ds) == int(np.sum(per_traj - 19))


def test_window_memory_stays_under_one_and_a_half_raw_arrays(smoke_data):
    dm = WindowDataModule(smoke_data, window=80)
    dm.setup()
    ds = dm.train_set
    raw = ds.x.nbytes + ds.y.nbytes
    held = {t.untyped_storage().data_ptr(): t.untyped_storage().nbytes()
            for t in (ds.x, ds.y, ds.ends, ds.windows)}
    assert sum(held.values()) < 1.5 * raw


def test_validation_windows_end_on_scored_points(smoke_data):
    dm = WindowDataModule(smoke_data, window=80)
    dm.setup()
    val = pd.read_parquet(smoke_data / "val.parquet")
    assert len(dm.val_set) == int(val["scored"].sum()) == 995
    assert set(window_ends(val["k"].to_numpy(), 80, val["scored"].to_numpy())) == set(
        dm.val_set.ends.numpy())


# --- model behaviour ---------------------------------------------------------------------


def test_relative_observer_ignores_where_the_vehicle_is(smoke_data):
    torch.manual_seed(0)
    net = WindowNet("cnn", 20)
    test = pd.read_parquet(smoke_data / "test.parquet")
    x, y = rows(test[test["alpha"] == 3.0])
    win = x.unfold(0, 20, 1)[:300].transpose(-1, -2)
    state = y[19:319]
    shift = torch.tensor([1234.5, -987.25, 0.0, 0.0, 0.0], dtype=torch.float64)
    with torch.no_grad():
        err = net(win) - state
        err_shifted = net(win + shift) - (state + shift[:3])
    torch.testing.assert_close(err_shifted, err, atol=1e-6, rtol=0)
    absolute = WindowNet("cnn", 20, features="absolute")
    with torch.no_grad():
        moved = absolute(win + shift) - (state + shift[:3]) - (absolute(win) - state)
    assert moved.abs().max() > 1e-3  # the paper-literal observer does care


# --- training ------------------------------------------------------------------------------


def test_fast_dev_run_trains_and_scores(tmp_path, smoke_data, tracking):
    cfg = train_cfg(tmp_path, smoke_data, "trainer.fast_dev_run=true", "model=lstm", "window=40")
    out = train(cfg)
    assert out["name"] == "lstm-N40"
    for a in (1, 3, 6):
        assert np.isfinite(out[f"test_nrmse_alpha_{a}"])
    table = pd.read_csv(tmp_path / "out" / "evaluation.csv")
    assert set(table["observer"]) == {"lstm-N40", "ekf", "oracle"}
    assert np.isfinite(out["worst_oracle_ratio"]) and out["worst_oracle_ratio"] > 0
    client, found = runs(tracking)  # in its data set's experiment, lbo-smoke
    assert [r.info.status for r in found] == ["FINISHED"]
    assert {e.name for e in client.search_experiments()} - {"Default"} == {"lbo-smoke"}
    # its description in the MLflow UI: the result table it printed
    note = found[0].data.tags["mlflow.note.content"]
    assert note.startswith("lstm-N40 on 21 test trajectories:")
    assert "NRMSE on the test grid (lower is better; the EKF at alpha 1 is 1):" in note
    assert f"{out['test_nrmse_alpha_3']:.3f}" in note


def test_same_seed_same_metrics(tmp_path, smoke_data, tracking):
    a = train(train_cfg(tmp_path / "a", smoke_data, "seed=0"))
    b = train(train_cfg(tmp_path / "b", smoke_data, "seed=0"))
    c = train(train_cfg(tmp_path / "c", smoke_data, "seed=1"))
    for key in ("val_loss", "test_nrmse_alpha_1", "test_nrmse_alpha_6"):
        assert a[key] == b[key]
    assert a["val_loss"] != c["val_loss"]


def test_checkpoint_carries_what_rebuilds_the_observer(tmp_path, smoke_data, tracking):
    out = train(train_cfg(tmp_path, smoke_data))
    module = TrainingModule.load_from_checkpoint(out["checkpoint"], map_location="cpu")
    hp = module.hparams
    assert hp["window"] == 20 and hp["features"] == "relative" and hp["model"]["name"] == "cnn"
    assert hp["meta"]["vehicle"]["dt"] == 0.02 and hp["meta"]["noise"]["name"] == "paper"
    assert hp["format"] == 1
    assert torch.all(module.observer.in_std != 1.0)  # the training set's statistics


@pytest.mark.parametrize("override, message", [
    ("window=3", "window must be an integer >= 4"),
    ("window=600", "longer than the shortest training trajectory"),
    ("window=150", "choose window <= 101"),
    ("features=polar", "features must be one of"),
    ("data_dir=/nonexistent/lbo", "data_dir: no train.parquet"),
    ("trainer.max_epochs=0", "trainer.max_epochs must be an integer >= 1, got 0"),
    ("optimizer.lr=-1", r"optimizer.lr must be a number > 0, got -1"),
    ("optimizer.lr=abc", r"optimizer.lr must be a number > 0, got 'abc'"),
    ("optimizer.lr=nan", r"optimizer.lr must be a number > 0, got nan"),
    ("optimizer.weight_decay=-1", r"optimizer.weight_decay must be a number >= 0, got -1"),
    ("batch_size=true", "batch_size must be an integer >= 1, got True"),
    ("trainer.limit_train_batches=0", "trainer.limit_train_batches must be an integer >= 1"),
])
def test_bad_training_input_is_one_clear_line(tmp_path, smoke_data, tracking, override, message):
    with pytest.raises(LboError, match=message) as err:
        train(train_cfg(tmp_path, smoke_data, override))
    assert "\n" not in str(err.value)
    assert runs(tracking)[1] == []  # refused before any MLflow run was opened


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a CPU-only machine")
def test_gpu_trainer_without_cuda_is_refused(tmp_path, smoke_data, tracking):
    with pytest.raises(LboError, match="trainer=gpu needs CUDA"):
        train(train_cfg(tmp_path, smoke_data, "trainer=gpu"))


@pytest.mark.parametrize("override, listed", [("model=gru", "cnn"), ("trainer=tpu", "auto")])
def test_unknown_group_options_are_listed_by_hydra(tmp_path, override, listed):
    res = cli("lbo.train", override, f"hydra.run.dir={tmp_path}")
    assert res.returncode != 0
    assert "Available options" in res.stderr and listed in res.stderr


def test_a_crash_is_marked_failed_and_leaves_no_half_artifact(tmp_path, smoke_data, tracking,
                                                              monkeypatch):
    def boom(self, batch, batch_idx):
        if batch_idx == 3:
            raise RuntimeError("simulated crash")
        return self.observer.loss(*batch)

    monkeypatch.setattr(TrainingModule, "training_step", boom)
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(train_cfg(tmp_path, smoke_data))
    client, found = runs(tracking)
    assert [r.info.status for r in found] == ["FAILED"]
    logged = {a.path for a in client.list_artifacts(found[0].info.run_id)}
    assert logged == {"config.yaml"}
    assert not (tmp_path / "out" / "evaluation.csv").exists()


def test_lightning_speaks_once_and_advertises_nothing():
    from lightning.pytorch.utilities.rank_zero import rank_zero_info

    quiet_lightning()
    quiet_lightning()  # idempotent: one filter, whatever the number of calls
    ranked = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    assert len(ranked.filters) == 1
    assert logging.getLogger("lightning").propagate is False
    seen = []
    handler = logging.Handler()
    handler.emit = seen.append
    ranked.addHandler(handler)
    # what ran before in this process (lbo.tune sets lightning.pytorch to WARNING; a logging
    # config may disable loggers) is not this test's business: the filter is
    level, disabled = ranked.level, ranked.disabled
    ranked.setLevel(logging.INFO)
    ranked.disabled = False
    try:
        rank_zero_info("\N{ELECTRIC LIGHT BULB} Tip: For seamless cloud logging, try installing x")
        rank_zero_info("GPU available: False, used: False")
    finally:
        ranked.removeHandler(handler)
        ranked.setLevel(level)
        ranked.disabled = disabled
    assert [r.getMessage() for r in seen] == ["GPU available: False, used: False"]


@pytest.mark.slow
def test_multirun_sweep_logs_eight_runs(tmp_path, paper_sweep):
    # the paper's command: python -m lbo.train -m model=cnn,lstm window=20,40,60,80 (conftest)
    assert paper_sweep["returncode"] == 0, paper_sweep["stderr"][-3000:]
    client, found = runs(paper_sweep["uri"])
    names = sorted(r.info.run_name for r in found)
    assert names == sorted(f"{m}-N{n}" for m in ("cnn", "lstm") for n in (20, 40, 60, 80))
    # each run ends with its result, not only a run id
    said = paper_sweep["stdout"] + paper_sweep["stderr"]
    assert said.count("NRMSE on the test grid") == 8
    assert said.count("worst ratio to the oracle over alpha 0.25-6: ") == 8
    assert said.count("`Trainer.fit` stopped") == 8  # Lightning's lines once, not twice
    assert "Tip:" not in said  # nor its advertisements
    assert "Trainable params" not in said  # nor its table of the model's layers (verbose=true)
    # and the sweep ends with one table of its eight runs (lbo.core.sweep)
    end = paper_sweep["stdout"].split("the sweep's runs side by side")[-1]
    assert end != paper_sweep["stdout"]
    assert all(f"{m}-N{n} (job " in end for m in ("cnn", "lstm") for n in (20, 40, 60, 80))
    assert "Downloading artifacts" not in said  # nor MLflow's bars after the result
    # the experiment opens in MLflow's model-training view, not its GenAI one
    kind = client.get_experiment(found[0].info.experiment_id).tags["mlflow.experimentKind"]
    assert kind == "custom_model_development"
    # each run says where its runs stand side by side (lbo.tracking.view; tests/test_mlflow_view)
    address = ("beside the other runs on its data, in mlflow ui (make ui): http://127.0.0.1:5000"
               f"/#/experiments/{found[0].info.experiment_id}/runs?viewStateShareKey=lbo")
    assert paper_sweep["stdout"].count(address) == 8
    for r in found:
        assert r.info.status == "FINISHED"
        for key in ("test_nrmse_alpha_1", "test_nrmse_alpha_3", "test_nrmse_alpha_6"):
            assert np.isfinite(r.data.metrics[key])
        assert len(client.get_metric_history(r.info.run_id, "val_loss")) == 2
        assert len(client.get_metric_history(r.info.run_id, "train_loss")) == 2
        assert {"git_commit", "data_hash"} <= set(r.data.tags)
        # the data set as the run's input: MLflow's UI lists it and groups runs by it
        (used,) = client.get_run(r.info.run_id).inputs.dataset_inputs
        assert (used.dataset.name, used.dataset.digest) == ("smoke", r.data.tags["data_hash"])
        assert [(t.key, t.value) for t in used.tags] == [("mlflow.data.context", "training")]
        assert r.data.params["window"] == r.info.run_name.split("-N")[1]
        top = {a.path for a in client.list_artifacts(r.info.run_id)}
        assert {"evaluation.csv", "nrmse.png", "config.yaml", "checkpoints"} <= top
        ckpt = [a.path for a in client.list_artifacts(r.info.run_id, "checkpoints")]
        assert ckpt == ["checkpoints/best.ckpt"]
        local = client.download_artifacts(r.info.run_id, "evaluation.csv", str(tmp_path))
        table = pd.read_csv(local)
        assert list(table.columns) == list(SCORE_COLUMNS)
        assert set(table["observer"]) == {r.info.run_name, "ekf", "oracle"}
    jobs = sorted(p.name for p in paper_sweep["sweep"].iterdir() if p.name.isdigit())
    assert jobs == [str(i) for i in range(8)]


def test_resume_reuses_a_finished_run_and_replaces_a_killed_one(tmp_path, smoke_data, tracking):
    first = train(train_cfg(tmp_path / "a", smoke_data, "resume=true"))
    again = train(train_cfg(tmp_path / "b", smoke_data, "resume=true"))
    assert again["reused"] and again["run_id"] == first["run_id"]
    assert again["test_nrmse_alpha_1"] == first["test_nrmse_alpha_1"]
    other = train(train_cfg(tmp_path / "c", smoke_data, "resume=true", "seed=3"))
    assert not other["reused"] and other["run_id"] != first["run_id"]
    # a run killed mid-way stays RUNNING; the rerun continues it from its last checkpoint
    # (here its final epoch's: nothing left to fit, so it is scored and finished)
    client, _ = runs(tracking)
    client.set_terminated(other["run_id"], "RUNNING")
    rerun = train(train_cfg(tmp_path / "d", smoke_data, "resume=true", "seed=3"))
    assert not rerun["reused"] and rerun["run_id"] == other["run_id"]
    assert rerun["test_nrmse_alpha_1"] == other["test_nrmse_alpha_1"]
    _, found = runs(tracking)
    assert sorted(r.info.status for r in found) == ["FINISHED", "FINISHED"]
    # without its last checkpoint, a killed run is deleted and trained once more
    client.set_terminated(other["run_id"], "RUNNING")
    (tmp_path / "c" / "out" / "checkpoints" / "last.ckpt").unlink()
    again = train(train_cfg(tmp_path / "e", smoke_data, "resume=true", "seed=3"))
    assert not again["reused"] and again["run_id"] != other["run_id"]
    _, found = runs(tracking)
    assert sorted(r.info.status for r in found) == ["FINISHED", "FINISHED"]


@pytest.mark.parametrize("trainer", ["cpu", "auto"])
def test_batches_are_drawn_on_the_device_the_observer_trains_on(trainer, tmp_path, smoke_data,
                                                                 tracking, monkeypatch):
    """In a real training step, every batch the data module yields is already on the device of
    the observer's parameters before Lightning would copy it there: the CPU for trainer=cpu
    (also where CUDA is present) and for trainer=auto without CUDA, the GPU for trainer=auto
    with it (trainer=gpu: test_training_on_cuda_draws_batches_on_the_gpu)."""
    import lightning as L

    drawn, held = [], []

    def on_before_batch_transfer(self, batch, dataloader_idx):  # as the data module yields it
        drawn.append({t.device.type for t in batch})
        return batch

    monkeypatch.setattr(WindowDataModule, "on_before_batch_transfer", on_before_batch_transfer,
                        raising=False)

    class Where(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            held.append({p.device.type for p in pl_module.parameters()})

    out = train(train_cfg(tmp_path, smoke_data, f"trainer={trainer}", "trainer.max_epochs=1",
                          "trainer.limit_train_batches=2"), callbacks=[Where()])
    assert np.isfinite(out["val_loss"])  # the steps ran on those batches
    expected = "cuda" if trainer == "auto" and torch.cuda.is_available() else "cpu"
    assert len(held) == 2 and all(h == {expected} for h in held)
    assert len(drawn) > 2  # two training batches and the validation ones
    assert all(d == {expected} for d in drawn), drawn


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="needs CUDA, which this machine lacks: run it where a GPU is present")
def test_training_on_cuda_draws_batches_on_the_gpu(tmp_path, smoke_data, tracking):
    from lbo.learn.draws import AlphaDraw

    dm = WindowDataModule(smoke_data, 20, 64, draw=AlphaDraw(), sigma=(0.25, 0.25, 0.004),
                          device="cuda")
    dm.setup("fit")
    win, state, weight = next(iter(dm.train_dataloader()))
    assert {t.device.type for t in (win, state, weight)} == {"cuda"}
    out = train(train_cfg(tmp_path, smoke_data, "trainer=gpu", "trainer.max_epochs=1",
                          "trainer.limit_train_batches=5"))
    assert np.isfinite(out["test_nrmse_alpha_1"])


def test_an_experiment_made_before_lbo_set_its_kind_gets_it(tmp_path):

    from lbo.tracking.runs import ensure_experiment

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    old = store_client(uri).create_experiment("older", artifact_location=str(tmp_path / "a"))
    client, found = ensure_experiment(uri, "older", None)
    assert found == old
    assert client.get_experiment(old).tags["mlflow.experimentKind"] == "custom_model_development"


def test_threads_sets_the_runs_intra_op_threads_and_leaves_its_hash(tmp_path, smoke_data,
                                                                   monkeypatch):
    import lbo.train as command
    from lbo.learn.identity import config_hash

    with pytest.raises(LboError, match=r"^threads must be an integer >= 1, got 0$"):
        train(train_cfg(tmp_path, smoke_data, "threads=0"))
    cfg = train_cfg(tmp_path, smoke_data, "threads=1")
    assert config_hash(cfg) == config_hash(train_cfg(tmp_path, smoke_data))
    before = torch.get_num_threads()
    seen = []
    monkeypatch.setattr(command, "_train", lambda *a: seen.append(torch.get_num_threads()) or {})
    try:
        torch.set_num_threads(2)  # what the run changes, whatever the test worker had
        train(cfg)
    finally:
        torch.set_num_threads(before)
    assert seen == [1]


@pytest.mark.slow
def test_verbose_brings_back_the_model_summary_and_is_a_flag(tmp_path, smoke_data):
    args = ("experiment=smoke", f"data.root={smoke_data.parent}", "trainer.max_epochs=1",
            "trainer.limit_train_batches=3", "keep_onnx=false", f"output_dir={tmp_path / 'out'}",
            f"hydra.run.dir={tmp_path}")
    env = {"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}
    # Lightning's own handler writes to the stream it started with, not the one captured
    # here: what it logs is read from its logger
    said: list[str] = []
    heard = logging.Handler()
    heard.emit = lambda record: said.append(record.getMessage())  # type: ignore[method-assign]
    logger = logging.getLogger("lightning.pytorch")
    logger.addHandler(heard)
    try:
        res = cli("lbo.train", *args, "verbose=true", env=env)
    finally:
        logger.removeHandler(heard)
    assert res.returncode == 0, res.stderr[-3000:]
    assert any("Trainable params" in line for line in said), said
    one_line_error(cli("lbo.train", *args, "verbose=yes", env=env),
                   "verbose must be true or false")
