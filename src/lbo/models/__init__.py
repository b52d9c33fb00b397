"""Learned observers as plain ``nn.Module``s: (B, N, C) windows -> (B, 3) states.

``build_model`` is the one place that turns a model name and hyperparameters (from a config, a
search space or a checkpoint) into a module, and rejects unknown names and parameters with a
one-line :class:`~lbo.core.errors.LboError` before anything trains. A name is looked up among
the installed packages' entry points (group ``lbo.models``, :mod:`lbo.core.plugins`): lbo's own
``cnn``, ``lstm``, ``filternet``, ``kalmannet`` and ``split_kalmannet`` are registered there as
a user's model is
(docs/plugins.md).
"""

from __future__ import annotations

import importlib
import inspect
from typing import TYPE_CHECKING, Any

from lbo.core import plugins
from lbo.core.errors import LboError

if TYPE_CHECKING:
    from torch import nn

_CLASSES = {"WindowCNN": "cnn", "WindowLSTM": "lstm", "WindowFilter": "filternet",
            "KalmanNet": "kalmannet", "SplitKalmanNet": "kalmannet"}
"""lbo's own model classes, by the module under ``lbo.models`` that holds each: imported
when first asked for, so that what needs no network (a checkpoint's envelope, a classical
observer) does not import torch."""


def __getattr__(name: str) -> Any:
    if name in _CLASSES:
        return getattr(importlib.import_module(f"lbo.models.{_CLASSES[name]}"), name)
    raise AttributeError(f"module 'lbo.models' has no attribute {name!r}")


def model_names() -> tuple[str, ...]:
    """The registered models' names, lbo's own first (``cnn``, ``lstm``, ``filternet``,
    ``kalmannet``, ``split_kalmannet``)."""
    return plugins.names("model")


def model_class(name: object, recorded: dict[str, Any] | None = None) -> type[nn.Module]:
    """The class registered as ``name``; ``recorded``: the provider a checkpoint stored, for
    the error when it is not installed. Raises LboError naming ``model.name`` (for a ``name``
    that is not a registered name, of any type: a checkpoint's is read unchecked)."""
    from torch import nn

    cls = plugins.load("model", name, "model.name", recorded)
    if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
        raise LboError(f"model.name: model {name!r} is registered as {cls!r}, not a "
                       "torch.nn.Module class")
    return cls


def model_parameters(name: str) -> tuple[str, ...]:
    """The keyword arguments that model ``name`` accepts besides ``window``."""
    params = inspect.signature(model_class(name)).parameters
    return tuple(p for p in params if p != "window")


def build_model(name: str, window: int, **kwargs: Any) -> nn.Module:
    """Build observer ``name`` for windows of ``window`` steps.

    Parameters
    ----------
    name : a registered model's name (:func:`model_names`).
    window : N, time steps per window.
    **kwargs : the model's hyperparameters (see :class:`WindowCNN`, :class:`WindowLSTM`,
        :class:`WindowFilter`, or the plug-in's class).

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
    cls = model_class(name)
    if name in plugins.OWN["model"]:  # lbo's own check every value in one line themselves
        return cls(window, **kwargs)
    try:
        return cls(window, **kwargs)
    except (TypeError, ValueError) as e:  # a plug-in's own check, said in lbo's one line
        raise LboError(f"model: model {name!r} refused its settings "
                       f"({', '.join(f'{k}={v!r}' for k, v in kwargs.items()) or 'defaults'}):"
                       f" {e}") from None


__all__ = ["KalmanNet", "SplitKalmanNet", "WindowCNN", "WindowFilter", "WindowLSTM",
           "build_model", "model_class", "model_names", "model_parameters"]
