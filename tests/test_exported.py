"""The robust observer's recursive form kept as ONNX graphs and run without torch
(lbo.serve.exported): engine=auto, lbo.observe's default."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from helpers import ROBUST_SMOKE, train_in_own_store
from lbo.core.errors import LboError
from lbo.models.checkpoint import read_checkpoint
from lbo.serve import exported
from lbo.serve.engines import TOLERANCE
from lbo.serve.observer import Observer
from lbo.sim.columns import WINDOW

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]

NO_TORCH = "import sys; sys.modules['torch'] = None  # any import of torch fails\n"
"""The first line of a script that proves it runs without torch."""


@pytest.fixture(scope="module")
def kept(robust_smoke, tmp_path_factory):
    """The robust observer's checkpoint, its graphs kept (exported: lbo's ONNX cache, a folder
    of this module, is empty), and in that cache too."""
    cache = tmp_path_factory.mktemp("cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("LBO_CACHE_DIR", str(cache))
        checkpoint = robust_smoke["out"]["checkpoint"]
        assert exported.find(checkpoint) is None
        folder = exported.keep(read_checkpoint(checkpoint)[0], checkpoint)
        assert folder == exported.folder(checkpoint)
        assert sorted(p.name for p in folder.iterdir()) == ["coast.onnx", "observer.json",
                                                            "step.onnx"]
        assert sorted(p.name.split("-")[0] for p in (cache / "onnx").glob("*.onnx")) == [
            "coast", "recursive"]  # beside the kept folder, onnx/observer-<key>/
        yield {"checkpoint": checkpoint, "cache": str(cache), "folder": folder}


@pytest.fixture
def cache(kept, monkeypatch):
    monkeypatch.setenv("LBO_CACHE_DIR", kept["cache"])
    return kept


@pytest.fixture(scope="module")
def log(manoeuvre):
    """A log whose fixes come at 10 Hz, then every 45 rows (44 rows without one: more than
    one coast of the window of 40 takes)."""
    frame = manoeuvre[list(WINDOW)].reset_index(drop=True).iloc[:600].copy()
    k = frame.index.to_numpy()
    frame.loc[(k < 300) & (k % 5 != 0) | (k >= 300) & (k % 45 != 0),
              ["x_m", "y_m", "psi_m"]] = np.nan
    frame.insert(0, "t", 0.02 * k)
    return frame


def _run(obs: Observer, frame) -> tuple[np.ndarray, ...]:
    found = obs.run(frame[["x_m", "y_m", "psi_m"]].to_numpy(), frame[["V", "delta"]].to_numpy())
    return found.state, found.valid, found.cov


def test_auto_runs_the_kept_graphs_without_torch_as_pytorch_runs_it(cache, log, tmp_path):
    ref, ok_ref, cov_ref = _run(Observer.load(cache["checkpoint"]), log)  # PyTorch
    assert ok_ref[300:].all()
    log.to_parquet(tmp_path / "log.parquet")
    script = NO_TORCH + (
        "import numpy as np, pandas as pd\n"
        "from lbo import Observer\n"
        f"obs = Observer.load({cache['checkpoint']!r}, engine='auto')\n"
        f"f = pd.read_parquet({str(tmp_path / 'log.parquet')!r})\n"
        "m, u = f[['x_m', 'y_m', 'psi_m']].to_numpy(), f[['V', 'delta']].to_numpy()\n"
        "found = obs.run(m, u); est, ok, cov = found.state, found.valid, found.cov\n"
        "obs.reset()\n"
        "steps = np.array([obs.step(None if np.isnan(a).all() else a, b).state\n"
        "                  for a, b in zip(m, u)])\n"
        f"np.savez({str(tmp_path / 'out.npz')!r}, est=est, ok=ok, cov=cov, steps=steps,\n"
        "         engine=obs.engine, form=obs.form, cov_given=obs.gives_covariance)\n")
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=300)
    assert res.returncode == 0, res.stderr
    out = np.load(tmp_path / "out.npz")
    assert (str(out["engine"]), str(out["form"]), bool(out["cov_given"])) == (
        "onnx", "recursive", True)
    np.testing.assert_array_equal(out["ok"], ok_ref)
    np.testing.assert_allclose(out["est"][ok_ref], ref[ok_ref], rtol=0, atol=TOLERANCE)
    np.testing.assert_allclose(out["cov"][ok_ref], cov_ref[ok_ref], rtol=0, atol=TOLERANCE)
    np.testing.assert_allclose(out["steps"][ok_ref], out["est"][ok_ref], rtol=0, atol=1e-9)


def test_observe_takes_them_by_default_and_smooths_in_pytorch(cache, log, tmp_path):
    log.to_csv(tmp_path / "log.csv", index=False)
    runner = NO_TORCH + "import runpy; runpy.run_module('lbo.observe', run_name='__main__')"

    def observe(*args: str, torch_free: bool = True) -> subprocess.CompletedProcess:
        argv = ["-c", runner, *args] if torch_free else ["-m", "lbo.observe", *args]
        return subprocess.run([sys.executable, *argv], capture_output=True, text=True,
                              env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=300,
                              cwd=tmp_path)

    common = (f"observer={cache['checkpoint']}", f"input={tmp_path / 'log.csv'}")
    res = observe(*common, f"output={tmp_path / 'auto.csv'}")
    assert res.returncode == 0, res.stderr
    # a smoother needs the torch engine: auto takes it (and fails without torch)
    res = observe(*common, f"output={tmp_path / 'smooth.csv'}", "smooth=true")
    assert res.returncode != 0 and not (tmp_path / "smooth.csv").exists()
    assert observe(*common, f"output={tmp_path / 'smooth.csv'}", "smooth=true",
                   torch_free=False).returncode == 0
    res = observe(*common, f"output={tmp_path / 'torch.csv'}", "engine=torch",
                  torch_free=False)
    assert res.returncode == 0, res.stderr
    import pandas as pd

    auto, ref = pd.read_csv(tmp_path / "auto.csv"), pd.read_csv(tmp_path / "torch.csv")
    assert list(auto.columns) == list(ref.columns)
    valid = ref["valid"].to_numpy()
    for c in ("x", "y", "psi", "var_x", "var_y", "var_psi", "cov_xy"):
        np.testing.assert_allclose(auto[c][valid], ref[c][valid], rtol=0, atol=TOLERANCE)


def test_a_changed_checkpoint_or_a_half_kept_folder_runs_in_pytorch(cache, tmp_path):
    ckpt = torch.load(cache["checkpoint"], map_location="cpu", weights_only=True)
    ckpt["epoch"] = ckpt.get("epoch", 0) + 1  # other bytes, the same weights
    changed = tmp_path / "changed.ckpt"
    torch.save(ckpt, changed)
    assert exported.find(changed) is None
    assert Observer.load(changed, engine="auto").engine == "torch"
    # a copy of the same bytes elsewhere finds them
    (tmp_path / "copy.ckpt").write_bytes(open(cache["checkpoint"], "rb").read())
    assert Observer.load(tmp_path / "copy.ckpt", engine="auto").engine == "onnx"
    # a folder whose description is gone, or of another layout, is not read
    folder = exported.folder(tmp_path / "copy.ckpt")
    info = (folder / "observer.json").read_text()
    try:
        (folder / "observer.json").write_text(json.dumps({**json.loads(info), "format": 0}))
        assert exported.find(tmp_path / "copy.ckpt") is None
        (folder / "observer.json").unlink()
        assert exported.find(tmp_path / "copy.ckpt") is None
    finally:
        (folder / "observer.json").write_text(info)
    assert exported.find(tmp_path / "copy.ckpt") is not None


@pytest.fixture
def copy(cache, tmp_path):
    """A copy of the checkpoint (the same bytes: its graphs are the kept ones) whose kept
    folder this test may damage; the folder is restored afterwards, from what it held."""
    path = tmp_path / "copy.ckpt"
    path.write_bytes(open(cache["checkpoint"], "rb").read())
    folder = exported.folder(path)
    saved = {p.name: p.read_bytes() for p in folder.iterdir()}
    yield {"checkpoint": path, "folder": folder, "files": saved}
    exported.discard(folder)
    folder.mkdir()
    for name, data in saved.items():
        (folder / name).write_bytes(data)


def test_the_kept_folder_holds_no_hyperparameters_they_are_the_checkpoints(cache):
    """The vehicle, noise and envelope an observer is told come from the checkpoint itself,
    read without torch, equal to what PyTorch reads; the kept folder holds only the graphs,
    their digests and the net's flags."""
    info = json.loads((cache["folder"] / "observer.json").read_text())
    assert sorted(info) == ["coast_limit", "files", "format", "net", "state"]
    net, hp = exported.find(cache["checkpoint"])
    assert hp == read_checkpoint(cache["checkpoint"])[1]


