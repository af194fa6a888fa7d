"""One pace for every burst the bridge sends: parameter lists, answers, status texts, reports.

A companion bridge is reached *through* its autopilot's MAVLink router, and
routers forward through small buffers. PX4 (v1.16, ``mavlink_main.cpp``) copies
each message for another link into that link's forwarding buffer
(``Mavlink::pass_message``: room for two ``mavlink_message_t``, 583 bytes,
about 14 PARAM_VALUEs; a full buffer drops the message and counts a
"forwarding error") and each link's loop sends *one* forwarded message per
iteration (``task_main``: "We only send one message at a time"; every 4 ms in
SITL). A parameter list sent at once -- one datagram of packets -- overflowed
it: 14 of 38 parameters arrived.

:class:`Pacer` releases the messages of bursts at most :data:`RATE_HZ` per
second after a :data:`BURST` of back-to-back ones (a token bucket shared by all
links: a router forwards every link's messages through the same buffer). A
single answer on an idle pacer leaves at once. The sample and clock streams
(ATTITUDE, HEARTBEAT, the heading feed...) are not paced: their schedule is
their pace. :class:`PacedLink` stands for a link inside the dispatcher, so
every answer it sends -- PARAM_VALUE, COMMAND_ACK, MESSAGE_INTERVAL, FTP -- is
paced without the answering code knowing.

Measured through the real PX4 (``tests/test_companion_px4.py``): docs/mavlink.md.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

from bridge.mavlink.dialect import Message

log = logging.getLogger(__name__)

#: Paced messages per second, sustained: below what PX4's slowest link loop drains
#: (one forwarded message per iteration) with the bridge's own telemetry beside them.
RATE_HZ = 100.0
#: Messages that may leave back to back: a few, well inside PX4's forwarding buffer.
BURST = 4
#: The most messages waiting; beyond it the oldest are dropped (counted).
MAX_QUEUED = 1024

Deliver = Callable[[Message], None]


class Pacer:
    """A token bucket in front of the endpoints for bursts (see the module docstring).

    :meth:`submit` never blocks: it sends at once what the bucket allows and queues
    the rest for the pacer's thread, in order. ``clock`` and ``sleep`` are for tests.
    """

    def __init__(
        self,
        rate_hz: float = RATE_HZ,
        burst: int = BURST,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if rate_hz <= 0.0 or burst < 1:
            raise ValueError("rate_hz must be > 0 and burst >= 1")
        self.period = 1.0 / rate_hz
        self.burst = burst
        self._clock = clock
        self._cond = threading.Condition()
        self._queue: deque[tuple[Deliver, Message]] = deque()
        self._tokens = float(burst)
        self._at = clock()
        self._stop = False
        self._thread: threading.Thread | None = None
        self.sent = 0  #: messages released
        self.dropped = 0  #: messages dropped because the queue was full
        self.max_queued = 0  #: the longest the queue has been

    def start(self) -> None:
        """Start the thread that releases queued messages."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="mavlink-pacer", daemon=True)
            self._thread.start()

    def close(self, timeout: float) -> None:
        """Stop; messages still queued are dropped."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def _refill(self, now: float) -> None:
        self._tokens = min(float(self.burst), self._tokens + (now - self._at) / self.period)
        self._at = now

    def submit(self, deliver: Deliver, messages: Sequence[Message]) -> None:
        """Send ``messages`` through ``deliver``, paced, in order (never blocks)."""
        now_send: list[Message] = []
        with self._cond:
            if not self._queue:
                self._refill(self._clock())
                while len(now_send) < len(messages) and self._tokens >= 1.0:
                    self._tokens -= 1.0
                    now_send.append(messages[len(now_send)])
            rest = messages[len(now_send) :]
            for m in rest:
                if len(self._queue) >= MAX_QUEUED:
                    self._queue.popleft()
                    self.dropped += 1
                self._queue.append((deliver, m))
            if rest:
                self.max_queued = max(self.max_queued, len(self._queue))
                self._cond.notify()
        for m in now_send:
            self._deliver(deliver, m)

    def _deliver(self, deliver: Deliver, m: Message) -> None:
        try:
            deliver(m)
        except Exception:  # a closed link: the message is lost, the pacer goes on
            log.debug("mavlink: paced message not delivered", exc_info=True)
        self.sent += 1

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                now = self._clock()
                self._refill(now)
                if self._tokens < 1.0:
                    wait = (1.0 - self._tokens) * self.period
                    self._cond.wait(wait)
                    continue
                self._tokens -= 1.0
                deliver, m = self._queue.popleft()
            self._deliver(deliver, m)


class PacedLink:
    """A link whose :meth:`send` goes through a :class:`Pacer`; everything else is the
    link's own (``name``, ``address``, ... for whoever reads them)."""

    __slots__ = ("_link", "_pacer")

    def __init__(self, link: Any, pacer: Pacer) -> None:
        self._link = link
        self._pacer = pacer

    @property
    def link(self) -> Any:
        """The link itself."""
        return self._link

    def send(self, packet: Message) -> None:
        """Queue ``packet`` for the link, paced."""
        self._pacer.submit(self._link.send, (packet,))

    def __getattr__(self, name: str) -> Any:
        return getattr(self._link, name)

    def __eq__(self, other: object) -> bool:
        other_link = other.link if isinstance(other, PacedLink) else other
        return bool(self._link == other_link)

    def __hash__(self) -> int:
        return hash(self._link)

    def __repr__(self) -> str:
        return f"<PacedLink {self._link!r}>"
