"""Feature modes: translation invariance, heading wrap, target round trips."""

import math

import numpy as np
import pytest
import torch

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.models import WindowCNN
from lbo.models.features import (
    FEATURE_MODES,
    last_measurement,
    state_to_target,
    target_to_state,
    window_features,
)
from lbo.models.poses import wrap_angle_torch


def _windows(rng: np.random.Generator, batch: int = 6, window: int = 20) -> np.ndarray:
    win = rng.normal(size=(batch, window, 5))
    win[..., :2] *= 20.0
    win[..., 2] = rng.uniform(-np.pi, np.pi, size=(batch, window))
    return win


def _angle_close(a, b, atol):
    np.testing.assert_allclose(wrap_angle(np.asarray(a) - np.asarray(b)), 0.0, atol=atol)


@pytest.mark.parametrize("mode", ["bogus", "", "Relative"])
def test_unknown_mode_names_field_and_choices(mode):
    win = np.zeros((4, 5))
    for call in (lambda: window_features(win, mode),
                 lambda: state_to_target(win[0, :3], win[0, :3], mode),
                 lambda: target_to_state(win[0, :3], win[0, :3], mode)):
        with pytest.raises(LboError, match=r"^features: .*relative, frame, absolute"):
            call()


def test_torch_wrap_matches_numpy():
    a = np.array([-3 * np.pi, -np.pi, -np.pi + 1e-9, 0.0, np.pi, np.pi + 1e-6, 7.0, -7.0])
    np.testing.assert_allclose(wrap_angle_torch(torch.from_numpy(a)).numpy(), wrap_angle(a),
                               atol=1e-12)
    assert wrap_angle_torch(torch.tensor([-math.pi], dtype=torch.float64)).item() == math.pi


@pytest.mark.parametrize("as_torch", [False, True])
def test_relative_features_ignore_translation(as_torch):
    win = _windows(np.random.default_rng(0))
    shifted = win.copy()
    shifted[..., 0] += 1234.5
    shifted[..., 1] -= 678.9
    shifted[..., 2] += 4 * np.pi  # the same headings on another branch
    if as_torch:
        win, shifted = torch.from_numpy(win), torch.from_numpy(shifted)
    f, g = window_features(win, "relative"), window_features(shifted, "relative")
    assert type(f) is type(win) and f.shape == win.shape
    np.testing.assert_allclose(np.asarray(g), np.asarray(f), atol=1e-9)
    f = np.asarray(f)
    np.testing.assert_array_equal(f[:, -1, :3], 0.0)
    np.testing.assert_array_equal(f[..., 3:], np.asarray(win)[..., 3:])


def test_relative_heading_wraps_across_pi():
    win = np.zeros((3, 5))
    win[:, 2] = [np.pi - 0.01, -np.pi + 0.02, -np.pi + 0.01]  # crosses +-pi at the last steps
    feat = window_features(win, "relative")
    np.testing.assert_allclose(feat[:, 2], [-0.02, 0.01, 0.0], atol=1e-12)
    state = np.array([0.0, 0.0, np.pi - 0.005])
    target = state_to_target(state, last_measurement(win), "relative")
    assert target[2] == pytest.approx(-0.015, abs=1e-12)
    back = target_to_state(target, last_measurement(win), "relative")
    assert back[2] == pytest.approx(np.pi - 0.005, abs=1e-12)


def test_absolute_features_are_the_window():
    win = _windows(np.random.default_rng(1))
    assert window_features(win, "absolute") is win


