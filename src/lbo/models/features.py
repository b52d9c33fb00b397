"""Observer inputs and targets: what the network sees and what it is trained to output.

A window is N consecutive steps ending at the current step t, with the channels
``[x_m, y_m, psi_m, V, delta]`` (shape ``(..., N, 5)``). Two feature modes:

``"relative"`` (default)
    Positions relative to the window's last (current) measurement and headings relative
    to the last measured heading, wrapped to (-pi, pi]. The observer then cannot depend on
    where the vehicle is, or on which branch of the angle the heading sits: the training set
    starts every trajectory at x=y=0, the test manoeuvres do not, and an absolute-position
    network would have to extrapolate. The target is the state relative to the current
    measurement, so the network learns a correction to it.
``"frame"``
    Invariant: the window and the target in the frame of the current measurement, translated
    to its position and rotated by its measured heading. Positions are
    ``R(-psi_m[t]) (p - p_m[t])``, headings ``wrap(psi - psi_m[t])``. Shifting and rotating a
    whole trajectory leaves the features unchanged, so the estimates shift and rotate with it
    exactly: the network never has to learn rotations.
``"absolute"``
    The paper's literal setting: windows and states as they are (target heading wrapped).

A missing position fix is a step whose ``x_m, y_m, psi_m`` are NaN. A window is then read
relative to its latest fix (its *anchor*) instead of its last step, and observers that can
take missing fixes see a sixth channel, ``fix`` (1 at a fix, 0 elsewhere, where the
measurement channels are 0): ``window_features(..., fixes=True)`` gives (..., N, 6).

Every function takes numpy arrays or torch tensors (the result has the same type, dtype and
device) and is vectorised over any leading batch dimensions. Torch inputs keep their autograd
graph.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.logs.checks import fix_mask

if TYPE_CHECKING:
    import torch
    from typing_extensions import TypeIs

FEATURE_MODES = ("relative", "frame", "absolute")

Array = TypeVar("Array", np.ndarray, "torch.Tensor")


def _is_tensor(a: object) -> TypeIs[torch.Tensor]:
    """Whether ``a`` is a torch tensor. A tensor exists only once torch is imported, so numpy
    work (a classical observer's run, a log's checks) never imports torch through here."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(a, torch.Tensor)


def _wrap(a: Array) -> Array:
    if _is_tensor(a):
        from lbo.models.poses import wrap_angle_torch

        return wrap_angle_torch(a)
    return wrap_angle(a)


def _cat_last(parts: list[Array]) -> Array:
    if _is_tensor(parts[0]):
        import torch

        return torch.cat(parts, dim=-1)
    return np.concatenate(parts, axis=-1)


def _rotate(xy: Array, psi: Array, sign: int) -> Array:
    """Rotate (..., 2) vectors by ``sign * psi`` (psi broadcasts as (..., 1))."""
    if _is_tensor(xy):
        import torch

        c, s = torch.cos(psi), torch.sin(psi) * sign
    else:
        c, s = np.cos(psi), np.sin(psi) * sign
    x, y = xy[..., :1], xy[..., 1:2]
    return _cat_last([c * x - s * y, s * x + c * y])


def window_view(series: Array, n: int) -> Array:
    """Every window of ``n`` consecutive steps, as a view (no copy): (..., T, C) ->
    (..., T-n+1, n, C), window ``j`` being steps ``j .. j+n-1``, oldest first.

    The one window extractor of lbo: training batches (:mod:`lbo.learn.datamodule`), the test grid
    (:func:`lbo.scoring.grid.predict_grid`) and a log (:meth:`lbo.Observer.run`) all cut their
    windows here, torch tensors and numpy arrays alike.
    """
    axis = series.ndim - 2
    if _is_tensor(series):
        return series.unfold(axis, n, 1).transpose(-1, -2)
    return np.lib.stride_tricks.sliding_window_view(series, n, axis=axis).swapaxes(-1, -2)


def held_within(held: np.ndarray, n: int) -> np.ndarray:
    """(T,) bool: whether each row's window of the last ``n`` rows (fewer at the start) holds
    a True of ``held`` (T,) bool, by a running count (not T x n)."""
    count = np.concatenate([[0], np.cumsum(held)])
    k = np.arange(1, len(held) + 1)
    return count[k] - count[np.maximum(k - n, 0)] > 0


def check_mode(mode: str) -> str:
    """Return ``mode`` if it is one of :data:`FEATURE_MODES`, else raise :class:`LboError`."""
    if mode not in FEATURE_MODES:
        raise LboError(f"features: unknown mode {mode!r}; "
                       f"expected one of {', '.join(FEATURE_MODES)}")
    return mode


