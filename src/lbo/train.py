"""`python -m lbo.train`: train one learned observer (or a sweep with -m), log it to MLflow.

    python -m lbo.train -m model=cnn,lstm window=20,40,60,80 experiment=quick

``train(cfg)`` is plain Python: it takes a composed config and returns the metrics. ``main``
is the thin Hydra shell around it.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from lbo.core.atomic import write_text
from lbo.core.checks import SCHEDULES, integer, number, require
from lbo.core.cli import entry
from lbo.core.errors import LboError
from lbo.core.paths import REPO_ROOT
from lbo.core.redact import scrub, scrub_tree
from lbo.core.runfolder import claim
from lbo.learn import noise_run
from lbo.learn.builders import (
    Built,
    build,
    datamodule,
    logs_spec,
    model_settings,
    prepare_data,
    say_fresh,
    targets,
    training_envelope,
)
from lbo.learn.identity import config_hash, run_tags, write_marker
from lbo.learn.resume import LAST, check_folder, clear_stale_checkpoints, folder_refusal, prior_runs
from lbo.learn.trainer_checks import check_device, check_optimizer, check_trainer
from lbo.logs.sets import is_logs
from lbo.models.carried import covariance_of, sequence_model
from lbo.models.features import FEATURE_MODES
from lbo.models.net import check_scaling
from lbo.models.slip_filter import SIDE_SLIP as SLIP
from lbo.sim.datasets import refuse_sideslip
from lbo.sim.truth import config_dict as truth_dict
from lbo.tracking import view
from lbo.tracking.runs import check_store, dataset_input, log_input, logger_experiment

if TYPE_CHECKING:  # Lightning takes seconds to import: only a training run needs it
    import lightning as L

# Lightning 2.6 on torch 2.13 warns once per fit about its own use of a torch API; a sweep or a
# study would print it once per run
warnings.filterwarnings("ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated")
# lbo logs its losses once per epoch, never per step, so Lightning's logging interval, and
# its warning that an epoch of fewer batches than it logs nothing per step, do not apply
warnings.filterwarnings("ignore", message=r"The number of training batches \(\d+\) is smaller "
                        r"than the logging interval")
# Lightning hints at srun wherever SLURM's commands are installed (twice a run); lbo reaches
# SLURM through its submitit launcher, whose jobs need no srun
warnings.filterwarnings("ignore", message=r"The `srun` command is available on your system")


def git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO_ROOT, capture_output=True,
                             text=True, timeout=10)
        return out.stdout.strip() or "unknown"
    except OSError:
        return "unknown"


def check_compile(cfg: DictConfig) -> None:
    """``compile``: a flag, set only with ``tbptt``, and a C++ compiler for torch's inductor."""
    flag = cfg.get("compile")
    require(flag is None or isinstance(flag, bool), "compile", "true or false", flag)
    if flag and cfg.get("tbptt") is None:
        raise LboError("compile: it compiles the step of a filter trained carried; set tbptt "
                       "too, or compile=false")
    if flag and not any(shutil.which(cc) for cc in ("g++", "c++", "clang++")):
        raise LboError("compile: torch.compile needs a C++ compiler (g++ or clang++) on the "
                       "PATH, and none was found; install one, or set compile=false")


LOSSES = ("truth", "next_fix")
"""``loss``: against the true states, or self-supervised against each window's next fix."""


def check_loss(cfg: DictConfig) -> None:
    """``loss``: one of :data:`LOSSES`; ``next_fix`` on windows of full poses (no ``tbptt``,
    no ``receiver``, no GNSS drift, ``sensors.gnss_sigma``: the next fix's noise must be its
    own)."""
    loss = cfg.get("loss", "truth")
    require(loss in LOSSES, "loss", f"one of {list(LOSSES)}", loss)
    if loss != "next_fix":
        return
    for field, value, why in (
            ("tbptt", cfg.get("tbptt"), "a filter trained carried learns from the truth"),
            ("receiver", cfg.get("receiver"), "a receiver's windows learn from the truth"),
            ("sensors.gnss_sigma", (cfg.get("sensors") or {}).get("gnss_sigma") or None,
             "a drifting fix shares its error with the window's, so it cannot stand in for "
             "the truth")):
        if value is not None:
            raise LboError(f"loss=next_fix: expected {field}=null or 0 ({why}); got {value}")


