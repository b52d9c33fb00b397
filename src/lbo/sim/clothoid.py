"""Paths made of clothoids, sampled by arc length.

Clothoids come from pyclothoids (G1 Hermite fits between poses, or given curvature
and sharpness); sampling integrates the heading theta(s) = theta0 + kappa0 s + dk s^2 / 2
in numpy, so no Python loop runs per sample.
"""

from __future__ import annotations

import numpy as np
from pyclothoids import Clothoid

Pose = tuple[float, float, float]  # x (m), y (m), heading (rad)


def through(poses: list[Pose]) -> list[Clothoid]:
    """G1 Hermite clothoids joining consecutive poses."""
    return [Clothoid.G1Hermite(*a, *b) for a, b in zip(poses[:-1], poses[1:])]


def spiral(start: Pose, kappa0: float, kappa1: float, length: float) -> Clothoid:
    """One clothoid whose curvature goes linearly from kappa0 to kappa1 over ``length`` m."""
    return Clothoid.StandardParams(*start, kappa0, (kappa1 - kappa0) / length, length)


def end_pose(c: Clothoid) -> Pose:
    return (c.X(c.length), c.Y(c.length), c.Theta(c.length))


def path_length(segments: list[Clothoid]) -> float:
    return float(sum(c.length for c in segments))


def _straight(x0: float, y0: float, theta: float, s: np.ndarray) -> np.ndarray:
    return np.stack([x0 + s * np.cos(theta), y0 + s * np.sin(theta), np.full_like(s, theta)], 1)


def sample(segments: list[Clothoid], ds: float = 0.1, lead_in: float = 0.0,
           tail: float = 0.0) -> np.ndarray:
    """Sample a chain of clothoids every ``ds`` metres.

    A straight of ``lead_in`` metres is put before the first segment and one of ``tail``
    metres after the last, along their headings.

    Returns
    -------
    (P, 4) rows ``[s, x, y, theta]``; s is the arc length from the start of the lead-in.
    """
    x0, y0, t0 = segments[0].Parameters[:3]
    pieces = [_straight(x0, y0, t0, np.arange(-lead_in, 0.0, ds))] if lead_in > 0 else []
    for c in segments:
        x, y, th, k0, dk, length = c.Parameters
        n = max(int(np.ceil(length / ds)), 1)
        h = length / n
        s_mid = (np.arange(n) + 0.5) * h
        th_mid = th + k0 * s_mid + 0.5 * dk * s_mid**2  # midpoint rule, error O(h^3) per step
        xs = x + np.r_[0.0, np.cumsum(h * np.cos(th_mid))][:-1]
        ys = y + np.r_[0.0, np.cumsum(h * np.sin(th_mid))][:-1]
        s0 = np.arange(n) * h
        pieces.append(np.stack([xs, ys, th + k0 * s0 + 0.5 * dk * s0**2], 1))
    xe, ye, te = end_pose(segments[-1])
    pieces.append(_straight(xe, ye, te, np.arange(0.0, tail + ds, ds)))
    xyt = np.concatenate(pieces)
    xyt[:, 2] = np.unwrap(xyt[:, 2])
    arc = np.r_[0.0, np.cumsum(np.hypot(*np.diff(xyt[:, :2], axis=0).T))]
    return np.column_stack([arc, xyt])