@pytest.mark.parametrize("mode", FEATURE_MODES)
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("as_torch", [False, True])
def test_target_round_trip(mode, dtype, as_torch):
    rng = np.random.default_rng(2)
    win = _windows(rng).astype(dtype)
    state = last_measurement(win) + rng.normal(scale=0.5, size=(6, 3)).astype(dtype)
    state[:, 2] = rng.uniform(-3 * np.pi, 3 * np.pi, size=6)
    last = last_measurement(win)
    if as_torch:
        state, last = torch.from_numpy(state), torch.from_numpy(last)
    target = state_to_target(state, last, mode)
    back = target_to_state(target, last, mode)
    assert type(back) is type(state) and back.shape == (6, 3) and back.dtype == state.dtype
    assert np.all(np.abs(np.asarray(target)[:, 2]) <= np.pi)
    atol = 1e-12 if dtype == np.float64 else 1e-4
    state, back = np.asarray(state), np.asarray(back)
    np.testing.assert_allclose(back[:, :2], state[:, :2], atol=atol)
    _angle_close(back[:, 2], state[:, 2], atol)
    assert np.all(np.abs(back[:, 2]) <= np.pi)


def test_torch_features_keep_gradients():
    win = torch.from_numpy(_windows(np.random.default_rng(3))).requires_grad_()
    window_features(win, "relative").sum().backward()
    assert win.grad is not None


def test_relative_cnn_observer_is_translation_equivariant():
    torch.manual_seed(0)
    model = WindowCNN(20).eval()
    win = _windows(np.random.default_rng(4))
    offset = np.array([1000.0, -2500.0])
    shifted = win.copy()
    shifted[..., :2] += offset

    def observe(w: np.ndarray) -> np.ndarray:
        feats = torch.from_numpy(window_features(w, "relative")).float()
        with torch.no_grad():
            out = model(feats).double().numpy()
        return target_to_state(out, last_measurement(w), "relative")

    base, moved = observe(win), observe(shifted)
    np.testing.assert_allclose(moved[:, :2], base[:, :2] + offset, atol=1e-5)
    _angle_close(moved[:, 2], base[:, 2], 1e-5)


# --- "frame": invariant to rotations and translations -----------------------------------------


def _move(a, theta: float, centre=(30.0, -40.0), shift=(1234.5, -678.9)):
    """A rigid motion of ``[x, y, psi, ...]`` rows (numpy or torch, any leading dimensions):
    positions rotated by theta about ``centre`` and shifted, headings + theta, wrapped."""
    torch_in = isinstance(a, torch.Tensor)
    a = a.detach().numpy() if torch_in else np.asarray(a)
    out = a.copy()
    c, s = np.cos(theta), np.sin(theta)
    dx, dy = a[..., 0] - centre[0], a[..., 1] - centre[1]
    out[..., 0] = c * dx - s * dy + centre[0] + shift[0]
    out[..., 1] = s * dx + c * dy + centre[1] + shift[1]
    out[..., 2] = wrap_angle(a[..., 2] + theta)
    return torch.from_numpy(out) if torch_in else out


def _drives(rng: np.random.Generator, batch: int = 8, window: int = 20, dt: float = 0.02,
            wheelbase: float = 2.7) -> tuple[np.ndarray, np.ndarray]:
    """Windows of kinematic-bicycle drives with paper-preset measurement noise, and the true
    states at their last steps: (B, N, 5), (B, 3)."""
    v = rng.uniform(5.0, 20.0, size=(batch, 1)) + np.linspace(0, 2, window)
    delta = rng.uniform(-0.05, 0.05, size=(batch, 1)) * np.cos(np.linspace(0, 3, window))
    psi = rng.uniform(-np.pi, np.pi, size=(batch, 1)) + np.cumsum(
        v * np.tan(delta) / wheelbase * dt, axis=1)
    x = rng.uniform(-300, 300, size=(batch, 1)) + np.cumsum(v * np.cos(psi) * dt, axis=1)
    y = rng.uniform(-300, 300, size=(batch, 1)) + np.cumsum(v * np.sin(psi) * dt, axis=1)
    z = np.stack([x, y, wrap_angle(psi)], axis=-1)
    m = z + rng.normal(size=z.shape) * np.array([1.0, 1.0, 0.0174])
    m[..., 2] = wrap_angle(m[..., 2])
    return np.concatenate([m, v[..., None], delta[..., None]], axis=-1), z[:, -1]


