"""The systemd adapter's status line: what ``systemctl status`` shows.

The service manager side of the daemon -- ``READY=1``, ``STATUS=``, the
watchdog, ``RELOADING=1`` -- is :mod:`bridge.systemd.notify`; the run loop that
drives it, with SIGHUP reload, is :class:`bridge.daemon.Service`. This module
turns the bridge's status into the one-line ``STATUS=`` text.
"""

from __future__ import annotations

from collections import deque

from bridge.app.sample import CompassSample, DaemonStatus
from bridge.calibration.sessions.snapshot import CalibratorSnapshot
from bridge.protocol.device import LinkState


def calibration_words(
    snap: CalibratorSnapshot, *, calibrated: bool | None, parameters_error: str
) -> str:
    """The status line's calibration: where it came from, running, saved or not.

    ``calibrated`` False: no hard- or soft-iron correction in use; ``parameters_error``:
    why params.json was last refused ("" if it was not). "NOT SAVED (storage error)" only
    when storage refused the calibration in use (it is retried); "saving" while it waits
    only for its pace (COMPASS_* values set a moment ago); nothing for one that was never
    ours to save (the simulator's true calibration, none at all).
    """
    if snap.running:
        return f"running ({snap.mode}, {snap.completion_pct:.0f}%)"
    text = snap.calibration_source
    if snap.calibration_saving:
        text += ", saving"
    elif snap.calibration_save_error:
        text += ", NOT SAVED (storage error)"
    if calibrated is False:
        text += ", UNCALIBRATED"
    if parameters_error:
        text += "; parameters NOT SAVED"
    return text


class StatusText:
    """The one-line ``STATUS=`` shown by ``systemctl status``.

    ``streaming /dev/compass at 10.0 Hz; hdg 123.4 mag (true 126.1); calibration stored``

    Rates come from counter differences over the last ``window_s`` seconds
    (the renderer keeps that history, hence a class).
    """

    def __init__(self, window_s: float = 3.0) -> None:
        self.window_s = window_s
        self._hist: deque[tuple[float, int, int, int]] = deque()

    def _rates(
        self, now: float, frames: int, answers: int, nbytes: int
    ) -> tuple[float | None, int, int, int]:
        """(attitude frame rate, new attitude frames, new other sentences, new bytes)."""
        self._hist.append((now, frames, answers, nbytes))
        while len(self._hist) > 2 and now - self._hist[1][0] >= self.window_s:
            self._hist.popleft()
        t0, f0, a0, b0 = self._hist[0]
        span = now - t0
        rate = (frames - f0) / span if span >= 0.5 else None
        return rate, frames - f0, answers - a0, nbytes - b0

    def render(
        self,
        status: DaemonStatus,
        sample: CompassSample | None,
        calibration: str,
        now: float,
    ) -> str:
        """The STATUS text for this moment."""
        c = status.counters
        # Only attitude frames are a stream (command answers are not: bridge.link).
        frames = c.attitude_frames
        rate, new_frames, new_answers, new_bytes = self._rates(
            now, frames, c.frames - frames, c.bytes_read
        )
        port, state = status.port, status.state
        bad = c.bad_lines_total
        if state is LinkState.STREAMING:
            head = f"streaming {port}"
            if rate is not None:
                head += f" at {rate:.1f} Hz"
            if sample is not None:
                ref = "mag" if sample.heading_reference == "magnetic" else "true"
                head += f"; hdg {sample.heading_deg:.1f} {ref}"
                if sample.heading_reference == "magnetic" and sample.heading_true_deg is not None:
                    head += f" (true {sample.heading_true_deg:.1f})"
        elif new_answers > 0 and new_frames == 0:
            # It answers commands but sends no attitude frame: alive, and not streaming.
            head = (
                f"NOT STREAMING: {port} answers commands but sends no attitude frame "
                f"({new_answers} answers in {self.window_s:g} s); reopening"
            )
        elif new_bytes > 0 and new_frames == 0:
            # Bytes arrive but nothing decodes: the classic wrong-baud / wrong-device case.
            head = (
                f"NO VALID FRAMES from {port}: {new_bytes} bytes in {self.window_s:g} s, "
                f"none decodes ({bad} bad lines): wrong baud rate or wrong device?"
            )
        elif state is LinkState.ABSENT:
            head = f"waiting for {port} (absent)"
        elif state is LinkState.STALE:
            head = f"no attitude frame from {port}; reopening"
        else:
            head = f"opening {port}"
        parts = [head, f"calibration {calibration}"]
        health = [
            f"{n} {what}"
            for n, what in (
                (c.lost_frames, "lost"),
                (bad, "bad"),
                (c.reconnects, "reconnects"),
                (c.device_resets, "resets"),
                (status.pipeline_errors, "pipeline errors"),
            )
            if n
        ]
        if health:
            parts.append(", ".join(health))
        return "; ".join(parts)
