"""Read a small settings file (a JSON of a few numbers) safely: a regular file of bounded size.

A path a user gives may name anything: ``/dev/zero`` (read until memory runs out), a FIFO
(``open`` blocks until a writer comes, forever), a folder, a huge file. :func:`read_small`
takes only a regular file, and at most ``cap`` bytes of it, each refusal in one
:class:`~lbo.core.errors.LboError` line.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from lbo.core.errors import LboError

SMALL_CAP = 64 * 1024
"""Default largest size (bytes) of a small settings file: a JSON of a few numbers is a few
hundred bytes."""


def read_small(path: str | Path, what: str, form: str, cap: int = SMALL_CAP) -> bytes:
    """The bytes of the regular file ``path``, at most ``cap`` of them.

    what : how the messages name it (``"gyro noise reports/gyro_noise.json"``).
    form : what is expected there, ending each message (``"a JSON file of GyroNoise"``).

    Raises one :class:`LboError` line where the path does not exist or cannot be read, is not
    a regular file (a device, a FIFO, a folder), or holds more than ``cap`` bytes. The path is
    checked with ``os.stat`` before it is opened, and opened with ``O_NONBLOCK``, so that a
    FIFO put there in between cannot block the open either (its ``fstat`` is then refused)."""
    expected = f"expected {form} (a regular file of at most {cap // 1024} KiB)"
    try:
        # stat first: /dev/zero or a FIFO is refused without being opened (a FIFO's open
        # would block until a writer came)
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise LboError(f"{what}: not a regular file; {expected}")
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as e:
        raise LboError(f"{what}: cannot read it ({e.strerror or e}); {expected}") from None
    with os.fdopen(fd, "rb") as f:  # owns fd from here: closed on every path below
        try:
            # the file may have been replaced between the stat and the open
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise LboError(f"{what}: not a regular file; {expected}")
            data = f.read(cap + 1)  # one byte past the cap tells a larger file, read no more
        except OSError as e:
            raise LboError(f"{what}: cannot read it ({e.strerror or e}); {expected}") from None
    if len(data) > cap:
        raise LboError(f"{what}: larger than {cap // 1024} KiB; {expected}")
    return data
