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
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from lbo.core import sources
from lbo.core.errors import LboError
from lbo.core.paths import cache_dir
from lbo.models.checkpoint import hyperparameters, stored_lateral_error
from lbo.serve.engines import (
    OPSET,
    Coast,
    RecursiveStep,
    chunked,
    kept_export,
    onnx_session,
    onnx_step,
    recursive_onnx_bytes,
)
from lbo.serve.onnx_cache import SOURCES, version

FORMAT = 2
"""The layout of a kept folder (``observer.json``'s ``format``); 2: each graph's digest kept,
the hyperparameters read from the checkpoint."""
_VERSIONS = ("torch", "onnxscript", "onnxruntime")
"""The packages whose versions make or read the graphs."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class ExportedFilter:
    """The settings of a :class:`~lbo.models.filternet.WindowFilter` that an observer reads."""

    gyro: bool
    residual: int = 0
    drift: bool = False
    single_track: bool = False


@dataclasses.dataclass(frozen=True, kw_only=True)
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
    lateral_error: np.ndarray | None = None
    """As :attr:`lbo.models.net.WindowNet.lateral_error`, read from the checkpoint."""

    def recursive_step(self) -> tuple[RecursiveStep, list[np.ndarray], Coast | None]:
        """The step on numpy arrays (one-thread ONNX Runtime), the state of a filter that
        has seen nothing, and the coast over rows without a measurement (None where the
        filter does not coast): as :func:`lbo.serve.engines.make_recursive_step` gives."""
        names = tuple(name for name, _ in self.state)
        step = onnx_step(self._session("step.onnx"), names)
        state0 = [np.zeros(shape) for _, shape in self.state]
        if not self.coast_limit:
            return step, state0, None
        session = self._session("coast.onnx")
        inputs = [i.name for i in session.get_inputs()]

        def coast(u: np.ndarray, st: list) -> tuple:
            feed = dict(zip(("u", *names), (np.ascontiguousarray(u), *st)))
            pose, cov, *st = session.run(None, {k: feed[k] for k in inputs})
            return pose, cov, st

        return step, state0, chunked(coast, self.coast_limit)

    def _session(self, file: str) -> Any:
        """A one-thread ONNX Runtime session of a kept graph; one line where ONNX Runtime
        refuses it (its digest held: the graph was made by another ONNX Runtime?)."""
        try:
            return onnx_session(self.folder / file, threads=1)
        except Exception as e:  # noqa: BLE001  # ONNX Runtime's errors share no base
            raise DamagedGraphs(f"kept ONNX graphs {self.folder}: ONNX Runtime refuses {file} "
                                f"({str(e).strip().splitlines()[0][:200]}); delete the folder, "
                                "or run with engine=torch") from None


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


class DamagedGraphs(LboError):
    """A kept folder that fails its check: unreadable, of another layout, a graph missing or
    not the bytes its digest names, or settings the checkpoint does not hold."""


class KeptGraphsWarning(UserWarning):
    """The kept graphs of a checkpoint were damaged: the observer runs without them."""


def find(checkpoint: str | os.PathLike) -> tuple[ExportedNet, dict[str, Any]] | None:
    """The kept graphs of ``checkpoint`` as an :class:`ExportedNet`, and the checkpoint's
    hyperparameters; None where none are kept, where the kept folder fails its check
    (:class:`DamagedGraphs`) or where the checkpoint cannot be read without torch."""
    try:
        return _find(checkpoint)
    except DamagedGraphs:
        return None


def _find(checkpoint: str | os.PathLike) -> tuple[ExportedNet, dict[str, Any]] | None:
    """:func:`find`, raising :class:`DamagedGraphs` for a kept folder that fails its check.
    The hyperparameters are read from the checkpoint itself, without torch
    (:func:`lbo.models.checkpoint.hyperparameters`): the vehicle, noise and training
    envelope an observer is told are never the cache's."""
    where = folder(checkpoint)
    if not where.exists():
        return None
    hp = hyperparameters(checkpoint)
    if hp is None:  # read_checkpoint says why, in PyTorch
        return None
    return _read(where, hp), hp


def load(checkpoint: str | os.PathLike, engine: str) -> tuple[ExportedNet, dict[str, Any]] | None:
    """:func:`find`'s answer for ``Observer.load`` on ``engine`` (``auto`` or ``onnx``); a
    folder that fails its check is removed and said (:class:`KeptGraphsWarning`): ``auto``
    then runs the observer in PyTorch, ``onnx`` keeps its graphs again (:func:`keep`: from
    lbo's ONNX cache, else exported afresh, about 20 s; torch either way)."""
    try:
        return _find(checkpoint)
    except DamagedGraphs as e:
        discard(folder(checkpoint))
        then = ("running it in PyTorch (engine=onnx keeps them again)" if engine == "auto"
                else "keeping them again (an export, about 20 s, where lbo's ONNX cache "
                     "holds none)")
        warnings.warn(f"{e}; removed them, {then}", KeptGraphsWarning, stacklevel=3)
        if engine == "auto":
            return None
    from lbo.models.checkpoint import read_checkpoint  # torch: the export needs it

    keep(read_checkpoint(checkpoint)[0], checkpoint)
    return _find(checkpoint)