def check(cfg: DictConfig) -> Built:
    """Reject bad training settings with one line naming the field, before any work; return
    the run's objects built on the way (:func:`lbo.learn.builders.build`). A net's: the gyro
    EKF's noise (``model=gyro_ekf``) is checked by :func:`lbo.learn.noise_run.check`."""
    if cfg.model.name == noise_run.NAME:  # tune, ablation and reproduce build nets
        raise LboError("model=gyro_ekf: the gyro EKF's noise is learned by python -m lbo.train "
                       "model=gyro_ekf alone; lbo.tune, lbo.ablation and lbo.reproduce "
                       "train nets (cnn, lstm, filternet, kalmannet, split_kalmannet)")
    if cfg.model.name in SLIP:  # lbo.tune checks it by slip_run.check
        raise LboError(f"model={cfg.model.name}: the side-slip observers are trained by "
                       f"python -m lbo.train "
                       f"and tuned by python -m lbo.tune on data=sideslip; lbo.ablation and "
                       "lbo.reproduce train the pose observers (cnn, lstm, filternet, "
                       "kalmannet, split_kalmannet)")
    refuse_sideslip(cfg)
    integer(cfg.model.window, "model.window", 4,
            form="an integer >= 4 (the CNN pools windows by 4)")
    require(cfg.model.features in FEATURE_MODES, "model.features",
            f"one of {list(FEATURE_MODES)}", cfg.model.features)
    integer(cfg.batch_size, "batch_size", 1)
    integer(cfg.seed, "seed", 0)
    if cfg.get("threads") is not None:
        integer(cfg.threads, "threads", 1)
    if cfg.get("tbptt") is not None:
        integer(cfg.tbptt, "tbptt", 2, form="null or an integer >= 2 (steps per chunk)")
        length = cfg.get("sequence_length") or cfg.model.window
        if cfg.get("sequence_length") is not None:
            integer(length, "sequence_length", 2, form="null or an integer >= 2 (steps)")
        require(cfg.tbptt <= length, "tbptt", f"at most the {length} steps of a training "
                "sequence (sequence_length, or model.window)", cfg.tbptt)
    elif cfg.get("sequence_length") is not None:
        raise LboError("sequence_length: set only with tbptt (the sequences trained carried); "
                       f"got {cfg.sequence_length} with tbptt=null")
    changes = (cfg.get("train_noise") or {}).get("changes") or 0
    if changes and cfg.get("tbptt") is None:
        raise LboError(f"train_noise.changes: the noise level changes along sequences trained "
                       f"carried; set tbptt too, or train_noise.changes=0 (got {changes})")
    nll = number(cfg.get("nll") or 0.0, "nll", low=0.0)
    if nll and cfg.get("tbptt") is None:
        raise LboError(f"nll: the Gaussian NLL term reads the covariance of a filter trained "
                       f"carried; set tbptt too, or nll=0 (got nll={nll} with tbptt=null)")
    check_compile(cfg)
    check_loss(cfg)
    for flag, default in (("keep_onnx", True), ("verbose", False)):
        require(isinstance(cfg.get(flag, default), bool), flag, "true or false", cfg.get(flag))
    check_scaling(cfg.model.normalisation, "model.normalisation")
    check_trainer(cfg.trainer)
    check_optimizer(cfg.optimizer)
    require(cfg.get("lr_schedule", "constant") in SCHEDULES, "lr_schedule",
            f"one of {list(SCHEDULES)}", cfg.get("lr_schedule"))
    from lbo.scoring.grid import REFERENCES

    reference = (cfg.get("metric") or {}).get("reference", "ekf")
    require(reference in REFERENCES, "metric.reference", f"one of {list(REFERENCES)}",
            reference)
    built = build(cfg)  # the model's own checks (its parameters, feature modes) before any data
    if nll and covariance_of(sequence_model(built.net.net)) is None:
        raise LboError(f"nll: model {cfg.model.name!r} gives no covariance for the Gaussian NLL "
                       "term (filternet does); expected nll=0")
    if is_logs(cfg):
        logs_spec(cfg)  # the logs named, found and of the right kind, before any run opens
    if cfg.get("logger") and cfg.logger.get("tracking_uri"):
        check_store(cfg.logger.tracking_uri)
    check_device(cfg.trainer)
    return built


