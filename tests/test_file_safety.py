"""No lbo command writes, deletes or uploads a file outside the paths it was given or its own
run folder; files get the user's umask; a damaged or replaced data-set cache is never reused as
it is (issue 41, items 1, 2, 4, 5, 6 and 10)."""

from __future__ import annotations

import json
import os
import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import torch

from helpers import compose_cfg, train_in_own_store
from lbo.core.errors import LboError

pytestmark = pytest.mark.usefixtures("one_torch_thread")

LOG = ["t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]


def _observer():
    """A small untrained CNN observer: enough to export, nothing to train."""
    from lbo.models.net import WindowNet
    from lbo.serve.observer import Observer

    torch.manual_seed(0)
    return Observer.from_net(WindowNet("cnn", 20, "relative"))


def _files(folder: Path) -> set[str]:
    """Every file under ``folder``, relative to it."""
    return {str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()}


def _cache_copy(smoke_data: Path, tmp_path: Path) -> tuple[Path, Path]:
    """A private copy of the smoke data-set cache (the session's one stays intact): the data
    root and the set's folder, which a config with ``data.root=<root>`` reuses."""
    root = tmp_path / "data"
    folder = root / smoke_data.name
    shutil.copytree(smoke_data, folder)
    return root, folder


def _datagen(root: Path) -> str:
    from lbo.datagen import generate

    return generate(compose_cfg("datagen", ["data=smoke", f"data.root={root}"]))


# item 1: name=../../x wrote x.pt, x.onnx and x.json two folders above out_dir


@pytest.mark.parametrize("name", ["../../x", "sub/x", "..", "TMP/abs/x", ".hidden"])
def test_export_name_must_be_a_plain_file_stem(tmp_path, name):
    from lbo.export import export, export_observer

    name = name.replace("TMP", str(tmp_path))  # an absolute path, inside this test's folder
    out = tmp_path / "a" / "b" / "exports"
    with pytest.raises(LboError, match=r"^name must be a plain file stem .*, got "):
        export(_observer(), out, name=name)
    # the command checks it before it reads any checkpoint (this one does not exist)
    with pytest.raises(LboError, match=r"^name must be a plain file stem"):
        export_observer(compose_cfg("export", [f"observer={tmp_path / 'none.ckpt'}",
                                               f"name='{name}'", f"out_dir={out}"]))
    assert _files(tmp_path) == set()


def test_export_writes_a_plain_name_into_out_dir(tmp_path):
    from lbo.export import export

    paths = export(_observer(), tmp_path / "exports", name="cnn.v2")
    assert _files(tmp_path) == {"exports/cnn.v2.pt", "exports/cnn.v2.onnx",
                                "exports/cnn.v2.json"}
    assert paths["onnx"] == tmp_path / "exports" / "cnn.v2.onnx"


# item 2: lbo.export deleted every hidden *.tmp file in out_dir


def test_export_removes_only_the_temps_of_its_own_files(tmp_path):
    from lbo.export import export

    out = tmp_path / "exports"
    out.mkdir()
    theirs = [out / ".notes.txt.swp.tmp", out / ".download.abc123.tmp",  # other programs'
              out / ".cnn-N40.onnx.k2j4.lbo-tmp"]  # another export's, to another name
    for p in theirs:
        p.write_bytes(b"being written by someone else")
    ours = [out / ".cnn-N20.onnx.k2j4.lbo-tmp", out / ".cnn-N20.pt.x7.tmp"]  # killed exports'
    for p in ours:
        p.write_bytes(b"half")
    export(_observer(), out)
    assert all(p.read_bytes() == b"being written by someone else" for p in theirs)
    assert not any(p.exists() for p in ours)
    assert _files(out) == {"cnn-N20.pt", "cnn-N20.onnx", "cnn-N20.json"} | \
        {p.name for p in theirs}


# item 4: lbo.observe wrote its estimates over a cached data set


@pytest.mark.parametrize("field, path", [("output", "test.parquet"),
                                         ("output", "estimates.csv"),
                                         ("plot", "friction_circle.png")])
def test_observe_refuses_to_write_into_a_data_set_cache(tmp_path, smoke_data, manoeuvre, field,
                                                        path):
    from lbo.observe import observe

    _, folder = _cache_copy(smoke_data, tmp_path)
    log = tmp_path / "log.csv"
    manoeuvre[LOG].to_csv(log, index=False)
    before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    outputs = {"output": str(tmp_path / "estimates.csv"), field: str(folder / path)}
    with pytest.raises(LboError, match=rf"^{field}: .* is in the data-set cache .*; give a path "
                                       "outside that folder$"):
        observe(compose_cfg("observe", ["observer=ekf", f"input={log}",
                                        *(f"{k}={v}" for k, v in outputs.items())]))
    assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} == before
    # the advice, followed: a path outside the cache
    observe(compose_cfg("observe", ["observer=ekf", f"input={log}",
                                    f"output={tmp_path / 'out' / 'test.parquet'}",
                                    f"plot={tmp_path / 'out' / 'friction_circle.png'}"]))
    assert _files(tmp_path / "out") == {"test.parquet", "friction_circle.png"}


def test_simulate_refuses_to_write_into_a_data_set_cache(tmp_path, smoke_data):
    from lbo.simulate import write_logs

    _, folder = _cache_copy(smoke_data, tmp_path)
    before = (folder / "test.parquet").read_bytes()
    with pytest.raises(LboError, match=r"^output: .* is in the data-set cache"):
        write_logs(compose_cfg("simulate", ["manoeuvre=stop_and_go", "alpha=1",
                                            f"output={folder / 'test.parquet'}"]))
    assert (folder / "test.parquet").read_bytes() == before


