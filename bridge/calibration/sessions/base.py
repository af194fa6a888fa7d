"""Calibration sessions: one small pure state machine per mode -- frames and ticks in, actions out.

A session does no I/O: no thread, no clock (time comes in as ``now``), no
device, no store. Each call returns the :data:`Action` list the runner
(:class:`~bridge.app.calibration.controller.CalibrationController`) carries out:

* :class:`Emit` -- an event for the bus (plain sentences; front ends cut or
  chunk them for their wire);
* :class:`Compute` -- a fit to run in the worker; its value comes back through
  :meth:`Session.resolve` (an exception through :meth:`Session.crashed`);
* :class:`Device` -- a device command to run in the worker; its answer (or the
  :class:`~bridge.protocol.device.CommandError`) comes back through :meth:`Session.resolve`;
* :class:`Apply` -- a calibration to use from now on (engine, store, flash).

The calls: :meth:`Session.begin` once, :meth:`Session.feed` for every frame,
:meth:`Session.tick` every 0.1 s while it runs, :meth:`Session.accept` /
:meth:`Session.cancel` for the commands, :meth:`Session.shutdown` when the
bridge stops. Results of jobs the session no longer waits for (cancelled,
failed, replaced) are ignored by the session itself.

The base class holds what every mode shares: the :class:`~bridge.calibration.sessions.state.Phase`,
the progress events (rate-limited), the time-outs (ArduPilot's: no data for
``no_data_timeout_s`` or the whole session over ``timeout_s`` fails it, a
time-out is final even with retry), success and failure.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple

from bridge.calibration.sessions.report import Failure, SessionReport, failure_report
from bridge.calibration.sessions.state import CalibratorSettings, Mode, Outcome, Phase, Result
from bridge.core.calibration import Calibration
from bridge.core.wmm import EarthField
from bridge.events import Severity
from bridge.types import Vec3

NO_MASK = bytes(10)

#: Every event kind the calibrator emits (sessions, and the controller applying results).
EVENT_KINDS: tuple[str, ...] = (
    "calibration.started",
    "calibration.progress",
    "calibration.instruction",
    "calibration.face_detected",
    "calibration.face_done",
    "calibration.done",
    "calibration.failed",
    "calibration.cancelled",
    "calibration.accepted",
    "calibration.saved",
    "calibration.storage_error",
    "calibration.device_updated",
    "calibration.device_error",
    "calibration.motion",
)


@dataclass(frozen=True, slots=True)
class Emit:
    """An event to emit (``data`` JSON-ready)."""

    kind: str
    text: str
    severity: Severity = Severity.INFO
    data: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class FitContext:
    """What a fit may need of the running bridge, read when the fit runs."""

    calibration: Calibration  #: the calibration in use
    field: EarthField | None  #: the local Earth field (None: unknown)


@dataclass(frozen=True, slots=True, eq=False)
class Compute:
    """A fit to run in the worker: ``fn(context)``; the value goes back to the session."""

    what: str
    fn: Callable[[FitContext], Any]


@dataclass(frozen=True, slots=True, eq=False)
class Device:
    """A device command to run in the worker; the answer or the error goes back to the session."""

    command: str
    args: tuple[str, ...] = ()
    retries: int = 2
    purpose: str = ""  #: the session's name for it ("start", "end", "abort" ...)


@dataclass(frozen=True, slots=True)
class Apply:
    """A calibration to use from now on: engine, calibration store, optionally the flash."""

    calibration: Calibration
    source: str
    report: SessionReport | None
    write_device: bool


Action = Emit | Compute | Device | Apply


def device_error(message: str) -> Emit:
    """``calibration.device_error``: the compass refused or did not answer a command."""
    return Emit(
        "calibration.device_error",
        f"Compass flash: {message}",
        Severity.WARNING,
        {"error": message},
    )


Job = Compute | Device


class Progress(NamedTuple):
    """How far a session is: percent (0-100), sphere coverage, where to turn, device spans,
    faces done.

    A named tuple rather than a frozen dataclass: a collecting session makes two a frame
    (its progress event's check, the status snapshot), and a frozen dataclass's
    ``__init__`` sets each field through ``object.__setattr__`` at three times the cost.
    """

    percent: float
    mask: bytes = NO_MASK
    direction: Vec3 = (0.0, 0.0, 0.0)
    spans: tuple[int, int, int] | None = None
    faces_done: tuple[str, ...] | None = None


class Session:
    """The part every mode shares (see the module docstring); subclasses add the routine."""

    mode: ClassVar[Mode]

    def __init__(self, settings: CalibratorSettings, now: float, *, autosave: bool = False):
        self.settings = settings
        self.phase = Phase.WAITING
        self.step = 1
        self.attempt = 1
        self.autosave = autosave
        self.started_at = now
        self.start_at = now
        self.last_frame_at: float | None = None
        self.report: SessionReport | None = None
        self.accepted = False  #: the result is in use (accepted, or saved without an accept)
        self.pending: Job | None = None  #: the job the session waits for
        self._progress_at = -math.inf
        self._progress_key: tuple[Any, ...] = ()

    # -- state -----------------------------------------------------------------------

    @property
    def running(self) -> bool:
        """Waiting, collecting or fitting."""
        return self.phase.running

    @property
    def busy(self) -> bool:
        """A job of this session is queued or running."""
        return self.pending is not None

    @property
    def pending_accept(self) -> bool:
        """A result waits for accept (only a host magnetometer fit does)."""
        return False

    def progress(self, *, hint: bool = True) -> Progress:
        """How far it is (``hint=False``: skip the costlier direction hint, per frame)."""
        if not self.running:  # (asked first: a running session is asked twice a frame)
            return self._progress(hint, 100.0 if self.phase is Phase.SUCCEEDED else 0.0)
        p = self._progress(hint, None)
        return (
            p if p.percent <= 99.0 else Progress(99.0, p.mask, p.direction, p.spans, p.faces_done)
        )

    def _progress(self, hint: bool, percent: float | None) -> Progress:
        """The mode's progress; ``percent`` overrides its figure when not None."""
        return Progress(0.0 if percent is None else percent)

    # -- the runner's calls ------------------------------------------------------------

    def begin(self, now: float) -> list[Action]:
        """The session starts (the ``started`` event, and whatever the mode does first)."""
        raise NotImplementedError

    def feed(self, frame: object, now: float) -> list[Action]:
        """One received frame (an attitude frame, a ``$PGMRC`` report ...)."""
        return []

    def tick(self, now: float) -> list[Action]:
        """Time-outs and delayed starts (every 0.1 s while running)."""
        if not self.running:
            return []
        if self.phase is Phase.WAITING:
            return self._tick_waiting(now)
        st = self.settings
        if self.last_frame_at is not None and now - self.last_frame_at > st.no_data_timeout_s:
            return self._timeout(f"no data from the compass for {st.no_data_timeout_s:g} s", now)
        if now - self.started_at > st.timeout_s and not self.busy:
            pct = self.progress(hint=False).percent
            return self._timeout(f"timed out after {st.timeout_s:g} s at {pct:.0f}%", now)
        return []

    def resolve(self, job: Job, value: Any, now: float) -> list[Action]:
        """A job's value: a fit's result, a device answer or its ``CommandError``."""
        if job is not self.pending or not self.running:
            return self._late(job, value)
        self.pending = None
        return self._resolved(job, value, now)

    def crashed(self, job: Job, error: Exception, now: float) -> list[Action]:
        """A job raised: the session fails rather than hangs (the device told to stop)."""
        if job is not self.pending or not self.running:
            return []
        self.pending = None
        aborts: list[Action] = list(self._abort())
        return [*self.fail(f"internal error: {error}", retry_ok=False, now=now), *aborts]

    def accept(self) -> tuple[Outcome, list[Action]]:
        """MAV_CMD_DO_ACCEPT_MAG_CAL: with nothing to accept ACCEPTED (as ArduPilot)."""
        if self.phase is Phase.CANCELLED:
            return Outcome(Result.ACCEPTED, "no calibration to accept"), []
        if self.running:
            return Outcome(Result.DENIED, "calibration still running"), []
        if self.phase is Phase.FAILED:
            why = self.report.reason if self.report is not None else ""
            return Outcome(Result.FAILED, f"last calibration failed ({why})"), []
        return Outcome(Result.ACCEPTED, "already accepted"), []

    def cancel(self) -> list[Action] | None:
        """Stop it (None: nothing to cancel). A result not yet accepted is discarded."""
        if not (self.running or self.pending_accept):
            return None
        out: list[Action] = list(self._abort())
        self.phase = Phase.CANCELLED
        self.pending = None
        notice = Emit(
            "calibration.cancelled",
            "Calibration cancelled",
            Severity.NOTICE,
            {"mode": self.mode.value, "sensor": self.mode.sensor},
        )
        return [notice, *out]

    def shutdown(self) -> list[Device]:
        """The bridge stops: the session ends quietly; what to tell the device (run at once)."""
        if not self.running:
            return []
        out = self._abort()
        self.phase = Phase.CANCELLED
        self.pending = None
        return out

    # -- hooks -------------------------------------------------------------------------

    def _tick_waiting(self, now: float) -> list[Action]:
        return []

    def _resolved(self, job: Job, value: Any, now: float) -> list[Action]:
        return []

    def _late(self, job: Job, value: Any) -> list[Action]:
        """A job the session no longer waits for (its value is void; a mode may still report)."""
        return []

    def _abort(self) -> list[Device]:
        """What tells the device to leave its routine (cancel, time-out, shutdown)."""
        return []

    def _retry(self, reason: str, now: float) -> list[Action] | None:
        """A failure the mode starts over from (None: it fails)."""
        return None

    # -- shared steps ----------------------------------------------------------------

    def _data(self, **extra: Any) -> dict[str, Any]:
        return {"mode": self.mode.value, "sensor": self.mode.sensor, **extra}

    def started(self, text: str, **extra: Any) -> Emit:
        """The ``calibration.started`` event."""
        data = self._data(onboard=self.mode.onboard, attempt=self.attempt, **extra)
        return Emit("calibration.started", text, data=data)

    def instruction(
        self,
        text: str,
        severity: Severity = Severity.INFO,
        *,
        instruction: str = "",
        **extra: Any,
    ) -> Emit:
        """A ``calibration.instruction``: ``text`` to show, ``instruction`` what to do (the
        text itself when not given)."""
        data = {"mode": self.mode.value, "instruction": instruction or text, **extra}
        return Emit("calibration.instruction", text, severity, data)

    def collect(self, now: float) -> list[Action]:
        """Start (or restart) taking frames; the first progress event goes out."""
        self.phase = Phase.COLLECTING
        self.started_at = now
        self.last_frame_at = now
        return [self.progress_event(now)]

    def progress_event(self, now: float) -> Emit:
        """A ``calibration.progress`` event now."""
        p = self.progress()
        self._progress_at = now
        self._progress_key = (self.phase, self.step, self.attempt, int(p.percent), p.mask)
        data = self._data(
            phase=self.phase.value,
            step=self.step,
            attempt=self.attempt,
            completion_pct=round(p.percent, 1),
            completion_mask=list(p.mask),
            direction=list(p.direction),
        )
        if p.spans is not None:
            data["spans"] = list(p.spans)
        if p.faces_done is not None:
            data["faces_done"] = list(p.faces_done)
        return Emit("calibration.progress", f"Calibration {p.percent:.0f}%", data=data)

    def maybe_progress(self, now: float) -> list[Action]:
        """A progress event when something changed, at most one per ``progress_interval_s``
        (a new phase, step or attempt goes out at once)."""
        if not self.running:
            return []
        last, soon = self._progress_key, now - self._progress_at < self.settings.progress_interval_s
        stage = (self.phase, self.step, self.attempt)
        if soon and last[:3] == stage:
            # Within the interval, at the last event's stage, nothing goes out whatever the
            # figure says: most frames stop here without working the progress out.
            return []
        p = self.progress(hint=False)
        key = (*stage, int(p.percent), p.mask)
        if key == last:
            return []
        moved_on = not last or last[:3] != stage
        if not moved_on and soon:
            return []
        return [self.progress_event(now)]

    def succeed(self, report: SessionReport, text: str = "") -> list[Action]:
        """Done with a result (``calibration.done``)."""
        self.phase = Phase.SUCCEEDED
        self.report = report
        self.pending = None
        data = self._data(
            onboard=self.mode.onboard,
            attempt=self.attempt,
            report=report.to_dict(),
            autosaved=report.autosaved,
        )
        return [
            Emit("calibration.done", text or f"Calibration done: {self.mode.sensor}", data=data)
        ]

    def fail(
        self,
        reason: str,
        failure: Failure = Failure.FAILED,
        *,
        report: SessionReport | None = None,
        retry_ok: bool = True,
        now: float,
    ) -> list[Action]:
        """Done without a result (``calibration.failed``), unless the mode retries."""
        if retry_ok:
            again = self._retry(reason, now)
            if again is not None:
                return again
        if report is None:
            report = failure_report(self.mode, reason, failure)
        self.phase = Phase.FAILED
        self.report = report
        self.pending = None
        data = self._data(
            onboard=self.mode.onboard,
            failure=(report.failure or failure).value,
            attempt=self.attempt,
            reason=reason,
            report=report.to_dict(),
        )
        return [Emit("calibration.failed", f"Calibration failed: {reason}", Severity.ERROR, data)]

    def _timeout(self, reason: str, now: float) -> list[Action]:
        # As ArduPilot: a time-out is final, retry or not.
        aborts: list[Action] = list(self._abort())
        return [*self.fail(reason, retry_ok=False, now=now), *aborts]
