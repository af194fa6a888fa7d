"""The device's own routines as sessions: MAGCAL (two guided turns) and ACCCAL (level), pure.

:class:`OnboardMagSession` sends ``MAGCAL,START``, guides the operator
through the datasheet's two turns, and sends ``MAGCAL,END`` itself once
:class:`OnboardMagTracker` has seen both (or at once on an accept); the
device computes and stores the result, read back with ``PAR,GET``.
:class:`OnboardLevelSession` sends ``ACCCAL`` (the device averages its level
reference). Device commands run in the controller's worker; their answers
come back to the session.

**When the bridge ends MAGCAL** (judged from the device's ``$PGMRC``
reports and the attitude frames): each turn is complete when

1. the field, seen only in frames the device itself counts -- level (tilt
   under 20 deg from its own level reference) for the level turn, on its
   side (|gz| under 0.35 g) for the side turn -- has gone round at least
   ``onboard_min_turn_deg`` (330 deg) of the circle it draws about the centre
   of the device's own min/max in the plane that turns. What counts is how far
   round it has *reached* (the extent of the unwrapped angle), not the net
   angle: tipping the unit onto its side moves the field against the turn by
   up to ~40 deg, which a net angle subtracts from a full turn on the side --
   with some units below 330 deg, so that END never came;
2. the ``$PGMRC`` spans of the axes that turn (x and y level, z on the side)
   have each reached the device's 400 counts and grown by no more than 8
   counts (or 1 %) over the last ``onboard_settle_reports`` (2) reports.

(1) alone would be fooled by a centre that is still wrong early in a turn,
(2) alone by a pause mid-turn. ``MAGCAL,END`` goes out when both turns are
complete, in either order; at hand pace (a turn in about 15 s) that is a
second or two after the side turn ends.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from bridge.calibration.sessions.base import Action, Device, Job, Progress, Session, device_error
from bridge.calibration.sessions.host import LEVEL_INSTRUCTION, LEVEL_TEXT
from bridge.calibration.sessions.report import (
    DeviceOutcome,
    SessionReport,
    failure_report,
    params_dict,
)
from bridge.calibration.sessions.state import CalibratorSettings, Mode, Outcome, Phase, Result
from bridge.core import sensor
from bridge.core.calibration import ArduPilotView
from bridge.protocol.device import (
    CommandError,
    CommandLate,
    CommandRejected,
    CommandTimeout,
    LinkDown,
)
from bridge.protocol.gmr import AckFrame, AttitudeFrame, CalProgressFrame, Flags, ParamsFrame

#: The device's two-step rotation, as the operator is told.
INSTRUCTION_LEVEL_TURN = "Turn the compass one full turn, level"
INSTRUCTION_SIDE_TURN = "Tip it 90 deg onto its side, turn one full turn"
INSTRUCTION_LEVEL_AGAIN = "Level turn not seen yet: one full turn, level"

#: Datasheet MAGCAL conditions: level = tilt under 20 deg; on its side = |gz| under 0.35 g.
ONBOARD_LEVEL_TILT_DEG = 20.0
ONBOARD_SIDE_GZ_G = 0.35
ONBOARD_MIN_SPAN = 400  #: counts: MAGCAL,END fails with RANGE below this on any axis
#: Frames in a row without the CAL flag that mean the device left its routine (a reset).
FRAMES_WITHOUT_CAL = 5


def _turned_deg(points: list[tuple[float, float]], centre: tuple[float, float]) -> float:
    """How far round ``centre`` a path of 2-D points has reached, in degrees.

    The extent of the path's unwrapped angle: a stretch backwards neither adds
    nor takes away (unlike the net angle), a second turn adds.
    """
    if len(points) < 2:
        return 0.0
    p = np.asarray(points, dtype=np.float64) - np.asarray(centre)
    ang = np.unwrap(np.arctan2(p[:, 1], p[:, 0]))
    return math.degrees(float(ang.max() - ang.min()))


class OnboardMagTracker:
    """Follows the device's two-turn MAGCAL routine and says when each turn is complete.

    The device tracks x/y extremes while level and the z extreme while on its
    side (its own tests, with its own level reference -- reproduced here from
    the flash page). The rule a turn is judged by is the module docstring's.
    :meth:`frame` takes every attitude frame, :meth:`progress` every
    ``$PGMRC`` report.
    """

    def __init__(
        self,
        level_reference: ParamsFrame | None = None,
        *,
        min_turn_deg: float = 330.0,
        settle_reports: int = 2,
        growth_tol: float = 8.0,
        point_spacing: float = 15.0,
    ) -> None:
        page = level_reference if level_reference is not None else ParamsFrame.factory()
        self._goff = (page.gxoff, page.gyoff, page.gzoff - sensor.ACC_COUNTS_PER_G)
        self.min_turn_deg = min_turn_deg
        self.settle_reports = settle_reports
        self.growth_tol = growth_tol
        self.point_spacing = point_spacing
        self.level_done = False
        self.side_done = False
        self.level_points: list[tuple[float, float]] = []
        self.side_points: list[tuple[float, float, float]] = []
        self.side_axis: int | None = None  #: 0 (x) or 1 (y): the other horizontal axis on the side
        self.history: deque[CalProgressFrame] = deque(maxlen=max(2, settle_reports + 1))
        self.level_swept = 0.0  #: how far round the level turn has reached (deg)
        self.side_swept = 0.0  #: how far round the side turn has reached (deg)
        self.attitude = "other"  #: "level", "side" or "other" (device's definitions)

    @property
    def step(self) -> int:
        """1: the level turn; 2: the side turn; 3: both seen."""
        if self.level_done and self.side_done:
            return 3
        return 2 if self.level_done else 1

    def classify(self, ax: int, ay: int, az: int) -> str:
        """The device's view of a frame: "level", "side" or "other"."""
        gx, gy, gz = ax - self._goff[0], ay - self._goff[1], az - self._goff[2]
        gn = math.sqrt(gx * gx + gy * gy + gz * gz)
        if gn == 0.0:
            return "other"
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, gz / gn))))
        if tilt < ONBOARD_LEVEL_TILT_DEG:
            return "level"
        if abs(gz) < ONBOARD_SIDE_GZ_G * sensor.ACC_COUNTS_PER_G:
            return "side"
        return "other"

    def frame(self, mx: int, my: int, mz: int, ax: int, ay: int, az: int) -> None:
        """One attitude frame: remember the path of the field while level / on the side."""
        self.attitude = self.classify(ax, ay, az)
        if self.attitude == "level":
            if _far(self.level_points, (mx, my), self.point_spacing):
                self.level_points.append((float(mx), float(my)))
        elif self.attitude == "side":
            gx, gy = abs(ax - self._goff[0]), abs(ay - self._goff[1])
            # On its side the horizontal plane holds z and whichever of x/y is not vertical.
            axis = 0 if gx < gy else 1
            if self.side_axis is None:
                self.side_axis = axis
            if axis == self.side_axis:
                h = float(mx if axis == 0 else my)
                pts = [(p[0] if axis == 0 else p[1], p[2]) for p in self.side_points[-1:]]
                if _far(pts, (h, mz), self.point_spacing):
                    self.side_points.append((float(mx), float(my), float(mz)))

    def progress(self, frame: CalProgressFrame) -> str | None:
        """One ``$PGMRC``: ``"level_done"`` (on to the side turn), ``"side_done"`` (the side
        turn before the level one), ``"done"`` (both: time for END) or None."""
        self.history.append(frame)
        xmid = (frame.xmin + frame.xmax) / 2.0 if frame.xmax > 0 else None
        ymid = (frame.ymin + frame.ymax) / 2.0 if frame.ymax > 0 else None
        zmid = (frame.zmin + frame.zmax) / 2.0 if frame.zmax > 0 else None
        if xmid is not None and ymid is not None:
            self.level_swept = _turned_deg(self.level_points, (xmid, ymid))
        if zmid is not None and self.side_axis is not None:
            hmid = xmid if self.side_axis == 0 else ymid
            pts = [(p[self.side_axis], p[2]) for p in self.side_points]
            if hmid is None:  # never level: centre the other axis on its own path
                hmid = float(np.mean([p[0] for p in pts])) if pts else 0.0
            self.side_swept = _turned_deg(pts, (hmid, zmid))
        was = (self.level_done, self.side_done)
        if not self.level_done:
            self.level_done = self._turn_done(("x", "y"), self.level_swept)
        if not self.side_done:
            self.side_done = self._turn_done(("z",), self.side_swept)
        if (self.level_done, self.side_done) == was:
            return None
        if self.level_done and self.side_done:
            return "done"
        return "level_done" if self.level_done else "side_done"

    def _turn_done(self, axes: tuple[str, ...], swept: float) -> bool:
        if swept < self.min_turn_deg or len(self.history) < self.settle_reports + 1:
            return False
        last = self.history[-1]
        first = self.history[-1 - self.settle_reports]
        for a in axes:
            span = last.span(a)  # type: ignore[arg-type]
            if span < ONBOARD_MIN_SPAN:
                return False
            tol = max(self.growth_tol, 0.01 * span)
            if span - first.span(a) > tol:  # type: ignore[arg-type]
                return False
        return True

    @property
    def spans(self) -> tuple[int, int, int]:
        """The last reported (x, y, z) spans in counts."""
        if not self.history:
            return (0, 0, 0)
        f = self.history[-1]
        return (f.span("x"), f.span("y"), f.span("z"))

    @property
    def percent(self) -> float:
        """Level turn up to 50 %, side turn up to 49 % more (100 is the device's OK)."""
        level = 50.0 if self.level_done else min(49.0, 50.0 * self.level_swept / 360.0)
        side = 49.0 if self.side_done else min(48.0, 49.0 * self.side_swept / 360.0)
        return min(99.0, level + side)


