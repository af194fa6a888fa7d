"""Telemetry: what the bridge says on MAVLink, and how often (pure: no I/O, no clock).

Every function here turns bridge state into a pymavlink message object
(framed per link when it is sent); times are passed in. Units and signs, as a ground station expects:

* ATTITUDE / ATTITUDE_QUATERNION: radians, body FRD relative to NED, yaw from
  the published heading (magnetic or true, as the daemon publishes it). The
  compass has no gyro: the rate fields are 0. A NAMED_VALUE_INT ``TILT_SRC``
  (same ``time_boot_ms``) goes beside an ATTITUDE when its tilt source changes,
  and once a second: where its roll and pitch came from, 0 accelerometer,
  1 autopilot, 2 magnetometer (:class:`TiltSourceNote`).
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
  large variance, the yaw variance sigma^2 at pose_covariance[20], which PX4's
  receiver reads as the yaw variance); ArduPilot VISION_POSITION_ESTIMATE (roll,
  pitch, true yaw), whose covariance is encoded for the way ArduPilot reads it:
  ``angErr = cbrt(c15^2 + c18^2 + c20^2)`` (``GCS_MAVLINK::handle_vision_position_estimate``)
  is taken as the yaw *standard deviation*, so c20 = sigma^1.5 and c15 = c18 = 0
  make ``angErr`` exactly sigma (:func:`ardupilot_covariance`). Time stamps are
  wall-clock (Unix epoch) microseconds, so they continue across bridge restarts.
  Both need true north: without a declination the magnetic heading is sent and
  the output warns once.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

from bridge.app.sample import CompassSample
from bridge.core.geometry import euler_to_quaternion, wrap_radians_pi
from bridge.core.quality import heading_usable
from bridge.core.sensor import STANDARD_GRAVITY
from bridge.core.tilt import TILT_SOURCES
from bridge.mavlink.dialect import Message, message
from bridge.mavlink.dialect import mavlink as M  # noqa: N812 - the generated module, short
from bridge.protocol.device import LinkState

Role = Literal["standalone", "companion"]
HeadingFeed = Literal["off", "px4_odometry", "ardupilot_vision"]

ROLES: tuple[str, ...] = ("standalone", "companion")
HEADING_FEEDS: tuple[str, ...] = ("off", "px4_odometry", "ardupilot_vision")

STATUSTEXT_LEN = 50
_INT16 = 32767
_UINT16 = 65535
_UINT32 = 0xFFFFFFFF

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


# ---------------------------------------------------------------------------- identity, health


@dataclass(frozen=True, slots=True)
class Identity:
    """Who we are on MAVLink, and which autopilot a standalone bridge presents itself as."""

    system_id: int
    component_id: int
    role: Role = "standalone"
    autopilot: str = "generic"  #: the standalone HEARTBEAT's flavour ([mavlink] autopilot)

    @property
    def mav_type(self) -> int:
        """HEARTBEAT.type: GENERIC for the standalone vehicle, IMU beside an autopilot."""
        return int(M.MAV_TYPE_IMU if self.role == "companion" else M.MAV_TYPE_GENERIC)

    @property
    def mav_autopilot(self) -> int:
        """HEARTBEAT.autopilot: INVALID beside an autopilot (a component, not a vehicle);
        standalone, the flavour ground stations need (docs/mavlink.md)."""
        if self.role == "companion":
            return int(M.MAV_AUTOPILOT_INVALID)
        return int(_AUTOPILOTS[self.autopilot])


_AUTOPILOTS = {
    "generic": M.MAV_AUTOPILOT_GENERIC,
    "px4": M.MAV_AUTOPILOT_PX4,
    "ardupilot": M.MAV_AUTOPILOT_ARDUPILOTMEGA,
}


def heartbeat(identity: Identity, system_status: int) -> Message:
    """HEARTBEAT."""
    return message(
        HEARTBEAT,
        type=identity.mav_type,
        autopilot=identity.mav_autopilot,
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


def sys_status(h: Health) -> Message:
    """SYS_STATUS: 3D_MAG and 3D_ACCEL present / enabled / healthy, link error counts.

    The magnetometer is healthy only while fresh frames come, the field is not
    disturbed and no channel is saturated; the accelerometer while fresh and
    not saturated. ``drop_rate_comm`` (c%) and ``errors_comm`` describe the
    compass's serial line (lines dropped as noise); ``errors_count1..4`` are
    lost frames, reconnects, stale events and pipeline errors.
    """
    mag, acc = M.MAV_SYS_STATUS_SENSOR_3D_MAG, M.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    live = h.fresh and h.link_state is LinkState.STREAMING
    # Every sensor we do not have counts as healthy, as ArduPilot reports them: ground
    # stations read a clear health bit as a fault (MAVProxy says "fence breach" when the
    # GEOFENCE bit is clear, whether or not a fence is present).
    absent = _UINT32 & ~(mag | acc)
    mag_ok = live and heading_usable(h.saturated, h.disturbed)
    health = absent | (mag if mag_ok else 0) | (acc if live and not h.saturated else 0)
    total = h.bad_lines + h.good_lines
    drop = round(10000 * h.bad_lines / total) if total else 0
    return message(
        SYS_STATUS,
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


def euler_of(sample: CompassSample) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians; yaw from the published heading, unknown angles 0."""
    a = sample.attitude
    if a is not None:
        return a.roll, a.pitch, a.yaw
    roll = math.radians(sample.roll_deg) if sample.roll_deg is not None else 0.0
    pitch = math.radians(sample.pitch_deg) if sample.pitch_deg is not None else 0.0
    return roll, pitch, wrap_radians_pi(math.radians(sample.heading_deg))


