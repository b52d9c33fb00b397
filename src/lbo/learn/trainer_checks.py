"""The training settings every lbo observer's Lightning run shares, checked before any work:
the trainer, the optimiser and the device (one line naming the field)."""

from __future__ import annotations

from omegaconf import DictConfig

from lbo.core.checks import integer, number
from lbo.core.errors import LboError


def check_trainer(trainer: DictConfig) -> None:
    """``trainer.max_epochs`` >= 1 (0 would finish with the metrics of an untrained net, which
    ``resume=true`` would then reuse), ``min_epochs`` and the batch limits of the right kind."""
    integer(trainer.get("max_epochs"), "trainer.max_epochs", 1)
    if trainer.get("min_epochs") is not None:
        integer(trainer.min_epochs, "trainer.min_epochs", 0)
    for key in ("limit_train_batches", "limit_val_batches"):
        value = trainer.get(key)
        if value is None:
            continue
        form = "an integer >= 1 (batches) or a fraction in (0, 1]"
        if isinstance(value, float):  # Lightning reads a float as a fraction of the batches
            number(value, f"trainer.{key}", low=0.0, high=1.0, low_open=True, form=form)
        else:
            integer(value, f"trainer.{key}", 1, form=form)


def check_optimizer(opt: DictConfig) -> None:
    """``optimizer.lr`` a finite number > 0, ``weight_decay`` (and ``eps``) >= 0, before any
    run opens: the optimiser is only built inside ``fit``."""
    number(opt.get("lr"), "optimizer.lr", low=0.0, low_open=True)
    if opt.get("weight_decay") is not None:
        number(opt.weight_decay, "optimizer.weight_decay", low=0.0)
    if opt.get("eps") is not None:
        number(opt.eps, "optimizer.eps", low=0.0, low_open=True)


def check_device(trainer: DictConfig) -> None:
    """``trainer=gpu`` only where torch sees CUDA."""
    import torch

    if trainer.get("accelerator") == "gpu" and not torch.cuda.is_available():
        raise LboError("trainer=gpu needs CUDA, which torch does not see here; "
                       "use trainer=cpu or trainer=auto")