def _far(points: list[tuple[float, float]], p: tuple[float, float], spacing: float) -> bool:
    if not points:
        return True
    q = points[-1]
    return (p[0] - q[0]) ** 2 + (p[1] - q[1]) ** 2 >= spacing * spacing


# ---------------------------------------------------------------------------
# sessions
# ---------------------------------------------------------------------------


def device_reason(e: CommandError) -> str:
    """A device command's failure in the operator's words."""
    if isinstance(e, CommandRejected):
        text = {
            "RANGE": "too little rotation (RANGE)",
            "MOTION": "the unit moved (MOTION)",
            "STATE": "the compass is busy (STATE)",
            "FLASH": "flash write failed (FLASH)",
        }.get(e.reason, e.reason)
        return f"{e.command}: {text}"
    if isinstance(e, CommandLate):
        return f"the compass answered too late ({e})"
    if isinstance(e, CommandTimeout):
        return f"no answer from the compass ({e})"
    return f"device command failed: {e}"


def abort_problem(answer: object) -> str:
    """What is worth telling about a ``MAGCAL,ABORT``'s answer ("" when it did its job)."""
    if isinstance(answer, CommandLate) and isinstance(answer.answer, AckFrame):
        answer = (
            answer.answer
            if answer.answer.ok
            else CommandRejected(
                "MAGCAL", answer.answer.fields[0] if answer.answer.fields else "?", answer.answer
            )
        )  # late, but it did its job (or said why not)
    if isinstance(answer, CommandRejected):
        # STATE: not calibrating any more, which is the goal
        return "" if answer.reason == "STATE" else f"MAGCAL,ABORT refused: {answer.reason}"
    if isinstance(answer, CommandError):
        return f"MAGCAL,ABORT failed: {answer}"
    return ""


