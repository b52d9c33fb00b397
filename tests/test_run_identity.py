"""A run's identity (``config_hash``, from version 2: today's layout only) and the runs a store
holds from before it: each carries its older version's hash, which
:data:`lbo.learn.layouts.OLDER_HASHES` still gives for today's configs, and is migrated once to
today's hash of today's config, so that ``resume=true`` and ``make reproduce`` find it instead
of training everything again."""

import enum
import json
import os
from pathlib import Path

import mlflow
import pytest
import torch
from conftest import compose_cfg
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf, open_dict

from helpers import cli, store_client, train_cfg
from lbo.core.paths import CONF_DIR, REPO_ROOT
from lbo.learn.identity import (
    HASH_VERSION,
    MARKER,
    computed,
    config_hash,
    read_marker,
    was_key,
    yaml_text,
)
from lbo.learn.layouts import (
    LATER_DEFAULTS,
    LATER_MODEL_DEFAULTS,
    OLDER_HASHES,
    hash_v1,
    unlayered,
    upgraded,
)
from lbo.learn.migrate import MIGRATED, V1_TAG, migrate
from lbo.learn.resume import EXPERIMENT_BEFORE, IDENTITY_KEY, finished_run

PRE_MOVE = {
    (): "e018b36dfba2bd07",
    ("experiment=robust",): "3967c9a49a629476",
    ("experiment=dynamic",): "d4eec27d40f3f414",
    ("experiment=dynamic_blackbox", "model=lstm"): "c01f2dc39014800d",
}
"""The hashes these configs had before the move (lbo.callbacks.Evaluation was then the
evaluation callback's path), as the runs of an existing store carry them in their
``config_hash`` tag: version 1 of today's configs. A change here means every such run would
be left unmigrated, and trained again."""

STORED = Path(__file__).parent / "data" / "stored_configs"
"""``config.yaml`` files as lbo logged them with each run (``OmegaConf.to_yaml(cfg,
resolve=True)``) at the commits of :data:`STORED_RUNS`, written by that commit's own code
(``git archive <commit> conf src``, composed there with its own spelling of the overrides,
``output_dir=/home/ada/lbo/outputs/<name>``), byte for byte."""
STORED_RUNS = {
    "pre_move_default": ("659a1c5", (), "e018b36dfba2bd07"),
    "pre_move_robust": ("659a1c5", ("experiment=robust",), "3967c9a49a629476"),
    "pre_move_dynamic": ("659a1c5", ("experiment=dynamic",), "d4eec27d40f3f414"),
    "pre_move_blackbox_lstm": ("659a1c5", ("experiment=dynamic_blackbox", "model=lstm"),
                               "c01f2dc39014800d"),
    "pre_split_dynamic_drift": ("8747360", ("experiment=dynamic", "data=dynamic_drift"),
                                "4a7fe7b6352bad5c"),
    "pre_split_carried_drift": ("8747360", ("experiment=dynamic_carried",
                                            "data=dynamic_drift"), "9f22da9d9da64c1c"),
    "pre_split_data_dynamic": ("8747360", ("data=dynamic",), "adb25d1b2027d6f7"),
    # then spelled truth.steering_offset=0.01
    "pre_split_robust_offset": ("8747360", ("experiment=robust", "sensors.steering_offset=0.01"),
                                "dd32348cea6058e3"),
    "pre_model_keys_lstm": ("1b58bcd", ("model=lstm", "window=60"), "3961f067d85918ee"),
    "pre_model_keys_quick_cnn": ("1b58bcd", ("experiment=quick_literal", "model=cnn",
                                             "window=60"), "f57995013e1b0c39"),
    "pre_model_keys_paper_lstm": ("1b58bcd", ("experiment=paper_literal", "model=lstm",
                                              "window=80", "normalisation=standard"),
                                  "f2fe7c53ed4985e6"),
    "pre_model_keys_absolute": ("1b58bcd", ("features=absolute", "window=40", "seed=3"),
                                "96c94486ff3d65a2"),
    "before_issue39": ("41d4f39", ("experiment=robust", "data=smoke", "window=40",
                                   "batch_size=64", "trainer.max_epochs=1",
                                   "trainer.limit_train_batches=5"), "1a3dac0ffb1381b6"),
}
"""Each stored config's commit (before the layers, the truth split and the model keys moved;
41d4f39, before issue 39), today's overrides for the same run and the ``config_hash`` tag its
run carries (that commit's own hash, checked when the file was written)."""


