"""Plug-ins (issue 37): parts found by name among the installed packages' entry points, lbo's
own by the same path; the example package (examples/plugin, installed by make install): its
model trained, tuned, evaluated, observed, streamed and exported as a built-in model is, its
classical filter observed, streamed and scored as lbo's are; checkpoints that name a part
refused in one line when it is missing, and never importing what they name."""

from __future__ import annotations

import re
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from helpers.commands import cli, one_line_error
from lbo.core import plugins
from lbo.core.errors import LboError
from lbo.models import build_model, model_class, model_names
from lbo.models.checkpoint import read_checkpoint
from lbo.models.net import CHECKPOINT_FORMAT
from lbo.serve.observer import Observer

EXAMPLE = "my_gru"
SEARCHPATH = "hydra.searchpath=[pkg://lbo_plugin_example.conf]"


def _checkpoint(path: Path, name: object, provider: dict | None = None) -> Path:
    """A checkpoint's outer form naming model ``name`` (no weights: the name is refused
    before any are read)."""
    hp = {"format": CHECKPOINT_FORMAT, "features": "relative", "window": 20,
          "model": {"name": name}, "provider": provider or {}}
    torch.save({"hyper_parameters": hp, "state_dict": {}}, path)
    return path


@pytest.fixture(scope="module")
def drive() -> pd.DataFrame:
    from helpers import compose_cfg
    from lbo.simulate import simulate

    return simulate(compose_cfg("simulate", ["manoeuvre=free_drive", "duration=20", "seed=5"]))


@pytest.fixture
def planted(tmp_path, monkeypatch):
    """A module on the import path that writes a file if it is ever imported."""
    folder = tmp_path / "path"
    folder.mkdir()
    marker = tmp_path / "imported.txt"
    (folder / "planted_evil.py").write_text(
        f"from pathlib import Path\nPath({str(marker)!r}).write_text('imported')\n"
        "class Evil:\n    pass\n")
    monkeypatch.syspath_prepend(str(folder))
    monkeypatch.setenv("PYTHONPATH", str(folder))
    return marker


@pytest.fixture
def registered(tmp_path, monkeypatch):
    """Register entry points from a distribution planted on the import path (as pip leaves
    one), for this test only: ``registered({"name": "mod:Cls"}, group="lbo.models")``.
    ``dist`` names the distribution; ``last`` puts its folder after the installed packages'
    on ``sys.path`` (found after them) instead of before. Each call plants a folder of its
    own, so one distribution planted twice is found twice, as through two path entries."""
    folders = iter(range(1000))
    monkeypatch.setattr(plugins, "_warned", set(), raising=False)  # each test its warnings

    def plant(points: dict[str, str], group: str = "lbo.models", dist: str = "planted-plugin",
              last: bool = False) -> None:
        site = tmp_path / f"site{next(folders)}"
        info = site / f"{dist.replace('-', '_')}-0.1.dist-info"
        info.mkdir(parents=True)
        (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
        (info / "entry_points.txt").write_text(
            f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in points.items()))
        if last:
            monkeypatch.setattr(sys, "path", [*sys.path, str(site)])
        else:
            monkeypatch.syspath_prepend(str(site))
        plugins._entry_points.cache_clear()

    yield plant
    plugins._entry_points.cache_clear()


def test_lbo_registers_its_own_models_as_a_plug_in_would():
    names = model_names()
    assert names[:5] == ("cnn", "lstm", "filternet", "kalmannet", "split_kalmannet")
    assert EXAMPLE in names  # the example package, installed beside lbo by make install
    assert plugins.provider("model", "cnn")["package"] == "lbo"
    assert plugins.provider("model", EXAMPLE) == {"package": "lbo-plugin-example",
                                                  "version": "0.1.0"}
    assert type(build_model(EXAMPLE, 20, hidden=8)).__name__ == "WindowGRU"


def test_a_plug_ins_bad_settings_and_bad_names_are_one_line_errors():
    with pytest.raises(LboError, match=r"^model: model 'my_gru' refused its settings "
                                       r"\(hidden=0\): hidden and layers must be"):
        build_model(EXAMPLE, 20, hidden=0)
    with pytest.raises(LboError, match=r"^model.my_width: not a parameter of model 'my_gru'; "
                                       r"accepted: in_features, hidden, layers$"):
        build_model(EXAMPLE, 20, my_width=3)
    with pytest.raises(LboError, match=r"^plug-in kind 'truths': expected one of model, "
                                       r"observer, truth$"):
        plugins.names("truths")