def meta(cfg: DictConfig, data_hash: str) -> dict[str, Any]:
    """What a checkpoint carries besides the weights, to rebuild the observer elsewhere."""
    return {"vehicle": OmegaConf.to_container(cfg.vehicle, resolve=True),
            "noise": OmegaConf.to_container(cfg.noise, resolve=True),
            "truth": truth_dict(cfg),
            "data": cfg.data.name, "data_hash": data_hash, "seed": cfg.seed}


def train(cfg: DictConfig, callbacks: list[L.Callback] | None = None,
          tags: dict[str, str] | None = None) -> dict[str, Any]:
    """Train the observer described by ``cfg``; return its metrics.

    Parameters
    ----------
    cfg : a composed ``train`` config.
    callbacks : extra Lightning callbacks (e.g. Optuna's pruning), added to the configured ones.
    tags : extra MLflow tags (e.g. ``mlflow.parentRunId`` to nest the run under a study).

    Returns
    -------
    ``name``, ``val_loss`` (best), ``test_nrmse_alpha_{1,3,6}``, ``run_id``, ``checkpoint``,
    ``epochs``.
    """
    if cfg.model.name == noise_run.NAME:  # seven noises, no weights: no Lightning
        return noise_run.train(cfg, _flat(cfg), {"git_commit": git_commit(),
                                                 "model": noise_run.NAME,
                                                 "data": str(cfg.data.name), **(tags or {})})
    if cfg.model.name in SLIP:  # a lateral observer on a real run, not a pose window's net
        from lbo.learn import slip_run

        return slip_run.train(cfg, _flat(cfg), {"git_commit": git_commit(), **(tags or {})},
                              callbacks)
    built = check(cfg)
    # before the folder is claimed (its lock file): a folder of another run's files is left
    # as it was. With resume=true, a finished run of this config may be reused from the
    # store (its folder then left alone too): :func:`_train` checks again once that is known
    refusal = folder_refusal(Path(cfg.output_dir), config_hash(cfg), bool(cfg.get("resume")),
                             finished_ok=bool(cfg.get("resume")), cfg=cfg)
    if refusal is not None:
        raise LboError(refusal)
    if cfg.get("threads") is not None:  # e.g. two tune workers on one machine: 1 each
        torch.set_num_threads(int(cfg.threads))
    with claim(cfg.output_dir):
        return _train(cfg, built, callbacks, tags)


def _train(cfg: DictConfig, built: Built, callbacks: list[L.Callback] | None,
           tags: dict[str, str] | None) -> dict[str, Any]:
    """Reuse a finished run of the same config, continue a killed one, or fit afresh."""
    digest = config_hash(cfg)
    from lightning.pytorch.loggers import MLFlowLogger

    if targets(cfg.get("logger"), MLFlowLogger):
        # under a parallel launcher the first job creates the store and the experiment
        logger_experiment(cfg.logger)
    resume_id, resume_ckpt = None, None
    if cfg.get("resume") and cfg.get("logger"):
        reused, (resume_id, folder) = prior_runs(cfg, digest, keep_resumable=True)
        if reused is not None:
            print(f"reusing finished run {reused['run_id']} ({reused['name']}, same config)")
            return reused
        if resume_id is not None:
            # the killed run's own folder, so its checkpoints and files carry on where they are
            cfg = cfg.copy()
            with open_dict(cfg):
                cfg.output_dir = str(folder)
            resume_ckpt = cast(Path, folder) / "checkpoints" / LAST  # an id comes with its folder
            print(f"resuming the killed run {resume_id} (same config) from {resume_ckpt}")
    if resume_ckpt is None:  # a new run: never into another run's files
        refusal = folder_refusal(Path(cfg.output_dir), digest, bool(cfg.get("resume")),
                                 cfg=cfg)
        if refusal is not None:
            raise LboError(refusal)
    with claim(cfg.output_dir):
        return _fit(cfg, built, callbacks, tags, digest, resume_id, resume_ckpt)


