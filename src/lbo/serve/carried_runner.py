"""A learned model carried from step to step: the runner of a model that keeps
:class:`lbo.models.carried.SequenceModel` (KalmanNet and Split-KalmanNet) in its recursive
form.

The model runs in float64 (:func:`lbo.models.carried.in_float64`), in the log's own
coordinates: one step of :func:`lbo.models.carried.run` per sample, or the same run over a
whole log. It gives no covariance, reads full poses only (no receiver channels), and runs in
PyTorch only. A model around the single-track body gives the ``[v_y, r]`` it carries
(``carries_lateral``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from lbo.core.errors import LboError
from lbo.models.carried import STARTED, body, carries_body, in_float64, run, run_arrays
from lbo.serve.estimate import Estimate, side_slip
from lbo.sim.measurements import Measurements


class CarriedRunner:
    """The model of ``net`` (a :class:`~lbo.models.net.WindowNet`) carried from its first
    fix; ``engine`` must be ``"torch"``."""

    first_valid = 0
    reads_receiver = False

    def __init__(self, name: str, net: Any, *, engine: str, device: str) -> None:
        if engine != "torch":
            raise LboError(f"engine={engine}: {name} carried from step to step runs in torch "
                           "only; use engine=torch, or form=window to run its window form "
                           f"on {engine}")
        self.device = device
        self.model = in_float64(net.net).to(device)
        self.carries_lateral = carries_body(self.model)
        self.reset()

    def reset(self) -> None:
        self.state: list[torch.Tensor] | None = None
        self.u_prev: torch.Tensor | None = None

    def log_rows(self, meas: Measurements, u: np.ndarray, source: str | None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """A checked log's poses (T, 3) and inputs (T, 2), as they are."""
        return meas.pose, u

    def sample(self, k: int, meas: Measurements, u: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """Sample ``k``'s pose (3,) and inputs (2,), as they are."""
        return meas.pose, u

    def take(self, k: int, m: np.ndarray, u: np.ndarray, fix: bool) -> Estimate:
        """The estimate after measurement m (3,) (NaN: no fix) and inputs u (2,); NaN until
        the first fix: one step of :func:`lbo.models.carried.run`, carried on."""
        row = np.asarray(m, np.float64) if fix else np.full(3, np.nan)
        uk = torch.as_tensor(np.asarray(u, np.float64), device=self.device)[None, None]
        with torch.inference_mode():
            est, self.state, *_ = run(self.model,
                                     torch.as_tensor(row, device=self.device)[None, None], uk,
                                     self.state, self.u_prev, covariance=False)
        self.u_prev = uk[:, 0]
        if not bool(self.state[STARTED][0]):
            return Estimate(np.full(3, np.nan), False, "no position fix yet")
        state = est[0, 0].cpu().numpy()
        finite = bool(np.isfinite(state).all())
        carried = body(self.state)[0].cpu().numpy() if self.carries_lateral else None
        return Estimate(state if finite else np.full(3, np.nan), finite,
                        "the network's estimate is not finite (diverged?)",
                        lateral=side_slip(carried, u[0], state))

    def run(self, m: np.ndarray, u: np.ndarray, fix: np.ndarray, smooth: bool = False,
            batch_size: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        mm = np.array(m, dtype=float)
        mm[~fix] = np.nan
        est, bodies = run_arrays(self.model, mm[None], u[None], self.device)
        est = np.where(np.isfinite(est[0]), est[0], np.nan)
        return (est, np.full((len(m), 3, 3), np.nan),
                side_slip(None if bodies is None else bodies[0], u[:, 0], est))