class _DeviceSession(Session):
    """What both on-board routines share: the device's answer, read back with PAR,GET."""

    def __init__(self, settings: CalibratorSettings, now: float) -> None:
        super().__init__(settings, now, autosave=True)
        self._answer: object = None  #: the routine's answer, kept while PAR,GET runs

    def _refresh(self, answer: object) -> list[Action]:
        """PAR,GET so the link (and everyone reading ``link.params``) sees the new flash."""
        self._answer = answer
        self.pending = Device("PAR", ("GET",), purpose="refresh")
        return [self.pending]

    def _finish(self, answer: object, params: ParamsFrame | None, now: float) -> list[Action]:
        raise NotImplementedError

    def _refreshed(self, value: object, now: float) -> list[Action]:
        params = value if isinstance(value, ParamsFrame) else None
        out: list[Action] = []
        if isinstance(value, CommandError):
            out.append(device_error(f"PAR,GET failed: {value}"))
        return out + self._finish(self._answer, params, now)

    def _failed(self, answer: object, now: float, **extra: Any) -> list[Action]:
        """The routine's refusal (or a wrong answer) as the session's failure."""
        reason = device_reason(answer) if isinstance(answer, CommandError) else "unexpected answer"
        code = answer.reason if isinstance(answer, CommandRejected) else ""
        device = DeviceOutcome(error=code, **extra)
        report = failure_report(self.mode, reason, device=device)
        return self.fail(reason, report=report, now=now)