def _fit(cfg: DictConfig, built: Built, callbacks: list[L.Callback] | None,
         tags: dict[str, str] | None, digest: str, resume_id: str | None,
         resume_ckpt: Path | None) -> dict[str, Any]:
    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint
    from lightning.pytorch.loggers import MLFlowLogger

    from lbo.learn.callbacks import Evaluation, LateralError, RunIdentity
    from lbo.learn.checkpoint_io import AtomicCheckpointIO
    from lbo.learn.lightning_module import TrainingModule

    L.seed_everything(cfg.seed, workers=True, verbose=False)
    folder, data_hash = prepare_data(cfg)
    dm = datamodule(cfg, folder, built)
    module = TrainingModule(model_settings(cfg), cfg.model.window, cfg.model.features,
                            optimizer=instantiate(cfg.optimizer),
                            meta={**meta(cfg, data_hash), "envelope": training_envelope(cfg, dm)},
                            lr_schedule=cfg.get("lr_schedule", "constant"),
                            fixes=bool(built.fix_periods), net=built.net,
                            receiver=built.net.receiver, tbptt=cfg.get("tbptt"),
                            clip=cfg.trainer.get("gradient_clip_val"),
                            nll=float(cfg.get("nll") or 0.0),
                            compiled=bool(cfg.get("compile")),
                            next_fix=((float(cfg.vehicle.dt), float(cfg.vehicle.wheelbase))
                                      if cfg.get("loss") == "next_fix" else None))
    module.observer.set_normalisation(**dm.normalisation(module.observer, cfg.model.normalisation))
    if built.init is not None:  # fine-tuning: its weights and its normalisation
        say_fresh(cfg, module.observer, built.init)
        module.observer.load_state_dict(built.init, strict=False)
        print(f"init_from: starting from the weights of {cfg.init_from}")

    name = f"{cfg.model.name}-N{cfg.model.window}"
    tags = {"git_commit": git_commit(), "data_hash": data_hash, "data": cfg.data.name,
            "model": cfg.model.name, "window": str(cfg.model.window),
            "features": cfg.model.features,
            "train_noise": _noise_tag(cfg),
            **run_tags(digest), **(tags or {})}
    logger = (instantiate(cfg.logger, tags=tags, **({"run_id": resume_id} if resume_id else {}))
              if cfg.get("logger") else None)
    identity = RunIdentity(resume_id, digest)
    callbacks = [*(instantiate(c) for c in (cfg.get("callbacks") or {}).values()),
                 *(callbacks or []), LateralError(), identity]
    # trained carried, the module clips each chunk's step itself (``clip``)
    manual: dict[str, Any] = ({"gradient_clip_val": None} if cfg.get("tbptt") is not None
                              else {})
    # Lightning's table of the model's layers: 10 lines before every run, asked for by verbose
    manual.setdefault("enable_model_summary", bool(cfg.get("verbose")))
    trainer = instantiate(cfg.trainer, logger=logger if logger is not None else False,
                          callbacks=callbacks, plugins=[AtomicCheckpointIO()], **manual)
    output = Path(cfg.output_dir)
    for cb in callbacks:
        if isinstance(cb, Evaluation) and isinstance(logger, MLFlowLogger):
            cb.mlflow = logger
        if isinstance(cb, ModelCheckpoint) and cb.dirpath and resume_ckpt is None:
            clear_stale_checkpoints(Path(cb.dirpath))
    try:
        if resume_id is None:  # the folder is this run's from its first file on
            identity.run_id = logger.run_id if isinstance(logger, MLFlowLogger) else None
            write_marker(output, identity.run_id, digest)
        if isinstance(logger, MLFlowLogger) and resume_id is None:  # logged before the kill
            logger.log_hyperparams(_flat(cfg))
            config_yaml = write_text(output / "config.yaml",
                                     scrub(OmegaConf.to_yaml(cfg, resolve=True)))
            logger.experiment.log_artifact(logger.run_id, str(config_yaml))
            log_input(logger.experiment, logger.run_id,
                      dataset_input(str(cfg.data.name), data_hash, folder))
        elif isinstance(logger, MLFlowLogger):
            logger.experiment.set_terminated(resume_id, "RUNNING")
        trainer.fit(module, datamodule=dm,
                    ckpt_path=str(resume_ckpt) if resume_ckpt is not None else None)
        ckpt = getattr(trainer.checkpoint_callback, "best_model_path", "") or ""
        if isinstance(logger, MLFlowLogger) and ckpt:  # with or without the evaluation
            _log_weights(logger, ckpt)
    except BaseException:
        if isinstance(logger, MLFlowLogger):
            logger.finalize("failed")  # also when the crash is outside Lightning's own hooks
        raise
    if isinstance(logger, MLFlowLogger):
        logger.finalize("success")  # fast_dev_run swaps the logger out, so Lightning would not
    write_marker(output, identity.run_id, digest, finished=True)  # no new run may replace it
    if ckpt and cfg.get("keep_onnx", True):
        _keep_graphs(ckpt)
    best = getattr(trainer.checkpoint_callback, "best_model_score", None)
    metrics: dict[str, Any] = {
        "name": name,
        "val_loss": float(best) if best is not None
        else float(trainer.callback_metrics.get("val_loss", float("nan"))),
        "checkpoint": ckpt,
        "run_id": logger.run_id if isinstance(logger, MLFlowLogger) else None,
        "epochs": trainer.current_epoch,
        "reused": False,
    }
    for cb in callbacks:
        if isinstance(cb, Evaluation):
            metrics.update(cb.metrics)
    return metrics


