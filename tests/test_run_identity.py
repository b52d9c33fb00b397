"""A run's identity (``config_hash``) does not depend on where lbo's modules live, so that
``resume=true`` and ``make reproduce`` find the runs of a store made before the modules moved
into layers, instead of training everything again."""

from pathlib import Path

import mlflow
import pytest
from conftest import compose_cfg
from hydra import compose, initialize_config_dir
from omegaconf import open_dict

from lbo.core.paths import CONF_DIR, REPO_ROOT
from lbo.learn.resume import EXPERIMENT_BEFORE, _unlayered, config_hash, finished_run

PRE_MOVE = {
    (): "e018b36dfba2bd07",
    ("experiment=robust",): "3967c9a49a629476",
    ("experiment=dynamic",): "d4eec27d40f3f414",
    ("experiment=dynamic_blackbox", "model=lstm"): "c01f2dc39014800d",
}
"""The hashes these configs had before the move (lbo.callbacks.Evaluation was then the
evaluation callback's path), as the runs of an existing store carry them in their
``config_hash`` tag. A change here means every such run would be trained again."""


@pytest.fixture(scope="module")
def old_store(tmp_path_factory):
    """An MLflow store with one FINISHED run per config above, tagged as before the move, in
    the one experiment every run went to then (each data set has its own since)."""
    uri = f"sqlite:///{tmp_path_factory.mktemp('store')}/mlflow.db"
    name = EXPERIMENT_BEFORE
    client = mlflow.MlflowClient(uri)
    exp = client.create_experiment(name)
    ids = {}
    for overrides, digest in PRE_MOVE.items():
        run = client.create_run(exp, tags={"config_hash": digest}, run_name="-".join(overrides))
        client.log_metric(run.info.run_id, "val_loss", 0.5, step=0)
        client.set_terminated(run.info.run_id, "FINISHED")
        ids[overrides] = run.info.run_id
    return uri, ids


@pytest.mark.parametrize("overrides", list(PRE_MOVE), ids=lambda o: " ".join(o) or "default")
def test_resume_finds_the_run_of_a_store_made_before_the_move(overrides, old_store):
    uri, ids = old_store
    cfg = compose_cfg("train", [*overrides, f"logger.tracking_uri={uri}"])
    assert config_hash(cfg) == PRE_MOVE[overrides]
    found = finished_run(cfg, config_hash(cfg), clean=False)
    assert found is not None and found["run_id"] == ids[overrides] and found["reused"]


def test_a_target_hashes_the_same_whichever_layer_its_module_is_in():
    cfg = compose_cfg("train")
    assert cfg.callbacks.evaluation._target_ == "lbo.learn.callbacks.Evaluation"
    before = config_hash(cfg)
    with open_dict(cfg):
        cfg.callbacks.evaluation._target_ = "lbo.callbacks.Evaluation"  # the path before
    assert config_hash(cfg) == before
    with open_dict(cfg):
        cfg.callbacks.evaluation._target_ = "lbo.learn.callbacks.Other"  # another class
    assert config_hash(cfg) != before


def test_only_lbo_targets_in_a_layer_lose_the_layer():
    tree = {"a": {"_target_": "lbo.learn.callbacks.Evaluation", "k": [1, {"_target_":
                                                                         "lbo.core.x.Y"}]},
            "b": {"_target_": "lightning.pytorch.callbacks.EarlyStopping"},
            "c": {"_target_": "lbo.train.Thing"}, "d": "lbo.learn.callbacks.Evaluation"}
    assert _unlayered(tree) == {
        "a": {"_target_": "lbo.callbacks.Evaluation", "k": [1, {"_target_": "lbo.x.Y"}]},
        "b": {"_target_": "lightning.pytorch.callbacks.EarlyStopping"},
        "c": {"_target_": "lbo.train.Thing"}, "d": "lbo.learn.callbacks.Evaluation"}


def test_a_setting_added_later_hashes_as_before_at_its_old_value_only():
    """``model.gyro`` came after these runs: false (their value) leaves the hash they carry,
    true makes another run."""
    plain = compose_cfg("train", ["experiment=robust"])
    gyro = compose_cfg("train", ["experiment=robust", "model.gyro=true"])
    assert plain.model.gyro is False
    assert config_hash(plain) == PRE_MOVE[("experiment=robust",)] != config_hash(gyro)


@pytest.mark.parametrize("setting", ["nll=0.1", "train_noise.changes=2", "tbptt=100"])
def test_the_sequence_trainers_settings_leave_old_runs_hashes_at_their_defaults(setting):
    """``tbptt``, ``nll`` and ``train_noise.changes`` came after these runs: at their
    defaults the hash is the one the runs carry; set, another run."""
    plain = compose_cfg("train", ["experiment=dynamic"])
    assert plain.nll == 0.0 and plain.train_noise.changes == 0 and plain.tbptt is None
    assert config_hash(plain) == PRE_MOVE[("experiment=dynamic",)]
    assert config_hash(compose_cfg("train", ["experiment=dynamic", setting])) != \
        config_hash(plain)


PRE_SPLIT = {
    ("experiment=dynamic", "data=dynamic_drift"): ("4a7fe7b6352bad5c", "f6b39670d94a"),
    ("experiment=dynamic_carried", "data=dynamic_drift"): ("9f22da9d9da64c1c", "f6b39670d94a"),
    ("data=dynamic",): ("adb25d1b2027d6f7", "e47207bbd8a4"),
    ("experiment=robust", "sensors.steering_offset=0.01"): ("dd32348cea6058e3", "ae120a23946c"),
}
"""Config hashes and data-set digests from before the ``truth`` group was split into ``car``
and ``sensors`` (the last override was then ``truth.steering_offset=0.01``)."""


