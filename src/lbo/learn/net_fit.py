"""Training a window net that reads a receiver on logs with truth: a real drive's train span.

``lbo.train`` teaches a net on simulated receivers, drawn afresh per window. A real drive
gives one receiver, one gyro, one car: :func:`fit` trains on its windows as they are.

- The windows are every N consecutive rows of a log that hold a position fix, read as an
  observer reads the log (:func:`lbo.serve.rows.receiver_rows`: the filters' row, ``V,
  delta`` and the gyro's ``r_m``); each one's target is the truth at its last row. A window
  that holds no heading teaches none (:meth:`lbo.models.net.WindowNet.loss`).
- **Fine-tuned** (``fresh=False``): from the net's weights and normalisation. **From
  scratch** (``fresh=True``): its architecture, its parameters drawn anew from ``seed``, its
  normalisation the train windows' (:meth:`~lbo.models.net.WindowNet.statistics`).
- Adam at ``lr``; each epoch visits every train window once, in minibatches of ``batch``
  in an order drawn from ``seed``. After each epoch the loss over every validation window;
  the weights kept are those with the lowest (epoch 0: the start).

:func:`fit_and_write` writes the net kept as a checkpoint that every lbo command loads
(``lbo.observe observer=<file>``): the source's hyperparameters, with the envelope of the
inputs it has now seen (:class:`lbo.models.envelope.Envelope`) and what it was trained on.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from lbo.core.errors import LboError
from lbo.learn.eta import more
from lbo.models.envelope import Envelope
from lbo.models.features import window_view
from lbo.serve.rows import receiver_rows, window_series
from lbo.sim.columns import INPUT, MEAS, STATE
from lbo.sim.measurements import Measurements

__all__ = ["LogWindows", "NetFit", "fit", "fit_and_write", "log_windows"]


@dataclass(frozen=True, kw_only=True)
class LogWindows:
    """The windows of logs with truth, as views.

    series : (T, 11) every log's rows, one after the other
        (:data:`lbo.models.receiver_window.COLUMNS`), float64.
    truth : (T, 3) the true pose of each row.
    ends : (W,) the row each window ends at (it holds rows ``end - N + 1 .. end``, of one log).
    window : N.
    """

    series: torch.Tensor
    truth: torch.Tensor
    ends: torch.Tensor
    window: int

    def __len__(self) -> int:
        return len(self.ends)

    def batch(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Windows (B, N, 11) and their true states (B, 3) of windows ``idx`` (B,)."""
        ends = self.ends[idx]
        return window_view(self.series, self.window)[ends - self.window + 1], self.truth[ends]


def log_windows(logs: pd.DataFrame | Sequence[pd.DataFrame], window: int,
                wheelbase: float) -> LogWindows:
    """Every window of ``window`` rows of each log (with truth) that holds a position fix."""
    logs = [logs] if isinstance(logs, pd.DataFrame) else list(logs)
    series, truth, ends, offset = [], [], [], 0
    for log in logs:
        meas = Measurements.from_frame(log)
        if not meas.reads_receiver:
            raise LboError("training on a log: a net that reads a receiver needs its channels "
                           "(sx_m, sy_m, ve_m, vn_m, sv_m, r_m); this log has none")
        u = log[list(INPUT)].to_numpy(dtype=float)
        series.append(window_series(receiver_rows(meas, u, wheelbase), u))
        truth.append(log[list(STATE)].to_numpy(dtype=float))
        fixes = np.concatenate([[0], np.cumsum(meas.has_fix)])
        end = np.arange(window - 1, len(log))
        ends.append(offset + end[fixes[end + 1] - fixes[end + 1 - window] > 0])
        offset += len(log)
    out = LogWindows(series=torch.from_numpy(np.concatenate(series)),
                     truth=torch.from_numpy(np.concatenate(truth)),
                     ends=torch.from_numpy(np.concatenate(ends)), window=int(window))
    if not len(out):
        raise LboError(f"training on a log: no window of {window} rows holds a position fix")
    return out


@dataclass(frozen=True)
class NetFit:
    """What :func:`fit` trained.

    net : the net with the lowest validation loss (eval mode).
    history : one row per epoch: ``epoch, loss`` (train, the mean over its minibatches; NaN
        at epoch 0), ``val`` (the loss over every validation window) and ``seconds``.
    best_epoch : the epoch of ``net`` (0: the start).
    """

    net: Any
    history: pd.DataFrame
    best_epoch: int


def _check_reads_receiver(net: Any) -> None:
    if not getattr(net, "receiver", False):
        raise LboError(f"training on a log: {net.model}-N{net.window} does not read a "
                       "receiver (train one with experiment=receiver)")


def _val_loss(net: Any, val: LogWindows, chunk: int = 1024) -> float:
    with torch.no_grad():
        total = 0.0
        for s in range(0, len(val), chunk):
            idx = torch.arange(s, min(s + chunk, len(val)))
            total += float(net.loss(*val.batch(idx))) * len(idx)
    return total / len(val)


