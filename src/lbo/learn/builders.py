"""A training run's objects built from its config: the net (with its initial weights), the data
set's folder and the data module with the training noise, and the device batches are made on.

`python -m lbo.train` builds through here, and so does :mod:`lbo.learn.eta`, which times a few
steps of the same run.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from lbo.core import plugins
from lbo.core.checks import integer, number, require
from lbo.core.cli import MODEL_SHORT
from lbo.core.errors import LboError
from lbo.learn.draws import SOURCES, AlphaDraw, OutageDraw, ReceiverDraw, fix_periods


@dataclass(frozen=True, kw_only=True)
class Built:
    """A training run's objects, built once from its config before any data is made or any
    run opens (building them is also how their settings are checked)."""

    net: Any
    """The untrained :class:`~lbo.models.net.WindowNet`, its weights drawn from ``cfg.seed``."""
    fix_periods: tuple[int, ...]
    """Steps between fixes the training drops to (``fix_rates``); () keeps every fix."""
    noise: dict[str, Any]
    """The data module's training-noise arguments (:func:`noise_settings`)."""
    init: dict[str, torch.Tensor] | None
    """``init_from``'s weights for ``net`` (:func:`initial_weights`), or None."""
    outages: OutageDraw | None = None
    """The GNSS outages drawn into the training windows (``train_outages``), or None."""


def build(cfg: DictConfig) -> Built:
    """Every object of the run ``cfg`` describes that needs no data: the net (and the weights
    ``init_from`` gives it), the fix periods and the training noise. One line naming the field
    for a bad one."""
    periods = fix_periods(cfg.get("fix_rates"), cfg.vehicle.dt)
    noise = noise_settings(cfg)
    net = build_net(cfg, periods)
    if net.model not in plugins.OWN["model"]:  # lbo's own keep it (tests/test_models.py)
        net.check_output(int(cfg.batch_size))  # on one batch, before any run or folder
    init = initial_weights(cfg, net, say=False) if cfg.get("init_from") else None
    return Built(net=net, fix_periods=periods, noise=noise, init=init,
                 outages=outage_draw(cfg, periods))


def outage_draw(cfg: DictConfig, periods: tuple[int, ...]) -> OutageDraw | None:
    """The outages ``train_outages`` draws into training windows, or None (one line naming
    the field for a bad setting)."""
    return OutageDraw.from_cfg(cfg.get("train_outages") or {}, float(cfg.vehicle.dt),
                               bool(periods))


def model_settings(cfg: DictConfig) -> dict[str, Any]:
    """``cfg.model`` without the settings every observer has (:data:`lbo.core.cli.MODEL_SHORT`:
    its window, feature mode and normalisation, given to it apart): its ``name`` and its
    architecture's own keyword arguments, as a checkpoint keeps them."""
    model = cast(dict, OmegaConf.to_container(cfg.model, resolve=True))  # a mapping's: a dict
    return {k: v for k, v in model.items() if k not in MODEL_SHORT}


def build_net(cfg: DictConfig, periods: tuple[int, ...] | None = None):
    """The :class:`~lbo.models.net.WindowNet` that ``cfg.model`` describes, untrained, its
    weights drawn from ``cfg.seed`` (the global random state is left as it was). ``periods``:
    the fix periods, if already known."""
    from lbo.models.net import WindowNet

    if periods is None:
        periods = fix_periods(cfg.get("fix_rates"), cfg.vehicle.dt)
    model = model_settings(cfg)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        return WindowNet(model.pop("name"), cfg.model.window, cfg.model.features,
                         fixes=bool(periods), receiver=bool(cfg.get("receiver")),
                         motion=(float(cfg.vehicle.dt), float(cfg.vehicle.wheelbase)),
                         carried=cfg.get("tbptt") is not None, **model)


