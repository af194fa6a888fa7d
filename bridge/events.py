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
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

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


class ChangeRefusedError(RuntimeError):
    """A change of the heading's settings was refused by a guard (the message says why and
    what to do); raised by the application's settings writer, caught by whoever asked."""


_T = TypeVar("_T")


class Subscribers(Generic[_T]):
    """The callbacks of one fan-out: added and removed from any thread, called without a lock.

    Copy-on-write: iterating takes the tuple in use with one reference read, so a
    delivery never holds a lock while the callbacks run, and a callback may add or
    remove subscribers (its own included) without disturbing the delivery in flight.
    Every fan-out of the bridge (events, parameter and settings changes, the MAVLink
    message tap) keeps its subscribers in one of these.
    """

    __slots__ = ("_fns", "_lock")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._fns: tuple[Callable[[_T], None], ...] = ()

    def add(self, fn: Callable[[_T], None]) -> Callable[[], None]:
        """Register ``fn``; returns the function that removes this registration."""
        with self._lock:
            self._fns = (*self._fns, fn)
        removed = False

        def remove() -> None:
            nonlocal removed
            with self._lock:
                if removed:  # once: a second call must not take another registration
                    return
                removed = True
                fns = list(self._fns)
                for i, f in enumerate(fns):
                    if f is fn:
                        del fns[i]
                        self._fns = tuple(fns)
                        return

        return remove

    def __iter__(self) -> Iterator[Callable[[_T], None]]:
        return iter(self._fns)  # one reference read: the set as it is now

    def __bool__(self) -> bool:
        return bool(self._fns)

    def __len__(self) -> int:
        return len(self._fns)


class EventBus:
    """Fan-out of :class:`Event` to subscribers, synchronously and safely.

    Subscribers must be quick and non-blocking (typically: append to their own
    queue). Keeps the last ``history`` events for late joiners (status queries).
    """

    def __init__(self, history: int = 50) -> None:
        self._lock = threading.Lock()
        self._subscribers: Subscribers[Event] = Subscribers()
        self._history: list[Event] = []
        self._history_len = history
        self.subscriber_errors = 0

    def subscribe(self, fn: Subscriber) -> Callable[[], None]:
        """Register ``fn``; returns a function that unsubscribes it."""
        return self._subscribers.add(fn)

    def emit(self, event: Event) -> None:
        """Deliver ``event`` to every subscriber; log it once."""
        # rate_key: the log's rate limit counts each kind of event on its own (bridge.logsetup)
        log.log(
            _LOG_LEVEL[event.severity],
            "%s: %s",
            event.kind,
            event.text,
            extra={"rate_key": event.kind},
        )
        with self._lock:
            self._history.append(event)
            del self._history[: -self._history_len]
        for fn in self._subscribers:
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
