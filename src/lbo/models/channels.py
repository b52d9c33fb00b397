"""The torch twin of :class:`lbo.Measurements`: a filter's row and a receiver window's
features read by name, in one place each.

The learned filters take arrays, as their exported graphs do: a filter's row (..., 8) of
:data:`lbo.filters.measure.CHANNELS` (the fix, its heading, the reported accuracies, and the
course over ground the GNSS velocity gives) and a receiver window's features (..., 15) of
:data:`lbo.models.receiver_window.FEATURES`. :func:`row_channels` and :func:`feature_channels`
give their columns as named views, with the field names of :class:`lbo.Measurements` where
the two hold the same thing, so that no filter reads a channel by its position. Views only:
the same numbers, and the same traced and exported graphs, as the indexing they replace.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from lbo.filters.measure import CHANNELS
from lbo.models.receiver_window import FEATURES


class Row(NamedTuple):
    """A filter's rows (..., 8) by name; each field (...) or (..., 2), NaN where not held."""

    fix: torch.Tensor
    """(..., 2) ``[x_m, y_m]``."""
    heading: torch.Tensor
    """``psi_m``."""
    fix_sigma: torch.Tensor
    """(..., 2) ``[sx_m, sy_m]``, the receiver's reported 1-sigma of the fix."""
    heading_sigma: torch.Tensor
    """``spsi_m``."""
    course: torch.Tensor
    """The course over ground of the row's GNSS velocity."""
    course_sigma: torch.Tensor
    """Its 1-sigma."""

    @property
    def sigma(self) -> torch.Tensor:
        """(..., 3) ``[sx_m, sy_m, spsi_m]``: the reported 1-sigma of each pose channel."""
        return torch.cat([self.fix_sigma, self.heading_sigma[..., None]], -1)


_X, _SX, _PSI, _SPSI, _COURSE, _SCOURSE = (
    CHANNELS.index(c) for c in ("x_m", "sx_m", "psi_m", "spsi_m", "course", "s_course"))


def row_channels(row: torch.Tensor) -> Row:
    """The columns of rows (..., 8) (:data:`lbo.filters.measure.CHANNELS`) by name."""
    return Row(row[..., _X:_X + 2], row[..., _PSI], row[..., _SX:_SX + 2], row[..., _SPSI],
               row[..., _COURSE], row[..., _SCOURSE])


class Features(NamedTuple):
    """A receiver window's features (..., N, 15) by name, in the frame of its anchor
    (:func:`lbo.models.receiver_window.features`): each field (..., N) or (..., N, 2), 0
    where not held, with a mask (1 or 0) per channel."""

    fix: torch.Tensor
    """(..., N, 2) the fix's position ``dx, dy`` relative to the anchor."""
    heading: torch.Tensor
    """``dpsi``: ``psi_m`` relative to the anchor's heading."""
    course: torch.Tensor
    """``dcourse``: the course over ground relative to it."""
    fix_sigma: torch.Tensor
    """(..., N, 2) ``sx, sy``: the reported 1-sigma of the fix (0: none)."""
    heading_sigma: torch.Tensor
    """``spsi``."""
    course_sigma: torch.Tensor
    """``s_course``."""
    has_fix: torch.Tensor
    """The masks: a position fix, ..."""
    has_heading: torch.Tensor
    """... ``psi_m``, ..."""
    has_course: torch.Tensor
    """... a course over ground."""
    V: torch.Tensor
    """The speed input."""
    delta: torch.Tensor
    """The steering input."""
    gyro: torch.Tensor
    """``r_m``, the gyro's yaw rate (0: none), ..."""
    has_gyro: torch.Tensor
    """... and its mask."""

    @property
    def pose(self) -> torch.Tensor:
        """(..., N, 3) ``[dx, dy, dpsi]``."""
        return torch.cat([self.fix, self.heading[..., None]], -1)

    @property
    def sigma(self) -> torch.Tensor:
        """(..., N, 3) ``[sx, sy, spsi]``."""
        return torch.cat([self.fix_sigma, self.heading_sigma[..., None]], -1)


_F = {name: FEATURES.index(name) for name in FEATURES}


def feature_channels(x: torch.Tensor) -> Features:
    """The columns of a receiver window's features (..., N, 15)
    (:data:`lbo.models.receiver_window.FEATURES`) by name."""
    def col(name: str) -> torch.Tensor:
        return x[..., _F[name]]

    return Features(x[..., _F["dx"]:_F["dx"] + 2], col("dpsi"), col("dcourse"),
                    x[..., _F["sx"]:_F["sx"] + 2], col("spsi"), col("s_course"), col("fix"),
                    col("heading"), col("course_held"), col("V"), col("delta"), col("r_m"),
                    col("gyro"))
