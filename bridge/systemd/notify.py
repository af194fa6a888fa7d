"""sd_notify(3) for the daemon, and a watchdog that only pings while the pipeline lives.

The protocol is a few lines, so it lives here instead of in a dependency (the
PyPI packages are unmaintained or schedule their pings on the wall clock, which
steps on boards without a real-time clock): one ``AF_UNIX`` datagram per
message to the socket named by ``$NOTIFY_SOCKET`` (``@name`` is an abstract
socket), holding newline-separated ``KEY=VALUE`` assignments.

Pieces:

* :class:`Notifier` -- sends ``READY=1``, ``STATUS=``, ``WATCHDOG=1``,
  ``STOPPING=1``, ``RELOADING=1`` + ``MONOTONIC_USEC=``; a silent no-op when
  ``$NOTIFY_SOCKET`` is unset (not under systemd), never blocks, never raises.
* :class:`Liveness` -- progress marks ("beats") of the threads the watchdog
  vouches for. Pure: callers pass the time.
  The serial reader beats through
  :class:`bridge.link.observed.ObservedTransport` (every return from a port
  call), which the daemon wires to it.
* :class:`ServiceNotifier` -- one thread: ``READY=1`` once the compass
  streams (or after a bounded wait, with a STATUS saying why not), ``STATUS=``
  about once a second, and ``WATCHDOG=1`` on the monotonic clock only while
  every watched part has beaten recently.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from bridge.types import Clock

log = logging.getLogger(__name__)


#: The datagram limit systemd reads per message is far larger; STATUS is cut here so a
#: runaway status text cannot make a message the manager would truncate mid-assignment.
MAX_STATUS_CHARS = 400


def notify_address(raw: str) -> str | None:
    """The socket address for a ``$NOTIFY_SOCKET`` value, or None if it is not usable.

    ``/path`` is a filesystem socket; ``@name`` an abstract one (the ``@`` stands
    for the leading NUL byte). Other forms (``vsock:``, systemd >= 254) are not
    supported: systemd 252 never hands them out.
    """
    if raw.startswith("/"):
        return raw
    if raw.startswith("@") and len(raw) > 1:
        return "\0" + raw[1:]
    return None


def watchdog_interval_s(
    env: Mapping[str, str] | None = None, pid: int | None = None
) -> float | None:
    """The watchdog timeout systemd asks for (``$WATCHDOG_USEC``), in seconds, or None.

    ``$WATCHDOG_PID``, when set, must be our pid: the variables may have been
    inherited from a parent that was the one being watched.
    """
    env = os.environ if env is None else env
    usec = env.get("WATCHDOG_USEC", "")
    if not usec:
        return None
    wd_pid = env.get("WATCHDOG_PID", "")
    if wd_pid and wd_pid != str(os.getpid() if pid is None else pid):
        return None
    try:
        value = int(usec)
    except ValueError:
        log.warning("sd_notify: ignoring malformed WATCHDOG_USEC=%r", usec)
        return None
    return value / 1e6 if value > 0 else None


def _clean(text: str) -> str:
    # A newline would end the assignment and start a bogus one.
    one_line = " ".join(text.split())
    return one_line[:MAX_STATUS_CHARS]


class Notifier:
    """Sends sd_notify messages to ``address`` (see :func:`notify_address`).

    With ``address=None`` every call is a no-op returning False. Sends use
    ``MSG_DONTWAIT``: a manager that does not drain its socket must not stall
    the daemon; a failed send is counted in ``errors`` (the first one logged).
    """

    def __init__(self, address: str | None) -> None:
        self.address = address
        self.errors = 0
        self.sent = 0
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        if address is not None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> Notifier:
        """A notifier for ``$NOTIFY_SOCKET`` (a no-op one when unset or unusable)."""
        env = os.environ if env is None else env
        raw = env.get("NOTIFY_SOCKET", "")
        if not raw:
            return cls(None)
        address = notify_address(raw)
        if address is None:
            log.warning("sd_notify: unsupported NOTIFY_SOCKET=%r; not notifying", raw)
        return cls(address)

    @property
    def enabled(self) -> bool:
        """Whether messages go anywhere."""
        return self._sock is not None

    def send(self, **fields: Any) -> bool:
        """Send one message of ``KEY=VALUE`` lines (keys as given, e.g. ``READY=1``).

        Returns True when the datagram was sent. STATUS values are folded to
        one line and cut to :data:`MAX_STATUS_CHARS`.
        """
        if self._sock is None or self.address is None:
            return False
        lines = []
        for key, value in fields.items():
            text = _clean(str(value)) if key == "STATUS" else str(value)
            lines.append(f"{key}={text}")
        data = "\n".join(lines).encode("utf-8", "replace")
        with self._lock:
            try:
                self._sock.sendto(data, socket.MSG_DONTWAIT, self.address)
            except OSError as e:
                self.errors += 1
                if self.errors == 1:
                    log.warning("sd_notify: cannot send to %r: %s", self.address, e)
                return False
            self.sent += 1
            return True

    def ready(self, status: str | None = None) -> bool:
        """``READY=1`` (with a STATUS if given)."""
        return self.send(READY=1, STATUS=status) if status is not None else self.send(READY=1)

    def status(self, text: str) -> bool:
        """``STATUS=text``."""
        return self.send(STATUS=text)

    def watchdog(self) -> bool:
        """``WATCHDOG=1``."""
        return self.send(WATCHDOG=1)

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1`` (with a STATUS if given)."""
        return self.send(STOPPING=1, STATUS=status) if status is not None else self.send(STOPPING=1)

    def reloading(self, monotonic_usec: int, status: str | None = None) -> bool:
        """``RELOADING=1`` with ``MONOTONIC_USEC`` (CLOCK_MONOTONIC, as systemd >= 253 wants)."""
        fields: dict[str, Any] = {"RELOADING": 1, "MONOTONIC_USEC": monotonic_usec}
        if status is not None:
            fields["STATUS"] = status
        return self.send(**fields)

    def close(self) -> None:
        """Close the socket (further sends are no-ops)."""
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None


