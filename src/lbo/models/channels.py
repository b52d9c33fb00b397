"""The torch twin of :class:`lbo.Measurements`: a paper window's and a receiver window's
features read by name, in one place each.

The learned filters take arrays, as their exported graphs do: a filter's row (..., 8) of
:data:`lbo.filters.measure.CHANNELS` (the fix, its heading, the reported accuracies, and the
course over ground the GNSS velocity gives; named by :func:`lbo.filters.measure.row_channels`,
NumPy's and torch's alike), a paper window's features (..., 5|6) of
:data:`lbo.sim.columns.WINDOW` (and ``fix``) and a receiver window's features (..., 15) of
:data:`lbo.models.receiver_window.FEATURES`. :func:`window_channels` and
:func:`feature_channels` give their columns as named views, with the field names of
:class:`lbo.Measurements` where the two hold the same thing, so that no filter reads a
channel by its position. Views only (a window of five's ``fix``, all ones, is made):
the same numbers, and the same traced, scripted and exported graphs, as the indexing they
replace (plain NamedTuples and slices, which TorchScript compiles).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from lbo.models.receiver_window import FEATURES
from lbo.sim.columns import WINDOW


class Window(NamedTuple):
    """A paper window's features (..., N, 5|6) by name: each field (..., N) or (..., N, k).

    pose : (..., N, 3) ``[x_m, y_m, psi_m]``, in the frame of the features.
    inputs : (..., N, 2) ``[V, delta]``; V, delta : each of them.
    fix : 1 where the row holds a fix (the sixth channel, where fixes may be missing; every
        row of a window of five).
    """

    pose: torch.Tensor
    inputs: torch.Tensor
    V: torch.Tensor
    delta: torch.Tensor
    fix: torch.Tensor


assert WINDOW == ("x_m", "y_m", "psi_m", "V", "delta"), \
    "window_channels reads these columns at these places"


def window_channels(x: torch.Tensor) -> Window:
    """The columns of a paper window's features (..., N, 5|6) (:data:`lbo.sim.columns.WINDOW`,
    then ``fix``) by name."""
    fix = x[..., 5] if x.shape[-1] > 5 else torch.ones_like(x[..., 4])
    return Window(x[..., 0:3], x[..., 3:5], x[..., 3], x[..., 4], fix)


class Features(NamedTuple):
    """A receiver window's features (..., N, 15) by name, in the frame of its anchor
    (:func:`lbo.models.receiver_window.features`): each field (..., N) or (..., N, k), 0 where
    not held, with a mask (1 or 0) per channel.

    pose : (..., N, 3) ``[dx, dy, dpsi]``, the fix and ``psi_m`` relative to the anchor;
    fix : (..., N, 2) ``[dx, dy]``; heading : ``dpsi``; course : ``dcourse``.
    sigma : (..., N, 3) ``[sx, sy, spsi]``, the reported 1-sigmas (0: none); course_sigma.
    has_fix, has_heading, has_course : the masks of the position, ``psi_m`` and the course.
    V, delta : the inputs; gyro : ``r_m`` (0: none); has_gyro : its mask.
    """

    pose: torch.Tensor
    fix: torch.Tensor
    heading: torch.Tensor
    course: torch.Tensor
    sigma: torch.Tensor
    course_sigma: torch.Tensor
    has_fix: torch.Tensor
    has_heading: torch.Tensor
    has_course: torch.Tensor
    V: torch.Tensor
    delta: torch.Tensor
    gyro: torch.Tensor
    has_gyro: torch.Tensor


assert FEATURES == ("dx", "dy", "dpsi", "dcourse", "sx", "sy", "spsi", "s_course", "fix",
                    "heading", "course_held", "V", "delta", "r_m", "gyro"), \
    "feature_channels reads these columns at these places"


def feature_channels(x: torch.Tensor) -> Features:
    """The columns of a receiver window's features (..., N, 15)
    (:data:`lbo.models.receiver_window.FEATURES`) by name."""
    # the places as literals: TorchScript compiles no global ints (checked above)
    return Features(x[..., 0:3], x[..., 0:2], x[..., 2], x[..., 3], x[..., 4:7], x[..., 7],
                    x[..., 8], x[..., 9], x[..., 10], x[..., 11], x[..., 12], x[..., 13],
                    x[..., 14])
