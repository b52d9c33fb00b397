"""The learned side-slip observer, trained: ``lbo.train model=slip_gru``.

    python -m lbo.train model=slip_gru data=sideslip [model.window=50] [trainer.max_epochs=30]
    python -m lbo.train model=slip_gru data=sideslip_sim        # simulation only
    python -m lbo.train model=slip_gru data=sideslip init_from=<its checkpoint>  # fine-tuned
    python -m lbo.tune hparams_search=slip_gru [tune.n_trials=20]

The network (:mod:`lbo.models.slip`) is fitted on the training windows of
:mod:`lbo.learn.slip_data` (the real run's first 60%, or simulated runs), its epoch kept by
the validation windows (``val_loss``: beta's RMSE there, in degrees) and, with the evaluation
callback configured (as ``lbo.train`` has it, and no trial of ``lbo.tune``), scored on each
span of the real run beside the linear single-track Kalman filter it corrects. The truth (vy,
beta) is the loss's target and the score's reference, never an input.

It is trained as every learned observer is: by Lightning, with the configured trainer and
callbacks (the checkpoint of the best epoch, early stopping; Optuna's pruning in a study),
logged as one MLflow run: params (the resolved config), ``train_loss`` (deg^2) and
``val_loss`` (deg) per epoch; ``<span>_beta_rmse_deg``, ``<span>_linear_beta_rmse_deg`` and
``test_vs_linear``; artifacts ``checkpoints/best.ckpt`` (:func:`lbo.models.slip.load` reads
it), ``slip/spans.md`` and ``config.yaml``. ``resume=true`` reuses a finished run of the same
config.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from lbo.core.atomic import write_text
from lbo.core.checks import integer, number
from lbo.core.errors import LboError
from lbo.core.redact import scrub
from lbo.filters.lateral import LateralEstimate
from lbo.learn.slip_data import DATA, REAL, SIMULATED
from lbo.learn.trainer_checks import check_device, check_optimizer, check_trainer
from lbo.models.slip import NAME, PARAMETERS, Prior, SlipNet, SlipObserver, load

if TYPE_CHECKING:  # Lightning takes seconds to import: only a training run needs it
    import lightning as L

__all__ = ["KEYS", "check", "score", "spans_markdown", "train"]

SPANS = ("train", "val", "test")


KEYS = ("name", "window", *PARAMETERS, "features", "normalisation")
"""The ``model`` keys it takes (``features`` and ``normalisation``, every model's, are the pose
windows' and not read: its six channels are standardised)."""
UNREAD = (("receiver", None, "it reads the car's lateral sensors, not a receiver"),
          ("tbptt", None, "it is trained on windows"),
          ("sequence_length", None, "it is trained on windows"),
          ("nll", 0.0, "it gives no covariance"),
          ("fix_rates", None, "it reads no position fixes"),
          ("loss", "truth", "it learns from the INS's side slip"),
          ("lr_schedule", "constant", "it trains at the optimiser's constant rate"),
          ("data_dir", None, "it reads the run lbo ships"))
"""Training settings of the pose observers it does not take: (key, the value it needs, why)."""


def check(cfg: DictConfig) -> None:
    """The run's settings, checked before any work (one line naming the field)."""
    if cfg.data.name not in DATA:
        raise LboError(f"data: model={NAME} learns on the side-slip run (data={REAL}) or "
                       f"simulated runs of its kind (data={SIMULATED}); got "
                       f"data={cfg.data.name}")
    if cfg.data.name == SIMULATED:
        from lbo.learn.slip_data import settings

        settings(cfg.data)
        for key in ("train", "val", "stride"):
            integer(cfg.data[key], f"data.{key}", 1)
        integer(cfg.data.seed, "data.seed", 0)
    start = cfg.get("init_from")
    if start is not None and not (isinstance(start, str) and Path(start).is_file()):
        raise LboError(f"init_from: expected the path of a model={NAME} checkpoint to fine-tune "
                       f"(outputs/<run>/checkpoints/best.ckpt), got {start!r}")
    for key in cfg.model:
        if key not in KEYS:
            raise LboError(f"model.{key}: not a parameter of model {NAME!r} (it takes "
                           f"window, {', '.join(PARAMETERS)})")
    for key, needed, why in UNREAD:
        value = cfg.get(key, needed)
        if value != needed and not (needed == 0.0 and value is None):
            raise LboError(f"{key}: expected {needed} with model={NAME} ({why}); got {value}")
    integer(cfg.model.window, "model.window", 2, form="an integer >= 2 (rows of a window)")
    integer(cfg.model.hidden, "model.hidden", 1)
    integer(cfg.model.layers, "model.layers", 1)
    number(cfg.model.prior_gain, "model.prior_gain", low=0.0, low_open=True)
    integer(cfg.batch_size, "batch_size", 1)
    integer(cfg.seed, "seed", 0)
    check_trainer(cfg.trainer)
    check_optimizer(cfg.optimizer)
    check_device(cfg.trainer)
    if cfg.get("logger") and cfg.logger.get("tracking_uri"):
        from lbo.tracking.runs import check_store

        check_store(cfg.logger.tracking_uri)


def score(observer: SlipObserver, spans: dict[str, pd.DataFrame],
          priors: dict[str, LateralEstimate] | None = None) -> pd.DataFrame:
    """beta's RMSE and largest error (deg) on each span, the observer's and its prior's: one
    row per span and estimator (``span, estimator, rmse_deg, max_deg``). ``priors``: the
    prior's estimate of each span, if made already."""
    from lbo.sim.sideslip import observed

    rows = []
    for name, span in spans.items():
        vx, delta, y = observed(span)
        prior = (priors or {}).get(name) or observer.prior.run(vx, delta, y)
        truth = span["beta"].to_numpy(float)
        for label, est in ((NAME, observer.run(vx, delta, y, prior=prior)),
                           ("linear single-track KF", prior)):
            err = np.rad2deg(est.beta - truth)
            rows.append({"span": name, "estimator": label,
                         "rmse_deg": float(np.sqrt(np.mean(err**2))),
                         "max_deg": float(np.abs(err).max())})
    return pd.DataFrame(rows)


def spans_markdown(table: pd.DataFrame) -> str:
    lines = ["| span | estimator | beta RMSE (deg) | largest error (deg) |", "|---|---|---:|---:|"]
    lines += [f"| {r.span} | {r.estimator} | {r.rmse_deg:.3f} | {r.max_deg:.2f} |"
              for r in table.itertuples()]
    return "\n".join(lines) + "\n"


def _metrics(table: pd.DataFrame) -> dict[str, float]:
    out: dict[str, float] = {}
    for span, estimator, rmse in table[["span", "estimator", "rmse_deg"]].itertuples(
            index=False):
        key = "beta_rmse_deg" if estimator == NAME else "linear_beta_rmse_deg"
        out[f"{span}_{key}"] = float(rmse)
    if "test_beta_rmse_deg" in out:
        out["test_vs_linear"] = out["test_beta_rmse_deg"] / out["test_linear_beta_rmse_deg"]
    return out


def _module(net: SlipNet, window: int, prior: Prior, optimizer: Any) -> L.LightningModule:
    """The Lightning module: the :class:`SlipNet`, its loss in deg^2 and ``val_loss``, beta's
    RMSE (deg) over the validation span."""
    import lightning as L

    from lbo.models.slip import UNIT

    class SlipModule(L.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            # plain numbers only: load() reads them with weights_only
            self.save_hyperparameters({"name": NAME, "hidden": net.gru.hidden_size,
                                       "layers": net.gru.num_layers, "window": window,
                                       "prior": prior.as_dict()})
            self.net = net
            self._sums = torch.zeros(2)

        def training_step(self, batch: list[torch.Tensor], batch_idx: int) -> torch.Tensor:
            w, target = batch
            loss = torch.mean(((self.net(w) - target) / UNIT) ** 2)
            self.log("train_loss", loss, on_step=False, on_epoch=True, batch_size=len(w))
            return loss

        def on_validation_epoch_start(self) -> None:
            self._sums = torch.zeros(2)

        def validation_step(self, batch: list[torch.Tensor], batch_idx: int) -> None:
            w, target = batch
            err = (self.net(w) - target) / UNIT  # the estimate's error: prior + fix - truth
            self._sums += torch.stack([torch.sum(err.detach().cpu() ** 2),
                                       torch.tensor(float(len(w)))])

        def on_validation_epoch_end(self) -> None:
            self.log("val_loss", torch.sqrt(self._sums[0] / self._sums[1].clamp(min=1.0)),
                     prog_bar=True)

        def configure_optimizers(self) -> Any:
            return optimizer(self.parameters())

    return SlipModule()


def train(cfg: DictConfig, params: dict[str, Any], tags: dict[str, str],
          callbacks: list[Any] | None = None) -> dict[str, Any]:
    """Fit the observer as ``cfg`` says and log it as an MLflow run.

    params : the run's flat params (the resolved config); tags : its tags besides lbo's;
    callbacks : extra Lightning callbacks (a study's pruning).

    Returns ``name``, ``val_loss`` (the kept epoch's), ``run_id`` (None without a logger),
    ``checkpoint``, ``epochs``, ``reused`` and the spans' metrics."""
    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint

    from lbo.core.runfolder import claim
    from lbo.learn import slip_data
    from lbo.learn.builders import targets
    from lbo.learn.callbacks import Evaluation
    from lbo.learn.checkpoint_io import AtomicCheckpointIO
    from lbo.learn.resume import (
        clear_stale_checkpoints,
        config_hash,
        folder_refusal,
        prior_runs,
        write_marker,
    )

    check(cfg)
    digest = config_hash(cfg)
    name = f"{NAME}-N{cfg.model.window}"
    if cfg.get("resume") and cfg.get("logger"):
        reused, _ = prior_runs(cfg, digest)
        if reused is not None:
            print(f"reusing finished run {reused['run_id']} ({name}, same config)")
            return reused
    configured = dict(cfg.get("callbacks") or {})
    scored = any(targets(c, Evaluation) for c in configured.values())  # never in a trial
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    start = load(cfg.init_from) if cfg.get("init_from") else None
    made = slip_data.sets(cfg.data, int(cfg.model.window), float(cfg.model.prior_gain),
                          start.prior if start else None)
    (w, target), (val_w, val_target), prior = made.train, made.val, made.prior
    net = SlipNet(int(cfg.model.hidden), int(cfg.model.layers))
    module = _module(net, int(cfg.model.window), prior, instantiate(cfg.optimizer))
    if start is not None:  # its weights and its normalisation: the windows are its prior's
        if (start.window, start.net.gru.hidden_size, start.net.gru.num_layers) != (
                cfg.model.window, cfg.model.hidden, cfg.model.layers):
            raise LboError(f"init_from: {cfg.init_from} has window {start.window}, hidden "
                           f"{start.net.gru.hidden_size}, layers {start.net.gru.num_layers}; "
                           "expected the same model.window, model.hidden and model.layers")
        net.load_state_dict(start.net.state_dict())
        print(f"init_from: starting from the weights of {cfg.init_from}")
    else:
        net.set_normalisation(w[:, -1])  # each row once: the last of each window
    loaders = [torch.utils.data.DataLoader(torch.utils.data.TensorDataset(
        torch.from_numpy(a), torch.from_numpy(b)), batch_size=int(cfg.batch_size), shuffle=s)
        for a, b, s in ((w, target, True), (val_w, val_target, False))]
    out = Path(cfg.output_dir)
    tags = {**tags, "data": str(cfg.data.name), "model": NAME, "window": str(cfg.model.window),
            "config_hash": digest}
    logger = instantiate(cfg.logger, tags=tags) if cfg.get("logger") else None
    cbs = [instantiate(c) for c in configured.values() if not targets(c, Evaluation)]
    cbs += callbacks or []
    trainer = instantiate(cfg.trainer, logger=logger if logger is not None else False,
                          callbacks=cbs, plugins=[AtomicCheckpointIO()],
                          enable_model_summary=bool(cfg.get("verbose")))
    refusal = folder_refusal(out, digest, bool(cfg.get("resume")))
    if refusal is not None:  # never into another run's files (a finished one was reused above)
        raise LboError(refusal)
    with claim(out):
        clear_stale_checkpoints(out / "checkpoints")  # a killed run's, replaced by this one
        write_marker(out, logger.run_id if logger is not None else None, digest)
        try:
            if logger is not None:
                logger.log_hyperparams(params)
                config_yaml = write_text(out / "config.yaml",
                                         scrub(OmegaConf.to_yaml(cfg, resolve=True)))
                logger.experiment.log_artifact(logger.run_id, str(config_yaml))
            if scored:  # a study's trial is one line of the study's
                where = ("the train span" if cfg.data.name == REAL
                         else f"{cfg.data.train} simulated runs")
                print(f"learning the side-slip correction on {where} ({len(w)} windows of "
                      f"{cfg.model.window} rows); the epoch best on the validation "
                      f"{'span' if cfg.data.name == REAL else 'runs'} is kept")
            trainer.fit(module, *loaders)
            ckpt = next((c.best_model_path for c in cbs if isinstance(c, ModelCheckpoint)
                         and c.best_model_path), "")
            observer = load(ckpt) if ckpt else SlipObserver(net.cpu(),
                                                            int(cfg.model.window), prior)
            # the real run scored: every span after a training, none of the test in a trial
            spans = slip_data.real_spans()
            shown = SPANS if scored else SPANS[:2] if cfg.data.name == REAL else ()
            table = score(observer, {k: spans[k] for k in shown},
                          slip_data.real_estimates(observer.prior) if shown else None)
            metrics = _metrics(table)
            report = write_text(out / "spans.md", spans_markdown(table))
            if logger is not None:
                logger.log_metrics(metrics, step=trainer.current_epoch)
                logger.experiment.log_artifact(logger.run_id, str(report), "slip")
                if ckpt:
                    logger.experiment.log_artifact(logger.run_id, ckpt, "checkpoints")
        except BaseException:
            if logger is not None:
                logger.finalize("failed")
            raise
        if logger is not None:
            logger.finalize("success")
        # the folder is a finished run's: a rerun with resume=true reuses it, no other trains there
        write_marker(out, logger.run_id if logger is not None else None, digest, finished=True)
    if scored:
        print(f"beta RMSE (deg) on each span:\n{spans_markdown(table)}", end="")
    best = next((c.best_model_score for c in cbs if isinstance(c, ModelCheckpoint)
                 and c.best_model_score is not None), None)
    val = float(best) if best is not None else float("nan")
    return {"name": name, "val_loss": val, "checkpoint": ckpt,
            "run_id": logger.run_id if logger is not None else None,
            "epochs": trainer.current_epoch, "reused": False, **metrics}