class OnboardMagSession(_DeviceSession):
    """The device's MAGCAL, guided and ended by the bridge (see the module docstring)."""

    mode = Mode.ONBOARD_MAG

    def __init__(
        self,
        settings: CalibratorSettings,
        now: float,
        *,
        params: ParamsFrame | None = None,
        delay_s: float = 0.0,
        retry: bool = False,
    ) -> None:
        super().__init__(settings, now)
        self.delay_s = delay_s
        self.retry = retry
        self.start_at = now + delay_s
        self.tracker = OnboardMagTracker(
            params,
            min_turn_deg=settings.onboard_min_turn_deg,
            settle_reports=settings.onboard_settle_reports,
        )
        self.device_started = False  #: MAGCAL,START acknowledged
        self.ending = False  #: MAGCAL,END sent
        self._starting = False  #: MAGCAL,START on its way
        self._without_cal = 0
        self._told_level_again = False

    def _progress(self, hint: bool, percent: float | None) -> Progress:
        tr = self.tracker
        return Progress(tr.percent if percent is None else percent, spans=tr.spans)

    def begin(self, now: float) -> list[Action]:
        """Started; the device's routine starts at once unless delayed."""
        started = self.started(
            "Calibration started: on-board mag",
            retry=self.retry,
            autosave=True,
            delay_s=self.delay_s,
        )
        return [started, *(self._start() if self.delay_s == 0.0 else [])]

    def _tick_waiting(self, now: float) -> list[Action]:
        return self._start() if now >= self.start_at and not self.busy else []

    def _start(self) -> list[Action]:
        self._starting = True
        self.pending = Device("MAGCAL", ("START",), retries=1, purpose="start")
        return [self.pending]

    def feed(self, frame: object, now: float) -> list[Action]:
        """Attitude frames (the path of the field, the CAL flag) and ``$PGMRC`` reports."""
        if not self.running or self.phase is Phase.WAITING:
            return []  # the device is not in our routine (yet)
        if isinstance(frame, AttitudeFrame):
            self.last_frame_at = now
            out = self._attitude(frame, now)
        elif isinstance(frame, CalProgressFrame):
            if self.ending:
                return []
            self.last_frame_at = now
            out = self._report(frame)
        else:
            return []
        return out + self.maybe_progress(now)

    def _attitude(self, f: AttitudeFrame, now: float) -> list[Action]:
        if self.ending:
            return []
        self.tracker.frame(f.mx, f.my, f.mz, f.ax, f.ay, f.az)
        # After the START answer every frame carries CAL; several without it mean the
        # device left calibration mode on its own (a reset or a power cycle).
        if f.flags & Flags.CAL:
            self._without_cal = 0
            return []
        self._without_cal += 1
        if self._without_cal < FRAMES_WITHOUT_CAL:
            return []
        self.device_started = False  # nothing to abort: it left by itself
        return self.fail("the compass left calibration mode (reset?)", retry_ok=False, now=now)

    def _report(self, f: CalProgressFrame) -> list[Action]:
        what = self.tracker.progress(f)
        if what == "level_done":
            self.step = 2
            return [self.instruction(INSTRUCTION_SIDE_TURN, step=2)]
        if what == "side_done" and not self._told_level_again:
            self._told_level_again = True
            return [self.instruction(INSTRUCTION_LEVEL_AGAIN, step=1)]
        if what == "done":
            self.step = 2
            return self._end()
        return []

    def _end(self) -> list[Action]:
        self.ending = True
        self.phase = Phase.FITTING
        # Not resent: a second END after a lost answer would hit ERR,STATE.
        self.pending = Device("MAGCAL", ("END",), retries=0, purpose="end")
        return [self.pending]

    def _resolved(self, job: Job, value: Any, now: float) -> list[Action]:
        assert isinstance(job, Device)
        if job.purpose == "refresh":
            return self._refreshed(value, now)
        if job.purpose == "end":
            return self._refresh(value)
        if job.purpose == "stale":
            if isinstance(value, CommandError) and not isinstance(value, CommandRejected):
                return self._start_failed(value, now)
            self.pending = Device("MAGCAL", ("START",), retries=0, purpose="restart")
            return [self.pending]
        # "start" or "restart"
        if (
            isinstance(value, CommandRejected)
            and value.reason == "STATE"
            and job.purpose == "start"
        ):
            # Still in a calibration mode from an earlier run (or our own START whose
            # answer was lost): leave it and start afresh.
            self.pending = Device("MAGCAL", ("ABORT",), retries=1, purpose="stale")
            return [self.pending]
        if isinstance(value, CommandError):
            return self._start_failed(value, now)
        self._starting = False
        self.device_started = True
        return [*self.collect(now), self.instruction(INSTRUCTION_LEVEL_TURN, step=1)]

    def _start_failed(self, e: CommandError, now: float) -> list[Action]:
        # A START that timed out (or answered late) may have started the routine: the
        # device is told to leave it, so it is left as found. A port that is down cannot
        # hear it; the controller aborts a left-over CAL mode once frames show it.
        aborts = [] if isinstance(e, LinkDown) else self._abort()
        self._starting = False
        return [*self.fail(device_reason(e), now=now), *aborts]

    def _late(self, job: Job, value: Any) -> list[Action]:
        if isinstance(job, Device) and job.purpose == "abort":
            problem = abort_problem(value)
            return [device_error(problem)] if problem else []
        return []

    def _abort(self) -> list[Device]:
        # END in flight leaves calibration mode by itself (an ABORT would hit ERR,STATE).
        if (self.device_started or self._starting) and not self.ending:
            return [Device("MAGCAL", ("ABORT",), retries=1, purpose="abort")]
        return []

    def accept(self) -> tuple[Outcome, list[Action]]:
        """An accept while the routine runs ends it now (``MAGCAL,END``)."""
        if self.running:
            if not self.device_started:
                return Outcome(Result.DENIED, "the compass has not entered calibration yet"), []
            actions = [] if self.ending else self._end()
            return Outcome(Result.IN_PROGRESS, "ending the on-board calibration"), actions
        return super().accept()

    def _finish(self, answer: object, params: ParamsFrame | None, now: float) -> list[Action]:
        spans = self.tracker.spans
        if not isinstance(answer, AckFrame):
            return self._failed(answer, now, spans=spans)
        names = ("xoff", "yoff", "zoff", "kx", "ky", "kz")
        device = dict(zip(names, answer.values, strict=True))
        rest = (params or ParamsFrame.factory()).values()[6:]
        page = ParamsFrame(*answer.values, *rest)
        report = SessionReport(
            self.mode,
            "device MAGCAL",
            autosaved=True,
            mag=ArduPilotView.of_device(page),
            device=DeviceOutcome(device, params_dict(params), spans),
        )
        self.accepted = True  # the device wrote its flash: nothing left to accept
        return self.succeed(report)