STORED_V2 = {
    "v2_default": ("0bdf592", (), "84843abcb4f2d3c9"),
    "v2_robust": ("0bdf592", ("experiment=robust",), "288113fff42ca7aa"),
    "v2_robust_residual": ("0bdf592", ("experiment=robust", "model.residual=16",
                                       "sensors.speed_scale=0.02"), "35fe3d5ad4a54bf4"),
}
"""Configs stored by runs under version 2 (the last commit before ``model.input_terms``, the
setting version 3 added to the window filter), written as :data:`STORED`'s are, with that
commit's own ``config_hash`` tag and ``hash_version`` 2."""
STORED_V3 = {
    "v3_dynamic": ("60c5527", ("experiment=dynamic",), "f8e0cb36103e4feb"),
    "v3_robust_terms": ("60c5527", ("experiment=robust", "model.input_terms=true"),
                        "6d7f376695456efb"),
    "v3_split_kalmannet_body": ("60c5527", ("experiment=dynamic", "model=split_kalmannet",
                                            "model.body=single_track"), "0022b0c7f76e9653"),
}
"""... and under version 3 (the last commit before ``model.body_rear``, which version 4
added), with ``hash_version`` 3."""
STORED_OLDER = {2: STORED_V2, 3: STORED_V3}
"""The configs stored under each older version from 2 on, by version."""
LATER_SETTING = {2: ("model.input_terms", False, True), 3: ("model.body_rear", None, 1.5)}
"""A setting added after each version (to the window filter's config; the one after 3 to the
KalmanNet peers' too), its value in the runs stored under it, and another value, which no such
run had."""


def _store(tmp: Path, runs: dict[str, tuple[str, str]], version: int = 1
           ) -> tuple[str, dict[str, str]]:
    """An MLflow store made under config-hash ``version``: per name, a FINISHED run in
    :data:`EXPERIMENT_BEFORE` tagged ``config_hash`` (and, from version 2, ``hash_version``),
    which logged ``config.yaml`` (``runs``: name -> (its text, its tag)). Returns the store's
    URI and the run ids by name."""
    uri = f"sqlite:///{tmp / 'mlflow.db'}"
    client = store_client(uri)
    exp = client.create_experiment(EXPERIMENT_BEFORE,
                                   artifact_location=(tmp / "artifacts").as_uri())
    ids = {}
    for name, (text, digest) in runs.items():
        tags = {"config_hash": digest} | ({"hash_version": str(version)} if version > 1 else {})
        run = client.create_run(exp, tags=tags, run_name=name)
        logged = tmp / "logged" / name / "config.yaml"
        logged.parent.mkdir(parents=True)
        logged.write_text(text)
        client.log_artifact(run.info.run_id, str(logged))
        client.log_metric(run.info.run_id, "val_loss", 0.5, step=0)
        client.set_terminated(run.info.run_id, "FINISHED")
        ids[name] = run.info.run_id
    return uri, ids


@pytest.fixture(scope="module")
def old_store(tmp_path_factory):
    """One run per stored config of :data:`STORED_RUNS`, as its store holds it."""
    return _store(tmp_path_factory.mktemp("store"), {
        name: ((STORED / f"{name}.yaml").read_text(), tag)
        for name, (_, _, tag) in STORED_RUNS.items()})


class _Side(enum.Enum):
    LEFT = 1


@pytest.mark.parametrize("overrides", [["experiment=smoke"], ["model=kalmannet"],
                                       ["experiment=dynamic"], ["data=logs"]])
def test_the_hashed_yaml_is_omegaconfs_to_yaml_of_the_tree(overrides):
    """The text a config hash reads is what ``OmegaConf.to_yaml`` writes of the tree, without
    building a config from it: the same quotes on strings that read as numbers or bools,
    enums by name and tuples as lists."""
    tree = computed(compose_cfg("train", overrides))
    tree["odd"] = {"float": "1e3", "int": "7", "bool": "yes", "none": None, "side": _Side.LEFT,
                   "list": [1.5, "0.5", [True]], "tuple": (1, "2")}
    assert yaml_text(tree) == OmegaConf.to_yaml(OmegaConf.create(tree), sort_keys=True)


