"""The robust observer's recursive form kept as ONNX graphs, read back without torch.

Importing torch takes 1.2-1.6 s on a 2-core machine, longer than the EKF takes for a whole
``lbo.observe`` of a 5000-row log. So ``lbo.train`` keeps, for an observer whose default form
is the recursive one (the robust observer, :func:`lbo.serve.runners.default_form`), what
running it needs and nothing of torch's: its step (:func:`lbo.serve.engines.recursive_onnx_bytes`)
and its coast over rows without a measurement (:meth:`lbo.models.recursive.RecursiveFilter.coast`)
as ONNX graphs, and ``observer.json``: the checkpoint's hyperparameters, the net's settings an
:class:`~lbo.serve.observer.Observer` reads (:class:`ExportedNet`) and the state's shapes.

They lie in lbo's cache folder (:func:`lbo.core.paths.cache_dir`, ``onnx/observer-<key>/``),
under a digest of the checkpoint file's bytes, the source of the lbo packages the graphs are
traced from, the exporters' and ONNX Runtime's versions and the opset: a checkpoint that
changes, or an lbo whose filter changes, finds none, and runs in PyTorch as before.
``Observer.load(..., engine="auto")`` (``lbo.observe``'s default) and ``engine="onnx"`` read
them where they are kept. The folder is written beside its final name and renamed into place
whole, so a killed export leaves none half-written.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from lbo.core import sources
from lbo.core.errors import LboError
from lbo.core.paths import cache_dir
from lbo.serve.engines import OPSET, Coast, RecursiveStep, chunked, onnx_session, onnx_step
from lbo.serve.onnx_cache import SOURCES, version

FORMAT = 1
"""The layout of a kept folder (``observer.json``'s ``format``)."""
_VERSIONS = ("torch", "onnxscript", "onnxruntime")
"""The packages whose versions make or read the graphs."""


@dataclasses.dataclass(frozen=True)
class ExportedFilter:
    """The settings of a :class:`~lbo.models.filternet.WindowFilter` that an observer reads."""

    gyro: bool
    residual: int = 0
    drift: bool = False
    single_track: bool = False


@dataclasses.dataclass(frozen=True)
class ExportedNet:
    """What an :class:`~lbo.serve.observer.Observer` reads of a window filter's
    :class:`~lbo.models.net.WindowNet`, for its recursive form kept as ONNX graphs in
    ``folder``; ``state`` holds each state tensor's name and shape
    (:meth:`lbo.models.recursive.RecursiveFilter.initial_state` of one filter), ``coast_limit``
    the most rows one coast takes (0: the filter does not coast)."""

    model: str
    window: int
    features: str
    fixes: bool
    net: ExportedFilter
    folder: Path
    state: tuple[tuple[str, tuple[int, ...]], ...]
    coast_limit: int
    receiver: bool = False
    carried: bool = False

    def recursive_step(self) -> tuple[RecursiveStep, list[np.ndarray], Coast | None]:
        """The step on numpy arrays (one-thread ONNX Runtime), the state of a filter that
        has seen nothing, and the coast over rows without a measurement (None where the
        filter does not coast): as :func:`lbo.serve.engines.make_recursive_step` gives."""
        names = tuple(name for name, _ in self.state)
        step = onnx_step(onnx_session(self.folder / "step.onnx", threads=1), names)
        state0 = [np.zeros(shape) for _, shape in self.state]
        if not self.coast_limit:
            return step, state0, None
        session = onnx_session(self.folder / "coast.onnx", threads=1)
        inputs = [i.name for i in session.get_inputs()]

        def coast(u: np.ndarray, st: list) -> tuple:
            feed = dict(zip(("u", *names), (np.ascontiguousarray(u), *st)))
            pose, cov, *st = session.run(None, {k: feed[k] for k in inputs})
            return pose, cov, st

        return step, state0, chunked(coast, self.coast_limit)


def key(checkpoint: str | os.PathLike) -> str:
    """The digest (24 hex digits) the graphs of ``checkpoint`` are kept under (see the
    module); read without torch."""
    h = hashlib.sha256()
    for part in (str(FORMAT), str(OPSET), sources.source_digest(SOURCES),
                 *(version(p) for p in _VERSIONS)):
        h.update(part.encode() + b"\0")
    h.update(Path(checkpoint).read_bytes())
    return h.hexdigest()[:24]


def folder(checkpoint: str | os.PathLike) -> Path:
    """Where the graphs of ``checkpoint`` are kept."""
    return cache_dir() / "onnx" / f"observer-{key(checkpoint)}"


def find(checkpoint: str | os.PathLike) -> tuple[ExportedNet, dict[str, Any]] | None:
    """The kept graphs of ``checkpoint`` as an :class:`ExportedNet`, and the checkpoint's
    hyperparameters; None where none are kept (or they cannot be read)."""
    return _read(folder(checkpoint))


def _read(where: Path) -> tuple[ExportedNet, dict[str, Any]] | None:
    """:func:`find`'s answer for the folder ``where``."""
    try:
        info = json.loads((where / "observer.json").read_text())
        if info.get("format") != FORMAT or not all(
                (where / f).is_file() for f in ("step.onnx", *(("coast.onnx",)
                                                               if info["coast_limit"] else ()))):
            return None
        net = ExportedNet(**{**info["net"], "net": ExportedFilter(**info["net"]["net"]),
                             "folder": where,
                             "state": tuple((n, tuple(s)) for n, s in info["state"]),
                             "coast_limit": int(info["coast_limit"])})
        return net, info["hparams"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def keep(net: Any, hp: dict[str, Any], checkpoint: str | os.PathLike) -> Path:
    """Export the recursive form of ``net`` (a window filter's
    :class:`~lbo.models.net.WindowNet`, read from ``checkpoint`` with its hyperparameters
    ``hp``) and keep it for :func:`find`; returns the folder. Needs torch; raises
    :class:`~lbo.core.errors.LboError` where the model does not export."""
    from lbo.models.recursive import STATE_NAMES, RecursiveFilter
    from lbo.serve.engines import recursive_onnx_bytes

    target = folder(checkpoint)
    if _read(target) is not None:
        return target
    rec = RecursiveFilter(net.net.cpu()).eval()
    inner = net.net
    info = {"format": FORMAT, "hparams": hp, "coast_limit": rec.coast_limit if rec.coasts else 0,
            "state": [[n, list(s.shape)] for n, s in zip(STATE_NAMES, rec.initial_state(1))],
            "net": {"model": net.model, "window": int(net.window), "features": net.features,
                    "fixes": bool(net.fixes), "receiver": bool(net.receiver),
                    "carried": bool(getattr(net, "carried", False)),
                    "net": {"gyro": bool(inner.gyro), "residual": int(inner.residual),
                            "drift": bool(inner.drift),
                            "single_track": bool(inner.single_track)}}}
    try:
        described = json.dumps(info, indent=1)
    except (TypeError, ValueError) as e:  # a plug-in's setting of a type JSON has not
        raise LboError(f"checkpoint {checkpoint}: its settings do not fit JSON ({e})") from None
    graphs = {"step.onnx": recursive_onnx_bytes(rec)}
    if rec.coasts:
        graphs["coast.onnx"] = _coast_bytes(rec)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    try:
        for name, data in graphs.items():
            (tmp / name).write_bytes(data)
        (tmp / "observer.json").write_text(described)
        os.replace(tmp, target)  # whole, or not at all
    except OSError:
        if not target.is_dir():
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target


def _coast_bytes(rec: Any) -> bytes:
    """ONNX model of ``rec.coast`` (:meth:`~lbo.models.recursive.RecursiveFilter.coast`), by
    the dynamo exporter: inputs ``u`` (K, I), K rows from 1 to ``coast_limit``, and the state
    tensors of one started filter, named as :data:`~lbo.models.recursive.STATE_NAMES`;
    outputs ``pose`` (K, 3), ``cov`` (K, 3, 3) and ``next_<name>`` for each state tensor."""
    import torch

    from lbo.models.recursive import STATE_NAMES
    from lbo.serve.engines import dynamo_onnx, exporting, recursive_example

    class Coast(torch.nn.Module):  # the exporter exports a module's forward
        def __init__(self) -> None:
            super().__init__()
            self.rec = rec

        def forward(self, u: torch.Tensor, *state: torch.Tensor) -> tuple[torch.Tensor, ...]:
            return self.rec.coast(u, *state)

    m, u, *state = recursive_example(rec)
    with torch.inference_mode():  # a started filter: its first fix taken
        state = list(rec(m, u, *state)[2:])
    rows = torch.tensor([[10.0, 0.02, 0.007][:len(rec.inputs)]] * 4, dtype=torch.float64)
    names = (["u", *STATE_NAMES], ["pose", "cov", *(f"next_{n}" for n in STATE_NAMES)])
    # K dynamic (a named Dim with bounds was specialised to the example's K); the state static:
    # {} per tensor, as a tuple of None alone is read back as a list that fits no input
    dynamic = {"u": {0: torch.export.Dim.DYNAMIC}, "state": tuple({} for _ in STATE_NAMES)}
    return exporting("ONNX", rec, lambda: dynamo_onnx(Coast().eval(), (rows, *state), names,
                                                        dynamic))
