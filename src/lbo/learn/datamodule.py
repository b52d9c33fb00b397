"""Data sets on disk -> zero-copy windows -> a LightningDataModule.

Rows of a set are stored once as a (R, 5) tensor ``[x_m, y_m, psi_m, V, delta]`` and a (R, 3)
tensor of true states. ``window_view`` gives every window as a view into the rows; a batch gathers
only the windows it needs. A window ends at row e and covers rows e-N+1..e; it is valid when
k >= N-1 at e, which keeps it inside one trajectory because k restarts at 0 in each.

A batch is ``(windows (B, N, 5), states (B, 3), loss weights (B,))``. With drawn noise
(:mod:`lbo.learn.draws`) the measurement channels of each training window are drawn afresh from
its true states; validation uses one fixed draw (``val_repeats`` of them per window) over the
same alpha distribution, so that early stopping measures what is being trained.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import lightning as L
import numpy as np
import pandas as pd
import torch
from torch.utils.data import (
    BatchSampler,
    DataLoader,
    Dataset,
    RandomSampler,
    SequentialSampler,
    get_worker_info,
)

from lbo.core.errors import LboError
from lbo.learn.draws import (
    AlphaDraw,
    OutageDraw,
    ReceiverDraw,
    draw_fixes,
    loss_weights,
    noisy_measurements,
)
from lbo.models.features import window_view
from lbo.models.net import check_scaling
from lbo.sim import schema
from lbo.sim.columns import MEAS, SCORED_SET, STATE, WINDOW


def rows(df: pd.DataFrame) -> tuple[torch.Tensor, torch.Tensor]:
    """(R, 5) inputs and (R, 3) states of a frame sorted by trajectory and step, float64."""
    x = torch.from_numpy(np.ascontiguousarray(df[list(WINDOW)].to_numpy(np.float64)))
    y = torch.from_numpy(np.ascontiguousarray(df[list(STATE)].to_numpy(np.float64)))
    return x, y


def window_ends(k: np.ndarray, window: int, keep: np.ndarray | None = None,
                next_step: bool = False) -> np.ndarray:
    """Rows where a full window of N steps ends inside one trajectory (and ``keep`` holds);
    with ``next_step``, only those whose trajectory goes on a step after them."""
    ok = k >= window - 1
    if keep is not None:
        ok &= keep
    if next_step:
        ok &= np.append(k[1:] == k[:-1] + 1, False)
    return np.flatnonzero(ok)


Batch = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


class WindowDataset(Dataset):
    """Windows ending at ``ends``, as views into ``x``.

    Indexing with a list of indices returns one batch: windows (B, N, 5), states (B, 3) and
    loss weights (B,).

    Parameters
    ----------
    x : (R, 5) rows ``[x_m, y_m, psi_m, V, delta]``; y : (R, 3) true states.
    ends : rows where the windows end.
    window : N.
    draw : None: the stored measurements. Else the measurement channels are drawn afresh
        for every window, at an alpha from ``draw``, with ``sigma`` (3,) at alpha=1.
    seed : seeds the draws: the same seed gives the same stream of batches, and each call
        continues the stream, so no two epochs repeat a draw.
    weight_offset : loss weights ``1 / (alpha + offset)^2``, or ones when None.
    fix_periods : drop position fixes: each window keeps them every one of these periods
        (steps), see :func:`lbo.learn.draws.draw_fixes`; the dropped ones become NaN. () keeps all.
    outages : GNSS outages drawn into the windows, every fix of a stretch dropped
        (:class:`lbo.learn.draws.OutageDraw`, with ``fix_periods``); None: none.
    drift : (sigma (m), tau (steps)) of a Gauss-Markov GNSS drift added to drawn noise, as
        the data set's truth has it; None: white noise only.
    receiver : draw a receiver's windows (B, N, 11) instead
        (:meth:`lbo.learn.draws.ReceiverDraw.windows`), at the alphas of ``draw`` (1 when
        None) and the fix rows of ``fix_periods`` (needed).
    sequences : a batch's states are the true states of every step of its windows (B, N, 3),
        for a filter trained carried through them (``tbptt``), not the last step's (B, 3); with
        ``draw.changes``, alpha changes along each window and the weights are per step (B, N).
    next_fix : no truth in the batches: in place of the states (B, 3), each window's next
        step (B, 5): its fix ``[x_m, y_m, psi_m]`` (drawn at the window's alpha, afresh; or
        stored, NaN where the step has none) and the window's last inputs ``[V, delta]``,
        which move the estimate onto it (:meth:`lbo.models.net.WindowNet.next_fix_loss`).
        ``ends`` must each have a next step in their trajectory.
    """

    def __init__(self, x: torch.Tensor, y: torch.Tensor, ends: np.ndarray, window: int, *,
                 draw: AlphaDraw | None = None, sigma: torch.Tensor | None = None,
                 seed: int = 0, weight_offset: float | None = None,
                 fix_periods: tuple[int, ...] = (),
                 drift: tuple[float, float] | None = None,
                 receiver: ReceiverDraw | None = None, sequences: bool = False,
                 next_fix: bool = False, outages: OutageDraw | None = None):
        if outages is not None and not fix_periods:
            raise LboError("train_outages: outages need fix rates (fix_rates=[10, 5, 1])")
        self.outages = outages
        if next_fix and (receiver is not None or sequences):
            raise LboError("loss=next_fix trains on windows of full poses (tbptt=null, no "
                           "receiver)")
        self.next_fix = bool(next_fix)
        if receiver is not None and not fix_periods:
            raise LboError("a receiver's windows need fix rates (fix_rates=[10, 5, 1])")
        if receiver is not None and sequences:
            raise LboError("tbptt: a filter trained carried reads full poses, not a receiver's "
                           "windows; leave receiver unset")
        self.receiver, self.sequences = receiver, bool(sequences)
        self.x, self.y, self.window = x, y, window
        self.fix_periods = tuple(fix_periods)
        self.ends = torch.from_numpy(ends)
        self.windows = window_view(x, window)  # (R-N+1, N, 5), a view: no copy
        self.truth = window_view(y, window)  # (R-N+1, N, 3), a view
        self.draw, self.weight_offset, self.drift = draw, weight_offset, drift
        self.sigma = None if sigma is None else torch.as_tensor(sigma, dtype=x.dtype)
        self.generator = torch.Generator().manual_seed(seed)
        self._worker_seed: int | None = None

    def __len__(self) -> int:
        return len(self.ends)

    def to(self, device: str | torch.device, seed: int = 0) -> WindowDataset:
        """Move the rows to ``device`` (in place), so that batches and their noise are made
        there, with a generator of that device seeded with ``seed`` (CUDA's stream differs
        from the CPU's: a run on the GPU is repeatable, not equal to one on the CPU)."""
        device = torch.device(device)
        if device == self.x.device:
            return self
        self.x, self.y, self.ends = self.x.to(device), self.y.to(device), self.ends.to(device)
        self.windows = window_view(self.x, self.window)
        self.truth = window_view(self.y, self.window)
        if self.sigma is not None:
            self.sigma = self.sigma.to(device)
        self.generator = torch.Generator(device=device).manual_seed(seed)
        return self

    def __getitem__(self, idx) -> Batch:
        info = get_worker_info()
        if info is not None and info.seed != self._worker_seed:
            # a worker holds a copy of this dataset, made anew every epoch: reseed it from the
            # loader's per-epoch, per-worker seed, or each epoch would repeat the first's draws
            self.generator.manual_seed(info.seed)
            self._worker_seed = info.seed
        return self.batch(idx, self.generator)

    def batch(self, idx, generator: torch.Generator) -> Batch:
        """The windows ``idx``, any noise drawn with ``generator``."""
        e = self.ends[torch.as_tensor(idx, device=self.ends.device)]
        s = e - self.window + 1
        win = self.windows[s]
        truth = self.truth[s] if self.sequences else self.y[e]
        if self.receiver is not None:
            alpha = (torch.ones(len(e), dtype=self.x.dtype, device=e.device)
                     if self.draw is None else self.draw.sample(len(e), generator))
            fix = self._fixes(len(e), generator, e.device)
            rx = self.receiver.windows(self.truth[s], win[..., 3:5], alpha, fix, generator)
            return rx, truth, loss_weights(alpha, self.weight_offset)
        if self.draw is None:
            weight = torch.ones(len(e), dtype=self.x.dtype, device=e.device)
            m = win[..., :3]
            if self.next_fix:  # the log's own next fix, which no window of these reads
                truth = torch.cat([self.x[e + 1, :3], self.x[e, 3:5]], -1)
        else:
            alpha = (self.draw.along(len(e), self.window, generator)
                     if self.sequences and self.draw.changes else
                     self.draw.sample(len(e), generator))
            weight = loss_weights(alpha, self.weight_offset)  # (B,), or (B, N) along
            assert self.sigma is not None, "drawn noise needs the measurement sigmas"
            m = noisy_measurements(self.truth[s], alpha, self.sigma, generator, self.drift)
            if self.next_fix:  # drawn apart from the window's: its noise is its own
                after = noisy_measurements(self.y[e + 1][:, None], alpha, self.sigma, generator)
                truth = torch.cat([after[:, 0], self.x[e, 3:5]], -1)
        if self.fix_periods:
            fix = self._fixes(len(e), generator, e.device)
            kept = torch.where(fix[..., None], m, torch.full_like(m, float("nan")))
            # stored measurements with gaps of their own (a user's 10 Hz logs): the mask may
            # miss every fix of a window, which keeps its own fixes then (never on full sets)
            lost = ~torch.isfinite(kept[..., 0]).any(1)
            m = torch.where(lost[:, None, None], m, kept)
        elif self.draw is None:
            return win, truth, weight
        return torch.cat([m, win[..., 3:]], dim=-1), truth, weight

    def _fixes(self, n: int, generator: torch.Generator, device: torch.device) -> torch.Tensor:
        """The steps of ``n`` windows that hold a fix (n, N) bool: at one of the fix periods,
        less the outages drawn."""
        fix = draw_fixes(n, self.window, self.fix_periods, generator, device)
        return fix if self.outages is None else self.outages.cut(fix, generator)


class FixedDataset(Dataset):
    """Materialised batches ``(windows, states, weights)``; indexing takes a batch of rows."""

    def __init__(self, *tensors: torch.Tensor) -> None:
        self.tensors = tensors

    def __len__(self) -> int:
        return len(self.tensors[0])

    def to(self, device: str | torch.device, seed: int = 0) -> FixedDataset:
        self.tensors = tuple(t.to(device) for t in self.tensors)
        return self

    def __getitem__(self, idx) -> Batch:
        idx = torch.as_tensor(idx, device=self.tensors[0].device)
        return tuple(t[idx] for t in self.tensors)  # type: ignore[return-value]


def _check_window(window: int, lengths: np.ndarray, first_scored: int | None, name: str) -> None:
    longest = int(lengths.max())
    if window > longest:  # shorter trajectories (segments of a user's logs) give no window
        what = "shortest" if lengths.min() == longest else "longest"
        raise LboError(f"window={window} is longer than the {what} {name} trajectory "
                       f"({longest} steps); choose window <= {longest}")
    if first_scored is not None and window - 1 > first_scored:
        raise LboError(f"window={window} needs {window - 1} steps of history, but the {name} "
                       f"set scores from step {first_scored}; choose window <= {first_scored + 1}")


class WindowDataModule(L.LightningDataModule):
    """Training and validation windows from a data-set folder (train/val/test.parquet).

    Parameters
    ----------
    folder : the folder printed by ``python -m lbo.datagen``.
    window : N.
    batch_size, eval_batch_size : training and validation batch sizes.
    seed : seeds the shuffling and the noise draws, so a run is repeatable.
    draw : None for the stored measurements, else how alpha is drawn per window.
    sigma : (3,) measurement sigmas at alpha=1 (needed with ``draw``).
    weight_offset : loss weights ``1 / (alpha + offset)^2``; None: equal weights.
    val_repeats : fixed noise draws per validation window (with ``draw``).
    device : where the rows live and batches and noise draws are made (``"cuda"`` on a GPU:
        no copy from the host per batch, and no loader workers).
    fix_periods : drop position fixes in training and validation windows (see
        :class:`WindowDataset`); () keeps every fix.
    drift : (sigma (m), tau (steps)) of the GNSS drift drawn with the noise (see
        :class:`WindowDataset`).
    receiver : draw a receiver's windows instead of the paper's (see :class:`WindowDataset`).
    sequences : batches hold the true states of every step (see :class:`WindowDataset`), and
        validation windows are as long as the validation set's run-in allows.
    next_fix : batches hold each window's next fix and last inputs, no truth (see
        :class:`WindowDataset`), in training and validation alike.
    outages : GNSS outages drawn into training and validation windows (see
        :class:`WindowDataset`); None: none.
    """

    def __init__(self, folder: str | Path, window: int, batch_size: int = 256, *,
                 eval_batch_size: int = 4096, num_workers: int = 0, seed: int = 0,
                 draw: AlphaDraw | None = None, sigma=None,
                 weight_offset: float | None = None, val_repeats: int = 1,
                 device: str = "cpu", fix_periods: tuple[int, ...] = (),
                 drift: tuple[float, float] | None = None,
                 receiver: ReceiverDraw | None = None, sequences: bool = False,
                 next_fix: bool = False, outages: OutageDraw | None = None) -> None:
        super().__init__()
        self.device = torch.device(device)
        self.folder = Path(folder)
        self.window, self.batch_size = int(window), int(batch_size)
        self.eval_batch_size, self.num_workers, self.seed = eval_batch_size, num_workers, seed
        if draw is not None and sigma is None:
            raise LboError("WindowDataModule: drawn noise needs the measurement sigmas")
        self.draw, self.sigma, self.weight_offset = draw, sigma, weight_offset
        self.val_repeats = int(val_repeats)
        self.fix_periods = tuple(fix_periods)
        self.drift, self.receiver, self.sequences = drift, receiver, bool(sequences)
        self.next_fix, self.outages = bool(next_fix), outages
        self.val_window = self.window  # shorter when trained carried (setup)
        self.train_set: WindowDataset | None = None
        self.val_set: WindowDataset | FixedDataset | None = None
        self.shuffle = torch.Generator().manual_seed(seed)  # the training order, epoch by epoch
        self._resumed_shuffle: torch.Tensor | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        # steps without a position fix (a user's logs, GNSS slower than the inputs) are NaN rows
        train = schema.read_set(self.folder / "train.parquet", missing_fixes=True,
                                missing_truth=True)
        val = schema.read_set(self.folder / "val.parquet", SCORED_SET, missing_fixes=True,
                              missing_truth=True)
        self._check_truth(train, val)
        first = int(val.loc[val["scored"], "k"].min())
        # a filter trained carried on long windows is validated carried over windows as long
        # as the validation set's run-in allows (it runs carried there, from their first fix)
        self.val_window = min(self.window, first + 1) if self.sequences else self.window
        for name, df, n in (("training", train, self.window),
                            ("validation", val, self.val_window)):
            lengths = df.groupby("traj", sort=False).size().to_numpy()
            _check_window(n, lengths, first if name == "validation" else None, name)
        if self.draw is None and not self.fix_periods and train[list(MEAS)].isna().any(
                axis=None):
            raise LboError("the training set has steps without a position fix (GNSS slower than "
                           "the inputs): train with fix_rates (e.g. fix_rates=[10]) so that the "
                           "observer takes them, or with drawn noise (train_noise=paper)")
        noise = {"draw": self.draw, "sigma": self.sigma, "weight_offset": self.weight_offset,
                 "fix_periods": self.fix_periods, "drift": self.drift,
                 "receiver": self.receiver, "sequences": self.sequences,
                 "next_fix": self.next_fix, "outages": self.outages}
        self.train_set = WindowDataset(*rows(train), window_ends(
            train["k"].to_numpy(), self.window, next_step=self.next_fix), self.window,
            seed=self.seed, **noise)
        val_set = WindowDataset(*rows(val), window_ends(
            val["k"].to_numpy(), self.val_window, val["scored"].to_numpy(), self.next_fix),
            self.val_window, **noise)
        if self.draw is None and not self.fix_periods and self.receiver is None:
            self.val_set = val_set
        else:  # one fixed draw, the same in every epoch and run of this seed
            g = torch.Generator().manual_seed(self.seed + 1)
            idx = torch.arange(len(val_set)).repeat(self.val_repeats)
            self.val_set = FixedDataset(*val_set.batch(idx, g))
        self.train_set.to(self.device, self.seed)
        self.val_set.to(self.device, self.seed)

    def _check_truth(self, train: pd.DataFrame, val: pd.DataFrame) -> None:
        """Logs without the truth (NaN ``x, y, psi``, :mod:`lbo.logs.sets`) train by their
        own next fixes alone, never by the truth or by noise drawn around it."""
        for name, df in (("training", train), ("validation", val)):
            if not df[list(STATE)].isna().to_numpy().any():
                continue
            if not self.next_fix:
                raise LboError(f"the {name} set holds logs without the truth (x, y, psi): "
                               "train on them with loss=next_fix, or give logs that have it")
            if self.draw is not None:
                raise LboError(f"the {name} set holds logs without the truth (x, y, psi), "
                               "and train_noise draws its noise around the truth: train on "
                               "the logs' own fixes (train_noise=stored)")

    def normalisation(self, net: Any, scaling: str = "standard",
                      n: int = 20_000) -> dict[str, torch.Tensor]:
        """The statistics (:meth:`lbo.models.net.WindowNet.statistics`) of ``n`` random
        training windows' features and targets, as ``net`` reads them (its feature mode, its
        ``fix`` channel, a receiver's features), for its :meth:`set_normalisation`."""
        check_scaling(scaling)
        self.setup()
        train = cast(WindowDataset, self.train_set)  # setup made it
        g = torch.Generator(device=self.device).manual_seed(self.seed)
        pick = torch.randperm(len(train), generator=g, device=self.device)[:n]
        win, state, _ = train.batch(pick, g)
        if self.sequences:  # every step's: the statistics are the last step's
            state = state[:, -1]
        if self.next_fix:  # no truth read: the next fixes stand in for the states
            held = torch.isfinite(state[:, :3]).all(1)
            win, state = win[held], state[held, :3]
        return net.statistics(win, state, scaling)

    def _loader(self, ds: WindowDataset | FixedDataset, batch: int, shuffle: bool) -> DataLoader:
        # one __getitem__ per batch: the gather is vectorised, never a loop over samples
        if shuffle:  # a new loader starts the order afresh, or where a checkpoint left it
            self.shuffle = torch.Generator().manual_seed(self.seed)
            if self._resumed_shuffle is not None:
                self.shuffle.set_state(self._resumed_shuffle)
                self._resumed_shuffle = None
        base = RandomSampler(ds, generator=self.shuffle) if shuffle else SequentialSampler(ds)
        # tensors on a GPU cannot go to worker processes: the main process gathers there
        workers = self.num_workers if self.device.type == "cpu" else 0
        # the loader's generator seeds the workers' per-epoch noise draws from `seed` alone
        return DataLoader(ds, sampler=BatchSampler(base, batch, drop_last=False),
                          batch_size=None, num_workers=workers,
                          generator=torch.Generator().manual_seed(self.seed))

    def state_dict(self) -> dict[str, Any]:
        """Where the random streams stand (the training order, the noise draws, torch's global
        generator): saved in every checkpoint, so a run resumed from its last checkpoint
        draws the batches the unbroken run would have drawn."""
        state = {"shuffle": self.shuffle.get_state(), "torch": torch.get_rng_state()}
        if self.train_set is not None:
            state["draws"] = self.train_set.generator.get_state()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.setup()
        self._resumed_shuffle = state["shuffle"]  # for the loader Lightning makes next
        torch.set_rng_state(state["torch"])
        if "draws" in state:
            cast(WindowDataset, self.train_set).generator.set_state(state["draws"])  # set up

    # the sets exist once set up, which Lightning does before it asks for a loader
    def train_dataloader(self) -> DataLoader:
        return self._loader(cast(WindowDataset, self.train_set), self.batch_size, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(cast(WindowDataset | FixedDataset, self.val_set),
                            self.eval_batch_size, shuffle=False)
