"""What undoes a car's input sensors' errors before a motion model reads them: a factor on the
speed, an offset and a factor on the steering (:class:`InputTerms`).

A CAN or wheel speed reads a percent or two off, and a steering angle comes with an offset and
through a ratio the user guessed; through a GNSS outage a filter runs on its motion model
alone, and these errors are most of its drift. :class:`lbo.Observer` takes the terms
(``inputs=``) and undoes every input with them; :mod:`lbo.learn.input_fit` learns them from a
log's fixes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lbo.core.checks import number
from lbo.sim.truth import Sensors


@dataclass(frozen=True)
class InputTerms:
    """What undoes a car's input sensors' errors: the true speed is ``speed_factor`` times the
    logged one, the road-wheel angle ``steering_factor`` times the logged steering less
    ``steering_offset`` (rad). The defaults undo nothing."""

    speed_factor: float = 1.0
    steering_offset: float = 0.0
    steering_factor: float = 1.0

    def __post_init__(self) -> None:
        number(self.speed_factor, "speed_factor", low=0.5, high=2.0)
        number(self.steering_offset, "steering_offset", low=-0.2, high=0.2)
        number(self.steering_factor, "steering_factor", low=0.5, high=2.0)

    @classmethod
    def told(cls, sensors: Sensors) -> InputTerms:
        """The terms that undo a simulated car's sensor errors (:class:`lbo.sim.truth.Sensors`:
        V logged ``1 + speed_scale`` times too high, ``steering_offset`` added to delta)."""
        return cls(1.0 / (1.0 + sensors.speed_scale), sensors.steering_offset, 1.0)

    def undo(self, u: np.ndarray) -> np.ndarray:
        """The inputs (..., 2) ``[V, delta]`` the terms make of logged ones (..., 2)."""
        u = np.asarray(u, dtype=float)
        return np.stack([u[..., 0] * self.speed_factor,
                         (u[..., 1] - self.steering_offset) * self.steering_factor], -1)

    def describe(self) -> str:
        """The terms as a line says them (mrad for the offset)."""
        return (f"speed x{self.speed_factor:.4f}, steering offset "
                f"{self.steering_offset * 1e3:.2f} mrad and factor x{self.steering_factor:.4f}")