@pytest.mark.parametrize("name", list(STORED_RUNS))
def test_a_stored_config_brought_to_todays_layout_hashes_as_todays_config(name):
    """Version 1 of the stored config, upgraded, is the tag its run carries, and of today's
    config too; version 2 of the upgraded config is today's config's, bit for bit."""
    _, overrides, tag = STORED_RUNS[name]
    today = compose_cfg("train", list(overrides))
    stored = upgraded(OmegaConf.create((STORED / f"{name}.yaml").read_text()))
    assert hash_v1(stored) == hash_v1(today) == tag
    assert config_hash(stored) == config_hash(today)


@pytest.mark.parametrize("name", list(STORED_RUNS))
def test_resume_finds_each_run_of_a_store_made_before_version_2(name, old_store):
    uri, ids = old_store
    cfg = compose_cfg("train", [*STORED_RUNS[name][1], f"logger.tracking_uri={uri}"])
    found = finished_run(cfg, config_hash(cfg), clean=False)
    assert found is not None and found["run_id"] == ids[name] and found["reused"]
    tags = mlflow.MlflowClient(uri).get_run(ids[name]).data.tags
    assert (tags["config_hash"], tags[V1_TAG], tags["hash_version"]) == (
        config_hash(cfg), STORED_RUNS[name][2], str(HASH_VERSION))


@pytest.mark.parametrize("overrides", list(PRE_MOVE), ids=lambda o: " ".join(o) or "default")
def test_version_1_of_todays_configs_is_the_hash_runs_carry_from_before_the_move(overrides):
    assert hash_v1(compose_cfg("train", list(overrides))) == PRE_MOVE[overrides]


def _counted(monkeypatch, *names: str) -> dict[str, int]:
    """Count the calls of MlflowClient's methods ``names`` from now on."""
    calls = dict.fromkeys(names, 0)

    def counting(name: str):
        method = getattr(mlflow.MlflowClient, name)

        def counted(self, *a, **k):
            calls[name] += 1
            return method(self, *a, **k)
        return counted

    for name in names:
        monkeypatch.setattr(mlflow.MlflowClient, name, counting(name))
    return calls


def test_a_store_is_migrated_once_and_a_run_that_does_not_match_its_tag_is_left(
        tmp_path, monkeypatch, capsys):
    """The first search migrates the experiment, in one line; a run whose stored config does
    not give its tag, or that logged none, keeps its tags, with a line why. The next search
    migrates nothing and asks the store nothing more than the search itself."""
    default, robust = ((STORED / f"{n}.yaml").read_text()
                       for n in ("pre_move_default", "pre_move_robust"))
    uri, ids = _store(tmp_path, {"default": (default, PRE_MOVE[()]),
                                 "robust": (robust, PRE_MOVE[("experiment=robust",)]),
                                 "other": (robust, "0123456789abcdef")})
    client = mlflow.MlflowClient(uri)
    bare = client.create_run(client.get_experiment_by_name(EXPERIMENT_BEFORE).experiment_id,
                             tags={"config_hash": "fedcba9876543210"})  # logged no config
    cfg = compose_cfg("train", [f"logger.tracking_uri={uri}"])
    capsys.readouterr()
    assert finished_run(cfg, config_hash(cfg), clean=False)["run_id"] == ids["default"]
    said = capsys.readouterr().out.splitlines()
    assert sorted(said[:-1]) == sorted([
        f"left run {bare.info.run_id} of lbo as it was: it logged no config.yaml",
        f"left run {ids['other']} of lbo as it was: its config.yaml hashes as "
        f"{PRE_MOVE[('experiment=robust',)]}, not as its tag 0123456789abcdef"])
    assert said[-1] == (f"migrated 2 runs of lbo to config hash version {HASH_VERSION} "
                        "(2 left as they were)")
    for run_id, tag in ((ids["other"], "0123456789abcdef"),
                        (bare.info.run_id, "fedcba9876543210")):
        assert client.get_run(run_id).data.tags.get("config_hash") == tag
        assert "hash_version" not in client.get_run(run_id).data.tags
    exp = client.get_experiment_by_name(EXPERIMENT_BEFORE)
    assert exp.tags[MIGRATED] == str(HASH_VERSION)

    before = {r.info.run_id: r.data.tags for r in client.search_runs([exp.experiment_id])}
    calls = _counted(monkeypatch, "search_runs", "list_artifacts", "log_batch",
                     "set_experiment_tag")
    assert finished_run(cfg, config_hash(cfg), clean=False)["run_id"] == ids["default"]
    assert capsys.readouterr().out == ""
    assert calls == {"search_runs": 1, "list_artifacts": 0, "log_batch": 0,
                     "set_experiment_tag": 0}  # the search for the run, nothing else
    monkeypatch.undo()
    assert {r.info.run_id: r.data.tags for r in client.search_runs([exp.experiment_id])} == before


