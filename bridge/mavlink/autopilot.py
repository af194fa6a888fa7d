"""The autopilot beside a companion bridge: who it is, what it needs, and what it must be spared.

Three pieces, all driven by the MAVLink output (messages in from the endpoint
threads through :meth:`AutopilotWatch.heard`, time from its telemetry thread
through :meth:`AutopilotWatch.tick`, which returns what to send and where):

* **The autopilot's identity and state** from its HEARTBEAT (our system id, a
  vehicle: ``autopilot`` not INVALID, not a ground station): its component, its
  flavour (ArduPilot, PX4), whether it is armed (``base_mode`` SAFETY_ARMED).
  A heading feed sent with the autopilot's own system *and* component id is
  dropped by ArduPilot (``MAVLink_routing::check_and_forward``); :attr:`same_identity`
  says when that is so, and the output then withholds the feed.
* **Messages the companion needs** (:class:`StreamRequests`): when one is not
  heard within :data:`REQUEST_AFTER_S` of the autopilot's first HEARTBEAT, ask
  for it as ground stations do -- MAV_CMD_SET_MESSAGE_INTERVAL to the
  autopilot, then, for ArduPilot, REQUEST_DATA_STREAM for the stream group that
  carries it (its SRx_ parameters) -- and say so in the log.
* **Heading steps and the autopilot's estimator** (:meth:`AutopilotWatch.guard`,
  :meth:`AutopilotWatch.heading_stepped`). PX4's EKF2 resets its yaw when the
  feed's ``reset_counter`` changes; ArduPilot's EKF3 does not (the counter only
  resets *position*: ``writeExtNavData``) and fuses a step as a measurement,
  learning it into its gyro bias. It realigns its yaw to external navigation only
  when its yaw *source* changes (``setYawSource`` -> ``yaw_source_reset`` ->
  ``alignYawAngle``). So for an ArduPilot fed by ``ardupilot_vision``: a change
  that steps the heading is refused while it is armed (the guard); when it is
  disarmed the change is applied and the bridge switches ArduPilot's EKF to
  source set 2 and, :data:`RESET_HOLD_S` later, back to 1
  (MAV_CMD_SET_EKF_SOURCE_SET), so EKF3 realigns its yaw to the new heading.
  Figures and sources: docs/mavlink.md, "Heading changes and the autopilot".
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bridge.app.settings import EngineSettings
from bridge.events import Event, EventBus, Severity
from bridge.mavlink.dialect import Message, message
from bridge.mavlink.dialect import mavlink as M  # noqa: N812 - the generated module, short

log = logging.getLogger(__name__)

#: A wanted message not heard this long after the autopilot's first HEARTBEAT is asked for.
REQUEST_AFTER_S = 3.0
#: Asked again this often while still not heard, at most :data:`REQUEST_TRIES` times.
REQUEST_EVERY_S = 5.0
REQUEST_TRIES = 5
#: The autopilot counts as gone (not armed, not known) after this long without a HEARTBEAT.
AUTOPILOT_TIMEOUT_S = 5.0
#: ArduPilot's yaw reset: the switch back to source set 1 comes this long after the switch
#: to set 2 (and the heading step). Longer than EKF3's fusion horizon lags behind the
#: samples it receives (its largest sensor delay), so every sample that arrived before
#: the step is recalled -- and not fused -- while set 2 is active, and the first one
#: recalled after the switch back carries the new heading: EKF3 realigns to it.
RESET_HOLD_S = 0.4
#: Refusal events at most this often (a learned step is retried every block).
_REFUSAL_EVENT_S = 30.0

FEED_ARDUPILOT = 2  #: BRG_HDG_FEED value of the ArduPilot feed (VISION_POSITION_ESTIMATE)

SET_EKF_SOURCE_SET = int(M.MAV_CMD_SET_EKF_SOURCE_SET)
SET_MESSAGE_INTERVAL = int(M.MAV_CMD_SET_MESSAGE_INTERVAL)
_ARMED = int(M.MAV_MODE_FLAG_SAFETY_ARMED)
_NOT_VEHICLES = frozenset(
    int(t)
    for t in (
        M.MAV_TYPE_GCS,
        M.MAV_TYPE_ONBOARD_CONTROLLER,
        M.MAV_TYPE_GIMBAL,
        M.MAV_TYPE_ADSB,
        M.MAV_TYPE_IMU,
        M.MAV_TYPE_CAMERA,
    )
)

Send = Callable[[Message], None]


@dataclass(frozen=True, slots=True)
class Wanted:
    """A message the companion needs from the autopilot: its id, the rate to ask for, and
    ArduPilot's stream group carrying it (MAV_DATA_STREAM, for REQUEST_DATA_STREAM)."""

    msgid: int
    hz: float
    ardupilot_stream: int