def _ms32(t_ms: int) -> int:
    return int(t_ms) & 0xFFFFFFFF


def attitude(sample: CompassSample, time_boot_ms: int) -> Message:
    """ATTITUDE."""
    a = sample.attitude
    if a is not None:  # a host sample: the solution's own angles (euler_of's first case)
        return M.MAVLink_attitude_message(
            _ms32(time_boot_ms), a.roll, a.pitch, a.yaw, 0.0, 0.0, 0.0
        )
    roll, pitch, yaw = euler_of(sample)
    return M.MAVLink_attitude_message(_ms32(time_boot_ms), roll, pitch, yaw, 0.0, 0.0, 0.0)


def attitude_quaternion(sample: CompassSample, time_boot_ms: int) -> Message:
    """ATTITUDE_QUATERNION (q1..q4 = w, x, y, z)."""
    a = sample.attitude
    q = a.quaternion if a is not None else euler_to_quaternion(*euler_of(sample))
    return M.MAVLink_attitude_quaternion_message(
        _ms32(time_boot_ms), q[0], q[1], q[2], q[3], 0.0, 0.0, 0.0, (0.0, 0.0, 0.0, 0.0)
    )


def vfr_hud(sample: CompassSample, alt_m: float = 0.0) -> Message:
    """VFR_HUD: heading in whole degrees (0..359)."""
    return M.MAVLink_vfr_hud_message(0.0, 0.0, round(sample.heading_deg) % 360, 0, alt_m, 0.0)


def _i16(v: float) -> int:
    """``v`` rounded into int16's symmetric range; 0 when it is not finite."""
    if -_INT16 <= v <= _INT16:  # the common case, one chained comparison (NaN fails it)
        return round(v)
    if math.isfinite(v):
        return _INT16 if v > 0.0 else -_INT16
    return 0


# The per-sample encoders below run for every stream of every sample: they call the
# generated message classes with positional fields (in the classes' constructor order)
# rather than through dialect.message(**fields), whose keyword dict and lookup cost more
# than the arithmetic here.


def scaled_imu(sample: CompassSample, time_boot_ms: int) -> Message | None:
    """SCALED_IMU (None without calibrated vectors: a heading-only compass)."""
    a = sample.attitude
    if a is None:
        return None
    gx, gy, gz = a.accel_g
    mx, my, mz = a.mag_G
    # specific force = -gravity vector, in mG; the field in mgauss
    xacc, yacc, zacc = _i16(-1000.0 * gx), _i16(-1000.0 * gy), _i16(-1000.0 * gz)
    xmag, ymag, zmag = _i16(1000.0 * mx), _i16(1000.0 * my), _i16(1000.0 * mz)
    # time, accelerometer, no gyro, magnetometer, temperature 0 (none)
    return M.MAVLink_scaled_imu_message(
        _ms32(time_boot_ms), xacc, yacc, zacc, 0, 0, 0, xmag, ymag, zmag, 0
    )