def test_the_command_migrates_every_experiment_and_changes_nothing_the_second_time(tmp_path):
    uri, ids = _store(tmp_path, {"dynamic": ((STORED / "pre_move_dynamic.yaml").read_text(),
                                             PRE_MOVE[("experiment=dynamic",)])})
    res = cli("lbo.learn.migrate", uri)
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines() == [
        f"migrated 1 run of lbo to config hash version {HASH_VERSION}",
        f"{uri}: 1 run migrated to config hash version {HASH_VERSION}"]
    client = mlflow.MlflowClient(uri)
    tags = client.get_run(ids["dynamic"]).data.tags
    assert tags["config_hash"] == config_hash(compose_cfg("train", ["experiment=dynamic"]))
    assert migrate(uri) == 0 and client.get_run(ids["dynamic"]).data.tags == tags
    # an experiment the command went through is not marked: it may not be lbo's
    assert MIGRATED not in client.get_experiment_by_name(EXPERIMENT_BEFORE).tags


def test_a_target_hashes_by_its_layer_and_a_run_stored_before_the_layers_is_migrated():
    cfg = compose_cfg("train")
    assert cfg.callbacks.evaluation._target_ == "lbo.learn.callbacks.Evaluation"
    before = cfg.copy()
    with open_dict(before):
        before.callbacks.evaluation._target_ = "lbo.callbacks.Evaluation"  # the path before
    assert hash_v1(before) == hash_v1(cfg)  # the tag a run stored before carries
    assert config_hash(before) != config_hash(cfg)  # no longer replayed at every hash...
    assert config_hash(upgraded(before)) == config_hash(cfg)  # ...but migrated once
    # lbo.tuning.callbacks exists too: the layer is the one whose module defines the class
    assert upgraded(before).callbacks.evaluation._target_ == "lbo.learn.callbacks.Evaluation"
    other = cfg.copy()
    with open_dict(other):
        other.callbacks.evaluation._target_ = "lbo.learn.callbacks.Other"  # another class
    assert hash_v1(other) != hash_v1(cfg) and config_hash(other) != config_hash(cfg)


def test_only_lbo_targets_in_a_layer_lose_the_layer():
    tree = {"a": {"_target_": "lbo.learn.callbacks.Evaluation", "k": [1, {"_target_":
                                                                         "lbo.core.x.Y"}]},
            "b": {"_target_": "lightning.pytorch.callbacks.EarlyStopping"},
            "c": {"_target_": "lbo.train.Thing"}, "d": "lbo.learn.callbacks.Evaluation"}
    assert unlayered(tree) == {
        "a": {"_target_": "lbo.callbacks.Evaluation", "k": [1, {"_target_": "lbo.x.Y"}]},
        "b": {"_target_": "lightning.pytorch.callbacks.EarlyStopping"},
        "c": {"_target_": "lbo.train.Thing"}, "d": "lbo.learn.callbacks.Evaluation"}


def _stored_without(cfg, *keys: str):
    """``cfg`` as a run stored before ``keys`` (dotted) were added."""
    before = cfg.copy()
    with open_dict(before):
        for key in keys:
            *group, name = key.split(".")
            (OmegaConf.select(before, ".".join(group)) if group else before).pop(name)
    return before


def test_a_setting_added_later_migrates_at_its_old_value_only():
    """``model.gyro`` came after these runs: false (their value) keeps the version-1 hash they
    carry, and the run migrated is the config's; true makes another run."""
    plain = compose_cfg("train", ["experiment=robust"])
    gyro = compose_cfg("train", ["experiment=robust", "model.gyro=true"])
    assert plain.model.gyro is False
    assert hash_v1(plain) == PRE_MOVE[("experiment=robust",)] != hash_v1(gyro)
    assert config_hash(upgraded(_stored_without(plain, "model.gyro"))) == config_hash(plain)
    assert config_hash(gyro) != config_hash(plain)


