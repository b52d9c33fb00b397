"""A training run's objects built from its config: the net (with its initial weights), the data
set's folder and the data module with the training noise, and the device batches are made on.

`python -m lbo.train` builds through here, and so does :mod:`lbo.learn.eta`, which times a few steps
of the same run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from lbo.core.checks import integer, number, require
from lbo.core.errors import LboError
from lbo.learn.draws import SOURCES, AlphaDraw, fix_periods


def build_net(cfg: DictConfig):
    """The :class:`~lbo.models.net.WindowNet` that ``cfg.model`` describes, untrained."""
    from lbo.models.net import WindowNet

    model = OmegaConf.to_container(cfg.model, resolve=True)
    return WindowNet(model.pop("name"), cfg.window, cfg.features, fixes(cfg), **model)


def initial_weights(cfg: DictConfig, net, say: bool = True) -> dict[str, torch.Tensor]:
    """The weights ``init_from`` gives ``net``: every tensor of that observer whose name and
    shape ``net`` shares (its normalisation too). Tensors only ``net`` has (e.g. a residual
    the source was trained without) keep their fresh initialisation, and are named.

    Raises LboError naming ``init_from`` for an unreadable source, another architecture or
    feature mode, or a tensor whose shape differs (another size or window).
    """
    from lbo.serve.observer import load_net

    source = str(cfg.init_from)
    try:
        src, hp = load_net(source)
    except LboError as e:
        raise LboError(f"init_from: {e}") from None
    name = hp["model"]["name"]
    require(name == cfg.model.name, "init_from",
            f"an observer of this run's model={cfg.model.name} ({source} is a {name})", source)
    require(hp["features"] == cfg.features, "init_from",
            f"an observer of features={cfg.features} ({source} has features={hp['features']})",
            source)
    own, theirs = net.state_dict(), src.state_dict()
    for key, value in theirs.items():
        if key in own and own[key].shape != value.shape:
            raise LboError(f"init_from: {source} has {key} of shape {tuple(value.shape)}, this "
                           f"run's {cfg.model.name}-N{cfg.window} {tuple(own[key].shape)}; give "
                           "the window, fix_rates and model sizes it was trained with")
    fresh = [k for k in own if k not in theirs]
    if fresh and say:
        print(f"init_from: {len(fresh)} tensor(s) that {source} lacks start fresh: "
              f"{', '.join(fresh[:6])}{' ...' if len(fresh) > 6 else ''}")
    return {k: v for k, v in theirs.items() if k in own}


def logs_spec(cfg: DictConfig):
    from lbo.sim.log_sets import spec_from_cfg

    return spec_from_cfg(cfg)


def fixes(cfg: DictConfig) -> bool:
    """Whether the observer is trained with fixes dropped (``fix_rates``), and so takes them."""
    return bool(fix_periods(cfg.get("fix_rates"), cfg.vehicle.dt))


def datamodule(cfg: DictConfig, folder: Path):
    """The training and validation windows of ``folder`` as ``cfg`` asks for them (batch size,
    seed, training noise, device), set up."""
    from lbo.learn.datamodule import WindowDataModule

    dm = WindowDataModule(folder, cfg.window, cfg.batch_size, seed=cfg.seed,
                          device=data_device(cfg),
                          fix_periods=fix_periods(cfg.get("fix_rates"), cfg.vehicle.dt),
                          **noise_settings(cfg))
    dm.setup("fit")
    return dm


def data_device(cfg: DictConfig) -> str:
    """Where the training rows live and batches are drawn: the trainer's CUDA device, so a
    GPU run never copies a batch from the host, else the CPU."""
    acc = str(cfg.trainer.get("accelerator", "cpu"))
    if acc in ("gpu", "cuda") or (acc == "auto" and torch.cuda.is_available()):
        return "cuda"
    return "cpu"


def noise_settings(cfg: DictConfig) -> dict[str, Any]:
    """Keyword arguments of :class:`~lbo.learn.datamodule.WindowDataModule` for the
    ``train_noise`` group.

    Raises LboError naming the field for a bad source, distribution, alpha or range.
    """
    tn = cfg.get("train_noise")
    if tn is None or tn.get("source", "stored") == "stored":
        return {}
    require(tn.source in SOURCES, "train_noise.source", f"one of {list(SOURCES)}", tn.source)
    draw = AlphaDraw.from_cfg(tn)
    offset = tn.get("loss_weight_offset")
    if offset is not None:
        number(offset, "train_noise.loss_weight_offset", low=0.0, low_open=True,
               form="null or a number > 0")
    repeats = integer(tn.get("val_repeats", 1), "train_noise.val_repeats", 1)
    out = {"draw": draw, "sigma": tuple(cfg.noise.measurement_sigma),
           "weight_offset": offset, "val_repeats": repeats}
    truth = cfg.get("truth") or {}
    if truth.get("gnss_sigma", 0) > 0:  # the drawn noise drifts as the data set's does
        out["drift"] = (float(truth.gnss_sigma), float(truth.gnss_tau) / cfg.vehicle.dt)
    return out


def prepare_data(cfg: DictConfig) -> tuple[Path, str]:
    """The data-set folder (generated if missing, or ``data_dir`` as given) and its hash."""
    if cfg.get("data_dir"):
        folder = Path(cfg.data_dir)
        if not (folder / "train.parquet").is_file():
            raise LboError(f"data_dir: no train.parquet in {folder} "
                           "(give a folder printed by `python -m lbo.datagen`)")
        return folder, folder.name
    from lbo.sim.datasets import build_from_cfg

    return build_from_cfg(cfg)
