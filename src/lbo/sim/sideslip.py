"""A real car at the limit of its tyres, with its side slip measured: the MBDS side-slip run.

The MBDS/sideslip-angle-vehicle-estimation repository (MIT, (c) 2021 Jose Luis Blanco-Claraco)
ships one run, 550 s at 100 Hz (vx 16 to 61 m/s, lateral acceleration up to 16.6 m/s^2), and
lbo ships its channels (``data/sideslip/``, with the licence). :func:`example` reads it as a
frame of lbo's names:

- the inputs: ``vx`` (m/s), the road wheels' steering ``delta`` (rad; ``delta_fl``,
  ``delta_fr`` each front wheel's);
- the measurements: ``r_m`` the yaw rate (rad/s), ``ax_m``, ``ay_m`` (m/s^2, at the centre of
  gravity);
- the truth, from the INS: ``vy`` (m/s) and ``beta`` = atan2(vy, vx) (rad). No observer may
  read them (:data:`TRUTH`): they are what it estimates.

``t`` is the run's own clock (s, from 150 s). The repository's text files are in rad and rad/s
but for ``yawRateFilt``, in deg/s, which lbo leaves out. :data:`CAR` holds the car's
parameters from the repository's code; :func:`split` cuts the run by time into the spans a
learned observer trains, validates and is tested on.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from lbo.core.paths import shipped
from lbo.sim.dynamic import G, SingleTrack

EXAMPLE = "run.npz"
"""The run's arrays (``data/sideslip/``), keyed by the repository's file names."""
COLUMNS = {"t": "t", "vx": "vx", "delta": "delta", "deltaFL": "delta_fl",
           "deltaFR": "delta_fr", "yawRate": "r_m", "axCG": "ax_m", "ayCG": "ay_m",
           "vy": "vy", "beta_true": "beta"}
"""The repository's file name -> lbo's column."""
INPUTS = ("vx", "delta")
MEASURED = ("ay_m", "r_m")
TRUTH = ("vy", "beta")
"""The columns an observer reads (inputs, measurements) and those it never reads (the INS's)."""
DT = 0.01
"""The run's sampling period (s)."""
CAR = SingleTrack(mass=982.0, yaw_inertia=982.0 / 12 * (1.7**2 + 4.09**2), l_f=1.33,
                  l_r=1.07, c_f=0.7e5, c_r=1.2e5)
"""The car as the repository's linear Kalman filter has it (``BetaStanfordLinear.m``): 982 kg,
the yaw inertia of a 1.7 m by 4.09 m box, the axles 1.33 m and 1.07 m from the centre of
gravity, 70 and 120 kN/rad of cornering stiffness."""
SPANS = (("train", 0.6), ("val", 0.2), ("test", 0.2))
"""The spans in time order and their shares of the run."""


def example() -> pd.DataFrame:
    """The shipped run, (55001 rows) with the columns of :data:`COLUMNS`, float64."""
    arrays = shipped("sideslip", EXAMPLE)
    return pd.DataFrame({ours: arrays[theirs].astype(np.float64)
                         for theirs, ours in COLUMNS.items()})


def split(run: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """The run cut by time into :data:`SPANS` (the first 60% to train, the next 20% to
    validate, the last 20% to test), each a contiguous slice with its index from 0."""
    edges = np.round(np.cumsum([0.0, *(share for _, share in SPANS)]) * len(run)).astype(int)
    return {name: run.iloc[a:b].reset_index(drop=True)
            for (name, _), a, b in zip(SPANS, edges[:-1], edges[1:], strict=True)}


def observed(run: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What an observer reads of the run, and nothing else: vx (T,), delta (T,) and the
    measurements y (T, 2) [ay_m, r_m], as :func:`lbo.filters.lateral.linear_single_track`
    takes them. The truth (:data:`TRUTH`) stays in the frame."""
    return (run["vx"].to_numpy(float), run["delta"].to_numpy(float),
            run[list(MEASURED)].to_numpy(float))


def friction(span: pd.DataFrame, share: float = 99.9) -> float:
    """The tyres' friction coefficient read off a span (the training one): the ``share``
    percentile of its lateral acceleration over g. The car reached 1.26 g on the training span
    (1.69 g at its single largest reading, which the percentile leaves out as a spike)."""
    return float(np.percentile(np.abs(span["ay_m"].to_numpy(float)), share) / G)