def test_a_registered_part_that_fails_to_import_or_is_no_module_says_so(registered, tmp_path,
                                                                       monkeypatch):
    mod = tmp_path / "mods"
    mod.mkdir()
    (mod / "half_done.py").write_text("import not_a_module_anywhere\n")
    (mod / "not_a_net.py").write_text("class Plain:\n    pass\n")
    monkeypatch.syspath_prepend(str(mod))
    registered({"half_done": "half_done:Net", "not_a_net": "not_a_net:Plain"})
    assert "half_done" in model_names()
    with pytest.raises(LboError, match=r"^model.name: model 'half_done' is registered "
                                       r"\(half_done:Net\) but does not import: "
                                       r"ModuleNotFoundError"):
        model_class("half_done")
    with pytest.raises(LboError, match=r"^model.name: model 'not_a_net' is registered as "
                                       r".*Plain.*, not a torch.nn.Module class$"):
        build_model("not_a_net", 20)


def test_a_plug_in_that_does_not_export_says_so_in_one_line(registered, tmp_path,
                                                          monkeypatch):
    """ONNX has no modified Bessel function: a model using one runs in PyTorch and is refused
    by the ONNX engine (export, engine=onnx) in one line."""
    from lbo.models.net import WindowNet
    from lbo.serve.engines import onnx_bytes, trace

    mod = tmp_path / "mods"
    mod.mkdir()
    (mod / "bessel_net.py").write_text(textwrap.dedent("""
        import torch
        from torch import nn

        class BesselNet(nn.Module):
            def __init__(self, window, in_features=5):
                super().__init__()
                self.head = nn.Linear(in_features, 3)

            def forward(self, x):
                return self.head(torch.special.i0(x)).mean(1)
        """))
    monkeypatch.syspath_prepend(str(mod))
    registered({"bessel": "bessel_net:BesselNet"})
    net = WindowNet("bessel", 20).eval()
    windows = torch.randn(4, 20, 5, dtype=torch.float64)
    assert torch.isfinite(net(windows)).all()
    torch.testing.assert_close(trace(net)(windows), net(windows))
    with pytest.raises(LboError, match=r"^engine: model BesselNet does not export to ONNX "
                                       r"\(DispatchError: No ONNX function found for .*i0.*\); "
                                       r"it still runs with engine=torch$"):
        onnx_bytes(net)


def test_a_checkpoint_whose_model_is_not_installed_names_the_package(tmp_path):
    path = _checkpoint(tmp_path / "absent.ckpt", "absent_gru",
                       {"package": "lbo-absent-plugin", "version": "1.2"})
    with pytest.raises(LboError) as err:
        read_checkpoint(path)
    assert str(err.value) == (
        f"checkpoint {path}: model.name: model 'absent_gru' is not installed (it was provided "
        f"by lbo-absent-plugin 1.2: pip install lbo-absent-plugin); installed: "
        f"{', '.join(model_names())}")
    # the command a user types says the same, in one line
    res = cli("lbo.export", f"observer={path}", f"out_dir={tmp_path / 'exp'}", cwd=tmp_path)
    one_line_error(res, "'absent_gru' is not installed", "pip install lbo-absent-plugin")
    assert not (tmp_path / "exp").exists()


@pytest.mark.parametrize("name", ["planted_evil", "planted_evil:Evil", "planted_evil.Evil",
                                  {"_target_": "planted_evil.Evil"}])
def test_a_checkpoint_never_imports_a_module_it_names(planted, tmp_path, name):
    path = _checkpoint(tmp_path / "planted.ckpt", name, {"package": "planted_evil"})
    with pytest.raises(LboError, match=r"^checkpoint .*: model.name: "):
        Observer.load(str(path))
    res = cli("lbo.export", f"observer={path}", f"out_dir={tmp_path / 'exp'}", cwd=tmp_path)
    one_line_error(res, "model")
    assert "planted_evil" not in sys.modules
    assert not planted.exists()
    assert not (tmp_path / "exp").exists()


