"""The autopilot's attitude into the bridge (companion role): ATTITUDE in, TIMESYNC out.

Beside an autopilot the bridge takes its roll and pitch as the tilt source while
the compass's accelerometer is unreliable (:mod:`bridge.app.tilt`). This module
only translates: ATTITUDE / ATTITUDE_QUATERNION from the autopilot (our system,
component :data:`AUTOPILOT_COMPONENT`) become down vectors stamped with its
``time_boot_ms`` and their arrival time, handed to
:meth:`~bridge.app.tilt.TiltSources.autopilot_attitude`; and once a second,
while the autopilot is heard, a TIMESYNC request goes to it on the link it
speaks on, whose answer (``tc1``: its clock, ``ts1``: ours echoed) gives
:meth:`~bridge.app.tilt.TiltSources.autopilot_timesync` a round trip.

Both autopilots stamp ATTITUDE and answer TIMESYNC on one clock, their time since
boot: ArduPilot's ``GCS_MAVLINK::send_attitude`` (libraries/GCS_MAVLink/GCS_Common.cpp)
stamps ``AP_HAL::millis()`` and its ``GCS_MAVLINK::handle_timesync`` answers ``tc1``
with ``timesync_receive_timestamp_ns()``, the request's arrival in
``AP_HAL::micros64()`` times 1000; PX4's ATTITUDE / ATTITUDE_QUATERNION streams
(src/modules/mavlink/streams/) stamp ``att.timestamp / 1000`` (``hrt``) and its
``MavlinkTimesync::handle_message`` answers ``hrt_absolute_time() * 1000``.

**The stream the companion wants.** :data:`WANTED_STREAMS` says which message at
what rate: the bridge's stream requester (SET_MESSAGE_INTERVAL /
REQUEST_DATA_STREAM when it is not heard) asks the autopilot for it. ArduPilot
sends ATTITUDE in its EXTRA1 stream group: ``MAVn_EXTRA1`` for MAVLink channel n
in 4.7 (``MAV2_`` for SERIAL1; ``SRn_EXTRA1`` before), 1 Hz on Rover SITL's
SERIAL1 with its defaults; PX4 in its MAVLink instance's stream set.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

from bridge.app.services import BridgeServices
from bridge.app.tilt import TiltSources
from bridge.core.vectors import down_from_euler, down_from_quaternion
from bridge.mavlink.dialect import Message, message
from bridge.mavlink.dialect import mavlink as M  # noqa: N812 - the generated module, short
from bridge.mavlink.endpoints import Link

log = logging.getLogger(__name__)

#: The autopilot's component (MAV_COMP_ID_AUTOPILOT1): its ATTITUDE is the one taken.
AUTOPILOT_COMPONENT = 1
#: How often the companion wants the autopilot's ATTITUDE (Hz): fast enough that its
#: interpolation between samples costs nothing at a vehicle's roll and pitch rates.
AUTOPILOT_ATTITUDE_HZ = 20.0
#: What the companion wants from its autopilot, for the stream requester (asked for when
#: not heard): (message id, Hz, ArduPilot's stream group carrying it -- MAV_DATA_STREAM,
#: for REQUEST_DATA_STREAM).
WANTED_STREAMS: tuple[tuple[int, float, int], ...] = (
    (int(M.MAVLINK_MSG_ID_ATTITUDE), AUTOPILOT_ATTITUDE_HZ, int(M.MAV_DATA_STREAM_EXTRA1)),
)
#: A TIMESYNC request to the autopilot this often while it is heard (s).
TIMESYNC_PERIOD_S = 1.0
_OUTSTANDING = 8  #: TIMESYNC requests remembered for their answer
ATTITUDE_TYPES = frozenset({"ATTITUDE", "ATTITUDE_QUATERNION"})


class AutopilotAttitudeIn:
    """The companion's side of the autopilot's attitude (see the module docstring).

    ``clock`` is the MAVLink output's (monotonic) clock and ``t0`` its start: our
    TIMESYNC ``ts1`` is nanoseconds since ``t0``. Endpoint threads call
    :meth:`on_message`; the telemetry thread calls :meth:`tick`.
    """

    def __init__(
        self, tilt: TiltSources, system_id: int, clock: Callable[[], float], t0: float
    ) -> None:
        self.tilt = tilt
        self.system_id = system_id
        self.clock = clock
        self.t0 = t0
        self._lock = threading.Lock()
        self._link: Link | None = None  # where the autopilot's attitude comes from
        self._sent: OrderedDict[int, float] = OrderedDict()  # ts1 -> when it left
        self._next_sync = -math.inf
        self.timesyncs_sent = 0
        self.ignored = 0  #: attitudes from another system or component

    @classmethod
    def beside(
        cls, settings: Any, services: BridgeServices, clock: Callable[[], float], t0: float
    ) -> AutopilotAttitudeIn | None:
        """One for a MAVLink output with ``settings`` (its ``role`` and ``system_id``): None
        unless in the companion role."""
        if settings.role != "companion":
            return None
        return cls(services.tilt, int(settings.system_id), clock, t0)

    def takes(self, msg: Any, link: Link, refused: Callable[[Any], bool]) -> bool:
        """Whether ``msg`` is this module's to take (the output's endpoint thread, as it
        arrives): the autopilot's ATTITUDE(_QUATERNION) -- refused when ``refused`` says
        so (a signing key and no valid signature) -- or an answer to our TIMESYNC."""
        kind = msg.get_type()
        if kind in ATTITUDE_TYPES:
            if self.is_autopilots(msg) and not refused(msg):
                self.on_message(msg, link, self.clock())
            return True
        if kind == "TIMESYNC" and int(msg.tc1) != 0:
            self.on_message(msg, link, self.clock())
            return True
        return False

    def is_autopilots(self, msg: Any) -> bool:
        """The message comes from our autopilot (our system, its component)."""
        return bool(
            msg.get_srcSystem() == self.system_id and msg.get_srcComponent() == AUTOPILOT_COMPONENT
        )

    def on_message(self, msg: Any, link: Link, now: float) -> None:
        """ATTITUDE, ATTITUDE_QUATERNION or a TIMESYNC answer that arrived at ``now``."""
        kind = msg.get_type()
        if kind == "TIMESYNC":
            self._timesync(msg, now)
            return
        if not self.is_autopilots(msg):
            self.ignored += 1
            return
        rates = (float(msg.rollspeed), float(msg.pitchspeed), float(msg.yawspeed))
        if kind == "ATTITUDE":
            down = down_from_euler(float(msg.roll), float(msg.pitch))
        else:  # ATTITUDE_QUATERNION: q1..q4 = w, x, y, z
            down = down_from_quaternion(float(msg.q1), float(msg.q2), float(msg.q3), float(msg.q4))
        self.tilt.autopilot_attitude(int(msg.time_boot_ms), down, now, rates)
        self._link = link

    def _timesync(self, msg: Any, now: float) -> None:
        ts1 = int(msg.ts1)
        with self._lock:
            sent = self._sent.pop(ts1, None)
        if sent is None or not self.is_autopilots(msg):
            return  # not an answer to ours, or not from the autopilot
        self.tilt.autopilot_timesync(sent, int(msg.tc1) / 1e9, now)

    def tick(self, now: float) -> Message | None:
        """Send the autopilot a TIMESYNC request if one is due (on the link it speaks on);
        returns it."""
        link = self._link
        if link is None or now < self._next_sync or not self.tilt.heard_autopilot():
            return None
        self._next_sync = now + TIMESYNC_PERIOD_S
        ts1 = max(1, int((now - self.t0) * 1e9))
        with self._lock:
            self._sent[ts1] = now
            while len(self._sent) > _OUTSTANDING:
                self._sent.popitem(last=False)
        self.timesyncs_sent += 1
        request = message(int(M.MAVLINK_MSG_ID_TIMESYNC), tc1=0, ts1=ts1)
        link.send(request)
        return request
