import json

import numpy as np
import onnxruntime as ort
import pandas as pd
import pytest
import torch

from helpers import cli, compose_cfg
from lbo.core.errors import LboError
from lbo.export import export, export_observer
from lbo.models.net import WindowNet
from lbo.serve.observer import Observer

# one torch thread, here and in the CLIs: see the one_torch_thread fixture in conftest.py
pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def checkpoint(smoke_cnn):
    """A smoke CNN (N=20): one short epoch."""
    return smoke_cnn["checkpoint"]


@pytest.fixture(scope="module")
def windows(smoke_data):
    """(B, 80, 5) raw windows of a simulated manoeuvre at alpha=3: real inputs, not noise."""
    test = pd.read_parquet(smoke_data / "test.parquet")
    frame = test[(test["traj"] == 2) & (test["alpha"] == 3.0)].sort_values("k")
    series = torch.tensor(frame[["x_m", "y_m", "psi_m", "V", "delta"]].to_numpy())
    return series.unfold(0, 80, 1).transpose(-1, -2)[::3].contiguous()


def compare(net, script, session, win):
    with torch.no_grad():
        ref = net(win).numpy()
        ts = script(win).numpy()
    onnx = session.run(None, {"window": win.numpy()})[0]
    assert ts.dtype == onnx.dtype == np.float64 and onnx.shape == ref.shape
    return np.abs(ts - ref).max(), np.abs(onnx - ref).max()


def test_export_cli_files_match_pytorch(tmp_path, checkpoint, windows):
    res = cli("lbo.export", f"observer={checkpoint}", "out_dir=exports", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    folder = tmp_path / "exports"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exports"]  # nothing else written
    assert sorted(p.name for p in folder.iterdir()) == ["cnn-N20.json", "cnn-N20.onnx",
                                                        "cnn-N20.pt"]
    meta = json.loads((folder / "cnn-N20.json").read_text())
    assert (meta["window"], meta["dt"], meta["features"]) == (20, 0.02, "relative")
    assert meta["input"]["columns"] == ["x_m", "y_m", "psi_m", "V", "delta"]
    assert meta["noise"]["name"] == "paper"
    # the control loop can check its inputs against what the observer was trained on
    assert meta["envelope"] == Observer.load(checkpoint).envelope.to_dict()
    assert meta["envelope"]["alpha"] == [1.0, 1.0]

    net = Observer.load(checkpoint).net
    script = torch.jit.load(str(folder / "cnn-N20.pt"))
    session = ort.InferenceSession(str(folder / "cnn-N20.onnx"),
                                   providers=["CPUExecutionProvider"])
    win = windows[:, -20:]
    for batch in (win[:1], win):  # one window as in the loop, and a batch
        ts_diff, onnx_diff = compare(net, script, session, batch)
        assert ts_diff < 1e-5 and onnx_diff < 1e-5
    # the trained observer, not a fresh one: these would differ
    assert not torch.allclose(net(win[:4]), WindowNet("cnn", 20)(win[:4]))


def test_lstm_exports_for_any_batch(tmp_path, windows):
    torch.manual_seed(0)
    # N = 20, the paper's shortest: the dynamo exporter unrolls the LSTM's steps (24 s at 80)
    net = WindowNet("lstm", 20)
    net.set_normalisation([0.0, 0.0, 0.0, 10.0, 0.0], [1.0, 1.0, 0.02, 5.0, 0.1],
                          [0.0, 0.0, 0.0], [0.5, 0.5, 0.01])
    paths = export(Observer.from_net(net), tmp_path)
    assert paths["onnx"].name == "lstm-N20.onnx"
    script = torch.jit.load(str(paths["torchscript"]))
    session = ort.InferenceSession(str(paths["onnx"]), providers=["CPUExecutionProvider"])
    win = windows[:, -20:]
    for batch in (win[:1], win[:7], win):
        ts_diff, onnx_diff = compare(net.eval(), script, session, batch)
        assert ts_diff < 1e-5 and onnx_diff < 1e-5


@pytest.mark.parametrize("engine", ["torchscript", "onnx"])
def test_engines_step_like_pytorch(checkpoint, smoke_data, engine):
    test = pd.read_parquet(smoke_data / "test.parquet")
    frame = test[(test["traj"] == 0) & (test["alpha"] == 6.0)].sort_values("k").iloc[:120]
    m, u = frame[["x_m", "y_m", "psi_m"]].to_numpy(), frame[["V", "delta"]].to_numpy()
    ref, valid = Observer.load(checkpoint).run(m, u)
    obs = Observer.load(checkpoint, engine=engine)
    assert obs.engine == engine
    streamed = np.array([obs.step(a, b).state for a, b in zip(m, u)])
    assert np.abs(streamed - ref).max() < 1e-5
    np.testing.assert_array_equal(obs.run(m, u)[1], valid)


@pytest.mark.parametrize("overrides, message", [
    (["observer=ekf"], "export needs a learned observer"),
    ([], "observer: give a checkpoint path"),
    (["observer=CKPT", "register=lbo"], "register needs observer=<MLflow run id>"),
    (["observer=CKPT", "features=absolute"], "trained with features=relative"),
    ([f"observer={'a' * 32}", "alias=champion"],
     "^alias names a registered model's version: give register=<model name> beside it$"),
    ([f"observer={'a' * 32}", "register=lbo", "alias=latest"],
     r"^alias: expected letters, digits, _ and - \(not 'latest' nor v<digits>, which name "
     r"versions\), got 'latest'$"),
])
def test_export_refusals(tmp_path, checkpoint, overrides, message):
    overrides = [o.replace("CKPT", str(checkpoint)) for o in overrides]
    with pytest.raises(LboError, match=message):
        export_observer(compose_cfg("export", [*overrides, f"out_dir={tmp_path / 'x'}"]))
    assert not (tmp_path / "x").exists()


def test_onnx_comes_from_the_dynamo_exporter_but_a_filters_window(capfd):
    """The CNN's window and the recursive step by the dynamo exporter, the window filter's
    window (its N steps unrolled) by the TorchScript-based one, which names its nodes by
    module scope (``/net/...``); neither says anything on the way (no warning, no exporter
    note on stderr)."""
    import warnings

    import onnx

    from lbo.models.recursive import RecursiveFilter
    from lbo.serve.engines import onnx_bytes, recursive_onnx_bytes

    torch.manual_seed(0)
    filt = WindowNet("filternet", 10, features="frame", fixes=True)
    made = {}
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        made["cnn"] = onnx_bytes(WindowNet("cnn", 20))
        made["step"] = recursive_onnx_bytes(RecursiveFilter(filt.net))
        made["window filter"] = onnx_bytes(filt)
    names = {k: [n.name for n in onnx.load_from_string(b).graph.node] for k, b in made.items()}
    assert not any(n.startswith("/") for n in names["cnn"] + names["step"])
    assert any(n.startswith("/") for n in names["window filter"])
    assert [str(w.message) for w in said] == []
    assert capfd.readouterr().err == ""