@pytest.mark.parametrize("overrides", list(PRE_SPLIT), ids=" ".join)
def test_the_car_apart_from_its_sensors_leaves_runs_and_data_sets_as_they_were(overrides):
    from lbo.sim.datasets import spec_from_cfg

    cfg = compose_cfg("train", list(overrides))
    assert (config_hash(cfg), spec_from_cfg(cfg).digest) == PRE_SPLIT[overrides]


PRE_MODEL_KEYS = {
    ("model=lstm", "window=60"): "3961f067d85918ee",
    ("experiment=quick_literal", "model=cnn", "window=60"): "f57995013e1b0c39",
    ("experiment=paper_literal", "model=lstm", "window=80", "normalisation=standard"):
        "f2fe7c53ed4985e6",
    ("features=absolute", "window=40", "seed=3"): "96c94486ff3d65a2",
}
"""Config hashes from before ``window``, ``features`` and ``normalisation`` moved under
``model``, with the overrides as they were then spelled."""


@pytest.mark.parametrize("overrides", list(PRE_MODEL_KEYS), ids=" ".join)
def test_the_model_keys_under_model_leave_runs_as_they_were_in_either_spelling(overrides):
    from lbo.core.cli import respell

    long = respell(list(overrides))
    assert [o for o in long if o.split("=")[0] in ("window", "features", "normalisation")] == []
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        plain = compose(config_name="train", overrides=long)  # Hydra itself: no respelling
    assert plain.model.window == int(next(o for o in long if "window=" in o).split("=")[1])
    assert config_hash(plain) == config_hash(compose_cfg("train", list(overrides))) \
        == PRE_MODEL_KEYS[overrides]


BEFORE = Path(__file__).parent / "data" / "before_issue39"
"""A run trained by lbo at 41d4f39, before the modules were split into one idea each: the
smoke robust observer (``BEFORE_OVERRIDES``) and what ``lbo.observe`` made of the example
log's first 600 rows with it then."""
BEFORE_OVERRIDES = ["experiment=robust", "data=smoke", "window=40", "batch_size=64",
                    "trainer.max_epochs=1", "trainer.limit_train_batches=5"]


def test_a_run_trained_before_the_rooms_were_split_resumes_and_observes_as_it_did(tmp_path):
    """Its config hash (the ``config_hash`` tag its MLflow run carries) is the one today's
    code gives, so ``resume=true`` finds it; its checkpoint observes the log as it did then."""
    import pandas as pd

    from helpers import observe

    assert config_hash(compose_cfg("train", BEFORE_OVERRIDES)) == "1a3dac0ffb1381b6"
    log = tmp_path / "log.csv"
    log.write_text("".join((REPO_ROOT / "examples" / "stop_and_go_10hz.csv").read_text()
                           .splitlines(keepends=True)[:601]))
    observe(f"observer={BEFORE / 'robust-N40.ckpt'}", f"input={log}",
            f"output={tmp_path / 'now.csv'}", f"hydra.run.dir={tmp_path / 'h'}", check=True)
    then, now = pd.read_csv(BEFORE / "estimates.csv.gz"), pd.read_csv(tmp_path / "now.csv")
    # to the rounding of the CPU's float32 kernels, not to the bit: the reference was written
    # on a CPU with other ones, and on a 2-core AVX2-only EPYC the net's float32 gains moved
    # the estimates by up to 4e-9 m and the variances by up to 1.6e-7 (a change in what the
    # filter computes moves them by orders more)
    pd.testing.assert_frame_equal(now, then, rtol=1e-6, atol=1e-6)


def test_the_paths_group_moves_what_lbo_writes_and_leaves_a_runs_identity():
    """``paths`` is the one home of every path: moving its root moves the data sets, the
    studies, the hand-offs and the reports, and no run or data set changes its hash."""
    here, there = compose_cfg("train"), compose_cfg("train", ["paths.root=/elsewhere"])
    assert here.data.root == f"{REPO_ROOT}/data" and there.data.root == "/elsewhere/data"
    assert config_hash(there) == config_hash(here) == PRE_MOVE[()]
    tune = compose_cfg("tune", ["paths.root=/elsewhere", "hparams_search=cnn"])
    assert tune.tune.storage == "sqlite:////elsewhere/optuna.db"
    assert tune.tune.handoff == "/elsewhere/conf/tuned/cnn.yaml"
    reproduce = compose_cfg("reproduce", ["paths.reports=/r", "scale=quick"])
    assert (reproduce.report_dir, reproduce.tracking_uri) == ("/r/quick", here.logger.tracking_uri)
    assert compose_cfg("datagen", ["paths.data=/d"]).data.root == "/d"


def test_a_compiled_run_is_the_same_run():
    """``compile=true`` changes how fast a carried filter trains, not what (the same numbers to
    rounding): it leaves the config hash, so a run trained either way is reused."""
    carried = compose_cfg("train", ["experiment=dynamic_carried"])
    assert carried.compile is True
    assert config_hash(carried) == config_hash(
        compose_cfg("train", ["experiment=dynamic_carried", "compile=false"]))
    assert config_hash(carried) != PRE_MOVE[("experiment=dynamic",)]
