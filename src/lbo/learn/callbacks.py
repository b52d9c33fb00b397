"""Lightning callbacks: score the best checkpoint on the whole test grid at the end of fit,
measure a single-track body's error on the validation set, and mark each checkpoint as the
run's."""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import pandas as pd
from lightning.pytorch.loggers import MLFlowLogger

from lbo.core import plots
from lbo.core.atomic import atomic_path
from lbo.filters.classical import DYNAMIC_PEERS, GRID_PEERS
from lbo.learn.resume import IDENTITY_KEY
from lbo.logs.sets import is_log_folder, test_files
from lbo.models.checkpoint import LATERAL_ERROR, read_checkpoint, trained_conditions
from lbo.scoring import logscore, peers_ahead
from lbo.scoring.grid import (
    classical_table,
    load_test,
    nrmse_at,
    oracle_ratio,
    predict,
    reference,
    score,
    summary,
)
from lbo.sim.schema import Trajectories
from lbo.sim.truth import Truth, of_folder

LOGGED_ALPHAS = (1.0, 3.0, 6.0)


class Evaluation(L.Callback):
    """At the end of fit: load the best checkpoint, run it on every test level, score it
    beside the EKF and the oracle EKF with :func:`lbo.scoring.grid.score`, write
    ``evaluation.csv`` and ``nrmse.png`` to ``output_dir`` and log them, the metrics and the
    checkpoint to MLflow. ``worst_oracle_ratio`` is the largest NRMSE ratio to the oracle over
    alpha in [0.25, 6], so that ``mlflow ui`` can sort observers by it. On a test set drawn from
    a car that slips (``car=dynamic``) the table also holds the adaptive EKF, the kinematic EKF
    with its Q tuned on the test set (``oracle_tuned``) and the oracle on the true car
    (``oracle_dynamic``); ``worst_dynamic_oracle_ratio`` and ``worst_tuned_oracle_ratio`` are
    the ratios to the last two. A training that leaves a core idle scores the classical
    observers there while it trains (:mod:`lbo.scoring.peers_ahead`), and this reads them back.

    Parameters
    ----------
    output_dir : where the table and the figure are written.
    reference : ``"ekf"`` (our EKF's RMSE at alpha=1) or ``"paper"``.
    """

    def __init__(self, output_dir: str, reference: str = "ekf", batch_size: int = 8192) -> None:
        self.output_dir = Path(output_dir)
        self.reference = reference
        self.batch_size = batch_size
        self.table: pd.DataFrame | None = None
        self._ahead: peers_ahead.Ahead | None = None
        self._ahead_tried = False
        self.metrics: dict[str, float] = {}
        self.description = ""  # the result table, as the run's MLflow description
        # set by lbo.train: Lightning hides the run's logger behind a dummy in fast_dev_run
        self.mlflow: MLFlowLogger | None = None

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule,
                           outputs: Any, batch: Any, batch_idx: int) -> None:
        # after the first batch, which compiles a compiled step on both cores
        if not self._ahead_tried:
            self._ahead_tried = True
            self._ahead = self._start_ahead(trainer, pl_module)

    def _start_ahead(self, trainer: L.Trainer, pl_module: L.LightningModule
                     ) -> peers_ahead.Ahead | None:
        """The classical peers of a generated test set scored on the core this training
        leaves idle (:mod:`lbo.scoring.peers_ahead`), or None where none is idle."""
        import torch

        folder = Path(trainer.datamodule.folder)  # type: ignore[attr-defined]  # Lightning sets it
        if (is_log_folder(folder) or not (folder / "test.parquet").is_file()
                or not os.access(folder, os.W_OK)  # where the rows would not be kept
                or not peers_ahead.spare_core(torch.get_num_threads())):
            return None
        vehicle, _ = trained_conditions(pl_module.hparams, "(in memory)")
        return peers_ahead.start(folder, pl_module.hparams["meta"],
                                 self._peers(of_folder(folder, vehicle.wheelbase)),
                                 self.reference)

    @staticmethod
    def _peers(truth: Truth) -> list[str]:
        """The classical observers scored beside a learned one on a test grid drawn from
        ``truth``: on a car that slips, the kinematic peers and the oracle told the car."""
        return list(DYNAMIC_PEERS if truth.car else GRID_PEERS)

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule,
                     exception: BaseException) -> None:
        if self._ahead is not None:
            self._ahead.stop()
            self._ahead = None

    def on_fit_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        start = time.perf_counter()
        if self._ahead is not None:  # its kept rows are read back below
            if self._ahead.running():
                print("waiting for the classical observers, scored beside the training ...",
                      flush=True)
            failed, self._ahead = self._ahead.wait(), None
            if failed:
                print(f"the classical observers scored beside the training failed ({failed}); "
                      "scoring them now", flush=True)
        best = getattr(trainer.checkpoint_callback, "best_model_path", "") or ""
        # the best weights through the one checkpoint reader, with its format checks
        net, hp = read_checkpoint(best) if best else (pl_module.observer, pl_module.hparams)
        vehicle, noise = trained_conditions(hp, best or "(in memory)")
        folder = Path(trainer.datamodule.folder)  # type: ignore[attr-defined]  # Lightning sets it
        name = f"{hp['model']['name']}-N{hp['window']}"
        device = str(trainer.strategy.root_device)
        if not is_log_folder(folder):
            self._score_grid(folder, net, hp, name, vehicle, noise, device)
        elif (folder / "test.parquet").is_file():
            self._score_logs(folder, net, hp, name, vehicle, noise, device)
        else:
            print(f"no test logs (data.test=[]): {name} is not scored; lbo.evaluate "
                  "data.test=[...] observer=<this run> scores it on logs with the truth",
                  flush=True)
            self.description = f"{name}: no test logs, not scored"
        self.metrics["eval_seconds"] = time.perf_counter() - start
        logger = self.mlflow or trainer.logger
        if isinstance(logger, MLFlowLogger):
            client, run = logger.experiment, logger.run_id
            for key, value in self.metrics.items():
                client.log_metric(run, key, value)
            # the run's description in the MLflow UI: its result table
            client.set_tag(run, "mlflow.note.content", self.description)
            for scored in ("evaluation.csv", "nrmse.png"):  # none without test logs
                if (self.output_dir / scored).is_file():
                    client.log_artifact(run, str(self.output_dir / scored))

    def _score_logs(self, folder: Path, net, hp: Mapping[str, Any], name: str, vehicle, noise,
                    device: str) -> None:
        """A user's test logs: the learned observer beside the EKF, the adaptive EKF and the
        UKF, pooled and per file (:mod:`lbo.scoring.logscore`)."""
        arr = logscore.load(folder)
        est = predict(net, arr, self.batch_size, device=device)
        estimates = {name: est, **logscore.peer_estimates(arr, vehicle, noise)}
        self.table = logscore.table(estimates, arr, test_files(folder))
        with atomic_path(self.output_dir / "evaluation.csv") as tmp:
            self.table.to_csv(tmp, index=False)
        plots.save(logscore.figure(self.table, f"{name} on the test logs"),
                   self.output_dir / "nrmse.png")
        self.metrics = logscore.metrics(self.table, name)
        said = logscore.printable(self.table)
        print(f"test logs ({logscore.NOTE}):\n{said}")
        self.description = f"{name} on the test logs ({logscore.NOTE}):\n\n```\n{said}\n```"

    def _score_grid(self, folder: Path, net, hp: Mapping[str, Any], name: str, vehicle, noise,
                    device: str) -> None:
        """The test grid of a generated data set, per alpha level."""
        arr = load_test(folder / "test.parquet")
        print(f"evaluating {name} on the test grid: {len(np.unique(arr.alpha))} noise "
              f"levels, {len(arr.alpha)} trajectories, beside the classical observers ...",
              flush=True)
        ref = reference(arr, vehicle, noise, self.reference)
        est = predict(net, arr, self.batch_size, device=device)
        truth = of_folder(folder, vehicle.wheelbase)
        peers = self._peers(truth)
        self.table = pd.concat([score(name, est, arr, ref),
                                classical_table(arr, vehicle, noise, peers, ref, truth=truth,
                                                keep=folder / "test.parquet")],
                               ignore_index=True)
        csv, png = self.output_dir / "evaluation.csv", self.output_dir / "nrmse.png"
        with atomic_path(csv) as tmp:
            self.table.to_csv(tmp, index=False)
        title = (f"{name} on a car that slips, against the kinematic EKFs and the EKF told "
                 "the car") if truth.car else f"{name} against the EKF"
        plots.save(plots.nrmse_curves(self.table, title=title), png)
        self.metrics = {f"test_nrmse_alpha_{a:g}": nrmse_at(self.table, name, a)
                        for a in LOGGED_ALPHAS if (abs(self.table["alpha"] - a) < 1e-9).any()}
        ratio = oracle_ratio(self.table, name)
        if len(ratio):
            self.metrics["worst_oracle_ratio"] = float(ratio.max())
        if truth.car is not None:  # the floor on a car that slips: the EKF told the car
            said = summary(self.table, name, peers=("ekf", "oracle", "oracle_dynamic"),
                           oracle="oracle_dynamic", reference=self.reference)
        else:
            said = summary(self.table, name, reference=self.reference)
        print(said)
        self.description = f"{name} on {len(arr.alpha)} test trajectories:\n\n```\n{said}\n```"
        if truth.car is not None and len(ratio):
            for peer, key in (("oracle_dynamic", "worst_dynamic_oracle_ratio"),
                              ("oracle_tuned", "worst_tuned_oracle_ratio")):
                self.metrics[key] = float(oracle_ratio(self.table, name, oracle=peer).max())


