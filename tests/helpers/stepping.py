"""An observer stepped through a log sample by sample, as a control loop would feed it."""

from __future__ import annotations

from typing import Any

import numpy as np


def step_log(obs: Any, m: np.ndarray, u: np.ndarray, receiver: np.ndarray,
             steps: int | None = None) -> list[Any]:
    """The :class:`lbo.serve.estimate.Estimate` of each of the first ``steps`` (None: all) rows
    of a log, m (T, 3) (a NaN row: no fix), u (T, 2), receiver channels (T, 7), stepped in
    order from the observer's current state."""
    return [obs.step(m[k] if np.isfinite(m[k, 0]) else None, u[k], receiver[k])
            for k in range(len(m) if steps is None else steps)]