def test_settings_written_into_the_kept_folder_are_not_read(copy, log):
    """Widening the envelope (or the vehicle, or the noise) in the kept ``observer.json``
    silenced the envelope check with engine=auto: they are read from the checkpoint."""
    ref = Observer.load(copy["checkpoint"], engine="torch")
    info = json.loads(copy["files"]["observer.json"])
    _, hp = read_checkpoint(copy["checkpoint"])
    meta = hp["meta"]
    forged = {**hp, "meta": {**meta, "envelope": {**meta["envelope"], "speed": [0, 1000]},
                             "vehicle": {**meta["vehicle"], "wheelbase": 9.0}}}
    (copy["folder"] / "observer.json").write_text(json.dumps({**info, "hparams": forged}))
    obs = Observer.load(copy["checkpoint"], engine="auto")
    assert obs.engine == "onnx"
    assert obs.envelope == ref.envelope and obs.vehicle == ref.vehicle
    fast = log.assign(V=39.0)
    m, u = fast[["x_m", "y_m", "psi_m"]].to_numpy(), fast[["V", "delta"]].to_numpy()
    with pytest.warns(UserWarning, match="outside the trained speed"):
        obs.run(m, u)


def test_the_bodys_error_is_read_from_the_checkpoint_and_a_bad_one_refused_as_torch_does(
        cache):
    """A kept folder's net carries the body's error its checkpoint's metadata holds (what its
    lateral states' variances are made of), as read_checkpoint's net does; a damaged one is
    refused in one line naming it, not taken for damaged graphs (which would be exported
    afresh)."""
    _, hp = read_checkpoint(cache["checkpoint"])
    where = exported.folder(cache["checkpoint"])
    assert exported._read(where, hp).lateral_error is None  # the robust observer has no body
    error = [[1e-4, 0.02], [1e-8, 0.0]]
    net = exported._read(where, {**hp, "meta": {**hp["meta"], "lateral_error": error}})
    np.testing.assert_array_equal(net.lateral_error, error)
    with pytest.raises(LboError, match=r"^the checkpoint of kept ONNX graphs .*: its stored "
                                       r"meta.lateral_error is not the body's error") as e:
        exported._read(where, {**hp, "meta": {**hp["meta"], "lateral_error": [[-1, 0], [0, 0]]}})
    assert not isinstance(e.value, exported.DamagedGraphs)


