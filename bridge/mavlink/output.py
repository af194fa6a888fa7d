"""MavlinkOutput: the bridge on MAVLink -- telemetry out, parameters and commands in.

It is a daemon :class:`~bridge.daemon.Output`: ``publish`` keeps the latest
sample (one reference store, never blocks); its threads do the rest:

* ``publish`` (the pipeline, in the link's reader thread) encodes the sample streams that are due
  (:class:`~bridge.mavlink.telemetry.StreamSchedule`) and queues them on the
  endpoints -- a few microseconds per due message, never blocking: at 100 Hz
  most frames carry no due message, and waking a thread per frame just to find
  that out cost more than the encoding. A frame with none due costs one
  comparison (``StreamSchedule.sample_due_at``); the messages due on one frame
  leave together (one datagram, one ``sendto``, per UDP peer);
* the **telemetry** thread wakes on the clock only: HEARTBEAT, SYS_STATUS,
  MAG_CAL_PROGRESS while a magnetometer calibration runs, command time-outs;
* the **dispatcher** thread handles what ground stations send (parameters,
  commands, the autopilot's position), one message at a time, in order;
* one thread per **endpoint** (:mod:`bridge.mavlink.endpoints`) does the I/O.

Operator events (the daemon's :class:`~bridge.events.EventBus`) become
STATUSTEXT, and calibration events MAG_CAL_PROGRESS / MAG_CAL_REPORT or PX4's
``[cal]`` lines (:class:`~bridge.mavlink.commands.CalibrationRelay`).

Roles: **standalone** -- component 1, HEARTBEAT type GENERIC / autopilot
INVALID, so QGroundControl makes a vehicle of it and draws its attitude;
**companion** -- component 200 (MAV_COMP_ID_IMU), type IMU, beside an
autopilot with the same system id, whose GLOBAL_POSITION_INT / GPS_RAW_INT
give the position for declination and the expected field.

Security: with a signing key every packet we send is signed, and COMMAND_LONG,
COMMAND_INT, PARAM_SET and position messages must carry a valid, fresh
signature (see :mod:`bridge.mavlink.signing`); others are refused, logged
and counted. Reads (PARAM_REQUEST_*) stay open so a ground station without
the key can still watch.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MethodType
from typing import Any, ClassVar, Protocol

from bridge import __version__
from bridge.calibration.model import Calibration
from bridge.calibrator import CalibrationController, Outcome, Result
from bridge.config import Config
from bridge.core.attitude import AttitudeEngine, FieldReference, field_reference_at
from bridge.core.mounting import Mounting, Rotation
from bridge.core.wmm import earth_field
from bridge.daemon import CompassSample, DaemonStatus
from bridge.events import Event, EventBus, Severity
from bridge.link.serial_link import CompassLink, LinkState
from bridge.mavlink import commands as C  # noqa: N812 - short
from bridge.mavlink import telemetry as T  # noqa: N812 - short
from bridge.mavlink.dialect import mavlink as M  # noqa: N812 - the generated module, short
from bridge.mavlink.endpoints import Endpoint, EndpointCounters, Link, open_endpoint
from bridge.mavlink.params import (
    CAL_PARAMS,
    ParamTable,
    calibration_from_values,
    limits_from_values,
    param_name,
    same_calibration,
    view_values,
)
from bridge.mavlink.signing import Signing, Verdict
from bridge.mavlink.wire import Packet
from bridge.storage import StateStore, StorageError

log = logging.getLogger(__name__)

#: Name of the parameter document in the state directory (``<storage.dir>/params.json``).
PARAMS_DOCUMENT = "params"
MAV_COMP_ID_IMU = int(M.MAV_COMP_ID_IMU)
DEFAULT_QUEUE_PACKETS = 128
_INBOX_MAX = 512
_FRESH_S = 2.0  # a sample older than this is not "fresh" (SYS_STATUS health, HEARTBEAT)
_PROGRESS_PERIOD_S = 0.5  # MAG_CAL_PROGRESS while a magnetometer calibration runs
_REPORT_PERIOD_S = 2.0  # MAG_CAL_REPORT repeated while a result waits for accept
_SAVE_DELAY_S = 0.2  # parameter saves are coalesced over this long
# The dispatch thread's longest sleep with nothing to do. Its housekeeping (a new
# calibration, a reloaded [location]) is also woken by every event, and a calibration
# change comes with one, so this only bounds the rest -- and costs one wake-up a second.
_HOUSEKEEPING_S = 1.0
_POSITION_MIN_S = 10.0  # autopilot position: at most one WMM update per this long ...
_POSITION_MOVE_DEG = 0.01  # ... unless the vehicle moved further than this
_FINAL_ACK_TIMEOUT_S = 5.0
_SIGNED_TYPES = frozenset(
    {"COMMAND_LONG", "COMMAND_INT", "PARAM_SET", "GLOBAL_POSITION_INT", "GPS_RAW_INT"}
)
_INBOX_TYPES = _SIGNED_TYPES | {"PARAM_REQUEST_LIST", "PARAM_REQUEST_READ"}
_FEED_INDEX = {"off": 0, "px4_odometry": 1, "ardupilot_vision": 2}


def _nothing(_s: CompassSample) -> Packet | None:
    """The heading feed's slot while the feed is off."""
    return None


class BridgeServices(Protocol):
    """What the output uses of the daemon (:class:`bridge.daemon.Daemon` provides it)."""

    engine: AttitudeEngine
    link: CompassLink
    events: EventBus
    calibrator: CalibrationController
    reference: FieldReference | None

    def status(self) -> DaemonStatus:
        """Link state and counters."""
        ...


