"""Learned observers as plain ``nn.Module``s: (B, N, 5) windows -> (B, 3) states.

``build_model`` is the one place that turns a model name and hyperparameters (from a config or
a search space) into a module, and rejects unknown names and parameters with a one-line
:class:`~lbo.core.errors.LboError` before anything trains.
"""

from __future__ import annotations

import inspect
from typing import Any

from torch import nn

from lbo.core.errors import LboError
from lbo.models.cnn import WindowCNN
from lbo.models.filternet import WindowFilter
from lbo.models.lstm import WindowLSTM

MODELS: dict[str, type[nn.Module]] = {"cnn": WindowCNN, "lstm": WindowLSTM,
                                      "filternet": WindowFilter}


def model_parameters(name: str) -> tuple[str, ...]:
    """The keyword arguments that model ``name`` accepts besides ``window``."""
    _check_name(name)
    params = inspect.signature(MODELS[name]).parameters
    return tuple(p for p in params if p != "window")


def _check_name(name: str) -> None:
    if name not in MODELS:
        raise LboError(f"model: unknown model {name!r}; expected one of {', '.join(MODELS)}")


def build_model(name: str, window: int, **kwargs: Any) -> nn.Module:
    """Build observer ``name`` for windows of ``window`` steps.

    Parameters
    ----------
    name : a key of :data:`MODELS` (``"cnn"`` or ``"lstm"``).
    window : N, time steps per window.
    **kwargs : the model's hyperparameters (see :class:`WindowCNN`, :class:`WindowLSTM`).

    Raises
    ------
    LboError
        For an unknown model name, a keyword the model does not accept, or a bad value.
    """
    accepted = model_parameters(name)
    unknown = [k for k in kwargs if k not in accepted]
    if unknown:
        raise LboError(f"model.{unknown[0]}: not a parameter of model {name!r}; "
                       f"accepted: {', '.join(accepted)}")
    return MODELS[name](window, **kwargs)


__all__ = ["MODELS", "WindowCNN", "WindowFilter", "WindowLSTM", "build_model",
           "model_parameters"]