def initial_weights(cfg: DictConfig, net, say: bool = True) -> dict[str, torch.Tensor]:
    """The weights ``init_from`` gives ``net``: every tensor of that observer whose name and
    shape ``net`` shares (its normalisation too). Tensors only ``net`` has (e.g. a residual
    the source was trained without) keep their fresh initialisation, and are named.

    Raises LboError naming ``init_from`` for an unreadable source, another architecture or
    feature mode, or a tensor whose shape differs (another size or window).
    """
    from lbo.tracking.artifacts import load_net

    source = str(cfg.init_from)
    try:
        src, hp = load_net(source)
    except LboError as e:
        raise LboError(f"init_from: {e}") from None
    name = hp["model"]["name"]
    require(name == cfg.model.name, "init_from",
            f"an observer of this run's model={cfg.model.name} ({source} is a {name})", source)
    require(hp["features"] == cfg.model.features, "init_from",
            f"an observer of features={cfg.model.features} ({source} has "
            f"features={hp['features']})",
            source)
    own, theirs = net.state_dict(), src.state_dict()
    for key, value in theirs.items():
        if key in own and own[key].shape != value.shape:
            raise LboError(f"init_from: {source} has {key} of shape {tuple(value.shape)}, this "
                           f"run's {cfg.model.name}-N{cfg.model.window} "
                           f"{tuple(own[key].shape)}; give "
                           "the window, fix_rates and model sizes it was trained with")
    init = {k: v for k, v in theirs.items() if k in own}
    if say:
        say_fresh(cfg, net, init)
    return init


def say_fresh(cfg: DictConfig, net, init: dict[str, torch.Tensor]) -> None:
    """Name the tensors of ``net`` that ``init_from``'s weights ``init`` lack (they start
    fresh), if any."""
    fresh = [k for k in net.state_dict() if k not in init]
    if fresh:
        print(f"init_from: {len(fresh)} tensor(s) that {cfg.init_from} lacks start fresh: "
              f"{', '.join(fresh[:6])}{' ...' if len(fresh) > 6 else ''}")


def logs_spec(cfg: DictConfig):
    """The checked ``data=logs`` config of a training: its training and validation logs
    given, its test logs optional (a fleet with no truth at all trains, scored nowhere)."""
    from lbo.logs.sets import spec_from_cfg

    return spec_from_cfg(cfg, need=("train", "val"))


def datamodule(cfg: DictConfig, folder: Path, built: Built | None = None):
    """The training and validation windows of ``folder`` as ``cfg`` asks for them (batch size,
    seed, training noise, device), set up; with the fix periods and training noise of
    ``built`` (worked out from ``cfg`` when None)."""
    from lbo.learn.datamodule import WindowDataModule

    periods = built.fix_periods if built else fix_periods(cfg.get("fix_rates"), cfg.vehicle.dt)
    noise = built.noise if built else noise_settings(cfg)
    outages = built.outages if built else outage_draw(cfg, periods)
    carried = cfg.get("tbptt") is not None  # its windows: sequences, maybe longer than N
    length = (cfg.get("sequence_length") or cfg.model.window) if carried else cfg.model.window
    dm = WindowDataModule(folder, length, cfg.batch_size, seed=cfg.seed,
                          device=data_device(cfg), fix_periods=periods,
                          sequences=carried, next_fix=cfg.get("loss") == "next_fix",
                          outages=outages, **noise)
    dm.setup("fit")
    return dm


