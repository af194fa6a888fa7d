"""Logging for a long-running service: one line per record, journald priorities, no floods.

* **One line per record.** journald (and most log shippers) split a stream on
  newlines, so a traceback would become twenty unrelated entries. Line breaks
  inside a message or traceback are written as the two characters ``\\n``
  (undo with ``journalctl -u compass-bridge -o cat | sed 's/\\\\n/\\n/g'``).
* **Priorities.** When stderr *is* the journal -- systemd sets
  ``$JOURNAL_STREAM=<dev>:<inode>`` and it matches stderr's ``fstat`` -- each
  line starts with ``<N>``, the syslog priority journald parses
  (``SyslogLevelPrefix=`` defaults to on), and carries no timestamp (the
  journal adds its own). Checking the inode, not just the variable, keeps a
  child whose stderr was redirected elsewhere from writing ``<4>`` into a file.
* **Repeats are rate-limited, per kind.** A record from the same call site
  (logger, level, file, line, message template) *and of the same kind* is let
  through ``burst`` times per ``interval_s``; the rest are counted and
  summarised in one line when the window ends ("... N similar messages
  suppressed"). The kind is the record's ``rate_key`` when the caller gives
  one (``extra={"rate_key": ...}``: the event bus logs every event through one
  call site, so it names the event kind), so a flood of one event does not
  hide another. A port that fails 20 times a second must not flood the journal
  (or its rate limit, which would then drop *other* messages).
"""

from __future__ import annotations

import logging
import os
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TextIO

from bridge.types import Clock

#: Python level -> syslog priority (sd-daemon(3): <2> crit, <3> err, <4> warning, <6> info, <7> debug).
SYSLOG_PRIORITIES = (
    (logging.CRITICAL, 2),
    (logging.ERROR, 3),
    (logging.WARNING, 4),
    (logging.INFO, 6),
)
DEBUG_PRIORITY = 7

DEFAULT_BURST = 5
DEFAULT_INTERVAL_S = 30.0
#: Call sites remembered by the rate limiter; beyond this, expired ones are forgotten first.
MAX_KEYS = 1024


def syslog_priority(levelno: int) -> int:
    """The syslog priority journald should file a record of ``levelno`` under."""
    for threshold, priority in SYSLOG_PRIORITIES:
        if levelno >= threshold:
            return priority
    return DEBUG_PRIORITY


def stream_is_journal(stream: TextIO, env: Mapping[str, str] | None = None) -> bool:
    """Whether ``stream`` is connected to journald (``$JOURNAL_STREAM`` names its dev:inode)."""
    env = os.environ if env is None else env
    value = env.get("JOURNAL_STREAM", "")
    dev, sep, ino = value.partition(":")
    if not sep or not dev.isdigit() or not ino.isdigit():
        return False
    try:
        st = os.fstat(stream.fileno())
    except (OSError, ValueError, AttributeError):
        return False  # no real file descriptor (a StringIO, a closed stream)
    return st.st_dev == int(dev) and st.st_ino == int(ino)


def one_line(text: str) -> str:
    """``text`` with every line break written as ``\\n`` (and trailing space dropped)."""
    return text.rstrip().replace("\r\n", "\n").replace("\r", "\n").replace("\n", "\\n")


@dataclass(slots=True)
class _Window:
    start: float
    count: int
    suppressed: int
    sample: str  # the first suppressed message, for the summary line
    record: logging.LogRecord | None


class RateLimiter:
    """At most ``burst`` records per key per ``interval_s``; the rest counted.

    Pure: the caller passes ``now``. :meth:`admit` answers whether one record
    goes through; :meth:`expired` hands back the windows that ended with
    suppressed records, so their summary can be written.
    """

    def __init__(self, burst: int = DEFAULT_BURST, interval_s: float = DEFAULT_INTERVAL_S) -> None:
        if burst < 1:
            raise ValueError(f"burst must be >= 1, got {burst}")
        if not interval_s > 0:
            raise ValueError(f"interval_s must be positive, got {interval_s}")
        self.burst = burst
        self.interval_s = interval_s
        self._windows: dict[tuple[object, ...], _Window] = {}
        self.suppressed_total = 0

    def admit(
        self,
        key: tuple[object, ...],
        now: float,
        message: str = "",
        record: logging.LogRecord | None = None,
    ) -> bool:
        """Whether a record with ``key`` at ``now`` may be written."""
        w = self._windows.get(key)
        if w is None or now - w.start >= self.interval_s:
            # A new window. (Call expired() first, or an ended window's count is lost.)
            if w is None and len(self._windows) >= MAX_KEYS:
                self._prune(now)
            self._windows[key] = _Window(now, 1, 0, "", None)
            return True
        w.count += 1
        if w.count <= self.burst:
            return True
        if not w.suppressed:
            w.sample, w.record = message, record
        w.suppressed += 1
        self.suppressed_total += 1
        return False

    def expired(self, now: float) -> list[tuple[tuple[object, ...], _Window]]:
        """Windows that ended with suppressed records (removed from the limiter)."""
        done = [
            (k, w)
            for k, w in self._windows.items()
            if w.suppressed and now - w.start >= self.interval_s
        ]
        for k, _ in done:
            del self._windows[k]
        return done

    def pending(self) -> list[tuple[tuple[object, ...], _Window]]:
        """Every window with suppressed records, ended or not (for a final flush); removed."""
        done = [(k, w) for k, w in self._windows.items() if w.suppressed]
        for k, _ in done:
            del self._windows[k]
        return done

    def _prune(self, now: float) -> None:
        for k in [k for k, w in self._windows.items() if now - w.start >= self.interval_s]:
            if not self._windows[k].suppressed:
                del self._windows[k]
        while len(self._windows) >= MAX_KEYS:  # still full: drop the oldest window
            del self._windows[next(iter(self._windows))]


