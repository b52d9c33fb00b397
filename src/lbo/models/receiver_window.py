"""A receiver's window as a network's input: every channel with its own mask.

A window net that reads a receiver (``WindowNet(..., receiver=True)``) takes windows of
:data:`COLUMNS` (shape ``(..., N, 11)``): the classical filters' row
(:data:`lbo.filters.measure.CHANNELS`: a position fix with or without a heading, the
accuracies the receiver reports, the course over ground and its sigma), the inputs ``V,
delta`` and a gyro's yaw rate ``r_m``, each NaN in the rows that do not hold it. A paper
window (..., N, 5) ``[x_m, y_m, psi_m, V, delta]`` is a receiver window without accuracies,
course or gyro (:func:`widen`).

The window is read in the frame of its *anchor* (:func:`anchor`): the position of its latest
fix, turned by its latest heading, measured (``psi_m``) or travelled (the course over
ground), whichever came last; a window that holds no heading at all (a car that has not yet
moved) is read in the world's axes, and its network sees that it held none (every heading
mask 0). The features (:data:`FEATURES`, ``(..., N, 15)``) are each held value in that frame,
0 where not held, and a mask per channel:

``dx, dy, dpsi, dcourse`` : the fix's position (rotated) and its heading and course, relative
    to the anchor (headings wrapped);
``sx, sy, spsi, s_course`` : the reported 1-sigmas (0: not reported);
``fix, heading, course_held`` : masks of the position, ``psi_m`` and course;
``V, delta, r_m, gyro`` : the inputs, the gyro's rate (0: none) and its mask.

The measurement channels come first and the inputs last, so the CNN's two branches split
them as they split a paper window (its first three channels, the position and heading).
The target and its inverse are the ``"frame"`` ones of :mod:`lbo.models.features`, taken
about the anchor. Torch tensors only (the nets' own path); vectorised over any batch shape.
"""

from __future__ import annotations

import torch

from lbo.filters.measure import CHANNELS
from lbo.models.poses import wrap_angle_torch

COLUMNS = (*CHANNELS, "V", "delta", "r_m")
"""A receiver window's columns, in order."""
WIDTH = len(COLUMNS)
FEATURES = ("dx", "dy", "dpsi", "dcourse", "sx", "sy", "spsi", "s_course", "fix", "heading",
            "course_held", "V", "delta", "r_m", "gyro")
"""The features of each step, in order."""
_X, _Y, _PSI, _SX, _SY, _SPSI, _COURSE, _SCOURSE, _V, _DELTA, _R = range(WIDTH)


def widen(win: torch.Tensor) -> torch.Tensor:
    """Paper windows (..., N, 5) -> receiver windows (..., N, 11), the receiver's channels
    NaN; receiver windows are returned as they are."""
    if win.shape[-1] == WIDTH:
        return win
    nan = torch.full((*win.shape[:-1], 1), float("nan"), dtype=win.dtype, device=win.device)
    return torch.cat([win[..., :3], nan.expand(*win.shape[:-1], 5), win[..., 3:5], nan], -1)


