"""Data sets on disk -> zero-copy windows -> a LightningDataModule.

Rows of a set are stored once as a (R, 5) tensor ``[x_m, y_m, psi_m, V, delta]`` and a (R, 3)
tensor of true states. ``unfold`` gives every window as a view into the rows; a batch gathers
only the windows it needs. A window ends at row e and covers rows e-N+1..e; it is valid when
k >= N-1 at e, which keeps it inside one trajectory because k restarts at 0 in each.
"""

from __future__ import annotations

from pathlib import Path

import lightning as L
import numpy as np
import pandas as pd
import torch
from torch.utils.data import BatchSampler, DataLoader, Dataset, RandomSampler, SequentialSampler

from lbo import schema
from lbo.errors import LboError
from lbo.features import last_measurement, state_to_target, window_features

INPUT_COLUMNS = [*schema.MEAS, *schema.INPUT]


def rows(df: pd.DataFrame) -> tuple[torch.Tensor, torch.Tensor]:
    """(R, 5) inputs and (R, 3) states of a frame sorted by trajectory and step, float64."""
    x = torch.from_numpy(np.ascontiguousarray(df[INPUT_COLUMNS].to_numpy(np.float64)))
    y = torch.from_numpy(np.ascontiguousarray(df[list(schema.STATE)].to_numpy(np.float64)))
    return x, y


def window_ends(k: np.ndarray, window: int, keep: np.ndarray | None = None) -> np.ndarray:
    """Rows where a full window of N steps ends inside one trajectory (and ``keep`` holds)."""
    ok = k >= window - 1
    if keep is not None:
        ok &= keep
    return np.flatnonzero(ok)


class WindowDataset(Dataset):
    """Windows ending at ``ends``, as views into ``x``.

    Indexing with a list of indices returns one batch: windows (B, N, 5) and states (B, 3).
    """

    def __init__(self, x: torch.Tensor, y: torch.Tensor, ends: np.ndarray, window: int):
        self.x, self.y, self.window = x, y, window
        self.ends = torch.from_numpy(ends)
        self.windows = x.unfold(0, window, 1)  # (R-N+1, 5, N), a view: no copy

    def __len__(self) -> int:
        return len(self.ends)

    def __getitem__(self, idx) -> tuple[torch.Tensor, torch.Tensor]:
        e = self.ends[torch.as_tensor(idx)]
        return self.windows[e - self.window + 1].transpose(-1, -2), self.y[e]


def _check_window(window: int, lengths: np.ndarray, first_scored: int | None, name: str) -> None:
    if window > lengths.min():
        raise LboError(f"window={window} is longer than the shortest {name} trajectory "
                       f"({int(lengths.min())} steps); choose window <= {int(lengths.min())}")
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
    seed : seeds the shuffling, so a run is repeatable.
    """

    def __init__(self, folder: str | Path, window: int, batch_size: int = 256,
                 eval_batch_size: int = 4096, num_workers: int = 0, seed: int = 0) -> None:
        super().__init__()
        self.folder = Path(folder)
        self.window, self.batch_size = int(window), int(batch_size)
        self.eval_batch_size, self.num_workers, self.seed = eval_batch_size, num_workers, seed
        self.train_set: WindowDataset | None = None
        self.val_set: WindowDataset | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        train = schema.read_set(self.folder / "train.parquet")
        val = schema.read_set(self.folder / "val.parquet", schema.EVAL_COLUMNS)
        for name, df in (("training", train), ("validation", val)):
            lengths = df.groupby("traj", sort=False).size().to_numpy()
            first = int(df.loc[df["scored"], "k"].min()) if "scored" in df else None
            _check_window(self.window, lengths, first, name)
        self.train_set = WindowDataset(*rows(train), window_ends(train["k"].to_numpy(),
                                                                 self.window), self.window)
        self.val_set = WindowDataset(*rows(val), window_ends(
            val["k"].to_numpy(), self.window, val["scored"].to_numpy()), self.window)

    def normalisation(self, features: str, n: int = 20_000) -> dict[str, torch.Tensor]:
        """Channel means and stds of ``n`` random training windows' features and targets."""
        self.setup()
        g = torch.Generator().manual_seed(self.seed)
        pick = torch.randperm(len(self.train_set), generator=g)[:n]
        win, state = self.train_set[pick]
        f = window_features(win, features).reshape(-1, 5)
        t = state_to_target(state, last_measurement(win), features)
        return {"in_mean": f.mean(0), "in_std": f.std(0),
                "out_mean": t.mean(0), "out_std": t.std(0)}

    def _loader(self, ds: WindowDataset, batch: int, shuffle: bool) -> DataLoader:
        # one __getitem__ per batch: the gather is vectorised, never a loop over samples
        base = (RandomSampler(ds, generator=torch.Generator().manual_seed(self.seed))
                if shuffle else SequentialSampler(ds))
        return DataLoader(ds, sampler=BatchSampler(base, batch, drop_last=False),
                          batch_size=None, num_workers=self.num_workers)

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_set, self.batch_size, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_set, self.eval_batch_size, shuffle=False)
