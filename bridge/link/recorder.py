"""The recorder: tap a compass port into a recording (``compass-bridge record``).

The file format is :mod:`bridge.link.record`; the ports are :mod:`bridge.link.transport`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

from bridge.link.record import RecordingWriter
from bridge.link.transport import EndOfRecording, TransportError, open_transport

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class RecordSummary:
    """What :func:`record` wrote."""

    path: Path
    seconds: float
    records: int
    bytes: int
    port_losses: int


_SYNC_INTERVAL_S = 1.0
_READ_TIMEOUT_S = 0.05
_BACKOFF_INITIAL_S = 0.1
_BACKOFF_MAX_S = 2.0


def record(
    port: str,
    baud: int,
    out_path: str | os.PathLike[str],
    duration: float | None = None,
    *,
    stop: threading.Event | None = None,
    handle_signals: bool = True,
    **options: object,
) -> RecordSummary:
    """Record the raw byte stream of ``port`` into ``out_path`` (``compass-bridge record``).

    Runs until ``duration`` seconds have passed, ``stop`` is set, or (when
    ``handle_signals`` and called from the main thread) SIGINT/SIGTERM arrives.
    ``port`` is anything :func:`bridge.link.transport.open_transport` accepts
    (a device path, ``"sim"``; ``options`` go to it). Nothing is written to the
    device: this is a passive tap. If the port goes away the recorder logs it
    once and reopens it with capped exponential backoff; the gap shows in the
    timestamps. Refuses to overwrite an existing file (FileExistsError).
    """
    stop_event = stop if stop is not None else threading.Event()
    clock = time.monotonic
    transport = open_transport(port, baud, **options)
    restore: list[tuple[signal.Signals, Any]] = []
    if handle_signals and threading.current_thread() is threading.main_thread():

        def _on_signal(signum: int, frame: FrameType | None) -> None:
            stop_event.set()

        for sig in (signal.SIGINT, signal.SIGTERM):
            restore.append((sig, signal.signal(sig, _on_signal)))

    losses = 0
    t0 = clock()
    writer = RecordingWriter(out_path, port, baud, time.time())
    try:
        deadline = None if duration is None else t0 + duration
        is_open = False
        backoff = _BACKOFF_INITIAL_S
        last_sync = t0
        while not stop_event.is_set():
            now = clock()
            if deadline is not None and now >= deadline:
                break
            if not is_open:
                try:
                    transport.open()
                except EndOfRecording:
                    break
                except OSError as e:
                    # OSError covers TransportError and pyserial's SerialException.
                    log.debug("record: cannot open %s: %s", port, e)
                    wait = backoff if deadline is None else min(backoff, max(0.0, deadline - now))
                    stop_event.wait(wait)
                    backoff = min(2 * backoff, _BACKOFF_MAX_S)
                    continue
                if losses:
                    log.info("record: %s is back", port)
                is_open = True
                backoff = _BACKOFF_INITIAL_S
            try:
                data = transport.read(4096, _READ_TIMEOUT_S)
            except EndOfRecording:
                break
            except (TransportError, OSError) as e:
                losses += 1
                log.warning("record: lost %s (%s); reopening", port, e)
                with contextlib.suppress(OSError):
                    transport.close()
                is_open = False
                continue
            now = clock()
            if data:
                writer.write(now - t0, data)
            if now - last_sync >= _SYNC_INTERVAL_S:
                writer.sync()
                last_sync = now
    finally:
        with contextlib.suppress(OSError):
            transport.close()
        writer.close()
        for sig, handler in restore:
            signal.signal(sig, handler)
    return RecordSummary(Path(out_path), clock() - t0, writer.records, writer.bytes, losses)