@pytest.mark.parametrize("setting", ["nll=0.1", "train_noise.changes=2", "tbptt=100"])
def test_the_sequence_trainers_settings_migrate_old_runs_at_their_defaults(setting):
    """``tbptt``, ``nll`` and ``train_noise.changes`` came after these runs: at their
    defaults the version-1 hash is the one the runs carry, and the runs migrated are the
    config's; set, another run."""
    plain = compose_cfg("train", ["experiment=dynamic"])
    assert plain.nll == 0.0 and plain.train_noise.changes == 0 and plain.tbptt is None
    assert hash_v1(plain) == PRE_MOVE[("experiment=dynamic",)]
    stored = _stored_without(plain, "nll", "train_noise.changes", "tbptt")
    assert config_hash(upgraded(stored)) == config_hash(plain)
    assert config_hash(compose_cfg("train", ["experiment=dynamic", setting])) != \
        config_hash(plain)


LATER = [(key, ()) for key in LATER_DEFAULTS if key not in ("receiver", "model.gyro",
                                                             "data.source")]
LATER += [("model.gyro", ("experiment=robust",))]
LATER += [(f"model.{key}", (f"model={name}",)) for name, keys in LATER_MODEL_DEFAULTS.items()
          for key in keys]
"""Each setting version 1 hashed as absent at its old value, and a config that holds it
(``data.source``, a user's logs': tests/test_next_fix.py)."""


@pytest.mark.parametrize("key, overrides", LATER, ids=[k for k, _ in LATER])
def test_a_run_stored_before_any_setting_was_added_is_migrated_to_todays_config(key,
                                                                              overrides):
    now = compose_cfg("train", list(overrides))
    before = _stored_without(now, key)
    assert hash_v1(before) == hash_v1(now)
    assert config_hash(upgraded(before)) == config_hash(now) != config_hash(before)


def test_the_receiver_is_a_group_no_run_holds_at_its_old_value():
    """``receiver: null`` in version 1's table: a group not chosen is absent, not null, so a
    migration adds nothing for it (and a chosen one is another run)."""
    plain = compose_cfg("train")
    assert "receiver" not in plain
    assert config_hash(upgraded(plain)) == config_hash(plain)
    assert config_hash(compose_cfg("train", ["receiver=single_antenna"])) != config_hash(plain)


PRE_SPLIT = {
    ("experiment=dynamic", "data=dynamic_drift"): ("4a7fe7b6352bad5c", "f6b39670d94a"),
    ("experiment=dynamic_carried", "data=dynamic_drift"): ("9f22da9d9da64c1c", "f6b39670d94a"),
    ("data=dynamic",): ("adb25d1b2027d6f7", "e47207bbd8a4"),
    ("experiment=robust", "sensors.steering_offset=0.01"): ("dd32348cea6058e3", "ae120a23946c"),
}
"""Config hashes (version 1) and data-set digests from before the ``truth`` group was split
into ``car`` and ``sensors`` (the last override was then ``truth.steering_offset=0.01``)."""


@pytest.mark.parametrize("overrides", list(PRE_SPLIT), ids=" ".join)
def test_the_car_apart_from_its_sensors_leaves_runs_and_data_sets_as_they_were(overrides):
    from lbo.sim.datasets import spec_from_cfg

    cfg = compose_cfg("train", list(overrides))
    assert (hash_v1(cfg), spec_from_cfg(cfg).digest) == PRE_SPLIT[overrides]


PRE_MODEL_KEYS = {
    ("model=lstm", "window=60"): "3961f067d85918ee",
    ("experiment=quick_literal", "model=cnn", "window=60"): "f57995013e1b0c39",
    ("experiment=paper_literal", "model=lstm", "window=80", "normalisation=standard"):
        "f2fe7c53ed4985e6",
    ("features=absolute", "window=40", "seed=3"): "96c94486ff3d65a2",
}
"""Config hashes (version 1) from before ``window``, ``features`` and ``normalisation`` moved
under ``model``, with the overrides as they were then spelled."""


@pytest.mark.parametrize("overrides", list(PRE_MODEL_KEYS), ids=" ".join)
def test_the_model_keys_under_model_leave_runs_as_they_were_in_either_spelling(overrides):
    from lbo.core.cli import respell

    long = respell(list(overrides))
    assert [o for o in long if o.split("=")[0] in ("window", "features", "normalisation")] == []
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        plain = compose(config_name="train", overrides=long)  # Hydra itself: no respelling
    assert plain.model.window == int(next(o for o in long if "window=" in o).split("=")[1])
    short = compose_cfg("train", list(overrides))
    assert hash_v1(plain) == hash_v1(short) == PRE_MODEL_KEYS[overrides]
    assert config_hash(plain) == config_hash(short)


