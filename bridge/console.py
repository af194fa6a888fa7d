"""The console adapter: a live line of heading, pitch, roll and link health (``run``).

On a terminal the line is rewritten in place, and only while the bridge is the
terminal's foreground job. Started with ``&`` (the README's calibration step) it
says its first lines (the intro, start-up warnings) and then holds everything --
the live line, notes (a calibration saved, a parameter stored), log lines
(:class:`TerminalGate` on stderr) -- until ``fg`` or until it stops, so the
calibrate tool's map and bar in the same terminal are never overwritten.
"""

from __future__ import annotations

import io
import os
import threading
from collections.abc import Callable
from typing import TextIO

from bridge.app.sample import CompassSample, DaemonStatus, LatestSampleWorker
from bridge.protocol.device import LinkState

#: The simulated truth of a sample's heading, in the sample's own reference (None: unknown).
TruthFn = Callable[[CompassSample], float | None]


def format_line(
    sample: CompassSample | None, status: DaemonStatus, truth_deg: float | None = None
) -> str:
    """The console line: heading, pitch, roll, where the heading and its tilt come from
    (accelerometer, autopilot, magnetometer), the simulated truth and how far the heading
    is from it (a simulator only), quality flags, link health."""
    c = status.counters
    health = f"{status.state.value}  frames {c.attitude_frames}"
    health += f"  lost {c.lost_frames}  bad {c.bad_lines_total}"
    if sample is None or status.state is not LinkState.STREAMING:
        what = "waiting for the compass" if sample is None else "no fresh data"
        return f"{what} on {status.port}  [{health}]"
    ref = "mag" if sample.heading_reference == "magnetic" else "true"
    parts = [f"hdg {sample.heading_deg:5.1f} {ref}"]
    if sample.heading_reference == "magnetic" and sample.heading_true_deg is not None:
        parts.append(f"(true {sample.heading_true_deg:5.1f})")
    parts.append(f"pitch {_deg(sample.pitch_deg)}")
    parts.append(f"roll {_deg(sample.roll_deg)}")
    src: str = sample.source
    if sample.device_heading_deg is not None:
        # the compass's own heading is magnetic, whatever the bridge publishes
        src += f", device hdg {sample.device_heading_deg:5.1f} mag"
    parts.append(f"[{src}]")
    parts.append(_tilt(sample))
    if truth_deg is not None:
        off = (sample.heading_deg - truth_deg + 180.0) % 360.0 - 180.0
        off = 0.0 if abs(off) < 0.05 else off  # no "-0.0"
        parts.append(f"[sim truth {truth_deg:5.1f} {ref}, off {off:+5.1f}]")
    flags = []
    if sample.saturated:
        flags.append("SATURATED")
    if sample.attitude is not None:
        a = sample.attitude
        flags += [n for n, on in (("degraded", a.degraded), ("disturbed", a.disturbed)) if on]
        if a.accelerating:
            flags.append("accelerating")
    if flags:
        parts.append(" ".join(flags).upper())
    return "  ".join(parts) + f"  [{health}]"


def _tilt(sample: CompassSample) -> str:
    """Where roll and pitch came from ("tilt accelerometer"), with the heading error that
    tilt leaves when it is not the accelerometer's own."""
    src = sample.tilt_source or "n/a"
    err = sample.heading_sigma_deg
    if src in ("accelerometer", "device") or err is None:
        return f"tilt {src}"
    return f"tilt {src} +-{err:.1f}"


def _deg(v: float | None) -> str:
    return "  n/a" if v is None else f"{v:+6.1f}"


def in_foreground(stream: TextIO) -> bool:
    """Whether this process is the foreground job of the terminal ``stream`` writes to.

    True when that cannot be told (not a terminal, not our controlling terminal).
    """
    try:
        return os.tcgetpgrp(stream.fileno()) == os.getpgrp()
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
        return True


def terminal_columns(stream: TextIO) -> int | None:
    """The width of the terminal ``stream`` writes to (None: unknown)."""
    try:
        return os.get_terminal_size(stream.fileno()).columns or None
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
        return None


