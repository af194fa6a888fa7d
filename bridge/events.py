"""Operator-visible events (link lost/restored, calibration started/finished, disturbance).

Every front end shows the same events: MAVLink as STATUSTEXT, Zenoh on
``<prefix>/events``, the journal as a log line. Producers call
:meth:`EventBus.emit` from any thread; it never blocks and never raises
because of a subscriber (a failing subscriber is logged once and counted).
"""

from __future__ import annotations

import enum
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger(__name__)


class Severity(enum.IntEnum):
    """MAV_SEVERITY values (RFC 5424 / journald priorities use the same numbers)."""

    EMERGENCY = 0
    ALERT = 1
    CRITICAL = 2
    ERROR = 3
    WARNING = 4
    NOTICE = 5
    INFO = 6
    DEBUG = 7


@dataclass(frozen=True, slots=True)
class Event:
    """One event. ``kind`` is a stable dotted name (``link.lost``, ``calibration.done``, ...);
    ``text`` is the human sentence (short: the MAVLink adapter chunks a long one into
    STATUSTEXT parts of 50 bytes);
    ``data`` holds machine-readable details (JSON-ready values only)."""

    kind: str
    text: str
    severity: Severity = Severity.INFO
    data: dict[str, Any] = field(default_factory=dict)
    t_monotonic: float = field(default_factory=time.monotonic)
    t_unix: float = field(default_factory=time.time)


Subscriber = Callable[[Event], None]


class EventBus:
    """Fan-out of :class:`Event` to subscribers, synchronously and safely.

    Subscribers must be quick and non-blocking (typically: append to their own
    queue). Keeps the last ``history`` events for late joiners (status queries).
    """

    def __init__(self, history: int = 50) -> None:
        self._lock = threading.Lock()
        self._subscribers: list[Subscriber] = []
        self._history: list[Event] = []
        self._history_len = history
        self.subscriber_errors = 0

    def subscribe(self, fn: Subscriber) -> Callable[[], None]:
        """Register ``fn``; returns a function that unsubscribes it."""
        with self._lock:
            self._subscribers.append(fn)

        def unsubscribe() -> None:
            with self._lock:
                if fn in self._subscribers:
                    self._subscribers.remove(fn)

        return unsubscribe

    def emit(self, event: Event) -> None:
        """Deliver ``event`` to every subscriber; log it once."""
        log.log(_LOG_LEVEL[event.severity], "%s: %s", event.kind, event.text)
        with self._lock:
            subs = list(self._subscribers)
            self._history.append(event)
            del self._history[: -self._history_len]
        for fn in subs:
            try:
                fn(event)
            except Exception:  # a broken front end must not break the producer
                self.subscriber_errors += 1
                if self.subscriber_errors == 1:
                    log.exception("event subscriber failed (further failures are only counted)")

    def recent(self) -> list[Event]:
        """The last events, oldest first."""
        with self._lock:
            return list(self._history)


_LOG_LEVEL = {
    Severity.EMERGENCY: logging.CRITICAL,
    Severity.ALERT: logging.CRITICAL,
    Severity.CRITICAL: logging.CRITICAL,
    Severity.ERROR: logging.ERROR,
    Severity.WARNING: logging.WARNING,
    Severity.NOTICE: logging.INFO,
    Severity.INFO: logging.INFO,
    Severity.DEBUG: logging.DEBUG,
}