def training_envelope(cfg: DictConfig, dm) -> dict[str, Any]:
    """The envelope of the training inputs of data module ``dm`` (set up), as a checkpoint
    stores it (:class:`~lbo.models.envelope.Envelope`): the rows' speed and steering, the
    noise scale the windows were drawn at (the data set's for stored noise; unknown for real
    logs) and the steps between fixes."""
    from lbo.models.envelope import Envelope

    x = dm.train_set.x.cpu().numpy()  # (R, 5) [x_m, y_m, psi_m, V, delta]
    if dm.draw is not None:
        alpha = dm.draw.bounds
    else:
        a = (cfg.data.get("train") or {}).get("alpha") if cfg.data.get("kind") != "logs" \
            else None
        alpha = None if a is None else (float(a), float(a))
    if dm.fix_periods:
        period = (float(min(dm.fix_periods)), float(max(dm.fix_periods)))
    else:  # as stored: every step, or a user's logs with GNSS slower than the inputs
        fixes = max(int(np.isfinite(x[:, :2]).all(1).sum()), 1)
        period = (len(x) / fixes,) * 2
    return Envelope.from_training(x[:, 3:5], alpha, period).to_dict()


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
        return {"receiver": receiver_draw(cfg)} if cfg.get("receiver") else {}
    require(tn.source in SOURCES, "train_noise.source", f"one of {list(SOURCES)}", tn.source)
    draw = AlphaDraw.from_cfg(tn)
    offset = tn.get("loss_weight_offset")
    if offset is not None:
        number(offset, "train_noise.loss_weight_offset", low=0.0, low_open=True,
               form="null or a number > 0")
    repeats = integer(tn.get("val_repeats", 1), "train_noise.val_repeats", 1)
    out = {"draw": draw, "sigma": tuple(cfg.noise.measurement_sigma),
           "weight_offset": offset, "val_repeats": repeats}
    sensors: Any = cfg.get("sensors") or {}  # a config node (read as one), or none
    if sensors.get("gnss_sigma", 0) > 0:  # the drawn noise drifts as the data set's does
        out["drift"] = (float(sensors.gnss_sigma), float(sensors.gnss_tau) / cfg.vehicle.dt)
    if cfg.get("receiver"):
        out["receiver"] = receiver_draw(cfg)
    return out


def receiver_draw(cfg: DictConfig) -> ReceiverDraw:
    """The receiver drawn per training window (groups ``receiver`` and
    ``receiver_training``); one line naming the field for a bad one."""
    from lbo.sim.receiver import ReceiverSpec

    require(bool(cfg.get("fix_rates")), "fix_rates",
            "the rates (Hz) of the receiver's fixes in training windows, e.g. [10, 5, 1]",
            cfg.get("fix_rates"))
    mix = dict(cfg.get("receiver_training") or {})
    unknown = [k for k in mix if k not in ("heading_share", "gyro_share")]
    if unknown:
        raise LboError(f"receiver_training.{unknown[0]}: not a field; accepted: heading_share, "
                       "gyro_share")
    dt = float(cfg.vehicle.dt)
    return ReceiverDraw(ReceiverSpec.from_cfg(cfg.receiver, dt), dt=dt,
                        heading_sigma=float(cfg.noise.measurement_sigma[2]),
                        wheelbase=float(cfg.vehicle.wheelbase), **mix)


def prepare_data(cfg: DictConfig) -> tuple[Path, str]:
    """The data-set folder a composed config names and its digest: ``data_dir`` as given,
    read from a user's logs with ``data=logs`` (:mod:`lbo.logs.sets`), or generated (or
    reused) from the ``data`` group."""
    if cfg.get("data_dir"):
        folder = Path(cfg.data_dir)
        if not (folder / "train.parquet").is_file():
            raise LboError(f"data_dir: no train.parquet in {folder} "
                           "(give a folder printed by `python -m lbo.datagen`)")
        return folder, folder.name
    from lbo.logs import sets as logs
    from lbo.sim import datasets

    if logs.is_logs(cfg):  # a user's logs (data=logs, data=hill)
        log_spec = logs_spec(cfg)
        return logs.build(log_spec)[0], log_spec.digest
    spec = datasets.spec_from_cfg(cfg)
    return datasets.build(spec)[0], spec.digest


def targets(node: Any, kind: type) -> bool:
    """Whether config ``node`` (a ``_target_`` map, or None) builds a ``kind``: its target class
    is ``kind`` or a subclass, by type, not by name. A target that cannot be imported is one
    line naming it."""
    from hydra.utils import get_class

    target = node.get("_target_") if node else None
    if not target:
        return False
    try:
        cls = get_class(str(target))
    except Exception as e:  # Hydra wraps the import's error in its own
        raise LboError(f"_target_ {target!r} cannot be imported ({type(e).__name__})") from None
    return isinstance(cls, type) and issubclass(cls, kind)