#: The position for the declination (the WMM there) and the altitude for VFR_HUD: asked
#: for by a companion without ``[location]``.
POSITION = Wanted(M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 1.0, M.MAV_DATA_STREAM_POSITION)


class StreamRequests:
    """Asks the autopilot for the messages the companion needs and does not hear.

    Generic over the messages: :meth:`want` adds one, e.g. the autopilot's attitude::

        output.autopilot.requests.want(
            mavlink.MAVLINK_MSG_ID_ATTITUDE, 10.0, mavlink.MAV_DATA_STREAM_EXTRA1
        )

    (call it before or after the output starts; any thread). For each wanted message that has not arrived
    :data:`REQUEST_AFTER_S` after the autopilot's first HEARTBEAT (or stops for that
    long), :meth:`due` returns MAV_CMD_SET_MESSAGE_INTERVAL (ArduPilot and PX4 both
    serve it, per link: the request comes from the link the answer should go to) and,
    for an ArduPilot, REQUEST_DATA_STREAM of its stream group -- the way ground stations
    set ArduPilot's SRx_ rates -- and logs once what it asked for and why. It asks again
    every :data:`REQUEST_EVERY_S`, at most :data:`REQUEST_TRIES` times, and stops as soon
    as the message is heard. Thread-safe: :meth:`heard` runs in the endpoint threads,
    :meth:`due` in the output's telemetry thread.
    """

    def __init__(self, wanted: tuple[Wanted, ...] = ()) -> None:
        self._lock = threading.Lock()
        self._wanted: dict[int, Wanted] = {w.msgid: w for w in wanted}
        self._last_heard: dict[int, float] = {}
        self._asked: dict[int, tuple[int, float]] = {}  # msgid -> (tries, last asked)
        self.requests_sent = 0  #: SET_MESSAGE_INTERVAL / REQUEST_DATA_STREAM sent

    def want(self, msgid: int, hz: float, ardupilot_stream: int) -> None:
        """Add a message to ask for (or change its rate)."""
        if not (math.isfinite(hz) and hz > 0.0):
            raise ValueError(f"hz must be a positive number, got {hz!r}")
        with self._lock:
            self._wanted[msgid] = Wanted(msgid, hz, ardupilot_stream)

    @property
    def wanted(self) -> tuple[int, ...]:
        """The message ids asked for when missing."""
        with self._lock:
            return tuple(self._wanted)

    def heard(self, msgid: int, now: float) -> None:
        """A message arrived from the autopilot."""
        if msgid in self._wanted:
            self._last_heard[msgid] = now

    def due(
        self, now: float, autopilot_since: float, target: tuple[int, int], ardupilot: bool
    ) -> list[Message]:
        """The requests to send now to ``target`` (the autopilot, heard since
        ``autopilot_since``)."""
        out: list[Message] = []
        with self._lock:
            wanted = list(self._wanted.values())
        for w in wanted:
            last = self._last_heard.get(w.msgid, autopilot_since)
            if now - last < REQUEST_AFTER_S:
                self._asked.pop(w.msgid, None)  # heard: a later silence starts afresh
                continue
            tries, at = self._asked.get(w.msgid, (0, -math.inf))
            if tries >= REQUEST_TRIES or now - at < REQUEST_EVERY_S:
                continue
            self._asked[w.msgid] = (tries + 1, now)
            name = M.mavlink_map[w.msgid].msgname if w.msgid in M.mavlink_map else str(w.msgid)
            if tries == 0:
                log.info(
                    "mavlink: no %s from the autopilot in %.0f s: asking it for %g Hz "
                    "(SET_MESSAGE_INTERVAL%s)",
                    name,
                    now - last,
                    w.hz,
                    ", REQUEST_DATA_STREAM" if ardupilot else "",
                )
            out.append(command_long(target, SET_MESSAGE_INTERVAL, w.msgid, 1e6 / w.hz))
            if ardupilot:
                out.append(
                    message(
                        M.MAVLINK_MSG_ID_REQUEST_DATA_STREAM,
                        target_system=target[0],
                        target_component=target[1],
                        req_stream_id=w.ardupilot_stream,
                        req_message_rate=max(1, round(w.hz)),
                        start_stop=1,
                    )
                )
        self.requests_sent += len(out)
        return out


