"""``compass-bridge record`` with a live line: elapsed time, bytes so far, ETA.

:func:`bridge.link.recorder.record` is a blocking loop that owns the port and the
signals; it reports nothing while it runs. It flushes every chunk it writes,
so the size of the output file *is* its progress: a small thread watches the
file and drives a :class:`~bridge.tools.progress.Progress` -- a bar with an ETA
when ``--duration`` is given, a spinner otherwise. Nothing in the recorder
changes.
"""

from __future__ import annotations

import os
import threading
from typing import TYPE_CHECKING, TextIO

from bridge.tools.progress import Progress

if TYPE_CHECKING:
    from bridge.link.recorder import RecordSummary

#: How often the watcher looks at the file (s): the bar redraws no faster anyway.
POLL_S = 0.2


def format_bytes(n: int) -> str:
    """``512 B``, ``12.3 kB``, ``4.56 MB`` (decimal units, as ``ls -h --si``)."""
    if n < 1000:
        return f"{n} B"
    if n < 1_000_000:
        return f"{n / 1e3:.1f} kB"
    return f"{n / 1e6:.2f} MB"


def record_with_progress(
    port: str,
    baud: int,
    out_path: str,
    duration: float | None,
    *,
    enabled: bool | None = None,
    stream: TextIO | None = None,
) -> RecordSummary:
    """Run the recorder in this thread (it handles SIGINT/SIGTERM) with a live line."""
    from bridge.link.recorder import record

    stop = threading.Event()
    with Progress("recording", duration, enabled=enabled, stream=stream, tick=True) as bar:

        def watch() -> None:
            while not stop.wait(POLL_S):
                try:
                    size = os.path.getsize(out_path)
                except OSError:  # not created yet (the port is still opening)
                    size = 0
                bar.update(bar.elapsed, note=f"{format_bytes(size)} to {out_path}")

        watcher = threading.Thread(target=watch, name="record-progress", daemon=True)
        if bar.enabled:
            watcher.start()
        try:
            return record(port, baud, out_path, duration)
        finally:
            stop.set()
            if watcher.is_alive():
                watcher.join(timeout=1.0)
            # where it stopped: the duration, or earlier on Ctrl-C / a recording's end
            size = os.path.getsize(out_path) if os.path.exists(out_path) else 0
            bar.update(bar.elapsed, note=f"{format_bytes(size)} to {out_path}")