@dataclass(frozen=True, slots=True)
class MavlinkSettings:
    """Everything the output takes from the configuration (``[mavlink]``, ``[calibration]``).

    ``component_id`` None means "by role": 1 standalone, 200 (MAV_COMP_ID_IMU)
    companion. ``param_defaults`` are parameter defaults that the
    configuration sets (stream rates, heading feed, BRG_CAL_ONBOARD); values
    set over MAVLink are persisted in ``state_dir`` and win over them.
    """

    endpoints: tuple[str, ...] = ("udpout:127.0.0.1:14550",)
    system_id: int = 1
    component_id: int | None = None
    role: T.Role = "standalone"
    signing_key: bytes | None = None
    state_dir: str = ""
    param_defaults: Mapping[str, float] = field(default_factory=dict)
    queue_packets: int = DEFAULT_QUEUE_PACKETS

    def __post_init__(self) -> None:
        if self.role not in T.ROLES:
            raise ValueError(f"role must be one of {T.ROLES}, got {self.role!r}")
        if not 1 <= self.system_id <= 255:
            raise ValueError(f"system_id must be 1..255, got {self.system_id}")
        if self.component_id is not None and not 1 <= self.component_id <= 255:
            raise ValueError(f"component_id must be 1..255, got {self.component_id}")

    @property
    def effective_component_id(self) -> int:
        """Our component id."""
        if self.component_id is not None:
            return self.component_id
        return MAV_COMP_ID_IMU if self.role == "companion" else 1

    @classmethod
    def from_config(cls, cfg: Config) -> MavlinkSettings:
        """From a loaded configuration."""
        m = cfg.mavlink
        role: T.Role = "companion" if m.role == "companion" else "standalone"
        # Component 1 is the autopilot's in companion role: 1 there means "the role's default".
        comp: int | None = m.component_id
        if role == "companion" and comp == 1:
            comp = None
        defaults: dict[str, float] = {
            "BRG_CAL_ONBOARD": 1.0 if cfg.calibration.onboard else 0.0,
            "BRG_HDG_FEED": float(_FEED_INDEX[m.heading_feed]),
            "BRG_YAW_SIGMA": m.heading_feed_sigma_deg,
        }
        for s in T.STREAMS:
            defaults[s.param] = float(getattr(m, s.config_key))
        return cls(
            endpoints=tuple(m.endpoints),
            system_id=m.system_id,
            component_id=comp,
            role=role,
            signing_key=m.signing_key,
            state_dir=cfg.storage.dir,
            param_defaults=defaults,
        )


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


@dataclass(slots=True)
class OutputCounters:
    """What the output counted (besides each endpoint's own counters)."""

    inbox_dropped: int = 0
    refused_unsigned: int = 0
    refused_bad_signature: int = 0
    refused_replay: int = 0
    param_sets_refused: int = 0
    commands: int = 0
    events_relayed: int = 0
    tap_errors: int = 0
    publish_errors: int = 0  #: sample streams that failed to encode (logged once)


