"""Progress bars and spinners with an ETA for the long CLI operations.

``calibrate``, ``bench`` and ``record`` take seconds to minutes; a person at
a terminal wants to see that something moves and how long is left. The
renderers (:func:`render_bar`, :func:`render_spinner`) are pure; a
:class:`Progress` writes them to a stream (stderr by default, so stdout stays
clean for the figures and ``--json``), rewriting one line in place with
``\\r`` at most ten times a second. On a stream that is not a terminal it
stays silent (a log or a pipe does not want a hundred ``\\r`` lines), unless
``enabled=True`` asks for it.

A bar can carry a block of ``detail`` lines under it (the live coverage map of
``calibrate --mavlink``); the block is redrawn in place with the ANSI "cursor
up" and "erase line" sequences every terminal emulator understands. Work
that gives no progress of its own (a fit, a recording) gets a spinner that
keeps turning by itself (``tick=True``: a small daemon thread redraws it).
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections.abc import Callable
from typing import TextIO

from bridge.types import ClosedOnExit

SPINNER = "|/-\\"
#: ANSI: cursor up N lines; erase to the end of the line.
_UP = "\x1b[{}A"
_ERASE = "\x1b[K"
#: Minimum time between two redraws (a terminal does not need more than 10 frames/s).
REDRAW_S = 0.1


def format_duration(seconds: float) -> str:
    """``m:ss`` (or ``h:mm:ss``) for an ETA; ``--:--`` when unknown."""
    if not math.isfinite(seconds) or seconds < 0:
        return "--:--"
    s = round(seconds)
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def eta_seconds(done: float, total: float, elapsed: float) -> float:
    """Remaining time at the average rate so far; ``nan`` before any progress."""
    if done <= 0 or elapsed <= 0 or total <= 0:
        return math.nan
    return max(0.0, elapsed * (total - done) / done)


def render_bar(
    label: str, done: float, total: float, elapsed: float, *, width: int = 30, note: str = ""
) -> str:
    """``label [#######.......]  45%  ETA 0:12  note`` (``done`` clamped to ``[0, total]``)."""
    frac = 0.0 if total <= 0 else min(1.0, max(0.0, done / total))
    filled = int(frac * width)
    bar = "#" * filled + "." * (width - filled)
    eta = "done" if frac >= 1.0 else f"ETA {format_duration(eta_seconds(done, total, elapsed))}"
    line = f"{label} [{bar}] {100.0 * frac:3.0f}%  {eta}"
    return f"{line}  {note}" if note else line


def render_spinner(label: str, tick: int, elapsed: float, *, note: str = "") -> str:
    """``label |  0:12  note`` for work of unknown length."""
    line = f"{label} {SPINNER[tick % len(SPINNER)]} {format_duration(elapsed)}"
    return f"{line}  {note}" if note else line


def progress_option(parser: argparse.ArgumentParser, shows: str) -> None:
    """``--progress`` / ``--no-progress``: :class:`Progress`'s ``enabled`` (absent: None,
    on when stderr is a terminal); ``shows`` says what it draws, for the help."""
    parser.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=None,
        help=f"{shows} on stderr (default: when stderr is a terminal)",
    )


class Progress(ClosedOnExit):
    """A live progress line: a bar when ``total`` is known, else a spinner.

    Use as a context manager; call :meth:`update` as often as you like (redraws
    are rate-limited; it may be called from another thread). ``detail`` lines
    are drawn under the bar and redrawn in place. ``tick=True`` starts a daemon
    thread that redraws every :data:`REDRAW_S` so a spinner turns and the ETA
    counts down while the caller is busy in one long call. :meth:`close` ends
    the block so later output starts on a fresh line.
    """

    def __init__(
        self,
        label: str,
        total: float | None = None,
        *,
        stream: TextIO | None = None,
        enabled: bool | None = None,
        clock: Callable[[], float] = time.monotonic,
        tick: bool = False,
    ) -> None:
        self.label = label
        self.total = total
        self._stream = stream if stream is not None else sys.stderr
        self.enabled = self._stream.isatty() if enabled is None else enabled
        self._clock = clock
        self._t0 = clock()
        self._last_draw = -math.inf
        self._tick = 0
        self._width = 0
        self._lines = 0  # lines of the block drawn last time (0: nothing drawn yet)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._closed = False
        self.done = 0.0
        self.note = ""
        self.detail = ""
        self._ticker: threading.Thread | None = None
        if tick and self.enabled:
            self._ticker = threading.Thread(target=self._tick_loop, name="progress", daemon=True)
            self._ticker.start()

    @property
    def elapsed(self) -> float:
        """Seconds since the bar was made."""
        return self._clock() - self._t0

    def line(self) -> str:
        """The line as it would be drawn now."""
        if self.total is None:
            return render_spinner(self.label, self._tick, self.elapsed, note=self.note)
        return render_bar(self.label, self.done, self.total, self.elapsed, note=self.note)

    def update(
        self, done: float | None = None, *, note: str | None = None, detail: str | None = None
    ) -> None:
        """Set progress (an optional short note, lines under the bar) and redraw if it is time."""
        with self._lock:
            if done is not None:
                self.done = done
            if note is not None:
                self.note = note
            if detail is not None:
                self.detail = detail
            now = self._clock()
            if now - self._last_draw >= REDRAW_S and not self._closed:
                self._last_draw = now
                self._tick += 1
                self._draw()

    def _tick_loop(self) -> None:
        while not self._stop.wait(REDRAW_S):
            self.update()

    def _draw(self) -> None:
        if not self.enabled:
            return
        text = self.line()
        if not self.detail and self._lines <= 1:
            # One line: rewrite it with \r and blank out what a longer line left.
            pad = max(0, self._width - len(text))
            self._width = len(text)
            self._lines = 1
            self._stream.write("\r" + text + " " * pad)
        else:
            rows = [text, *self.detail.split("\n")]
            rows += [""] * max(0, self._lines - len(rows))  # erase rows a taller block left
            up = _UP.format(self._lines - 1) if self._lines > 1 else ""
            self._stream.write("\r" + up + "\n".join(r + _ERASE for r in rows))
            self._lines = len(rows)
            self._width = len(rows[-1]) or 1
        self._stream.flush()

    def close(self) -> None:
        """Draw the final state and end the block (idempotent)."""
        self._stop.set()
        if self._ticker is not None and self._ticker is not threading.current_thread():
            self._ticker.join(timeout=1.0)
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._draw()  # stopped early, the bar shows where it stopped
            if self.enabled and (self._width or self._lines):
                self._stream.write("\n")
                self._stream.flush()
            self._width = 0
            self._lines = 0
