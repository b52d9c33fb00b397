"""Why an observer refuses a sample, in one line each: the text of the errors that
:class:`lbo.Observer` and ``lbo.observe`` raise, naming the observers that take it."""

from __future__ import annotations

from lbo.filters import classical

_ALSO = ("the robust observer (filternet) in its recursive form, and a CNN, LSTM or window "
         "filter trained on a receiver (experiment=receiver)")
"""The learned observers that take a receiver's channels."""


def no_heading(name: str) -> str:
    """Why a learned observer refuses a position fix without a heading."""
    return (f"a position fix without a heading (psi_m empty), but {name} takes full fixes "
            f"only (x_m, y_m and psi_m); the classical observers "
            f"({', '.join(classical.OBSERVERS)}) take it, {_ALSO}")


def no_receiver(name: str) -> str:
    """Why a learned observer refuses a receiver's channels."""
    return (f"{name} does not take a receiver's channels; the classical observers "
            f"({', '.join(classical.OBSERVERS)}) do, {_ALSO}")


def no_fix(name: str) -> str:
    """Why an observer trained with a fix at every step refuses a step without one."""
    return (f"no fix, but {name} was trained with a fix at every step; use an observer trained "
            "with fix_rates (experiment=robust) or a classical one")


def blind_window(name: str, n: int, dt: float, carries: bool) -> str:
    """Why a net that reads a receiver gives no estimate for a window of ``n`` steps (period
    ``dt`` s) that holds no heading; ``carries``: a window filter, which carries its own
    estimate through a stop and so is blind only on a car that has stood since it began."""
    if carries:
        return (f"no heading in the last {n} steps ({n * dt:g} s), and no estimate before them "
                f"to carry: {name} reads the heading from its window's psi_m or course over "
                "ground, and a car that has stood or crept since it began gave none")
    return (f"no heading in the last {n} steps ({n * dt:g} s): {name} reads the heading from "
            "its window's psi_m or course over ground, and a car that stood or crept that long "
            "gave none (the window filter, model=filternet, carries its own through a stop)")
