"""lbo: learning-based observers for the kinematic bicycle.

The names below are loaded on first use, so ``import lbo`` stays light (no torch)::

    import lbo
    obs = lbo.Observer.load("ekf")          # imports lbo.serve.observer (and its dependencies) now
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

from lbo.core import LAYERS as LAYERS  # the layers, bottom up (its home: lbo.core)

_EXPORTS = {
    "Observer": "lbo.serve.observer",
    "Estimate": "lbo.serve.observer",
    "Estimates": "lbo.serve.observer",
    "Vehicle": "lbo.sim.vehicle",
    "Noise": "lbo.sim.noise",
    "LboError": "lbo.core.errors",
    "LogFormat": "lbo.logs.formats",
    "Measurements": "lbo.sim.measurements",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name == "__version__":  # one home: pyproject.toml, as the installed package records it
        from importlib.metadata import version

        return version("lbo")
    if name in _EXPORTS:
        value = getattr(import_module(_EXPORTS[name]), name)
        globals()[name] = value  # later look-ups skip this function
        return value
    raise AttributeError(f"module 'lbo' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
