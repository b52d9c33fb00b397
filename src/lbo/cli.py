"""What every entry point does with bad input: one line on stderr, exit code 2."""

from __future__ import annotations

import sys
from typing import NoReturn


def fail(err: Exception) -> NoReturn:
    print(f"error: {err}", file=sys.stderr, flush=True)
    sys.exit(2)
