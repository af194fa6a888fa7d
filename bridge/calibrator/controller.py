"""CalibrationController: the state machine behind every calibration front end.

MAVLink (ArduPilot's MAV_CMD_DO_START/ACCEPT/CANCEL_MAG_CAL, PX4's
MAV_CMD_PREFLIGHT_CALIBRATION), the zenoh ``cmd/calibration/*`` queryables and
the CLI all drive this one object; it answers each command with an
:class:`Outcome` and reports everything else as :class:`~bridge.events.Event`
on the bus (kinds in :data:`EVENT_KINDS`), which each front end maps to its
wire format. :meth:`CalibrationController.snapshot` serves status queries.

Threads:

* the daemon's **pipeline** (in the link's reader thread) calls :meth:`~CalibrationController.feed`
  for every frame -- O(1) when idle, a few tens of microseconds while
  collecting; it never waits for a fit or a device command;
* one **worker thread** runs fits, persistence and device commands
  (``MAGCAL``, ``ACCCAL``, ``PAR``) and checks the time-outs every 0.1 s;
* front ends call the command methods from their own threads.

One lock guards the session; events are queued under it and delivered after
it is released, in order, so a subscriber may call back into the controller.

Routes (``onboard`` = the BRG_CAL_ONBOARD parameter):

=================  ============================================  ===============================
command            host (``onboard=False``)                      on-board (``onboard=True``)
=================  ============================================  ===============================
magnetometer       ArduPilot's two-step sample collection, then  the device's ``MAGCAL``: two
                   the engine's best fit (ellipsoid + alignment) guided turns, ``END`` sent
                                                                 when both are seen
accelerometer      PX4's six faces, then the six-face fit        (host only: the device has
                                                                 no six-face routine)
level              one still average, then the level trim        the device's ``ACCCAL``
fixed yaw          offsets from a known yaw and the WMM field    (host; written to the device)
=================  ============================================  ===============================
"""

from __future__ import annotations

import contextlib
import enum
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from bridge.calibration.accel_faces import Face, fit_six_face, level_trim
from bridge.calibration.methods import BEST, CalibrationData, calibrate
from bridge.calibration.model import (
    AffineCalibration,
    Calibration,
    CalibrationReport,
    CalibrationResult,
)
from bridge.calibration.sanity import MagCalStatus, check_accel_calibration
from bridge.calibrator.collect import (
    FaceCollector,
    MagCollector,
    OnboardMagTracker,
    StillCollector,
    counts_to_nominal,
    sphere_step,
)
from bridge.calibrator.motion import MotionJudge
from bridge.calibrator.results import (
    CAL_MASK,
    COMPASS_ID,
    attitude_from_gravity,
    device_calibration_view,
    device_params_for,
    fixed_yaw_calibration,
    judge_accuracy,
    mag_report,
    orientation_confidence,
)
from bridge.calibrator.store import CalibrationStore
from bridge.core.mounting import Mounting
from bridge.core.wmm import EarthField, earth_field
from bridge.events import Event, EventBus, Severity
from bridge.ports import (
    CommandError,
    CommandRejected,
    CommandTimeout,
    DevicePort,
    DocumentStore,
    StorageError,
)
from bridge.protocol.gmr import (
    AckFrame,
    AttitudeFrame,
    CalProgressFrame,
    CommandFrame,
    Flags,
    ParamsFrame,
)

log = logging.getLogger(__name__)

#: Every event kind this controller emits.
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
    "calibration.storage_error",
    "calibration.device_updated",
    "calibration.device_error",
    "calibration.motion",
)
STATUSTEXT_MAX = 50  #: MAVLink STATUSTEXT carries 50 characters

#: The device's two-step rotation, as the operator is told.
INSTRUCTION_LEVEL_TURN = "Turn the compass one full turn, level"
INSTRUCTION_SIDE_TURN = "Tip it 90 deg onto its side, turn one full turn"

_RUNNING = frozenset(
    {
        MagCalStatus.MAG_CAL_WAITING_TO_START,
        MagCalStatus.MAG_CAL_RUNNING_STEP_ONE,
        MagCalStatus.MAG_CAL_RUNNING_STEP_TWO,
    }
)


class Mode(enum.StrEnum):
    """What a session calibrates, and where."""

    MAG = "mag"  #: host magnetometer: two-step collection, ellipsoid + alignment
    ACCEL = "accel"  #: host accelerometer: six faces
    LEVEL = "level"  #: host level trim
    FIXED_YAW = "fixed_yaw"  #: host offsets from one known yaw
    ONBOARD_MAG = "onboard_mag"  #: the device's MAGCAL
    ONBOARD_LEVEL = "onboard_level"  #: the device's ACCCAL

    @property
    def onboard(self) -> bool:
        """Runs in the device (result in its flash)."""
        return self in (Mode.ONBOARD_MAG, Mode.ONBOARD_LEVEL)

    @property
    def sensor(self) -> str:
        """PX4's word for it in "[cal] calibration done: <sensor>": mag, accel or level."""
        if self in (Mode.MAG, Mode.FIXED_YAW, Mode.ONBOARD_MAG):
            return "mag"
        return "accel" if self is Mode.ACCEL else "level"


class Result(enum.StrEnum):
    """How a command was taken (front ends map it to MAV_RESULT / a zenoh reply)."""

    ACCEPTED = "accepted"  #: done (or nothing to do)
    IN_PROGRESS = "in_progress"  #: started; the outcome follows as events
    DENIED = "denied"  #: not now (another calibration runs, nothing to accept ...)
    FAILED = "failed"  #: could not be done (bad argument, no position, no device ...)


