"""A filter trained as it runs: truncated back-propagation through time over long sequences.

lbo's window trainer draws fresh windows and starts each filter at the window's first fix; a
filter in a control loop is carried from step to step for the whole drive. Here B sequences
of T steps are cut into consecutive chunks of L steps: the filter's state is carried from
chunk to chunk, the gradient is cut at each chunk's start (truncated back-propagation through
time), and the optimiser steps once per chunk, as KalmanNet's authors train it. Any module
that keeps :class:`lbo.models.carried.SequenceModel` trains here: KalmanNet and Split-KalmanNet
(:mod:`lbo.models.kalmannet`), and the window filter through its recursive form
(:class:`lbo.models.carried.CarriedFilter`). :func:`train_batch` is the one chunk loop:
``lbo.train tbptt=L`` runs it inside Lightning (:mod:`lbo.learn.lightning_module`), and
:func:`fit`, a plain loop over :class:`Sequences`, serves the tests and benchmarks.

The loss is the mean square error in the measurement sigmas at alpha = 1 (metres and radians
made comparable, the headings' differences wrapped), over the steps where the filter has
started; optionally plus the Gaussian negative log-likelihood of the errors under the
filter's own covariance, so that its P is trained too. Sequences are moved to start at their
first fix (a filter's differences do not depend on where it is, and float32 keeps
millimetres near the origin).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from lbo.core.checks import integer, number
from lbo.core.errors import LboError
from lbo.models.carried import SequenceModel, run
from lbo.models.poses import wrap_heading


@dataclass(frozen=True)
class Sequences:
    """B sequences of T steps (float64 arrays).

    m : (B, T, 3) measured poses, NaN in the rows without a fix.
    u : (B, T, 2) inputs ``[V, delta]``.
    z : (B, T, 3) the true poses.
    """

    m: np.ndarray
    u: np.ndarray
    z: np.ndarray

    def __post_init__(self) -> None:
        b, t = np.shape(self.z)[:2]
        if (np.shape(self.m) != (b, t, 3) or np.shape(self.u) != (b, t, 2)
                or np.shape(self.z) != (b, t, 3) or t < 2):
            raise LboError(f"sequences: expected m (B, T, 3), u (B, T, 2), z (B, T, 3) with "
                           f"T >= 2, got {np.shape(self.m)}, {np.shape(self.u)}, "
                           f"{np.shape(self.z)}")
        if not np.isfinite(self.m[:, 0, :2]).all():
            raise LboError("sequences: every sequence must start with a position fix")

    def __len__(self) -> int:
        return len(self.z)

    def take(self, rows: np.ndarray) -> Sequences:
        return Sequences(self.m[rows], self.u[rows], self.z[rows])

    def centred(self) -> Sequences:
        """The same sequences moved so that each starts at its first fix's position."""
        shift = np.zeros((len(self), 1, 3))
        shift[:, 0, :2] = self.m[:, 0, :2]
        return Sequences(self.m - shift, self.u, self.z - shift)


def draw(z: np.ndarray, u: np.ndarray, sigma: np.ndarray, alpha: np.ndarray,
         every: np.ndarray, rng: np.random.Generator) -> Sequences:
    """Measured sequences of true ones: z (B, T, 3), u (B, T, 2), the measurement sigmas
    (3,) at alpha = 1, each sequence's noise scale alpha (B,) and fix period every (B,) in
    steps (1: a fix at every step; the first step always holds one)."""
    z, u = np.asarray(z, dtype=float), np.asarray(u, dtype=float)
    b, t = z.shape[:2]
    scale = np.asarray(alpha, dtype=float).reshape(b, 1, 1) * np.asarray(sigma, dtype=float)
    m = z + scale * rng.standard_normal(z.shape)
    m[..., 2] = np.angle(np.exp(1j * m[..., 2]))
    fix = np.arange(t)[None, :] % np.asarray(every, dtype=np.int64).reshape(b, 1) == 0
    m[~fix] = np.nan
    return Sequences(m, u, z)


def loss(est: torch.Tensor, z: torch.Tensor, units: torch.Tensor,
         weight: torch.Tensor | None = None, cov: torch.Tensor | None = None,
         nll: float = 0.0) -> torch.Tensor:
    """Mean square error of estimates (B, L, 3) against the truth (B, L, 3) in the
    measurement sigmas ``units`` (3,), over the steps with an estimate (those before a
    sequence's first fix are NaN: :func:`lbo.models.carried.run`); ``weight`` (B,): each
    sequence's weight, or (B, L) each step's (None: equal). A diverged estimate (inf) makes
    it NaN or inf.

    With ``nll`` > 0, plus ``nll`` times the mean Gaussian negative log-likelihood of the
    errors under the estimates' own covariances ``cov`` (B, L, 3, 3) (:func:`gaussian_nll`):
    the MSE alone never asks a filter's P to be right; this term is least where P is the
    errors' covariance. It is a plain mean over the steps with an estimate, not weighted by
    ``weight``: the weights even out the MSE of noise levels whose errors differ in size,
    and the NLL is free of that size already (weighted, a noise 6 times the paper's counted
    70 times less than half of it, and its P went uncalibrated)."""
    d = wrap_heading(est - z) / units
    held = ~torch.isnan(est).all(-1) & torch.isfinite(z).all(-1)
    if not held.any():
        return d.new_zeros(())
    d = torch.where(held[..., None], d, 0.0)
    if weight is None:
        w = held.to(d.dtype)
    else:
        w = held * (weight[:, None] if weight.dim() == 1 else weight).to(d.dtype)
    mse = ((d ** 2).mean(-1) * w).sum() / w.sum()
    if not nll:
        return mse
    if cov is None:
        raise LboError("nll: this model gives no covariance for the Gaussian NLL term; "
                       "expected nll=0")
    scaled = cov / (units[:, None] * units[None, :])
    eye = torch.eye(3, dtype=d.dtype, device=d.device)
    per_step = gaussian_nll(d, torch.where(held[..., None, None], scaled, eye))
    return mse + nll * torch.where(held, per_step, 0.0).sum() / held.sum()


