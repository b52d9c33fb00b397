"""The side-slip observer served: its network as an ONNX model, and its stream run by ONNX
Runtime, one thread (a car's computer), as ``lbo.observe`` runs the pose observers' graphs.

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
from lbo.models.slip_filter import FilterObserver, FilterStream, load_any
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


def stream(observer: SlipObserver | FilterObserver, engine: str = "torch"
           ) -> SlipStream | FilterStream:
    """A stream of rows from the start of a log, its network run by ``engine``: ``torch``,
    or ``onnx`` (ONNX Runtime, one thread; the side-slip network's alone)."""
    if engine not in ENGINES:
        raise LboError(f"engine: expected one of {list(ENGINES)}, got {engine!r}")
    if engine == "torch":
        return observer.stream()
    if isinstance(observer, FilterObserver):
        raise LboError("engine: the learned side-slip filter (model=slip_filter) runs in "
                       "PyTorch alone; expected engine='torch'")
    session = onnx_session(onnx_bytes(observer), threads=1)

    def correct(rows: np.ndarray) -> float:
        return float(session.run(None, {"window": rows[None]})[0][0])

    return observer.stream(correct)