def discard(where: Path) -> None:
    """Remove a kept folder: renamed aside first, so that a folder kept afresh meanwhile
    under the same name is never the one removed."""
    aside = where.with_name(f".{where.name}.{os.getpid()}.removed")
    try:
        os.replace(where, aside)
    except OSError:
        return
    shutil.rmtree(aside, ignore_errors=True)


def digest(path: Path) -> str:
    """The SHA-256 of a file's bytes, in hex."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _read(where: Path, hp: dict[str, Any]) -> ExportedNet:
    """The :class:`ExportedNet` kept in the folder ``where`` for a checkpoint of
    hyperparameters ``hp``; raises :class:`DamagedGraphs` naming what fails."""
    name = f"kept ONNX graphs {where}"
    # the checkpoint's own, refused as read_checkpoint refuses it (not the graphs' damage)
    error = stored_lateral_error(f"the checkpoint of {name}", hp.get("meta") or {})
    try:
        info = json.loads((where / "observer.json").read_text())
    except (OSError, ValueError) as e:
        raise DamagedGraphs(f"{name}: observer.json unreadable ({e})") from None
    if not isinstance(info, dict) or info.get("format") != FORMAT:
        raise DamagedGraphs(f"{name}: observer.json is not of format {FORMAT}")
    try:
        files = dict(info["files"])
        if set(files) != {"step.onnx", *(("coast.onnx",) if info["coast_limit"] else ())}:
            raise DamagedGraphs(f"{name}: observer.json names the graphs {sorted(files)}")
        for file, expected in files.items():
            try:
                got = digest(where / file)
            except OSError as e:
                raise DamagedGraphs(f"{name}: {file} unreadable ({e.strerror})") from None
            if got != expected:
                raise DamagedGraphs(f"{name}: {file} is not the graph kept (its SHA-256 "
                                    f"{got[:12]}..., kept as {str(expected)[:12]}...)")
        model = hp["model"]["name"]
        return ExportedNet(model=str(model), window=int(hp["window"]),
                           features=str(hp["features"]), fixes=bool(hp.get("fixes", False)),
                           receiver=bool(hp.get("receiver", False)),
                           carried=hp.get("tbptt") is not None,
                           net=ExportedFilter(**info["net"]), folder=where,
                           state=tuple((str(n), tuple(int(d) for d in s))
                                       for n, s in info["state"]),
                           coast_limit=int(info["coast_limit"]), lateral_error=error)
    except (KeyError, TypeError, ValueError) as e:
        raise DamagedGraphs(f"{name}: observer.json or the checkpoint's settings "
                            f"unreadable ({type(e).__name__}: {e})") from None


def keep(net: Any, checkpoint: str | os.PathLike) -> Path:
    """Export the recursive form of ``net`` (a window filter's
    :class:`~lbo.models.net.WindowNet`, read from ``checkpoint``) and keep it for
    :func:`find`, replacing a folder that fails its check; returns the folder. Each graph
    comes through lbo's ONNX cache (:func:`lbo.serve.engines.kept_export`): a folder kept
    again, an ``engine=onnx`` session and ``lbo.export`` of the same model export nothing
    anew. Needs torch; raises :class:`~lbo.core.errors.LboError` where the model does not
    export."""
    from lbo.models.recursive import STATE_NAMES, RecursiveFilter

    target = folder(checkpoint)
    try:
        if _find(checkpoint) is not None:
            return target
    except DamagedGraphs:
        discard(target)

    def fresh() -> Any:
        # a filter per graph, each as lbo.export and engine=onnx build theirs: the cache key
        # reads the module's train/eval flag, and an export sets it to eval, so a filter
        # exported once keys the next graph differently from a cache hit's
        return RecursiveFilter(net.net.cpu())

    rec = fresh()
    inner = net.net
    graphs = {"step.onnx": kept_export(rec, "recursive", lambda: recursive_onnx_bytes(rec))[0]}
    if rec.coasts:
        coasting = fresh()
        graphs["coast.onnx"] = kept_export(coasting, "coast",
                                           lambda: _coast_bytes(coasting))[0]
    # only what the checkpoint's hyperparameters do not hold, and each graph's digest:
    # whatever an observer is told about its training (vehicle, noise, envelope) is read
    # from the checkpoint itself (find)
    info = {"format": FORMAT, "coast_limit": rec.coast_limit if rec.coasts else 0,
            "state": [[n, list(s.shape)] for n, s in zip(STATE_NAMES, rec.initial_state(1))],
            "net": {"gyro": bool(inner.gyro), "residual": int(inner.residual),
                    "drift": bool(inner.drift), "single_track": bool(inner.single_track)},
            "files": {name: hashlib.sha256(data).hexdigest() for name, data in graphs.items()}}
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    try:
        for name, data in graphs.items():
            (tmp / name).write_bytes(data)
        (tmp / "observer.json").write_text(json.dumps(info, indent=1))
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
