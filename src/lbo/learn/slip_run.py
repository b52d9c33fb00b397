"""The learned side-slip observers, trained: ``lbo.train model=slip_gru`` or ``slip_filter``.

    python -m lbo.train model=slip_gru data=sideslip [model.window=50] [trainer.max_epochs=30]
    python -m lbo.train model=slip_filter data=sideslip   # the filter whose tyres and noise learn
    python -m lbo.train model=slip_gru data=sideslip_sim        # simulation only
    python -m lbo.train model=slip_gru data=sideslip init_from=<its checkpoint>  # fine-tuned
    python -m lbo.tune hparams_search=slip_gru [tune.n_trials=20]

The network (:mod:`lbo.models.slip`) or the filter (:mod:`lbo.models.slip_filter`) is fitted on
the training rows of :mod:`lbo.learn.slip_data` (the real run's first 60%, or simulated runs;
:mod:`lbo.learn.slip_models` holds what differs between the two), its epoch kept by the
validation rows (``val_loss``: beta's RMSE there, in degrees) and, with the evaluation callback
configured (as ``lbo.train`` has it, and no trial of ``lbo.tune``), scored on each span of the
real run beside the linear single-track Kalman filter it corrects. The truth (vy, beta) is the
loss's target and the score's reference, never an input.

It is trained as every learned observer is: by Lightning, with the configured trainer and
callbacks (the checkpoint of the best epoch, early stopping; Optuna's pruning in a study),
logged as one MLflow run: params (the resolved config), ``train_loss`` (deg^2) and
``val_loss`` (deg) per epoch; ``<span>_beta_rmse_deg``, ``<span>_linear_beta_rmse_deg`` and
``test_vs_linear``; artifacts ``checkpoints/best.ckpt`` (:func:`lbo.learn.slip_models.load`
reads it), ``slip/spans.md`` and ``config.yaml``. ``resume=true`` reuses a finished run of the same
config.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

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
from lbo.learn import slip_models
from lbo.learn.slip_data import DATA, REAL, SIMULATED
from lbo.learn.slip_models import PARAMETERS, Observer, load, run_name
from lbo.learn.trainer_checks import check_device, check_optimizer, check_trainer
from lbo.models.slip import NAME as SLIP_GRU

__all__ = ["check", "score", "spans_markdown", "train"]

SPANS = ("train", "val", "test")
LINEAR = "linear single-track KF"
"""The prior's row in :func:`score`'s table (the learned observer's is its model's name)."""


COMMON = ("name", "window", "features", "normalisation")
"""The ``model`` keys every model has (``features`` and ``normalisation`` are the pose
windows' and not read: a side-slip observer reads its own channels; the filter reads no
window)."""
UNREAD = (("receiver", None, "it reads the car's lateral sensors, not a receiver"),
          ("tbptt", None, "it sets its own windows or sequences (model.window, model.sequence)"),
          ("sequence_length", None,
           "it sets its own windows or sequences (model.window, model.sequence)"),
          ("nll", 0.0, "it gives no covariance: its loss is beta's squared error"),
          ("fix_rates", None, "it reads no position fixes"),
          ("loss", "truth", "it learns from the INS's side slip"),
          ("lr_schedule", "constant", "it trains at the optimiser's constant rate"),
          ("data_dir", None, "it reads the run lbo ships"))
"""Training settings of the pose observers it does not take: (key, the value it needs, why)."""


def check(cfg: DictConfig) -> None:
    """The run's settings, checked before any work (one line naming the field)."""
    name = cfg.model.name
    if cfg.data.name not in DATA:
        raise LboError(f"data: model={name} learns on the side-slip run (data={REAL}) or "
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
        raise LboError(f"init_from: expected the path of a model={name} checkpoint to "
                       f"fine-tune (outputs/<run>/checkpoints/best.ckpt), got {start!r}")
    takes = ("window", *PARAMETERS[name]) if name == SLIP_GRU else PARAMETERS[name]
    for key in cfg.model:
        if key not in (*COMMON, *PARAMETERS[name]):
            raise LboError(f"model.{key}: not a parameter of model {name!r} (it takes "
                           f"{', '.join(takes)})")
    for key, needed, why in UNREAD:
        if key == "nll" and name != SLIP_GRU:  # the filter's covariance can be trained
            number(cfg.get("nll") or 0.0, "nll", low=0.0)
            continue
        value = cfg.get(key, needed)
        if value != needed and not (needed == 0.0 and value is None):
            raise LboError(f"{key}: expected {needed} with model={name} ({why}); got {value}")
    slip_models.check(cfg.model)
    integer(cfg.batch_size, "batch_size", 1)
    integer(cfg.seed, "seed", 0)
    check_trainer(cfg.trainer)
    check_optimizer(cfg.optimizer)
    check_device(cfg.trainer)
    if cfg.get("logger") and cfg.logger.get("tracking_uri"):
        from lbo.tracking.runs import check_store

        check_store(cfg.logger.tracking_uri)


def score(observer: Observer, spans: dict[str, pd.DataFrame],
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
        for label, est in ((slip_models.shape(observer)[0],
                            observer.run(vx, delta, y, prior=prior)), (LINEAR, prior)):
            err = np.rad2deg(est.beta - truth)
            rows.append({"span": name, "estimator": label,
                         "rmse_deg": float(np.sqrt(np.mean(err**2))),
                         "max_deg": float(np.abs(err).max())})
    return pd.DataFrame(rows, columns=["span", "estimator", "rmse_deg", "max_deg"])


def spans_markdown(table: pd.DataFrame) -> str:
    lines = ["| span | estimator | beta RMSE (deg) | largest error (deg) |", "|---|---|---:|---:|"]
    lines += [f"| {r.span} | {r.estimator} | {r.rmse_deg:.3f} | {r.max_deg:.2f} |"
              for r in table.itertuples()]
    return "\n".join(lines) + "\n"


def _metrics(table: pd.DataFrame) -> dict[str, float]:
    out: dict[str, float] = {}
    for span, estimator, rmse in table[["span", "estimator", "rmse_deg"]].itertuples(
            index=False):
        key = "linear_beta_rmse_deg" if estimator == LINEAR else "beta_rmse_deg"
        out[f"{span}_{key}"] = float(rmse)
    if "test_beta_rmse_deg" in out:
        out["test_vs_linear"] = out["test_beta_rmse_deg"] / out["test_linear_beta_rmse_deg"]
    return out


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
    from lbo.learn.identity import config_hash, run_tags, write_marker
    from lbo.learn.resume import clear_stale_checkpoints, folder_refusal, prior_runs
    from lbo.tracking.runs import logger_experiment

    check(cfg)
    digest = config_hash(cfg)
    name = run_name(cfg.model)
    if cfg.get("logger"):  # as training's: the first of jobs started together makes them
        logger_experiment(cfg.logger)
    if cfg.get("resume") and cfg.get("logger"):
        reused, _ = prior_runs(cfg, digest)
        if reused is not None:
            print(f"reusing finished run {reused['run_id']} ({name}, same config)")
            return reused
    configured = dict(cfg.get("callbacks") or {})
    scored = any(targets(c, Evaluation) for c in configured.values())  # never in a trial
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    start = load(cfg.init_from) if cfg.get("init_from") else None
    made = slip_models.make(cfg, instantiate(cfg.optimizer), start)
    if start is not None:
        print(f"init_from: starting from the weights of {cfg.init_from}")
    loaders = [torch.utils.data.DataLoader(torch.utils.data.TensorDataset(*data),
                                           batch_size=int(cfg.batch_size), shuffle=shuffle)
               for data, shuffle in ((made.train, True), (made.val, False))]
    out = Path(cfg.output_dir)
    tags = {**tags, "data": str(cfg.data.name), "model": str(cfg.model.name),
            **run_tags(digest),
            **({"window": str(cfg.model.window)} if "window" in cfg.model else {})}
    logger = instantiate(cfg.logger, tags=tags, run_name=name) if cfg.get("logger") else None
    cbs = [instantiate(c) for c in configured.values() if not targets(c, Evaluation)]
    cbs += callbacks or []
    trainer = instantiate(cfg.trainer, logger=logger if logger is not None else False,
                          callbacks=cbs, plugins=[AtomicCheckpointIO()],
                          enable_model_summary=bool(cfg.get("verbose")))
    refusal = folder_refusal(out, digest, bool(cfg.get("resume")), cfg=cfg)
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
                print(f"learning {cfg.model.name} on {where} ({made.what}); the epoch best "
                      f"on the validation {'span' if cfg.data.name == REAL else 'runs'} is kept")
            trainer.fit(made.module, *loaders)
            ckpt = next((c.best_model_path for c in cbs if isinstance(c, ModelCheckpoint)
                         and c.best_model_path), "")
            observer = load(ckpt) if ckpt else made.observer()
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
