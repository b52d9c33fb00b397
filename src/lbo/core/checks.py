"""Small checks that turn a bad config value into one line naming the field and its form."""

from __future__ import annotations

import numbers
from typing import Any

from lbo.core.errors import LboError

SCHEDULES = ("constant", "cosine")
"""The values of ``lr_schedule`` (:class:`lbo.learn.lightning_module.TrainingModule`), here so
that the training config is checked without importing Lightning."""


def require(ok: bool, field: str, form: str, value: Any) -> None:
    """Raise ``LboError("<field> must be <form>, got <value>")`` unless ok."""
    if not ok:
        raise LboError(f"{field} must be {form}, got {value!r}")


def boolean(value: Any, field: str) -> bool:
    """``value`` if it is true or false (not 1, not "yes"), else one line naming ``field``."""
    require(isinstance(value, bool), field, "true or false", value)
    return bool(value)


def one_of(value: Any, choices: tuple[str, ...], field: str) -> str:
    """``value`` if it is one of ``choices``, else one line naming ``field`` and them."""
    require(value in choices, field, f"one of {list(choices)}", value)
    return str(value)


def positive(cfg, key: str, prefix: str, integer: bool = False) -> float:
    """``cfg[key]`` checked by :func:`integer` (an integer >= 1, with ``integer``) or
    :func:`number` (a number > 0) under the field name ``<prefix>.<key>``."""
    if integer:
        return _integer(cfg[key], f"{prefix}.{key}", 1)
    return number(cfg[key], f"{prefix}.{key}", low=0.0, low_open=True)


def integer(value: Any, field: str, minimum: int | None = None, form: str | None = None) -> int:
    """``value`` as an int, or LboError unless it is an integer >= ``minimum``: a Python or
    NumPy int, not a bool (``batch_size=true`` is no batch size) nor a float (``window=20.0``
    would reach the code that slices windows). ``form`` replaces the standard wording,
    ``an integer >= <minimum>``."""
    ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if ok and minimum is not None:
        ok = value >= minimum
    if form is None:
        form = "an integer" if minimum is None else f"an integer >= {minimum}"
    require(ok, field, form, _shown(value))
    return int(value)


_integer = integer  # for positive(), whose argument ``integer`` hides the function


def number(value: Any, field: str, low: float | None = None, high: float | None = None,
           low_open: bool = False, form: str | None = None) -> float:
    """``value`` as a float, or LboError unless it is a finite number (a Python or NumPy
    number, not a bool, not a string) in [low, high] (``(low, high]`` with ``low_open``).
    ``form`` replaces the standard wording, ``a number in [low, high]`` or ``a number > low``."""
    import math

    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value <= high
    if form is None and low is not None and high is not None:
        form = f"a number in {'(' if low_open else '['}{low:g}, {high:g}]"
    elif form is None and low is not None:
        form = f"a number {'>' if low_open else '>='} {low:g}"
    elif form is None:
        form = "a finite number"
    require(ok, field, form, _shown(value))
    return float(value)


def _shown(value: Any) -> Any:
    """A NumPy scalar as the Python number it holds, for the message (its repr would be
    ``np.float64(...)``)."""
    return value.item() if isinstance(value, numbers.Number) and hasattr(value, "item") \
        else value