def command_long(target: tuple[int, int], command: int, *params: float) -> Message:
    """COMMAND_LONG to ``target`` (missing parameters 0)."""
    p = [float(x) for x in params] + [0.0] * (7 - len(params))
    return message(
        M.MAVLINK_MSG_ID_COMMAND_LONG,
        target_system=target[0],
        target_component=target[1],
        command=command,
        confirmation=0,
        param1=p[0],
        param2=p[1],
        param3=p[2],
        param4=p[3],
        param5=p[4],
        param6=p[5],
        param7=p[6],
    )


@dataclass(slots=True)
class _Reset:
    """ArduPilot's yaw reset in progress (times on the output's clock)."""

    started: float
    back_sent: bool = False


class AutopilotWatch:
    """The autopilot beside a companion bridge (see the module docstring).

    ``identity`` is our (system, component); ``feed`` returns BRG_HDG_FEED now;
    ``events`` is where refusals and resets are told (STATUSTEXT, Zenoh, log).
    """

    def __init__(
        self,
        identity: tuple[int, int],
        feed: Callable[[], int],
        events: EventBus,
        clock: Callable[[], float],
    ) -> None:
        self.identity = identity
        self._feed = feed
        self._events = events
        self._clock = clock
        self._lock = threading.Lock()
        self.target: tuple[int, int] | None = None  #: the autopilot's (system, component)
        self.flavour = 0  #: its HEARTBEAT.autopilot (MAV_AUTOPILOT)
        self._armed = False
        self._calibrating = False  # its HEARTBEAT says MAV_STATE_CALIBRATING
        self._magcal_at = -math.inf  # its last MAG_CAL_PROGRESS (ArduPilot's compass calibration)
        self._heard_at = -math.inf
        self._first_heard = -math.inf
        self._send: Send | None = None  # to the link the autopilot was last heard on
        self.requests = StreamRequests()
        self._reset: _Reset | None = None
        self._refused_at = -math.inf
        self.resets = 0  #: yaw resets asked of ArduPilot
        self.refusals = 0  #: heading changes refused
        self.acks: list[tuple[int, int]] = []  #: (command, result) of the autopilot's answers
        self.on_due: Callable[[], None] | None = None  #: told when :attr:`due_at` moved earlier

    def attach(self, settings: EngineSettings) -> Callable[[], None]:
        """Guard the heading's settings (:meth:`guard`); without ``[location]`` ask the
        autopilot for its position (:data:`POSITION`). Returns the remover of the guard."""
        if settings.field is None:
            self.requests.want(POSITION.msgid, POSITION.hz, POSITION.ardupilot_stream)
        return settings.add_guard(self.guard)

    # -- what the autopilot says (endpoint threads) ------------------------------------

    def heard(self, msg: Any, send: Send) -> None:
        """A message from the link: the autopilot's HEARTBEAT, its answers, wanted messages."""
        if msg.get_srcSystem() != self.identity[0]:
            return
        kind = msg.get_type()
        now = self._clock()
        if kind == "HEARTBEAT":
            if int(msg.autopilot) == int(M.MAV_AUTOPILOT_INVALID) or int(msg.type) in _NOT_VEHICLES:
                return
            with self._lock:
                if self.target is None or now - self._heard_at > AUTOPILOT_TIMEOUT_S:
                    self._first_heard = now
                self.target = (msg.get_srcSystem(), msg.get_srcComponent())
                self.flavour = int(msg.autopilot)
                self._armed = bool(int(msg.base_mode) & _ARMED)
                self._calibrating = int(msg.system_status) == int(M.MAV_STATE_CALIBRATING)
                self._heard_at = now
                self._send = send
            if self.same_identity:
                log.error(
                    "mavlink: the autopilot uses our own system and component id %d/%d: it "
                    "drops what we send it (the heading feed); give the bridge another "
                    "component_id",
                    *self.identity,
                )
        elif kind == "COMMAND_ACK":
            if int(msg.target_component) == self.identity[1]:
                self.acks.append((int(msg.command), int(msg.result)))
                if int(msg.command) == SET_EKF_SOURCE_SET and int(msg.result) != 0:
                    log.warning("mavlink: the autopilot refused the EKF source set switch")
        else:
            if msg.get_srcComponent() != self.identity[1]:
                if kind == "MAG_CAL_PROGRESS":
                    self._magcal_at = now
                elif kind == "MAG_CAL_REPORT":  # finished: a result (waiting for accept)
                    self._magcal_at = -math.inf
            self.requests.heard(msg.get_msgId(), now)

    # -- state -----------------------------------------------------------------------

    @property
    def present(self) -> bool:
        """An autopilot was heard within :data:`AUTOPILOT_TIMEOUT_S`."""
        return self.target is not None and self._clock() - self._heard_at <= AUTOPILOT_TIMEOUT_S

    @property
    def ardupilot(self) -> bool:
        """The autopilot is ArduPilot."""
        return self.flavour == int(M.MAV_AUTOPILOT_ARDUPILOTMEGA)

    @property
    def armed(self) -> bool:
        """The autopilot is present and armed."""
        return self.present and self._armed

    @property
    def calibrating(self) -> bool:
        """The autopilot runs a sensor calibration of its own: its HEARTBEAT says
        CALIBRATING (PX4, every sensor) or it sent MAG_CAL_PROGRESS within 2 s and no
        MAG_CAL_REPORT since (ArduPilot's compass calibration, which does not change its
        HEARTBEAT)."""
        return self.present and (self._calibrating or self._clock() - self._magcal_at < 2.0)

    @property
    def same_identity(self) -> bool:
        """The autopilot has our system *and* component id (it drops what we send)."""
        return self.target == self.identity

    # -- heading changes ---------------------------------------------------------------

    def _fed_ardupilot(self) -> bool:
        return self._feed() == FEED_ARDUPILOT and self.ardupilot and self.present

    def guard(self, aspect: str, source: str) -> str:
        """The settings guard: refuse a heading step while an armed ArduPilot takes its yaw
        from us ("" lets it through)."""
        if not (self._fed_ardupilot() and self._armed):
            return ""
        self.refusals += 1
        what = {"calibration": "calibration", "mounting": "mounting"}.get(aspect, "declination")
        reason = (
            f"{what} change ({source}) refused while ArduPilot is armed: its EKF3 would take "
            "the heading step as a measurement, need tens of seconds to follow, overshoot and "
            "learn it into its gyro bias; disarm, then repeat the change (the bridge then "
            "resets ArduPilot's yaw to the new heading)"
        )
        now = self._clock()
        if now - self._refused_at >= _REFUSAL_EVENT_S:
            self._refused_at = now
            self._events.emit(
                Event(
                    "mavlink.heading_change_refused",
                    f"{what.capitalize()} change refused: ArduPilot armed, disarm first",
                    Severity.WARNING,
                    {"aspect": aspect, "source": source, "reason": reason},
                )
            )
        log.warning("mavlink: %s", reason)
        return reason

    def heading_stepped(self, aspect: str) -> None:
        """A heading step was applied: reset a (disarmed) ArduPilot's yaw to it."""
        if not self._fed_ardupilot() or self._armed:
            return
        with self._lock:
            self._reset = _Reset(self._clock())
            send, target = self._send, self.target
        if send is None or target is None:
            return
        self.resets += 1
        send(command_long(target, SET_EKF_SOURCE_SET, 2))
        if self.on_due is not None:
            self.on_due()  # the telemetry thread: sleep no longer than RESET_HOLD_S
        log.info(
            "mavlink: %s changed: resetting ArduPilot's yaw to the new heading "
            "(EKF source set 2, then 1)",
            aspect,
        )

    # -- the clock (telemetry thread) ----------------------------------------------------

    @property
    def due_at(self) -> float:
        """When :meth:`tick` next has something to send at a set time (a yaw reset's second
        switch), on the output's clock; +inf when nothing waits."""
        r = self._reset
        return r.started + RESET_HOLD_S if r is not None and not r.back_sent else math.inf

    def tick(self, now: float) -> None:
        """Finish a yaw reset; ask for missing messages."""
        with self._lock:
            send, target, r = self._send, self.target, self._reset
        if send is None or target is None:
            return
        if r is not None and not r.back_sent and now >= r.started + RESET_HOLD_S:
            r.back_sent = True
            self._reset = None
            send(command_long(target, SET_EKF_SOURCE_SET, 1))
            self._events.emit(
                Event(
                    "mavlink.autopilot_yaw_reset",
                    "ArduPilot yaw reset to the new heading",
                    Severity.INFO,
                    {"source_sets": [2, 1]},
                )
            )
        if self.present:
            for m in self.requests.due(now, self._first_heard, target, self.ardupilot):
                send(m)