@dataclass(frozen=True, slots=True)
class Outcome:
    """A command's immediate answer."""

    result: Result
    message: str = ""

    @property
    def ok(self) -> bool:
        """ACCEPTED or IN_PROGRESS."""
        return self.result in (Result.ACCEPTED, Result.IN_PROGRESS)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (zenoh replies)."""
        return {"result": self.result.value, "ok": self.ok, "message": self.message}


@dataclass(frozen=True, slots=True)
class CalibratorSettings:
    """Tunables (defaults follow ArduPilot / PX4 where they have one).

    Times are seconds of the controller's clock.
    """

    capacity: int = 300  #: magnetometer sample buffer (ArduPilot's COMPASS_CAL_NUM_SAMPLES)
    timeout_s: float = 180.0  #: a whole session (collection or device routine) gives up after this
    no_data_timeout_s: float = 2.0  #: running without any frame this long fails (ArduPilot: 1 s)
    progress_interval_s: float = 1.0  #: at most one progress event per interval (on change)
    face_still_s: float = 1.0  #: stillness window that detects a face
    face_collect_s: float = 1.5  #: further still time averaged per face
    still_tol_g: float = 0.02  #: per-axis standard deviation for "still" (PX4: 0.25 m/s^2)
    face_norm_tol_g: float = 0.5  #: |g| tolerance for a face of an uncalibrated unit
    level_collect_s: float = 1.0  #: host level calibration: still time averaged
    fixed_yaw_window_s: float = 1.0  #: fixed yaw: recent frames averaged
    onboard_min_turn_deg: float = 330.0  #: a device turn counts from this much rotation
    onboard_settle_reports: int = 2  #: $PGMRC reports without span growth that end a turn
    motion_limit_g: float = 0.09  #: linear acceleration (g RMS per axis) the operator is told of
    motion_interval_s: float = 5.0  #: at most one "calibration.motion" warning per interval
    max_heading_error_deg: float = 0.25  #: a fit predicting a larger heading error fails

    def __post_init__(self) -> None:
        if self.capacity < 20:
            raise ValueError(f"capacity must be at least 20, got {self.capacity}")
        for name in (
            "timeout_s",
            "no_data_timeout_s",
            "progress_interval_s",
            "face_still_s",
            "face_collect_s",
            "still_tol_g",
            "face_norm_tol_g",
            "level_collect_s",
            "fixed_yaw_window_s",
            "onboard_min_turn_deg",
            "motion_limit_g",
            "motion_interval_s",
            "max_heading_error_deg",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive and finite, got {v!r}")
        if self.onboard_settle_reports < 1:
            raise ValueError("onboard_settle_reports must be at least 1")


@dataclass(frozen=True, slots=True)
class CalibratorSnapshot:
    """The controller's state for status queries (MAVLink HEARTBEAT, zenoh status, CLI).

    ``status`` is the MAG_CAL_STATUS of the current (or last) session;
    ``pending_accept`` a successful host magnetometer fit waiting for accept;
    ``calibration_age_s`` how long ago the calibration in use was accepted
    (None: never, or unknown).
    """

    mode: str | None
    status: MagCalStatus
    running: bool
    attempt: int
    completion_pct: float
    completion_mask: bytes
    direction: tuple[float, float, float]
    onboard: bool
    faces_done: tuple[str, ...]
    last_report: dict[str, Any] | None
    pending_accept: bool
    calibration_source: str
    calibration_age_s: float | None
    calibration_saved: bool

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "mode": self.mode,
            "status": self.status.name,
            "status_code": int(self.status),
            "running": self.running,
            "attempt": self.attempt,
            "completion_pct": self.completion_pct,
            "completion_mask": list(self.completion_mask),
            "direction": list(self.direction),
            "onboard": self.onboard,
            "faces_done": list(self.faces_done),
            "last_report": self.last_report,
            "pending_accept": self.pending_accept,
            "calibration_source": self.calibration_source,
            "calibration_age_s": self.calibration_age_s,
            "calibration_saved": self.calibration_saved,
        }


@dataclass(eq=False)
class _Session:
    """One calibration run (mutable; guarded by the controller's lock)."""

    mode: Mode
    gen: int
    started_at: float
    status: MagCalStatus = MagCalStatus.MAG_CAL_WAITING_TO_START
    start_at: float = 0.0
    attempt: int = 1
    retry: bool = False
    autosave: bool = False
    mask: int = 0
    last_frame_at: float | None = None
    last_progress_at: float = -math.inf
    last_progress_key: tuple[Any, ...] = ()
    busy: bool = False  #: a worker job for this session is queued or running
    device_started: bool = False  #: MAGCAL,START acknowledged
    ending: bool = False  #: MAGCAL,END sent
    frames_without_cal: int = 0
    mag: MagCollector | None = None
    faces: FaceCollector | None = None
    still: StillCollector | None = None
    onboard: OnboardMagTracker | None = None
    result: CalibrationResult | None = None
    report: dict[str, Any] | None = None
    accepted: bool = False
    percent_done: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def running(self) -> bool:
        return self.status in _RUNNING


class CalibrationTarget(Protocol):
    """Where an accepted calibration goes: the attitude engine, or the application's
    :class:`~bridge.app.settings.EngineSettings` (its one writer, which tells the others)."""

    @property
    def calibration(self) -> Calibration:
        """The calibration in use."""
        ...

    @property
    def mounting(self) -> Mounting:
        """The mounting in use."""
        ...

    def update_calibration(self, calibration: Calibration) -> None:
        """Use ``calibration`` from now on."""
        ...


def _short(text: str) -> str:
    return text if len(text) <= STATUSTEXT_MAX else text[: STATUSTEXT_MAX - 1] + "~"


def _is_identity(cal: AffineCalibration) -> bool:
    return cal == AffineCalibration()


class CalibrationController:
    """Front-end-neutral calibration state machine (see the module docstring).

    ``engine`` is the daemon's attitude engine (its calibration is what
    accept replaces); ``bus`` receives the events; ``link`` runs device
    commands (None: host-only, nothing written to the device); ``store``
    persists accepted calibrations (None: memory only); ``field`` is the
    WMM field here (None: fits are not scaled to it and fixed yaw needs a
    position). ``onboard`` is the default route (BRG_CAL_ONBOARD).
    ``clock`` is the controller's time base (monotonic seconds);
    ``wall_clock`` dates calibrations.
    """

    def __init__(
        self,
        engine: CalibrationTarget,
        bus: EventBus,
        *,
        link: DevicePort | None = None,
        store: DocumentStore | None = None,
        field: EarthField | None = None,
        onboard: bool = False,
        settings: CalibratorSettings | None = None,
        calibration_source: str = "",
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self._engine = engine
        self._bus = bus
        self._link = link
        self._store = CalibrationStore(store) if store is not None else None
        self._field = field
        self.settings = settings if settings is not None else CalibratorSettings()
        self._onboard = bool(onboard)
        self._clock = clock
        self._wall = wall_clock
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._emit_lock = threading.RLock()
        self._pending: list[Event] = []
        self._session: _Session | None = None
        self._gen = 0
        self._recent: deque[tuple[float, AttitudeFrame]] = deque(maxlen=256)
        self._jobs: queue.Queue[Callable[[], None] | None] = queue.Queue()
        self._worker: threading.Thread | None = None
        self._stop = threading.Event()
        self.errors = 0  #: unexpected exceptions caught (logged once)
        self._calibration_source = calibration_source
        self._calibration_time: float | None = None
        self._calibration_saved = False
        if self._store is not None:
            stored = self._store.load()  # never raises
            if stored.stored:
                self._calibration_time = stored.accepted_unix
                self._calibration_saved = True

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> CalibrationController:
        """Start the worker thread (idempotent; commands also start it)."""
        with self._lock:
            if self._worker is None and not self._stop.is_set():
                self._worker = threading.Thread(
                    target=self._run, name="calibration-worker", daemon=True
                )
                self._worker.start()
        return self

    def close(self, timeout: float = 2.0) -> None:
        """Stop the worker within about ``timeout`` s; a device MAGCAL in progress is aborted."""
        with self._lock:
            s = self._session
            abort = s is not None and s.mode is Mode.ONBOARD_MAG and s.running and s.device_started
            if s is not None and s.running:
                self._gen += 1
                s.status = MagCalStatus.MAG_CAL_NOT_STARTED
        if abort and self._link is not None:
            # Leaving the device in calibration mode would stop its own heading from
            # improving and refuse PAR,SET; the link may already be closed (then it is moot).
            with contextlib.suppress(CommandError, ValueError):
                self._link.command("MAGCAL", "ABORT", retries=0)
        self._stop.set()
        self._jobs.put(None)
        w = self._worker
        if w is not None and w is not threading.current_thread():
            w.join(timeout)
            if w.is_alive():
                log.error("calibration worker did not stop within %.1f s", timeout)

    def __enter__(self) -> CalibrationController:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ configuration

    @property
    def onboard(self) -> bool:
        """Default route for magnetometer and level calibrations (BRG_CAL_ONBOARD)."""
        return self._onboard

    @onboard.setter
    def onboard(self, value: bool) -> None:
        self._onboard = bool(value)

    def set_field(self, field: EarthField | None) -> None:
        """The local Earth field (WMM at the vehicle's position), e.g. when the position changes."""
        with self._lock:
            self._field = field

    @property
    def field(self) -> EarthField | None:
        """The Earth field fits are scaled to."""
        return self._field

    @property
    def calibrating(self) -> bool:
        """A session is waiting, collecting or fitting (a cheap, lock-free read for the pipeline)."""
        s = self._session
        return s is not None and s.status in _RUNNING

    # ------------------------------------------------------------------ the per-frame hook

    def feed(self, frame: object) -> None:
        """Hand over one received frame (any type); called from the pipeline (the link's reader thread).

        ``$PGMRA`` frames feed the running session (and a short history kept for
        the fixed-yaw calibration); ``$PGMRC`` frames the device's MAGCAL
        progress. Anything else is ignored. Never blocks on fits or commands,
        never raises.
        """
        if type(frame) is AttitudeFrame:
            s = self._session
            if s is None or s.status not in _RUNNING:
                # Nearly every frame: no session collects. Only the fixed-yaw history
                # wants it, and that needs no lock: deque.append is atomic, and
                # start_fixed_yaw copies the deque (list(), one step under the GIL)
                # before it iterates. A session that starts meanwhile begins with the
                # next frame, as if this one had come a moment earlier.
                self._recent.append((self._clock(), frame))
                if self._pending:
                    self._flush()
                return
        try:
            if isinstance(frame, AttitudeFrame):
                self._feed_attitude(frame)
            elif isinstance(frame, CalProgressFrame):
                self._feed_progress(frame)
            else:
                return
        except Exception:
            self._internal_error("feed")
        self._flush()

    def _feed_attitude(self, f: AttitudeFrame) -> None:
        now = self._clock()
        with self._lock:
            self._recent.append((now, f))
            s = self._session
            if s is None or not s.running:
                return
            if s.status is MagCalStatus.MAG_CAL_WAITING_TO_START:
                if s.mode is not Mode.MAG or now < s.start_at:
                    return
                self._enter_running(s, now)
            s.last_frame_at = now
            mag, acc, sat = counts_to_nominal(f.mx, f.my, f.mz, f.ax, f.ay, f.az)
            sat = sat or bool(f.flags & Flags.SAT)
            if s.mode is Mode.MAG:
                self._feed_mag(s, now, mag, acc, sat)
            elif s.mode is Mode.ACCEL:
                self._feed_faces(s, now, acc, sat)
            elif s.mode is Mode.LEVEL:
                self._feed_level(s, now, mag, acc, sat)
            elif s.mode is Mode.ONBOARD_MAG:
                self._feed_onboard_frame(s, f)
            self._maybe_progress(s, now)

    def _feed_progress(self, f: CalProgressFrame) -> None:
        now = self._clock()
        with self._lock:
            s = self._session
            if s is None or s.mode is not Mode.ONBOARD_MAG or not s.running or s.ending:
                return
            assert s.onboard is not None
            s.last_frame_at = now
            what = s.onboard.progress(f)
            if what == "level_done":
                s.status = MagCalStatus.MAG_CAL_RUNNING_STEP_TWO
                self._event(
                    "calibration.instruction",
                    INSTRUCTION_SIDE_TURN,
                    mode=s.mode.value,
                    step=2,
                    instruction=INSTRUCTION_SIDE_TURN,
                )
                self._changed.notify_all()
            elif what == "side_done":
                self._begin_end(s, reason="both turns seen")
            self._maybe_progress(s, now)

    # -- per-mode feeding (lock held) ----------------------------------------------

    def _feed_mag(
        self,
        s: _Session,
        now: float,
        mag: tuple[float, float, float],
        acc: tuple[float, float, float],
        sat: bool,
    ) -> None:
        col = s.mag
        assert col is not None
        col.offer(mag, acc, sat, now)
        warning = col.pop_motion_warning()
        if warning is not None:
            data = warning.data()
            self._event("calibration.motion", warning.text, Severity.WARNING, mode="mag", **data)
        if col.full and not s.busy:
            s.busy = True
            self._submit_for(s, self._job_sphere if col.step == 1 else self._job_mag_fit)

    def _feed_faces(
        self, s: _Session, now: float, acc: tuple[float, float, float], sat: bool
    ) -> None:
        col = s.faces
        assert col is not None
        if s.busy:
            return
        for n in col.feed(now, acc, sat):
            side = n.face.px4_side
            if n.kind == "detected":
                self._event(
                    "calibration.face_detected",
                    f"{side} orientation detected",
                    mode=s.mode.value,
                    side=side,
                    label=n.face.label,
                )
            elif n.kind == "done":
                self._event(
                    "calibration.face_done",
                    f"{side} side done, rotate to a different side",
                    mode=s.mode.value,
                    side=side,
                    label=n.face.label,
                    faces_done=[f.px4_side for f in col.means],
                )
            elif n.kind == "already_done":
                self._event(
                    "calibration.instruction",
                    f"{side} side already completed",
                    mode=s.mode.value,
                    side=side,
                    instruction="rotate to a different side",
                )
            elif n.kind == "moved":
                self._event(
                    "calibration.instruction",
                    f"motion detected on {side}, hold still",
                    mode=s.mode.value,
                    side=side,
                    instruction="hold still",
                )
        if col.done:
            s.busy = True
            self._submit_for(s, self._job_faces_fit)

    def _feed_level(
        self,
        s: _Session,
        now: float,
        mag: tuple[float, float, float],
        acc: tuple[float, float, float],
        sat: bool,
    ) -> None:
        col = s.still
        assert col is not None
        if s.busy:
            return
        if col.feed(now, mag, acc, sat):
            s.busy = True
            self._submit_for(s, self._job_level)

    def _feed_onboard_frame(self, s: _Session, f: AttitudeFrame) -> None:
        tr = s.onboard
        assert tr is not None
        if not s.device_started or s.ending:
            return
        tr.frame(f.mx, f.my, f.mz, f.ax, f.ay, f.az)
        # After the START answer every frame carries CAL; several without it mean the
        # device left calibration mode on its own (a reset or a power cycle).
        if f.flags & Flags.CAL:
            s.frames_without_cal = 0
        else:
            s.frames_without_cal += 1
            if s.frames_without_cal >= 5:
                self._finish_failed(
                    s,
                    MagCalStatus.MAG_CAL_FAILED,
                    "the compass left calibration mode (reset?)",
                    retry_ok=False,
                )

    # ------------------------------------------------------------------ commands

    def start_mag(
        self,
        *,
        mask: float = 0,
        retry: bool = False,
        autosave: bool = False,
        delay_s: float = 0.0,
        onboard: bool | None = None,
    ) -> Outcome:
        """Start a magnetometer calibration (MAV_CMD_DO_START_MAG_CAL / PX4 param2=1).

        ``mask`` selects compasses (0 = all; the bridge has compass 0 only);
        ``retry`` restarts a failed fit; ``autosave`` accepts a success at
        once; ``delay_s`` waits before collecting. ``onboard`` overrides the
        default route (None: :attr:`onboard`).
        """
        if not self._mask_ok(mask):
            return Outcome(Result.FAILED, f"compass mask {mask} does not include compass 0")
        delay = _number(delay_s)
        if delay is None or not 0.0 <= delay <= 3600.0:
            return Outcome(Result.FAILED, f"delay {delay_s!r} s outside 0-3600")
        delay_s = delay
        use_onboard = self._onboard if onboard is None else bool(onboard)
        problem = self._link_problem(need_device=use_onboard)
        if problem:
            return Outcome(Result.FAILED, problem)
        mode = Mode.ONBOARD_MAG if use_onboard else Mode.MAG
        with self._lock:
            denied = self._busy_reason()
            if denied:
                return Outcome(Result.DENIED, denied)
            now = self._clock()
            s = self._new_session(mode, now)
            s.retry, s.autosave, s.mask = bool(retry), bool(autosave), int(mask)
            s.start_at = now + delay_s
            if use_onboard:
                params = self._link.params if self._link is not None else None
                s.onboard = self._new_tracker(params)
            else:
                s.mag = self._new_mag_collector(s.gen)
            self._event(
                "calibration.started",
                f"Calibration started: {'on-board ' if use_onboard else ''}mag",
                mode=mode.value,
                sensor="mag",
                onboard=use_onboard,
                attempt=s.attempt,
                cal_mask=CAL_MASK,
                retry=s.retry,
                autosave=s.autosave,
                delay_s=delay_s,
            )
            if use_onboard and delay_s == 0.0:
                s.busy = True
                self._submit_for(s, self._job_onboard_start)
            elif not use_onboard and delay_s == 0.0:
                self._enter_running(s, now)
        self._flush()
        self.start()
        return Outcome(Result.IN_PROGRESS, f"{mode.value} calibration started")

    def start_accel(self) -> Outcome:
        """Start the six-face accelerometer calibration (PX4 param5=1; host only)."""
        problem = self._link_problem(need_device=False)
        if problem:
            return Outcome(Result.FAILED, problem)
        with self._lock:
            denied = self._busy_reason()
            if denied:
                return Outcome(Result.DENIED, denied)
            now = self._clock()
            s = self._new_session(Mode.ACCEL, now)
            st = self.settings
            s.faces = FaceCollector(
                st.face_still_s, st.face_collect_s, st.still_tol_g, st.face_norm_tol_g
            )
            s.autosave = True  # PX4 saves an accelerometer calibration as soon as it is done
            self._event(
                "calibration.started",
                "Calibration started: accel",
                mode=s.mode.value,
                sensor="accel",
                onboard=False,
                attempt=1,
            )
            self._enter_running(s, now)
            self._event(
                "calibration.instruction",
                "Hold still on each of the six faces",
                mode=s.mode.value,
                step=1,
                instruction="hold the unit still on each of its six faces in turn",
            )
        self._flush()
        self.start()
        return Outcome(Result.IN_PROGRESS, "accelerometer calibration started")

    def start_level(self, *, onboard: bool | None = None) -> Outcome:
        """Start a level calibration (PX4 param5=2): host level trim, or the device's ACCCAL."""
        use_onboard = self._onboard if onboard is None else bool(onboard)
        problem = self._link_problem(need_device=use_onboard)
        if problem:
            return Outcome(Result.FAILED, problem)
        mode = Mode.ONBOARD_LEVEL if use_onboard else Mode.LEVEL
        with self._lock:
            denied = self._busy_reason()
            if denied:
                return Outcome(Result.DENIED, denied)
            now = self._clock()
            s = self._new_session(mode, now)
            s.autosave = True
            self._event(
                "calibration.started",
                f"Calibration started: {'on-board ' if use_onboard else ''}level",
                mode=mode.value,
                sensor="accel",
                onboard=use_onboard,
                attempt=1,
            )
            self._enter_running(s, now)
            self._event(
                "calibration.instruction",
                "Keep the vehicle level and still",
                mode=mode.value,
                step=1,
                instruction="keep the vehicle level and still",
            )
            if use_onboard:
                s.busy = True
                self._submit_for(s, self._job_acccal)
            else:
                s.still = StillCollector(self.settings.level_collect_s, self.settings.still_tol_g)
        self._flush()
        self.start()
        return Outcome(Result.IN_PROGRESS, f"{mode.value} calibration started")

    def accept(self, mask: float = 0) -> Outcome:
        """Accept the result (MAV_CMD_DO_ACCEPT_MAG_CAL).

        A successful host fit is applied, persisted and written to the device;
        a running on-board MAGCAL is ended now (``MAGCAL,END``). With nothing
        to accept the answer is ACCEPTED (as ArduPilot does); after a failure
        it is FAILED.
        """
        if not self._mask_ok(mask):
            return Outcome(Result.FAILED, f"compass mask {mask} does not include compass 0")
        with self._lock:
            s = self._session
            if s is None or s.status is MagCalStatus.MAG_CAL_NOT_STARTED:
                return Outcome(Result.ACCEPTED, "no calibration to accept")
            if s.mode is Mode.ONBOARD_MAG and s.running:
                if not s.device_started:
                    return Outcome(Result.DENIED, "the compass has not entered calibration yet")
                if not s.ending:
                    self._begin_end(s, reason="accepted by the operator")
                return Outcome(Result.IN_PROGRESS, "ending the on-board calibration")
            if s.running:
                return Outcome(Result.DENIED, "calibration still running")
            if s.status.failed:
                return Outcome(Result.FAILED, f"last calibration failed ({s.status.name})")
            if s.accepted or s.result is None or s.mode is not Mode.MAG:
                return Outcome(Result.ACCEPTED, "already accepted")
            s.accepted = True
            result, report = s.result, s.report
        return self._apply(result.calibration, source="mag", report=report, write_device=True)

    def cancel(self, mask: float = 0) -> Outcome:
        """Cancel (MAV_CMD_DO_CANCEL_MAG_CAL); ACCEPTED even when idle (QGC probes with it).

        A pending (unaccepted) host result is discarded; a device MAGCAL is
        aborted (``MAGCAL,ABORT``, flash unchanged). A device ACCCAL already
        averaging cannot be stopped: its result is ignored.
        """
        if not self._mask_ok(mask):
            return Outcome(Result.FAILED, f"compass mask {mask} does not include compass 0")
        with self._lock:
            s = self._session
            pending = (
                s is not None
                and s.status is MagCalStatus.MAG_CAL_SUCCESS
                and s.mode is Mode.MAG
                and not s.accepted
            )
            if s is None or not (s.running or pending):
                return Outcome(Result.ACCEPTED, "no calibration running")
            abort = s.mode is Mode.ONBOARD_MAG and (s.device_started or s.busy)
            self._gen += 1  # results of queued jobs for this session are void now
            s.status = MagCalStatus.MAG_CAL_NOT_STARTED
            s.busy = False
            self._event(
                "calibration.cancelled",
                "Calibration cancelled",
                Severity.NOTICE,
                mode=s.mode.value,
                sensor=s.mode.sensor,
            )
            self._changed.notify_all()
            if abort:
                self._submit(self._job_onboard_abort)
        self._flush()
        return Outcome(Result.ACCEPTED, "calibration cancelled")

    def fixed_yaw(
        self,
        yaw_deg: float,
        *,
        mask: float = 0,
        latitude_deg: float | None = None,
        longitude_deg: float | None = None,
    ) -> Outcome:
        """Offsets from a known yaw and the WMM field (MAV_CMD_FIXED_MAG_CAL_YAW).

        ``yaw_deg`` is the vehicle's true yaw; the position is
        ``latitude_deg``/``longitude_deg`` when given (0, 0 = unset, as the
        MAVLink command says), else the configured field. The unit must be
        still; the last ``fixed_yaw_window_s`` of frames are averaged. The new
        offsets are applied, persisted and written to the device at once.
        """
        if not self._mask_ok(mask):
            return Outcome(Result.FAILED, f"compass mask {mask} does not include compass 0")
        yaw = _number(yaw_deg)
        if yaw is None:
            return Outcome(Result.FAILED, f"yaw {yaw_deg!r} is not a number")
        yaw_deg = yaw
        problem = self._link_problem(need_device=False)
        if problem:
            return Outcome(Result.FAILED, problem)
        ef = self._field
        if latitude_deg is not None or longitude_deg is not None:
            lat, lon = _number(latitude_deg), _number(longitude_deg)
            if lat is None or lon is None:
                return Outcome(Result.FAILED, "bad position: latitude and longitude, in degrees")
            if lat or lon:  # 0, 0 means "use the configured position" (MAVLink's convention)
                try:
                    ef = earth_field(lat, lon)
                except ValueError as e:
                    return Outcome(Result.FAILED, f"bad position: {e}")
        if ef is None:
            return Outcome(Result.FAILED, "no position: set [location] or give one")
        with self._lock:
            denied = self._busy_reason()
            if denied:
                return Outcome(Result.DENIED, denied)
            now = self._clock()
            # list(): feed() appends without the lock (see there).
            rows = [f for t, f in list(self._recent) if t >= now - self.settings.fixed_yaw_window_s]
        still = StillCollector(0.0, self.settings.still_tol_g, min_rows=2)
        for i, f in enumerate(rows):
            mag, acc, sat = counts_to_nominal(f.mx, f.my, f.mz, f.ax, f.ay, f.az)
            still.feed(float(i), mag, acc, sat or bool(f.flags & Flags.SAT))
        if not still.complete:
            return Outcome(Result.FAILED, "no recent frames from the compass")
        if not still.still:
            return Outcome(Result.FAILED, "the unit is moving: hold it still")
        mag_mean, acc_mean, _ = still.means()
        current = self._engine.calibration
        try:
            cal = fixed_yaw_calibration(
                mag_mean, acc_mean, yaw_deg, ef.ned_G, current, self._engine.mounting.matrix()
            )
        except ValueError as e:
            return Outcome(Result.FAILED, f"fixed-yaw calibration failed: {e}")
        report = mag_report(
            cal, CalibrationReport(method="fixed_yaw", n_samples=len(rows)), autosaved=True
        )
        report["yaw_deg"] = float(yaw_deg)
        with self._lock:
            s = self._new_session(Mode.FIXED_YAW, now)
            s.status = MagCalStatus.MAG_CAL_SUCCESS
            s.report = report
            s.accepted = True
            s.percent_done = 100.0
            self._event(
                "calibration.done",
                "Calibration done: mag (fixed yaw)",
                mode=s.mode.value,
                sensor="mag",
                onboard=False,
                report=report,
                autosaved=True,
            )
        self._flush()
        return self._apply(cal, source="fixed_yaw", report=report, write_device=True)

    def apply_calibration(
        self,
        calibration: Calibration,
        *,
        source: str,
        report: dict[str, Any] | None = None,
        write_device: bool = True,
        view: dict[str, float] | None = None,
    ) -> Outcome:
        """Use ``calibration`` from now on: engine, state file and (optionally) the device flash.

        ``view`` is the parameter values a user set it with (stored with it, so they
        read back as written).

        For front ends that set parameters directly (PARAM_SET COMPASS_OFS_X,
        PREFLIGHT_STORAGE reset ...). A failed save keeps the calibration in
        memory and emits ``calibration.storage_error``; the device write runs in
        the worker and reports ``calibration.device_updated`` / ``device_error``.
        """
        return self._apply(
            calibration, source=source, report=report, write_device=write_device, view=view
        )

    # ------------------------------------------------------------------ status

    def snapshot(self) -> CalibratorSnapshot:
        """The current state (thread-safe, cheap)."""
        with self._lock:
            s = self._session
            now_wall = self._wall()
            age = (
                None
                if self._calibration_time is None
                else max(0.0, now_wall - self._calibration_time)
            )
            if s is None:
                return CalibratorSnapshot(
                    mode=None,
                    status=MagCalStatus.MAG_CAL_NOT_STARTED,
                    running=False,
                    attempt=0,
                    completion_pct=0.0,
                    completion_mask=bytes(10),
                    direction=(0.0, 0.0, 0.0),
                    onboard=self._onboard,
                    faces_done=(),
                    last_report=None,
                    pending_accept=False,
                    calibration_source=self._calibration_source,
                    calibration_age_s=age,
                    calibration_saved=self._calibration_saved,
                )
            pct, mask, direction = self._progress_of(s)
            return CalibratorSnapshot(
                mode=s.mode.value,
                status=s.status,
                running=s.running,
                attempt=s.attempt,
                completion_pct=pct,
                completion_mask=mask,
                direction=direction,
                onboard=self._onboard,
                faces_done=tuple(f.px4_side for f in s.faces.means) if s.faces else (),
                last_report=s.report,
                pending_accept=(
                    s.mode is Mode.MAG
                    and s.status is MagCalStatus.MAG_CAL_SUCCESS
                    and not s.accepted
                ),
                calibration_source=self._calibration_source,
                calibration_age_s=age,
                calibration_saved=self._calibration_saved,
            )

    def wait_for(
        self, predicate: Callable[[CalibratorSnapshot], bool], timeout: float
    ) -> CalibratorSnapshot | None:
        """Block until ``predicate(snapshot())`` holds (None after ``timeout`` seconds)."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                snap = self.snapshot()
                if predicate(snap):
                    return snap
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                # Progress does not always notify: wake now and then to re-check.
                self._changed.wait(min(left, 0.1))

    # ------------------------------------------------------------------ internals: sessions

    @staticmethod
    def _mask_ok(mask: float) -> bool:
        """MAVLink carries the mask as a float param: 0 (all) or a byte that includes compass 0."""
        m = _number(mask)
        if m is None or m != int(m) or not 0 <= m <= 255:
            return False
        return int(m) == 0 or bool(int(m) & 1)

    def _link_problem(self, *, need_device: bool) -> str:
        link = self._link
        if link is not None and link.protocol != "gmr":
            return "heading-only compass: it sends no raw vectors to calibrate"
        if need_device and link is None:
            return "no device link for an on-board calibration"
        return ""

    def _busy_reason(self) -> str:
        s = self._session
        if s is not None and (s.running or s.busy):
            return f"a {s.mode.value} calibration is running"
        return ""

    def _new_session(self, mode: Mode, now: float) -> _Session:
        self._gen += 1
        s = _Session(mode=mode, gen=self._gen, started_at=now, start_at=now)
        self._session = s
        self._changed.notify_all()
        self._jobs.put(None)  # wake the worker: it only ticks while a session runs
        return s

    def _new_mag_collector(self, seed: int) -> MagCollector:
        st = self.settings
        return MagCollector(
            st.capacity, seed=seed, judge=MotionJudge(st.motion_limit_g, st.motion_interval_s)
        )

    def _new_tracker(self, params: ParamsFrame | None) -> OnboardMagTracker:
        st = self.settings
        return OnboardMagTracker(
            params,
            min_turn_deg=st.onboard_min_turn_deg,
            settle_reports=st.onboard_settle_reports,
        )

    def _enter_running(self, s: _Session, now: float) -> None:
        s.status = MagCalStatus.MAG_CAL_RUNNING_STEP_ONE
        s.started_at = now
        s.last_frame_at = now
        self._changed.notify_all()
        self._progress_event(s, now)

    def _current(self, gen: int) -> _Session | None:
        s = self._session
        return s if s is not None and s.gen == gen and self._gen == gen else None

    def _progress_of(
        self, s: _Session, *, hint: bool = True
    ) -> tuple[float, bytes, tuple[float, float, float]]:
        """(percent, completion mask, direction hint); ``hint=False`` skips the hint (per frame)."""
        mask = bytes(10)
        direction = (0.0, 0.0, 0.0)
        if s.status is MagCalStatus.MAG_CAL_SUCCESS:
            pct = 100.0
        elif not s.running:
            pct = 0.0
        elif s.mag is not None:
            pct = s.mag.percent
            mask = s.mag.mask
            if hint:
                direction = s.mag.direction_hint()
        elif s.faces is not None:
            pct = s.faces.percent
        elif s.still is not None:
            pct = s.still.percent
        elif s.onboard is not None:
            pct = s.onboard.percent
        else:
            pct = s.percent_done
        if s.running:
            pct = min(pct, 99.0)
        return pct, mask, direction

    def _maybe_progress(self, s: _Session, now: float) -> None:
        if not s.running:
            return
        pct, mask, _ = self._progress_of(s, hint=False)
        key = (s.status, s.attempt, int(pct), mask)
        if key == s.last_progress_key:
            return
        status_changed = not s.last_progress_key or s.last_progress_key[:2] != key[:2]
        if not status_changed and now - s.last_progress_at < self.settings.progress_interval_s:
            return
        self._progress_event(s, now)

    def _progress_event(self, s: _Session, now: float) -> None:
        pct, mask, direction = self._progress_of(s)
        s.last_progress_at = now
        s.last_progress_key = (s.status, s.attempt, int(pct), mask)
        data: dict[str, Any] = {
            "mode": s.mode.value,
            "sensor": s.mode.sensor,
            "compass_id": COMPASS_ID,
            "cal_mask": CAL_MASK,
            "cal_status": s.status.name,
            "cal_status_code": int(s.status),
            "attempt": s.attempt,
            "completion_pct": round(pct, 1),
            "completion_mask": list(mask),
            "direction": list(direction),
        }
        if s.onboard is not None:
            data["spans"] = list(s.onboard.spans)
        if s.faces is not None:
            data["faces_done"] = [f.px4_side for f in s.faces.means]
        self._event("calibration.progress", f"Calibration {pct:.0f}%", **data)

    def _finish_success(
        self, s: _Session, report: dict[str, Any], result: CalibrationResult | None
    ) -> None:
        s.status = MagCalStatus.MAG_CAL_SUCCESS
        s.result = result
        s.report = report
        s.busy = False
        s.percent_done = 100.0
        self._changed.notify_all()
        self._event(
            "calibration.done",
            f"Calibration done: {s.mode.sensor}",
            mode=s.mode.value,
            sensor=s.mode.sensor,
            onboard=s.mode.onboard,
            attempt=s.attempt,
            report=report,
            autosaved=bool(report.get("autosaved", False)),
        )

    def _finish_failed(
        self,
        s: _Session,
        status: MagCalStatus,
        reason: str,
        *,
        report: dict[str, Any] | None = None,
        retry_ok: bool = True,
    ) -> None:
        if s.mode is Mode.MAG and s.retry and retry_ok:
            # ArduPilot's retry: a fresh attempt at once (no start delay after the first).
            s.attempt += 1
            s.mag = self._new_mag_collector(1000 * s.gen + s.attempt)
            s.busy = False
            now = self._clock()
            self._event(
                "calibration.instruction",
                _short(f"Attempt {s.attempt}: keep turning"),
                Severity.WARNING,
                mode=s.mode.value,
                attempt=s.attempt,
                instruction="keep turning the unit through every direction",
                reason=reason,
            )
            self._enter_running(s, now)
            return
        if report is None:
            report = _failure_report(s.mode, status, reason)
        s.status = status
        s.report = report
        s.busy = False
        self._changed.notify_all()
        self._event(
            "calibration.failed",
            _short(f"Calibration failed: {reason}"),
            Severity.ERROR,
            mode=s.mode.value,
            sensor=s.mode.sensor,
            onboard=s.mode.onboard,
            cal_status=status.name,
            cal_status_code=int(status),
            attempt=s.attempt,
            reason=reason,
            report=report,
        )

    def _begin_end(self, s: _Session, *, reason: str) -> None:
        s.ending = True
        s.busy = True
        log.info("on-board calibration: sending MAGCAL,END (%s)", reason)
        self._submit_for(s, self._job_onboard_end)

    # ------------------------------------------------------------------ internals: worker

    def _submit(self, job: Callable[[], None]) -> None:
        self._jobs.put(job)
        self.start()

    def _submit_for(self, s: _Session, fn: Callable[[int], None]) -> None:
        """Queue ``fn(gen)`` for session ``s``; an exception in it fails the session, never hangs it."""
        gen = s.gen

        def run() -> None:
            try:
                fn(gen)
            except Exception as e:
                self._internal_error(getattr(fn, "__name__", "job"))
                with self._lock:
                    cur = self._current(gen)
                    if cur is not None and (cur.running or cur.busy):
                        self._finish_failed(
                            cur, MagCalStatus.MAG_CAL_FAILED, f"internal error: {e}", retry_ok=False
                        )

        self._jobs.put(run)
        self.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            # Time-outs and delayed starts need a tick every 0.1 s while a session runs;
            # otherwise the worker sleeps until a job (or a new session, or close()) comes.
            s = self._session
            try:
                job = self._jobs.get(timeout=0.1 if s is not None and s.running else None)
            except queue.Empty:
                job = None
            if job is None and self._stop.is_set():
                break
            if job is not None:
                try:
                    job()
                except Exception:
                    self._internal_error("worker job")
            try:
                self._tick()
            except Exception:
                self._internal_error("tick")
            self._flush()

    def _tick(self) -> None:
        """Time-outs and delayed starts (worker thread, every 0.1 s)."""
        now = self._clock()
        with self._lock:
            s = self._session
            if s is None or not s.running:
                return
            st = self.settings
            if s.status is MagCalStatus.MAG_CAL_WAITING_TO_START:
                if now >= s.start_at and not s.busy:
                    if s.mode is Mode.MAG:
                        self._enter_running(s, now)
                    elif s.mode is Mode.ONBOARD_MAG:
                        s.busy = True
                        self._submit_for(s, self._job_onboard_start)
                return
            if s.last_frame_at is not None and now - s.last_frame_at > st.no_data_timeout_s:
                self._timeout(s, f"no data from the compass for {st.no_data_timeout_s:g} s")
                return
            if now - s.started_at > st.timeout_s and not s.busy:
                pct, _, _ = self._progress_of(s, hint=False)
                self._timeout(s, f"timed out after {st.timeout_s:g} s at {pct:.0f}%")

    def _timeout(self, s: _Session, reason: str) -> None:
        # As ArduPilot: a time-out is final, retry or not.
        abort = s.mode is Mode.ONBOARD_MAG and s.device_started and not s.ending
        self._gen += 1
        self._finish_failed(s, MagCalStatus.MAG_CAL_FAILED, reason, retry_ok=False)
        if abort:
            self._jobs.put(self._job_onboard_abort)

    # -- host jobs ----------------------------------------------------------------

    def _job_sphere(self, gen: int) -> None:
        with self._lock:
            s = self._current(gen)
            if s is None or s.mag is None:
                return
            samples = s.mag.acceptor.samples
        sph = sphere_step(samples)
        with self._lock:
            s = self._current(gen)
            if s is None or s.mag is None:
                return
            if sph is None:
                self._finish_failed(
                    s, MagCalStatus.MAG_CAL_FAILED_RADIUS, "sphere fit failed (field radius)"
                )
                return
            removed = s.mag.begin_step_two(sph[0], sph[1])
            s.status = MagCalStatus.MAG_CAL_RUNNING_STEP_TWO
            s.busy = False
            log.info(
                "magnetometer calibration: step one done, radius %.0f mG, %d samples thinned",
                1000.0 * sph[1],
                removed,
            )
            self._changed.notify_all()
            self._progress_event(s, self._clock())

    def _job_mag_fit(self, gen: int) -> None:
        with self._lock:
            s = self._current(gen)
            if s is None or s.mag is None:
                return
            mag, acc = s.mag.data()
            t, mag_all, acc_all, sat_all = s.mag.series.arrays()
            ef = self._field
            autosave = s.autosave
        current_accel = self._engine.calibration.accel
        # The current accelerometer calibration sets the tilt, hence the heading at high
        # dip; an uncalibrated (identity) one is better replaced by a fit of the tumble.
        accel = None if _is_identity(current_accel) else current_accel
        # Every frame of the collection, in order: the hand-held fit averages a shake away.
        data = CalibrationData(
            mag_all, acc_all, sat_all, reference=ef, accel_calibration=accel, t_s=t
        )
        res = judge_accuracy(calibrate(BEST, data), self.settings.max_heading_error_deg)
        status = MagCalStatus.parse(res.report.status)
        conf = math.nan
        if status is MagCalStatus.MAG_CAL_SUCCESS:
            conf = orientation_confidence(
                res.calibration.mag.apply(mag), res.calibration.accel.apply(acc)
            )
        report = mag_report(res.calibration, res.report, autosaved=autosave, confidence=conf)
        with self._lock:
            s = self._current(gen)
            if s is None:
                return
            if status is not MagCalStatus.MAG_CAL_SUCCESS:
                reasons = [n for n in res.report.notes if not n.startswith("accelerometer:")]
                self._finish_failed(
                    s, status, reasons[0] if reasons else status.name, report=report
                )
                return
            self._finish_success(s, report, res)
            if autosave:
                s.accepted = True
        self._flush()
        if autosave:
            self._apply(res.calibration, source="mag", report=report, write_device=True)

    def _job_faces_fit(self, gen: int) -> None:
        with self._lock:
            s = self._current(gen)
            if s is None or s.faces is None:
                return
            means = dict(s.faces.means)
        res = fit_six_face(means)
        check = check_accel_calibration(res.calibration.accel) if res.report.ok else None
        current = self._engine.calibration
        new = Calibration(mag=current.mag, accel=res.calibration.accel)
        report = _accel_report(res, means)
        with self._lock:
            s = self._current(gen)
            if s is None:
                return
            if check is None or not check.ok:
                why = (check.reasons if check is not None else res.report.notes) or ("fit failed",)
                self._finish_failed(s, MagCalStatus.MAG_CAL_FAILED, why[0], report=report)
                return
            report["autosaved"] = True
            self._finish_success(s, report, CalibrationResult(new, res.report))
            s.accepted = True
        self._flush()
        self._apply(new, source="accel", report=report, write_device=False)

    def _job_level(self, gen: int) -> None:
        with self._lock:
            s = self._current(gen)
            if s is None or s.still is None:
                return
            _, acc_mean, spread = s.still.means()
        current = self._engine.calibration
        err = ""
        new: Calibration | None = None
        if spread >= self.settings.still_tol_g:
            err = f"the unit moved ({1000.0 * spread:.0f} mg): hold it still"
        else:
            try:
                new = level_trim(acc_mean, current)
            except ValueError as e:
                err = str(e)
        with self._lock:
            s = self._current(gen)
            if s is None:
                return
            if new is None:
                self._finish_failed(s, MagCalStatus.MAG_CAL_FAILED, err)
                return
            roll, pitch = attitude_from_gravity(current.accel.apply(acc_mean))
            report: dict[str, Any] = {
                "cal_status": MagCalStatus.MAG_CAL_SUCCESS.name,
                "cal_status_code": int(MagCalStatus.MAG_CAL_SUCCESS),
                "method": "level_trim",
                "trim_roll_deg": math.degrees(roll),
                "trim_pitch_deg": math.degrees(pitch),
                "accel_spread_mg": 1000.0 * spread,
                "autosaved": True,
            }
            self._finish_success(s, report, CalibrationResult(new, CalibrationReport("level_trim")))
            s.accepted = True
        self._flush()
        self._apply(new, source="level", report=report, write_device=False)

    # -- device jobs ----------------------------------------------------------------

    def _command(self, name: str, *args: object, retries: int = 2) -> Any:
        link = self._link
        if link is None:
            raise CommandError("no device link")
        return link.command(name, *args, retries=retries)

    def _job_onboard_start(self, gen: int) -> None:
        with self._lock:
            if self._current(gen) is None:
                return
        try:
            try:
                self._command("MAGCAL", "START", retries=1)
            except CommandRejected as e:
                if e.reason != "STATE":
                    raise
                # Still in a calibration mode from an earlier run (or our own START whose
                # answer was lost): leave it and start afresh.
                with contextlib.suppress(CommandRejected):
                    self._command("MAGCAL", "ABORT", retries=1)
                self._command("MAGCAL", "START", retries=0)
        except CommandError as e:
            with self._lock:
                s = self._current(gen)
                if s is not None:
                    self._finish_failed(s, MagCalStatus.MAG_CAL_FAILED, _device_reason(e))
            return
        with self._lock:
            s = self._current(gen)
            if s is None:
                # Cancelled while the START was on its way: the device is calibrating now.
                self._jobs.put(self._job_onboard_abort)
                return
            s.device_started = True
            s.busy = False
            now = self._clock()
            self._enter_running(s, now)
            self._event(
                "calibration.instruction",
                INSTRUCTION_LEVEL_TURN,
                mode=s.mode.value,
                step=1,
                instruction=INSTRUCTION_LEVEL_TURN,
            )

    def _job_onboard_end(self, gen: int) -> None:
        with self._lock:
            s = self._current(gen)
            if s is None:
                return
            spans = list(s.onboard.spans) if s.onboard is not None else []
        answer: Any = None
        error: CommandError | None = None
        try:
            # Not resent: a second END after a lost answer would hit ERR,STATE.
            answer = self._command("MAGCAL", "END", retries=0)
        except CommandError as e:
            error = e
        params = self._refresh_params()
        with self._lock:
            s = self._current(gen)
            if s is None:
                return
            if error is not None or not isinstance(answer, AckFrame):
                reason = _device_reason(error) if error is not None else "unexpected answer"
                report = _failure_report(s.mode, MagCalStatus.MAG_CAL_FAILED, reason)
                report["spans"] = spans
                if isinstance(error, CommandRejected):
                    report["device_error"] = error.reason
                self._finish_failed(s, MagCalStatus.MAG_CAL_FAILED, reason, report=report)
                return
            v = answer.values
            device = dict(zip(("xoff", "yoff", "zoff", "kx", "ky", "kz"), v, strict=True))
            report = _onboard_mag_report(device, spans, params)
            self._finish_success(s, report, None)
            s.accepted = True  # the device wrote its flash: nothing left to accept

    def _job_onboard_abort(self) -> None:
        try:
            self._command("MAGCAL", "ABORT", retries=1)
        except CommandRejected as e:
            if e.reason != "STATE":  # STATE: not calibrating any more, which is the goal
                self._device_error(f"MAGCAL,ABORT refused: {e.reason}")
        except CommandError as e:
            self._device_error(f"MAGCAL,ABORT failed: {e}")

    def _job_acccal(self, gen: int) -> None:
        answer: Any = None
        error: CommandError | None = None
        try:
            # ACCCAL is never resent: a second one would average again (or hit ERR,STATE).
            answer = self._command("ACCCAL", retries=0)
        except CommandError as e:
            error = e
        params = self._refresh_params() if error is None else None
        with self._lock:
            s = self._current(gen)
            if s is None:
                return
            if error is not None or not isinstance(answer, AckFrame):
                reason = _device_reason(error) if error is not None else "unexpected answer"
                report = _failure_report(s.mode, MagCalStatus.MAG_CAL_FAILED, reason)
                if isinstance(error, CommandRejected):
                    report["device_error"] = error.reason
                self._finish_failed(s, MagCalStatus.MAG_CAL_FAILED, reason, report=report)
                return
            g = answer.values
            report = {
                "cal_status": MagCalStatus.MAG_CAL_SUCCESS.name,
                "cal_status_code": int(MagCalStatus.MAG_CAL_SUCCESS),
                "method": "device ACCCAL",
                "gxoff": g[0],
                "gyoff": g[1],
                "gzoff": g[2],
                "device_params": _params_dict(params),
                "autosaved": True,
            }
            self._finish_success(s, report, None)
            s.accepted = True

    def _refresh_params(self) -> ParamsFrame | None:
        """PAR,GET so the link (and everyone reading ``link.params``) sees the new flash."""
        try:
            p = self._command("PAR", "GET")
        except CommandError as e:
            self._device_error(f"PAR,GET failed: {e}")
            return None
        return p if isinstance(p, ParamsFrame) else None

    def _job_write_device(self, cal: Calibration) -> None:
        """PAR,SET the magnetometer part of a host calibration, keeping the device's level reference."""
        try:
            wanted = device_params_for(cal.mag)
        except ValueError as e:
            self._device_error(f"the compass cannot hold this calibration: {e}")
            return
        try:
            current = self._command("PAR", "GET")
            if not isinstance(current, ParamsFrame):
                raise CommandError("PAR,GET gave no parameters")
            cmd = CommandFrame.par_set(wanted.with_level_reference(current))
            self._command(cmd.command, *cmd.args)
            after = self._command("PAR", "GET")
        except CommandRejected as e:
            why = "the compass is calibrating" if e.reason == "STATE" else e.reason
            self._device_error(f"PAR,SET refused: {why}")
            return
        except (CommandError, ValueError) as e:
            self._device_error(f"PAR,SET failed: {e}")
            return
        with self._lock:
            self._event(
                "calibration.device_updated",
                "Compass flash updated",
                params=_params_dict(after if isinstance(after, ParamsFrame) else None),
                written=wanted.to_dict(),
            )

    def _device_error(self, message: str) -> None:
        log.warning("calibration: %s", message)
        with self._lock:
            self._event(
                "calibration.device_error",
                _short(f"Compass flash: {message}"),
                Severity.WARNING,
                error=message,
            )

    # -- applying -----------------------------------------------------------------

    def _apply(
        self,
        cal: Calibration,
        *,
        source: str,
        report: dict[str, Any] | None,
        write_device: bool,
        view: dict[str, float] | None = None,
    ) -> Outcome:
        self._engine.update_calibration(cal)
        now = self._wall()
        saved = True
        error = ""
        if self._store is not None:
            try:
                self._store.save(cal, source=source, accepted_unix=now, report=report, view=view)
            except StorageError as e:
                saved, error = False, str(e)
        else:
            saved, error = False, "no state directory configured"
        with self._lock:
            self._calibration_source = source
            self._calibration_time = now
            self._calibration_saved = saved
            if saved:
                self._event(
                    "calibration.accepted",
                    "Calibration accepted and saved",
                    source=source,
                    saved=True,
                )
            else:
                self._event(
                    "calibration.accepted",
                    "Calibration applied, NOT saved",
                    Severity.WARNING,
                    source=source,
                    saved=False,
                    error=error,
                )
                if self._store is not None:
                    self._event(
                        "calibration.storage_error",
                        _short(f"Calibration not saved: {error}"),
                        Severity.ERROR,
                        error=error,
                    )
            self._changed.notify_all()
        if write_device and self._link is not None and self._link.protocol == "gmr":
            self._submit(lambda: self._job_write_device(cal))
        self._flush()
        if saved:
            return Outcome(Result.ACCEPTED, "calibration applied and saved")
        return Outcome(Result.ACCEPTED, f"calibration applied but not saved: {error}")

    # -- events -------------------------------------------------------------------

    def _event(self, kind: str, text: str, severity: Severity = Severity.INFO, **data: Any) -> None:
        """Queue an event (lock held); :meth:`_flush` delivers it."""
        with self._lock:
            self._pending.append(Event(kind, _short(text), severity, data))

    def _flush(self) -> None:
        if not self._pending:  # unlocked peek: an event queued meanwhile goes with the next flush
            return
        with self._emit_lock:
            with self._lock:
                events, self._pending = self._pending, []
            for e in events:
                self._bus.emit(e)

    def _internal_error(self, where: str) -> None:
        self.errors += 1
        if self.errors == 1:
            log.exception("calibration %s failed (further failures are only counted)", where)


# ---------------------------------------------------------------------------
# report helpers
# ---------------------------------------------------------------------------


def _number(v: object) -> float | None:
    """``v`` as a finite float, or None (bools, strings, NaN and infinities are not numbers here)."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def _device_reason(e: CommandError | None) -> str:
    if isinstance(e, CommandRejected):
        text = {
            "RANGE": "too little rotation (RANGE)",
            "MOTION": "the unit moved (MOTION)",
            "STATE": "the compass is busy (STATE)",
            "FLASH": "flash write failed (FLASH)",
        }.get(e.reason, e.reason)
        return f"{e.command}: {text}"
    if isinstance(e, CommandTimeout):
        return f"no answer from the compass ({e})"
    return f"device command failed: {e}"


def _params_dict(p: ParamsFrame | None) -> dict[str, float] | None:
    if p is None:
        return None
    names = ("xoff", "yoff", "zoff", "kx", "ky", "kz", "gxoff", "gyoff", "gzoff")
    return dict(zip(names, p.values(), strict=True))


def _failure_report(mode: Mode, status: MagCalStatus, reason: str) -> dict[str, Any]:
    """A failure in MAG_CAL_REPORT shape (identity parameters) plus the reason."""
    rep = mag_report(
        Calibration(), CalibrationReport(method=mode.value, status=status.name, notes=(reason,))
    )
    rep["reason"] = reason
    return rep


def _onboard_mag_report(
    device: dict[str, float], spans: list[int], params: ParamsFrame | None
) -> dict[str, Any]:
    """The device's MAGCAL,END result in MAG_CAL_REPORT shape (the device computes no fitness)."""
    page = ParamsFrame(
        device["xoff"],
        device["yoff"],
        device["zoff"],
        device["kx"],
        device["ky"],
        device["kz"],
        *(params.values()[6:] if params is not None else ParamsFrame.factory().values()[6:]),
    )
    view = device_calibration_view(page)
    rep = mag_report(
        Calibration(),
        CalibrationReport(method="device MAGCAL", status="MAG_CAL_SUCCESS"),
        autosaved=True,
    )
    rep.update(view)
    rep.update({"device": device, "spans": spans, "device_params": _params_dict(params)})
    return rep


def _accel_report(res: CalibrationResult, means: dict[Face, Any]) -> dict[str, Any]:
    cal = res.calibration.accel
    return {
        "cal_status": res.report.status,
        "cal_status_code": int(MagCalStatus.parse(res.report.status)),
        "method": res.report.method,
        "offset_g": list(cal.offset),
        "matrix": [list(r) for r in cal.matrix],
        "gravity_spread_before_mg": _nan_none(res.report.gravity_spread_before_mg),
        "gravity_spread_after_mg": _nan_none(res.report.gravity_spread_after_mg),
        "faces": {f.px4_side: [float(x) for x in np.asarray(v).tolist()] for f, v in means.items()},
        "notes": list(res.report.notes),
        "autosaved": False,
    }


def _nan_none(v: float) -> float | None:
    return v if math.isfinite(v) else None
