"""Runs that would collide or lie, stores and folders that cannot be used: one line each, and
nothing half-written."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from helpers import cli, one_line_error, store_client, train_cfg
from helpers.servers import free_port
from lbo.core.errors import LboError, TrainingDiverged
from lbo.core.runfolder import claim
from lbo.export import export
from lbo.models.net import WindowNet
from lbo.serve.observer import Observer
from lbo.train import train

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@contextlib.contextmanager
def tmpfs(folder: Path, options: str) -> None:
    """A real small or read-only file system at ``folder`` (root only; else skipped)."""
    folder.mkdir(parents=True, exist_ok=True)
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
                         capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({res.stderr.strip()[:120]}): needs root")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def runs_in(uri: str) -> list:
    client = store_client(uri)
    exp = client.get_experiment_by_name("lbo-smoke")
    return client.search_runs([exp.experiment_id]) if exp else []


# --- one run per folder -----------------------------------------------------------------------


def test_a_second_training_into_a_busy_folder_is_refused_and_writes_nothing(tmp_path,
                                                                             smoke_data):
    """A run holds its folder: another training given the same hydra.run.dir (as two started
    in one second once were) stops before it writes anything there."""
    folder = tmp_path / "run"
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    with claim(folder):  # a training that is running there, with its files
        for name, text in ((".hydra/config.yaml", "window: 40\n"), ("train.log", "epoch 1\n"),
                           ("checkpoints/best.ckpt", "weights")):
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_text(text)
        before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
        # another process: the folder's lock is held by a process, and this one holds it
        res = cli("lbo.train", "experiment=smoke", f"data.root={smoke_data.parent}",
                  f"hydra.run.dir={folder}", env={"MLFLOW_TRACKING_URI": uri}, process=True)
        after = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
        assert after == before
    one_line_error(res, f"run folder {folder}", "is in use by another run")
    assert runs_in(uri) == []


def test_train_holds_its_output_dir(tmp_path, smoke_data, tracking):
    cfg = train_cfg(tmp_path, smoke_data)
    code = ("import sys, time; from lbo.core.runfolder import claim\n"
            f"with claim({str(tmp_path / 'out')!r}):\n"
            "    print('held', flush=True); time.sleep(60)\n")
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(LboError, match="output folder .* is in use by another run"):
            train(cfg)
    finally:
        holder.kill()
        holder.wait()
    assert runs_in(tracking) == []
    assert not (tmp_path / "out" / "checkpoints").exists()


# --- training that diverges ---------------------------------------------------------------------


def test_a_diverged_training_says_so_and_keeps_no_nan_checkpoint(tmp_path, smoke_data, tracking):
    cfg = train_cfg(tmp_path, smoke_data, "optimizer.lr=1e300", "trainer.max_epochs=2",
                    "trainer.limit_train_batches=5")
    with pytest.raises(TrainingDiverged, match=r"training diverged: .* lower optimizer.lr") as e:
        train(cfg)
    assert "\n" not in str(e.value)
    assert [r.info.status for r in runs_in(tracking)] == ["FAILED"]
    for ckpt in (tmp_path / "out").rglob("*.ckpt"):  # none, or only finite weights
        state = torch.load(ckpt, weights_only=True)["state_dict"]
        assert all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point())
    assert not (tmp_path / "out" / "evaluation.csv").exists()


def test_a_model_whose_output_is_never_finite_is_not_told_to_lower_the_rate(
        tmp_path, smoke_data, tracking, monkeypatch):
    """A model whose output is NaN from its first batch, before any update, did not diverge:
    a smaller learning rate cannot help, and the one line says so."""
    from lbo.models.cnn import WindowCNN

    forward = WindowCNN.forward
    monkeypatch.setattr(WindowCNN, "forward", lambda self, x: forward(self, x) * float("nan"))
    cfg = train_cfg(tmp_path, smoke_data, "trainer.max_epochs=1", "trainer.limit_train_batches=2")
    with pytest.raises(TrainingDiverged, match=r"^training cannot start: val_loss was NaN or inf "
                       r"before any update \(the first training batch's loss too\): model 'cnn' "
                       r".*cannot help\)$") as e:
        train(cfg)
    assert "lower optimizer.lr" not in str(e.value) and "\n" not in str(e.value)
    assert not list((tmp_path / "out").rglob("*.ckpt"))


# --- export ---------------------------------------------------------------------------------


def _cnn() -> WindowNet:
    torch.manual_seed(0)
    return WindowNet("cnn", 20, "relative")


def test_export_refuses_nan_weights_and_writes_nothing(tmp_path):
    net = _cnn()
    with torch.no_grad():
        next(net.parameters()).fill_(float("nan"))
    with pytest.raises(LboError, match="weights hold NaN or inf"):
        export(Observer.from_net(net), tmp_path / "exports")
    assert not (tmp_path / "exports").exists() or not any((tmp_path / "exports").iterdir())


def test_export_is_valid_json_with_the_hashes_of_its_files_and_clears_killed_temps(tmp_path):
    import hashlib

    out = tmp_path / "exports"
    out.mkdir()
    stale = out / ".cnn-N20.onnx.k2j4.tmp"  # what a killed export leaves
    stale.write_bytes(b"half")
    paths = export(Observer.from_net(_cnn()), out)
    assert not stale.exists()
    meta = json.loads(paths["json"].read_text(), parse_constant=lambda c: pytest.fail(c))
    for kind in ("torchscript", "onnx"):
        digest = hashlib.sha256(paths[kind].read_bytes()).hexdigest()
        assert meta["sha256"][paths[kind].name] == digest
    assert sorted(p.name for p in out.iterdir()) == ["cnn-N20.json", "cnn-N20.onnx",
                                                      "cnn-N20.pt"]


def test_a_failed_export_replaces_none_of_the_three_files(tmp_path, monkeypatch):
    out = tmp_path / "exports"
    first = export(Observer.from_net(_cnn()), out)
    before = {k: p.read_bytes() for k, p in first.items()}
    torch.manual_seed(1)
    other = WindowNet("cnn", 20, "relative")

    def fail(self, data):  # the disk fills while the ONNX file is written
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", fail)
    with pytest.raises(LboError, match="cannot write .*No space left on device"):
        export(Observer.from_net(other), out)
    monkeypatch.undo()
    assert {k: p.read_bytes() for k, p in first.items()} == before
    assert sorted(p.name for p in out.iterdir()) == ["cnn-N20.json", "cnn-N20.onnx",
                                                      "cnn-N20.pt"]


# --- stores ---------------------------------------------------------------------------------


@pytest.mark.parametrize("uri, words", [
    ("foo://bar", ["MLFLOW_TRACKING_URI: 'foo://bar' is not a tracking store lbo can use"]),
    ("postgresql://alice:pw@127.0.0.1:{port}/mlflow",
     ["MLFLOW_TRACKING_URI: cannot open the tracking store postgresql://alice:***@127.0.0.1"]),
    ("sqlite:////nonexistent/lbo/mlflow.db", ["folder of the SQLite store", "does not exist"]),
])
def test_a_store_that_cannot_be_used_is_one_line_before_any_work(tmp_path, uri, words):
    uri = uri.format(port=free_port())
    res = cli("lbo.train", "experiment=smoke", f"hydra.run.dir={tmp_path / 'run'}",
              env={"MLFLOW_TRACKING_URI": uri})
    line = one_line_error(res, *words)
    assert ":pw@" not in line
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_a_sqlite_store_in_a_read_only_folder_is_one_line(tmp_path):
    with tmpfs(tmp_path / "ro", "ro,size=64k") as ro:
        res = cli("lbo.train", "experiment=smoke", f"hydra.run.dir={tmp_path / 'run'}",
                  env={"MLFLOW_TRACKING_URI": f"sqlite:///{ro / 'mlflow.db'}"})
    one_line_error(res, "cannot write the SQLite store", "read-only")


# --- output folders -------------------------------------------------------------------------


@pytest.fixture
def small_log(tmp_path, manoeuvre) -> Path:
    path = tmp_path / "log.csv"
    manoeuvre[["t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]].to_csv(path,
                                                                                   index=False)
    return path


def test_output_into_a_read_only_folder_is_one_line(tmp_path, small_log):
    with tmpfs(tmp_path / "ro", "ro,size=64k") as ro:
        res = cli("lbo.observe", "observer=ekf", f"input={small_log}",
                  f"output={ro / 'est.csv'}", cwd=tmp_path)
        assert list(ro.iterdir()) == []
    one_line_error(res, f"cannot write {ro / 'est.csv'}", "Read-only file system")


def test_output_onto_a_full_disk_is_one_line_and_leaves_nothing(tmp_path, small_log):
    with tmpfs(tmp_path / "full", "size=16k") as full:
        res = cli("lbo.observe", "observer=ekf", f"input={small_log}",
                  f"output={full / 'est.csv'}", cwd=tmp_path)
        left = list(full.iterdir())
    one_line_error(res, f"cannot write {full / 'est.csv'}", "No space left on device")
    assert left == []


def test_output_that_is_a_folder_is_one_line(tmp_path, small_log):
    (tmp_path / "est.csv").mkdir()
    res = cli("lbo.observe", "observer=ekf", f"input={small_log}",
              f"output={tmp_path / 'est.csv'}", cwd=tmp_path)
    one_line_error(res, "est.csv is a folder; give a file path")
    assert list((tmp_path / "est.csv").iterdir()) == []


def test_the_estimates_of_a_log_fit_in_the_small_disk(small_log):
    # the full-disk test above is only a test if the output is larger than its 16 KiB
    frame = pd.read_csv(small_log)
    assert len(frame) * 5 * 8 > 16 * 1024 and np.isfinite(frame["x_m"]).all()
