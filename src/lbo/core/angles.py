"""Angles: the one home of wrapping a heading to (-pi, pi] in NumPy (the torch form, for the
networks and filters written in torch, is :func:`lbo.models.poses.wrap_angle_torch`)."""

from __future__ import annotations

import numpy as np


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles (any shape, rad) wrapped to (-pi, pi]."""
    return np.pi - np.mod(np.pi - a, 2 * np.pi)