def gaussian_nll(d: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """The negative log-likelihood of errors d (..., 3) under zero-mean Gaussians of
    covariances cov (..., 3, 3), per channel and without its constant:
    ``(d^T cov^-1 d + log det cov) / 6``. For a scalar variance s over errors of variance v,
    it is least at s = v."""
    chol, info = torch.linalg.cholesky_ex(cov)
    # a covariance that is not positive definite (a diverged filter) scores inf, not NaN
    ok = info == 0
    chol = torch.where(ok[..., None, None], chol, torch.eye(3, dtype=d.dtype, device=d.device))
    white = torch.linalg.solve_triangular(chol, d[..., None], upper=False)[..., 0]
    log_det = 2 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    out = ((white ** 2).sum(-1) + log_det) / 6
    return torch.where(ok, out, torch.full_like(out, math.inf))


class BatchFit(NamedTuple):
    """What :func:`train_batch` did: every chunk's loss, over the sequences still carried
    (not finite, and given no step, where every one had diverged), and how many sequences
    it dropped because their filter diverged."""

    losses: list[float]
    dropped: int


def diverged(est: torch.Tensor, cov: torch.Tensor | None = None) -> torch.Tensor:
    """(B,) whether each sequence's filter diverged in a chunk: an estimate (B, L, 3) that is
    inf (:func:`lbo.models.carried.run`), or a covariance (B, L, 3, 3) not finite, after its
    start."""
    out = torch.isinf(est).flatten(1).any(1)
    if cov is not None:
        started = ~torch.isnan(est).all(-1)
        out = out | (started & ~torch.isfinite(cov).flatten(2).all(-1)).any(1)
    return out


def _rows(state: list[torch.Tensor], keep: torch.Tensor) -> list[torch.Tensor]:
    """The state of the sequences ``keep`` ((B,) bool): each tensor with a leading dimension
    of B taken at those rows, any other (the recursive form's step count) as it is."""
    return [s[keep] if s.dim() and s.shape[0] == len(keep) else s for s in state]


def train_batch(model: SequenceModel, m: torch.Tensor, u: torch.Tensor, z: torch.Tensor,
                chunk: int, step: Callable[[torch.Tensor], None],
                weight: torch.Tensor | None = None, nll: float = 0.0) -> BatchFit:
    """One batch trained by truncated back-propagation through time: B sequences m (B, T, 3)
    (NaN: no fix), u (B, T, 2), z (B, T, 3) true, the filter carried through consecutive
    chunks of ``chunk`` steps. Each chunk's :func:`loss` (``weight`` (B,): the sequences', or
    (B, T): the steps'; ``nll``: its Gaussian NLL term's weight) is handed to ``step`` (its
    backward pass and optimiser step) where it is finite; the state is then cut from the
    graph, so no gradient reaches back past a chunk's start.

    A sequence whose filter diverges in a chunk (:func:`diverged`) is dropped from the batch
    and the chunk run again without it: its NaN would reach every parameter's gradient
    through the batch's shared weights (a masked loss still back-propagates 0 * inf), and
    one such sequence would cost the whole batch its steps."""
    state: list[torch.Tensor] | None = None
    u_prev: torch.Tensor | None = None
    t = z.shape[1]
    losses: list[float] = []
    dropped = 0
    for k in range(0, t, chunk):
        part = slice(k, k + chunk)
        # the covariances only where the NLL term reads them
        est, after, cov, _ = run(model, m[:, part], u[:, part], state, u_prev, bool(nll))
        bad = diverged(est, cov)
        if bad.any() and not bad.all():
            keep = ~bad
            dropped += int(bad.sum())
            m, u, z = m[keep], u[keep], z[keep]
            weight = None if weight is None else weight[keep]
            if state is not None and u_prev is not None:
                state, u_prev = _rows(state, keep), u_prev[keep]
            est, after, cov, _ = run(model, m[:, part], u[:, part], state, u_prev, bool(nll))
        w = weight[:, part] if weight is not None and weight.dim() == 2 else weight
        chunk_loss = loss(est, z[:, part], model.units, w, cov, nll)
        if chunk_loss.requires_grad and torch.isfinite(chunk_loss):
            step(chunk_loss)
        losses.append(float(chunk_loss.detach()))
        if bad.all():  # nothing left to carry: the batch's other chunks give no step either
            losses += [math.nan] * len(range(k + chunk, t, chunk))
            break
        # the truncation; each tensor keeps its requires_grad (its gradient is dropped), so
        # that a chunk's first step is the same compiled graph as its others: a new one for
        # it cost a first run 17 s more compiling (compile=true, the car that slips)
        state = [s.detach().requires_grad_(s.requires_grad) for s in after]
        u_prev = u[:, min(k + chunk, t) - 1]
    return BatchFit(losses, dropped)


def from_batch(batch: tuple[torch.Tensor, ...], dtype: torch.dtype) -> tuple[torch.Tensor, ...]:
    """A training batch of windows (B, N, 5|6) with every step's true states (B, N, 3) and
    weights (B,) or (B, N) (:class:`lbo.learn.datamodule.WindowDataset` with ``sequences``)
    as a carried filter takes them: measured poses m (B, N, 3) (NaN: no fix), inputs
    u (B, N, 2), truth z (B, N, 3), each window moved to start at its first fix (see the
    module), in ``dtype``; and the weights."""
    win, z, weight = batch
    m = win[..., :3]
    first = torch.isfinite(m[..., 0]).to(torch.int8).argmax(1)  # the first fix's step
    shift = torch.zeros_like(m[:, :1])
    shift[:, 0, :2] = m[torch.arange(len(m), device=m.device), first, :2]
    return ((m - shift).to(dtype), win[..., 3:5].to(dtype), (z - shift).to(dtype),
            weight.to(dtype))


@dataclass(frozen=True)
class SequenceFit:
    """What :func:`fit` did: the mean training loss and the validation loss per epoch
    (epoch 0: before training), and the epoch whose weights it kept."""

    train: list[float]
    validation: list[float]
    best_epoch: int


def _tensors(seq: Sequences, device: str) -> tuple[torch.Tensor, ...]:
    return tuple(torch.as_tensor(a, dtype=torch.float32, device=device)
                 for a in (seq.m, seq.u, seq.z))


def evaluate(model: SequenceModel, seq: Sequences, device: str = "cpu") -> float:
    """The loss over whole sequences, each carried from its first step (no gradient)."""
    m, u, z = _tensors(seq.centred(), device)
    with torch.no_grad():
        est = run(model, m, u, covariance=False).est
    return float(loss(est, z, model.units))


def fit(model: SequenceModel, train: Sequences, validation: Sequences, epochs: int,
        chunk: int, batch: int, lr: float, seed: int = 0, device: str = "cpu",
        progress: Callable[[str], None] | None = print) -> SequenceFit:
    """Train ``model`` (a ``torch.nn.Module``) by truncated back-propagation through time
    (see the module): ``epochs`` passes over ``train`` in batches of ``batch`` sequences,
    each cut into chunks of ``chunk`` steps, Adam at ``lr``; keeps the weights of the epoch
    with the lowest validation loss (epoch 0: the weights it started with)."""
    epochs = integer(epochs, "sequence.epochs", 0)
    chunk = integer(chunk, "sequence.chunk", 2)
    batch = integer(batch, "sequence.batch", 1)
    lr = number(lr, "sequence.lr", low=0.0, low_open=True)
    net: torch.nn.Module = model  # type: ignore[assignment]
    net.to(device)
    opt = torch.optim.Adam(net.parameters(), lr=lr)

    def step(chunk_loss: torch.Tensor) -> None:
        opt.zero_grad()
        chunk_loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()

    rng = np.random.default_rng(seed)
    data = train.centred()
    history, val = [], [evaluate(model, validation, device)]
    best, kept = 0, copy.deepcopy(net.state_dict())
    for epoch in range(1, epochs + 1):
        net.train()
        losses, skipped, dropped = [], 0, 0
        order = rng.permutation(len(data))
        for start in range(0, len(order), batch):
            m, u, z = _tensors(data.take(order[start:start + batch]), device)
            done = train_batch(model, m, u, z, chunk, step)
            losses += [v for v in done.losses if math.isfinite(v)]
            # diverged: no step, or the sequence dropped; say so
            skipped += sum(not math.isfinite(v) for v in done.losses)
            dropped += done.dropped
        net.eval()
        history.append(float(np.mean(losses)) if losses else math.nan)
        val.append(evaluate(model, validation, device))
        if val[-1] < val[best]:  # NaN compares False: a diverged epoch is never kept
            best, kept = epoch, copy.deepcopy(net.state_dict())
        if progress is not None:
            progress(f"  epoch {epoch}/{epochs}: train {history[-1]:.4g}, validation "
                     f"{val[-1]:.4g} (before training {val[0]:.4g})"
                     + (f", {skipped} diverged chunks skipped" if skipped else "")
                     + (f", {dropped} diverged sequences dropped" if dropped else ""))
    net.load_state_dict(kept)
    return SequenceFit(history, val, best)
