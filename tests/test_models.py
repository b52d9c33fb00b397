"""CNN and LSTM observers: shapes, validation, initialisation, scripting, gradients."""

import math

import pytest
import torch

from lbo.core.errors import LboError
from lbo.core.plugins import OWN
from lbo.models import WindowCNN, WindowLSTM, build_model

MODELS = OWN["model"]  # lbo's own (a plug-in installed beside them has its own tests)

WINDOWS = [4, 20, 40, 60, 80]


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("window", WINDOWS)
def test_output_shape(name, window):
    from lbo.models.net import WindowNet

    torch.manual_seed(0)
    model = build_model(name, window)
    out = model(torch.randn(6, window, 5))
    assert out.shape == (6, 3)
    assert out.dtype == torch.float32
    assert torch.isfinite(out).all()
    # wrapped as the observer that trains and runs: float64 windows in, float64 states out
    # they read metres in the latest fix's frame
    frame = name in ("filternet", "kalmannet", "split_kalmannet")
    net = WindowNet(name, window, features="frame" if frame else "relative")
    state = net(torch.randn(7, window, 5, dtype=torch.float64))
    assert state.shape == (7, 3) and state.dtype == torch.float64
    assert torch.isfinite(state).all()


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("window", [0, 3])
def test_short_window_is_rejected(name, window):
    with pytest.raises(LboError, match=r"window.*>= 4"):
        build_model(name, window)


def test_unknown_model_names_field_and_choices():
    with pytest.raises(LboError, match=r"^model.name: model 'gru' is not installed \(install "
                       r"the package that registers it .*lbo.models\); installed: cnn, lstm, "):
        build_model("gru", 20)


def test_unknown_kwarg_names_it_and_accepted_ones():
    with pytest.raises(LboError) as err:
        build_model("cnn", 20, hidden_sizes=(8, 8))
    msg = str(err.value)
    assert "\n" not in msg
    assert "hidden_sizes" in msg and "conv_channels" in msg and "dense_units" in msg
    with pytest.raises(LboError, match=r"conv_channels.*hidden_sizes"):
        build_model("lstm", 20, conv_channels=8)


@pytest.mark.parametrize("kwargs", [{"dense_units": 0}, {"conv_channels": 2.5},
                                    {"feature_channels": -1}])
def test_bad_cnn_values(kwargs):
    with pytest.raises(LboError, match=next(iter(kwargs))):
        build_model("cnn", 20, **kwargs)


@pytest.mark.parametrize("sizes", [(), "8", (8, 0)])
def test_bad_lstm_sizes(sizes):
    with pytest.raises(LboError, match="hidden_sizes"):
        build_model("lstm", 20, hidden_sizes=sizes)


def test_kwargs_reach_the_model():
    cnn = build_model("cnn", 20, conv_channels=4, feature_channels=6, dense_units=10)
    assert cnn.measurements.layers[0].out_channels == 4
    assert cnn.head[0].out_features == 10
    lstm = build_model("lstm", 20, hidden_sizes=[4, 12], dense_units=7)
    assert [m.hidden_size for m in lstm.lstms] == [4, 12]
    assert lstm(torch.randn(2, 20, 5)).shape == (2, 3)


def _xavier_std(fan_in: int, fan_out: int) -> float:
    # U(-a, a) with a = sqrt(6 / (fan_in + fan_out)) has std a / sqrt(3).
    return math.sqrt(6.0 / (fan_in + fan_out)) / math.sqrt(3.0)


def test_cnn_xavier_init():
    torch.manual_seed(0)
    model = WindowCNN(80, conv_channels=32, feature_channels=32, dense_units=64)
    for m in model.modules():
        if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear)):
            w = m.weight
            receptive = w[0, 0].numel() if w.dim() > 2 else 1
            expected = _xavier_std(w.shape[1] * receptive, w.shape[0] * receptive)
            assert w.std().item() == pytest.approx(expected, rel=0.25)
            assert w.abs().max().item() <= expected * math.sqrt(3) + 1e-6
            assert torch.count_nonzero(m.bias) == 0