def _damage(copy, damage: str) -> None:
    folder = copy["folder"]
    if damage == "step cut short":
        (folder / "step.onnx").write_bytes(copy["files"]["step.onnx"][:1000])
    elif damage == "coast empty":
        (folder / "coast.onnx").write_bytes(b"")
    elif damage == "coast as step":
        (folder / "step.onnx").write_bytes(copy["files"]["coast.onnx"])
    else:  # the digest listed for a graph edited
        info = json.loads(copy["files"]["observer.json"])
        info["files"]["step.onnx"] = "0" * 64
        (folder / "observer.json").write_text(json.dumps(info))


def _exporting(*args) -> bytes:
    """In place of an exporter where lbo's ONNX cache holds the graph: fails the test."""
    raise AssertionError("exported again, though lbo's ONNX cache holds the graph")


@pytest.mark.parametrize("damage", ["step cut short", "coast empty", "coast as step",
                                    "digest edited"])
def test_a_damaged_kept_folder_is_said_and_runs_in_pytorch(copy, log, damage):
    """A graph cut short or emptied failed every later run with ONNX Runtime's traceback;
    one swapped for the other ran the wrong graph (NRMSE 7.26 for 1.75). Each fails the
    digest kept beside the graphs, as does a listed digest edited: ``auto`` says so in one
    warning, removes the folder and runs PyTorch, with PyTorch's numbers."""
    _damage(copy, damage)
    assert exported.find(copy["checkpoint"]) is None
    ref = _run(Observer.load(copy["checkpoint"], engine="torch"), log)
    with pytest.warns(exported.KeptGraphsWarning, match=r"^kept ONNX graphs .*; removed them, "
                      r"running it in PyTorch"):
        obs = Observer.load(copy["checkpoint"], engine="auto")
    assert obs.engine == "torch" and not copy["folder"].exists()
    for got, want in zip(_run(obs, log), ref):
        np.testing.assert_array_equal(got, want)


def test_engine_onnx_keeps_a_damaged_kept_folder_again_from_lbos_onnx_cache(copy, log,
                                                                           monkeypatch):
    """``engine=onnx`` on a folder that fails its check keeps the graphs again, from lbo's
    ONNX cache, which holds the graphs the folder was first kept with (``kept``: exported
    there, into an empty cache): the same bytes, no export; the next ``auto`` runs them, with
    PyTorch's numbers."""
    monkeypatch.setattr(exported, "recursive_onnx_bytes", _exporting)
    monkeypatch.setattr(exported, "_coast_bytes", _exporting)
    _damage(copy, "step cut short")
    with pytest.warns(exported.KeptGraphsWarning, match="keeping them again"):
        obs = Observer.load(copy["checkpoint"], engine="onnx")
    assert isinstance(obs.net, exported.ExportedNet)
    assert exported.find(copy["checkpoint"]) is not None
    for name in ("step.onnx", "coast.onnx"):
        assert (copy["folder"] / name).read_bytes() == copy["files"][name]
    obs = Observer.load(copy["checkpoint"], engine="auto")
    assert obs.engine == "onnx"
    est, ok, _ = _run(obs, log)
    ref, ok_ref, _ = _run(Observer.load(copy["checkpoint"], engine="torch"), log)
    np.testing.assert_array_equal(ok, ok_ref)
    np.testing.assert_allclose(est[ok], ref[ok], rtol=0, atol=TOLERANCE)


