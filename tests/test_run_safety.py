"""What a training run may touch (issue 41, items 3, 7, 8 and 9 of the audit).

- a new run never deletes or overwrites another run's files: an ``output_dir`` (or
  ``hydra.run.dir``) holding them is refused in one line, and nothing there changes;
- ``resume=true`` trusts the run folder, not the tracking store: a run that anyone can plant
  in a store without authentication cannot steer a training into a folder of their choosing,
  nor make it log a checkpoint of their choosing;
- a password in a store's URI is masked whatever characters it holds;
- a damaged SQLite tracking store is one line that names it and says how to fix it.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import torch

from helpers import cli, one_line_error, store_client, train_cfg
from helpers.servers import free_port
from lbo.core.errors import LboError
from lbo.core.paths import EXAMPLE_LOG
from lbo.core.redact import scrub
from lbo.train import config_hash, train

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SHORT = ("trainer.max_epochs=1", "trainer.limit_train_batches=5")
"""One short epoch: these tests check which files a run touches, not what it learns."""


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> bytes): what a refused run must leave."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def one_thread_cli(module: str, *args: str, env: dict[str, str],
                   process: bool = False) -> subprocess.CompletedProcess:
    return cli(module, *args, env={"OMP_NUM_THREADS": "1", **env}, process=process)


# --- item 3: an output_dir that holds another run's files ------------------------------------


def test_training_into_a_finished_runs_folder_is_refused_and_changes_nothing(
        tmp_path, smoke_data, tracking):
    """A copied command, or a typo, that names a finished run's folder as ``output_dir``:
    that run's ``best.ckpt`` (which ``observer=`` commands were given) must stay its own."""
    first = train(train_cfg(tmp_path / "a", smoke_data, *SHORT))
    folder = tmp_path / "a" / "out"
    assert Path(first["checkpoint"]) == folder / "checkpoints" / "best.ckpt"
    before = snapshot(folder)
    # the same command again (no resume), and another config into the same folder
    for more in ((), ("seed=7",), ("seed=7", "resume=true")):
        cfg = train_cfg(tmp_path / "a", smoke_data, *SHORT, *more)
        with pytest.raises(LboError, match=rf"output_dir: {folder} already holds the files of "
                                           rf"the finished run {first['run_id']}; nothing"):
            train(cfg)
        assert snapshot(folder) == before
    # the advice, followed: a new folder trains
    again = train(train_cfg(tmp_path / "b", smoke_data, *SHORT, "seed=7"))
    assert Path(again["checkpoint"]).is_relative_to(tmp_path / "b" / "out")


def test_a_folder_of_foreign_files_is_refused_and_changes_nothing(tmp_path, smoke_data,
                                                                  tracking):
    """Not only lbo runs: any non-empty folder that is not this run's own is left alone."""
    folder = tmp_path / "out"
    (folder / "checkpoints").mkdir(parents=True)
    (folder / "checkpoints" / "best.ckpt").write_bytes(b"someone's weights")
    (folder / "notes.txt").write_text("keep me\n")
    before = snapshot(folder)
    with pytest.raises(LboError, match=r"already holds files that are not this run's "
                                       r"\(checkpoints, notes.txt\)"):
        train(train_cfg(tmp_path, smoke_data, *SHORT, "resume=true"))
    assert snapshot(folder) == before