class RunIdentity(L.Callback):
    """Writes the run's identity (MLflow run id, config hash) into every checkpoint, under
    :data:`~lbo.learn.resume.IDENTITY_KEY`: ``resume=true`` continues a run only from a
    ``last.ckpt`` that carries that run's own (:func:`lbo.learn.resume.resumable_folder`)."""

    def __init__(self, run_id: str | None, digest: str) -> None:
        self.run_id, self.digest = run_id, digest

    def on_save_checkpoint(self, trainer: Any, pl_module: Any, checkpoint: dict) -> None:
        checkpoint[IDENTITY_KEY] = {"run_id": self.run_id, "config_hash": self.digest}


class LateralError(L.Callback):
    """After each validation of an observer that carries a single-track body
    (:func:`lbo.scoring.lateral.carries`) on a set that holds the car's lateral states
    (``data=dynamic``'s validation set): the error of the ``[v_y, r]`` its recursive form
    carries there (:func:`lbo.scoring.lateral.body_error`), logged as ``val_body_rmse_vy``
    (m/s) and ``val_body_rmse_r`` (rad/s) and written into every checkpoint's metadata
    (:data:`lbo.models.checkpoint.LATERAL_ERROR`): the error of the weights it holds, of
    which its lateral states' variances are made. Nothing for any other observer or set."""

    def __init__(self) -> None:
        self.error: np.ndarray | None = None
        self._val: Trajectories | None = None
        self._read = False  # the validation set read (None: a user's logs)

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        from lbo.scoring import lateral

        net = pl_module.observer  # lbo's TrainingModule
        if trainer.sanity_checking or not lateral.carries(net):
            return
        if not self._read:
            self._read = True
            folder = Path(trainer.datamodule.folder)  # type: ignore[attr-defined]
            self._val = load_test(folder / "val.parquet") if not is_log_folder(folder) else None
        val = self._val
        if val is None or val.lateral is None:  # nothing to measure on
            return
        body = lateral.carried(net, val, str(pl_module.device))
        self.error = lateral.body_error(body, val)
        pl_module.log_dict({f"val_body_rmse_{name}": lateral.rmse(
            body[..., i], val.lateral[..., i], val.mask) for i, name in enumerate(("vy", "r"))})

    def on_save_checkpoint(self, trainer: Any, pl_module: Any, checkpoint: dict) -> None:
        if self.error is not None:  # a copy: the module's own hyperparameters stay as built
            hp = checkpoint["hyper_parameters"]
            hp["meta"] = {**(hp.get("meta") or {}), LATERAL_ERROR: self.error.tolist()}
