"""The side-slip observers served: the network's (``slip_gru``) and the learned filter's
(``slip_filter``) step as ONNX models, and their streams run by ONNX Runtime, one thread (a
car's computer), as ``lbo.observe`` runs the pose observers' graphs.

    from lbo.serve import lateral
    observer = lateral.load("outputs/slip/checkpoints/best.ckpt")  # or its MLflow run id
    stream = lateral.stream(observer, "onnx")
    beta, r = stream.step(vx, delta, ay, r_m)
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from lbo.core.errors import LboError
from lbo.models.slip import FEATURES, SlipObserver, SlipStream
from lbo.models.slip_filter import FilterObserver, FilterStream, StepGraph, load_any
from lbo.serve.engines import legacy_onnx, onnx_session

ENGINES = ("torch", "onnx")
"""What runs a stream's network (:func:`stream`)."""


def load(source: str) -> SlipObserver | FilterObserver:
    """The observer of ``source``: an ``lbo.train model=slip_gru`` or ``slip_filter``
    checkpoint file, its MLflow run id or a ``runs:/`` or ``models:/`` URI (in the store of
    ``MLFLOW_TRACKING_URI``), read as :func:`lbo.models.slip_filter.load_any` reads one."""
    from lbo.tracking.artifacts import checkpoint_file

    with checkpoint_file(source) as path:
        return load_any(path)


def onnx_bytes(observer: SlipObserver) -> bytes:
    """The observer's network as an ONNX model: input ``window`` (batch, N, 6) of raw
    :data:`~lbo.models.slip.FEATURES`, output ``fix`` (batch,) the correction (rad), float32.
    By the TorchScript-based exporter, which writes the GRU as ONNX's own GRU node."""
    example = torch.zeros(1, observer.window, len(FEATURES))
    with warnings.catch_warnings():
        # that a GRU with a dynamic batch "can cause an error" at another batch: its state
        # starts at zero, and batches of 1 to 300 give PyTorch's numbers (tests/test_slip.py)
        warnings.filterwarnings("ignore", message="Exporting a model to ONNX with a batch")
        return legacy_onnx(observer.net.eval(), (example,), (["window"], ["fix"]))


STEP_INPUTS = ["x", "P", "vx_prev", "delta_prev", "sq_prev", "started", "vx", "delta", "y"]
"""The inputs of the learned filter's ONNX step (:class:`lbo.models.slip_filter.StepGraph`)."""


def filter_onnx_bytes(observer: FilterObserver) -> bytes:
    """The learned side-slip filter's one-row step as an ONNX model, float64, batch dynamic
    (:class:`lbo.models.slip_filter.StepGraph`: inputs :data:`STEP_INPUTS`, outputs ``x``,
    ``P``, ``sq``), by the TorchScript-based exporter."""
    one = torch.ones(1, dtype=torch.float64)
    example = (torch.zeros(1, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64)[None],
               10 * one, 0 * one, 0 * one, one, 10 * one, 0 * one,
               torch.zeros(1, 2, dtype=torch.float64))
    return legacy_onnx(StepGraph(observer.net).eval(), example,
                       (STEP_INPUTS, ["x_next", "P_next", "sq"]))


class OnnxFilterStream:
    """The learned side-slip filter one row at a time in ONNX Runtime (one thread): the
    numbers of :class:`lbo.models.slip_filter.FilterStream` (tested to 1e-9)."""

    def __init__(self, observer: FilterObserver) -> None:
        self.session = onnx_session(filter_onnx_bytes(observer), threads=1)
        start = observer.net.start(1)
        self.x, self.P = start.x.numpy(), start.P.numpy()
        self.last: tuple[np.ndarray, ...] | None = None

    def step(self, vx: float, delta: float, ay: float, r: float) -> np.ndarray:
        """The estimate [beta rad, r rad/s] (2,) at this row (a NaN measurement is not
        held)."""
        v, d = np.array([vx], np.float64), np.array([delta], np.float64)
        first = self.last is None
        prev = (v, d, np.zeros(1)) if self.last is None else self.last
        out = self.session.run(None, dict(zip(STEP_INPUTS, (
            self.x, self.P, *prev, np.array([0.0 if first else 1.0]), v, d,
            np.array([[ay, r]], np.float64)))))
        self.x, self.P = out[0], out[1]
        self.last = (v, d, out[2])
        return self.x[0].copy()


def stream(observer: SlipObserver | FilterObserver, engine: str = "torch"
           ) -> SlipStream | FilterStream | OnnxFilterStream:
    """A stream of rows from the start of a log, run by ``engine``: ``torch``, or ``onnx``
    (ONNX Runtime, one thread: the side-slip network, or the learned filter's whole step)."""
    if engine not in ENGINES:
        raise LboError(f"engine: expected one of {list(ENGINES)}, got {engine!r}")
    if engine == "torch":
        return observer.stream()
    if isinstance(observer, FilterObserver):
        return OnnxFilterStream(observer)
    session = onnx_session(onnx_bytes(observer), threads=1)

    def correct(rows: np.ndarray) -> float:
        return float(session.run(None, {"window": rows[None]})[0][0])

    return observer.stream(correct)
