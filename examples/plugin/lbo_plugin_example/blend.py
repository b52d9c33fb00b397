"""A classical observer kept to lbo's stepper contract (docs/plugins.md): a constant-gain
filter on the kinematic bicycle.

The contract, in short: the class is built as ``Stepper(m0, vehicle, Q, R)`` over G
trajectories at once (m0 (G, 8): the first rows; Q (3, 3); R (G, 3, 3)), holds its state in
``x`` (G, n), the pose first, and its covariance in ``P`` (G, n, n), and ``update(m, u_prev)``
takes one row per trajectory (G, 8) and the inputs of the step before (G, 2) ``[V, delta]``,
and returns the poses (G, 3). lbo does the rest: the batch run, streaming, the test grid.
"""

from __future__ import annotations

import numpy as np

GAIN = 0.3
"""Share of each innovation taken (x, y and psi alike)."""


class BlendFilter:
    """Predict with the bicycle; at each row that holds a channel, move the pose by GAIN of
    its innovation. Its covariance is the fixes' R times GAIN (a blend of GAIN of a fix)."""

    def __init__(self, m0: np.ndarray, vehicle, Q: np.ndarray, R: np.ndarray) -> None:
        m0 = np.asarray(m0, dtype=float)
        self.dt, self.wheelbase = vehicle.dt, vehicle.wheelbase
        self.x = np.nan_to_num(m0[:, :3])  # no heading yet: 0, corrected by later fixes
        self.P = GAIN * np.asarray(R, dtype=float).copy()

    def update(self, m: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        v, delta = u_prev[:, 0], u_prev[:, 1]
        psi = self.x[:, 2]
        self.x = self.x + self.dt * np.stack(
            [v * np.cos(psi), v * np.sin(psi), v * np.tan(delta) / self.wheelbase], -1)
        y = np.asarray(m, dtype=float)[:, :3] - self.x
        y[:, 2] = (y[:, 2] + np.pi) % (2 * np.pi) - np.pi
        self.x = self.x + GAIN * np.nan_to_num(y)
        return self.x