def _keep_graphs(checkpoint: str) -> None:
    """Keep the recursive form of the observer in ``checkpoint`` as ONNX graphs
    (:mod:`lbo.serve.exported`) where that is the form it runs in by default (the robust
    observer), saying so: the export takes about 20 s on 2 cores, and ``lbo.observe`` then
    runs it without torch. One that does not export is said in one line; it runs in PyTorch."""
    import time

    from lbo.models.checkpoint import read_checkpoint
    from lbo.serve import exported
    from lbo.serve.runners import default_form, is_window_filter

    net, _ = read_checkpoint(checkpoint)
    if not is_window_filter(net) or default_form(net) != "recursive":
        return
    print("keeping its recursive form as ONNX graphs, so that lbo.observe runs it without "
          "torch (about 20 s) ...", flush=True)
    start = time.perf_counter()
    try:
        kept = exported.keep(net, checkpoint)
    except (LboError, OSError) as e:
        print(f"not kept ({e}); lbo.observe runs it in PyTorch")
        return
    print(f"kept in {time.perf_counter() - start:.0f} s: {kept}")


def _log_weights(logger: Any, checkpoint: str) -> None:
    """Log the best checkpoint to the run (``checkpoints/best.ckpt``: ``Observer.load(<run
    id>)`` reads it) and the same weights as an MLflow model (``model/``: pyfunc
    ``load_model``, ``mlflow models serve``)."""
    from lbo.serve.serving import log_model

    logger.experiment.log_artifact(logger.run_id, checkpoint, artifact_path="checkpoints")
    log_model(logger.experiment.tracking_uri, logger.run_id, checkpoint)


def _noise_tag(cfg: DictConfig) -> str:
    """``stored``, ``fixed 1``, ``uniform [0, 6.5]``, ...: the training noise in a few words."""
    tn = cfg.get("train_noise")
    if tn is None or tn.source == "stored":
        return "stored"
    if tn.distribution == "fixed":
        return f"fixed {tn.alpha:g}"
    if tn.distribution == "levels":
        return f"levels {list(tn.levels)}"
    return f"{tn.distribution} [{tn.low:g}, {tn.high:g}]"


def _flat(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config as flat ``a.b.c`` params (lists as strings), Hydra's own left out,
    passwords masked."""
    out: dict[str, Any] = {}

    def walk(node: Any, prefix: str) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}{k}.")
        else:
            out[prefix[:-1]] = node

    walk(scrub_tree(OmegaConf.to_container(cfg, resolve=True)), "")
    return out


def _command(cfg: DictConfig) -> float:
    """``python -m lbo.train``: train, say where the observer is, and return the value a
    sweeper minimises."""
    metrics = train(cfg)
    if metrics.get("checkpoint"):
        print(f"trained {metrics['name']}: checkpoint {metrics['checkpoint']}"
              + (f", MLflow run {metrics['run_id']}" if metrics.get("run_id") else ""))
    if metrics.get("run_id") and cfg.get("logger"):
        import mlflow

        uri = cfg.logger.tracking_uri
        experiment = mlflow.MlflowClient(uri).get_run(metrics["run_id"]).info.experiment_id
        print(f"beside the other runs on its data, in mlflow ui (make ui): "
              f"{view.address(uri, experiment)}")
    return metrics["val_loss"]


main = entry("train", _command, guard=check_folder, short_model_keys=True)


if __name__ == "__main__":
    sys.exit(main())
