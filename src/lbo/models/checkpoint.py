"""Reading a learned observer's checkpoint: the net it names, rebuilt from the installed parts.

A checkpoint (as ``lbo.train`` writes it) stores the model's registered name, its
hyperparameters, the vehicle and noise it was trained with, its training envelope and its
weights. lbo reads it with ``torch.load(weights_only=True)`` (tensors and plain containers
only) and looks the name up among the installed plug-ins (:mod:`lbo.core.plugins`): nothing a
file names is ever imported.
"""

from __future__ import annotations

import collections
import os
import pickle
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lbo.core.errors import LboError
from lbo.models.envelope import Envelope
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle


def read_checkpoint(path: str | os.PathLike, features: str | None = None,
                    device: str = "cpu") -> tuple[Any, dict[str, Any]]:
    """Rebuild the :class:`~lbo.models.net.WindowNet` of an ``lbo.train`` checkpoint.

    The checkpoint's hyperparameters name the architecture, window and feature mode, its
    buffers hold the normalisation statistics and ``meta`` the vehicle (dt) and noise preset.
    Only tensors and plain containers are unpickled (``weights_only``).

    Returns
    -------
    (net in eval mode, hyperparameters dict).

    Raises
    ------
    LboError
        Unreadable file, not an lbo checkpoint, another checkpoint format, an unknown
        feature mode or not the ``features`` asked for, weights that do not fit, weights
        that hold NaN or inf (a diverged training).
    """
    import torch

    from lbo.models import model_class
    from lbo.models.net import CHECKPOINT_FORMAT, WindowNet

    path = Path(path)
    check_features(path, None, features)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except PermissionError as e:
        raise LboError(f"checkpoint {path}: cannot read it ({e.strerror})") from None
    except Exception as e:  # zip, pickle, EOF: not a file lbo wrote
        # torch's own message suggests weights_only=False: unsafe advice for a foreign file
        what = ("it holds pickled objects beyond tensors and plain containers, which lbo "
                "never unpickles" if "weights_only" in str(e).lower() or
                "weights only" in str(e).lower() else "damaged, or another kind of file")
        raise LboError(f"checkpoint {path}: not a readable lbo checkpoint ({what})") from None
    hp = ckpt.get("hyper_parameters") if isinstance(ckpt, dict) else None
    if not isinstance(hp, dict) or "state_dict" not in ckpt:
        raise LboError(f"checkpoint {path}: not an lbo observer checkpoint "
                       "(no hyper_parameters and state_dict)")
    fmt = hp.get("format")
    if fmt != CHECKPOINT_FORMAT:
        raise LboError(f"checkpoint {path}: checkpoint format {fmt}, this lbo reads format "
                       f"{CHECKPOINT_FORMAT}; retrain it, or use the lbo version that wrote it")
    mode = hp.get("features")
    check_features(path, mode, features)
    try:
        model = dict(hp["model"])
        # the name is looked up among the installed plug-ins only (nothing the file names is
        # imported); one that is missing says which package provided it
        model_class(model.get("name"), hp.get("provider"))
        net = WindowNet(model.pop("name"), hp["window"], str(mode),
                        fixes=bool(hp.get("fixes", False)),
                        receiver=bool(hp.get("receiver", False)),
                        carried=hp.get("tbptt") is not None, **model)
        state = {k.removeprefix("observer."): v for k, v in ckpt["state_dict"].items()
                 if k.startswith("observer.")}
        net.load_state_dict(state)
    except LboError as e:
        raise LboError(f"checkpoint {path}: {e}") from None
    except (KeyError, TypeError, RuntimeError) as e:
        reason = str(e).strip().splitlines()[0]
        raise LboError(f"checkpoint {path}: its weights do not fit the architecture it "
                       f"names ({reason})") from None
    bad = next((k for k, v in state.items() if torch.is_tensor(v) and v.is_floating_point()
                and not bool(torch.isfinite(v).all())), None)
    if bad is not None:
        raise LboError(f"checkpoint {path}: its weights hold NaN or inf ({bad}: training "
                       "diverged?); retrain it, e.g. with a smaller optimizer.lr")
    net.lateral_error = stored_lateral_error(f"checkpoint {path}", hp.get("meta") or {})
    return net.to(device).eval(), hp


class _Tensor:
    """Stands in for a tensor (or its storage) where :func:`hyperparameters` reads a
    checkpoint without torch: the weights are not read there."""

    def __init__(self, *_: Any) -> None:
        pass


class _Hyperparameters(pickle.Unpickler):
    """Unpickles a checkpoint's ``data.pkl`` building nothing but plain containers: the names
    it may refer to map to :class:`_Tensor` or ``OrderedDict``, and any other raises, so no
    code a file names runs (the same allowance as ``torch.load(weights_only=True)``, less)."""

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("collections", "OrderedDict"):
            return collections.OrderedDict
        if (module == "torch._utils" and name.startswith("_rebuild_")) or (
                module == "torch" and name.endswith("Storage")):
            return _Tensor
        raise pickle.UnpicklingError(f"{module}.{name} is not a plain container")

    def persistent_load(self, pid: Any) -> Any:
        return _Tensor()


