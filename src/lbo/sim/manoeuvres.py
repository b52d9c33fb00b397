"""The validation path and the 15 named test manoeuvres, built from clothoids.

Each manoeuvre fixes its geometry, its number of scored steps and the shape of its speed
profile; the mean speed follows from the path length and the step count. The step counts
add up to the paper's 9,829 scored test points.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import KW_ONLY, dataclass

import numpy as np
from pyclothoids import Clothoid

from lbo.sim.clothoid import Pose, end_pose, spiral, through


class Chain:
    """Builds a path piece by piece: straights, clothoid-eased turns, free spirals."""

    def __init__(self, start: Pose = (0.0, 0.0, 0.0)):
        self.segments: list[Clothoid] = []
        self._start = start

    @property
    def pose(self) -> Pose:
        return end_pose(self.segments[-1]) if self.segments else self._start

    def straight(self, length: float) -> Chain:
        self.segments.append(spiral(self.pose, 0.0, 0.0, length))
        return self

    def spiral(self, kappa0: float, kappa1: float, length: float) -> Chain:
        self.segments.append(spiral(self.pose, kappa0, kappa1, length))
        return self

    def turn(self, radius: float, angle_deg: float, transition: float) -> Chain:
        """Turn by angle (left > 0) on a circle of ``radius`` entered and left by clothoids."""
        kappa = np.sign(angle_deg) / radius
        arc = abs(np.radians(angle_deg)) - transition / radius  # each easing turns by L/(2R)
        if arc <= 0:
            raise ValueError("transition too long for this turn")
        self.spiral(0.0, kappa, transition).spiral(kappa, kappa, arc * radius)
        return self.spiral(kappa, 0.0, transition)


def _poses(*xy_heading_deg: tuple[float, float, float]) -> list[Clothoid]:
    return through([(x, y, np.radians(h)) for x, y, h in xy_heading_deg])


def _weave(spacings: list[float], amplitude: float) -> list[Clothoid]:
    xs = np.r_[0.0, 15.0, 15.0 + np.cumsum(spacings)]
    ys = np.r_[0.0, 0.0, amplitude * (-1.0) ** np.arange(len(spacings))]
    ys[-1] = 0.0
    return _poses(*[(x, y, 0.0) for x, y in zip(xs, ys)], (xs[-1] + 15.0, 0.0, 0.0))


def _on_circle(radius_at: list[tuple[float, float]]) -> list[Clothoid]:
    """Poses on circles about the origin, travelled anticlockwise: (angle_deg, radius)."""
    return _poses(*[(r * np.cos(np.radians(a)), r * np.sin(np.radians(a)), a + 90.0)
                    for a, r in radius_at])


@dataclass(frozen=True)
class Manoeuvre:
    """A test manoeuvre: geometry, scored steps, and speed shape (start, end) around its mean."""

    build: Callable[[], list[Clothoid]]
    steps: int
    _: KW_ONLY
    speed_shape: tuple[float, float] = (1.0, 1.0)
    about: str = ""


MANOEUVRES: dict[str, Manoeuvre] = {
    "double_lane_change": Manoeuvre(
        lambda: _poses((0, 0, 0), (15, 0, 0), (45, 3.5, 0), (70, 3.5, 0), (95, 0, 0), (125, 0, 0)),
        450, about="ISO 3888-1 double lane change"),
    "emergency_avoidance": Manoeuvre(
        lambda: _poses((0, 0, 0), (10, 0, 0), (22, 3.0, 0), (30, 3.0, 0), (42, 0, 0), (70, 0, 0)),
        350, speed_shape=(1.2, 0.8), about="sudden swerve round an obstacle while braking"),
    "slalom": Manoeuvre(lambda: _weave([18.0] * 9, 1.8), 850, about="nine cones 18 m apart"),
    "hairpin": Manoeuvre(lambda: Chain().straight(15).turn(10, 180, 8).straight(15).segments,
                         550, speed_shape=(1.1, 0.9), about="180 degree turn of radius 10 m"),
    "roundabout": Manoeuvre(
        lambda: Chain().straight(20).turn(12, -35, 5).turn(15, 250, 6).turn(12, -35, 5)
        .straight(20).segments, 1100, about="enter, three quarters round, exit"),
    "figure_eight": Manoeuvre(
        lambda: Chain().turn(15, 355, 6).turn(15, -355, 6).segments, 1300,
        about="two loops of radius 15 m"),
    "chicane": Manoeuvre(
        lambda: _poses((0, 0, 0), (20, 0, 0), (30, 4, 45), (40, 8, 0), (50, 4, -45), (60, 0, 0),
                       (80, 0, 0)), 500, about="tight S at 45 degrees"),
    "tightening_spiral": Manoeuvre(
        lambda: Chain().straight(10).spiral(0.01, 0.12, 120).segments, 700,
        speed_shape=(1.2, 0.8), about="curvature rising from 1/100 to 1/8.3 m"),
    "braking_in_bend": Manoeuvre(
        lambda: Chain().straight(20).turn(40, 90, 15).straight(20).segments, 500,
        speed_shape=(1.6, 0.45), about="hard braking in a 40 m bend"),
    "right_angle_turn": Manoeuvre(
        lambda: Chain().straight(25).turn(8, -90, 4).straight(25).segments, 550,
        speed_shape=(1.1, 0.9), about="urban 90 degree corner"),
    "cloverleaf_ramp": Manoeuvre(
        lambda: Chain().straight(20).turn(25, 270, 15).straight(20).segments, 750,
        about="270 degree motorway loop"),
    "weave": Manoeuvre(lambda: _weave([30, 26, 22, 19, 16, 14, 12, 12], 2.0), 650,
                       about="slalom with shrinking spacing"),
    "lane_change_in_bend": Manoeuvre(
        lambda: _on_circle([(0, 80), (15, 80), (30, 76.5), (45, 76.5), (60, 80), (75, 80)]), 400,
        about="3.5 m lane change in an 80 m bend"),
    "s_curve": Manoeuvre(
        lambda: Chain().straight(15).turn(20, 90, 6).turn(20, -90, 6).straight(15).segments,
        620, about="two opposite 90 degree bends"),
    "accelerating_exit": Manoeuvre(
        lambda: Chain().straight(10).turn(15, 90, 5).straight(70).segments, 559,
        speed_shape=(0.45, 1.55), about="full throttle out of a 15 m corner"),
}


def validation_path(length: float = 200.0, amplitude: float = 5.0,
                    period: float = 100.0) -> list[Clothoid]:
    """Clothoid sinusoid between y=+amplitude and -amplitude over ``length`` m of x.

    Poses sit on y = amplitude sin(2 pi x / period) at every quarter period, with the
    sinusoid's own heading.
    """
    xs = np.arange(0.0, length + 1e-9, period / 4)
    ys = amplitude * np.sin(2 * np.pi * xs / period)
    slope = amplitude * 2 * np.pi / period * np.cos(2 * np.pi * xs / period)
    heading = np.degrees(np.arctan(slope))
    return _poses(*zip(xs, ys, heading))