def last_measurement(win: Array, fixes: bool = False) -> Array:
    """The anchor ``[x_m, y_m, psi_m]`` of each window: (..., N, 5) -> (..., 3).

    Its last step; with ``fixes``, its latest fix (NaN for a window without any fix).
    """
    if not fixes:
        return win[..., -1, :3]
    fix = fix_mask(win)
    n = win.shape[-2]
    if _is_tensor(win):
        import torch

        last = n - 1 - torch.flip(fix, [-1]).to(win.dtype).argmax(-1)
        idx = last[..., None, None].expand(*last.shape, 1, 3)
        return torch.gather(win[..., :3], -2, idx).squeeze(-2)
    last = n - 1 - np.flip(fix, -1).argmax(-1)
    return np.take_along_axis(win[..., :3], last[..., None, None], -2)[..., 0, :]


def window_features(win: Array, mode: str = "relative", fixes: bool = False) -> Array:
    """Turn raw windows into network inputs.

    Parameters
    ----------
    win : (..., N, 5) windows ``[x_m, y_m, psi_m, V, delta]``, the last step is the current one.
    mode : one of :data:`FEATURE_MODES`.
    fixes : the windows may miss fixes (NaN measurements): read them relative to their
        anchor (:func:`last_measurement`), put 0 in the missing measurements and append the
        ``fix`` channel.

    Returns
    -------
    (..., N, 5) features, (..., N, 6) with ``fixes``. ``"relative"``: ``[x_m - x_m[t],
    y_m - y_m[t], wrap(psi_m - psi_m[t]), V, delta]`` (a new array). ``"frame"``: the same
    with the position offsets rotated by ``-psi_m[t]``. ``"absolute"``: ``win`` itself (no
    copy, so a view of a larger array stays a view).
    """
    if check_mode(mode) == "absolute" and not fixes:
        return win
    if mode == "absolute":
        out = win
    else:
        last = last_measurement(win, fixes)[..., None, :]
        xy = win[..., :2] - last[..., :2]
        if mode == "frame":
            xy = _rotate(xy, last[..., 2:3], -1)
        out = _cat_last([xy, _wrap(win[..., 2:3] - last[..., 2:3]), win[..., 3:]])
    if not fixes:
        return out
    fix = fix_mask(win)[..., None]
    if _is_tensor(win):
        import torch

        meas = torch.where(fix, out[..., :3], torch.zeros_like(out[..., :3]))
        return torch.cat([meas, out[..., 3:5], fix.to(win.dtype)], -1)
    meas = np.where(fix, out[..., :3], 0.0)
    return np.concatenate([meas, out[..., 3:5], fix.astype(win.dtype)], -1)


def state_to_target(state: Array, last_meas: Array, mode: str = "relative") -> Array:
    """Training target for the state at the current step.

    Parameters
    ----------
    state : (..., 3) true ``[x, y, psi]`` at the window's last step.
    last_meas : (..., 3) the window's last measurement ``[x_m, y_m, psi_m]``
        (see :func:`last_measurement`).
    mode : one of :data:`FEATURE_MODES`.

    Returns
    -------
    (..., 3) ``[x - x_m, y - y_m, wrap(psi - psi_m)]`` for ``"relative"``, the same with
    the position offset rotated by ``-psi_m`` for ``"frame"``, ``[x, y, wrap(psi)]`` for
    ``"absolute"``.
    """
    if check_mode(mode) == "absolute":
        return _cat_last([state[..., :2], _wrap(state[..., 2:3])])
    xy = state[..., :2] - last_meas[..., :2]
    if mode == "frame":
        xy = _rotate(xy, last_meas[..., 2:3], -1)
    return _cat_last([xy, _wrap(state[..., 2:3] - last_meas[..., 2:3])])


def target_to_state(out: Array, last_meas: Array, mode: str = "relative") -> Array:
    """Map a network output back to the absolute state; the inverse of :func:`state_to_target`.

    Parameters
    ----------
    out : (..., 3) network output in target coordinates.
    last_meas : (..., 3) the window's last measurement ``[x_m, y_m, psi_m]``.
    mode : one of :data:`FEATURE_MODES`.

    Returns
    -------
    (..., 3) ``[x, y, psi]`` with psi wrapped to (-pi, pi].
    """
    if check_mode(mode) == "absolute":
        return _cat_last([out[..., :2], _wrap(out[..., 2:3])])
    xy = out[..., :2]
    if mode == "frame":
        xy = _rotate(xy, last_meas[..., 2:3], 1)
    return _cat_last([xy + last_meas[..., :2], _wrap(out[..., 2:3] + last_meas[..., 2:3])])
