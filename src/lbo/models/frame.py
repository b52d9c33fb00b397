"""What a model over the kinematic bicycle in the latest fix's frame holds and checks: the
window filter (:mod:`lbo.models.filternet`) and KalmanNet's peers (:mod:`lbo.models.kalmannet`)
both read their windows so, in metres and radians."""

from __future__ import annotations

import math
from collections.abc import Sequence

from lbo.core.checks import integer, number
from lbo.core.errors import LboError
from lbo.models.motion import ProcessModel
from lbo.models.receiver_window import FEATURES


def check_sigmas(name: str, values: Sequence[float]) -> tuple[float, float, float]:
    """``model.<name>``: three sigmas > 0 for ``[x (m), y (m), psi (rad)]``, checked in one
    line."""
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        out = ()
    if len(out) != 3 or not all(math.isfinite(v) and v > 0 for v in out):
        raise LboError(f"model.{name}: expected three sigmas > 0 for [x (m), y (m), psi (rad)], "
                       f"got {values!r}")
    return out


def frame_model(module: ProcessModel, window: int, in_features: int, dt: float,
                wheelbase: float, receiver: bool = False) -> None:
    """Set what a model over the kinematic bicycle in the latest fix's frame holds (the window
    filter, KalmanNet), each checked in one line: ``physical`` (it reads and writes metres and
    radians, see WindowNet), ``feature_modes``, ``window`` (>= 4), ``in_features`` (5, or 6
    with the fix channel, or with ``receiver`` (a model that can read one) 15, a receiver's
    :data:`lbo.models.receiver_window.FEATURES`), ``fixes`` and ``receiver`` (whether it
    reads them), ``dt`` (s) and ``wheelbase`` (m)."""
    module.physical = True
    module.feature_modes = ("frame",)
    module.window = integer(window, "window", 4)
    module.in_features = integer(in_features, "in_features", 5)
    module.receiver = receiver and module.in_features == len(FEATURES)
    if module.in_features > 6 and not module.receiver:
        raise LboError(f"model.in_features: expected 5, or 6 with the fix channel"
                       f"{f', or {len(FEATURES)} (a receiver)' if receiver else ''}, "
                       f"got {in_features!r}")
    module.fixes = module.in_features == 6 or module.receiver
    module.dt = number(dt, "model.dt", low=0.0, low_open=True, form="a period in seconds > 0")
    module.wheelbase = number(wheelbase, "model.wheelbase", low=0.0, low_open=True,
                              form="a length in metres > 0")