@pytest.mark.parametrize("provider, hint", [
    ({"package": "evil; rm -rf ~", "version": "1.2"},
     "the provider its file records, 'evil; rm -rf ~', is not a package name; install the "
     "package that registers it under the entry-point group lbo.models"),
    ({"package": "$(touch pwned)\nx"},
     "the provider its file records, '$(touch pwned)\\nx', is not a package name; install "
     "the package that registers it under the entry-point group lbo.models"),
    ({"package": "lbo-absent-plugin", "version": "1.2 && curl x"},
     "it was provided by lbo-absent-plugin: pip install lbo-absent-plugin"),
])
def test_a_checkpoints_recorded_provider_is_data_not_a_command(tmp_path, provider, hint):
    """The provider a checkpoint records is read from a file: it is put in ``pip install``
    advice only if it is a distribution's name (PEP 508), quoted, and its version only if it
    is one; any other gets no advice, shown as a Python literal in the one line."""
    path = _checkpoint(tmp_path / "odd.ckpt", "absent_gru", provider)
    with pytest.raises(LboError) as err:
        read_checkpoint(path)
    assert str(err.value) == (f"checkpoint {path}: model.name: model 'absent_gru' is not "
                              f"installed ({hint}); installed: {', '.join(model_names())}")


# ----------------------------------------------------------- one name, two distributions


@pytest.mark.parametrize("last", [False, True], ids=["found-first", "found-last"])
@pytest.mark.parametrize("kind, own, field", [("model", "cnn", "model.name"),
                                              ("observer", "ekf", "observer"),
                                              ("truth", "kinematic", "car.name")])
def test_lbos_own_name_registered_by_another_package_stays_lbos_and_says_so(
        registered, planted, capsys, kind, own, field, last):
    """Whichever of the two is found first, lbo's own name is lbo's: the other package's
    entry point is ignored (its module never imported) and named once, in one line."""
    group = plugins.GROUPS[kind]
    lbos = plugins.load(kind, own, field)
    registered({own: "planted_evil:Evil"}, group=group, last=last)
    assert plugins.load(kind, own, field) is lbos
    assert plugins.load(kind, own, field) is lbos  # said once a process
    assert plugins.provider(kind, own)["package"] == "lbo"
    assert plugins.names(kind).count(own) == 1
    assert capsys.readouterr().err.splitlines() == [
        f"warning: {field}: {kind} '{own}' is lbo's own; the entry point of planted-plugin 0.1 "
        f"(planted_evil:Evil) registered under that name in {group} is ignored (lbo's own "
        "names always belong to lbo; rename it there)"]
    assert "planted_evil" not in sys.modules and not planted.exists()


@pytest.mark.parametrize("kind, field", [("model", "model.name"), ("observer", "observer"),
                                         ("truth", "car.name")])
def test_a_name_two_packages_register_is_refused_naming_both_when_used(
        registered, planted, kind, field):
    """Neither wins by the order of a directory listing: using the name is one line naming
    both packages, nothing of either imported; the other names load as before."""
    group = plugins.GROUPS[kind]
    registered({"twin": "planted_evil:Evil"}, group=group, dist="plugin-a")
    registered({"twin": "planted_evil:Other"}, group=group, dist="plugin-b", last=True)
    assert plugins.names(kind).count("twin") == 1
    with pytest.raises(LboError) as err:
        plugins.load(kind, "twin", field)
    assert str(err.value) == (
        f"{field}: {kind} 'twin' is registered by 2 packages, plugin-a 0.1 (planted_evil:Evil)"
        f" and plugin-b 0.1 (planted_evil:Other), under the entry-point group {group}; "
        "uninstall all but one (none of them was imported)")
    with pytest.raises(LboError, match=rf"^{field}: {kind} 'twin' is registered by 2 "):
        plugins.provider(kind, "twin")  # what a checkpoint would record: the same rule
    unrelated = {"model": EXAMPLE, "observer": "my_blend", "truth": "linear_car"}[kind]
    assert plugins.load(kind, unrelated, field).__name__ in ("WindowGRU", "BlendFilter",
                                                             "LinearCar")
    assert plugins.load(kind, plugins.OWN[kind][0], field) is not None
    assert "planted_evil" not in sys.modules and not planted.exists()