def _latest(held: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Index (...,) of the last True along the last axis of ``held`` (..., N), and whether
    there is one (...,)."""
    n = held.shape[-1]
    last = n - 1 - torch.flip(held, [-1]).to(torch.int64).argmax(-1)
    return last, held.any(-1)


def _at(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """values (..., N) at index (...,) -> (...,)."""
    return torch.gather(values, -1, index[..., None]).squeeze(-1)


def heading_known(win: torch.Tensor) -> torch.Tensor:
    """Whether each receiver window (..., N, 11) holds a heading, ``psi_m`` or a course:
    (...,) bool. Where it holds none (a car that has stood or crept for the whole window) its
    anchor's heading is 0 and the window tells nothing of the car's: the net is not trained
    on that heading (:meth:`lbo.models.net.WindowNet.loss`)."""
    return (torch.isfinite(win[..., _PSI]) | torch.isfinite(win[..., _COURSE])).any(-1)


def _zeroed(t: torch.Tensor) -> torch.Tensor:
    """t with 0 where it is NaN (a channel not held). Not ``nan_to_num``, which also maps inf
    to the dtype's largest number: exported, that float64 bound is cast to a float32 attribute
    and overflows (a warning at every export). lbo refuses inf in every channel it reads, so
    the numbers are the same."""
    return torch.where(torch.isnan(t), torch.zeros_like(t), t)


def anchor(win: torch.Tensor, dt: float, wheelbase: float) -> torch.Tensor:
    """The frame each window is read in: ``[x_a, y_a, psi_a]`` (..., 3) from receiver
    windows (..., N, 11): the latest fix's position and the latest heading (``psi_m`` or the
    course, whichever is later; 0 where the window holds none), each carried to the window's
    last step by dead reckoning on the kinematic bicycle (its inputs V, delta; period ``dt``
    s, ``wheelbase`` m). With fixes at 1 Hz the latest one lies up to a second, 10-30 m,
    behind the car: the network then learns a correction to the dead reckoning, not the
    reckoning itself. A window whose last step holds a full fix is anchored there, as a paper
    window in the ``"frame"`` mode. NaN where the window holds no fix."""
    fix = torch.isfinite(win[..., _X]) & torch.isfinite(win[..., _Y])
    last_fix, any_fix = _latest(fix)
    has_psi = torch.isfinite(win[..., _PSI])
    heading = torch.where(has_psi, _zeroed(win[..., _PSI]), _zeroed(win[..., _COURSE]))
    last_h, any_h = _latest(has_psi | torch.isfinite(win[..., _COURSE]))
    zero = torch.zeros_like(win[..., 0])
    # yaw turned before each step (..., N) and the heading at each step, from the latest one
    v, delta = win[..., _V], win[..., _DELTA]
    turn = v * torch.sin(delta) / torch.cos(delta) * (dt / wheelbase)  # tan: no float64 ONNX
    turned = torch.cumsum(turn, -1) - turn
    psi0 = torch.where(any_h, _at(heading, last_h), zero[..., 0])
    psi = psi0[..., None] + turned - _at(turned, last_h)[..., None]
    # the way travelled before each step, and from the latest fix to the last step
    step = v[..., None] * dt * torch.stack([torch.cos(psi), torch.sin(psi)], -1)
    way = torch.cumsum(step, -2) - step  # before each step
    ahead = way[..., -1, :] - torch.gather(way, -2, last_fix[..., None, None].expand(
        *last_fix.shape, 1, 2)).squeeze(-2)
    nan = torch.full_like(psi0, float("nan"))
    x = torch.where(any_fix, _at(win[..., _X], last_fix), nan) + ahead[..., 0]
    y = torch.where(any_fix, _at(win[..., _Y], last_fix), nan) + ahead[..., 1]
    return torch.stack([x, y, psi[..., -1]], -1)


def features(win: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Network inputs (..., N, 15) (:data:`FEATURES`) of receiver windows (..., N, 11) in
    the frame of their anchors a (..., 3) (:func:`anchor`)."""
    a = a[..., None, :]
    fix = torch.isfinite(win[..., _X]) & torch.isfinite(win[..., _Y])
    c, s = torch.cos(a[..., 2]), torch.sin(a[..., 2])
    dx = _zeroed(win[..., _X] - a[..., 0])
    dy = _zeroed(win[..., _Y] - a[..., 1])
    zero = torch.zeros_like(dx)

    def held(col: int) -> tuple[torch.Tensor, torch.Tensor]:
        ok = torch.isfinite(win[..., col])
        return ok, torch.where(ok, win[..., col], zero)

    has_psi, psi = held(_PSI)
    has_course, course = held(_COURSE)
    has_rate, rate = held(_R)
    parts = [torch.where(fix, c * dx + s * dy, zero), torch.where(fix, -s * dx + c * dy, zero),
             torch.where(has_psi, wrap_angle_torch(psi - a[..., 2]), zero),
             torch.where(has_course, wrap_angle_torch(course - a[..., 2]), zero),
             held(_SX)[1], held(_SY)[1], held(_SPSI)[1], held(_SCOURSE)[1],
             fix.to(win.dtype), has_psi.to(win.dtype), has_course.to(win.dtype),
             win[..., _V], win[..., _DELTA], rate, has_rate.to(win.dtype)]
    return torch.stack(parts, -1)