class ServiceFormatter(logging.Formatter):
    """``[<N>][time ]LEVEL logger: message`` on one line (``<N>`` and time per target)."""

    def __init__(self, *, journal: bool) -> None:
        fmt = "%(levelname)s %(name)s: %(message)s"
        if not journal:
            fmt = "%(asctime)s " + fmt
        super().__init__(fmt)
        self.journal = journal

    def format(self, record: logging.LogRecord) -> str:
        """The record as one line."""
        line = one_line(super().format(record))
        if self.journal:
            line = f"<{syslog_priority(record.levelno)}>{line}"
        return line


class ServiceLogHandler(logging.StreamHandler):
    """A stream handler that writes one line per record and rate-limits repeats."""

    def __init__(
        self,
        stream: TextIO | None = None,
        *,
        journal: bool | None = None,
        burst: int = DEFAULT_BURST,
        interval_s: float = DEFAULT_INTERVAL_S,
        clock: Clock = time.monotonic,
        env: Mapping[str, str] | None = None,
    ) -> None:
        stream = sys.stderr if stream is None else stream
        super().__init__(stream)
        self.journal = stream_is_journal(stream, env) if journal is None else journal
        self.setFormatter(ServiceFormatter(journal=self.journal))
        self.limiter = RateLimiter(burst, interval_s)
        self._clock = clock

    def emit(self, record: logging.LogRecord) -> None:
        """Write ``record`` unless its call site is over its rate; summarise ended windows."""
        # Handler.handle() holds self.lock around emit(): the limiter needs no lock of its own.
        try:
            now = self._clock()
            summaries = self.limiter.expired(now)
            key = (
                record.name,
                record.levelno,
                record.pathname,
                record.lineno,
                record.msg,
                getattr(record, "rate_key", None),
            )
            admitted = self.limiter.admit(key, now, record.getMessage(), record)
            for _, w in summaries:
                self._summary(w)
            if admitted:
                super().emit(record)
        except Exception:
            self.handleError(record)

    def _summary(self, w: _Window) -> None:
        base = w.record
        if base is None:
            return
        summary = logging.makeLogRecord(
            {
                "name": base.name,
                "levelno": base.levelno,
                "levelname": base.levelname,
                "pathname": base.pathname,
                "lineno": base.lineno,
                "msg": "%d similar messages suppressed in %.0f s (first: %s)",
                "args": (w.suppressed, self.limiter.interval_s, w.sample),
                "created": time.time(),
            }
        )
        super().emit(summary)

    def flush_suppressed(self) -> None:
        """Write the summaries of every window with suppressed records (at exit)."""
        with self.lock:  # type: ignore[union-attr]
            for _, w in self.limiter.pending():
                self._summary(w)
        self.flush()

    def close(self) -> None:
        """Flush pending summaries, then close."""
        try:
            self.flush_suppressed()
        finally:
            super().close()


def setup_logging(
    level: int | str = logging.WARNING,
    stream: TextIO | None = None,
    *,
    env: Mapping[str, str] | None = None,
    burst: int = DEFAULT_BURST,
    interval_s: float = DEFAULT_INTERVAL_S,
) -> ServiceLogHandler:
    """Replace the root logger's handlers with one :class:`ServiceLogHandler`; returns it."""
    handler = ServiceLogHandler(stream, env=env, burst=burst, interval_s=interval_s)
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
        old.close()
    root.addHandler(handler)
    root.setLevel(level)
    return handler