def raw_imu(sample: CompassSample, time_usec: int) -> Message | None:
    """RAW_IMU: the ADC counts as the device sent them (None when not known)."""
    rc = sample.raw_counts
    if rc is None:
        return None
    mx, my, mz, ax, ay, az = rc
    # time, accelerometer, no gyro, magnetometer, id 0, temperature 0 (none)
    return M.MAVLink_raw_imu_message(max(0, int(time_usec)), ax, ay, az, 0, 0, 0, mx, my, mz, 0, 0)


#: HIGHRES_IMU.fields_updated: xacc..zacc (bits 0-2) and xmag..zmag (bits 6-8).
HIGHRES_FIELDS_ACC_MAG = 0b111 | (0b111 << 6)


def highres_imu(sample: CompassSample, time_usec: int) -> Message | None:
    """HIGHRES_IMU: specific force in m/s^2, field in gauss (None without vectors)."""
    a = sample.attitude
    if a is None:
        return None
    gx, gy, gz = a.accel_g
    mx, my, mz = a.mag_G
    k = -STANDARD_GRAVITY
    t = max(0, int(time_usec))
    xacc, yacc, zacc = k * gx, k * gy, k * gz  # specific force, m/s^2
    # time, accelerometer, no gyro, magnetometer, no pressures or temperature, flags, id 0
    return M.MAVLink_highres_imu_message(
        t,
        xacc,
        yacc,
        zacc,
        0.0,
        0.0,
        0.0,
        mx,
        my,
        mz,
        0.0,
        0.0,
        0.0,
        0.0,
        HIGHRES_FIELDS_ACC_MAG,
        0,
    )


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
    return heading_usable(sample.saturated, a is not None and a.disturbed)


def feed_yaw_sigma_rad(sample: CompassSample, sigma_deg: float) -> float:
    """Yaw standard deviation: ``sigma_deg`` with the heading error the sample's tilt
    leaves (``heading_sigma_deg``, in quadrature); five times that while degraded, or
    while accelerating with the accelerometer as the only tilt source."""
    a = sample.attitude
    if a is None:
        return math.radians(sigma_deg)
    tilt = a.heading_sigma_deg
    s = math.hypot(sigma_deg, tilt) if tilt is not None and math.isfinite(tilt) else sigma_deg
    blind = a.accelerating and a.tilt_source == "accelerometer"
    return math.radians((5.0 if a.degraded or blind else 1.0) * s)


#: NAMED_VALUE_INT name of the tilt source each ATTITUDE used: 0 accelerometer,
#: 1 autopilot, 2 magnetometer (:data:`bridge.core.tilt.TILT_SOURCES`).
TILT_SOURCE_NAME = "TILT_SRC"


#: TILT_SRC goes beside an ATTITUDE when the tilt source changes, and at least this often.
TILT_SOURCE_EVERY_S = 1.0


class TiltSourceNote:
    """When TILT_SRC goes out: beside the ATTITUDE of a sample whose tilt source differs from
    the last one sent, and beside one a second otherwise. Every sample's source is the one
    last sent before it, without a second packet per ATTITUDE: 50 Hz of them would take a
    quarter of a 57600 baud radio. Used by the pipeline's thread only."""

    def __init__(self) -> None:
        self._last: str | None = None
        self._at = -math.inf

    def due(self, sample: CompassSample, now: float, time_boot_ms: int) -> tuple[Message, ...]:
        """The TILT_SRC to send with this sample's ATTITUDE: one, or none."""
        src = sample.tilt_source
        if src == self._last and 0.0 <= now - self._at < TILT_SOURCE_EVERY_S:
            return ()
        self._last, self._at = src, now
        return (tilt_source(sample, time_boot_ms),)


def tilt_source(sample: CompassSample, time_boot_ms: int) -> Message:
    """NAMED_VALUE_INT ``TILT_SRC``: the tilt source of ``sample`` (sent with its ATTITUDE,
    same ``time_boot_ms``, see :class:`TiltSourceNote`): 0 accelerometer, 1 autopilot,
    2 magnetometer; -1 a heading-only compass's own."""
    src = sample.tilt_source
    value = TILT_SOURCES.index(src) if src in TILT_SOURCES else -1
    return message(
        M.MAVLINK_MSG_ID_NAMED_VALUE_INT,
        time_boot_ms=_ms32(time_boot_ms),
        name=TILT_SOURCE_NAME.encode(),
        value=value,
    )