def monotonic_usec() -> int:
    """CLOCK_MONOTONIC in microseconds (what ``MONOTONIC_USEC=`` carries)."""
    return time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000


class Liveness:
    """The last progress mark of each watched part, and which ones went silent.

    Pure bookkeeping: every method takes ``now`` (monotonic seconds) from the
    caller. A part is *silent* when it has not beaten for longer than its
    ``max_silence_s``; pick that above the part's longest legitimate pause
    (a reader backing off between reopen attempts, for instance).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._limit: dict[str, float] = {}
        self._last: dict[str, float] = {}

    def watch(self, name: str, max_silence_s: float, now: float) -> None:
        """Start watching ``name`` (counted as having just beaten)."""
        if not max_silence_s > 0:
            raise ValueError(f"max_silence_s must be positive, got {max_silence_s}")
        with self._lock:
            self._limit[name] = max_silence_s
            self._last[name] = now

    def forget(self, name: str) -> None:
        """Stop watching ``name`` (a part that was stopped on purpose)."""
        with self._lock:
            self._limit.pop(name, None)
            self._last.pop(name, None)

    def beat(self, name: str, now: float) -> None:
        """``name`` made progress at ``now``; unknown names are ignored."""
        # A plain dict store: cheap enough for a reader that beats 20 times a second.
        if name in self._limit:
            self._last[name] = now

    def silent(self, now: float) -> list[tuple[str, float]]:
        """``(name, seconds since its last beat)`` of every part silent for too long."""
        with self._lock:
            return [
                (name, now - self._last[name])
                for name, limit in self._limit.items()
                if now - self._last.get(name, now) > limit
            ]

    @property
    def watched(self) -> tuple[str, ...]:
        """The names being watched."""
        with self._lock:
            return tuple(self._limit)


class ServiceNotifier:
    """The thread that tells the service manager how the daemon is.

    * ``READY=1`` once ``streaming()`` is true, or after ``ready_timeout_s``
      with the STATUS saying why not (a unit must not hang in "activating"
      because the compass is unplugged; the daemon keeps retrying the port);
    * ``STATUS=<status()>`` when it changes, at most every ``status_interval_s``;
    * ``WATCHDOG=1`` every ``watchdog_s / 3`` while ``liveness`` reports no
      silent part (the thread itself being scheduled is part of the proof).

    All pacing uses ``clock`` (monotonic). ``status`` and ``streaming`` are
    called from this thread; they must be quick and not raise (an exception
    is logged and that round is skipped, never fatal).
    """

    def __init__(
        self,
        notifier: Notifier,
        liveness: Liveness,
        *,
        status: Callable[[], str],
        streaming: Callable[[], bool],
        watchdog_s: float | None = None,
        ready_timeout_s: float = 10.0,
        status_interval_s: float = 1.0,
        clock: Clock = time.monotonic,
    ) -> None:
        if watchdog_s is not None and not watchdog_s > 0:
            raise ValueError(f"watchdog_s must be positive, got {watchdog_s}")
        self.notifier = notifier
        self.liveness = liveness
        self._status = status
        self._streaming = streaming
        self.watchdog_s = watchdog_s
        self.ready_timeout_s = ready_timeout_s
        self.status_interval_s = status_interval_s
        self._clock = clock
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._ready_sent = False
        self._reloading = False
        self._stopping = False
        self._started_at = 0.0
        self._last_status = ""
        self._last_status_at = -float("inf")
        self._withheld: tuple[str, ...] = ()
        self.pings = 0
        self.withheld_pings = 0

    @property
    def tick_s(self) -> float:
        """How often the thread looks (also bounds how late READY and pings are)."""
        tick = 0.2
        if self.watchdog_s is not None:
            tick = min(tick, self.watchdog_s / 6)
        return tick

    @property
    def active(self) -> bool:
        """The thread runs: a service manager is told (``$NOTIFY_SOCKET`` is set)."""
        return self._thread is not None

    @property
    def ready_sent(self) -> bool:
        """READY=1 has been sent (and no reload is in progress)."""
        return self._ready_sent and not self._reloading

    def start(self) -> ServiceNotifier:
        """Start the thread; none when there is no manager to tell (``$NOTIFY_SOCKET`` unset).

        Without a manager every READY, STATUS and ping goes nowhere; a thread waking
        five times a second to build status lines for nobody cost the daemon about
        0.1 % of a core (``python -m benchmarks versus``, per-thread figures).
        """
        if self._thread is not None:
            raise RuntimeError("already started")
        self._started_at = self._clock()
        if not self.notifier.enabled:
            return self
        self._thread = threading.Thread(target=self._run, name="sd-notify", daemon=True)
        self._thread.start()
        return self

    def reloading(self) -> None:
        """Tell the manager a reload began; READY=1 waits for :meth:`reloaded`."""
        with self._lock:
            self._reloading = True
            self.notifier.reloading(monotonic_usec(), "reloading configuration")

    def reloaded(self, note: str | None = None) -> None:
        """The reload finished (applied or refused): READY=1 with the current STATUS."""
        with self._lock:
            self._reloading = False
            text = self._safe_status()
            if note:
                text = f"{note}; {text}" if text else note
            self._ready_sent = True
            self.notifier.ready(text)
            self._last_status, self._last_status_at = text, self._clock()

    def stopping(self, status: str = "stopping") -> None:
        """``STOPPING=1``; the thread keeps pinging until :meth:`close`."""
        with self._lock:
            self._stopping = True  # no READY/STATUS after this: they would undo STOPPING
            self.notifier.stopping(status)
            self._last_status, self._last_status_at = status, self._clock()

    def close(self, timeout: float = 1.0) -> None:
        """Stop the thread."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    # ------------------------------------------------------------------ thread

    def _safe_status(self) -> str:
        try:
            return self._status()
        except Exception:
            log.exception("sd_notify: status text failed")
            return ""

    def _run(self) -> None:
        next_ping = self._started_at  # ping at once: WatchdogSec counts from the start
        while not self._stop.is_set():
            now = self._clock()
            with self._lock:
                if not (self._reloading or self._stopping):
                    self._ready_and_status(now)
            if self.watchdog_s is not None and now >= next_ping:
                self._ping(now)
                next_ping = now + self.watchdog_s / 3
            self._wake.wait(self._sleep_s(next_ping))
            self._wake.clear()

    def _sleep_s(self, next_ping: float) -> float:
        """How long the thread sleeps: a tick while READY is still to be sent or a reload
        runs (READY goes out promptly); after that, until the next STATUS look or ping,
        whichever is first -- not a tick: five wake-ups a second cost about 0.1 % of a
        core under a service manager."""
        if not self._ready_sent or self._reloading:
            return self.tick_s
        due = math.inf if self._stopping else self._last_status_at + self.status_interval_s
        if self.watchdog_s is not None:
            due = min(due, next_ping)
        if due == math.inf:  # stopping, no watchdog: nothing more to send until close()
            return self.status_interval_s
        return max(0.0, due - self._clock())

    def _ready_and_status(self, now: float) -> None:
        if not self._ready_sent:
            try:
                up = self._streaming()
            except Exception:
                log.exception("sd_notify: streaming check failed")
                up = False
            waited = now - self._started_at
            if up or waited >= self.ready_timeout_s:
                text = self._safe_status()
                if not up:
                    text = f"started without a streaming compass after {waited:.0f} s; {text}"
                    log.warning("ready without a streaming compass: %s", text)
                self.notifier.ready(text)
                self._ready_sent = True
                self._last_status, self._last_status_at = text, now
                return
        if now - self._last_status_at < self.status_interval_s:
            return
        text = self._safe_status()
        if text and text != self._last_status:
            self.notifier.status(text)
            self._last_status = text
        self._last_status_at = now

    def _ping(self, now: float) -> None:
        silent = self.liveness.silent(now)
        names = tuple(name for name, _ in silent)
        if not silent:
            if self._withheld:
                log.warning("watchdog: %s alive again; pinging", ", ".join(self._withheld))
                self._withheld = ()
            self.notifier.watchdog()
            self.pings += 1
            return
        self.withheld_pings += 1
        if names != self._withheld:
            # Logged once per episode: the manager will restart us if it lasts.
            log.error(
                "watchdog: not pinging, no progress from %s",
                ", ".join(f"{n} for {s:.1f} s" for n, s in silent),
            )
            self._withheld = names