BEFORE = Path(__file__).parent / "data" / "before_issue39"
"""A run trained by lbo at 41d4f39, before the modules were split into one idea each: the
smoke robust observer (``BEFORE_OVERRIDES``) and what ``lbo.observe`` made of the example
log's first 600 rows with it then."""
BEFORE_OVERRIDES = ["experiment=robust", "data=smoke", "window=40", "batch_size=64",
                    "trainer.max_epochs=1", "trainer.limit_train_batches=5"]


def test_a_run_trained_before_the_rooms_were_split_resumes_and_observes_as_it_did(tmp_path):
    """Its config hash (the ``config_hash`` tag its MLflow run carries) is version 1 of
    today's config, so its run is migrated and ``resume=true`` finds it
    (``before_issue39`` above); its checkpoint observes the log as it did then."""
    import pandas as pd

    from helpers import observe

    assert hash_v1(compose_cfg("train", BEFORE_OVERRIDES)) == "1a3dac0ffb1381b6"
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
    assert config_hash(there) == config_hash(here)
    assert hash_v1(there) == hash_v1(here) == PRE_MOVE[()]
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
    assert hash_v1(carried) != PRE_MOVE[("experiment=dynamic",)]
    assert config_hash(carried) != config_hash(compose_cfg("train", ["experiment=dynamic"]))


# --- the run-identity file and the checkpoints of a run killed before its migration ------------


def _as_killed_under_version_1(client, run_id: str, folder: Path, v1: str) -> None:
    """Make finished run ``run_id`` (in ``folder``) what lbo left of a run killed before
    version 2: RUNNING, tagged with its version-1 hash only, the run-identity file and the
    last checkpoint carrying that hash, its experiment not yet migrated."""
    run = client.get_run(run_id)
    client.set_terminated(run_id, "RUNNING")
    client.set_tag(run_id, "config_hash", v1)
    client.delete_tag(run_id, "hash_version")
    client.delete_experiment_tag(run.info.experiment_id, MIGRATED)
    (folder / MARKER).write_text(json.dumps(  # as lbo wrote it then
        {"run_id": run_id, "config_hash": v1, "folder": str(folder.resolve()),
         "uid": os.getuid(), "finished": False}, indent=1) + "\n")
    last = folder / "checkpoints" / "last.ckpt"
    ckpt = torch.load(last, map_location="cpu", weights_only=True)
    ckpt[IDENTITY_KEY] = {"run_id": run_id, "config_hash": v1}
    torch.save(ckpt, last)


@pytest.mark.usefixtures("one_torch_thread")
@pytest.mark.parametrize("rerun_in", ["elsewhere", "first"])
def test_a_run_killed_before_version_2_is_migrated_and_continued(tmp_path, smoke_data,
                                                                 tracking, capsys, rerun_in):
    """Its store migrated on the rerun's first search, its marker rewritten with both hashes,
    its last checkpoint (which carries the old one) accepted: the rerun continues it, from
    another ``output_dir`` or from its own (whose marker still names the old hash)."""
    from lbo.train import train

    short = ("trainer.max_epochs=1", "trainer.limit_train_batches=5", "seed=5", "resume=true")
    cfg = train_cfg(tmp_path / "first", smoke_data, *short)
    got = train(cfg)
    folder = tmp_path / "first" / "out"
    client = mlflow.MlflowClient(tracking)
    assert client.get_run(got["run_id"]).data.tags["hash_version"] == str(HASH_VERSION)
    assert read_marker(folder)[0]["hash_version"] == HASH_VERSION
    v1, digest = hash_v1(cfg), config_hash(cfg)
    _as_killed_under_version_1(client, got["run_id"], folder, v1)

    capsys.readouterr()
    rerun = train(train_cfg(tmp_path / rerun_in, smoke_data, *short))
    out = capsys.readouterr().out
    assert f"migrated 1 run of lbo-smoke to config hash version {HASH_VERSION}" in out
    assert f"resuming the killed run {got['run_id']}" in out
    assert rerun["run_id"] == got["run_id"] and not rerun["reused"]
    assert Path(rerun["checkpoint"]) == folder / "checkpoints" / "best.ckpt"
    run = client.get_run(got["run_id"])
    assert run.info.status == "FINISHED"
    assert (run.data.tags["config_hash"], run.data.tags[V1_TAG]) == (digest, v1)
    marker, _ = read_marker(folder)
    assert (marker["config_hash"], marker["finished"]) == (digest, True)


