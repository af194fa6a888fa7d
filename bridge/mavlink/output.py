"""MavlinkOutput: the bridge on MAVLink -- telemetry out, parameters and commands in.

It is an :class:`~bridge.app.sample.Output` built on the application's
:class:`~bridge.app.services.BridgeServices`:

* ``publish`` (the pipeline, in the link's reader thread) sends the sample
  streams that are due (:class:`~bridge.mavlink.schedule.StreamSchedule`):
  a frame with none due costs one comparison; the messages due on one frame
  leave together (one datagram per UDP peer, or two: the attitude first);
* the **telemetry** thread wakes on the clock only, when something is due:
  HEARTBEAT, SYS_STATUS, MAG_CAL_PROGRESS while a magnetometer calibration
  runs, MAG_CAL_REPORT (about once a second) while a result waits for accept,
  command time-outs; a rate change or a calibration event wakes it to plan anew;
* the **dispatch** thread handles what ground stations send, one message at a
  time: parameters (:mod:`~bridge.mavlink.paramproto`), commands
  (:mod:`~bridge.mavlink.dispatch`), the autopilot's position;
* one thread per **endpoint** (:mod:`bridge.mavlink.endpoints`) does the I/O.

Changes made elsewhere reach it as notifications, never by polling: parameter
changes go out as PARAM_VALUE on every link, events as STATUSTEXT or the
calibration flows' messages (:class:`~bridge.mavlink.commands.CalibrationRelay`).

Roles: **standalone** -- component 1, HEARTBEAT type GENERIC and the
``[mavlink] autopilot`` flavour; answers what is addressed to its system (any
component); **companion** -- component 200 (MAV_COMP_ID_IMU), type IMU,
autopilot INVALID, beside an autopilot with the same system id: it obeys only
what names its own component (reads of parameters addressed to every component
are answered too), reports its calibration as compass :data:`COMPANION_COMPASS_ID`,
and takes the position for declination (:mod:`~bridge.mavlink.autopilot`) and its
attitude for the tilt (:mod:`~bridge.mavlink.attitude_in`) from the autopilot.

Security: with a signing key what we send is signed and COMMAND_*, PARAM_SET,
position and attitude messages must be validly signed (:mod:`bridge.mavlink.signing`).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

from bridge.app.params import ParamChange
from bridge.app.sample import CompassSample
from bridge.app.services import BridgeServices, SentMessage
from bridge.calibration.sessions import CalibratorSnapshot
from bridge.events import Event
from bridge.mavlink import calmap, ftp
from bridge.mavlink import commands as C  # noqa: N812 - short
from bridge.mavlink import schedule as S  # noqa: N812 - short
from bridge.mavlink import telemetry as T  # noqa: N812 - short
from bridge.mavlink.attitude_in import WANTED_STREAMS, AutopilotAttitudeIn
from bridge.mavlink.autopilot import AutopilotWatch
from bridge.mavlink.dialect import Message
from bridge.mavlink.dispatch import CommandDispatcher
from bridge.mavlink.endpoints import Endpoint, EndpointCounters, Link, open_endpoint
from bridge.mavlink.feed import HeadingFeed
from bridge.mavlink.pacing import PacedLink, Pacer
from bridge.mavlink.paramproto import ParamEncoding, ParamProtocol
from bridge.mavlink.settings import MavlinkSettings
from bridge.mavlink.signing import Signing, Verdict
from bridge.mavlink.signing_table import SigningTable

log = logging.getLogger(__name__)

#: The compass id a companion bridge reports its calibration as: beyond ArduPilot's
#: three compasses (COMPASS_MAX_INSTANCES), so neither the autopilot nor a ground
#: station takes it, or an accept sent for it, for one of the autopilot's.
COMPANION_COMPASS_ID = 7
_INBOX_MAX = 512
_SIGNED_TYPES = frozenset(
    {"COMMAND_LONG", "COMMAND_INT", "PARAM_SET", "GLOBAL_POSITION_INT", "GPS_RAW_INT"}
)
#: Signed messages that change state: the replay table is saved before one is obeyed.
_OBEYED_TYPES = frozenset({"COMMAND_LONG", "COMMAND_INT", "PARAM_SET"})
#: Beside an autopilot the telemetry thread also looks this often (TIMESYNC requests, the
#: streams asked of the autopilot: :mod:`~bridge.mavlink.autopilot`); standalone it sleeps
#: until its next stream or deadline.
_COMPANION_LOOK_S = 0.5
_INBOX_TYPES = _SIGNED_TYPES | {
    "PARAM_REQUEST_LIST",
    "PARAM_REQUEST_READ",
    "FILE_TRANSFER_PROTOCOL",
}
#: The parameter change source of this output's own SETs (their echo is sent by the SET).
_OWN_SET = "mavlink PARAM_SET"


@dataclass(slots=True)
class OutputCounters:
    """What the output counted (besides each endpoint's own counters)."""

    inbox_dropped: int = 0
    refused_unsigned: int = 0
    refused_bad_signature: int = 0
    refused_replay: int = 0
    param_sets_refused: int = 0
    param_lists_refused: int = 0  #: PARAM_REQUEST_LIST inside a peer's rate limit
    events_relayed: int = 0
    publish_errors: int = 0  #: sample streams that failed to encode (logged once)
    handler_errors: int = 0  #: received messages whose handling raised (logged once)


class MavlinkOutput:
    """The MAVLink front end (see the module docstring)."""

    FRESH_S = 2.0  #: a sample older than this is not "fresh" (SYS_STATUS health, HEARTBEAT)

    def __init__(
        self,
        settings: MavlinkSettings,
        services: BridgeServices,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings
        self.services = services
        self.clock = clock
        self._t0 = clock()
        self.identity = T.Identity(
            settings.system_id, settings.effective_component_id, settings.role, settings.autopilot
        )
        self.signing = Signing(settings.signing_key) if settings.signing_key else None
        self.counters = OutputCounters()
        self.endpoints: list[Endpoint] = []
        self.params = ParamProtocol(
            services.params,
            ParamEncoding(settings.autopilot, companion=settings.role == "companion"),
        )
        self.schedule = S.StreamSchedule({})
        self.relay = C.CalibrationRelay(self.compass_id, self.clock)
        self.dispatcher = CommandDispatcher(self)
        #: The autopilot's attitude as the tilt source (companion role only); TILT_SRC out.
        self.autopilot_in = AutopilotAttitudeIn.beside(settings, services, clock, self._t0)
        self._tilt_note = T.TiltSourceNote()
        self.latest: CompassSample | None = None
        self.alt_m = 0.0  #: the autopilot's altitude (companion role), for VFR_HUD
        self._running = False  # publish() sends only between start() and close()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._inbox: deque[tuple[Any, Link]] = deque()
        self._inbox_cond = threading.Condition()
        self._threads: list[threading.Thread] = []
        self._unsubscribe: list[Callable[[], None]] = []
        # The feed's clock is the wall clock (Unix epoch), so its time stamps continue across
        # restarts; the output's own clock (monotonic) plus this offset.
        self._epoch_offset = time.time() - clock()
        self.autopilot = AutopilotWatch(
            (self.identity.system_id, self.identity.component_id),
            lambda: int(services.params.get("BRG_HDG_FEED")),
            services.events,
            clock,
        )
        self.autopilot.on_due = self._wake.set
        self.relay.on_due = self._wake.set
        if self.autopilot_in is not None:  # the tilt source: the autopilot's ATTITUDE, asked for
            for msgid, hz, group in WANTED_STREAMS:
                self.autopilot.requests.want(msgid, hz, group)
        self.feed = HeadingFeed(self)
        #: Every burst (answers, lists, status texts, reports) leaves through it:
        #: routers in between forward through small buffers (bridge.mavlink.pacing).
        self.pacer = Pacer()
        # Schedule id -> encoder of the per-sample stream in that slot (the heading feed's
        # slot holds the feed BRG_HDG_FEED chooses): see _apply_rates.
        self._sample_encoders: dict[int, Callable[[CompassSample], Message | None]] = {}
        self._refusal_logged: dict[str, float] = {}
        #: The signing replay table, kept in the state directory across restarts.
        self.signing_table = SigningTable(self.signing, services.documents, clock)
        self._stream_encoders: dict[int, Callable[[CompassSample], Message | None]] = {
            S.ATTITUDE: lambda s: T.attitude(s, self.time_boot_ms(s.t)),
            S.ATTITUDE_QUATERNION: lambda s: T.attitude_quaternion(s, self.time_boot_ms(s.t)),
            S.VFR_HUD: lambda s: T.vfr_hud(s, self.alt_m),
            S.SCALED_IMU: lambda s: T.scaled_imu(s, self.time_boot_ms(s.t)),
            S.RAW_IMU: lambda s: T.raw_imu(s, self._us(s.t)),
            S.HIGHRES_IMU: lambda s: T.highres_imu(s, self._us(s.t)),
            S.ODOMETRY: self.feed.odometry,
            S.VISION_POSITION_ESTIMATE: self.feed.vision_position_estimate,
        }

    # ------------------------------------------------------------------ roles

    @property
    def name(self) -> str:
        """Short name for logs."""
        return "mavlink"

    @property
    def companion(self) -> bool:
        """Beside an autopilot (component 200), not a vehicle of its own."""
        return self.settings.role == "companion"

    @property
    def compass_id(self) -> int:
        """The compass id of our MAG_CAL_* messages."""
        return COMPANION_COMPASS_ID if self.settings.role == "companion" else 0

    def addressed_to_us(self, target_system: int, target_component: int) -> bool:
        """Whether a command or parameter message is for us.

        Standalone we are the vehicle: our system (or all), any of its components.
        Beside an autopilot only what names our component: a broadcast is the
        autopilot's (MAVProxy's ``magcal start`` is one), and acting on it would
        start, stop or accept both calibrations at once.
        """
        if target_system not in (0, self.identity.system_id):
            return False
        if self.companion:
            return target_component == self.identity.component_id
        return target_component in (0, self.identity.component_id)

    def _reading_for_us(self, msg: Any) -> bool:
        """A parameter read for us: to component 0 it is for every component (a companion's too)."""
        t = (msg.target_system, msg.target_component)
        return self.addressed_to_us(*t) or (t[0] in (0, self.identity.system_id) and t[1] == 0)

    # ------------------------------------------------------------------ Output protocol

    @property
    def due_at(self) -> float:
        """When a sample stream next falls due (``-inf`` before the schedule knows:
        every frame then; ``+inf`` when none is on or the output is not running)."""
        return self.schedule.sample_due_at if self._running else math.inf

    def publish(self, sample: CompassSample) -> None:
        """Keep ``sample`` as the latest and send the sample streams now due; never blocks.

        Runs in the pipeline's thread; never raises: a failure is counted in
        ``counters.publish_errors`` and logged once."""
        self.latest = sample
        if not self._running:
            return
        try:
            # A sample is due by its own time (its frame's arrival), not by when the pipeline
            # got to it: of frames read in one burst, none is younger than the read.
            now = sample.t
            # The fast path, most frames at 100 Hz: nothing is due before sample_due_at (reset
            # on every rate, override or stream-set change: it takes effect at the next sample).
            if now < self.schedule.sample_due_at:
                return
            encoders = self._sample_encoders
            packets: list[Message] = []
            head = True  # the attitude streams lead the plan (S.ATTITUDE_FIRST)
            try:
                for sid in self.schedule.due_samples(now):
                    if head and sid not in S.ATTITUDE_FIRST:  # the attitude leaves first
                        self.broadcast_now(packets)  # (nothing when it is not due)
                        head, packets = False, []
                    p = encoders[sid](sample)
                    if p is not None:
                        packets.append(p)
                        if sid == S.ATTITUDE:  # its tilt source beside it (TILT_SRC)
                            packets.extend(self._tilt_note.due(sample, now, p.time_boot_ms))
            finally:  # a stream that fails to encode does not hold back those before it
                self.broadcast_now(packets)
        except Exception:
            self.counters.publish_errors += 1
            if self.counters.publish_errors == 1:
                log.exception("mavlink: encoding telemetry failed (further failures counted)")

    def start(self) -> None:
        """Open endpoints, follow the parameters, events and settings, start the threads."""
        if self._threads:
            raise RuntimeError("mavlink output already started")
        svc = self.services
        self.signing_table.restore()
        self._apply_rates()
        for i, text in enumerate(self.settings.endpoints):
            self.endpoints.append(
                open_endpoint(
                    text,
                    system_id=self.identity.system_id,
                    component_id=self.identity.component_id,
                    on_message=self._on_message,
                    signing=self.signing,
                    link_id=i,
                    queue_packets=self.settings.queue_packets,
                )
            )
        for ep in self.endpoints:
            ep.start()
        self.pacer.start()
        self._running = True
        self._unsubscribe = [
            svc.events.subscribe(self._on_event),
            svc.params.subscribe(self._on_params),
            svc.settings.subscribe(self.feed.on_settings),
        ]
        if self.companion:
            self._unsubscribe.append(self.autopilot.attach(svc.settings))
        for fn, name in ((self._telemetry_loop, "telemetry"), (self._dispatch_loop, "dispatch")):
            t = threading.Thread(target=self._guard(fn, name), name=f"mavlink-{name}", daemon=True)
            self._threads.append(t)
            t.start()
        log.info(
            "mavlink: system %d component %d (%s, %s)%s on %s",
            self.identity.system_id,
            self.identity.component_id,
            self.settings.role,
            self.settings.autopilot,
            ", signed" if self.signing else ", UNSIGNED",
            ", ".join(self.settings.endpoints) or "no endpoint",
        )
        if self.signing is None:
            log.warning(
                "mavlink: no signing key (mavlink.signing_key_file): anyone on the link can "
                "change parameters and recalibrate the compass"
            )

    def close(self, timeout: float) -> None:
        """Stop threads and endpoints within about ``timeout`` seconds."""
        deadline = self.clock() + timeout
        self._running = False
        self._stop.set()
        self._wake.set()
        with self._inbox_cond:
            self._inbox_cond.notify_all()
        for unsubscribe in self._unsubscribe:
            unsubscribe()
        self._unsubscribe = []
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(max(0.05, deadline - self.clock()))
        self.pacer.close(max(0.05, deadline - self.clock()))
        for ep in self.endpoints:
            ep.close(max(0.05, deadline - self.clock()))
        if self.signing_table.dirty:
            self.signing_table.save()

    # ------------------------------------------------------------------ sending

    def endpoint_counters(self) -> dict[str, EndpointCounters]:
        """Each endpoint's counters, by connection string."""
        return {ep.name: ep.counters() for ep in self.endpoints}

    def time_boot_ms(self, t: float) -> int:
        """Milliseconds since the output started, for ``t`` on the output's clock."""
        return max(0, int((t - self._t0) * 1000.0))

    def _us(self, t: float) -> int:
        return max(0, int((t - self._t0) * 1e6))

    def epoch_us(self, t: float) -> int:
        """``t`` on the output's clock as Unix-epoch microseconds (the feed's time stamps)."""
        return int((t + self._epoch_offset) * 1e6)

    def _guard(self, fn: Callable[[], None], name: str) -> Callable[[], None]:
        def run() -> None:
            try:
                fn()
            except Exception:
                log.exception("mavlink %s thread crashed", name)

        return run

    def broadcast(self, packets: list[Message] | Message) -> None:
        """To every peer of every endpoint, in order, paced (:mod:`bridge.mavlink.pacing`)."""
        if not isinstance(packets, list):
            packets = [packets]
        if packets:
            self.pacer.submit(self._broadcast_one, packets)

    def _broadcast_one(self, packet: Message) -> None:
        self.broadcast_now([packet])

    def broadcast_now(self, packets: list[Message] | Message) -> None:
        """Send to every peer of every endpoint at once, not paced (the sample and clock
        streams, whose schedule is their pace); a list goes out together, in order (one
        datagram per UDP peer while it fits). Every message is also offered to the
        application's MAVLink tap (the Zenoh mirror)."""
        if not isinstance(packets, list):
            packets = [packets]
        if not packets:
            return
        for ep in self.endpoints:
            if len(packets) == 1:
                ep.broadcast(packets[0])
            else:
                ep.broadcast_many(packets)
        tap = self.services.mavlink_tap
        if tap.active:
            sysid, compid = self.identity.system_id, self.identity.component_id
            for p in packets:
                tap.publish(SentMessage(sysid, compid, p))

    # ------------------------------------------------------------------ what we send

    def health(self, now: float) -> T.Health:
        """What HEARTBEAT and SYS_STATUS report now."""
        svc = self.services
        st = svc.status()
        snap = svc.calibrator.snapshot()
        latest = self.latest
        fresh = latest is not None and now - latest.t < self.FRESH_S
        a = latest.attitude if latest is not None else None
        c = st.counters
        return T.Health(
            link_state=st.state,
            fresh=fresh,
            calibrating=snap.running,
            disturbed=bool(a is not None and a.disturbed),
            saturated=bool(latest is not None and latest.saturated),
            compass_use=svc.params.get("COMPASS_USE") != 0,
            bad_lines=c.bad_lines_total,
            good_lines=c.frames,
            lost_frames=c.lost_frames,
            reconnects=c.reconnects,
            stale_events=c.stale_events,
            pipeline_errors=st.pipeline_errors,
        )

    def heartbeat(self, now: float) -> Message:
        """Our HEARTBEAT now."""
        return T.heartbeat(self.identity, T.system_status(self.health(now)))

    def progress_message(self, snap: CalibratorSnapshot) -> Message:
        """MAG_CAL_PROGRESS from a calibrator snapshot."""
        return calmap.progress_message(snap, self.compass_id)

    def calibration_started(self) -> None:
        """A calibration command was handled: progress at once, not at the next tick."""
        self.relay.hurry()
        self._wake.set()

    def streams_changed(self) -> None:
        """A stream's rate changed (MAV_CMD_SET_MESSAGE_INTERVAL, BRG_SR_*): the telemetry
        thread, asleep until the clock streams' next slot, plans anew."""
        self._wake.set()

    def _sample_streams(self) -> list[int]:
        feed = int(self.services.params.get("BRG_HDG_FEED"))
        ids = list(S.SAMPLE_STREAMS[:-1])  # all but the feed's slot
        if feed == 1:
            ids.append(S.ODOMETRY)
        elif feed == 2:
            ids.append(S.VISION_POSITION_ESTIMATE)
        return ids

    def encode_sample(self, msgid: int, s: CompassSample) -> Message | None:
        """One per-sample message (None when the sample cannot fill it, or not one)."""
        enc = self._stream_encoders.get(msgid)
        return enc(s) if enc is not None else None

    def _apply_rates(self) -> None:
        """BRG_SR_* into the schedule's rates; BRG_HDG_FEED into its set of sample streams."""
        params = self.services.params
        for s in S.STREAMS:
            self.schedule.set_base(s.msgid, params.get(s.param))
        wanted = self._sample_streams()
        enc = self._stream_encoders
        # Encoders first, then the schedule: publish() in the pipeline may see the new
        # encoders with the old streams (a feed just switched off: its slot encodes
        # nothing), never a due stream without an encoder.
        self._sample_encoders = {
            S.ODOMETRY: lambda _s: None,
            **{S.schedule_id(m): enc[m] for m in wanted},
        }
        self.schedule.set_sample_streams(S.schedule_id(m) for m in wanted)

    # ------------------------------------------------------------------ the telemetry thread

    def next_look(self, now: float) -> float:
        """When the telemetry thread next has something to do (clock seconds): the clock
        streams' next slot, the calibration keep-alive while one runs or a report waits,
        a command's deadline, the signing table's save; beside an autopilot at least every
        :data:`_COMPANION_LOOK_S`. Whatever makes one of them earlier wakes the thread
        (:meth:`streams_changed`, the relay's and the autopilot watch's ``on_due``)."""
        due_at = min(
            self.schedule.next_clock_due(now),
            self.relay.keepalive_due,
            self.autopilot.due_at,
            self.dispatcher.pending.due_at,
            self.signing_table.save_due,
        )
        return min(due_at, now + _COMPANION_LOOK_S) if self.companion else due_at

    def _telemetry_loop(self) -> None:
        # Asleep until next_look (samples: from publish()).
        while not self._stop.is_set():
            now = self.clock()
            due_at = self.next_look(now)
            self._wake.wait(max(0.0, due_at - now))
            self._wake.clear()
            if self._stop.is_set():
                break
            now = self.clock()
            out: list[Message] = []
            clock_due = self.schedule.due_on_clock(now)
            if clock_due:
                h = self.health(now)
                for msgid in clock_due:
                    if msgid == S.HEARTBEAT:
                        out.append(T.heartbeat(self.identity, T.system_status(h)))
                    elif msgid == S.SYS_STATUS:
                        out.append(T.sys_status(h))
            if out:
                self.broadcast_now(out)
            keepalive = self.relay.keepalive(now, self.services.calibrator.snapshot)
            if keepalive:
                self.broadcast(keepalive)
            if self.autopilot_in is not None:  # TIMESYNC to the autopilot, now and then
                self.autopilot_in.tick(now)
            self.dispatcher.pending.expire(now)
            if self.companion:
                self.autopilot.tick(now)
            if now >= self.signing_table.save_due:
                self.signing_table.save()

    def report_answered(self) -> None:
        """DO_ACCEPT_MAG_CAL or DO_CANCEL_MAG_CAL for our compass: stop repeating the report."""
        self.relay.answered()

    # ------------------------------------------------------------------ notifications

    def _on_event(self, event: Event) -> None:
        """EventBus subscriber (any thread): relay (see :class:`~bridge.mavlink.commands.CalibrationRelay`),
        finish IN_PROGRESS commands."""
        packets = self.relay.packets(event)
        if packets:
            self.counters.events_relayed += 1
            self.broadcast(packets)
        self.dispatcher.pending.on_event(event)

    def _on_params(self, change: ParamChange) -> None:
        """Parameters changed (any thread): tell every ground station; follow the rates."""
        if any(n.startswith("BRG_SR_") or n == "BRG_HDG_FEED" for n in change.names):
            self._apply_rates()
            self.streams_changed()
        if change.source == _OWN_SET:
            return  # the SET's echo is already on its way
        self.broadcast([self.params.value_of(n) for n in change.names])

    # ------------------------------------------------------------------ inbound

    def _on_message(self, msg: Any, link: Link) -> None:
        """Endpoint threads: answer TIMESYNC at once, tell the autopilot watch what the
        autopilot says, queue what the dispatcher handles."""
        kind = msg.get_type()
        self.autopilot.heard(msg, link.send)  # its HEARTBEAT, position, wanted streams
        ap = self.autopilot_in  # its attitude, its TIMESYNC answers: taken here, on arrival
        if ap is not None and ap.takes(msg, link, self._refuse_unsigned):
            return
        if kind == "TIMESYNC":
            if int(msg.tc1) == 0:  # a request: answer with our (feed's) time, echo theirs
                now_ns = int((self.clock() + self._epoch_offset) * 1e9)
                link.send(
                    T.timesync_reply(
                        now_ns, int(msg.ts1), msg.get_srcSystem(), msg.get_srcComponent()
                    )
                )
            return
        if kind not in _INBOX_TYPES:
            return
        with self._inbox_cond:
            if len(self._inbox) >= _INBOX_MAX:
                self._inbox.popleft()
                self.counters.inbox_dropped += 1
            self._inbox.append((msg, link))
            self._inbox_cond.notify()

    def _dispatch_loop(self) -> None:
        while True:
            with self._inbox_cond:
                # Asleep until a message comes or close() (which sets _stop, then notifies
                # under this lock: looked at here, under it, so the notice is never missed).
                while not self._inbox and not self._stop.is_set():
                    self._inbox_cond.wait()
                if self._stop.is_set():
                    return
                item = self._inbox.popleft()
            msg, link = item
            try:
                # Duck-typed: send() is all the handlers use of a link.
                self._handle(msg, cast(Link, PacedLink(link, self.pacer)))
            except Exception:
                self.counters.handler_errors += 1
                if self.counters.handler_errors == 1:
                    log.exception(
                        "mavlink: handling %s failed (further failures counted)", msg.get_type()
                    )

    def _refuse_unsigned(self, msg: Any) -> bool:
        """True (and logged, counted) when signing is on and ``msg`` must not be obeyed."""
        if self.signing is None:
            return False
        verdict = self.signing.verify(msg.get_msgbuf(), msg.get_srcSystem(), msg.get_srcComponent())
        if verdict is Verdict.OK:
            return False
        if verdict is Verdict.UNSIGNED:
            self.counters.refused_unsigned += 1
        elif verdict is Verdict.BAD_SIGNATURE:
            self.counters.refused_bad_signature += 1
        else:
            self.counters.refused_replay += 1
        key = f"{msg.get_type()}:{verdict.name}"
        now = self.clock()
        if now - self._refusal_logged.get(key, -math.inf) > 10.0:  # at most one line per 10 s
            self._refusal_logged[key] = now
            log.warning(
                "mavlink: refused %s from %d/%d: %s",
                msg.get_type(),
                msg.get_srcSystem(),
                msg.get_srcComponent(),
                verdict.value,
            )
        return True

    def _handle(self, msg: Any, link: Link) -> None:
        kind = msg.get_type()
        if kind in _SIGNED_TYPES and self.signing is not None:
            if self._refuse_unsigned(msg):
                return
            if self.signing_table.mark():
                self._wake.set()  # the telemetry thread plans the table's next save
            if kind in _OBEYED_TYPES:
                # Write-ahead: the packet's timestamp is on disk before it changes anything,
                # so a copy replayed after a restart is still refused.
                self.signing_table.save()
        if kind in ("COMMAND_LONG", "COMMAND_INT"):
            self.dispatcher.handle(C.command_from_message(msg), link)
        elif kind in ("GLOBAL_POSITION_INT", "GPS_RAW_INT"):
            self.dispatcher.position(msg)
        elif kind.startswith("PARAM_REQUEST_") and self._reading_for_us(msg):
            answers = self.params.answer_read(msg, link)
            if answers is None:
                self.counters.param_lists_refused += 1
            for a in answers or ():
                link.send(a)
        elif not self.addressed_to_us(msg.target_system, msg.target_component):
            return
        elif kind == "PARAM_SET":
            self._param_set(msg)
        elif kind == "FILE_TRANSFER_PROTOCOL":
            answer = ftp.reply(msg, int(msg.target_network))
            if answer is not None:
                link.send(answer)

    def _param_set(self, msg: Any) -> None:
        name, reason, echo = self.params.set(msg, source=_OWN_SET)
        if reason:
            self.counters.param_sets_refused += 1
            params = self.services.params
            log.warning(
                "mavlink: PARAM_SET %s = %r (type %d) refused: %s%s",
                name,
                msg.param_value,
                msg.param_type,
                reason,
                f"; stays {params.get(name):g}" if params.spec(name) is not None else "",
            )
        if echo is not None:
            # Every SET is answered by the value now in force, on every link.
            self.broadcast(echo)