def test_hydra_run_dir_of_a_finished_run_keeps_its_hydra_record(tmp_path, smoke_data):
    """``hydra.run.dir=<a finished run's folder>``: refused before lbo's shell rewrites that
    run's ``.hydra`` files, in one line."""
    env = {"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}
    args = ["experiment=smoke", f"data.root={smoke_data.parent}", *SHORT]
    folder = tmp_path / "run"
    done = one_thread_cli("lbo.train", *args, f"hydra.run.dir={folder}", env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    before = snapshot(folder)
    res = one_thread_cli("lbo.train", *args, "seed=5", f"hydra.run.dir={folder}", env=env)
    one_line_error(res, f"hydra.run.dir: {folder} already holds the files of the finished run",
                   "give hydra.run.dir=<a new or empty folder>")
    after = snapshot(folder)
    # Hydra opens the job's log (train.log) for appending before lbo runs: nothing is lost
    assert {k: v for k, v in after.items() if k != "train.log"} == \
        {k: v for k, v in before.items() if k != "train.log"}
    assert after.get("train.log", b"").startswith(before.get("train.log", b""))


# --- item 7: resume trusts the run's own folder, not the store --------------------------------


def test_a_run_planted_in_the_store_cannot_steer_resume(tmp_path, smoke_data, tracking,
                                                        capsys):
    """Anyone who can write to a shared store adds an unfinished run with the config hash of
    the victim's next training, pointing at a folder they prepared: a real last.ckpt of that
    config whose stored ``best_model_path`` names a checkpoint of their choosing. The
    victim's ``resume=true`` must neither continue in that folder nor log that checkpoint."""
    overrides = (*SHORT, "seed=5", "resume=true")
    victim = train_cfg(tmp_path / "victim", smoke_data, *overrides)
    digest = config_hash(victim)
    # the planted folder: a run of the same config trained elsewhere (another store), its
    # run-identity file gone as another user's folder would not have this user's
    planted = tmp_path / "planted" / "out"
    planted.parent.mkdir()
    other_store = f"sqlite:///{tmp_path / 'planted' / 'mlflow.db'}"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", other_store)
        train(train_cfg(tmp_path / "planted", smoke_data, *SHORT, "seed=5"))
    (planted / ".lbo-run.json").unlink(missing_ok=True)
    evil = tmp_path / "planted" / "evil.ckpt"
    shutil.copy(planted / "checkpoints" / "best.ckpt", evil)
    last = planted / "checkpoints" / "last.ckpt"
    ckpt = torch.load(last, map_location="cpu", weights_only=True)
    for key, state in ckpt["callbacks"].items():
        if key.startswith("ModelCheckpoint"):
            state["best_model_path"] = str(evil)
    torch.save(ckpt, last)
    # the planted run in the victim's store: this config's hash, that folder, RUNNING
    client = store_client(tracking)
    exp = client.create_experiment(victim.logger.experiment_name,
                                   artifact_location=(tmp_path / "artifacts").as_uri())
    run = client.create_run(exp, tags={"config_hash": digest}, run_name="cnn-N20")
    client.log_param(run.info.run_id, "output_dir", str(planted))
    before = snapshot(tmp_path / "planted")

    capsys.readouterr()
    got = train(victim)
    out = capsys.readouterr().out
    assert got["run_id"] != run.info.run_id and not got["reused"]
    assert Path(got["checkpoint"]) == tmp_path / "victim" / "out" / "checkpoints" / "best.ckpt"
    assert snapshot(tmp_path / "planted") == before  # not a byte written there
    assert f"not resuming the unfinished run {run.info.run_id} of the same config" in out
    assert "this run starts afresh" in out
    logged = client.download_artifacts(got["run_id"], "checkpoints/best.ckpt", str(tmp_path))
    assert Path(logged).read_bytes() == Path(got["checkpoint"]).read_bytes()
    assert Path(logged).read_bytes() != evil.read_bytes()

    # the victim's own killed run still resumes in its own folder, from another output_dir
    client.set_terminated(got["run_id"], "RUNNING")
    capsys.readouterr()
    rerun = train(train_cfg(tmp_path / "elsewhere", smoke_data, *overrides))
    assert rerun["run_id"] == got["run_id"] and not rerun["reused"]
    assert f"resuming the killed run {got['run_id']}" in capsys.readouterr().out
    assert Path(rerun["checkpoint"]) == Path(got["checkpoint"])


def test_a_shared_store_cannot_hand_over_a_finished_run_nor_lose_another_users_run(
        tmp_path, smoke_data, tracking, capsys):
    """In a store that others can write, ``resume=true`` reuses a FINISHED run of the same
    config only where its folder shows it is this user's (a planted one would hand over its
    metrics and checkpoint as this user's observer), and deletes only this user's own
    unfinished runs, never a colleague's training of the same config."""
    from lbo.learn.resume import own_store

    victim = train_cfg(tmp_path / "victim", smoke_data, *SHORT, "seed=6", "resume=true")
    digest = config_hash(victim)
    client = store_client(tracking)
    exp = client.create_experiment(victim.logger.experiment_name,
                                   artifact_location=(tmp_path / "artifacts").as_uri())
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    planted = client.create_run(exp, tags={"config_hash": digest}, run_name="cnn-N20")
    client.log_param(planted.info.run_id, "output_dir", str(foreign))
    client.log_metric(planted.info.run_id, "val_loss", 1e-9)
    client.set_terminated(planted.info.run_id, "FINISHED")
    colleague = client.create_run(exp, tags={"config_hash": digest}, run_name="cnn-N20")
    client.log_param(colleague.info.run_id, "output_dir", str(foreign))
    store = Path(tracking.removeprefix("sqlite:///"))
    assert own_store(tracking)  # this user's file: every run in it is this user's
    store.chmod(0o666)  # now anyone on the machine can write runs into it
    assert not own_store(tracking) and not own_store("http://127.0.0.1:1")

    capsys.readouterr()
    got = train(victim)
    out = capsys.readouterr().out
    assert not got["reused"] and got["run_id"] not in (planted.info.run_id,
                                                       colleague.info.run_id)
    assert f"not reusing the finished run {planted.info.run_id}" in out
    assert client.get_run(colleague.info.run_id).info.lifecycle_stage == "active"
    # this user's own finished run, shown by its folder, is reused as before
    again = train(train_cfg(tmp_path / "again", smoke_data, *SHORT, "seed=6", "resume=true"))
    assert again["reused"] and again["run_id"] == got["run_id"]


def test_resume_checks_the_marker_the_checkpoint_and_its_best_path(tmp_path):
    """Each check of a folder that a store's run names, on a hand-made folder: this user's
    run-identity file for that run and config, a last.ckpt carrying the same identity, and a
    best checkpoint inside that folder."""
    from lbo.learn.identity import write_marker
    from lbo.learn.resume import IDENTITY_KEY, resumable_folder

    folder = tmp_path / "run"
    (folder / "checkpoints").mkdir(parents=True)
    last = folder / "checkpoints" / "last.ckpt"

    def ckpt(run_id: str, best: Path) -> None:
        torch.save({IDENTITY_KEY: {"run_id": run_id, "config_hash": "h1"},
                    "callbacks": {"ModelCheckpoint{'monitor': 'val_loss'}":
                                  {"best_model_path": str(best)}}}, last)

    ckpt("r1", folder / "checkpoints" / "best.ckpt")
    assert "was not created for it here" in resumable_folder(folder, "r1", "h1")
    write_marker(folder, "r1", "h1")
    assert resumable_folder(folder, "r1", "h1") is None
    assert "belongs to run r1" in resumable_folder(folder, "r2", "h1")
    assert "belongs to run r1" in resumable_folder(folder, "r1", "h2")
    ckpt("r2", folder / "checkpoints" / "best.ckpt")
    assert "was not written by that run" in resumable_folder(folder, "r1", "h1")
    ckpt("r1", tmp_path / "elsewhere.ckpt")
    assert "names a best checkpoint outside" in resumable_folder(folder, "r1", "h1")
    # a marker copied from another folder is not this folder's
    other = tmp_path / "copy"
    shutil.copytree(folder, other)
    assert "written for another folder" in resumable_folder(other, "r1", "h1")


# --- item 8: passwords that hold / : @ ----------------------------------------------------------


@pytest.mark.parametrize("password", ["s3cr3t-pw", "a/b", "k9/Qz:x@y/7"])
def test_a_password_with_slashes_is_masked_like_any_other(password):
    for uri in (f"postgresql://alice:{password}@db.example.org:5432/mlflow",
                f"http://alice:{password}@127.0.0.1:5000"):
        shown = scrub(f"error: no store at {uri} (ConnectionError)")
        assert password not in shown and "alice:***@" in shown, shown
        assert shown.startswith("error: no store at ") and shown.endswith(" (ConnectionError)")


@pytest.mark.parametrize("password", ["pl4nted-pw", "pl4nted/pw", "pl4/nted:pw@x/y"])
def test_the_error_line_and_hydra_files_never_hold_a_password_with_slashes(tmp_path, password):
    """The audit's command: a tracking URI with a password on the command line, to a server
    that does not answer. The error line and the run folder's ``.hydra`` files mask it,
    whether or not it holds a ``/``."""
    uri = f"http://alice:{password}@127.0.0.1:{free_port()}"
    folder = tmp_path / "run"
    res = one_thread_cli("lbo.train", "experiment=smoke", f"logger.tracking_uri={uri}",
                         f"hydra.run.dir={folder}", env={})
    one_line_error(res, "no MLflow tracking server answers at http://alice:***@127.0.0.1")
    assert password not in res.stdout + res.stderr
    written = snapshot(folder)
    assert {".hydra/config.yaml", ".hydra/hydra.yaml", ".hydra/overrides.yaml"} <= set(written)
    assert not [name for name, text in written.items() if password.encode() in text]
    assert b"alice:***@" in written[".hydra/overrides.yaml"]


# --- item 9: a damaged SQLite tracking store ----------------------------------------------------


def test_a_damaged_tracking_store_is_one_line_naming_it(tmp_path, smoke_data):
    """A store overwritten with bytes that are no database: lbo.train and lbo.observe with a
    run id say so in one line, naming the file, and leave it as it was; following the advice
    (moving it aside) gives working commands again."""
    store = tmp_path / "mlflow.db"
    store.write_bytes(b"this is not an SQLite database\n" * 300)
    damaged = store.read_bytes()
    env = {"MLFLOW_TRACKING_URI": f"sqlite:///{store}"}
    run_id = "0123456789abcdef0123456789abcdef"
    observe = ("lbo.observe", f"observer={run_id}", f"input={EXAMPLE_LOG}",
               f"output={tmp_path / 'est.csv'}")
    train = ("lbo.train", "experiment=smoke", f"data.root={smoke_data.parent}",
             f"hydra.run.dir={tmp_path / 'run'}")
    for res in (one_thread_cli(*train, env=env), one_thread_cli(*observe, env=env)):
        one_line_error(res, f"MLFLOW_TRACKING_URI: the SQLite tracking store {store} is "
                            "damaged (file is not a database)",
                       f"mv {store} {store}.damaged")
        assert "Traceback" not in res.stderr and "sqlalchemy" not in res.stderr.lower()
    assert store.read_bytes() == damaged
    assert not (tmp_path / "run" / "checkpoints").exists()
    # the advice, followed: a new store (MLflow says it creates its tables); the run id is
    # then simply not found
    store.rename(tmp_path / "mlflow.db.damaged")
    # a process of its own, as the user's next command is: MLflow keeps the store it opened
    # at this URI (on the damaged file) for the life of a process
    res = one_thread_cli(*observe, env=env, process=True)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines()[-1].startswith(
        f"error: observer: MLflow run {run_id} not found in sqlite:///{store}")
