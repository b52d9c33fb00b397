"""A simulated single-antenna drive with a biased gyro: what the gyro EKF's noise fits are
tested and timed on (``tests/``, ``benchmarks/bench_gyro_fit.py``)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from lbo.sim.columns import RECEIVER
from lbo.sim.receiver import ReceiverSpec, sense
from lbo.sim.vehicle import Vehicle, simulate

VEHICLE = Vehicle()
"""The car it drives (the paper's, at its dt)."""


def draw(seed: int, seconds: float = 60.0, reported: float = 1.0) -> pd.DataFrame:
    """A log of ``seconds`` (rows at :data:`VEHICLE`'s dt): the car weaves at 5-11 m/s, stops
    for 4 s a third of the way in (a zero-rate update) and drives on; the receiver's fixes
    with their reported accuracy (times ``reported``: 1 tracks the true error's scale), no
    heading (one antenna), its velocity, and a biased gyro ``r_m`` at every row; the truth in
    ``x, y, psi``."""
    t = int(round(seconds / VEHICLE.dt))
    k = np.arange(t)
    speed = 8.0 + 3.0 * np.sin(2 * np.pi * k / 1500)
    speed[(k > t // 3) & (k < t // 3 + 200)] = 0.0
    u = np.stack([speed, 0.08 * np.sin(2 * np.pi * k / 700)], axis=1)[None]
    rng = np.random.default_rng(seed)
    z = simulate(np.zeros((1, 3)), u, VEHICLE.dt, VEHICLE.wheelbase, np.zeros(3), rng)
    out = sense(z, u, VEHICLE.dt, ReceiverSpec(), 1.0, rng)
    cols = {c: out[c][0] if c in out else np.full(t, np.nan)  # spsi_m: one antenna
            for c in ("x_m", "y_m", "psi_m", *RECEIVER)}
    cols["sx_m"], cols["sy_m"] = reported * cols["sx_m"], reported * cols["sy_m"]
    return pd.DataFrame({"t": k * VEHICLE.dt, **cols, "V": u[0, :, 0], "delta": u[0, :, 1],
                         "x": z[0, :, 0], "y": z[0, :, 1], "psi": z[0, :, 2]})
