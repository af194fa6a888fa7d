"""Telemetry: what the bridge says on MAVLink, and how often (pure: no I/O, no clock).

Every function here turns bridge state into :class:`~bridge.mavlink.wire.Packet`
objects; times are passed in. Units and signs, as a ground station expects:

* ATTITUDE / ATTITUDE_QUATERNION: radians, body FRD relative to NED, yaw from
  the published heading (magnetic or true, as the daemon publishes it). The
  compass has no gyro: the rate fields are 0.
* SCALED_IMU: accelerations in mG and the calibrated field in mgauss, vehicle
  axes. MAVLink IMU messages carry *specific force* (a level unit at rest reads
  z = -1 g), the negative of the datasheet's gravity vector, so the sign is
  flipped here.
* RAW_IMU: the ADC counts of the frame as the device sent them (0..4095).
* HIGHRES_IMU: m/s^2 (specific force) and gauss; ``fields_updated`` flags the
  accelerometer and magnetometer only.
* VFR_HUD: heading in whole degrees [0, 359]; altitude from the autopilot's
  position when known (companion role), else 0.
* Autopilot heading feed: PX4 ODOMETRY (frame LOCAL_NED, child BODY_FRD,
  estimator VISION, q from the *true* heading, finite zero position with a
  large variance, yaw variance at pose_covariance[20]); ArduPilot
  VISION_POSITION_ESTIMATE (roll, pitch, true yaw; same covariance layout).
  Both need true north: without a declination the magnetic heading is sent and
  the output warns once.

:class:`StreamSchedule` decides which streams are due: sample streams go out
when a new sample arrives and their interval has elapsed (with a quarter
period of slack, so a 10 Hz stream on 10 Hz frames does not skip frames that
come a little early); clock streams (HEARTBEAT, SYS_STATUS) go out on time
whether or not samples come.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

from bridge.core.sensor import STANDARD_GRAVITY
from bridge.daemon import CompassSample
from bridge.link.serial_link import LinkState
from bridge.mavlink.dialect import mavlink as M  # noqa: N812 - the generated module, short
from bridge.mavlink.wire import Packet, codec

Role = Literal["standalone", "companion"]
HeadingFeed = Literal["off", "px4_odometry", "ardupilot_vision"]

ROLES: tuple[str, ...] = ("standalone", "companion")
HEADING_FEEDS: tuple[str, ...] = ("off", "px4_odometry", "ardupilot_vision")

STATUSTEXT_LEN = 50
_INT16 = 32767
_UINT16 = 65535

# The message ids, by name, for readability below.
HEARTBEAT = M.MAVLINK_MSG_ID_HEARTBEAT
SYS_STATUS = M.MAVLINK_MSG_ID_SYS_STATUS
ATTITUDE = M.MAVLINK_MSG_ID_ATTITUDE
ATTITUDE_QUATERNION = M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
VFR_HUD = M.MAVLINK_MSG_ID_VFR_HUD
SCALED_IMU = M.MAVLINK_MSG_ID_SCALED_IMU
RAW_IMU = M.MAVLINK_MSG_ID_RAW_IMU
HIGHRES_IMU = M.MAVLINK_MSG_ID_HIGHRES_IMU
ODOMETRY = M.MAVLINK_MSG_ID_ODOMETRY
VISION_POSITION_ESTIMATE = M.MAVLINK_MSG_ID_VISION_POSITION_ESTIMATE
STATUSTEXT = M.MAVLINK_MSG_ID_STATUSTEXT
AUTOPILOT_VERSION = M.MAVLINK_MSG_ID_AUTOPILOT_VERSION
MAG_CAL_PROGRESS = M.MAVLINK_MSG_ID_MAG_CAL_PROGRESS
MAG_CAL_REPORT = M.MAVLINK_MSG_ID_MAG_CAL_REPORT


@dataclass(frozen=True, slots=True)
class StreamSpec:
    """One configurable stream: its message, parameter, config key and default rate."""

    msgid: int
    param: str  #: the BRG_SR_* parameter holding its rate (Hz, 0 = off)
    config_key: str  #: the [mavlink] key giving the parameter's default
    default_hz: float
    clock: bool  #: sent on time (True) or when a new sample arrives (False)


#: The configurable streams. The heading feed's message depends on BRG_HDG_FEED.
STREAMS: tuple[StreamSpec, ...] = (
    StreamSpec(ATTITUDE, "BRG_SR_ATT", "rate_attitude_hz", 10.0, False),
    StreamSpec(ATTITUDE_QUATERNION, "BRG_SR_QUAT", "rate_attitude_quaternion_hz", 10.0, False),
    StreamSpec(VFR_HUD, "BRG_SR_HUD", "rate_vfr_hud_hz", 4.0, False),
    StreamSpec(SCALED_IMU, "BRG_SR_SIMU", "rate_scaled_imu_hz", 2.0, False),
    StreamSpec(RAW_IMU, "BRG_SR_RIMU", "rate_raw_imu_hz", 2.0, False),
    StreamSpec(HIGHRES_IMU, "BRG_SR_HIMU", "rate_highres_imu_hz", 2.0, False),
    StreamSpec(SYS_STATUS, "BRG_SR_SYS", "rate_sys_status_hz", 1.0, True),
    StreamSpec(ODOMETRY, "BRG_SR_FEED", "rate_heading_feed_hz", 10.0, False),
)
#: The streams sent when a sample arrives (the rest go on the clock), in STREAMS' order.
SAMPLE_STREAMS: tuple[int, ...] = tuple(s.msgid for s in STREAMS if not s.clock)
#: VISION_POSITION_ESTIMATE shares the feed's rate (only one of the two is ever on).
FEED_MSGIDS = (ODOMETRY, VISION_POSITION_ESTIMATE)
HEARTBEAT_HZ = 1.0
#: Messages whose interval MAV_CMD_SET_MESSAGE_INTERVAL may change.
STREAMABLE: frozenset[int] = frozenset(
    {s.msgid for s in STREAMS} | {HEARTBEAT, VISION_POSITION_ESTIMATE}
)


def stream_for(msgid: int) -> StreamSpec | None:
    """The :class:`StreamSpec` of a message (the feed's for VISION_POSITION_ESTIMATE)."""
    if msgid == VISION_POSITION_ESTIMATE:
        msgid = ODOMETRY
    for s in STREAMS:
        if s.msgid == msgid:
            return s
    return None


# ---------------------------------------------------------------------------- scheduling


class StreamSchedule:
    """Which streams are due (pure; ``now`` is any monotonic time in seconds).

    ``rates`` maps message id -> Hz (0 = off). A rate set with
    :meth:`set_override` (MAV_CMD_SET_MESSAGE_INTERVAL) wins over the base rate
    until cleared; base rates come from the BRG_SR_* parameters.

    The per-sample fast path: :meth:`set_sample_streams` names the sample
    streams the owner sends, :meth:`due_samples` is :meth:`due_on_sample` over
    them, and :attr:`sample_due_at` is the earliest time any of them can next
    fall due (``-inf``: unknown, ask :meth:`due_samples`; ``+inf``: none is on).
    At 100 Hz frames and a 50 Hz ATTITUDE half the frames carry no due stream:
    ``now < schedule.sample_due_at`` tells the caller so with one comparison
    instead of a rate lookup per stream. Every change of a rate, an override
    or the set of sample streams resets it to ``-inf``.
    """

    SLACK = 0.25  #: fraction of a period a sample may come early and still count as due

    def __init__(self, rates: Mapping[int, float]) -> None:
        self._base: dict[int, float] = {}
        self._override: dict[int, float] = {}
        self._next: dict[int, float] = {}
        self._clock: set[int] = {HEARTBEAT} | {s.msgid for s in STREAMS if s.clock}
        self._sample_ids: tuple[int, ...] = ()
        # Bumped by every change. due_samples() notices a change made (by another thread)
        # while it ran, and then leaves sample_due_at at -inf rather than a stale value.
        self._generation = 0
        # (generation it was built for, ((msgid, period, SLACK * period), ...)) of the sample
        # streams that are on: rebuilt when the generation moved on.
        self._plan: tuple[int, tuple[tuple[int, float, float], ...]] = (-1, ())
        #: Earliest time a sample stream can be due (see the class docstring).
        self.sample_due_at = -math.inf
        for msgid, hz in rates.items():
            self.set_base(msgid, hz)
        self._base.setdefault(HEARTBEAT, HEARTBEAT_HZ)

    def _changed(self) -> None:
        # Order matters for a due_samples() running in another thread: the generation
        # first, then the cached time (see due_samples).
        self._generation += 1
        self.sample_due_at = -math.inf

    def set_base(self, msgid: int, hz: float) -> None:
        """The configured rate of a stream (Hz, 0 = off)."""
        if not (math.isfinite(hz) and hz >= 0.0):
            raise ValueError(f"rate must be a finite number >= 0, got {hz!r}")
        self._base[msgid] = float(hz)
        self._changed()

    def set_override(self, msgid: int, hz: float | None) -> None:
        """A temporary rate (``None``: back to the configured one)."""
        if hz is None:
            self._override.pop(msgid, None)
        else:
            if not (math.isfinite(hz) and hz >= 0.0):
                raise ValueError(f"rate must be a finite number >= 0, got {hz!r}")
            self._override[msgid] = float(hz)
        self._next.pop(msgid, None)  # start the new rhythm with the next opportunity
        self._changed()

    def set_sample_streams(self, msgids: Iterable[int]) -> None:
        """The sample streams :meth:`due_samples` looks at, in the order it reports them."""
        self._sample_ids = tuple(m for m in dict.fromkeys(msgids) if m not in self._clock)
        self._changed()

    @property
    def sample_streams(self) -> tuple[int, ...]:
        """The streams set with :meth:`set_sample_streams` (clock streams left out)."""
        return self._sample_ids

    def rate(self, msgid: int) -> float:
        """The rate in effect (Hz, 0 = off)."""
        return self._override.get(msgid, self._base.get(msgid, 0.0))

    def interval_us(self, msgid: int) -> int:
        """MESSAGE_INTERVAL's interval: microseconds, -1 when off."""
        hz = self.rate(msgid)
        return -1 if hz <= 0.0 else round(1e6 / hz)

    def _due(self, msgid: int, now: float) -> bool:
        hz = self.rate(msgid)
        if hz <= 0.0:
            return False
        period = 1.0 / hz
        nxt = self._next.get(msgid)
        if nxt is not None and now < nxt - self.SLACK * period:
            return False
        # Keep the average rate exact (next += period), but never build up a
        # backlog after a pause (resync when more than a period behind).
        self._next[msgid] = now + period if nxt is None or now - nxt > period else nxt + period
        return True

    def due_on_sample(self, msgids: Iterable[int], now: float) -> list[int]:
        """The sample streams among ``msgids`` to send with a sample arriving at ``now``."""
        # It moves the streams' next times: the fast path's cached time must be worked out anew.
        self.sample_due_at = -math.inf
        return [m for m in msgids if m not in self._clock and self._due(m, now)]

    def due_samples(self, now: float) -> list[int]:
        """:meth:`due_on_sample` over :meth:`set_sample_streams`'s streams; updates
        :attr:`sample_due_at`.

        The same arithmetic as :meth:`_due`, with each stream's period worked out
        once per rate change instead of on every sample.
        """
        # The generation is read before anything it guards: a plan built from rates read
        # after it carries it, so a change made meanwhile makes the plan stale, never wrong.
        generation = self._generation
        built_for, plan = self._plan
        if built_for != generation:
            rate = self.rate
            plan = tuple(
                (m, 1.0 / hz, self.SLACK * (1.0 / hz))
                for m in self._sample_ids
                if (hz := rate(m)) > 0.0
            )
            self._plan = (generation, plan)
        nexts = self._next
        due: list[int] = []
        earliest = math.inf
        for m, period, early in plan:
            nxt = nexts.get(m)
            if nxt is None or now >= nxt - early:
                nxt = now + period if nxt is None or now - nxt > period else nxt + period
                nexts[m] = nxt
                due.append(m)
            if nxt - early < earliest:
                earliest = nxt - early
        self.sample_due_at = earliest
        if self._generation != generation:
            # Changed meanwhile (another thread): the value just stored may predate the
            # change, whose own reset may have come before it. Reset again.
            self.sample_due_at = -math.inf
        return due

    def due_on_clock(self, now: float) -> list[int]:
        """The clock streams due at ``now``."""
        return [m for m in sorted(self._clock) if self._due(m, now)]

    def next_clock_due(self, now: float) -> float:
        """When the next clock stream falls due (``now + 1`` when none is on)."""
        times = [
            self._next.get(m, now) - self.SLACK / self.rate(m)
            for m in self._clock
            if self.rate(m) > 0.0
        ]
        return min(times) if times else now + 1.0


# ---------------------------------------------------------------------------- identity, health


@dataclass(frozen=True, slots=True)
class Identity:
    """Who we are on MAVLink."""

    system_id: int
    component_id: int
    role: Role = "standalone"

    @property
    def mav_type(self) -> int:
        """HEARTBEAT.type: GENERIC for the standalone vehicle, IMU beside an autopilot."""
        return int(M.MAV_TYPE_IMU if self.role == "companion" else M.MAV_TYPE_GENERIC)


def heartbeat(identity: Identity, system_status: int) -> Packet:
    """HEARTBEAT (autopilot INVALID: we are not a flight controller)."""
    return codec(HEARTBEAT).packet(
        type=identity.mav_type,
        autopilot=M.MAV_AUTOPILOT_INVALID,
        base_mode=0,
        custom_mode=0,
        system_status=system_status,
        mavlink_version=3,
    )


@dataclass(frozen=True, slots=True)
class Health:
    """What HEARTBEAT.system_status and SYS_STATUS report."""

    link_state: LinkState
    fresh: bool  #: a sample arrived recently (the link is not stale)
    calibrating: bool
    disturbed: bool
    saturated: bool
    compass_use: bool
    bad_lines: int = 0
    good_lines: int = 0
    lost_frames: int = 0
    reconnects: int = 0
    stale_events: int = 0
    pipeline_errors: int = 0


def system_status(h: Health) -> int:
    """MAV_STATE for HEARTBEAT.

    CALIBRATING during a calibration; ACTIVE while frames stream; BOOT while
    the port is being opened and nothing came yet; CRITICAL when the link is
    stale or the port is gone (no heading).
    """
    if h.calibrating:
        return int(M.MAV_STATE_CALIBRATING)
    if h.link_state is LinkState.STREAMING and h.fresh:
        return int(M.MAV_STATE_ACTIVE)
    if h.link_state is LinkState.OPENING:
        return int(M.MAV_STATE_BOOT)
    return int(M.MAV_STATE_CRITICAL)


def _u16(n: int) -> int:
    return max(0, min(_UINT16, int(n)))


def sys_status(h: Health) -> Packet:
    """SYS_STATUS: 3D_MAG and 3D_ACCEL present / enabled / healthy, link error counts.

    The magnetometer is healthy only while fresh frames come, the field is not
    disturbed and no channel is saturated; the accelerometer while fresh and
    not saturated. ``drop_rate_comm`` (c%) and ``errors_comm`` describe the
    compass's serial line (lines dropped as noise); ``errors_count1..4`` are
    lost frames, reconnects, stale events and pipeline errors.
    """
    mag, acc = M.MAV_SYS_STATUS_SENSOR_3D_MAG, M.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    ok = h.fresh and h.link_state is LinkState.STREAMING and not h.saturated
    health = (mag if ok and not h.disturbed else 0) | (acc if ok else 0)
    total = h.bad_lines + h.good_lines
    drop = round(10000 * h.bad_lines / total) if total else 0
    return codec(SYS_STATUS).packet(
        onboard_control_sensors_present=mag | acc,
        onboard_control_sensors_enabled=(mag if h.compass_use else 0) | acc,
        onboard_control_sensors_health=health,
        load=0,
        voltage_battery=_UINT16,  # unknown
        current_battery=-1,
        battery_remaining=-1,
        drop_rate_comm=_u16(drop),
        errors_comm=_u16(h.bad_lines),
        errors_count1=_u16(h.lost_frames),
        errors_count2=_u16(h.reconnects),
        errors_count3=_u16(h.stale_events),
        errors_count4=_u16(h.pipeline_errors),
        onboard_control_sensors_present_extended=0,
        onboard_control_sensors_enabled_extended=0,
        onboard_control_sensors_health_extended=0,
    )


# ---------------------------------------------------------------------------- per-sample messages


def _wrap_pi(a: float) -> float:
    a = math.fmod(a + math.pi, 2.0 * math.pi)
    if a <= 0.0:
        a += 2.0 * math.pi
    return a - math.pi


def euler_of(sample: CompassSample) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians; yaw from the published heading, unknown angles 0."""
    a = sample.attitude
    if a is not None:
        return a.roll, a.pitch, a.yaw
    roll = math.radians(sample.roll_deg) if sample.roll_deg is not None else 0.0
    pitch = math.radians(sample.pitch_deg) if sample.pitch_deg is not None else 0.0
    return roll, pitch, _wrap_pi(math.radians(sample.heading_deg))


def quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) body->NED from ZYX Euler angles, w >= 0."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    w = cr * cp * cy + sr * sp * sy
    x = sr * cp * cy - cr * sp * sy
    y = cr * sp * cy + sr * cp * sy
    z = cr * cp * sy - sr * sp * cy
    return (w, x, y, z) if w >= 0.0 else (-w, -x, -y, -z)


def _ms32(t_ms: int) -> int:
    return int(t_ms) & 0xFFFFFFFF


# The per-sample messages go out up to 50 times a second: positional encoders, their
# constant fields fixed once (Codec.packer: the same bytes as Codec.packet, tested).
_ATTITUDE = codec(ATTITUDE).packer(
    ("time_boot_ms", "roll", "pitch", "yaw"), rollspeed=0.0, pitchspeed=0.0, yawspeed=0.0
)
_ATTITUDE_QUATERNION = codec(ATTITUDE_QUATERNION).packer(
    ("time_boot_ms", "q1", "q2", "q3", "q4"),
    rollspeed=0.0,
    pitchspeed=0.0,
    yawspeed=0.0,
    repr_offset_q=(0.0, 0.0, 0.0, 0.0),
)
_VFR_HUD = codec(VFR_HUD).packer(
    ("heading", "alt"), airspeed=0.0, groundspeed=0.0, throttle=0, climb=0.0
)
_SCALED_IMU = codec(SCALED_IMU).packer(
    ("time_boot_ms", "xacc", "yacc", "zacc", "xmag", "ymag", "zmag"),
    xgyro=0,
    ygyro=0,
    zgyro=0,
    temperature=0,  # 0 = no temperature
)
_RAW_IMU = codec(RAW_IMU).packer(
    ("time_usec", "xacc", "yacc", "zacc", "xmag", "ymag", "zmag"),
    xgyro=0,
    ygyro=0,
    zgyro=0,
    id=0,
    temperature=0,
)


def attitude(sample: CompassSample, time_boot_ms: int) -> Packet:
    """ATTITUDE."""
    a = sample.attitude
    if a is not None:  # euler_of(), inlined for the common case
        return _ATTITUDE(int(time_boot_ms) & 0xFFFFFFFF, a.roll, a.pitch, a.yaw)
    roll, pitch, yaw = euler_of(sample)
    return _ATTITUDE(_ms32(time_boot_ms), roll, pitch, yaw)


def attitude_quaternion(sample: CompassSample, time_boot_ms: int) -> Packet:
    """ATTITUDE_QUATERNION (q1..q4 = w, x, y, z)."""
    a = sample.attitude
    q = a.quaternion if a is not None else quaternion(*euler_of(sample))
    return _ATTITUDE_QUATERNION(_ms32(time_boot_ms), q[0], q[1], q[2], q[3])


def vfr_hud(sample: CompassSample, alt_m: float = 0.0) -> Packet:
    """VFR_HUD: heading in whole degrees (0..359)."""
    return _VFR_HUD(round(sample.heading_deg) % 360, alt_m)


def _i16(v: float) -> int:
    if not math.isfinite(v):
        return 0
    return max(-_INT16, min(_INT16, round(v)))


def scaled_imu(sample: CompassSample, time_boot_ms: int) -> Packet | None:
    """SCALED_IMU (None without calibrated vectors: a heading-only compass)."""
    a = sample.attitude
    if a is None:
        return None
    gx, gy, gz = a.accel_g
    mx, my, mz = a.mag_G
    return _SCALED_IMU(
        _ms32(time_boot_ms),
        # specific force = -gravity vector, in mG
        _i16(-1000.0 * gx),
        _i16(-1000.0 * gy),
        _i16(-1000.0 * gz),
        _i16(1000.0 * mx),
        _i16(1000.0 * my),
        _i16(1000.0 * mz),
    )


def raw_counts(sample: CompassSample) -> tuple[int, int, int, int, int, int] | None:
    """The frame's ADC counts (mx, my, mz, ax, ay, az), if the sample carries them."""
    return sample.raw_counts


def raw_imu(sample: CompassSample, time_usec: int) -> Packet | None:
    """RAW_IMU: the ADC counts as the device sent them (None when not known)."""
    rc = raw_counts(sample)
    if rc is None:
        return None
    mx, my, mz, ax, ay, az = rc
    return _RAW_IMU(max(0, int(time_usec)), ax, ay, az, mx, my, mz)


#: HIGHRES_IMU.fields_updated: xacc..zacc (bits 0-2) and xmag..zmag (bits 6-8).
HIGHRES_FIELDS_ACC_MAG = 0b111 | (0b111 << 6)
_HIGHRES_IMU = codec(HIGHRES_IMU).packer(
    ("time_usec", "xacc", "yacc", "zacc", "xmag", "ymag", "zmag"),
    xgyro=0.0,
    ygyro=0.0,
    zgyro=0.0,
    abs_pressure=0.0,
    diff_pressure=0.0,
    pressure_alt=0.0,
    temperature=0.0,
    fields_updated=HIGHRES_FIELDS_ACC_MAG,
    id=0,
)


def highres_imu(sample: CompassSample, time_usec: int) -> Packet | None:
    """HIGHRES_IMU: specific force in m/s^2, field in gauss (None without vectors)."""
    a = sample.attitude
    if a is None:
        return None
    gx, gy, gz = a.accel_g
    mx, my, mz = a.mag_G
    k = -STANDARD_GRAVITY
    return _HIGHRES_IMU(max(0, int(time_usec)), k * gx, k * gy, k * gz, mx, my, mz)


# ---------------------------------------------------------------------------- autopilot heading feed


#: Position variance (m^2) sent with the feed's placeholder zero position: large, so an
#: estimator that fuses position anyway gives it no weight.
FEED_POSITION_VARIANCE = 1.0e4


def feed_usable(sample: CompassSample) -> bool:
    """Whether a sample's heading may be offered to an autopilot at all.

    Not while the field is disturbed or a channel saturated: the heading is
    then wrong by an unknown amount, and an estimator is better served by a
    gap (it falls back on its own sources) than by a confident bad value.
    """
    a = sample.attitude
    return not sample.saturated and not (a is not None and a.disturbed)


def feed_yaw_sigma_rad(sample: CompassSample, sigma_deg: float) -> float:
    """Yaw standard deviation: ``sigma_deg``, five times that while accelerating or degraded."""
    a = sample.attitude
    k = 5.0 if a is not None and (a.accelerating or a.degraded) else 1.0
    return math.radians(k * sigma_deg)


def feed_euler(sample: CompassSample) -> tuple[float, float, float, bool]:
    """(roll, pitch, yaw, is_true): yaw from the true heading when a declination is known."""
    roll, pitch, _published = euler_of(sample)
    true = sample.heading_true_deg
    if true is not None:
        return roll, pitch, _wrap_pi(math.radians(true)), True
    mag = sample.heading_magnetic_deg
    hdg = mag if mag is not None else sample.heading_deg
    return roll, pitch, _wrap_pi(math.radians(hdg)), False


def _pose_covariance(yaw_var: float) -> list[float]:
    cov = [0.0] * 21
    cov[0] = cov[6] = cov[11] = FEED_POSITION_VARIANCE  # x, y, z: unknown (placeholder)
    cov[15] = cov[18] = cov[20] = yaw_var  # roll, pitch, yaw
    return cov


def odometry(
    sample: CompassSample, time_usec: int, sigma_deg: float, reset_counter: int = 0
) -> Packet:
    """PX4 ODOMETRY for EKF2 external-vision yaw fusion (EKF2_EV_CTRL bit 3)."""
    roll, pitch, yaw, _true = feed_euler(sample)
    var = feed_yaw_sigma_rad(sample, sigma_deg) ** 2
    nan = math.nan
    a = sample.attitude
    quality = 50 if a is not None and (a.accelerating or a.degraded) else 100
    return codec(ODOMETRY).packet(
        time_usec=max(0, int(time_usec)),
        frame_id=M.MAV_FRAME_LOCAL_NED,
        child_frame_id=M.MAV_FRAME_BODY_FRD,
        x=0.0,
        y=0.0,
        z=0.0,
        q=quaternion(roll, pitch, yaw),
        vx=nan,
        vy=nan,
        vz=nan,
        rollspeed=nan,
        pitchspeed=nan,
        yawspeed=nan,
        pose_covariance=_pose_covariance(var),
        velocity_covariance=[nan] + [0.0] * 20,  # first element NaN: velocity unknown
        reset_counter=reset_counter & 0xFF,
        estimator_type=M.MAV_ESTIMATOR_TYPE_VISION,
        quality=quality,
    )


def vision_position_estimate(
    sample: CompassSample, time_usec: int, sigma_deg: float, reset_counter: int = 0
) -> Packet:
    """ArduPilot VISION_POSITION_ESTIMATE for ExternalNav yaw (EK3_SRC1_YAW = 6)."""
    roll, pitch, yaw, _true = feed_euler(sample)
    var = feed_yaw_sigma_rad(sample, sigma_deg) ** 2
    return codec(VISION_POSITION_ESTIMATE).packet(
        usec=max(0, int(time_usec)),
        x=0.0,
        y=0.0,
        z=0.0,
        roll=roll,
        pitch=pitch,
        yaw=yaw,
        covariance=_pose_covariance(var),
        reset_counter=reset_counter & 0xFF,
    )


# ---------------------------------------------------------------------------- replies and events


def statustext(severity: int, text: str, chunk_id: int = 0) -> list[Packet]:
    """STATUSTEXT packets for ``text``: one when it fits in 50 bytes, else chunks.

    Longer texts are split into 50-byte chunks sharing ``chunk_id`` (must be
    non-zero for chunked text) with ``chunk_seq`` 0, 1, ...; text is UTF-8 and
    never split inside a character.
    """
    data = text.encode("utf-8")
    c = codec(STATUSTEXT)
    if len(data) <= STATUSTEXT_LEN:
        return [c.packet(severity=severity, text=data, id=0, chunk_seq=0)]
    chunks: list[bytes] = []
    while data:
        cut = min(STATUSTEXT_LEN, len(data))
        while cut < len(data) and (data[cut] & 0xC0) == 0x80:  # inside a UTF-8 sequence
            cut -= 1
        chunks.append(data[:cut])
        data = data[cut:]
    ident = chunk_id & 0xFFFF or 1
    return [
        c.packet(severity=severity, text=chunk, id=ident, chunk_seq=i & 0xFF)
        for i, chunk in enumerate(chunks)
    ]


def command_ack(
    command: int,
    result: int,
    target_system: int,
    target_component: int,
    progress: int = 0,
    result_param2: int = 0,
) -> Packet:
    """COMMAND_ACK to the sender of a command."""
    return codec(M.MAVLINK_MSG_ID_COMMAND_ACK).packet(
        command=command,
        result=result,
        progress=max(0, min(255, int(progress))),
        result_param2=int(result_param2),
        target_system=target_system,
        target_component=target_component,
    )


def message_interval(msgid: int, interval_us: int) -> Packet:
    """MESSAGE_INTERVAL (answer to MAV_CMD_GET_MESSAGE_INTERVAL)."""
    return codec(M.MAVLINK_MSG_ID_MESSAGE_INTERVAL).packet(
        message_id=msgid, interval_us=interval_us
    )


def timesync_reply(tc1_ns: int, ts1: int) -> Packet:
    """TIMESYNC answer: our time (ns) in tc1, the request's ts1 echoed."""
    return codec(M.MAVLINK_MSG_ID_TIMESYNC).packet(tc1=int(tc1_ns), ts1=int(ts1))


def encode_version(text: str, release_type: int = 255) -> int:
    """``"1.2.3"`` as MAVLink's (major << 24 | minor << 16 | patch << 8 | type)."""
    parts = [int(p) if p.isdigit() else 0 for p in text.split(".")[:3]]
    parts += [0] * (3 - len(parts))
    major, minor, patch = (max(0, min(255, p)) for p in parts)
    return major << 24 | minor << 16 | patch << 8 | (release_type & 0xFF)


#: Protocol capabilities we implement: MAVLink 2, COMMAND_INT, compass calibration,
#: and integer parameters C-cast into param_value (as ArduPilot; MAVProxy expects it).
CAPABILITIES = (
    M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | M.MAV_PROTOCOL_CAPABILITY_COMPASS_CALIBRATION
    | M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
)


def autopilot_version(
    bridge_version: str,
    device_firmware: str | None,
    device_serial: str | None,
    uid: int,
) -> Packet:
    """AUTOPILOT_VERSION: the bridge as flight software, the compass firmware as middleware."""
    return codec(AUTOPILOT_VERSION).packet(
        capabilities=CAPABILITIES,
        flight_sw_version=encode_version(bridge_version),
        middleware_sw_version=encode_version(device_firmware) if device_firmware else 0,
        os_sw_version=0,
        board_version=0,
        flight_custom_version=bytes(8),
        middleware_custom_version=bytes(8),
        os_custom_version=bytes(8),
        vendor_id=0,
        product_id=0,
        uid=uid & 0xFFFFFFFFFFFFFFFF,
        uid2=_uid2(device_serial),
    )


def _uid2(serial: str | None) -> bytes:
    raw = (serial or "").encode("ascii", "replace")[:18]
    return raw + bytes(18 - len(raw))


def mag_cal_progress(
    cal_status: int,
    attempt: int,
    completion_pct: float,
    completion_mask: bytes | Sequence[int],
    direction: Sequence[float] = (0.0, 0.0, 0.0),
    compass_id: int = 0,
) -> Packet:
    """MAG_CAL_PROGRESS (ArduPilot): percent, the 80-section coverage mask, the field direction."""
    mask = bytes(completion_mask)
    if len(mask) != 10:
        raise ValueError(f"completion_mask must be 10 bytes, got {len(mask)}")
    return codec(MAG_CAL_PROGRESS).packet(
        compass_id=compass_id,
        cal_mask=1 << compass_id,
        cal_status=cal_status,
        attempt=max(0, min(255, int(attempt))),
        completion_pct=max(0, min(100, int(completion_pct))),
        completion_mask=list(mask),
        direction_x=float(direction[0]),
        direction_y=float(direction[1]),
        direction_z=float(direction[2]),
    )


@dataclass(frozen=True, slots=True)
class MagCalReport:
    """The figures of MAG_CAL_REPORT (ArduPilot's units: offsets in mG, fitness in mG)."""

    cal_status: int
    autosaved: bool
    fitness: float
    ofs: tuple[float, float, float]
    diag: tuple[float, float, float]
    offdiag: tuple[float, float, float]
    orientation_confidence: float
    old_orientation: int
    new_orientation: int
    scale_factor: float


def mag_cal_report(r: MagCalReport, compass_id: int = 0) -> Packet:
    """MAG_CAL_REPORT."""

    def f(v: float) -> float:
        return float(v) if math.isfinite(v) else 0.0

    return codec(MAG_CAL_REPORT).packet(
        compass_id=compass_id,
        cal_mask=1 << compass_id,
        cal_status=r.cal_status,
        autosaved=1 if r.autosaved else 0,
        fitness=f(r.fitness),
        ofs_x=f(r.ofs[0]),
        ofs_y=f(r.ofs[1]),
        ofs_z=f(r.ofs[2]),
        diag_x=f(r.diag[0]),
        diag_y=f(r.diag[1]),
        diag_z=f(r.diag[2]),
        offdiag_x=f(r.offdiag[0]),
        offdiag_y=f(r.offdiag[1]),
        offdiag_z=f(r.offdiag[2]),
        orientation_confidence=f(r.orientation_confidence),
        old_orientation=r.old_orientation,
        new_orientation=r.new_orientation,
        scale_factor=f(r.scale_factor),
    )


def param_value(name: str, value: float, param_type: int, count: int, index: int) -> Packet:
    """PARAM_VALUE (value already C-cast to float by the caller)."""
    return codec(M.MAVLINK_MSG_ID_PARAM_VALUE).packet(
        param_id=name.encode("ascii"),
        param_value=float(value),
        param_type=param_type,
        param_count=count,
        param_index=index,
    )