def test_a_folder_of_a_run_written_before_version_2_is_its_configs_only(tmp_path):
    """A run-identity file from before version 2 names the version-1 hash: an unfinished run
    there is this config's (``resume=true`` may continue or replace it) where that is this
    config's version 1, and another config's otherwise."""
    from lbo.learn.resume import folder_refusal

    cfg, other = compose_cfg("train"), compose_cfg("train", ["seed=1"])
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / MARKER).write_text(json.dumps(
        {"run_id": "r1", "config_hash": PRE_MOVE[()], "folder": str(folder.resolve()),
         "uid": os.getuid(), "finished": False}))
    assert folder_refusal(folder, config_hash(cfg), True, cfg=cfg) is None
    for refused, given in ((other, other), (cfg, None)):
        why = folder_refusal(folder, config_hash(refused), True, cfg=given)
        assert "already holds the files of run r1 of another config" in why


def test_a_marker_left_by_someone_elses_migration_is_mended_only_for_its_own_config(
        tmp_path, capsys):
    """In a shared store another user migrated, this user's finished run is found by its new
    hash while its folder's marker still names the old: it is reused, and the marker
    rewritten, where this config's own version-1 hash is the marker's; a run the store says
    is the same, with another config's hash, is not."""
    from lbo.learn.resume import own_store

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = store_client(uri)
    exp = client.create_experiment("lbo-paper", artifact_location=(tmp_path / "a").as_uri())
    client.set_experiment_tag(exp, MIGRATED, str(HASH_VERSION))
    runs = {}
    for seed in (0, 1):
        cfg = compose_cfg("train", [f"seed={seed}", f"logger.tracking_uri={uri}"])
        folder = tmp_path / f"run{seed}"
        folder.mkdir()
        # both markers name the default config's version-1 hash
        run = client.create_run(exp, tags={"config_hash": config_hash(cfg), V1_TAG: PRE_MOVE[()],
                                           "hash_version": str(HASH_VERSION)})
        client.log_param(run.info.run_id, "output_dir", str(folder))
        client.log_metric(run.info.run_id, "val_loss", 0.5, step=0)
        client.set_terminated(run.info.run_id, "FINISHED")
        (folder / MARKER).write_text(json.dumps(
            {"run_id": run.info.run_id, "config_hash": PRE_MOVE[()],
             "folder": str(folder.resolve()), "uid": os.getuid(), "finished": True}))
        runs[seed] = cfg, run.info.run_id, folder
    (tmp_path / "mlflow.db").chmod(0o666)
    assert not own_store(uri)
    cfg, run_id, folder = runs[0]
    assert finished_run(cfg, config_hash(cfg), clean=False)["run_id"] == run_id
    assert read_marker(folder)[0]["config_hash"] == config_hash(cfg)
    assert read_marker(folder)[0][V1_TAG] == PRE_MOVE[()]
    cfg, run_id, folder = runs[1]
    capsys.readouterr()
    assert finished_run(cfg, config_hash(cfg), clean=False) is None
    assert f"not reusing the finished run {run_id}" in capsys.readouterr().out
    assert read_marker(folder)[0]["config_hash"] == PRE_MOVE[()]


@pytest.mark.parametrize("version, name", [(v, n) for v, runs in STORED_OLDER.items()
                                            for n in runs])
def test_a_config_stored_under_an_older_version_gives_its_tag_and_todays_hash(version, name):
    """That version of the stored config, upgraded (the settings added since filled at their
    old values), is the tag its run carries, and of today's config too; today's hash of the
    upgraded config is today's config's. With the setting added next at another value, it is
    no run of before."""
    _, overrides, tag = STORED_OLDER[version][name]
    then = OLDER_HASHES[version]
    today = compose_cfg("train", list(overrides))
    stored = upgraded(OmegaConf.create((STORED / f"{name}.yaml").read_text()))
    assert then(stored) == then(today) == tag
    assert config_hash(stored) == config_hash(today)
    if today.model.name == "filternet" or version == 3:
        key, old, other = LATER_SETTING[version]
        assert OmegaConf.select(stored, key) == old and config_hash(today) != tag
        changed = compose_cfg("train", [*overrides, f"{key}={other}"])
        assert tag != then(changed) != config_hash(today)