def test_one_distribution_found_twice_is_no_clash(registered, tmp_path, monkeypatch, capsys):
    """An editable install seen through two ``sys.path`` entries registers its names once."""
    mod = tmp_path / "mods"
    mod.mkdir()
    (mod / "solo_net.py").write_text("from torch import nn\n\nclass Solo(nn.Module):\n"
                                     "    def __init__(self, window):\n"
                                     "        super().__init__()\n")
    monkeypatch.syspath_prepend(str(mod))
    registered({"solo": "solo_net:Solo", "cnn": "solo_net:Solo"}, dist="twice-found")
    registered({"solo": "solo_net:Solo", "cnn": "solo_net:Solo"}, dist="twice_found", last=True)
    assert model_class("solo").__name__ == "Solo"
    assert plugins.provider("model", "solo") == {"package": "twice-found", "version": "0.1"}
    assert model_class("cnn").__name__ == "WindowCNN"
    assert capsys.readouterr().err.count("warning: ") == 1  # its cnn named once, not twice


# ------------------------------------------------------- the contract, on one batch first


_BROKEN = {
    "flat": ("class Net(nn.Module):\n"
             "    def __init__(self, window, in_features=5):\n"
             "        super().__init__()\n"
             "        self.head = nn.Linear(in_features, 2)\n\n"
             "    def forward(self, x):  # (B, N, C) -> (B, 2): one state short\n"
             "        return self.head(x).mean(1)\n",
             r"model: model 'flat' gives an output of shape \(128, 2\) on a batch of windows "
             r"\(128, 20, 5\); expected \(128, 3\) \(the state x, y, psi of each window; "
             r"docs/plugins.md\)"),
    "wide": ("class Net(nn.Module):\n"
             "    def __init__(self, window, in_features=5):\n"
             "        super().__init__()\n"
             "        self.head = nn.Linear(7, 3)  # reads 7 features, is given 5\n\n"
             "    def forward(self, x):\n"
             "        return self.head(x[:, -1])\n",
             r"model: model 'wide' fails on a batch of windows \(128, 20, 5\) \(RuntimeError: "
             r"mat1 and mat2 shapes cannot be multiplied [^\n]*\); expected an output of shape "
             r"\(128, 3\) \(docs/plugins.md\)"),
}


def _plug_in_cfg(tmp_path: Path, name: str, command: str = "train"):
    """A smoke training (or tuning) config of plug-in model ``name``, with the settings every
    model has only; its data and output folders under ``tmp_path``."""
    from omegaconf import open_dict

    from helpers import compose_cfg
    from lbo.core.cli import MODEL_SHORT

    cfg = compose_cfg(command, ["experiment=smoke", f"data.root={tmp_path / 'data'}",
                                f"output_dir={tmp_path / 'out'}"])
    with open_dict(cfg):
        cfg.model = {"name": name, **{k: cfg.model[k] for k in MODEL_SHORT}}
    return cfg


@pytest.mark.parametrize("name", list(_BROKEN))
def test_a_plug_in_breaking_the_output_contract_is_refused_before_any_run(
        registered, tmp_path, monkeypatch, tracking, name):
    """A model whose output is (B, 2), or that fails on the windows it is given, is refused
    on one batch of the training's shape, in one line naming the model and the shapes,
    by lbo.train and lbo.tune alike: no data set, output folder or MLflow store is made."""
    from lbo.train import train
    from lbo.tune import check_tune

    mod = tmp_path / "mods"
    mod.mkdir()
    (mod / f"{name}_net.py").write_text("from torch import nn\n\n\n" + _BROKEN[name][0])
    monkeypatch.syspath_prepend(str(mod))
    registered({name: f"{name}_net:Net"})
    for command, run in (("train", train), ("tune", check_tune)):
        with pytest.raises(LboError) as err:
            run(_plug_in_cfg(tmp_path, name, command))
        assert re.fullmatch(_BROKEN[name][1], str(err.value)), str(err.value)
    assert not any(p.exists() for p in (tmp_path / "out", tmp_path / "data",
                                        tmp_path / "mlflow.db"))


def test_tunes_training_line_keeps_the_studys_search_path(tmp_path):
    from lbo.tuning.handoff import train_command

    line = train_command(EXAMPLE, tmp_path / "tuned" / "my_gru.yaml",
                         ["pkg://lbo_plugin_example.conf"])
    assert line.endswith("'hydra.searchpath=[pkg://lbo_plugin_example.conf,"
                         f"file://{tmp_path.resolve()}]'")


