"""Feature modes: translation invariance, heading wrap, target round trips."""

import math

import numpy as np
import pytest
import torch

from lbo.errors import LboError
from lbo.features import (
    FEATURE_MODES,
    last_measurement,
    state_to_target,
    target_to_state,
    window_features,
    wrap_angle_torch,
)
from lbo.models import CNNObserver
from lbo.vehicle import wrap_angle


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
    model = CNNObserver(20).eval()
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
