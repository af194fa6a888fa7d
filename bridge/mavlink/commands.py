"""Commands and calibration reporting: the pure half of the command protocol.

* :class:`Command` normalises COMMAND_LONG and COMMAND_INT (whose param5/6
  are the int32 ``x``/``y`` and param7 the float ``z``) and says whether it
  is addressed to us;
* :func:`result_code` maps a :class:`~bridge.calibration.sessions.Outcome` to MAV_RESULT;
* :class:`CalibrationRelay` turns the calibration controller's events into
  what each ground-station flow expects:

  - **ArduPilot flow** (MAV_CMD_DO_START_MAG_CAL; Mission Planner, MAVProxy
    ``magcal``, QGroundControl on ArduPilot): MAG_CAL_PROGRESS while running
    (sent from the controller's snapshot by the output), MAG_CAL_REPORT at
    the end, plain STATUSTEXT for the rest;
  - **PX4 flow** (MAV_CMD_PREFLIGHT_CALIBRATION; QGroundControl on PX4): the
    ``[cal]`` STATUSTEXT lines QGroundControl's sensor calibration page parses
    (PX4's ``calibration_messages.h``, calibration protocol version 2)::

        [cal] calibration started: 2 <mag|accel|level>
        [cal] progress <N>
        [cal] <side> orientation detected
        [cal] <side> side done, rotate to a different side
        [cal] calibration done: <mag|accel|level>
        [cal] calibration failed: <reason>
        [cal] calibration cancelled

    ``<side>`` is PX4's name: down, up, left, right, front (nose down), back.
    The angle brackets around N are literal: QGroundControl takes the number
    between ``<`` and ``>``.

Calibrations started elsewhere (zenoh, the CLI) are relayed ArduPilot-style.
The mapping of the calibrator's state, reports and texts is :mod:`bridge.mavlink.calmap`.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from bridge.calibration.sessions import CalibratorSnapshot, Outcome, Result
from bridge.events import Event
from bridge.mavlink import calmap
from bridge.mavlink.dialect import Message
from bridge.mavlink.dialect import mavlink as M  # noqa: N812 - the generated module, short
from bridge.mavlink.telemetry import (
    STATUSTEXT_LEN,
    MagCalReport,
    mag_cal_report,
    statustext,
)

Flow = Literal["ardupilot", "px4"]

# Command ids used here (names as in MAVLink's MAV_CMD).
DO_START_MAG_CAL = int(M.MAV_CMD_DO_START_MAG_CAL)
DO_ACCEPT_MAG_CAL = int(M.MAV_CMD_DO_ACCEPT_MAG_CAL)
DO_CANCEL_MAG_CAL = int(M.MAV_CMD_DO_CANCEL_MAG_CAL)
FIXED_MAG_CAL_YAW = int(M.MAV_CMD_FIXED_MAG_CAL_YAW)
PREFLIGHT_CALIBRATION = int(M.MAV_CMD_PREFLIGHT_CALIBRATION)
PREFLIGHT_STORAGE = int(M.MAV_CMD_PREFLIGHT_STORAGE)
SET_MESSAGE_INTERVAL = int(M.MAV_CMD_SET_MESSAGE_INTERVAL)
GET_MESSAGE_INTERVAL = int(M.MAV_CMD_GET_MESSAGE_INTERVAL)
REQUEST_MESSAGE = int(M.MAV_CMD_REQUEST_MESSAGE)
REQUEST_AUTOPILOT_CAPABILITIES = int(M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES)

ACCEPTED = int(M.MAV_RESULT_ACCEPTED)
TEMPORARILY_REJECTED = int(M.MAV_RESULT_TEMPORARILY_REJECTED)
DENIED = int(M.MAV_RESULT_DENIED)
UNSUPPORTED = int(M.MAV_RESULT_UNSUPPORTED)
FAILED = int(M.MAV_RESULT_FAILED)
IN_PROGRESS = int(M.MAV_RESULT_IN_PROGRESS)

RESULT_NAMES = {
    ACCEPTED: "ACCEPTED",
    TEMPORARILY_REJECTED: "TEMPORARILY_REJECTED",
    DENIED: "DENIED",
    UNSUPPORTED: "UNSUPPORTED",
    FAILED: "FAILED",
    IN_PROGRESS: "IN_PROGRESS",
}


@dataclass(frozen=True, slots=True)
class Command:
    """A COMMAND_LONG or COMMAND_INT, with params 1..7 as numbers."""

    command: int
    params: tuple[float, float, float, float, float, float, float]
    target_system: int
    target_component: int
    source_system: int
    source_component: int
    is_int: bool = False

    def p(self, i: int) -> float:
        """Parameter ``i`` (1..7)."""
        return self.params[i - 1]

    def addressed_to(self, system_id: int, component_id: int) -> bool:
        """For our system (or all) and our component (or all)."""
        return self.target_system in (0, system_id) and self.target_component in (0, component_id)

    @property
    def broadcast(self) -> bool:
        """Sent to every component (target_component 0)."""
        return self.target_component == 0


def command_from_message(msg: Any) -> Command:
    """A :class:`Command` from a received COMMAND_LONG or COMMAND_INT."""
    is_int = msg.get_type() == "COMMAND_INT"
    # COMMAND_INT: x and y (int32) take the places of param5 and param6, z of param7.
    p5, p6, p7 = (msg.x, msg.y, msg.z) if is_int else (msg.param5, msg.param6, msg.param7)
    params = (
        float(msg.param1),
        float(msg.param2),
        float(msg.param3),
        float(msg.param4),
        float(p5),
        float(p6),
        float(p7),
    )
    return Command(
        command=int(msg.command),
        params=params,
        target_system=int(msg.target_system),
        target_component=int(msg.target_component),
        source_system=int(msg.get_srcSystem()),
        source_component=int(msg.get_srcComponent()),
        is_int=is_int,
    )


def whole(v: float) -> int | None:
    """``v`` as an int when it is a whole finite number (command params are floats)."""
    if not math.isfinite(v) or v != math.floor(v):
        return None
    return int(v)


def result_code(outcome: Outcome, *, in_progress_is_final: bool = True) -> int:
    """MAV_RESULT for a controller outcome.

    A calibration *started* (IN_PROGRESS) is answered ACCEPTED, as ArduPilot and
    PX4 do -- its progress travels as MAG_CAL_PROGRESS / STATUSTEXT -- unless
    ``in_progress_is_final`` is False (the caller then sends IN_PROGRESS and a
    final ack later). "Not now" (DENIED) is TEMPORARILY_REJECTED.
    """
    if outcome.result is Result.ACCEPTED:
        return ACCEPTED
    if outcome.result is Result.IN_PROGRESS:
        return ACCEPTED if in_progress_is_final else IN_PROGRESS
    if outcome.result is Result.DENIED:
        return TEMPORARILY_REJECTED
    return FAILED


# ---------------------------------------------------------------------------- calibration events


#: MAG_CAL_PROGRESS while a magnetometer calibration runs, every this many seconds.
PROGRESS_PERIOD_S = 0.5
#: MAG_CAL_REPORT repeated while a result waits for accept (ArduPilot), every this many seconds.
REPORT_PERIOD_S = 1.0
#: Outside the PX4 flow, a progress STATUSTEXT at least this often while a magnetometer
#: calibration runs, even when it does not move on (a unit turned level only: never silent).
PROGRESS_TEXT_REMIND_S = 15.0
#: The compass's own MAGCAL is in its flash when reported -- nothing to accept or cancel: its
#: MAG_CAL_REPORT goes out this many times in all (one lost datagram is no loss), not forever.
ONBOARD_REPORTS = 3
#: Event STATUSTEXTs (progress lines aside) are paced by a token bucket: a burst of this many,
#: then this many a second -- a flood of commands (start, cancel, start ...) or of failing
#: saves must not become a flood to every ground station; a calibration's own lines fit.
TEXT_BURST = 30
TEXT_RATE_HZ = 2.0


class CalibrationRelay:
    """Calibration events -> MAVLink packets, in the style of the flow that started them.

    :meth:`begin` is called *before* the controller is asked to start (the
    ``started`` event is emitted from inside the start call); the flow ends
    with the session (done, failed, cancelled). Thread-safe: events arrive on
    the controller's threads.

    :meth:`keepalive` (the output's telemetry thread) sends MAG_CAL_PROGRESS
    while a magnetometer calibration runs, and repeats a result's
    MAG_CAL_REPORT about once a second, as ArduPilot does, until a
    DO_ACCEPT_MAG_CAL or DO_CANCEL_MAG_CAL answers it (:meth:`answered`) or
    another calibration starts: one lost datagram must not leave a ground
    station waiting (QGroundControl waits for the report and never accepts,
    MAVProxy accepts on every report). The PX4 flow has no report to wait for,
    and the compass's own MAGCAL (saved in its flash) none to accept: its report
    goes out :data:`ONBOARD_REPORTS` times. Event STATUSTEXTs other than progress go
    through a token bucket (:data:`TEXT_BURST`, :data:`TEXT_RATE_HZ`); the rest are
    counted in :attr:`throttled`.
    """

    def __init__(self, compass_id: int = 0, clock: Callable[[], float] = time.monotonic) -> None:
        self.compass_id = compass_id  #: the compass id of our MAG_CAL_REPORT
        self._clock = clock
        self._lock = threading.Lock()
        self._flow: Flow | None = None
        self._last_pct: int | None = None
        self._last_step = 0  # the last progress step said in a STATUSTEXT (ArduPilot flow)
        self._text_at = clock()  # when a progress text last went out (or the flow began)
        self.last_report: MagCalReport | None = None
        self._repeat: Message | None = None  # the MAG_CAL_REPORT repeated until answered
        self._repeat_left: int | None = None  # repeats still to go (None: until answered)
        self._repeat_at = -math.inf
        self._progress_at = -math.inf
        # Whether keepalive() may have something to say: from the start (a calibration may
        # be running already: a reloaded output) and from any calibration event or hurry()
        # until a look finds no magnetometer calibration running and no report to repeat.
        # Idle, keepalive_due is +inf and the telemetry thread does not wake for it.
        self._active = True
        self._activations = 0  # counts _activate(): a look that began before one keeps it
        #: Told (any thread) when :attr:`keepalive_due` comes back from +inf (the telemetry
        #: thread, asleep until its next stream, wakes for it).
        self.on_due: Callable[[], None] | None = None
        self._tokens = float(TEXT_BURST)
        self._tokens_at = clock()
        self.throttled = 0  #: event STATUSTEXTs not sent (over the bucket's rate)

    # -- the keep-alive -------------------------------------------------------------

    @property
    def keepalive_due(self) -> float:
        """When :meth:`keepalive` next may have something to say (clock seconds; +inf while
        no calibration runs and no report waits for an answer)."""
        return self._progress_at + PROGRESS_PERIOD_S if self._active else math.inf

    def _activate(self) -> None:
        with self._lock:
            self._activations += 1
            woke, self._active = not self._active, True
        if woke and self.on_due is not None:
            self.on_due()

    def keepalive(self, now: float, snapshot: Callable[[], CalibratorSnapshot]) -> list[Message]:
        """MAG_CAL_PROGRESS while a magnetometer calibration runs; else the MAG_CAL_REPORT
        waiting for an answer, about once a second."""
        if not self._active or now - self._progress_at < PROGRESS_PERIOD_S:
            return []  # asleep; else the controller is asked twice a second, not every frame
        self._progress_at = now
        with self._lock:
            activations = self._activations  # before the snapshot: see the idle case below
        snap = snapshot()
        if snap.running and snap.mode in ("mag", "onboard_mag"):
            out = [calmap.progress_message(snap, self.compass_id)]
            with self._lock:
                remind = self._flow != "px4" and now - self._text_at >= PROGRESS_TEXT_REMIND_S
                if remind:
                    self._text_at = now
            if remind:
                text = calmap.progress_text({"sensor": "mag"}, int(snap.completion_pct))
                out += statustext(int(M.MAV_SEVERITY_INFO), text)
            return out
        with self._lock:
            report = self._repeat
            if report is None and activations == self._activations:
                # Nothing runs, nothing waits: idle until an event or hurry() (one that
                # came while the snapshot was taken keeps it looking).
                self._active = False
            if report is None or now - self._repeat_at < REPORT_PERIOD_S:
                return []
            self._repeat_at = now
            if self._repeat_left is not None:
                self._repeat_left -= 1
                if self._repeat_left <= 0:
                    self._repeat = None
        return [report]

    def hurry(self) -> None:
        """A calibration command was handled: progress (or the report) at the next look."""
        self._progress_at = self._repeat_at = -math.inf
        self._activate()

    def answered(self) -> None:
        """DO_ACCEPT_MAG_CAL or DO_CANCEL_MAG_CAL for our compass: stop repeating the report."""
        with self._lock:
            self._repeat = None

    # -- events ---------------------------------------------------------------------

    def _progress_text(self, event: Event) -> list[Message]:
        """A STATUSTEXT when a progress event passes a new step (20 %, 40 % ...; not 100 %,
        which the result says), once per step and attempt; :meth:`keepalive` repeats the
        figure when no step is passed for :data:`PROGRESS_TEXT_REMIND_S`."""
        step = calmap.progress_step(event.data)
        with self._lock:
            if step is None or not 0 < step < 100 or step <= self._last_step:
                if step is not None and step < self._last_step:
                    self._last_step = step  # a retry started over
                return []
            self._last_step = step
            self._text_at = self._clock()
        return statustext(int(event.severity), calmap.progress_text(event.data, step))

    @property
    def flow(self) -> Flow | None:
        """The flow of the calibration in progress (None: none, or started elsewhere)."""
        with self._lock:
            return self._flow

    def begin(self, flow: Flow | None) -> None:
        """A calibration is about to be started by ``flow``."""
        with self._lock:
            self._flow = flow
            self._last_pct = None
            self._last_step = 0
            self._text_at = self._clock()

    def _text(self, event: Event, text: str | None = None) -> list[Message]:
        """``event``'s STATUSTEXT (``text``: another line for it) if the bucket allows one
        (progress lines always: they go out once per percent anyway)."""
        if event.kind != "calibration.progress":
            now = self._clock()
            with self._lock:
                elapsed = max(0.0, now - self._tokens_at)
                self._tokens = min(float(TEXT_BURST), self._tokens + elapsed * TEXT_RATE_HZ)
                self._tokens_at = now
                if self._tokens < 1.0:
                    self.throttled += 1
                    return []
                self._tokens -= 1.0
        if text is not None:
            return statustext(int(event.severity), text)
        return statustext(int(event.severity), event.text, chunk_id=_chunk_id(event))

    def packets(self, event: Event) -> list[Message]:
        """What to broadcast for ``event`` (any kind; non-calibration events become STATUSTEXT)."""
        if not event.kind.startswith("calibration."):
            return self._text(event)
        self._activate()  # a calibration started, ended or moved on: keepalive looks again
        if (
            event.kind == "calibration.accepted"
            and event.data.get("source") == "parameters"
            and (event.data.get("saved") or event.data.get("paced"))
        ):
            return []  # a PARAM_SET of COMPASS_*: its PARAM_VALUE echo says enough
        with self._lock:
            flow = self._flow
            if event.kind in ("calibration.started", "calibration.cancelled"):
                self._repeat = None
                self._last_step = 0
                self._text_at = self._clock()
            if event.kind in ("calibration.done", "calibration.failed", "calibration.cancelled"):
                self._flow = None
            if event.kind == "calibration.progress":
                pct = event.data.get("completion_pct")
                ipct = int(pct) if isinstance(pct, int | float) and math.isfinite(pct) else None
                if ipct is not None and ipct == self._last_pct:
                    return []  # QGroundControl needs changes only
                self._last_pct = ipct
        out: list[Message] = []
        if event.kind in ("calibration.done", "calibration.failed"):
            r = calmap.event_report(event.data)
            if r is not None:
                self.last_report = r
                out.append(mag_cal_report(r, self.compass_id))
                if flow != "px4":
                    with self._lock:
                        self._repeat, self._repeat_at = out[-1], self._clock()
                        saved = bool(event.data.get("onboard") and event.data.get("autosaved"))
                        self._repeat_left = ONBOARD_REPORTS - 1 if saved else None
        # The calibrator's texts are whole sentences: they go out chunked when longer than
        # one STATUSTEXT ("Calibration failed: MAGCAL,END: too little rotation (RANGE)").
        if flow == "px4":
            line = calmap.px4_text(event)
            if line is not None:
                text = self._text(event, line)
                out += text
                cut = len(line.encode()) >= STATUSTEXT_LEN
                if text and cut and event.kind == "calibration.failed":
                    # the [cal] line had to be cut: the whole reason follows for the log
                    out += statustext(int(event.severity), event.text, chunk_id=_chunk_id(event))
            return out
        if event.kind == "calibration.progress":
            # ArduPilot flow: MAG_CAL_PROGRESS carries it, which MAVProxy's console does
            # not show: a line every PROGRESS_TEXT_STEP per cent says it is working.
            return out + self._progress_text(event)
        return out + self._text(event)


def _chunk_id(event: Event) -> int:
    # Any non-zero id that differs between consecutive long texts will do.
    return (int(event.t_monotonic * 1000) & 0xFFFF) or 1