def feed_euler(sample: CompassSample) -> tuple[float, float, float, bool]:
    """(roll, pitch, yaw, is_true): yaw from the true heading when a declination is known."""
    roll, pitch, _published = euler_of(sample)
    true = sample.heading_true_deg
    if true is not None:
        return roll, pitch, wrap_radians_pi(math.radians(true)), True
    mag = sample.heading_magnetic_deg
    hdg = mag if mag is not None else sample.heading_deg
    return roll, pitch, wrap_radians_pi(math.radians(hdg)), False


def _pose_covariance(yaw_var: float) -> list[float]:
    cov = [0.0] * 21
    cov[0] = cov[6] = cov[11] = FEED_POSITION_VARIANCE  # x, y, z: unknown (placeholder)
    cov[15] = cov[18] = cov[20] = yaw_var  # roll, pitch, yaw
    return cov


def ardupilot_covariance(sigma_rad: float) -> list[float]:
    """VISION_POSITION_ESTIMATE.covariance for ArduPilot, whose yaw noise is
    ``angErr = cbrtf(sq(c[15]) + sq(c[18]) + sq(c[20]))`` (GCS_Common.cpp,
    ``handle_vision_position_estimate``; ``posErr`` likewise from c[0], c[6], c[11]) and
    is used as a standard deviation (``AP_VisualOdom_MAV::handle_pose_estimate`` floors it
    at VISO_YAW_M_NSE, EKF3's ``writeExtNavData`` at 5 deg). With c[20] = sigma^1.5 and
    c[15] = c[18] = 0, ``angErr`` is sigma itself; the variance in all three slots would
    give ``cbrt(3 sigma^4)`` (2 deg arrived as 0.94 deg). Roll and pitch are not fused
    from this message, so their slots carry nothing. The position slots keep
    :data:`FEED_POSITION_VARIANCE` (``posErr`` 669 m, floored to ArduPilot's 100 m cap).
    """
    cov = [0.0] * 21
    cov[0] = cov[6] = cov[11] = FEED_POSITION_VARIANCE
    cov[20] = sigma_rad**1.5
    return cov


def odometry(
    sample: CompassSample, time_usec: int, sigma_deg: float, reset_counter: int = 0
) -> Message:
    """PX4 ODOMETRY for EKF2 external-vision yaw fusion (EKF2_EV_CTRL bit 3)."""
    roll, pitch, yaw, _true = feed_euler(sample)
    var = feed_yaw_sigma_rad(sample, sigma_deg) ** 2
    nan = math.nan
    a = sample.attitude
    quality = 50 if a is not None and (a.accelerating or a.degraded) else 100
    return message(
        ODOMETRY,
        time_usec=max(0, int(time_usec)),
        frame_id=M.MAV_FRAME_LOCAL_NED,
        child_frame_id=M.MAV_FRAME_BODY_FRD,
        x=0.0,
        y=0.0,
        z=0.0,
        q=euler_to_quaternion(roll, pitch, yaw),
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
) -> Message:
    """ArduPilot VISION_POSITION_ESTIMATE for ExternalNav yaw (EK3_SRC1_YAW = 6)."""
    roll, pitch, yaw, _true = feed_euler(sample)
    sigma = feed_yaw_sigma_rad(sample, sigma_deg)
    return message(
        VISION_POSITION_ESTIMATE,
        usec=max(0, int(time_usec)),
        x=0.0,
        y=0.0,
        z=0.0,
        roll=roll,
        pitch=pitch,
        yaw=yaw,
        covariance=ardupilot_covariance(sigma),
        reset_counter=reset_counter & 0xFF,
    )


# ---------------------------------------------------------------------------- replies and events


def statustext(severity: int, text: str, chunk_id: int = 0) -> list[Message]:
    """STATUSTEXT messages for ``text`` (UTF-8), as the MAVLink spec chunks it.

    A text of at most 50 bytes is one message with ``id`` 0. A longer one is cut
    into chunks of exactly 50 bytes sharing ``chunk_id`` (non-zero), with
    ``chunk_seq`` 0, 1, ...: the spec takes a chunk with a NUL in it -- one
    shorter than 50 bytes -- as the last, so every chunk but the last is full
    (a chunk may end inside a UTF-8 character: the receiver joins the bytes
    before decoding), and a text whose length is a multiple of 50 ends with an
    empty chunk.
    """
    data = text.encode("utf-8")
    if len(data) <= STATUSTEXT_LEN:
        return [message(STATUSTEXT, severity=severity, text=data, id=0, chunk_seq=0)]
    ident = chunk_id & 0xFFFF or 1
    chunks = [data[i : i + STATUSTEXT_LEN] for i in range(0, len(data), STATUSTEXT_LEN)]
    if len(chunks[-1]) == STATUSTEXT_LEN:
        chunks.append(b"")  # the terminating chunk: all NUL
    return [
        message(STATUSTEXT, severity=severity, text=chunk, id=ident, chunk_seq=i & 0xFF)
        for i, chunk in enumerate(chunks)
    ]


