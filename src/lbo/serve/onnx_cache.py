"""ONNX exports kept between sessions.

``engine="onnx"`` runs a learned observer in ONNX Runtime, exported in memory when it is
loaded. The dynamo exporter takes about 11 s for the robust observer's recursive step and 3 s
for a CNN, at every load; so each export is kept in lbo's cache folder
(:func:`lbo.core.paths.cache_dir`, ``onnx/``) and read back by the next session of the same
model. A file's name is a digest of everything the export depends on: the module's structure
(its ``repr``, and each submodule's settings: a window's N, a feature mode, a flag) and every
tensor of its state, the form exported, torch's and onnxscript's
versions, the opset and the source of the lbo packages the graph is traced from. A kept
file that ONNX Runtime refuses is exported afresh and replaced; a cache folder that cannot be
written leaves each session to export for itself.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from lbo.core import sources
from lbo.core.atomic import atomic_path
from lbo.core.errors import LboError
from lbo.core.paths import cache_dir

SOURCES = ("models", "filters", "serve", "sim", "core")
"""The lbo packages whose code an exported graph is traced from."""


def key(module: Any, form: str, opset: int) -> str:
    """The digest (24 hex digits) of an export of ``module`` as ``form`` (e.g. ``window``,
    ``recursive``) at ``opset`` (see the module)."""
    import torch

    h = hashlib.sha256()
    for part in (form, str(opset), torch.__version__, version("onnxscript"),
                 sources.source_digest(SOURCES), repr(module)):
        h.update(part.encode() + b"\0")
    for prefix, sub in module.named_modules():
        h.update(f"{prefix}:{type(sub).__module__}.{type(sub).__qualname__}".encode() + b"\0")
        # every setting held beside the weights: a window's N, a feature mode, a flag, a ring's
        # size; each shapes the traced graph, and none is in the state dict
        for name, value in sorted(vars(sub).items()):
            if not name.startswith("_"):
                _update(h, f"{prefix}.{name}", value)
    for name, tensor in [*module.named_parameters(), *module.named_buffers()]:
        _update(h, name, tensor)
    for name, value in module.state_dict().items():  # a plug-in's extra state
        if not isinstance(value, torch.Tensor):
            h.update(f"{name}={value!r}".encode() + b"\0")
    return h.hexdigest()[:24]


def _update(h: Any, name: str, value: Any) -> None:
    """Add one named setting or tensor to the digest ``h``: a tensor or an array by its dtype,
    shape and bytes; a number, string, flag or dataclass (a vehicle) by its repr; anything
    else (a function, a module, already walked) by its type alone, as its repr may hold an
    address that changes from run to run."""
    import torch

    if isinstance(value, torch.Tensor):
        t = value.detach().cpu().contiguous()
        h.update(f"{name}:{t.dtype}:{tuple(t.shape)}".encode() + b"\0")
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    elif isinstance(value, np.ndarray):
        h.update(f"{name}:{value.dtype}:{value.shape}".encode() + b"\0")
        h.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, (bool, int, float, str, bytes, type(None), tuple, list, dict)) or (
            dataclasses.is_dataclass(value) and not isinstance(value, type)):
        h.update(f"{name}={value!r}".encode() + b"\0")
    else:
        h.update(f"{name}:{type(value).__qualname__}".encode() + b"\0")


def version(package: str) -> str:
    """An installed package's version, read without importing it; ``none`` where absent."""
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "none"


def kept(module: Any, form: str, opset: int, export: Callable[[], bytes],
         open_session: Callable[[bytes], Any]) -> tuple[bytes, Any]:
    """``module``'s export as ``form`` and a session of it (``open_session(bytes)``): the kept
    file's where there is one that ONNX Runtime opens, else a new ``export()``'s, which is
    then kept. ``lbo.export`` writes these bytes: an observer already run with
    ``engine=onnx`` exports without tracing again."""
    path = cache_dir() / "onnx" / f"{form}-{key(module, form, opset)}.onnx"
    try:
        model = path.read_bytes()
        return model, open_session(model)
    except Exception:  # noqa: BLE001  # none kept, or damaged (ONNX Runtime's errors share no base)
        pass
    model = export()
    out = open_session(model)
    _keep(path, model)
    return model, out


def _keep(path: Path, model: bytes) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            tmp.write_bytes(model)
    except (OSError, LboError):  # a read-only home: every session exports for itself
        pass