def test_lstm_xavier_init_and_forget_bias():
    torch.manual_seed(0)
    model = WindowLSTM(20, hidden_sizes=(32, 32))
    for lstm in model.lstms:
        h = lstm.hidden_size
        for name, p in lstm.named_parameters():
            if name.startswith("weight"):
                for gate in p.split(h):
                    expected = _xavier_std(gate.shape[1], gate.shape[0])
                    assert gate.std().item() == pytest.approx(expected, rel=0.25)
            elif name.startswith("bias_ih"):
                assert torch.equal(p[h:2 * h], torch.ones(h))
                assert torch.count_nonzero(p[:h]) == 0 and torch.count_nonzero(p[2 * h:]) == 0
            else:
                assert torch.count_nonzero(p) == 0
    for m in model.head:
        if isinstance(m, torch.nn.Linear):
            assert torch.count_nonzero(m.bias) == 0


@pytest.mark.parametrize("name", sorted(MODELS))
def test_torchscript_matches_eager(name):
    torch.manual_seed(0)
    model = build_model(name, 20).eval()
    scripted = torch.jit.script(model)
    x = torch.randn(5, 20, 5)
    torch.testing.assert_close(scripted(x), model(x))


def test_gradients_reach_both_cnn_branches():
    torch.manual_seed(0)
    model = WindowCNN(20)
    loss = torch.nn.functional.mse_loss(model(torch.randn(8, 20, 5)), torch.randn(8, 3))
    loss.backward()
    for branch in (model.measurements, model.inputs):
        for p in branch.parameters():
            assert p.grad is not None and p.grad.abs().sum() > 0


@pytest.mark.parametrize("channels", [slice(0, 3), slice(3, 5)])
def test_cnn_output_depends_on_each_branch(channels):
    torch.manual_seed(0)
    model = WindowCNN(20)
    x = torch.randn(2, 20, 5)
    y = x.clone()
    y[:, :, channels] += 1.0
    assert not torch.allclose(model(x), model(y))


def test_cnn_activation_choice_and_refusal():
    from lbo.models.cnn import CentredSigmoid

    paper = build_model("cnn", 20)  # a checkpoint without the key keeps the paper's sigmoid
    assert not any(isinstance(m, CentredSigmoid) for m in paper.modules())
    centred = build_model("cnn", 20, activation="centred_sigmoid")
    acts = [m for m in centred.modules() if isinstance(m, CentredSigmoid)]
    assert len(acts) == 9  # four per branch and the dense layer's
    x = torch.linspace(-6, 6, 101)
    assert torch.allclose(acts[0](x), torch.sigmoid(x) - 0.5)
    assert torch.allclose(acts[0](-x), -acts[0](x), atol=1e-7)  # zero-mean: odd around 0
    with pytest.raises(LboError, match=r"^model.activation: expected one of sigmoid, "
                                       r"centred_sigmoid, got 'relu'$"):
        build_model("cnn", 20, activation="relu")


def test_centred_cnn_keeps_the_dense_layer_out_of_saturation_at_n80():
    """The cause of the N>=60 CNNs that learned nothing: with sigmoid inputs near 0.5, one Adam
    step at the lr tuned at N=20 moves the dense layer's pre-activations by about lr * 10 N.
    Centred, the same step moves them by a fraction of that."""
    torch.manual_seed(0)
    x = torch.randn(256, 80, 5)
    y = torch.randn(256, 3)
    shift = {}
    for act in ("sigmoid", "centred_sigmoid"):
        torch.manual_seed(1)
        net = build_model("cnn", 80, activation=act)
        dense = net.head[0]
        feats = torch.cat([net.measurements(x[:, :, :3]), net.inputs(x[:, :, 3:])], 1)
        before = dense(feats).detach()
        opt = torch.optim.Adam(net.parameters(), lr=2.7e-3)
        torch.nn.functional.mse_loss(net(x), y).backward()
        opt.step()
        feats = torch.cat([net.measurements(x[:, :, :3]), net.inputs(x[:, :, 3:])], 1)
        shift[act] = (dense(feats).detach() - before).abs().mean().item()
    assert shift["sigmoid"] > 2.0                   # lr * 10 N = 2.2: saturation in a step
    assert shift["centred_sigmoid"] < shift["sigmoid"] / 5