def test_a_set_replaced_in_the_cache_is_said_and_generated_again(tmp_path, smoke_data, capsys):
    root, folder = _cache_copy(smoke_data, tmp_path)
    before = (folder / "test.parquet").read_bytes()
    # what an observer's estimates written over the test set look like
    pd.DataFrame({"t": [0.0, 0.02], "x": [0.0, 1.0], "y": [0.0, 0.0], "psi": [0.0, 0.0],
                  "valid": [True, True]}).to_parquet(folder / "test.parquet")
    _datagen(root)
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith(f"{folder / 'test.parquet'}: "))
    assert "replaced" in line and line.endswith("; generating it again")
    assert "generated data sets" in out  # not "reused cached"
    assert (folder / "test.parquet").read_bytes() == before


# item 5: lbo.evaluate logged every *.csv and *.png of output_dir to the run


def test_evaluate_uploads_only_the_files_it_wrote(tmp_path, smoke_data):
    import mlflow

    from lbo.evaluate import evaluate

    _, out, uri = train_in_own_store(tmp_path, smoke_data, "experiment=smoke",
                                     "trainer.max_epochs=1", "trainer.limit_train_batches=5")
    folder = tmp_path / "shared"
    folder.mkdir()
    (folder / "salaries.csv").write_text("name,salary\nalice,1\n")
    (folder / "holiday.png").write_bytes(b"\x89PNG not lbo's")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", uri)
        evaluate(compose_cfg("evaluate", ["data=smoke", f"data.root={smoke_data.parent}",
                                          f"output_dir={folder}", "observers=[ekf]",
                                          f"observer={out['run_id']}"]))
    client = mlflow.MlflowClient(uri)
    logged = {a.path for a in client.list_artifacts(out["run_id"], "evaluations/smoke")}
    assert logged == {"evaluations/smoke/evaluation.csv",
                      "evaluations/smoke/nrmse_classical.png"}


# item 6: outputs were chmod-ed to 0644 whatever the user's umask


@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o077, 0o600), (0o027, 0o640)])
def test_atomic_writes_take_the_users_umask(tmp_path, mask, mode):
    from lbo.core.atomic import write_text

    old = os.umask(mask)
    try:
        write_text(tmp_path / "a.txt", "x")
        write_text(tmp_path / "a.txt", "y")  # a replaced file too
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == mode


def test_a_private_umask_keeps_simulated_logs_estimates_and_run_records_private(tmp_path):
    def run(*args):
        res = subprocess.run([sys.executable, "-m", *args], cwd=tmp_path, capture_output=True,
                             text=True, preexec_fn=lambda: os.umask(0o077))
        assert res.returncode == 0, res.stderr[-2000:]

    run("lbo.simulate", "manoeuvre=stop_and_go", "alpha=1", "output=log.csv",
        "hydra.run.dir=run")
    run("lbo.observe", "observer=ekf", "input=log.csv", "output=est.parquet", "plot=true")
    written = ["log.csv", "est.parquet", "est.png", "run/.hydra/config.yaml",
               "run/.hydra/hydra.yaml", "run/.hydra/overrides.yaml"]
    modes = {f: oct(stat.S_IMODE((tmp_path / f).stat().st_mode)) for f in written}
    assert modes == {f: oct(0o600) for f in written}


# item 10: a cached set cut short under its final name was reused as it is


@pytest.mark.parametrize("recorded", [True, False], ids=["manifest-records-files",
                                                         "older-manifest"])
def test_a_set_cut_short_in_the_cache_is_said_and_generated_again(tmp_path, smoke_data, capsys,
                                                                  recorded):
    root, folder = _cache_copy(smoke_data, tmp_path)
    train = folder / "train.parquet"
    before = train.read_bytes()
    train.write_bytes(before[:len(before) // 2])  # a disk error, an interrupted copy
    if not recorded:  # a cache lbo wrote before it recorded its files' sizes and hashes
        manifest = json.loads((folder / "manifest.json").read_text())
        manifest.pop("files", None)
        (folder / "manifest.json").write_text(json.dumps(manifest))
    _datagen(root)
    out = capsys.readouterr().out
    assert f"{train}: " in out and "generating it again" in out
    assert train.read_bytes() == before
    files = json.loads((folder / "manifest.json").read_text())["files"]
    assert files["train.parquet"]["bytes"] == len(before)
    # training reads its sets through the same check: the next run reuses them as they are
    from lbo.learn.builders import prepare_data

    prepare_data(compose_cfg("train", ["experiment=smoke", f"data.root={root}"]))
    assert "generating" not in capsys.readouterr().out


def test_a_test_file_cut_short_is_one_line_naming_it(tmp_path, smoke_data):
    from lbo.evaluate import evaluate

    cut = tmp_path / "drive.parquet"
    data = (smoke_data / "test.parquet").read_bytes()
    cut.write_bytes(data[:len(data) // 3])
    one_line = rf"^{re.escape(str(cut))}: not a readable Parquet file \(cut short, or not " \
        r"Parquet: [^\n]*\)$"
    with pytest.raises(LboError, match=one_line):
        evaluate(compose_cfg("evaluate", ["data=smoke", f"test_file={cut}", "observers=[ekf]",
                                          f"output_dir={tmp_path / 'ev'}"]))
    assert not (tmp_path / "ev").exists()