class TerminalGate:
    """A terminal stream that holds what is written while the process is in the background.

    Open at first (the start-up lines go out at once); after :meth:`close_in_background`
    a write from a background process is kept (up to ``limit`` characters, then
    counted) and written, in order, by :meth:`release` once the process is the
    terminal's foreground job again, or by :meth:`release_all` when it stops. A
    stand-in for the stream (logging writes to it); anything else is passed through.
    """

    def __init__(
        self,
        stream: TextIO,
        *,
        foreground: Callable[[], bool] | None = None,
        limit: int = 64 * 1024,
    ) -> None:
        self._stream = stream
        self._foreground = foreground or (lambda: in_foreground(stream))
        self._limit = limit
        self._held: list[str] = []
        self._size = 0
        self._dropped = 0
        self._gated = False
        self._lock = threading.RLock()

    def __getattr__(self, attr: str) -> object:
        return getattr(self._stream, attr)

    def close_in_background(self) -> None:
        """From now on, hold writes made while in the background."""
        self._gated = True

    def write(self, text: str) -> int:
        """Write now (foreground, or not gated yet) or hold."""
        with self._lock:
            if not self._gated or self._foreground():
                self._release_locked()
                return self._stream.write(text)
            if self._size + len(text) > self._limit:
                self._dropped += 1
            else:
                self._held.append(text)
                self._size += len(text)
            return len(text)

    def flush(self) -> None:
        """Flush the stream (what is held stays held)."""
        self._stream.flush()

    def release(self) -> None:
        """Write what is held if the process is in the foreground now."""
        with self._lock:
            if (self._held or self._dropped) and (not self._gated or self._foreground()):
                self._release_locked()
                self._stream.flush()

    def release_all(self) -> None:
        """Write what is held, foreground or not (the bridge is stopping)."""
        with self._lock:
            self._release_locked()
            self._stream.flush()

    def _release_locked(self) -> None:
        if self._held:
            self._stream.write("".join(self._held))
            self._held, self._size = [], 0
        if self._dropped:
            self._stream.write(f"({self._dropped} more lines written in the background lost)\n")
            self._dropped = 0


class ConsoleOutput(LatestSampleWorker):
    """A live line of heading/pitch/roll on a text stream (``run --simulate``).

    On a terminal the line is rewritten in place with ``\\r`` ten times a
    second, cut to the terminal's width (a wrapped line cannot be rewritten),
    and only while the process is the terminal's foreground job; otherwise (a
    pipe, a log) one full line per second, so the output stays readable and
    testable. ``truth`` gives a simulated sample's true heading (the line then
    shows how far the heading is from it); :meth:`note` adds a whole line.
    """

    def __init__(
        self,
        status: Callable[[], DaemonStatus],
        stream: TextIO | None = None,
        *,
        tty: bool | None = None,
        interval: float | None = None,
        intro: str = "",
        truth: TruthFn | None = None,
        foreground: Callable[[], bool] | None = None,
        gate: TerminalGate | None = None,
    ) -> None:
        self._stream = stream if stream is not None else sys_stdout()
        self._intro = intro
        self.tty = self._stream.isatty() if tty is None else tty
        super().__init__(
            "console",
            interval if interval is not None else (0.1 if self.tty else 1.0),
            wake_on_publish=False,  # paced by the clock, not by the frame rate
        )
        self._status = status
        self._truth = truth
        self._foreground = foreground or (lambda: in_foreground(self._stream))
        self._width = 0
        self._notes: list[str] = []
        self._notes_lock = threading.Lock()
        self._gate = gate

    def note(self, text: str) -> None:
        """A whole line to print at the next update (from any thread)."""
        with self._notes_lock:
            self._notes.append(text)

    def emit(self, sample: CompassSample | None) -> None:
        """Write the line for the latest sample (after the intro line and notes, if any)."""
        live = not self.tty or self._foreground()
        with self._notes_lock:
            notes = self._notes if live else []  # in the background notes wait for fg
            if live:
                self._notes = []
        if self._intro:
            notes.insert(0, self._intro)  # the first lines go out in any case
            self._intro = ""
        if notes:
            if self._width:  # a live line is drawn: clear it, the notes go above it
                self._stream.write("\r" + " " * self._width + "\r")
                self._width = 0
            self._stream.write("".join(n + "\n" for n in notes))
        if self._gate is not None:
            self._gate.close_in_background()  # the start-up lines are out
            if live:
                self._gate.release()
        if not live:
            self._width = 0  # back in the foreground, the line starts afresh
            self._stream.flush()
            return
        truth = self._truth(sample) if self._truth is not None and sample is not None else None
        line = format_line(sample, self._status(), truth)
        if self.tty:
            cols = terminal_columns(self._stream)
            if cols is not None:
                line = line[: max(20, cols - 1)]
            pad = max(0, self._width - len(line))
            self._width = len(line)
            self._stream.write("\r" + line + " " * pad)
        else:
            self._stream.write(line + "\n")
        self._stream.flush()

    def finish(self) -> None:
        """End the in-place line so the shell prompt starts on a fresh one; say what waited."""
        if self.tty and self._width:
            self._stream.write("\n")
        with self._notes_lock:
            notes, self._notes = self._notes, []
        self._stream.write("".join(n + "\n" for n in notes))
        self._stream.flush()
        if self._gate is not None:
            self._gate.release_all()


def sys_stdout() -> TextIO:
    """The process's stdout (looked up when the output is made, so tests can swap it)."""
    import sys

    return sys.stdout
