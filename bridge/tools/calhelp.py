"""What ``calibrate --mavlink`` says while it works: where it looks, what it found, how far.

A person at a terminal sees the live bar and map (:class:`bridge.tools.progress.Progress`);
piped into a log or a script, the bar is off, and :class:`PlainProgress` writes
a line at every :data:`STEP_PCT` per cent and each text the bridge sends
instead, so a two-minute calibration is never silent. :func:`no_bridge_hint`
says why no bridge answered and what to change -- the default configuration
has no endpoint for the tool. PURE apart from writing to the given stream.
"""

from __future__ import annotations

import re
from typing import Any, TextIO

from bridge.calibration.fits.coverage import N_SECTIONS

#: A line every this many per cent when the bar is off.
STEP_PCT = 20
#: The bridge's own progress STATUSTEXT ("Mag calibration 40%: keep turning it"): the
#: tool's bar or lines already say it.
_PROGRESS_TEXT = re.compile(r"^\w+ calibration \d+%")

#: What the default configuration does with MAVLink (config.MavlinkConfig's default).
DEFAULT_ENDPOINT = "udpout:127.0.0.1:14550"


#: What the operator is asked to do once a bridge answered.
TURN = "turn the compass slowly through every direction (a tumble: over, round, on its side)"


def say(out: TextIO, *lines: str) -> None:
    """Whole lines on ``out``, at once (a pipe or a log sees them as they happen)."""
    out.write("".join(line + "\n" for line in lines))
    out.flush()


def is_progress_text(text: str) -> bool:
    """A STATUSTEXT that only says how far the calibration is."""
    return bool(_PROGRESS_TEXT.match(text))


def looking_line(url: str, system: int, component: int) -> str:
    """Said before anything else: where the tool looks for a bridge."""
    return f"looking for a bridge (system {system}, component {component}) on {url} ..."


def found_line(heartbeat: Any, url: str) -> str:
    """Said when the bridge's HEARTBEAT came: who answered, and that it starts."""
    from pymavlink import mavutil

    names = mavutil.mavlink.enums["MAV_AUTOPILOT"]
    entry = names.get(int(heartbeat.autopilot))
    flavour = entry.name.replace("MAV_AUTOPILOT_", "").lower() if entry is not None else "?"
    return (
        f"bridge found on {url}: system {heartbeat.get_srcSystem()} component "
        f"{heartbeat.get_srcComponent()} (autopilot {flavour}); starting the calibration"
    )


def _peer_endpoint(url: str) -> str | None:
    """The endpoint a bridge needs for the tool's ``url`` (udpout:H:P -> udpin:H:P ...)."""
    kind, _, rest = url.partition(":")
    # pymavlink's kinds: udpout sends, udpin and udp listen, tcp connects, tcpin listens
    mirror = {"udpout": "udpin", "udpin": "udpout", "udp": "udpout", "tcp": "tcpin"}.get(kind)
    mirror = mirror or ("tcp" if kind == "tcpin" else None)
    return f"{mirror}:{rest}" if mirror and rest else None


def no_bridge_hint(url: str) -> str:
    """Why no bridge may have answered on ``url``, and what to change."""
    need = _peer_endpoint(url)
    lines = ["Is a compass bridge running, with a MAVLink endpoint for this tool?"]
    if need is not None:
        lines.append(
            f"The bridge must list {need!r} in mavlink.endpoints; the default configuration "
            f"has only {DEFAULT_ENDPOINT!r} (a ground station's port) and no endpoint for "
            "this tool:"
        )
        lines.append(
            f'  compass-bridge run ... --set \'mavlink.endpoints=["{DEFAULT_ENDPOINT}", "{need}"]\''
        )
    if url != "udpin:127.0.0.1:14550":
        lines.append(
            "With no ground station on this machine, --mavlink udpin:127.0.0.1:14550 "
            "listens where the default configuration sends."
        )
    lines.append("compass-bridge config shows a bridge's endpoints (docs/tools.md, 'calibrate').")
    return "\n".join(lines)


class PlainProgress:
    """Progress as whole lines on ``out`` (the live bar's stand-in when it is off)."""

    def __init__(self, out: TextIO) -> None:
        self._out = out
        self._step = -1
        self._last_text = ""
        self._pct, self._missing = 0.0, N_SECTIONS

    def progress(self, pct: float, missing: int) -> None:
        """A line when ``pct`` reaches a new :data:`STEP_PCT` step (0 % included)."""
        self._pct, self._missing = pct, missing
        step = int(max(0.0, min(100.0, pct)) // STEP_PCT) * STEP_PCT
        if step <= self._step:
            return
        self._step = step
        self._line(step)

    def again(self) -> None:
        """The progress as it is now, though no step was passed (the calibration goes on)."""
        self._line(int(max(0.0, min(100.0, self._pct))))

    def _line(self, pct: int) -> None:
        self._write(
            f"calibrating: {pct}% ({self._missing} of {N_SECTIONS} sphere sections still missing)"
        )

    def text(self, text: str) -> None:
        """A text from the bridge (repeats in a row are said once)."""
        if text != self._last_text and not is_progress_text(text):
            self._last_text = text
            self._write(f"bridge: {text}")

    def _write(self, line: str) -> None:
        say(self._out, line)


__all__ = [
    "TURN",
    "PlainProgress",
    "found_line",
    "is_progress_text",
    "looking_line",
    "no_bridge_hint",
    "say",
]
