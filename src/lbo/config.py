"""Small checks that turn a bad config value into one line naming the field and its form."""

from __future__ import annotations

from typing import Any

from lbo.errors import LboError

SCHEDULES = ("constant", "cosine")
"""The values of ``lr_schedule`` (:class:`lbo.module.ObserverModule`), here so that the
training config is checked without importing Lightning."""


def require(ok: bool, field: str, form: str, value: Any) -> None:
    """Raise ``LboError("<field> must be <form>, got <value>")`` unless ok."""
    if not ok:
        raise LboError(f"{field} must be {form}, got {value!r}")


def positive(cfg, key: str, prefix: str, integer: bool = False) -> float:
    value = cfg[key]
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0
    if integer:
        ok = ok and float(value).is_integer()
    require(ok, f"{prefix}.{key}", "an integer >= 1" if integer else "a number > 0", value)
    return int(value) if integer else float(value)


def integer(value: Any, field: str, minimum: int) -> int:
    """``value`` as an int, or LboError unless it is an integer >= ``minimum`` (a bool is not:
    ``batch_size=true`` is no batch size)."""
    ok = (isinstance(value, int) and not isinstance(value, bool)) or (
        isinstance(value, float) and value.is_integer())
    require(ok and value >= minimum, field, f"an integer >= {minimum}", value)
    return int(value)


def number(value: Any, field: str, low: float | None = None, high: float | None = None,
           low_open: bool = False) -> float:
    """``value`` as a float, or LboError unless it is a finite number (not a bool, not a string)
    in [low, high] (``(low, high]`` with ``low_open``)."""
    import math

    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value <= high
    if low is not None and high is not None:
        form = f"a number in {'(' if low_open else '['}{low:g}, {high:g}]"
    elif low is not None:
        form = f"a number {'>' if low_open else '>='} {low:g}"
    else:
        form = "a finite number"
    require(ok, field, form, value)
    return float(value)