@pytest.mark.parametrize("theta", [0.3, -2.5, np.pi, 5.0])
@pytest.mark.parametrize("as_torch", [False, True])
def test_frame_features_ignore_rotation_and_translation(theta, as_torch):
    rng = np.random.default_rng(5)
    win = _windows(rng)
    state = last_measurement(win) + rng.normal(scale=0.5, size=(6, 3))
    moved, moved_state = _move(win, theta), _move(state, theta)
    if as_torch:
        win, moved = torch.from_numpy(win), torch.from_numpy(moved)
        state, moved_state = torch.from_numpy(state), torch.from_numpy(moved_state)
    f, g = window_features(win, "frame"), window_features(moved, "frame")
    assert type(f) is type(win) and f.shape == win.shape and f.dtype == win.dtype
    f, g = np.asarray(f), np.asarray(g)
    np.testing.assert_allclose(g[..., :2], f[..., :2], rtol=0, atol=1e-9)
    _angle_close(g[..., 2], f[..., 2], 1e-9)
    np.testing.assert_array_equal(g[..., 3:], f[..., 3:])
    np.testing.assert_array_equal(f[:, -1, :3], 0.0)
    t = np.asarray(state_to_target(state, last_measurement(win), "frame"))
    u = np.asarray(state_to_target(moved_state, last_measurement(moved), "frame"))
    np.testing.assert_allclose(u[:, :2], t[:, :2], rtol=0, atol=1e-9)
    _angle_close(u[:, 2], t[:, 2], 1e-9)
    # "relative" is only translation invariant: a rotation changes it
    r, q = window_features(win, "relative"), window_features(moved, "relative")
    assert np.abs(np.asarray(q)[..., :2] - np.asarray(r)[..., :2]).max() > 1.0


@pytest.mark.parametrize("psi", [0.0, 0.7, np.pi / 2, -2.0, np.pi])
def test_frame_is_the_current_measurement_frame(psi):
    """Driving straight along the measured heading: earlier steps lie behind (x < 0), on the
    axis (y = 0); a state 1 m ahead and 2 m to the left is [1, 2] in the frame."""
    n, step = 10, 0.3
    k = np.arange(n) - (n - 1)
    win = np.zeros((n, 5))
    win[:, 0] = 50.0 + k * step * np.cos(psi)
    win[:, 1] = -20.0 + k * step * np.sin(psi)
    win[:, 2] = psi
    feat = window_features(win, "frame")
    np.testing.assert_allclose(feat[:, 0], k * step, atol=1e-12)
    np.testing.assert_allclose(feat[:, 1], 0.0, atol=1e-12)
    last = last_measurement(win)
    ahead = last + np.array([np.cos(psi) - 2 * np.sin(psi), np.sin(psi) + 2 * np.cos(psi), 0.1])
    target = state_to_target(ahead, last, "frame")
    np.testing.assert_allclose(target, [1.0, 2.0, 0.1], atol=1e-12)
    np.testing.assert_allclose(target_to_state(target, last, "frame")[:2], ahead[:2], atol=1e-12)


@pytest.mark.parametrize("as_torch", [False, True])
def test_frame_round_trip_across_pi(as_torch):
    state = np.array([[3.0, -4.0, np.pi - 0.01], [-1.0, 2.0, -np.pi + 0.02],
                      [10.0, 10.0, 7.5], [0.0, 0.0, -9.0]])
    last = np.array([[2.5, -4.5, -np.pi + 0.01], [-1.2, 2.1, np.pi - 0.03],
                     [9.0, 11.0, 1.2], [0.5, -0.5, np.pi]])
    if as_torch:
        state, last = torch.from_numpy(state), torch.from_numpy(last)
    target = state_to_target(state, last, "frame")
    back = np.asarray(target_to_state(target, last, "frame"))
    assert np.all(np.abs(np.asarray(target)[:, 2]) <= np.pi)
    np.testing.assert_allclose(np.asarray(target)[:2, 2], [-0.02, 0.05], atol=1e-12)
    state = np.asarray(state)
    np.testing.assert_allclose(back[:, :2], state[:, :2], rtol=0, atol=1e-12)
    _angle_close(back[:, 2], state[:, 2], 1e-12)
    assert np.all(np.abs(back[:, 2]) <= np.pi)