def hyperparameters(path: str | os.PathLike) -> dict[str, Any] | None:
    """The hyperparameters stored in an ``lbo.train`` checkpoint (its ``hyper_parameters``,
    with the vehicle, noise and training envelope in ``meta``), read without torch: from the
    zip's pickle of plain containers, tensors left out (:class:`_Hyperparameters`). None
    where the file is not such a checkpoint, or holds anything else;
    :func:`read_checkpoint` then says why in one line."""
    try:
        with zipfile.ZipFile(path) as z:
            pkl = [n for n in z.namelist() if n.endswith("/data.pkl") or n == "data.pkl"]
            if len(pkl) != 1:
                return None
            with z.open(pkl[0]) as f:
                ckpt = _Hyperparameters(f).load()
    except (OSError, zipfile.BadZipFile, pickle.UnpicklingError, EOFError, ValueError,
            TypeError, AttributeError, IndexError, KeyError, MemoryError, RecursionError):
        return None
    hp = ckpt.get("hyper_parameters") if isinstance(ckpt, dict) else None
    return hp if isinstance(hp, dict) else None


def check_features(path: str | os.PathLike, mode: Any, features: str | None) -> None:
    """One line where the feature mode asked for (``features``; None: any) is unknown, or
    where the checkpoint at ``path`` was trained with another ``mode`` (None: not read
    yet)."""
    from lbo.models.features import FEATURE_MODES

    if features is not None and features not in FEATURE_MODES:
        raise LboError(f"features: unknown mode {features!r}; expected one of "
                       f"{', '.join(FEATURE_MODES)}")
    if mode is None:
        return
    if mode not in FEATURE_MODES:
        raise LboError(f"checkpoint {path}: feature mode {mode!r} is unknown to this lbo "
                       f"(it knows {', '.join(FEATURE_MODES)})")
    if features is not None and features != mode:
        raise LboError(f"checkpoint {path}: trained with features={mode}, "
                       f"but features={features} was asked for")


def trained_conditions(hp: Mapping[str, Any], path: str | os.PathLike) -> tuple[Vehicle, Noise]:
    """The vehicle and noise preset a checkpoint was trained with (``hp["meta"]``), for the
    reference filters and the streaming fallback; raises LboError naming the file."""
    meta = hp.get("meta") or {}
    try:
        vehicle = Vehicle(**meta["vehicle"])
    except (KeyError, TypeError) as e:
        raise LboError(f"checkpoint {path}: no usable meta.vehicle ({e})") from None
    except LboError as e:
        raise LboError(f"checkpoint {path}: its stored {e}") from None
    try:
        n = meta["noise"]
        noise = Noise(n["process_sigma"], n["measurement_sigma"], n.get("name", "custom"))
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, LboError):  # a bad value stored in the checkpoint: its fault
            raise LboError(f"checkpoint {path}: its stored {e}") from None
        raise LboError(f"checkpoint {path}: no usable meta.noise ({e})") from None
    return vehicle, noise


def stored_envelope(name: str, meta: dict[str, Any]) -> Envelope | None:
    """The training envelope in a checkpoint's metadata, None for one written before lbo
    stored it; one line naming the observer for a damaged one."""
    stored = meta.get("envelope")
    if stored is None:
        return None
    try:
        return Envelope.from_dict(stored)
    except LboError as e:
        raise LboError(f"observer {name}: its stored {e}") from None


LATERAL_ERROR = "lateral_error"
"""The key of a checkpoint's ``meta`` that holds its single-track body's error on the
validation set, measured as it trained (:class:`lbo.learn.callbacks.LateralError`): per
state ``[v_y, r]`` (a row), the floor (m^2/s^2, rad^2/s^2) and the relative part (1) of its
error's variance, var = floor + part state^2 (:func:`lbo.scoring.lateral.body_error`); absent
for an observer without a body, or trained on data without lateral states."""


def stored_lateral_error(name: str, meta: Mapping[str, Any]) -> np.ndarray | None:
    """The body's error (2, 2) stored in a checkpoint's metadata (:data:`LATERAL_ERROR`), None
    where there is none; one line starting with ``name`` (the checkpoint) for one that is not
    a 2 x 2 matrix of finite, non-negative numbers."""
    stored = meta.get(LATERAL_ERROR)
    if stored is None:
        return None
    try:
        error = np.array(stored, dtype=float)
    except (TypeError, ValueError):
        error = np.full(1, np.nan)
    if error.shape != (2, 2) or not np.isfinite(error).all() or (error < 0).any():
        raise LboError(f"{name}: its stored meta.{LATERAL_ERROR} is not the body's error as "
                       f"a 2 x 2 matrix of finite, non-negative numbers (per state v_y, r: "
                       f"the floor and the relative part of its variance): {stored!r}")
    return error
