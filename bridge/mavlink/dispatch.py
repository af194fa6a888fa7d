"""Commands from ground stations: COMMAND_LONG / COMMAND_INT handlers, and the autopilot's position.

Each handler answers with a MAV_RESULT (the dispatcher sends the COMMAND_ACK)
or sends its own answer and returns None. Long work (an accept that writes the
compass flash, PREFLIGHT_STORAGE's flash write) is answered IN_PROGRESS and
finished by the event that reports its outcome (:class:`PendingAcks`).

Command parameters arrive as floats. A NaN in a parameter means "not given"
(MAVSDK fills unused parameters with NaN for non-ArduPilot autopilots), and
integer parameters are read as ArduPilot and PX4 read them: truncated
(:func:`int_param`); yes/no parameters as ArduPilot reads them (:func:`flag_param`);
compass masks as ArduPilot checks them (:func:`_mask`: outside 0..255 is FAILED).
docs/mavlink.md has the rules and their sources.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

from bridge import __version__
from bridge.app.sample import CompassSample
from bridge.app.services import BridgeServices
from bridge.calibration.sessions import CalibratorSnapshot, Outcome, Result
from bridge.core.calibration import Calibration
from bridge.events import ChangeRefusedError, Event, Severity
from bridge.mavlink import calmap
from bridge.mavlink import commands as C  # noqa: N812 - short
from bridge.mavlink import schedule as S  # noqa: N812 - short
from bridge.mavlink import telemetry as T  # noqa: N812 - short
from bridge.mavlink.autopilot import AutopilotWatch
from bridge.mavlink.dialect import Message
from bridge.mavlink.endpoints import Link
from bridge.mavlink.paramproto import ParamProtocol
from bridge.protocol.device import LinkState

log = logging.getLogger(__name__)

FINAL_ACK_TIMEOUT_S = 5.0
_POSITION_MIN_S = 10.0  # autopilot position: at most one WMM update per this long ...
_POSITION_MOVE_DEG = 0.01  # ... unless the vehicle moved further than this
#: Fastest MESSAGE_INTERVAL a stream may be given: the compass's fastest frame rate.
MIN_INTERVAL_US = 10_000
#: Slowest: MESSAGE_INTERVAL.interval_us is an int32 (about 35 minutes).
MAX_INTERVAL_US = 2**31 - 1


def given(v: float) -> bool:
    """A command parameter that carries a value (NaN means "not given")."""
    return not math.isnan(v)


def int_param(v: float, default: int = 0) -> int | None:
    """An integer command parameter as ArduPilot and PX4 read it: C-cast, truncated toward
    zero (``(uint8_t)packet.param1``, ``(int)cmd.param1``).

    NaN is "not given" (``default``), where C would be undefined; infinities and
    values outside 32 bits are refused (None).
    """
    if math.isnan(v):
        return default
    if not math.isfinite(v) or abs(v) >= 2**31:
        return None
    return int(v)


def flag_param(v: float) -> bool:
    """A yes/no command parameter as ArduPilot reads it (``!is_zero(param)``); NaN is no."""
    return not math.isnan(v) and v != 0.0


def _mask(v: float) -> int | None:
    """A compass mask as ArduPilot reads it: None (answered FAILED) unless 0 <= v <= 255,
    then the uint8 C-cast (``handle_mag_cal_command``); NaN is "not given", all compasses."""
    if math.isnan(v):
        return 0
    if not 0.0 <= v <= 255.0:
        return None
    return int(v)


@dataclass(slots=True)
class _PendingAck:
    """A command answered IN_PROGRESS, waiting for its final COMMAND_ACK."""

    command: int
    link: Link
    system: int
    component: int
    kinds: tuple[str, ...]  #: event kinds that end it
    failure_kinds: tuple[str, ...]
    deadline: float
    announced: bool = False  #: the IN_PROGRESS ack is out
    final: int | None = None  #: FAILED: an outcome that failed before the IN_PROGRESS ack
    #: Outcomes still to come; counted down from zero while the work runs (an outcome can
    #: come before the work has said how many it started), up when it has said.
    parts: int = 0


class PendingAcks:
    """Commands answered IN_PROGRESS whose final ACK an event (or a time-out) brings.

    The lock is held only to look at the list and send (a non-blocking hand-off),
    never while the work runs: the work calls into the calibration controller, whose
    events come back here from its own threads.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self.lock = threading.Lock()
        self._pending: list[_PendingAck] = []

    def long_work(
        self,
        cmd: C.Command,
        link: Link,
        work: Callable[[Callable[[bool], None]], int],
        kinds: tuple[str, ...],
        failures: tuple[str, ...],
    ) -> bool:
        """Run ``work``; if it returns a count of outcomes still to come, the command is long
        work: IN_PROGRESS now, and the final COMMAND_ACK when they have all come -- ACCEPTED,
        or FAILED at the first that failed, or FAILED after a time-out. An outcome is an
        event of ``kinds`` (or ``failures``), or a call of the ``done(ok)`` handed to the
        work (any thread: a write another thread finishes). Registered *before* the work
        starts, so an outcome that comes at once is not missed; the final ack then follows
        the IN_PROGRESS one, so the two always go out in that order. ``work`` returning 0
        answered nothing: the caller answers.
        """
        pending = _PendingAck(
            cmd.command,
            link,
            cmd.source_system,
            cmd.source_component,
            kinds,
            failures,
            self._clock() + FINAL_ACK_TIMEOUT_S,
        )
        with self.lock:
            self._pending.append(pending)
        parts = 0
        try:
            parts = work(lambda ok: self._outcome(pending, ok))
        finally:
            with self.lock:
                if parts <= 0:
                    if pending in self._pending:
                        self._pending.remove(pending)
                else:
                    link.send(
                        T.command_ack(
                            cmd.command, C.IN_PROGRESS, cmd.source_system, cmd.source_component
                        )
                    )
                    pending.announced = True
                    pending.parts += parts
                    self._finish_if_done(pending)  # the outcomes came during the work
        return parts > 0

    def _outcome(self, p: _PendingAck, ok: bool) -> None:
        """One of ``p``'s outcomes came (any thread)."""
        with self.lock:
            if p not in self._pending or p.final is not None:
                return
            if ok:
                p.parts -= 1
            else:
                p.final = C.FAILED
            self._finish_if_done(p)

    def _finish_if_done(self, p: _PendingAck) -> None:
        """Send ``p``'s final ack if it is announced and its outcome known (lock held)."""
        if not p.announced or (p.final is None and p.parts > 0):
            return
        self._pending.remove(p)
        p.link.send(
            T.command_ack(
                p.command, C.ACCEPTED if p.final is None else p.final, p.system, p.component,
                progress=100,
            )
        )  # fmt: skip

    def on_event(self, event: Event) -> None:
        """Count ``event`` as an outcome of the commands that wait for its kind (any thread)."""
        with self.lock:
            waiting = [p for p in self._pending if p.final is None]
        for p in waiting:
            if event.kind in p.failure_kinds:
                self._outcome(p, False)
            elif event.kind in p.kinds:
                self._outcome(p, True)

    @property
    def due_at(self) -> float:
        """The earliest deadline of a command answered IN_PROGRESS (+inf: none waits).

        A command is announced, and its deadline set, at most a second before the
        telemetry thread next plans (its HEARTBEAT): FINAL_ACK_TIMEOUT_S is far longer.
        """
        with self.lock:
            return min((p.deadline for p in self._pending if p.announced), default=math.inf)

    def expire(self, now: float) -> None:
        """FAILED for the commands whose outcome did not come in time."""
        with self.lock:
            if not self._pending:
                return
            late = [p for p in self._pending if p.announced and now >= p.deadline]
            self._pending = [p for p in self._pending if p not in late]
        for p in late:
            log.warning("mavlink: no outcome for command %d in time; answering FAILED", p.command)
            p.link.send(T.command_ack(p.command, C.FAILED, p.system, p.component))