def test_lbo_export_of_the_kept_observer_exports_nothing_anew(cache, tmp_path, monkeypatch):
    """The graphs kept for a checkpoint are in lbo's ONNX cache: ``lbo.export`` of its observer
    writes the kept step (checked against PyTorch, as always) without exporting again."""
    import lbo.export as command

    monkeypatch.setattr(command, "recursive_onnx_bytes", _exporting)
    obs = Observer.load(cache["checkpoint"], engine="torch")
    assert obs.form == "recursive"
    paths = command.export(obs, tmp_path)
    assert paths["onnx"].read_bytes() == (cache["folder"] / "step.onnx").read_bytes()


def test_what_the_kept_graphs_refuse_is_said_in_one_line(cache, log):
    obs = Observer.load(cache["checkpoint"], engine="onnx")
    assert isinstance(obs.net, exported.ExportedNet)
    m, u = log[["x_m", "y_m", "psi_m"]].to_numpy(), log[["V", "delta"]].to_numpy()
    with pytest.raises(LboError, match=r"^smooth: .* engine=torch to smooth$"):
        obs.run(m, u, smooth=True)
    with pytest.raises(LboError, match=r"trained with features=frame, but features=relative"):
        Observer.load(cache["checkpoint"], engine="auto", features="relative")
    # another form, or another device, is PyTorch's
    assert Observer.load(cache["checkpoint"], engine="auto", form="window").engine == "torch"


def test_training_keeps_the_graphs_of_the_robust_observer_only(tmp_path, smoke_data,
                                                               monkeypatch, capsys):
    """``keep_onnx`` (true by default) keeps them after training the robust observer (the
    export itself: the fixture ``kept``); a CNN has none to keep, and ``keep_onnx=false``
    keeps none."""
    calls: list[str] = []
    for run in "abc":
        (tmp_path / run).mkdir()
    monkeypatch.setattr(exported, "keep", lambda net, path: calls.append(path) or tmp_path)
    _, out, _ = train_in_own_store(tmp_path / "a", smoke_data, *ROBUST_SMOKE, "keep_onnx=true",
                                   "trainer.limit_train_batches=2", "window=40",
                                   "batch_size=64")
    assert calls == [out["checkpoint"]]
    assert "keeping its recursive form as ONNX graphs" in capsys.readouterr().out
    train_in_own_store(tmp_path / "b", smoke_data, *ROBUST_SMOKE, "trainer.max_epochs=1",
                       "trainer.limit_train_batches=2", "window=40", "batch_size=64")
    train_in_own_store(tmp_path / "c", smoke_data, "experiment=smoke", "keep_onnx=true")
    assert calls == [out["checkpoint"]]


def test_keep_onnx_is_a_flag_checked_before_any_run(tmp_path, smoke_data):
    from helpers import train_cfg
    from lbo.train import check

    with pytest.raises(LboError, match=r"^keep_onnx must be true or false, got 'yes'$"):
        check(train_cfg(tmp_path, smoke_data, "keep_onnx=yes"))
    assert not (tmp_path / "out").exists()


def test_the_observe_benchmark_times_both_commands(cache):
    """``benchmarks/bench_observe.py``: the EKF's and the observer's commands, their medians
    and the ratio."""
    from lbo.core.paths import REPO_ROOT

    res = subprocess.run([sys.executable, str(REPO_ROOT / "benchmarks" / "bench_observe.py"),
                          cache["checkpoint"], "--repeats", "1"], capture_output=True,
                         text=True, env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=300)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    assert [line.split(":")[0] for line in lines] == ["ekf", cache["checkpoint"], "ratio"]
    ekf, learned = (float(line.split("median ")[1].split(" s")[0]) for line in lines[:2])
    ratio = float(lines[2].split("ratio: ")[1].split(" times")[0])
    assert ratio == pytest.approx(learned / ekf, abs=0.01)
    assert "engine=auto" in lines[2]


def test_the_exporters_notes_are_not_logged(caplog):
    """The dynamo exporter's optimiser logs a line per merged initializer (about 380 for the
    robust observer's coast): under Hydra's INFO logging they flooded ``lbo.train``'s end."""
    import logging

    from lbo.serve import engines

    with caplog.at_level(logging.INFO), engines._quiet():
        for name in ("onnx_ir.passes.common.initializer_deduplication", "onnxscript.optimizer",
                     "torch.onnx._internal.exporter"):
            logging.getLogger(name).info("a note")
    assert caplog.records == []