def fit(net: Any, train: LogWindows, val: LogWindows, *, epochs: int, lr: float,
        batch: int = 256, seed: int = 0, fresh: bool = False,
        progress: Callable[[str], None] | None = None) -> NetFit:
    """Train a copy of ``net`` (a :class:`~lbo.models.net.WindowNet` that reads a receiver) on
    ``train``'s windows, keeping the epoch with the lowest loss on ``val``'s (see the module's
    docstring); ``fresh``: from new parameters drawn from ``seed`` and the train windows'
    normalisation. ``progress`` gets one line per epoch, and after the first how long the
    others will take."""
    _check_reads_receiver(net)
    net = copy.deepcopy(net)  # float32 parameters, float64 buffers, as lbo.train keeps them
    g = torch.Generator().manual_seed(seed)
    if fresh:
        with torch.random.fork_rng():  # the caller's random stream is left as it was
            torch.manual_seed(seed)
            net.renew()  # every parameter, a window filter's own scalars included
        pick = torch.randperm(len(train), generator=g)[:20_000]
        net.set_normalisation(**net.statistics(*train.batch(pick)))
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    net.eval()
    best, best_epoch = _val_loss(net, val), 0
    kept = copy.deepcopy(net.state_dict())
    rows = [{"epoch": 0, "loss": float("nan"), "val": best, "seconds": 0.0}]
    for epoch in range(1, epochs + 1):
        begin, losses = time.perf_counter(), []
        net.train()
        for idx in torch.randperm(len(train), generator=g).split(batch):
            loss = net.loss(*train.batch(idx))
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item())
        net.eval()
        val_loss = _val_loss(net, val)
        rows.append({"epoch": epoch, "loss": float(np.mean(losses)), "val": val_loss,
                     "seconds": time.perf_counter() - begin})
        if val_loss < best:
            best, best_epoch, kept = val_loss, epoch, copy.deepcopy(net.state_dict())
        if progress is not None:
            progress(f"epoch {epoch}/{epochs}: loss {rows[-1]['loss']:.4f}, val {val_loss:.4f}"
                     f"{' (best)' if best_epoch == epoch else ''}, {rows[-1]['seconds']:.0f} s")
            if epoch == 1 and epochs > 1:  # the others take as long
                progress(more(epochs - 1, "epoch", rows[-1]["seconds"], "epoch 1's time"))
    net.load_state_dict(kept)
    return NetFit(net.eval(), pd.DataFrame(rows), best_epoch)


def fit_and_write(path: Path, source: str, train_logs: Sequence[pd.DataFrame],
                  val_logs: Sequence[pd.DataFrame], where: str, *, fresh: bool, epochs: int,
                  lr: float, batch: int = 256, seed: int = 0) -> Path:
    """:func:`fit` the net of checkpoint ``source`` (a file or an MLflow run id) on
    ``train_logs``, kept by ``val_logs``, one printed line per epoch; written as the
    checkpoint ``path`` and ``<path stem>_history.csv`` beside it (each whole or not at all).
    ``where`` says what it is trained on (the first line, and ``meta["trained_on"]``).
    Returns ``path``."""
    from lbo.core.atomic import atomic_path
    from lbo.logs.io import write_table
    from lbo.models.checkpoint import read_checkpoint, stored_envelope
    from lbo.tracking.artifacts import checkpoint_file

    with checkpoint_file(source) as file:
        net, hp = read_checkpoint(file)
    _check_reads_receiver(net)
    wheelbase = float(net.motion[1])  # the one its anchor's dead reckoning uses
    how = "from scratch" if fresh else f"fine-tuned from {source}"
    print(f"training {net.model}-N{net.window} {where}, {how} ({epochs} epochs; keeps the "
          "best on its validation span)")
    train = log_windows(train_logs, net.window, wheelbase)
    val = log_windows(val_logs, net.window, wheelbase)
    fitted = fit(net, train, val, epochs=epochs, lr=lr, batch=batch, seed=seed, fresh=fresh,
                 progress=lambda line: print("  " + line))
    print(f"  kept epoch {fitted.best_epoch}")
    meta = dict(hp.get("meta") or {})
    u = np.concatenate([log[list(INPUT)].to_numpy(dtype=float) for log in train_logs])
    rows = sum(len(log) for log in train_logs)
    fixes = sum(int(log[list(MEAS[:2])].notna().all(axis=1).sum()) for log in train_logs)
    seen = Envelope.from_training(u, None, (rows / max(fixes, 1),) * 2)
    before = None if fresh else stored_envelope(f"{net.model}-N{net.window}", meta)
    meta["envelope"] = (seen if before is None else before.union(seen)).to_dict()
    meta["trained_on"] = f"{where}, {how}, {fitted.best_epoch} of {epochs} epochs kept"
    state = {f"observer.{k}": v for k, v in fitted.net.state_dict().items()}
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save({"hyper_parameters": {**hp, "meta": meta}, "state_dict": state}, tmp)
    write_table(fitted.history, path.with_name(f"{path.stem}_history.csv"))
    return path