class Sender(Protocol):
    """What the dispatcher uses of the MAVLink output (:class:`~bridge.mavlink.output.MavlinkOutput`)."""

    services: BridgeServices
    autopilot: AutopilotWatch
    clock: Callable[[], float]
    relay: C.CalibrationRelay
    schedule: S.StreamSchedule
    params: ParamProtocol
    identity: T.Identity
    latest: CompassSample | None
    alt_m: float
    FRESH_S: float

    @property
    def companion(self) -> bool:
        """Beside an autopilot."""
        ...

    @property
    def compass_id(self) -> int:
        """Our MAG_CAL_* compass id."""
        ...

    def addressed_to_us(self, target_system: int, target_component: int) -> bool:
        """For us."""
        ...

    def broadcast(self, packets: list[Message] | Message) -> None:
        """To every link."""
        ...

    def streams_changed(self) -> None:
        """A stream's rate changed: the clock streams are planned anew."""
        ...

    def calibration_started(self) -> None:
        """Progress at once."""
        ...

    def report_answered(self) -> None:
        """Stop repeating MAG_CAL_REPORT."""
        ...

    def heartbeat(self, now: float) -> Message:
        """Our HEARTBEAT."""
        ...

    def health(self, now: float) -> T.Health:
        """Our health."""
        ...

    def progress_message(self, snap: CalibratorSnapshot) -> Message:
        """MAG_CAL_PROGRESS."""
        ...

    def encode_sample(self, msgid: int, s: CompassSample) -> Message | None:
        """A per-sample message."""
        ...


