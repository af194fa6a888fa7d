"""The console adapter: a live line of heading, pitch, roll and link health (``run``)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import TextIO

from bridge.app.sample import CompassSample, DaemonStatus, LatestSampleWorker
from bridge.ports import LinkState


def format_line(sample: CompassSample | None, status: DaemonStatus) -> str:
    """The console line: heading, pitch, roll, where the heading and its tilt come from
    (accelerometer, autopilot, magnetometer), quality flags, link health."""
    c = status.counters
    health = f"{status.state.value}  frames {c.attitude_frames or c.frames}"
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
        src += f", device hdg {sample.device_heading_deg:5.1f}"
    parts.append(f"[{src}]")
    parts.append(_tilt(sample))
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


class ConsoleOutput(LatestSampleWorker):
    """A live line of heading/pitch/roll on a text stream (``run --simulate``).

    On a terminal the line is rewritten in place with ``\\r`` ten times a
    second; otherwise (a pipe, a log) one full line per second, so the output
    stays readable and testable.
    """

    def __init__(
        self,
        status: Callable[[], DaemonStatus],
        stream: TextIO | None = None,
        *,
        tty: bool | None = None,
        interval: float | None = None,
        intro: str = "",
    ) -> None:
        self._stream = stream if stream is not None else sys.stdout
        self._intro = intro
        self.tty = self._stream.isatty() if tty is None else tty
        super().__init__(
            "console",
            interval if interval is not None else (0.1 if self.tty else 1.0),
            wake_on_publish=False,  # paced by the clock, not by the frame rate
        )
        self._status = status
        self._width = 0

    def emit(self, sample: CompassSample | None) -> None:
        """Write the line for the latest sample (after the intro line, the first time)."""
        if self._intro:
            self._stream.write(self._intro + "\n")
            self._intro = ""
        line = format_line(sample, self._status())
        if self.tty:
            pad = max(0, self._width - len(line))
            self._width = len(line)
            self._stream.write("\r" + line + " " * pad)
        else:
            self._stream.write(line + "\n")
        self._stream.flush()

    def finish(self) -> None:
        """End the in-place line so the shell prompt starts on a fresh one."""
        if self.tty and self._width:
            self._stream.write("\n")
            self._stream.flush()
