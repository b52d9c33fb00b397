"""Small checks that turn a bad config value into one line naming the field and its form."""

from __future__ import annotations

from typing import Any

from lbo.errors import LboError


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
