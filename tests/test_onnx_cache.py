"""ONNX exports of in-memory sessions kept between sessions (lbo.serve.onnx_cache)."""

import numpy as np
import pytest
import torch

from lbo.core.paths import cache_dir
from lbo.models.net import WindowNet
from lbo.serve import engines, onnx_cache
from lbo.serve.observer import Observer

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture
def own_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("LBO_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache" / "onnx"


def _cnn(seed: int = 0) -> WindowNet:
    torch.manual_seed(seed)
    return WindowNet("cnn", 20, "relative")


def _windows() -> np.ndarray:
    return np.random.default_rng(0).normal(size=(4, 20, 5)) * [1, 1, 0.1, 5, 0.05] + [0, 0, 0,
                                                                                      10, 0]


def _refuse(*args, **kwargs):
    raise AssertionError("exported again, though its export is kept")


def test_an_export_is_kept_and_the_next_session_reads_it(own_cache, monkeypatch):
    assert cache_dir() == own_cache.parent
    first = Observer.from_net(_cnn(), engine="onnx")
    (kept,) = own_cache.iterdir()
    assert kept.name.startswith("window-") and kept.suffix == ".onnx"
    monkeypatch.setattr(engines, "onnx_bytes", _refuse)
    again = Observer.from_net(_cnn(), engine="onnx")  # the same weights: read back
    win = _windows()
    np.testing.assert_array_equal(again._runner.predict(win), first._runner.predict(win))
    # other weights: another key, so an export of their own (refused here)
    with pytest.raises(AssertionError, match="exported again"):
        Observer.from_net(_cnn(seed=1), engine="onnx")


@pytest.mark.slow  # an export (3 s): the tests of 1 s or more are out of make test-fast
def test_lbo_export_writes_the_kept_export_of_an_observer_run_in_onnx_runtime(
        own_cache, monkeypatch, tmp_path):
    """An observer run with engine=onnx and then exported: lbo.export writes the kept graph
    (and checks it against PyTorch as it checks a new one) rather than tracing it again."""
    import lbo.export

    Observer.from_net(_cnn(), engine="onnx")
    (kept,) = own_cache.iterdir()
    monkeypatch.setattr(lbo.export, "onnx_bytes", _refuse)
    paths = lbo.export.export(Observer.from_net(_cnn()), tmp_path / "out")
    assert paths["onnx"].read_bytes() == kept.read_bytes()
    with pytest.raises(AssertionError, match="exported again"):  # other weights: traced
        lbo.export.export(Observer.from_net(_cnn(seed=1)), tmp_path / "other")


def test_the_key_follows_the_settings_beside_the_weights():
    """Nets of the same weights whose window or feature mode differ trace other graphs (a
    recursive step's ring of N steps): each has a key of its own."""
    from lbo.models.recursive import RecursiveFilter

    def net(window: int) -> WindowNet:
        torch.manual_seed(0)
        return WindowNet("filternet", window, "frame", fixes=True)

    assert onnx_cache.key(RecursiveFilter(net(30).net), "recursive", 20) != onnx_cache.key(
        RecursiveFilter(net(60).net), "recursive", 20)
    assert onnx_cache.key(net(30), "window", 20) != onnx_cache.key(net(60), "window", 20)
    torch.manual_seed(0)
    relative = WindowNet("cnn", 20, "relative")
    torch.manual_seed(0)
    frame = WindowNet("cnn", 20, "frame")
    assert onnx_cache.key(relative, "window", 20) != onnx_cache.key(frame, "window", 20)
    assert onnx_cache.key(net(30), "window", 20) == onnx_cache.key(net(30), "window", 20)
    train, infer = net(30), net(30).eval()
    assert onnx_cache.key(train, "window", 20) != onnx_cache.key(infer, "window", 20)


def test_the_key_follows_the_weights_the_form_and_the_opset():
    net = _cnn()
    base = onnx_cache.key(net, "window", 20)
    assert onnx_cache.key(_cnn(), "window", 20) == base
    assert onnx_cache.key(net, "recursive", 20) != base
    assert onnx_cache.key(net, "window", 21) != base
    with torch.no_grad():
        next(net.parameters()).view(-1)[0] += 1e-3
    assert onnx_cache.key(net, "window", 20) != base


def test_a_damaged_kept_export_is_exported_afresh_and_replaced(own_cache):
    win = _windows()
    ref = Observer.from_net(_cnn(), engine="onnx")._runner.predict(win)
    (kept,) = own_cache.iterdir()
    good = kept.read_bytes()
    kept.write_bytes(good[: len(good) // 2])
    np.testing.assert_array_equal(Observer.from_net(_cnn(), engine="onnx")._runner.predict(win),
                                  ref)
    assert kept.read_bytes() == good


def test_a_cache_folder_that_cannot_be_written_leaves_each_session_to_export(tmp_path,
                                                                            monkeypatch):
    blocker = tmp_path / "cache"
    blocker.write_text("a file where the folder would go")
    monkeypatch.setenv("LBO_CACHE_DIR", str(blocker))
    win = _windows()
    with torch.inference_mode():
        ref = _cnn().eval()(torch.from_numpy(win)).numpy()
    np.testing.assert_allclose(Observer.from_net(_cnn(), engine="onnx")._runner.predict(win),
                               ref, atol=engines.TOLERANCE)  # float32 inside
    assert blocker.read_text() == "a file where the folder would go"


def test_the_key_reads_a_modules_extra_state():
    class WithExtra(torch.nn.Module):
        def __init__(self, tag: str) -> None:
            super().__init__()
            self.lin = torch.nn.Linear(2, 1)
            self.tag = tag

        def get_extra_state(self):
            return {"tag": self.tag}

        def set_extra_state(self, state):
            self.tag = state["tag"]

    torch.manual_seed(0)
    a = WithExtra("a")
    b = WithExtra("b")
    b.load_state_dict({k: v for k, v in a.state_dict().items() if k != "_extra_state"},
                      strict=False)
    assert onnx_cache.key(a, "window", 20) != onnx_cache.key(b, "window", 20)
