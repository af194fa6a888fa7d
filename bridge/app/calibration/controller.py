"""CalibrationController: the runner behind every calibration front end.

MAVLink (ArduPilot's MAV_CMD_DO_START/ACCEPT/CANCEL_MAG_CAL, PX4's
MAV_CMD_PREFLIGHT_CALIBRATION), the zenoh ``cmd/calibration/*`` queryables and
the CLI all drive this one object; it answers each command with an
:class:`~bridge.calibration.sessions.state.Outcome` and reports everything else as
:class:`~bridge.events.Event` on the bus (kinds in
:data:`~bridge.calibration.sessions.base.EVENT_KINDS`), which
each front end maps to its wire format. :meth:`CalibrationController.snapshot`
serves status queries.

The calibration itself is a pure session per mode
(:mod:`bridge.calibration.sessions.base`: frames and ticks in, actions out); this
class only runs them: it holds the lock, feeds the session, and carries out
what it returns -- events to the bus, fits and device commands in its worker
thread, results into the engine, the calibration store and the compass flash.

Threads:

* the daemon's **pipeline** (in the link's reader thread) calls :meth:`~CalibrationController.feed`
  for every frame -- O(1) when idle, a few tens of microseconds while
  collecting; it never waits for a fit or a device command;
* one **worker thread** runs fits, persistence and device commands
  (``MAGCAL``, ``ACCCAL``, ``PAR``) in order and ticks the session every 0.1 s;
* front ends call the command methods from their own threads.

One lock guards the session; events are queued under it and delivered after
it is released, in order, so a subscriber may call back into the controller
(by whichever thread is delivering: a command never waits for another thread's
delivery).

Routes: ``onboard`` (the BRG_CAL_ONBOARD parameter) sends magnetometer and level
calibrations to the compass's own ``MAGCAL`` and ``ACCCAL``; the accelerometer's six
faces and fixed yaw are the host's either way (docs/calibration.md, "Sessions").
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

from bridge.app.calibration.flash import write_calibration
from bridge.app.calibration.keeper import (
    CalibrationKeeper,
    StrayCalibration,
    applied,
    storage_error,
)
from bridge.app.calibration.store import CalibrationStore
from bridge.calibration.sessions.base import (
    Action,
    Apply,
    Compute,
    Device,
    Emit,
    FitContext,
    Job,
    Session,
)
from bridge.calibration.sessions.host import (
    FaceSession,
    FixedYawSession,
    LevelSession,
    MagSession,
    fixed_yaw_inputs,
    fixed_yaw_result,
)
from bridge.calibration.sessions.onboard import OnboardLevelSession, OnboardMagSession
from bridge.calibration.sessions.report import SessionReport
from bridge.calibration.sessions.snapshot import CalibrationTarget, CalibratorSnapshot
from bridge.calibration.sessions.state import (
    CalibratorSettings,
    Mode,
    Outcome,
    Result,
    mask_refusal,
    number,
)
from bridge.core.calibration import Calibration
from bridge.core.wmm import EarthField
from bridge.documents import DocumentStore
from bridge.events import ChangeRefusedError, Event, EventBus, Severity
from bridge.protocol.device import CommandError, DevicePort
from bridge.protocol.gmr import AttitudeFrame, CalProgressFrame, Flags

log = logging.getLogger(__name__)

_CAL = int(Flags.CAL)


class CalibrationController:
    """Runs the calibration sessions (see the module docstring).

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
        self._fitness_limit = self.settings.fitness_max_mG
        self._clock = clock
        self._wall = wall_clock
        self._lock = threading.RLock()
        self._emit_lock = threading.RLock()
        self._pending: list[Event] = []
        self._session: Session | None = None
        self._sessions = 0
        self._recent: deque[tuple[float, AttitudeFrame]] = deque(maxlen=256)
        self._jobs: queue.Queue[Callable[[], None] | None] = queue.Queue()
        self._worker: threading.Thread | None = None
        self._inline = False  # the owner of the clock runs the jobs (step), no worker
        self._stop = threading.Event()
        self.errors = 0  #: unexpected exceptions caught (logged once)
        self._keeper = CalibrationKeeper(self._store, calibration_source)
        self._stray = StrayCalibration()

    # ------------------------------------------------------------------ lifecycle

    def use_device(self, link: DevicePort) -> None:
        """Run device commands over ``link`` (built after this controller: it feeds it frames)."""
        self._link = link

    def start(self) -> CalibrationController:
        """Start the worker thread (idempotent; commands also start it)."""
        with self._lock:
            if self._worker is None and not self._stop.is_set() and not self._inline:
                self._worker = threading.Thread(
                    target=self._run, name="calibration-worker", daemon=True
                )
                self._worker.start()
        return self

    def close(self, timeout: float = 2.0) -> None:
        """Stop the worker within about ``timeout`` s; a device MAGCAL in progress is aborted."""
        with self._lock:
            s = self._session
            aborts = s.shutdown() if s is not None else []
            if not aborts and self._stray.calibrating(self._clock()):
                aborts = [Device("MAGCAL", ("ABORT",), retries=0, purpose="abort")]
        if self._link is not None:
            for d in aborts:
                # Leaving the device in calibration mode would stop its own heading from
                # improving and refuse PAR,SET; the link may already be closed (then it is moot).
                with contextlib.suppress(CommandError, ValueError):
                    self._link.command(d.command, *d.args, retries=0)
        self._stop.set()
        self._jobs.put(None)
        w = self._worker
        if w is not None and w is not threading.current_thread():
            w.join(timeout)
            if w.is_alive():
                log.error("calibration worker did not stop within %.1f s", timeout)
        self._keeper.flush(self._clock())  # a paced save still to come

    def run_inline(self) -> None:
        """No worker thread: the owner of the clock (a simulation) calls :meth:`step`."""
        self._inline = True

    def step(self) -> None:
        """What the worker does, in this thread: the queued jobs, a tick after each."""
        jobs = []
        while not self._jobs.empty():
            jobs.append(self._jobs.get_nowait())
        for job in jobs or [None]:
            self._work(job)

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

    @property
    def fitness_limit_mG(self) -> float:
        """The largest fitness a host magnetometer fit may have (COMPASS_CAL_FIT, mG).

        A session takes the value it starts with (as ArduPilot); the application
        sets it whenever the parameter changes. Not finite or not positive:
        ``ValueError``.
        """
        return self._fitness_limit

    @fitness_limit_mG.setter
    def fitness_limit_mG(self, value: float) -> None:
        v = number(value)
        if v is None or v <= 0.0:
            raise ValueError(f"fitness limit must be positive and finite, got {value!r}")
        self._fitness_limit = v

    def set_field(self, field: EarthField | None) -> None:
        """The local Earth field (WMM at the vehicle's position), e.g. when the position changes."""
        with self._lock:
            self._field = field

    @property
    def field(self) -> EarthField | None:
        """The Earth field fits are scaled to."""
        return self._field

    def calibrating(self) -> bool:
        """A session is waiting, collecting or fitting (a cheap, lock-free read for the pipeline)."""
        s = self._session
        return s is not None and s.running

    # ------------------------------------------------------------------ the per-frame hook

    def feed(self, frame: object, t: float | None = None) -> None:
        """Hand over one received frame (any type), sampled at ``t`` (None: now); called from
        the pipeline (the link's reader thread), which gives its frame clock's instant: frames
        read together must not look sampled together to the series fits.

        ``$PGMRA`` frames feed the running session (and a short history kept for the
        fixed-yaw calibration); ``$PGMRC`` frames the device's MAGCAL progress. Anything
        else is ignored. Never blocks on fits or commands, never raises."""
        now = self._clock() if t is None else t
        if type(frame) is AttitudeFrame:
            s = self._session
            if int(frame.flags) & _CAL or self._stray.last_cal_at > -math.inf:
                self._watch_stray(frame, s)
            if s is None or not s.running:
                # Nearly every frame: no session collects. Only the fixed-yaw history
                # wants it, and that needs no lock: deque.append is atomic, and
                # fixed_yaw copies the deque (list(), one step under the GIL) before it
                # iterates. A session that starts meanwhile begins with the next frame,
                # as if this one had come a moment earlier.
                self._recent.append((now, frame))
                if self._pending:
                    self._flush()
                return
        elif not isinstance(frame, AttitudeFrame | CalProgressFrame):
            return
        try:
            with self._lock:
                if isinstance(frame, AttitudeFrame):
                    self._recent.append((now, frame))
                s = self._session
                applies = self._queue(s, s.feed(frame, now)) if s is not None else []
            self._after(applies)
        except Exception:
            self._internal_error("feed")
        self._flush()

    def _watch_stray(self, frame: AttitudeFrame, s: Session | None) -> None:
        """The CAL flag with no MAGCAL of ours: the device was left calibrating; abort it."""
        ours = s is not None and s.mode is Mode.ONBOARD_MAG and (s.running or s.busy)
        if self._stray.frame(bool(int(frame.flags) & _CAL), ours, self._clock()):
            self._jobs.put(functools.partial(self._stray.abort, self._command))
            self.start()

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
        if (refused := mask_refusal(mask)) is not None:
            return refused
        delay = number(delay_s)
        if delay is None or not 0.0 <= delay <= 3600.0:
            return Outcome(Result.FAILED, f"delay {delay_s!r} s outside 0-3600")
        use_onboard = self._onboard if onboard is None else bool(onboard)

        def make(now: float) -> Session:
            if use_onboard:
                params = self._link.params if self._link is not None else None
                return OnboardMagSession(
                    self.settings, now, params=params, delay_s=delay, retry=bool(retry)
                )
            return MagSession(
                self.settings,
                now,
                retry=bool(retry),
                autosave=bool(autosave),
                delay_s=delay,
                fitness_limit_mG=self._fitness_limit,
                seed=self._sessions + 1,
            )

        return self._start(make, need_device=use_onboard)

    def start_accel(self) -> Outcome:
        """Start the six-face accelerometer calibration (PX4 param5=1; host only)."""
        return self._start(lambda now: FaceSession(self.settings, now), need_device=False)

    def start_level(self, *, onboard: bool | None = None) -> Outcome:
        """Start a level calibration (PX4 param5=2): host level trim, or the device's ACCCAL."""
        use_onboard = self._onboard if onboard is None else bool(onboard)
        kind = OnboardLevelSession if use_onboard else LevelSession
        return self._start(lambda now: kind(self.settings, now), need_device=use_onboard)

    def accept(self, mask: float = 0) -> Outcome:
        """Accept the result (MAV_CMD_DO_ACCEPT_MAG_CAL).

        A successful host fit is applied, persisted and written to the device;
        a running on-board MAGCAL is ended now (``MAGCAL,END``). With nothing
        to accept the answer is ACCEPTED (as ArduPilot does); after a failure
        it is FAILED.
        """
        if (refused := mask_refusal(mask)) is not None:
            return refused
        with self._lock:
            s = self._session
            if s is None:
                return Outcome(Result.ACCEPTED, "no calibration to accept")
            outcome, actions = s.accept()
            applies = self._queue(s, actions)
        applied = self._after(applies)
        return applied if applied is not None else outcome

    def cancel(self, mask: float = 0) -> Outcome:
        """Cancel (MAV_CMD_DO_CANCEL_MAG_CAL); ACCEPTED even when idle (QGC probes with it).

        A pending (unaccepted) host result is discarded; a device MAGCAL is
        aborted (``MAGCAL,ABORT``, flash unchanged). A device ACCCAL already
        averaging cannot be stopped: its result is ignored.
        """
        if (refused := mask_refusal(mask)) is not None:
            return refused
        with self._lock:
            s = self._session
            actions = s.cancel() if s is not None else None
            if s is None or actions is None:
                return Outcome(Result.ACCEPTED, "no calibration running")
            applies = self._queue(s, actions)
        self._after(applies)
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
        MAVLink command says), else the configured field. Every input and the
        result are checked for plausibility (:func:`~bridge.calibration.sessions.host.fixed_yaw_inputs`).
        The unit must be still; the last ``fixed_yaw_window_s`` of frames are
        averaged. The new offsets are applied, persisted and written to the
        device at once.
        """
        if (refused := mask_refusal(mask)) is not None:
            return refused
        problem = self._link_problem(need_device=False)
        inputs = problem or fixed_yaw_inputs(yaw_deg, self._field, latitude_deg, longitude_deg)
        if isinstance(inputs, str):
            return Outcome(Result.FAILED, inputs)
        yaw, ef = inputs
        with self._lock:
            denied = self._busy_reason()
            if denied:
                return Outcome(Result.DENIED, denied)
            now = self._clock()
            # list(): feed() appends without the lock (see there).
            window = now - self.settings.fixed_yaw_window_s
            rows = [f for t, f in list(self._recent) if t >= window]
            done = fixed_yaw_result(
                rows,
                yaw,
                ef.ned_G,
                self._engine.calibration,
                self._engine.mounting.matrix(),
                self.settings.still_tol_g,
            )
            if isinstance(done, str):
                return Outcome(Result.FAILED, done)
            applies = self._install(FixedYawSession(self.settings, now, *done), now)
        applied = self._after(applies)
        assert applied is not None
        return applied

    def apply_calibration(
        self,
        calibration: Calibration,
        *,
        source: str,
        report: SessionReport | Mapping[str, Any] | None = None,
        write_device: bool = True,
        view: dict[str, float] | None = None,
        paced: bool = False,
    ) -> Outcome:
        """Use ``calibration`` from now on: engine, state file and (optionally) the device flash.

        ``report`` is stored with it (a :class:`SessionReport`, or its JSON form);
        ``view`` is the parameter values a user set it with (stored with it, so they
        read back as written); ``paced``: set value by value, its save paced
        (:mod:`~bridge.app.calibration.keeper`).

        For front ends that set parameters directly (PARAM_SET COMPASS_OFS_X,
        PREFLIGHT_STORAGE reset ...). A failed save keeps the calibration in
        memory and emits ``calibration.storage_error``; the device write runs in
        the worker and reports ``calibration.device_updated`` / ``device_error``.
        """
        if isinstance(report, SessionReport):
            report = report.to_dict()
        return self._apply(
            calibration, source=source, report=report, write_device=write_device, view=view,
            paced=paced,
        )  # fmt: skip

    # ------------------------------------------------------------------ status

    def snapshot(self) -> CalibratorSnapshot:
        """The current state (thread-safe, cheap)."""
        with self._lock:
            k = self._keeper
            age = None if k.accepted_unix is None else max(0.0, self._wall() - k.accepted_unix)
            return CalibratorSnapshot.of(
                self._session,
                onboard=self._onboard,
                calibration_source=k.source,
                calibration_age_s=age,
                calibration_saved=k.saved,
                calibration_saving=k.paced,
                calibration_save_error=k.error,
            )

    # ------------------------------------------------------------------ running sessions

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

    def _start(self, make: Callable[[float], Session], *, need_device: bool) -> Outcome:
        problem = self._link_problem(need_device=need_device)
        if problem:
            return Outcome(Result.FAILED, problem)
        with self._lock:
            denied = self._busy_reason()
            if denied:
                return Outcome(Result.DENIED, denied)
            now = self._clock()
            session = make(now)
            applies = self._install(session, now)
        self._after(applies)
        self.start()
        return Outcome(Result.IN_PROGRESS, f"{session.mode.value} calibration started")

    def _install(self, session: Session, now: float) -> list[Apply]:
        """``session`` is the current one from now on (lock held)."""
        self._sessions += 1
        self._session = session
        self._jobs.put(None)  # wake the worker: it only ticks while a session runs
        return self._queue(session, session.begin(now))

    def _queue(self, session: Session, actions: list[Action]) -> list[Apply]:
        """Carry out what ``session`` asked for (lock held): events are queued, jobs go to
        the worker; the calibrations to apply are returned (applied without the lock)."""
        applies: list[Apply] = []
        for a in actions:
            if isinstance(a, Emit):
                self._pending.append(Event(a.kind, a.text, a.severity, dict(a.data)))
            elif isinstance(a, Apply):
                applies.append(a)
            else:
                self._jobs.put(functools.partial(self._run_job, session, a))
                self.start()
        return applies

    def _after(self, applies: list[Apply]) -> Outcome | None:
        """Apply (lock released), then deliver the queued events; the last apply's outcome."""
        outcome = None
        for a in applies:
            report = a.report.to_dict() if a.report is not None else None
            outcome = self._apply(
                a.calibration, source=a.source, report=report, write_device=a.write_device
            )
        self._flush()  # after: an autosaved fit is in use before its report says so
        return outcome

    def _run_job(self, session: Session, job: Job) -> None:
        """Worker: one fit or device command, its value back to the session that asked."""
        value: Any
        try:
            if isinstance(job, Compute):
                value = job.fn(FitContext(self._engine.calibration, self._field))
            else:
                value = self._device(job)
        except Exception as e:
            self._internal_error(job.what if isinstance(job, Compute) else job.command)
            with self._lock:
                applies = self._queue(session, session.crashed(job, e, self._clock()))
        else:
            with self._lock:
                applies = self._queue(session, session.resolve(job, value, self._clock()))
        self._after(applies)

    def _device(self, job: Device) -> object:
        """A device command's answer, or the ``CommandError`` it failed with."""
        try:
            return self._command(job.command, *job.args, retries=job.retries)
        except CommandError as e:
            return e

    def _command(self, name: str, *args: object, retries: int = 2) -> Any:
        link = self._link
        if link is None:
            raise CommandError("no device link")
        return link.command(name, *args, retries=retries)

    def _run(self) -> None:
        while not self._stop.is_set():
            # Time-outs and delayed starts need a tick every 0.1 s while a session runs;
            # otherwise the worker sleeps until a job (or a new session, or close()) comes.
            s = self._session
            wait = self._keeper.retry_due(self._clock()) - self._clock()  # an unsaved one
            if s is not None and s.running:
                wait = min(wait, 0.1)
            try:
                job = self._jobs.get(timeout=max(0.0, wait) if wait < math.inf else None)
            except queue.Empty:
                job = None
            if job is None and self._stop.is_set():
                break
            self._work(job)

    def _work(self, job: Callable[[], None] | None) -> None:
        """One job (if any), then the tick and a save retry; events delivered."""
        if job is not None:
            try:
                job()
            except Exception:
                self._internal_error("worker job")
        try:
            self._tick()
            self._retry_save()
        except Exception:
            self._internal_error("tick")
        self._flush()

    def _tick(self) -> None:
        """Time-outs and delayed starts (worker thread, every 0.1 s)."""
        with self._lock:
            s = self._session
            if s is None or not s.running:
                return
            applies = self._queue(s, s.tick(self._clock()))
        self._after(applies)

    def _retry_save(self) -> None:
        """Worker: a calibration in use that could not be saved, saved once storage takes it;
        a paced one saved when its second is over (refused: said, as at once)."""
        k = self._keeper
        paced = k.paced
        if k.pending and k.retry(self._clock()):
            text = "Calibration saved (storage is back)"
            self._emit(Emit("calibration.saved", text, Severity.NOTICE, {"source": k.source}))
        elif paced and k.error:
            with self._lock:
                self._pending.append(storage_error(k.error))

    # ------------------------------------------------------------------ applying

    def _apply(
        self,
        cal: Calibration,
        *,
        source: str,
        report: Mapping[str, Any] | None,
        write_device: bool,
        view: dict[str, float] | None = None,
        paced: bool = False,
    ) -> Outcome:
        try:
            self._engine.update_calibration(cal)
        except ChangeRefusedError as e:  # a guard of the heading (an armed autopilot fed by us)
            return Outcome(Result.DENIED, str(e))
        k = self._keeper
        error = k.keep(
            cal, source=source, accepted_unix=self._wall(), report=report, view=view,
            now=self._clock(), paced=paced,
        )  # fmt: skip
        events, said = applied(source, error, k.paced, stored=self._store is not None)
        with self._lock:
            self._pending += events
        if write_device and self._link is not None and self._link.protocol == "gmr":
            self._jobs.put(functools.partial(self._write_device, cal))
            self.start()
        elif k.pending:
            self._jobs.put(None)  # wake the worker: the save is due later (paced, or refused)
        self._flush()
        return Outcome(Result.ACCEPTED, said)

    def _write_device(self, cal: Calibration) -> None:
        """Worker: the magnetometer part of a host calibration into the compass flash."""
        self._emit(write_calibration(self._command, cal))

    # ------------------------------------------------------------------ events

    def _emit(self, e: Emit) -> None:
        with self._lock:
            self._pending.append(Event(e.kind, e.text, e.severity, dict(e.data)))
        self._flush()

    def _flush(self) -> None:
        """Deliver the queued events, in order; never waits for another thread's delivery.

        A thread that finds another one delivering leaves its events to it: a subscriber
        may take its own lock (the MAVLink adapter's pending acks) while a command holding
        that lock calls in here, and waiting would deadlock the two.
        """
        if not self._pending:  # unlocked peek: an event queued meanwhile goes with the next flush
            return
        while self._emit_lock.acquire(blocking=False):
            try:
                while True:
                    with self._lock:
                        events, self._pending = self._pending, []
                    if not events:
                        break
                    for e in events:
                        self._bus.emit(e)
            finally:
                self._emit_lock.release()
            if not self._pending:  # nothing slipped in after the last look
                return

    def _internal_error(self, where: str) -> None:
        self.errors += 1
        if self.errors == 1:
            log.exception("calibration %s failed (further failures are only counted)", where)