@pytest.mark.parametrize("version", list(STORED_OLDER))
def test_a_store_made_under_an_older_version_is_migrated_once_keeping_its_old_hashes(
        version, tmp_path, capsys):
    """Each run of that version is found by today's hash and keeps its hash of that version
    (``config_hash_v2``, ``config_hash_v3``); a run tagged with a version lbo never wrote is
    left, in a line."""
    runs = STORED_OLDER[version]
    texts = {name: (STORED / f"{name}.yaml").read_text() for name in runs}
    uri, ids = _store(tmp_path, {name: (texts[name], tag)
                                 for name, (_, _, tag) in runs.items()}, version=version)
    client = mlflow.MlflowClient(uri)
    odd = client.create_run(client.get_experiment_by_name(EXPERIMENT_BEFORE).experiment_id,
                            tags={"config_hash": "0123456789abcdef", "hash_version": "x"})
    capsys.readouterr()
    for name, (_, overrides, tag) in runs.items():
        cfg = compose_cfg("train", [*overrides, f"logger.tracking_uri={uri}"])
        found = finished_run(cfg, config_hash(cfg), clean=False)
        assert found is not None and found["run_id"] == ids[name]
        tags = client.get_run(ids[name]).data.tags
        assert (tags["config_hash"], tags[was_key(version)], tags["hash_version"]) == (
            config_hash(cfg), tag, str(HASH_VERSION))
    said = capsys.readouterr().out.splitlines()
    assert said == [f"left run {odd.info.run_id} of lbo as it was: its hash_version 'x' is "
                    "none of [1, 2, 3]",
                    f"migrated {len(runs)} runs of lbo to config hash version {HASH_VERSION} "
                    "(1 left as they were)"]


def test_a_folder_and_a_checkpoint_written_under_version_2_are_their_configs(tmp_path):
    """A run-identity file written under version 2 names the version-2 hash: an unfinished
    run there is this config's where that is this config's version 2. Migrated, the file
    keeps it beside today's, and a killed run's last checkpoint, which carries it, is the
    run's."""
    from lbo.learn.migrate import migrate_run
    from lbo.learn.resume import folder_refusal, resumable_folder

    cfg = compose_cfg("train", ["experiment=robust"])
    other = compose_cfg("train", ["experiment=robust", "model.input_terms=true"])
    v2 = STORED_V2["v2_robust"][2]
    folder = tmp_path / "run"
    (folder / "checkpoints").mkdir(parents=True)
    (folder / MARKER).write_text(json.dumps(
        {"run_id": "r1", "config_hash": v2, "hash_version": 2, "config_hash_v1": "0" * 16,
         "folder": str(folder.resolve()), "uid": os.getuid(), "finished": False}))
    assert folder_refusal(folder, config_hash(cfg), True, cfg=cfg) is None
    why = folder_refusal(folder, config_hash(other), True, cfg=other)
    assert "already holds the files of run r1 of another config" in why

    uri, ids = _store(tmp_path / "store", {"robust": (
        (STORED / "v2_robust.yaml").read_text(), v2)}, version=2)
    client = mlflow.MlflowClient(uri)
    client.log_param(ids["robust"], "output_dir", str(folder))
    marker = json.loads((folder / MARKER).read_text()) | {"run_id": ids["robust"]}
    (folder / MARKER).write_text(json.dumps(marker))
    assert migrate_run(client, client.get_run(ids["robust"])) is None
    marker, _ = read_marker(folder)
    assert (marker["config_hash"], marker[was_key(2)], marker[was_key(1)],
            marker["hash_version"]) == (config_hash(cfg), v2, "0" * 16, HASH_VERSION)
    torch.save({IDENTITY_KEY: {"run_id": ids["robust"], "config_hash": v2}},
               folder / "checkpoints" / "last.ckpt")
    assert resumable_folder(folder, ids["robust"], config_hash(cfg)) is None
    torch.save({IDENTITY_KEY: {"run_id": ids["robust"], "config_hash": "f" * 16}},
               folder / "checkpoints" / "last.ckpt")
    assert "was not written by that run" in resumable_folder(folder, ids["robust"],
                                                              config_hash(cfg))