class OnboardLevelSession(_DeviceSession):
    """The device's ACCCAL: it averages 1 s of its accelerometer as its level reference.

    A cancel cannot stop an ACCCAL already averaging: its result is ignored.
    """

    mode = Mode.ONBOARD_LEVEL

    def begin(self, now: float) -> list[Action]:
        """Started, ``ACCCAL`` on its way."""
        # ACCCAL is never resent: a second one would average again (or hit ERR,STATE).
        self.pending = Device("ACCCAL", retries=0, purpose="acccal")
        return [
            self.started("Calibration started: on-board level"),
            *self.collect(now),
            self.instruction(LEVEL_TEXT, instruction=LEVEL_INSTRUCTION, step=1),
            self.pending,
        ]

    def feed(self, frame: object, now: float) -> list[Action]:
        """Frames only show the device is alive (the no-data time-out)."""
        if isinstance(frame, AttitudeFrame) and self.running:
            self.last_frame_at = now
        return []

    def _resolved(self, job: Job, value: Any, now: float) -> list[Action]:
        assert isinstance(job, Device)
        if job.purpose == "refresh":
            return self._refreshed(value, now)
        if isinstance(value, AckFrame):
            return self._refresh(value)
        return self._failed(value, now)

    def _finish(self, answer: object, params: ParamsFrame | None, now: float) -> list[Action]:
        assert isinstance(answer, AckFrame)
        g = dict(zip(("gxoff", "gyoff", "gzoff"), answer.values, strict=True))
        device = DeviceOutcome(g, params_dict(params))
        report = SessionReport(self.mode, "device ACCCAL", autosaved=True, device=device)
        self.accepted = True
        return self.succeed(report)