@pytest.mark.slow
def test_the_example_plug_in_trains_tunes_evaluates_observes_streams_and_exports(
        tmp_path, smoke_data, one_torch_thread):
    tracking = f"logger.tracking_uri=sqlite:///{tmp_path / 'mlflow.db'}"
    data = f"data.root={smoke_data.parent}"
    res = cli("lbo.train", f"model={EXAMPLE}", SEARCHPATH, "experiment=smoke", data,
              f"output_dir={tmp_path / 'out'}", "trainer.max_epochs=1", tracking,
              f"hydra.run.dir={tmp_path / 'train'}", "model.hidden=8")
    assert res.returncode == 0, res.stderr[-3000:]
    ckpt = tmp_path / "out" / "checkpoints" / "best.ckpt"
    assert f"trained {EXAMPLE}-N20" in res.stdout
    net, hp = read_checkpoint(ckpt)
    assert hp["provider"] == {"package": "lbo-plugin-example", "version": "0.1.0"}
    assert hp["model"] == {"name": EXAMPLE, "hidden": 8, "layers": 1}

    res = cli("lbo.tune", f"hparams_search={EXAMPLE}", SEARCHPATH, "experiment=smoke", data,
              "trainer.limit_train_batches=3", "tune.n_trials=1",
              f"tune.storage=sqlite:///{tmp_path / 'optuna.db'}",
              f"tune.handoff={tmp_path / 'tuned' / 'my_gru.yaml'}", tracking,
              f"hydra.run.dir={tmp_path / 'tune'}")
    assert res.returncode == 0, res.stderr[-3000:]
    assert "model.hidden=" in res.stdout and "pkg://lbo_plugin_example.conf" in res.stdout

    res = cli("lbo.evaluate", "data=smoke", data, f"learned=[{ckpt}]",
              f"output_dir={tmp_path / 'eval'}", "observers=[ekf]",
              f"hydra.run.dir={tmp_path / 'evaluate'}", cwd=tmp_path,
              env={"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"})
    assert res.returncode == 0, res.stderr[-3000:]
    table = pd.read_csv(tmp_path / "eval" / "evaluation.csv")
    rows = table[table["observer"].str.startswith(EXAMPLE)]
    assert len(rows) > 0 and np.isfinite(rows["nrmse"]).all()

    log = tmp_path / "log.csv"
    assert cli("lbo.simulate", "manoeuvre=free_drive", "duration=4", f"output={log}",
               cwd=tmp_path).returncode == 0
    res = cli("lbo.observe", f"observer={ckpt}", f"input={log}", "output=est.csv",
              cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    batch = pd.read_csv(tmp_path / "est.csv")

    # streamed one sample at a time, it gives what the batch run gave
    frame = pd.read_csv(log)
    obs = Observer.load(str(ckpt))
    streamed = np.array([obs.step(m, u)[0] for m, u in zip(
        frame[["x_m", "y_m", "psi_m"]].to_numpy(), frame[["V", "delta"]].to_numpy())])
    valid = batch["valid"].to_numpy(bool)
    assert valid.sum() > 100
    np.testing.assert_allclose(streamed[valid], batch[["x", "y", "psi"]].to_numpy()[valid],
                               atol=1e-6)

    res = cli("lbo.export", f"observer={ckpt}", f"out_dir={tmp_path / 'exp'}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    scripted = torch.jit.load(str(tmp_path / "exp" / f"{EXAMPLE}-N20.pt"))
    windows = torch.as_tensor(np.lib.stride_tricks.sliding_window_view(
        frame[["x_m", "y_m", "psi_m", "V", "delta"]].to_numpy(), 20, axis=0)
        .transpose(0, 2, 1)[:8].copy())
    torch.testing.assert_close(scripted(windows), net(windows))
    assert (tmp_path / "exp" / f"{EXAMPLE}-N20.onnx").stat().st_size > 0



def test_lbo_registers_its_own_classical_observers_as_a_plug_in_would():
    from lbo.filters import classical
    from lbo.filters.gyro import GyroStepper
    from lbo.filters.kalman import AdaptiveStepper, KalmanStepper
    from lbo.filters.unscented import UnscentedStepper

    assert plugins.names("observer")[:4] == ("ekf", "adaptive", "ukf", "gyro")
    assert [plugins.load("observer", n, "observer") for n in plugins.OWN["observer"]] == [
        KalmanStepper, AdaptiveStepper, UnscentedStepper, GyroStepper]
    assert classical.on_logs() == (*classical.ON_LOGS, "my_blend")


def test_a_plug_in_observer_runs_batch_and_stream_alike_and_filters(drive):
    """The example's constant-gain filter, through Observer: step by step as in one batch
    run, every estimate finite, and its position closer to the truth than the raw fixes."""
    m = drive[["x_m", "y_m", "psi_m"]].to_numpy()
    u = drive[["V", "delta"]].to_numpy()
    z = drive[["x", "y", "psi"]].to_numpy()
    est, valid = Observer.load("my_blend").run(m, u)
    assert valid.all() and np.isfinite(est).all()
    obs = Observer.load("my_blend")
    streamed = np.array([obs.step(mk, uk)[0] for mk, uk in zip(m, u)])
    np.testing.assert_allclose(streamed, est, atol=1e-9)
    raw = np.sqrt(np.mean((m[:, :2] - z[:, :2]) ** 2))
    assert np.sqrt(np.mean((est[:, :2] - z[:, :2]) ** 2)) < 0.8 * raw
    with pytest.raises(LboError, match=r"^my_blend: a plug-in's observer has no smoother"):
        Observer.load("my_blend").run(m, u, smooth=True)


def test_a_plug_in_observer_that_fails_to_start_says_so(registered, tmp_path, monkeypatch):
    mod = tmp_path / "mods"
    mod.mkdir()
    (mod / "picky.py").write_text("class Picky:\n    def __init__(self, m0, vehicle, Q, R):\n"
                                  "        raise ValueError('needs a heading at its start')\n")
    monkeypatch.syspath_prepend(str(mod))
    registered({"picky": "picky:Picky"}, group="lbo.observers")
    with pytest.raises(LboError, match=r"^observer 'picky' failed to start \(ValueError: needs "
                                       r"a heading at its start\)$"):
        Observer.load("picky").run(np.zeros((3, 3)), np.full((3, 2), 0.1))
    with pytest.raises(LboError, match=r"^observer: 'nobody' is not a checkpoint file, .*nor "
                                       r"one of ekf, oracle, adaptive, ukf, gyro, my_blend, "
                                       r"picky$"):
        Observer.load("nobody")


def test_a_plug_in_observer_is_observed_and_scored_on_the_test_grid(tmp_path, smoke_data,
                                                                    drive):
    res = cli("lbo.evaluate", "data=smoke", f"data.root={smoke_data.parent}",
              "observers=[ekf,my_blend]", f"output_dir={tmp_path / 'eval'}",
              f"hydra.run.dir={tmp_path / 'evaluate'}", cwd=tmp_path,
              env={"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"})
    assert res.returncode == 0, res.stderr[-3000:]
    table = pd.read_csv(tmp_path / "eval" / "evaluation.csv")
    rows = table[table["observer"] == "my_blend"]
    assert len(rows) == table["alpha"].nunique() and np.isfinite(rows["nrmse"]).all()
    drive.to_csv(tmp_path / "log.csv", index=False)
    res = cli("lbo.observe", "observer=my_blend", "input=log.csv", "output=est.csv",
              cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert pd.read_csv(tmp_path / "est.csv")["valid"].all()


# --------------------------------------------------------------------------- truth models


def test_lbo_registers_its_own_truth_models_as_a_plug_in_would():
    from lbo.sim.dynamic import SingleTrack
    from lbo.sim.truth import Car, Kinematic

    assert plugins.names("truth")[:2] == ("kinematic", "dynamic")
    assert "linear_car" in plugins.names("truth")  # the example's, installed by make install
    assert [plugins.load("truth", n, "car.name") for n in plugins.OWN["truth"]] == [
        Kinematic, SingleTrack]
    assert isinstance(SingleTrack(), Car)


def test_a_plug_in_truth_drives_the_simulator_and_the_ekf_told_the_car(tmp_path):
    """The example's car with linear tyres, named in a config found by the search path: a
    simulated manoeuvre is drawn from it (its rear axle slips, as lbo's car's does), and the
    EKF told the car (``oracle_dynamic``) runs on it, closer to the truth in heading than the
    kinematic EKF told the noise (``oracle``), whose model the car breaks. Measured: psi RMSE
    3.2 mrad against 11.9."""
    from lbo.filters import classical
    from lbo.sim.noise import Noise
    from lbo.sim.truth import from_cfg, of_folder
    from lbo.sim.vehicle import Vehicle

    log = tmp_path / "log.csv"
    res = cli("lbo.simulate", "car=linear_car", "manoeuvre=double_lane_change",
              "alpha=1", f"output={log}", "hydra.searchpath=[pkg://lbo_plugin_example.conf]",
              cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    frame = pd.read_csv(log)
    truth = from_cfg({"name": "linear_car", "process_scale": 0.1}, None, Vehicle().wheelbase)
    assert type(truth.car).__name__ == "LinearCar" and truth.to_dict()["c_f"] == 80_000.0
    m = frame[["x_m", "y_m", "psi_m"]].to_numpy()[None]
    u = frame[["V", "delta"]].to_numpy()[None]
    z = frame[["x", "y", "psi"]].to_numpy()
    noise = Noise.preset("paper")

    def heading(name: str) -> float:
        est = classical.estimate(name, m, u, Vehicle(), noise, truth=truth).mean[0]
        return float(np.sqrt(np.mean(np.angle(np.exp(1j * (est[:, 2] - z[:, 2]))) ** 2)))

    told, kinematic = heading("oracle_dynamic"), heading("oracle")
    assert np.isfinite(told) and told < 0.8 * kinematic, (told, kinematic)
    # a data set drawn from it records it by name and fields, and reads it back through the
    # entry points
    res = cli("lbo.datagen", "data=smoke", "car=linear_car", f"data.root={tmp_path / 'd'}",
              "hydra.searchpath=[pkg://lbo_plugin_example.conf]", f"hydra.run.dir={tmp_path}",
              cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    (folder,) = [f for f in (tmp_path / "d").iterdir() if f.is_dir()]
    assert of_folder(folder, Vehicle().wheelbase) == truth


def test_a_truth_model_that_is_not_installed_or_breaks_the_contract_is_one_line(
        registered, planted, tmp_path, monkeypatch):
    """A name no package registers is refused before anything is imported (a planted module
    that would write a file is never imported), a registered class that is not a car, or
    one without the contract's methods, each in one line; so is a plug-in's own refusal of
    its settings."""
    from lbo.sim.truth import from_cfg

    for name in ("planted_evil", "planted_evil:Evil"):
        with pytest.raises(LboError, match=r"^car.name: (truth 'planted_evil' is not "
                                           r"installed|expected the name of a registered)"):
            from_cfg({"name": name}, None, 2.7)
    assert not planted.exists()
    mod = tmp_path / "mods"
    mod.mkdir()
    (mod / "cars.py").write_text(textwrap.dedent("""\
        from dataclasses import dataclass

        @dataclass(frozen=True)
        class Cart:
            wheelbase: float = 2.7

        class Plain:
            pass
        """))
    monkeypatch.syspath_prepend(str(mod))
    registered({"cart": "cars:Cart", "plain": "cars:Plain"}, group="lbo.truths")
    with pytest.raises(LboError, match=r"^car.name: truth model 'cart' lacks "
                                       r"understeer_gradient, start, step, rear_slip"):
        from_cfg({"name": "cart"}, None, 2.7)
    with pytest.raises(LboError, match=r"^car.name: truth model 'plain' is registered as .*"
                                       r"not a dataclass"):
        from_cfg({"name": "plain"}, None, 2.7)
    with pytest.raises(LboError, match=r"^car.mass: not a field of car=cart; accepted: "
                                       r"name, process_scale, lateral_sigma, wheelbase$"):
        from_cfg({"name": "cart", "mass": 1.0}, None, 2.7)
    with pytest.raises(LboError, match=r"^car: truth model 'linear_car' refused its "
                                       r"settings \(car.mass must be a number > 0"):
        from_cfg({"name": "linear_car", "mass": -1.0}, None, 2.7)
    with pytest.raises(LboError, match=r"^car.l_f \+ car.l_r must be the vehicle's "
                                       r"wheelbase \(2.5 m\), got 2.7"):
        from_cfg({"name": "linear_car"}, None, 2.5)
