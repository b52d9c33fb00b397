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