class MavlinkOutput:
    """The MAVLink front end (see the module docstring)."""

    def __init__(
        self,
        settings: MavlinkSettings,
        services: Callable[[], BridgeServices],
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings
        self._services_fn = services
        self._clock = clock
        self._t0 = clock()
        self.identity = T.Identity(
            settings.system_id, settings.effective_component_id, settings.role
        )
        self.signing = Signing(settings.signing_key) if settings.signing_key else None
        self.counters = OutputCounters()
        self.endpoints: list[Endpoint] = []
        self.params = ParamTable(overrides=settings.param_defaults)
        self.schedule = T.StreamSchedule({})
        self.relay = C.CalibrationRelay()
        self._svc: BridgeServices | None = None
        self._latest: CompassSample | None = None
        self._running = False  # publish() sends only between start() and close()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._inbox: deque[tuple[Any, Link]] = deque()
        self._inbox_cond = threading.Condition()
        self._threads: list[threading.Thread] = []
        self._unsubscribe: Callable[[], None] | None = None
        self._user_set: set[str] = set()  # parameters set over MAVLink (persisted)
        self._save_due: float | None = None
        self._cal_seen: Calibration | None = None
        self._wmm: FieldReference | None = None  # the WMM here ([location] or the autopilot)
        self._daemon_reference: FieldReference | None = None
        self._position: tuple[float, float, float] | None = None
        self._position_at = -math.inf
        self._alt_m = 0.0
        self._reset_counter = 0
        self._warned_magnetic_feed = False
        # Schedule id -> encoder of the per-sample stream in that slot (the heading feed's
        # slot holds the feed BRG_HDG_FEED chooses): see _apply_rates.
        self._sample_encoders: dict[int, Callable[[CompassSample], Packet | None]] = {}
        self._pending: list[_PendingAck] = []
        # Re-entrant: an event may be emitted (and finish a pending command) from inside the
        # very controller call the dispatcher makes while it holds this lock.
        self._pending_lock = threading.RLock()
        self._last_progress = -math.inf
        self._last_report = -math.inf
        self._refusal_logged: dict[str, float] = {}
        self._taps: list[Callable[[Packet], None]] = []  # see add_tap

    # ------------------------------------------------------------------ Output protocol

    @property
    def name(self) -> str:
        """Short name for logs."""
        return "mavlink"

    def publish(self, sample: CompassSample) -> None:
        """Keep ``sample`` as the latest and queue the sample streams now due; never blocks.

        Runs in the caller's (pipeline) thread: encoding is pure and cheap, and
        :meth:`Link.send <bridge.mavlink.endpoints.Link.send>` only appends to a
        bounded queue and pokes the endpoint's thread. Never raises: a failure
        is counted in ``counters.publish_errors`` and logged once.
        """
        self._latest = sample
        if not self._running:
            return
        try:
            now = self._clock()
            # The fast path, most frames at 100 Hz: no sample stream can be due before
            # sample_due_at (the schedule resets it on every rate, override or stream-set
            # change, so a change takes effect with the very next sample).
            if now < self.schedule.sample_due_at:
                return
            encoders = self._sample_encoders
            due = self.schedule.due_samples(now)
            if len(due) == 1:  # the usual due frame: one message, no list
                p = encoders[due[0]](sample)
                if p is not None:
                    self._broadcast_one(p)
                return
            # Several due on this frame: they leave together (one datagram per UDP peer).
            packets: list[Packet] = []
            try:
                for sid in due:
                    p = encoders[sid](sample)
                    if p is not None:
                        packets.append(p)
            finally:  # a stream that fails to encode does not hold back those before it
                self.broadcast(packets)
        except Exception:
            self.counters.publish_errors += 1
            if self.counters.publish_errors == 1:
                log.exception("mavlink: encoding telemetry failed (further failures counted)")

    def start(self) -> None:
        """Resolve the daemon's services, restore parameters, open endpoints, start threads."""
        if self._threads:
            raise RuntimeError("mavlink output already started")
        svc = self._services_fn()
        self._svc = svc
        self._wmm = self._daemon_reference = svc.reference
        self._load_params(svc)
        self._apply_all(svc)
        for i, text in enumerate(self.settings.endpoints):
            ep = open_endpoint(
                text,
                system_id=self.identity.system_id,
                component_id=self.identity.component_id,
                on_message=self._on_message,
                signing=self.signing,
                link_id=i,
                queue_packets=self.settings.queue_packets,
            )
            self.endpoints.append(ep)
        for ep in self.endpoints:
            ep.start()
        self._running = True
        self._unsubscribe = svc.events.subscribe(self._on_event)
        for target, name in (
            (self._telemetry_loop, "telemetry"),
            (self._dispatch_loop, "dispatch"),
        ):
            t = threading.Thread(
                target=self._guard(target, name), name=f"mavlink-{name}", daemon=True
            )
            self._threads.append(t)
            t.start()
        log.info(
            "mavlink: system %d component %d (%s)%s on %s",
            self.identity.system_id,
            self.identity.component_id,
            self.settings.role,
            ", signed" if self.signing else ", UNSIGNED",
            ", ".join(self.settings.endpoints) or "no endpoint",
        )
        if self.signing is None:
            log.warning(
                "mavlink: no signing key (mavlink.signing_key_file): anyone on the link can "
                "change parameters and recalibrate the compass"
            )

    def close(self, timeout: float) -> None:
        """Stop threads and endpoints within about ``timeout`` seconds; pending saves are written."""
        deadline = self._clock() + timeout
        self._running = False
        self._stop.set()
        self._wake.set()
        with self._inbox_cond:
            self._inbox_cond.notify_all()
        if self._unsubscribe is not None:
            self._unsubscribe()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(max(0.05, deadline - self._clock()))
        for ep in self.endpoints:
            ep.close(max(0.05, deadline - self._clock()))
        if self._save_due is not None:
            self._save_params()

    # ------------------------------------------------------------------ status

    def endpoint_counters(self) -> dict[str, EndpointCounters]:
        """Each endpoint's counters, by connection string."""
        return {ep.name: ep.counters() for ep in self.endpoints}

    def time_boot_ms(self, t: float) -> int:
        """Milliseconds since the output started, for ``t`` on the output's clock."""
        return max(0, int((t - self._t0) * 1000.0))

    def _us(self, t: float) -> int:
        return max(0, int((t - self._t0) * 1e6))

    def _guard(self, fn: Callable[[], None], name: str) -> Callable[[], None]:
        def run() -> None:
            try:
                fn()
            except Exception:
                log.exception("mavlink %s thread crashed", name)

        return run

    @property
    def svc(self) -> BridgeServices:
        """The daemon's services (after :meth:`start`)."""
        if self._svc is None:
            raise RuntimeError("mavlink output not started")
        return self._svc

    def broadcast(self, packets: list[Packet] | Packet) -> None:
        """Queue packets for every peer of every endpoint; a list goes out together, in
        order (one datagram per UDP peer while it fits: :meth:`Link.send_many
        <bridge.mavlink.endpoints.Link.send_many>`)."""
        if isinstance(packets, Packet):
            self._broadcast_one(packets)
        elif len(packets) == 1:
            self._broadcast_one(packets[0])
        elif packets:
            self._broadcast_many(packets)

    def _broadcast_one(self, p: Packet) -> None:
        for ep in self.endpoints:
            ep.broadcast(p)
        for tap in self._taps:
            try:
                tap(p)
            except Exception:  # a broken mirror must not stop the telemetry thread
                self.counters.tap_errors += 1

    def _broadcast_many(self, packets: list[Packet]) -> None:
        """:meth:`_broadcast_one` for packets that leave together: each endpoint gets them
        in one call, each tap gets each packet once, in order."""
        for ep in self.endpoints:
            ep.broadcast_many(packets)
        taps = self._taps
        if taps:
            for p in packets:
                for tap in taps:
                    try:
                        tap(p)
                    except Exception:  # a broken mirror must not stop the sender
                        self.counters.tap_errors += 1

    def add_tap(self, fn: Callable[[Packet], None]) -> Callable[[], None]:
        """Also hand every broadcast packet to ``fn`` (the Zenoh MAVLink mirror); returns the
        function that removes it. ``fn`` runs in the sending thread: it must be quick and
        must not raise."""
        self._taps = [*self._taps, fn]  # one reference store: broadcast reads the list once

        def remove() -> None:
            self._taps = [t for t in self._taps if t is not fn]

        return remove

    # ------------------------------------------------------------------ telemetry thread

    def _health(self, now: float) -> T.Health:
        svc = self.svc
        st = svc.status()
        snap = svc.calibrator.snapshot()
        latest = self._latest
        fresh = latest is not None and now - latest.t < _FRESH_S
        a = latest.attitude if latest is not None else None
        c = st.counters
        return T.Health(
            link_state=st.state,
            fresh=fresh,
            calibrating=snap.running,
            disturbed=bool(a is not None and a.disturbed),
            saturated=bool(latest is not None and latest.saturated),
            compass_use=self.params.get("COMPASS_USE") != 0,
            bad_lines=c.bad_lines_total,
            good_lines=c.frames,
            lost_frames=c.lost_frames,
            reconnects=c.reconnects,
            stale_events=c.stale_events,
            pipeline_errors=st.pipeline_errors,
        )

    def _sample_streams(self) -> list[int]:
        feed = int(self.params.get("BRG_HDG_FEED"))
        ids = [T.ATTITUDE, T.ATTITUDE_QUATERNION, T.VFR_HUD, T.SCALED_IMU, T.RAW_IMU, T.HIGHRES_IMU]
        if feed == 1:
            ids.append(T.ODOMETRY)
        elif feed == 2:
            ids.append(T.VISION_POSITION_ESTIMATE)
        return ids

    def _encode_sample(self, msgid: int, s: CompassSample) -> Packet | None:
        """One per-sample message (None when the sample cannot fill it, or not one)."""
        enc = self._ENCODERS.get(msgid)
        return enc(self, s) if enc is not None else None

    def _enc_attitude(self, s: CompassSample) -> Packet:
        # time_boot_ms(), inlined: the 50 Hz stream
        return T.attitude(s, max(0, int((s.t - self._t0) * 1000.0)))

    def _enc_attitude_quaternion(self, s: CompassSample) -> Packet:
        return T.attitude_quaternion(s, self.time_boot_ms(s.t))

    def _enc_vfr_hud(self, s: CompassSample) -> Packet:
        return T.vfr_hud(s, self._alt_m)

    def _enc_scaled_imu(self, s: CompassSample) -> Packet | None:
        return T.scaled_imu(s, self.time_boot_ms(s.t))

    def _enc_raw_imu(self, s: CompassSample) -> Packet | None:
        return T.raw_imu(s, self._us(s.t))

    def _enc_highres_imu(self, s: CompassSample) -> Packet | None:
        return T.highres_imu(s, self._us(s.t))

    def _feed_ok(self, s: CompassSample) -> bool:
        if self.params.get("COMPASS_USE") == 0 or not T.feed_usable(s):
            return False
        if s.heading_true_deg is None and not self._warned_magnetic_feed:
            self._warned_magnetic_feed = True
            log.warning(
                "mavlink: heading feed sends the MAGNETIC heading: no declination known "
                "(set [location], or COMPASS_AUTODEC=0 and COMPASS_DEC)"
            )
        return True

    def _enc_odometry(self, s: CompassSample) -> Packet | None:
        if not self._feed_ok(s):
            return None
        sigma = self.params.get("BRG_YAW_SIGMA")
        return T.odometry(s, self._us(s.t), sigma, self._reset_counter)

    def _enc_vision_position_estimate(self, s: CompassSample) -> Packet | None:
        if not self._feed_ok(s):
            return None
        sigma = self.params.get("BRG_YAW_SIGMA")
        return T.vision_position_estimate(s, self._us(s.t), sigma, self._reset_counter)

    _ENCODERS: ClassVar[dict[int, Callable[[MavlinkOutput, CompassSample], Packet | None]]] = {
        T.ATTITUDE: _enc_attitude,
        T.ATTITUDE_QUATERNION: _enc_attitude_quaternion,
        T.VFR_HUD: _enc_vfr_hud,
        T.SCALED_IMU: _enc_scaled_imu,
        T.RAW_IMU: _enc_raw_imu,
        T.HIGHRES_IMU: _enc_highres_imu,
        T.ODOMETRY: _enc_odometry,
        T.VISION_POSITION_ESTIMATE: _enc_vision_position_estimate,
    }

    def _schedule_id(self, msgid: int) -> int:
        # VISION_POSITION_ESTIMATE shares the heading feed's schedule slot.
        return T.ODOMETRY if msgid == T.VISION_POSITION_ESTIMATE else msgid

    def _telemetry_loop(self) -> None:
        # Paced by the clock streams and the calibration keep-alive, not by the frame rate:
        # sample streams go out from publish().
        while not self._stop.is_set():
            now = self._clock()
            due_at = min(
                self.schedule.next_clock_due(now), self._last_progress + _PROGRESS_PERIOD_S
            )
            self._wake.wait(min(0.5, max(0.0, due_at - now)))
            self._wake.clear()
            if self._stop.is_set():
                break
            now = self._clock()
            out: list[Packet] = []
            clock_due = self.schedule.due_on_clock(now)
            if clock_due:
                h = self._health(now)
                for msgid in clock_due:
                    if msgid == T.HEARTBEAT:
                        out.append(T.heartbeat(self.identity, T.system_status(h)))
                    elif msgid == T.SYS_STATUS:
                        out.append(T.sys_status(h))
            out += self._calibration_keepalive(now)
            if out:
                self.broadcast(out)
            self._expire_pending(now)

    def _calibration_keepalive(self, now: float) -> list[Packet]:
        """MAG_CAL_PROGRESS while a magnetometer calibration runs; the report until accepted."""
        if now - self._last_progress < _PROGRESS_PERIOD_S:
            return []  # the controller is asked twice a second, not on every frame
        self._last_progress = now
        snap = self.svc.calibrator.snapshot()
        out: list[Packet] = []
        if snap.running and snap.mode in ("mag", "onboard_mag"):
            out.append(self._progress_packet(snap))
        elif (
            snap.pending_accept
            and snap.last_report is not None
            and now - self._last_report >= _REPORT_PERIOD_S
        ):
            self._last_report = now
            out.append(T.mag_cal_report(C.report_from_dict(snap.last_report)))
        return out

    @staticmethod
    def _progress_packet(snap: Any) -> Packet:
        return T.mag_cal_progress(
            int(snap.status),
            snap.attempt,
            snap.completion_pct,
            snap.completion_mask,
            snap.direction,
        )

    # ------------------------------------------------------------------ events

    def _on_event(self, event: Event) -> None:
        """EventBus subscriber (any thread): relay, finish IN_PROGRESS commands, and have the
        dispatch thread look at once for what the event may have changed (a calibration)."""
        with self._inbox_cond:
            self._inbox_cond.notify()
        packets = self.relay.packets(event)
        if packets:
            self.counters.events_relayed += 1
            self.broadcast(packets)
        with self._pending_lock:
            done = [
                p for p in self._pending if event.kind in p.kinds or event.kind in p.failure_kinds
            ]
            if not done:
                return
            self._pending = [p for p in self._pending if p not in done]
            # Under the lock: the IN_PROGRESS ack of the same command goes out first.
            for p in done:
                result = C.FAILED if event.kind in p.failure_kinds else C.ACCEPTED
                p.link.send(T.command_ack(p.command, result, p.system, p.component, progress=100))

    def _expire_pending(self, now: float) -> None:
        with self._pending_lock:
            if not self._pending:
                return
            late = [p for p in self._pending if now > p.deadline]
            self._pending = [p for p in self._pending if p not in late]
        for p in late:
            log.warning("mavlink: no outcome for command %d in time; answering FAILED", p.command)
            p.link.send(T.command_ack(p.command, C.FAILED, p.system, p.component))

    # ------------------------------------------------------------------ inbound

    def _on_message(self, msg: Any, link: Link) -> None:
        """Endpoint threads: answer TIMESYNC at once, queue what the dispatcher handles."""
        kind = msg.get_type()
        if kind == "TIMESYNC":
            if int(msg.tc1) == 0:  # a request: answer with our time, echo theirs
                now_ns = int((self._clock() - self._t0) * 1e9)
                link.send(T.timesync_reply(now_ns, int(msg.ts1)))
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
        while not self._stop.is_set():
            with self._inbox_cond:
                if not self._inbox:
                    wait = _HOUSEKEEPING_S
                    if self._save_due is not None:
                        wait = min(wait, max(0.0, self._save_due - self._clock()))
                    self._inbox_cond.wait(wait)
                item = self._inbox.popleft() if self._inbox else None
            if item is not None:
                msg, link = item
                try:
                    self._handle(msg, link)
                except Exception:
                    log.exception("mavlink: handling %s failed", msg.get_type())
            self._housekeeping()

    def _housekeeping(self) -> None:
        now = self._clock()
        if self._save_due is not None and now >= self._save_due:
            self._save_params()
        svc = self.svc
        cal = svc.engine.calibration
        if cal is not self._cal_seen:
            self._calibration_changed(cal)
        if svc.reference is not self._daemon_reference:
            # [location] changed (a configuration reload): the WMM there, then our declination rule
            self._daemon_reference = self._wmm = svc.reference
            self._apply_declination()

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
        now = self._clock()
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

    def _for_us(self, target_system: int, target_component: int) -> bool:
        return target_system in (0, self.identity.system_id) and target_component in (
            0,
            self.identity.component_id,
        )

    def _handle(self, msg: Any, link: Link) -> None:
        kind = msg.get_type()
        if kind in _SIGNED_TYPES and self._refuse_unsigned(msg):
            return
        if kind in ("COMMAND_LONG", "COMMAND_INT"):
            self._handle_command(C.command_from_message(msg), link)
        elif kind == "PARAM_REQUEST_LIST":
            if self._for_us(msg.target_system, msg.target_component):
                for i in range(len(self.params)):
                    link.send(self._param_value_at(i))
        elif kind == "PARAM_REQUEST_READ":
            if self._for_us(msg.target_system, msg.target_component):
                self._param_read(msg, link)
        elif kind == "PARAM_SET":
            if self._for_us(msg.target_system, msg.target_component):
                self._param_set(msg)
        elif kind in ("GLOBAL_POSITION_INT", "GPS_RAW_INT"):
            self._position_message(msg)

    # ------------------------------------------------------------------ parameters

    def _param_value_at(self, index: int) -> Packet:
        spec, value = self.params.by_index(index)
        return T.param_value(spec.name, value, spec.ptype, len(self.params), index)

    def _param_value(self, name: str) -> Packet:
        return self._param_value_at(self.params.index(name))

    def _param_read(self, msg: Any, link: Link) -> None:
        idx = int(msg.param_index)
        if idx >= 0:
            if idx < len(self.params):
                link.send(self._param_value_at(idx))
            return
        name = param_name(msg.param_id)
        if self.params.spec(name) is not None:
            link.send(self._param_value(name))

    def _param_set(self, msg: Any) -> None:
        name = param_name(msg.param_id)
        spec = self.params.spec(name)
        if spec is None:
            log.warning("mavlink: PARAM_SET of unknown parameter %r ignored", name)
            self.counters.param_sets_refused += 1
            return
        old = self.params.get(name)
        outcome = self.params.set(name, float(msg.param_value), int(msg.param_type))
        reason = outcome.reason
        if outcome.accepted and outcome.value != old:
            reason = self._apply_param(name, old)
            if reason:
                self.params.restore(name, old)
        if reason:
            self.counters.param_sets_refused += 1
            log.warning(
                "mavlink: PARAM_SET %s = %r (type %d) refused: %s; stays %g",
                name,
                msg.param_value,
                msg.param_type,
                reason,
                self.params.get(name),
            )
        elif outcome.value != old:
            log.info("mavlink: %s = %g (was %g)", name, outcome.value, old)
            self._user_set.add(name)
            self._mark_dirty()
        # Every SET is answered by the value now in force, on every link (other GCSs learn it).
        self.broadcast(self._param_value(name))

    def _apply_param(self, name: str, old: float) -> str:
        """The side effects of a changed parameter; a non-empty reason undoes the change."""
        spec = self.params.spec(name)
        assert spec is not None
        svc = self.svc
        group = spec.group
        if group == "cal":
            try:
                cal = calibration_from_values(self.params.values(), svc.engine.calibration.accel)
            except ValueError as e:
                return f"the calibration it gives is unusable ({e})"
            self._cal_seen = cal  # our own change: the values stay as the user set them
            svc.calibrator.apply_calibration(cal, source="parameters", write_device=False)
            self._reset_counter += 1
        elif group == "dec":
            self._apply_declination()
        elif group == "mount":
            self._apply_mounting()
            self._reset_counter += 1
        elif group == "limits":
            try:
                svc.engine.update_limits(
                    limits_from_values(self.params.values(), svc.engine.limits)
                )
            except ValueError as e:
                return str(e)
        elif group == "routing":
            svc.calibrator.onboard = self.params.get("BRG_CAL_ONBOARD") != 0
        elif group in ("rates", "feed"):
            self._apply_rates()
        return ""

    def _apply_rates(self) -> None:
        """BRG_SR_* into the schedule's rates; BRG_HDG_FEED into its set of sample streams.

        Called on every change of either (parameter SET, storage read/reset, start): the
        schedule's fast path (see :meth:`publish`) depends on both.
        """
        for s in T.STREAMS:
            self.schedule.set_base(s.msgid, self.params.get(s.param))
        wanted = self._sample_streams()
        enc = self._ENCODERS
        # Encoders first, then the schedule: publish() in the pipeline (reader thread) may see the
        # new encoders with the old streams (a feed just switched off: its slot encodes
        # nothing), never a due stream without an encoder.
        encoders: dict[int, Callable[[CompassSample], Packet | None]] = {
            T.ODOMETRY: _nothing,
            **{self._schedule_id(m): MethodType(enc[m], self) for m in wanted},
        }
        self._sample_encoders = encoders
        self.schedule.set_sample_streams(self._schedule_id(m) for m in wanted)

    def _apply_mounting(self) -> None:
        engine = self.svc.engine
        cur = engine.mounting
        want = Rotation(int(self.params.get("AHRS_ORIENTATION")))
        if cur.orientation is not want:
            engine.update_mounting(
                Mounting(
                    orientation=want,
                    trim_roll_deg=cur.trim_roll_deg,
                    trim_pitch_deg=cur.trim_pitch_deg,
                    trim_yaw_deg=cur.trim_yaw_deg,
                )
            )

    def _apply_declination(self) -> None:
        """COMPASS_AUTODEC=1: the WMM's declination (shown in COMPASS_DEC); 0: COMPASS_DEC's."""
        engine = self.svc.engine
        wmm = self._wmm
        if self.params.get("COMPASS_AUTODEC") != 0:
            ref = wmm
            if wmm is not None and wmm.declination_deg is not None:
                self.params.put("COMPASS_DEC", math.radians(wmm.declination_deg))
        else:
            ref = FieldReference(
                declination_deg=math.degrees(self.params.get("COMPASS_DEC")),
                total_G=wmm.total_G if wmm is not None else None,
                dip_deg=wmm.dip_deg if wmm is not None else None,
                source="COMPASS_DEC",
            )
        if ref != engine.reference:
            engine.update_reference(ref)
            self._reset_counter += 1

    def _apply_all(self, svc: BridgeServices) -> None:
        """Bring the engine, calibrator and schedule in line with the parameters (at start)."""
        self._cal_seen = svc.engine.calibration
        self._apply_mounting()
        self._apply_declination()
        limits = limits_from_values(self.params.values(), svc.engine.limits)
        if limits != svc.engine.limits:
            svc.engine.update_limits(limits)
        svc.calibrator.onboard = self.params.get("BRG_CAL_ONBOARD") != 0
        self._apply_rates()

    def _calibration_changed(self, cal: Calibration) -> None:
        """A calibration from elsewhere (a fit, a reset): show it as COMPASS_* and tell the GCSs."""
        self._cal_seen = cal
        self._reset_counter += 1
        before = {n: self.params.get(n) for n in CAL_PARAMS}
        for name, v in view_values(cal.mag).items():
            self.params.put(name, v)
        changed = [n for n in CAL_PARAMS if self.params.get(n) != before[n]]
        for n in changed:
            self._user_set.discard(n)
            self.broadcast(self._param_value(n))
        self._mark_dirty()

    def _mark_dirty(self) -> None:
        if self._save_due is None:
            self._save_due = self._clock() + _SAVE_DELAY_S

    def _store(self) -> StateStore | None:
        return StateStore(self.settings.state_dir) if self.settings.state_dir else None

    def _save_params(self) -> None:
        self._save_due = None
        store = self._store()
        if store is None:
            return
        values = self.params.values()
        payload: dict[str, Any] = {
            # Only what was set over MAVLink: configuration defaults stay in charge otherwise.
            "set": {n: values[n] for n in sorted(self._user_set) if n not in CAL_PARAMS},
            # The calibration group as shown, and the calibration it was shown for.
            "calibration_view": {n: values[n] for n in CAL_PARAMS},
            "calibration": self.svc.engine.calibration.to_dict(),
        }
        try:
            store.save(PARAMS_DOCUMENT, payload)
        except StorageError as e:
            log.error("mavlink: parameters not saved: %s", e)
            self.svc.events.emit(
                Event(
                    "params.storage_error",
                    "Parameters NOT saved",
                    Severity.ERROR,
                    {"error": str(e)},
                )
            )

    def _load_params(self, svc: BridgeServices) -> None:
        """Restore persisted parameters (refusing, with a warning, what no longer validates)."""
        cal = svc.engine.calibration
        for name, v in view_values(cal.mag).items():
            self.params.put(name, v)
        store = self._store()
        if store is None:
            return
        try:
            loaded = store.load(PARAMS_DOCUMENT)
        except Exception as e:  # an unreadable state dir must not stop the bridge
            log.warning("mavlink: cannot read stored parameters: %s", e)
            return
        for p in loaded.problems:
            log.warning("mavlink: stored parameters: %s", p)
        doc = loaded.payload
        if not isinstance(doc, dict):
            return
        stored_set = doc.get("set")
        if isinstance(stored_set, dict):
            for name, v in stored_set.items():
                spec = self.params.spec(str(name))
                if spec is None or spec.group == "cal":
                    log.warning("mavlink: stored parameter %r unknown, ignored", name)
                    continue
                out = self.params.set(spec.name, v, spec.ptype)
                if out.accepted:
                    self._user_set.add(spec.name)
                else:
                    log.warning("mavlink: stored %s = %r refused (%s)", name, v, out.reason)
        view, stored_cal = doc.get("calibration_view"), doc.get("calibration")
        if isinstance(view, dict) and isinstance(stored_cal, dict):
            try:
                same = same_calibration(Calibration.from_dict(stored_cal), cal)
            except (KeyError, TypeError, ValueError):
                same = False
            if same and all(isinstance(view.get(n), int | float) for n in CAL_PARAMS):
                # The values as the user set them (the calibration itself came from its own file).
                for n in CAL_PARAMS:
                    self.params.put(n, float(view[n]))

    # ------------------------------------------------------------------ position (companion)

    def _position_message(self, msg: Any) -> None:
        if self.settings.role != "companion" or msg.get_srcSystem() != self.identity.system_id:
            return
        if msg.get_type() == "GPS_RAW_INT" and int(msg.fix_type) < 2:
            return  # no fix
        lat, lon = msg.lat * 1e-7, msg.lon * 1e-7
        alt = msg.alt * 1e-3
        if (lat == 0.0 and lon == 0.0) or not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            return
        self._alt_m = alt
        now = self._clock()
        prev = self._position
        moved = prev is None or max(abs(lat - prev[0]), abs(lon - prev[1])) > _POSITION_MOVE_DEG
        if not moved and now - self._position_at < _POSITION_MIN_S:
            return
        try:
            ref = field_reference_at(lat, lon, alt)
            ef = earth_field(lat, lon, alt)
        except ValueError as e:
            log.warning("mavlink: autopilot position %.5f, %.5f unusable: %s", lat, lon, e)
            return
        self._position, self._position_at = (lat, lon, alt), now
        if prev is None:
            log.info(
                "mavlink: position from the autopilot %.5f, %.5f: declination %+.2f deg",
                lat,
                lon,
                ref.declination_deg or 0.0,
            )
        self._wmm = ref
        self.svc.calibrator.set_field(ef)
        self._apply_declination()

    # ------------------------------------------------------------------ commands

    def _ack(self, cmd: C.Command, link: Link, result: int, progress: int = 0) -> None:
        link.send(
            T.command_ack(cmd.command, result, cmd.source_system, cmd.source_component, progress)
        )

    def _handle_command(self, cmd: C.Command, link: Link) -> None:
        if not cmd.addressed_to(self.identity.system_id, self.identity.component_id):
            return
        self.counters.commands += 1
        handler = self._HANDLERS.get(cmd.command)
        if handler is None:
            # Beside an autopilot, a broadcast command we do not know is the autopilot's
            # business: answering UNSUPPORTED would race its real answer.
            if not (cmd.broadcast and self.settings.role == "companion"):
                self._ack(cmd, link, C.UNSUPPORTED)
            return
        result = handler(self, cmd, link)
        if result is not None:
            self._ack(cmd, link, result)
        log.info(
            "mavlink: command %d from %d/%d: %s",
            cmd.command,
            cmd.source_system,
            cmd.source_component,
            C.RESULT_NAMES.get(result, "answered") if result is not None else "answered",
        )

    def _long_work(
        self,
        cmd: C.Command,
        link: Link,
        work: Callable[[], bool],
        kinds: tuple[str, ...],
        failures: tuple[str, ...],
    ) -> bool:
        """Run ``work``; if it returns True the command is long work: IN_PROGRESS now, and
        the final COMMAND_ACK when one of ``kinds`` (ACCEPTED) or ``failures`` (FAILED)
        is emitted, or FAILED after a time-out. Registered *before* the work starts, so an
        outcome that comes at once is not missed; the lock keeps the two acks in order.
        """
        pending = _PendingAck(
            cmd.command,
            link,
            cmd.source_system,
            cmd.source_component,
            kinds,
            failures,
            self._clock() + _FINAL_ACK_TIMEOUT_S,
        )
        with self._pending_lock:
            self._pending.append(pending)
            long = False
            try:
                long = work()
            finally:
                if not long and pending in self._pending:
                    self._pending.remove(pending)
            if long:
                self._ack(cmd, link, C.IN_PROGRESS, progress=0)
        return long

    def _cmd_start_mag_cal(self, cmd: C.Command, link: Link) -> int | None:
        mask = C.whole(cmd.p(1))
        if mask is None or not 0 <= mask <= 255:
            return C.DENIED
        self.relay.begin("ardupilot")
        out = self.svc.calibrator.start_mag(
            mask=mask, retry=cmd.p(2) != 0, autosave=cmd.p(3) != 0, delay_s=max(0.0, cmd.p(4))
        )
        if not out.ok:
            self.relay.begin(None)
            log.warning("mavlink: magnetometer calibration not started: %s", out.message)
        self._last_progress = -math.inf
        self._wake.set()  # the first MAG_CAL_PROGRESS now, not at the telemetry thread's next tick
        return C.result_code(out)

    def _cmd_accept_mag_cal(self, cmd: C.Command, link: Link) -> int | None:
        mask = C.whole(cmd.p(1))
        if mask is None or not 0 <= mask <= 255:
            return C.DENIED
        outcome: list[Outcome] = []

        def accept() -> bool:
            outcome.append(self.svc.calibrator.accept(mask))
            # The device's MAGCAL,END: its answer (RANGE failure included) comes as an event.
            return outcome[0].result is Result.IN_PROGRESS

        if self._long_work(cmd, link, accept, ("calibration.done",), ("calibration.failed",)):
            return None
        return C.result_code(outcome[0])

    def _cmd_cancel_mag_cal(self, cmd: C.Command, link: Link) -> int | None:
        mask = C.whole(cmd.p(1))
        out = self.svc.calibrator.cancel(mask if mask is not None and 0 <= mask <= 255 else 0)
        # ArduPilot answers ACCEPTED whatever the state; QGroundControl probes with it.
        return C.ACCEPTED if out.ok else C.result_code(out)

    def _cmd_fixed_yaw(self, cmd: C.Command, link: Link) -> int | None:
        mask = C.whole(cmd.p(2))
        if mask is None or not 0 <= mask <= 255:
            return C.DENIED
        lat, lon = cmd.p(3), cmd.p(4)
        self.relay.begin("ardupilot")
        out = self.svc.calibrator.fixed_yaw(
            cmd.p(1),
            mask=mask,
            latitude_deg=lat if (lat or lon) else None,
            longitude_deg=lon if (lat or lon) else None,
        )
        if not out.ok:
            self.relay.begin(None)
            log.warning("mavlink: fixed-yaw calibration refused: %s", out.message)
        return C.result_code(out)

    def _cmd_preflight_calibration(self, cmd: C.Command, link: Link) -> int | None:
        p = [C.whole(cmd.p(i)) for i in range(1, 8)]
        if any(v is None for v in p):
            return C.DENIED
        cal = self.svc.calibrator
        if all(v == 0 for v in p):
            cal.cancel()  # PX4: all zero cancels (the event says "[cal] calibration cancelled")
            return C.ACCEPTED
        requests = [i for i, v in enumerate(p, start=1) if v != 0]
        if requests == [2] and p[1] == 1:
            self.relay.begin("px4")
            out = cal.start_mag(autosave=True)  # PX4 has no accept step: a success is saved
        elif requests == [5] and p[4] == 1:
            self.relay.begin("px4")
            out = cal.start_accel()
        elif requests == [5] and p[4] == 2:
            self.relay.begin("px4")
            out = cal.start_level()
        else:
            return C.UNSUPPORTED  # gyro, baro, radio, airspeed, ESC: not this device
        if not out.ok:
            self.relay.begin(None)
            # PX4 reports a refusal the same way as a failure, so QGroundControl shows it.
            self.broadcast(
                T.statustext(int(Severity.ERROR), C.cal_line(f"calibration failed: {out.message}"))
            )
        self._last_progress = -math.inf
        self._wake.set()  # the first MAG_CAL_PROGRESS now, not at the telemetry thread's next tick
        return C.result_code(out)

    def _cmd_preflight_storage(self, cmd: C.Command, link: Link) -> int | None:
        action = C.whole(cmd.p(1))
        svc = self.svc
        if action == 0:  # read: back to the stored values
            if self._save_due is not None:  # every SET counts as saved: write it first
                self._save_params()
            self._user_set.clear()
            self.params = ParamTable(overrides=self.settings.param_defaults)
            self._load_params(svc)
            self._apply_all(svc)
            self._broadcast_all_params()
            return C.ACCEPTED
        if action == 1:  # write: parameters, calibration file and the compass flash
            self._save_params()
            link_ok = svc.link.protocol == "gmr" and svc.link.state is LinkState.STREAMING

            def write() -> bool:
                cal = svc.engine.calibration
                svc.calibrator.apply_calibration(cal, source="storage", write_device=link_ok)
                self._cal_seen = cal
                return link_ok  # the flash write (PAR,SET) reports as an event

            done = ("calibration.device_updated",)
            if self._long_work(cmd, link, write, done, ("calibration.device_error",)):
                return None
            return C.ACCEPTED
        if action == 2:  # reset the bridge's parameters (not the calibration) to defaults
            for spec in self.params.specs:
                if spec.group != "cal" and not spec.read_only and spec.name != "COMPASS_DEC":
                    self.params.restore(spec.name, self.params.defaults[spec.name])
            self._user_set.clear()
            self._apply_all(svc)
            self._save_params()
            self._broadcast_all_params()
            return C.ACCEPTED
        if action == 3:  # reset the calibration to identity (the compass flash keeps its own)
            out = svc.calibrator.apply_calibration(
                Calibration(), source="reset", write_device=False
            )
            return C.result_code(out)
        return C.DENIED

    def _broadcast_all_params(self) -> None:
        for i in range(len(self.params)):
            self.broadcast(self._param_value_at(i))

    def _cmd_set_message_interval(self, cmd: C.Command, link: Link) -> int | None:
        msgid = C.whole(cmd.p(1))
        interval = cmd.p(2)
        if msgid is None or msgid not in T.STREAMABLE or not math.isfinite(interval):
            return C.DENIED
        sid = self._schedule_id(msgid)
        if interval == -1:
            self.schedule.set_override(sid, 0.0)
        elif interval == 0:
            self.schedule.set_override(sid, None)
        elif interval >= 10_000:  # at most 100 Hz, the device's fastest frame rate
            self.schedule.set_override(sid, 1e6 / interval)
        else:
            return C.DENIED
        return C.ACCEPTED

    def _cmd_get_message_interval(self, cmd: C.Command, link: Link) -> int | None:
        msgid = C.whole(cmd.p(1))
        if msgid is None or not 0 <= msgid <= 0xFFFF:
            return C.DENIED
        sid = self._schedule_id(msgid)
        interval = self.schedule.interval_us(sid) if msgid in T.STREAMABLE else 0
        self._ack(cmd, link, C.ACCEPTED)
        link.send(T.message_interval(msgid, interval))
        return None

    def _cmd_request_message(self, cmd: C.Command, link: Link) -> int | None:
        msgid = C.whole(cmd.p(1))
        if msgid is None:
            return C.DENIED
        packet = self._requested(msgid)
        if packet is None:
            known = msgid in T.STREAMABLE or msgid in (
                T.AUTOPILOT_VERSION,
                T.MAG_CAL_REPORT,
                T.MAG_CAL_PROGRESS,
            )
            return C.FAILED if known else C.DENIED
        self._ack(cmd, link, C.ACCEPTED)
        if C.whole(cmd.p(7)) == 2:
            self.broadcast(packet)
        else:
            link.send(packet)
        return None

    def _cmd_request_capabilities(self, cmd: C.Command, link: Link) -> int | None:
        packet = self._requested(T.AUTOPILOT_VERSION)
        assert packet is not None
        self._ack(cmd, link, C.ACCEPTED)
        link.send(packet)
        return None

    def _requested(self, msgid: int) -> Packet | None:
        """A message asked for with MAV_CMD_REQUEST_MESSAGE (None: cannot be produced now)."""
        now = self._clock()
        if msgid == T.AUTOPILOT_VERSION:
            v = self.svc.link.version
            serial = v.serial if v is not None else None
            uid = zlib.crc32(serial.encode()) if serial else 0
            return T.autopilot_version(__version__, v.firmware if v else None, serial, uid)
        if msgid == T.HEARTBEAT:
            return T.heartbeat(self.identity, T.system_status(self._health(now)))
        if msgid == T.SYS_STATUS:
            return T.sys_status(self._health(now))
        if msgid == T.MAG_CAL_REPORT:
            snap = self.svc.calibrator.snapshot()
            r = snap.last_report
            return T.mag_cal_report(C.report_from_dict(r)) if r is not None else None
        if msgid == T.MAG_CAL_PROGRESS:
            return self._progress_packet(self.svc.calibrator.snapshot())
        s = self._latest
        if s is None or now - s.t > _FRESH_S:
            return None
        return self._encode_sample(msgid, s)

    _HANDLERS: ClassVar[dict[int, Callable[[MavlinkOutput, C.Command, Link], int | None]]] = {
        C.DO_START_MAG_CAL: _cmd_start_mag_cal,
        C.DO_ACCEPT_MAG_CAL: _cmd_accept_mag_cal,
        C.DO_CANCEL_MAG_CAL: _cmd_cancel_mag_cal,
        C.FIXED_MAG_CAL_YAW: _cmd_fixed_yaw,
        C.PREFLIGHT_CALIBRATION: _cmd_preflight_calibration,
        C.PREFLIGHT_STORAGE: _cmd_preflight_storage,
        C.SET_MESSAGE_INTERVAL: _cmd_set_message_interval,
        C.GET_MESSAGE_INTERVAL: _cmd_get_message_interval,
        C.REQUEST_MESSAGE: _cmd_request_message,
        C.REQUEST_AUTOPILOT_CAPABILITIES: _cmd_request_capabilities,
    }