def _frame_net(model: str, dtype: torch.dtype):
    from lbo.models.net import WindowNet

    torch.manual_seed(0)
    net = WindowNet(model, 20, features="frame")
    gen = torch.Generator().manual_seed(1)
    if net.physical:  # filternet: make its learned noise model and Q scale do something
        torch.nn.init.normal_(net.net.noise[-1].weight, std=0.3, generator=gen)
        torch.nn.init.normal_(net.net.noise[-1].bias, std=0.3, generator=gen)
        with torch.no_grad():
            net.net.log_q_scale.copy_(torch.tensor([0.5, -0.3, 0.2]))
    else:  # statistics as training would set them
        net.set_normalisation(torch.randn(5, generator=gen), torch.rand(5, generator=gen) + 0.5,
                              torch.randn(3, generator=gen), torch.rand(3, generator=gen) + 0.5)
    return net.to(dtype).eval()


@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-9), (torch.float32, 1e-6)])
@pytest.mark.parametrize("model", ["cnn", "lstm", "filternet"])
@pytest.mark.parametrize("theta", [1.1, -2.9])
def test_frame_observer_moves_with_the_vehicle(model, theta, dtype, atol):
    """The estimate of a rotated and shifted window is the rotated and shifted estimate."""
    net = _frame_net(model, dtype)
    win, _ = _drives(np.random.default_rng(6))
    win, moved = torch.from_numpy(win), torch.from_numpy(_move(win, theta))
    with torch.no_grad():
        est, est_moved = net(win), net(moved)
    assert est.dtype == torch.float64 and est.shape == (8, 3)
    assert torch.isfinite(est).all()
    expected = _move(est, theta).numpy()
    est_moved = est_moved.numpy()
    np.testing.assert_allclose(est_moved[:, :2], expected[:, :2], rtol=0, atol=atol)
    _angle_close(est_moved[:, 2], expected[:, 2], atol)
    # not trivially: the estimate is not just the last measurement
    assert np.abs(est.numpy()[:, :2] - win[:, -1, :2].numpy()).max() > 1e-3


def test_relative_observer_does_not_move_with_a_rotation():
    """The contrast: with "relative" features a rotation changes what the network sees."""
    from lbo.models.net import WindowNet

    torch.manual_seed(0)
    net = WindowNet("cnn", 20, features="relative").double().eval()
    win, _ = _drives(np.random.default_rng(6))
    win, moved = torch.from_numpy(win), torch.from_numpy(_move(win, 1.1))
    with torch.no_grad():
        gap = net(moved).numpy()[:, :2] - _move(net(win), 1.1).numpy()[:, :2]
    assert np.abs(gap).max() > 1e-3


def test_filternet_needs_frame_features():
    from lbo.models.net import WindowNet

    for mode in ("relative", "absolute"):
        with pytest.raises(LboError, match=r"^features: model 'filternet' needs features in "
                                           r"\['frame'\], got '" + mode + "'$"):
            WindowNet("filternet", 20, features=mode)


def test_window_view_is_one_extractor_for_torch_and_numpy():
    import numpy as np
    import torch

    from lbo.models.features import window_view

    series = np.arange(2 * 9 * 5, dtype=float).reshape(2, 9, 5)  # (G, T, C)
    for arr in (series, torch.from_numpy(series)):
        w = window_view(arr, 4)
        assert tuple(w.shape) == (2, 6, 4, 5)
        for g, j in ((0, 0), (1, 5), (1, 2)):
            np.testing.assert_array_equal(np.asarray(w[g, j]), series[g, j:j + 4])
    assert np.shares_memory(window_view(series, 4), series)  # a view, not a copy