def command_ack(
    command: int,
    result: int,
    target_system: int,
    target_component: int,
    progress: int = 0,
    result_param2: int = 0,
) -> Message:
    """COMMAND_ACK to the sender of a command."""
    return message(
        M.MAVLINK_MSG_ID_COMMAND_ACK,
        command=command,
        result=result,
        progress=max(0, min(255, int(progress))),
        result_param2=int(result_param2),
        target_system=target_system,
        target_component=target_component,
    )


def message_interval(msgid: int, interval_us: int) -> Message:
    """MESSAGE_INTERVAL (answer to MAV_CMD_GET_MESSAGE_INTERVAL)."""
    return message(M.MAVLINK_MSG_ID_MESSAGE_INTERVAL, message_id=msgid, interval_us=interval_us)


class _TimesyncWithTarget(M.MAVLink_timesync_message):
    """TIMESYNC with MAVLink 2's extension fields ``target_system`` / ``target_component``,
    which pymavlink's ardupilotmega dialect (2.4.50) does not know yet: packed after tc1
    and ts1 as the current common.xml defines them (a parser without the extension reads
    tc1 and ts1 and ignores the rest)."""

    def __init__(self, tc1: int, ts1: int, target_system: int, target_component: int) -> None:
        super().__init__(tc1, ts1)
        self.target_system = target_system
        self.target_component = target_component

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        payload = struct.pack(
            "<qqBB", self.tc1, self.ts1, self.target_system, self.target_component
        )
        data: bytes = self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1)
        return data


def timesync_reply(
    tc1_ns: int, ts1: int, target_system: int = 0, target_component: int = 0
) -> Message:
    """TIMESYNC answer: our time (ns) in tc1, the request's ts1 echoed, addressed to the
    requester (MAVLink 2's target fields; 0 = every system / component)."""
    return _TimesyncWithTarget(
        int(tc1_ns), int(ts1), int(target_system) & 0xFF, int(target_component) & 0xFF
    )


def encode_version(text: str, release_type: int = 255) -> int:
    """``"1.2.3"`` as MAVLink's (major << 24 | minor << 16 | patch << 8 | type)."""
    parts = [int(p) if p.isdigit() else 0 for p in text.split(".")[:3]]
    parts += [0] * (3 - len(parts))
    major, minor, patch = (max(0, min(255, p)) for p in parts)
    return major << 24 | minor << 16 | patch << 8 | (release_type & 0xFF)


#: Protocol capabilities we implement: MAVLink 2, COMMAND_INT, compass calibration (and
#: the parameter encoding of the flavour, added by the caller).
CAPABILITIES = (
    M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | M.MAV_PROTOCOL_CAPABILITY_COMPASS_CALIBRATION
)


def autopilot_version(
    bridge_version: str,
    device_firmware: str | None,
    device_serial: str | None,
    uid: int,
    param_encoding: int = M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST,
) -> Message:
    """AUTOPILOT_VERSION: the bridge as flight software, the compass firmware as middleware."""
    return message(
        AUTOPILOT_VERSION,
        capabilities=CAPABILITIES | param_encoding,
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
) -> Message:
    """MAG_CAL_PROGRESS (ArduPilot): percent, the 80-section coverage mask, the field direction."""
    mask = bytes(completion_mask)
    if len(mask) != 10:
        raise ValueError(f"completion_mask must be 10 bytes, got {len(mask)}")
    return message(
        MAG_CAL_PROGRESS,
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


def mag_cal_report(r: MagCalReport, compass_id: int = 0) -> Message:
    """MAG_CAL_REPORT."""

    def f(v: float) -> float:
        return float(v) if math.isfinite(v) else 0.0

    return message(
        MAG_CAL_REPORT,
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


def param_value(name: str, value: float, param_type: int, count: int, index: int) -> Message:
    """PARAM_VALUE (value already C-cast to float by the caller)."""
    return message(
        M.MAVLINK_MSG_ID_PARAM_VALUE,
        param_id=name.encode("ascii"),
        param_value=float(value),
        param_type=param_type,
        param_count=count,
        param_index=index,
    )
