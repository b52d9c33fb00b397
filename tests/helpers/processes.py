"""Faults injected into the processes a test starts."""

from __future__ import annotations

from pathlib import Path


def kill_when_written(proc, path: Path, times: int = 1, delay: float = 0.0):
    """A started thread that SIGKILLs the process group of ``proc`` once ``path`` has been
    written ``times`` times (e.g. a run's first checkpoint; ``last.ckpt`` once per epoch), and
    ``delay`` seconds more; join it after ``proc`` ends."""
    import os
    import signal
    import threading
    import time

    def watch() -> None:
        seen, stamp = 0, None
        while proc.poll() is None:
            if path.exists() and path.stat().st_mtime_ns != stamp:
                stamp, seen = path.stat().st_mtime_ns, seen + 1
                if seen >= times:
                    time.sleep(delay)
                    os.killpg(proc.pid, signal.SIGKILL)
                    return
            time.sleep(0.005)

    thread = threading.Thread(target=watch)
    thread.start()
    return thread