class CommandDispatcher:
    """Answers the commands addressed to us (see the module docstring)."""

    def __init__(self, out: Sender) -> None:
        self.out = out
        self.svc = out.services
        self.pending = PendingAcks(out.clock)
        self.commands = 0
        self._position: tuple[float, float, float] | None = None
        self._position_at = -math.inf

    # -- commands ------------------------------------------------------------------

    def ack(self, cmd: C.Command, link: Link, result: int, progress: int = 0) -> None:
        """COMMAND_ACK to the sender, on the link it came from."""
        link.send(
            T.command_ack(cmd.command, result, cmd.source_system, cmd.source_component, progress)
        )

    def handle(self, cmd: C.Command, link: Link) -> None:
        """Answer one command (or ignore it when it is not ours)."""
        out = self.out
        if not out.addressed_to_us(cmd.target_system, cmd.target_component):
            return
        self.commands += 1
        handler = self._HANDLERS.get(cmd.command)
        if handler is None:
            # Beside an autopilot, a broadcast command we do not know is the autopilot's
            # business: answering UNSUPPORTED would race its real answer.
            if not (cmd.broadcast and out.companion):
                self.ack(cmd, link, C.UNSUPPORTED)
            return
        result = handler(self, cmd, link)
        if result is not None:
            self.ack(cmd, link, result)
        log.info(
            "mavlink: command %d from %d/%d: %s",
            cmd.command,
            cmd.source_system,
            cmd.source_component,
            C.RESULT_NAMES.get(result, "answered") if result is not None else "answered",
        )

    def _for_our_compass(self, mask: int) -> bool:
        """A compass mask that names ours (0: every compass)."""
        return mask == 0 or bool(mask & (1 << self.out.compass_id))

    def _device_mask(self, mask: int) -> int:
        """The calibrator's mask for a MAVLink one: its compass is always compass 0 (our
        MAVLink compass id differs beside an autopilot); a mask without ours names none."""
        return 0 if self._for_our_compass(mask) else 0xFE

    def _autopilot_busy(self, cmd: C.Command) -> bool:
        """Beside an autopilot that runs its own sensor calibration a calibration of ours is
        refused (TEMPORARILY_REJECTED, what both autopilots answer when busy): two at once
        would mix their STATUSTEXT on ground-station pages that ignore the component."""
        if not (self.out.companion and self.out.autopilot.calibrating):
            return False
        log.warning(
            "mavlink: calibration command %d refused: the autopilot is calibrating", cmd.command
        )
        return True

    def _start_mag_cal(self, cmd: C.Command, link: Link) -> int | None:
        mask = _mask(cmd.p(1))
        if mask is None:
            return C.FAILED
        if self._autopilot_busy(cmd):
            return C.TEMPORARILY_REJECTED
        delay = cmd.p(4) if given(cmd.p(4)) and math.isfinite(cmd.p(4)) else 0.0
        self.out.relay.begin("ardupilot")
        result = self.svc.calibrator.start_mag(
            mask=self._device_mask(mask),
            retry=flag_param(cmd.p(2)),
            autosave=flag_param(cmd.p(3)),
            delay_s=max(0.0, delay),
        )
        if not result.ok:
            self.out.relay.begin(None)
            log.warning("mavlink: magnetometer calibration not started: %s", result.message)
        self.out.calibration_started()
        return C.result_code(result)

    def _accept_mag_cal(self, cmd: C.Command, link: Link) -> int | None:
        mask = _mask(cmd.p(1))
        if mask is None:
            return C.FAILED
        if self._for_our_compass(mask):
            self.out.report_answered()
        outcome: list[Outcome] = []

        def accept(_done: Callable[[bool], None]) -> int:
            outcome.append(self.svc.calibrator.accept(self._device_mask(mask)))
            # The device's MAGCAL,END: its answer (RANGE failure included) comes as an event.
            return 1 if outcome[0].result is Result.IN_PROGRESS else 0

        if self.pending.long_work(
            cmd, link, accept, ("calibration.done",), ("calibration.failed",)
        ):
            return None
        return C.result_code(outcome[0])

    def _cancel_mag_cal(self, cmd: C.Command, link: Link) -> int | None:
        mask = _mask(cmd.p(1))
        if mask is None:
            return C.FAILED  # ArduPilot cancels nothing then
        if self._for_our_compass(mask):
            self.out.report_answered()
        out = self.svc.calibrator.cancel(self._device_mask(mask))
        # ArduPilot answers ACCEPTED whatever the state; QGroundControl probes with it.
        return C.ACCEPTED if out.ok else C.result_code(out)

    def _fixed_yaw(self, cmd: C.Command, link: Link) -> int | None:
        mask = _mask(cmd.p(2))
        yaw = cmd.p(1)
        if mask is None:
            return C.FAILED
        if self._autopilot_busy(cmd):
            return C.TEMPORARILY_REJECTED
        lat, lon = cmd.p(3), cmd.p(4)
        have_position = given(lat) and given(lon) and (lat != 0.0 or lon != 0.0)
        self.out.relay.begin("ardupilot")
        out = self.svc.calibrator.fixed_yaw(
            yaw,
            mask=self._device_mask(mask),
            latitude_deg=lat if have_position else None,
            longitude_deg=lon if have_position else None,
        )
        if not out.ok:
            self.out.relay.begin(None)
            log.warning("mavlink: fixed-yaw calibration refused: %s", out.message)
        return C.result_code(out)

    def _preflight_calibration(self, cmd: C.Command, link: Link) -> int | None:
        # PX4's commander: (int) of each parameter; NaN is "not given" (MAVSDK sends it).
        p = [int_param(cmd.p(i)) for i in range(1, 8)]
        if any(v is None for v in p):
            return C.DENIED
        cal = self.svc.calibrator
        if all(v == 0 for v in p[:6]):
            cal.cancel()  # PX4: params 1-6 all zero cancel ("[cal] calibration cancelled")
            return C.ACCEPTED
        requests = [i for i, v in enumerate(p[:6], start=1) if v != 0]
        if requests in ([2], [5]) and self._autopilot_busy(cmd):
            return C.TEMPORARILY_REJECTED
        if requests == [2] and p[1] == 1:
            self.out.relay.begin("px4")
            out = cal.start_mag(autosave=True)  # PX4 has no accept step: a success is saved
        elif requests == [5] and p[4] == 1:
            self.out.relay.begin("px4")
            out = cal.start_accel()
        elif requests == [5] and p[4] == 2:
            self.out.relay.begin("px4")
            out = cal.start_level()
        else:
            return C.UNSUPPORTED  # gyro, baro, radio, airspeed, ESC: not this device
        if not out.ok:
            self.out.relay.begin(None)
            # PX4 reports a refusal the same way as a failure, so QGroundControl shows it.
            self.out.broadcast(
                T.statustext(
                    int(Severity.ERROR), calmap.cal_line(f"calibration failed: {out.message}")
                )
            )
        self.out.calibration_started()
        return C.result_code(out)

    def _preflight_storage(self, cmd: C.Command, link: Link) -> int | None:
        action = int_param(cmd.p(1))
        svc = self.svc
        params = svc.params
        # Nothing here waits on this (MAVLink's dispatch) thread: a params.json write that
        # its pacing puts off (a value set less than a second ago) and the compass flash's
        # PAR,SET are outcomes still to come -- IN_PROGRESS now, the final ack when they came.
        if action == 0:  # read: back to the stored values
            params.reload(source="PREFLIGHT_STORAGE")
            self.out.broadcast(self.out.params.all_values())
            return C.ACCEPTED
        if action == 1:  # write: parameters, calibration file and the compass flash
            device = svc.device
            link_ok = device.protocol == "gmr" and device.state is LinkState.STREAMING
            failed: list[str] = []

            def write(done: Callable[[bool], None]) -> int:
                params_saved = params.save_then(done)
                if params_saved is False:
                    failed.append(params.last_error or "parameters not saved")
                cal = svc.settings.calibration
                out = svc.calibrator.apply_calibration(cal, source="storage", write_device=link_ok)
                if not out.ok or not svc.calibrator.snapshot().calibration_saved:
                    failed.append(out.message or "calibration not saved")
                if failed:
                    return 0
                # The flash write (PAR,SET) reports as an event.
                return int(params_saved is None) + int(link_ok)

            done = ("calibration.device_updated",) if link_ok else ()
            if self.pending.long_work(cmd, link, write, done, ("calibration.device_error",)):
                return None
            if failed:
                log.error("mavlink: PREFLIGHT_STORAGE write failed: %s", "; ".join(failed))
                return C.FAILED
            return C.ACCEPTED
        if action == 2:  # reset the bridge's parameters (not the calibration) to defaults
            params.reset(source="PREFLIGHT_STORAGE")
            self.out.broadcast(self.out.params.all_values())
            saved: list[bool | None] = []

            def store(done: Callable[[bool], None]) -> int:
                saved.append(params.save_then(done))
                return 1 if saved[0] is None else 0

            if self.pending.long_work(cmd, link, store, (), ()):
                return None
            return C.ACCEPTED if saved[0] else C.FAILED
        if action == 3:  # reset the calibration to identity (the compass flash keeps its own)
            out = svc.calibrator.apply_calibration(
                Calibration(), source="reset", write_device=False
            )
            cal_saved = svc.calibrator.snapshot().calibration_saved
            return C.result_code(out) if cal_saved else C.FAILED
        return C.DENIED

    def _set_message_interval(self, cmd: C.Command, link: Link) -> int | None:
        msgid = int_param(cmd.p(1), default=-1)
        interval = cmd.p(2)
        if msgid is None or msgid not in S.STREAMABLE or not math.isfinite(interval):
            return C.DENIED
        schedule = self.out.schedule
        sid = S.schedule_id(msgid)
        if interval == -1:
            schedule.set_override(sid, 0.0)
        elif interval == 0:
            schedule.set_override(sid, None)
        elif MIN_INTERVAL_US <= interval <= MAX_INTERVAL_US:
            schedule.set_override(sid, 1e6 / interval)
        else:
            return C.DENIED
        self.out.streams_changed()
        return C.ACCEPTED

    def _get_message_interval(self, cmd: C.Command, link: Link) -> int | None:
        msgid = int_param(cmd.p(1), default=-1)
        if msgid is None or not 0 <= msgid <= 0xFFFF:
            return C.DENIED
        interval = 0
        if msgid in S.STREAMABLE:
            interval = self.out.schedule.interval_us(S.schedule_id(msgid))
        self.ack(cmd, link, C.ACCEPTED)
        link.send(T.message_interval(msgid, max(-1, min(MAX_INTERVAL_US, interval))))
        return None

    def _request_message(self, cmd: C.Command, link: Link) -> int | None:
        msgid = int_param(cmd.p(1), default=-1)
        if msgid is None or msgid < 0:
            return C.DENIED
        packet = self.requested(msgid)
        if packet is None:
            known = msgid in S.STREAMABLE or msgid in (
                T.AUTOPILOT_VERSION,
                T.MAG_CAL_REPORT,
                T.MAG_CAL_PROGRESS,
            )
            return C.FAILED if known else C.DENIED
        self.ack(cmd, link, C.ACCEPTED)
        if int_param(cmd.p(7)) == 2:
            self.out.broadcast(packet)
        else:
            link.send(packet)
        return None

    def _request_capabilities(self, cmd: C.Command, link: Link) -> int | None:
        packet = self.requested(T.AUTOPILOT_VERSION)
        assert packet is not None
        self.ack(cmd, link, C.ACCEPTED)
        link.send(packet)
        return None

    def requested(self, msgid: int) -> Message | None:
        """A message asked for with MAV_CMD_REQUEST_MESSAGE (None: cannot be produced now)."""
        out = self.out
        now = out.clock()
        if msgid == T.AUTOPILOT_VERSION:
            v = self.svc.device.version
            serial = v.serial if v is not None else None
            uid = zlib.crc32(serial.encode()) if serial else 0
            return T.autopilot_version(
                __version__,
                v.firmware if v else None,
                serial,
                uid,
                param_encoding=out.params.encoding.capability,
            )
        if msgid == T.HEARTBEAT:
            return out.heartbeat(now)
        if msgid == T.SYS_STATUS:
            return T.sys_status(out.health(now))
        if msgid == T.MAG_CAL_REPORT:
            snap = self.svc.calibrator.snapshot()
            r = snap.report
            if r is None or snap.mode not in calmap.MAG_MODES:
                return None
            return T.mag_cal_report(calmap.report_figures(r), out.compass_id)
        if msgid == T.MAG_CAL_PROGRESS:
            return out.progress_message(self.svc.calibrator.snapshot())
        s = out.latest
        if s is None or now - s.t > out.FRESH_S:
            return None
        return out.encode_sample(msgid, s)

    _HANDLERS: ClassVar[dict[int, Callable[[CommandDispatcher, C.Command, Link], int | None]]] = {
        C.DO_START_MAG_CAL: _start_mag_cal,
        C.DO_ACCEPT_MAG_CAL: _accept_mag_cal,
        C.DO_CANCEL_MAG_CAL: _cancel_mag_cal,
        C.FIXED_MAG_CAL_YAW: _fixed_yaw,
        C.PREFLIGHT_CALIBRATION: _preflight_calibration,
        C.PREFLIGHT_STORAGE: _preflight_storage,
        C.SET_MESSAGE_INTERVAL: _set_message_interval,
        C.GET_MESSAGE_INTERVAL: _get_message_interval,
        C.REQUEST_MESSAGE: _request_message,
        C.REQUEST_AUTOPILOT_CAPABILITIES: _request_capabilities,
    }

    # -- the autopilot's position (companion role) ----------------------------------

    def position(self, msg: Any) -> None:
        """GLOBAL_POSITION_INT / GPS_RAW_INT from our own autopilot: the WMM there."""
        out = self.out
        if not out.companion or msg.get_srcSystem() != out.identity.system_id:
            return
        if msg.get_type() == "GPS_RAW_INT" and int(msg.fix_type) < 2:
            return  # no fix
        lat, lon = msg.lat * 1e-7, msg.lon * 1e-7
        alt = msg.alt * 1e-3
        if (lat == 0.0 and lon == 0.0) or not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            return
        out.alt_m = alt
        now = out.clock()
        prev = self._position
        moved = prev is None or max(abs(lat - prev[0]), abs(lon - prev[1])) > _POSITION_MOVE_DEG
        if not moved and now - self._position_at < _POSITION_MIN_S:
            return
        try:
            field = self.svc.settings.set_position(lat, lon, alt, "autopilot position")
        except ChangeRefusedError:
            return  # the guard said why (an armed ArduPilot); the next position tries again
        except ValueError as e:
            log.warning("mavlink: autopilot position %.5f, %.5f unusable: %s", lat, lon, e)
            return
        self._position, self._position_at = (lat, lon, alt), now
        if prev is None:
            log.info(
                "mavlink: position from the autopilot %.5f, %.5f: declination %+.2f deg",
                lat,
                lon,
                field.declination_deg,
            )
