"""Telemetry encoders and the stream schedule (pure), decoded by pymavlink."""

from __future__ import annotations

import math
import random
from typing import Any

import numpy as np
import pytest

from bridge.app.sample import CompassSample
from bridge.core.attitude import AttitudeEngine, FieldReference
from bridge.core.geometry import euler_to_dcm, euler_to_quaternion
from bridge.core.sensor import STANDARD_GRAVITY, g_to_acc_counts, gauss_to_mag_counts
from bridge.link.serial_link import LinkState
from bridge.mavlink import schedule as S  # noqa: N812 - short
from bridge.mavlink import telemetry as T  # noqa: N812 - short
from bridge.mavlink.dialect import Message
from bridge.mavlink.dialect import mavlink as M  # noqa: N812 - the generated module

B_NED = np.array([0.21, 0.0, 0.42])  # gauss: north and down (dip 63 deg), as in Zurich
DECL = 3.0  # deg east


def decode(p: Message | None) -> Any:
    """The message as a ground station decodes it from the bytes pymavlink frames; ``None``
    (a builder such as ``T.scaled_imu`` that built nothing) fails the test."""
    assert p is not None, "no message built"
    (msg,) = M.MAVLink(None).parse_buffer(p.pack(M.MAVLink(None, 1, 1)))
    return msg


def make_sample(
    roll_deg: float = 0.0,
    pitch_deg: float = 0.0,
    yaw_deg: float = 30.0,
    *,
    declination: float | None = DECL,
    t: float = 12.5,
    field_scale: float = 1.0,
) -> CompassSample:
    """A host sample of a perfect unit at the given attitude (truth from the geometry)."""
    R = euler_to_dcm(*(math.radians(a) for a in (roll_deg, pitch_deg, yaw_deg)))
    mag = R.T @ (B_NED * field_scale)
    acc = R.T @ np.array([0.0, 0.0, 1.0])
    ref = FieldReference(declination, float(np.linalg.norm(B_NED)), 63.4, "test")
    engine = AttitudeEngine(reference=ref)
    a = None
    for _ in range(6):  # past the quality debounce
        a = engine.solve_vectors(mag, acc)
    assert a is not None
    mc = np.rint(gauss_to_mag_counts(mag)).astype(int)
    ac = np.rint(g_to_acc_counts(acc)).astype(int)
    return CompassSample.from_solution(
        a, t, raw_counts=(int(mc[0]), int(mc[1]), int(mc[2]), int(ac[0]), int(ac[1]), int(ac[2]))
    )


def test_attitude_and_quaternion_carry_the_published_heading() -> None:
    s = make_sample(roll_deg=5.0, pitch_deg=-10.0, yaw_deg=30.0)
    att = decode(T.attitude(s, 4321))
    assert att.time_boot_ms == 4321
    assert math.degrees(att.roll) == pytest.approx(5.0, abs=1e-4)
    assert math.degrees(att.pitch) == pytest.approx(-10.0, abs=1e-4)
    assert math.degrees(att.yaw) == pytest.approx(30.0, abs=1e-4)  # magnetic, as published
    assert (att.rollspeed, att.pitchspeed, att.yawspeed) == (0.0, 0.0, 0.0)  # no gyro
    q = decode(T.attitude_quaternion(s, 4321))
    want = euler_to_quaternion(math.radians(5.0), math.radians(-10.0), math.radians(30.0))
    assert np.allclose([q.q1, q.q2, q.q3, q.q4], want, atol=1e-6)
    hud = decode(T.vfr_hud(make_sample(yaw_deg=359.6), alt_m=12.5))
    assert hud.heading == 0 and hud.alt == 12.5  # whole degrees, 360 folds to 0
    assert decode(T.vfr_hud(make_sample(yaw_deg=181.4))).heading == 181


def test_heading_only_sample_gives_attitude_but_no_imu() -> None:
    s = CompassSample(
        t=1.0, source="device", heading_deg=270.0, heading_reference="magnetic",
        heading_magnetic_deg=270.0, heading_true_deg=None, declination_deg=None,
        pitch_deg=None, roll_deg=None,
    )  # fmt: skip
    att = decode(T.attitude(s, 0))
    assert math.degrees(att.yaw) == pytest.approx(-90.0) and att.roll == 0.0
    assert T.scaled_imu(s, 0) is None and T.highres_imu(s, 0) is None and T.raw_imu(s, 0) is None


def test_imu_messages_units_and_signs() -> None:
    s = make_sample(yaw_deg=0.0)
    si = decode(T.scaled_imu(s, 77))
    # a level unit at rest: specific force straight up = -1 g on z (MAVLink IMU convention)
    assert (si.xacc, si.yacc) == (0, 0) and si.zacc == -1000
    assert si.xmag == 210 and si.ymag == 0 and si.zmag == 420  # mgauss, facing north
    hr = decode(T.highres_imu(s, 5_000_000))
    assert hr.time_usec == 5_000_000
    assert hr.zacc == pytest.approx(-STANDARD_GRAVITY, abs=1e-5)
    assert hr.xmag == pytest.approx(0.21, abs=1e-6) and hr.zmag == pytest.approx(0.42, abs=1e-6)
    assert hr.fields_updated == 0b111 | 0b111 << 6  # accelerometer and magnetometer only
    raw = decode(T.raw_imu(s, 99))
    assert (raw.xmag, raw.ymag, raw.zmag, raw.xacc, raw.yacc, raw.zacc) == s.raw_counts
    # a field too strong for int16 mgauss is clipped, not wrapped
    big = decode(T.scaled_imu(make_sample(yaw_deg=0.0, field_scale=200.0), 0))
    assert big.xmag == 32767


def test_heading_feed_messages() -> None:
    s = make_sample(roll_deg=2.0, pitch_deg=1.0, yaw_deg=100.0)
    od = decode(T.odometry(s, 123_000, sigma_deg=2.0, reset_counter=3))
    assert od.frame_id == M.MAV_FRAME_LOCAL_NED and od.child_frame_id == M.MAV_FRAME_BODY_FRD
    assert od.estimator_type == M.MAV_ESTIMATOR_TYPE_VISION and od.reset_counter == 3
    assert (od.x, od.y, od.z) == (0.0, 0.0, 0.0)  # finite: PX4 then takes the NED pose frame
    want = euler_to_quaternion(math.radians(2.0), math.radians(1.0), math.radians(100.0 + DECL))
    assert np.allclose(list(od.q), want, atol=1e-5)  # the TRUE heading
    assert od.pose_covariance[20] == pytest.approx(math.radians(2.0) ** 2, rel=1e-6)
    assert od.pose_covariance[0] >= 1e3  # position: no information
    assert math.isnan(od.velocity_covariance[0]) and math.isnan(od.vx)
    vpe = decode(T.vision_position_estimate(s, 123_000, sigma_deg=2.0))
    assert math.degrees(vpe.yaw) == pytest.approx(100.0 + DECL, abs=1e-4)
    # ArduPilot reads angErr = cbrt(c15^2 + c18^2 + c20^2) as the yaw sigma (GCS_Common.cpp)
    c = vpe.covariance
    ang_err = (c[15] ** 2 + c[18] ** 2 + c[20] ** 2) ** (1.0 / 3.0)
    assert ang_err == pytest.approx(math.radians(2.0), rel=1e-5)
    pos_err = (c[0] ** 2 + c[6] ** 2 + c[11] ** 2) ** (1.0 / 3.0)
    assert pos_err > 100.0  # ArduPilot's cap: no position information
    # no declination: the magnetic heading, flagged as such
    nodecl = make_sample(yaw_deg=100.0, declination=None)
    assert T.feed_euler(nodecl)[3] is False and T.feed_euler(s)[3] is True
    assert math.degrees(T.feed_euler(nodecl)[2]) == pytest.approx(100.0, abs=1e-6)


def test_feed_is_withheld_when_disturbed_and_widened_when_accelerating() -> None:
    calm = make_sample()
    assert T.feed_usable(calm)
    disturbed = make_sample(field_scale=1.5)  # 50 % too strong: not the Earth's field
    assert disturbed.attitude is not None and disturbed.attitude.disturbed
    assert not T.feed_usable(disturbed)
    acc = calm.attitude
    assert acc is not None
    shaken = CompassSample(**{**_fields(calm), "attitude": _replace(acc, accelerating=True)})
    assert T.feed_yaw_sigma_rad(shaken, 2.0) == pytest.approx(5 * T.feed_yaw_sigma_rad(calm, 2.0))


def _fields(s: CompassSample) -> dict[str, Any]:
    return {n: getattr(s, n) for n in CompassSample.__dataclass_fields__}


def _replace(a: Any, **kw: Any) -> Any:
    from dataclasses import replace

    return replace(a, **kw)


def health(**kw: Any) -> T.Health:
    base: dict[str, Any] = dict(
        link_state=LinkState.STREAMING, fresh=True, calibrating=False, disturbed=False,
        saturated=False, compass_use=True,
    )  # fmt: skip
    base.update(kw)
    return T.Health(**base)


MAG, ACC = M.MAV_SYS_STATUS_SENSOR_3D_MAG, M.MAV_SYS_STATUS_SENSOR_3D_ACCEL


@pytest.mark.parametrize(
    ("kw", "healthy", "enabled"),
    [
        ({}, MAG | ACC, MAG | ACC),
        ({"disturbed": True}, ACC, MAG | ACC),
        ({"fresh": False}, 0, MAG | ACC),
        ({"link_state": LinkState.STALE}, 0, MAG | ACC),
        ({"saturated": True}, 0, MAG | ACC),
        ({"compass_use": False}, MAG | ACC, ACC),
    ],
)
def test_sys_status_sensor_bits(kw: dict[str, Any], healthy: int, enabled: int) -> None:
    m = decode(T.sys_status(health(**kw)))
    assert m.onboard_control_sensors_present == MAG | ACC
    assert m.onboard_control_sensors_enabled == enabled
    assert m.onboard_control_sensors_health & (MAG | ACC) == healthy
    # every sensor we do not have reads healthy (MAVProxy takes a clear GEOFENCE bit for
    # "fence breach"), as ArduPilot reports its absent sensors
    absent = 0xFFFFFFFF & ~(MAG | ACC)
    assert m.onboard_control_sensors_health & absent == absent


def test_sys_status_link_counters() -> None:
    m = decode(T.sys_status(health(bad_lines=5, good_lines=995, lost_frames=70000, reconnects=2)))
    assert m.drop_rate_comm == 50 and m.errors_comm == 5  # 0.5 % in c%
    assert m.errors_count1 == 65535 and m.errors_count2 == 2  # clipped, not wrapped
    assert m.voltage_battery == 65535 and m.battery_remaining == -1  # unknown


def test_heartbeat_by_role_and_state() -> None:
    sa = decode(T.heartbeat(T.Identity(1, 1, "standalone"), T.system_status(health())))
    assert (sa.type, sa.autopilot) == (M.MAV_TYPE_GENERIC, M.MAV_AUTOPILOT_GENERIC)
    assert sa.system_status == M.MAV_STATE_ACTIVE and sa.mavlink_version == 3
    for flavour, autopilot in (
        ("px4", M.MAV_AUTOPILOT_PX4),
        ("ardupilot", M.MAV_AUTOPILOT_ARDUPILOTMEGA),
    ):
        hb = decode(T.heartbeat(T.Identity(1, 1, "standalone", flavour), 0))
        assert hb.autopilot == autopilot
    # beside an autopilot a component is no vehicle, whatever the flavour
    co = decode(T.heartbeat(T.Identity(1, 200, "companion", "px4"), 0))
    assert (co.type, co.autopilot) == (M.MAV_TYPE_IMU, M.MAV_AUTOPILOT_INVALID)
    assert T.system_status(health(calibrating=True)) == M.MAV_STATE_CALIBRATING
    assert T.system_status(health(link_state=LinkState.OPENING, fresh=False)) == M.MAV_STATE_BOOT
    assert T.system_status(health(link_state=LinkState.STALE)) == M.MAV_STATE_CRITICAL
    assert T.system_status(health(link_state=LinkState.ABSENT, fresh=False)) == M.MAV_STATE_CRITICAL


def test_statustext_chunks_long_texts_as_the_spec_says() -> None:
    short = T.statustext(6, "Compass link restored")
    assert len(short) == 1 and decode(short[0]).id == 0
    text = "Magnetic disturbance near the sensor: " + "é" * 40 + " -- move away from the iron"
    packets = T.statustext(4, text, chunk_id=77)
    assert len(packets) >= 2
    chunks = [wire_text(p) for p in packets]
    # Only the last chunk is shorter than 50 bytes (has a NUL): the spec's end marker, so no
    # middle chunk may be cut short at a character boundary; the receiver joins the bytes.
    assert all(len(c) == 50 for c in chunks[:-1]) and len(chunks[-1]) < 50
    assert b"".join(chunks).decode("utf-8") == text
    msgs = [decode(p) for p in packets]
    assert {m.id for m in msgs} == {77} and [m.chunk_seq for m in msgs] == list(range(len(msgs)))
    assert all(m.severity == 4 for m in msgs)


@pytest.mark.parametrize("n", [51, 99, 100, 150])
def test_a_chunked_text_always_ends_with_a_short_chunk(n: int) -> None:
    text = "x" * n
    chunks = [wire_text(p) for p in T.statustext(6, text, chunk_id=5)]
    assert b"".join(chunks).decode() == text
    assert len(chunks[-1]) < 50  # a text of exactly 50 k bytes gets an empty final chunk
    assert len(chunks) == n // 50 + 1


def wire_text(p: Any) -> bytes:
    """The text bytes a STATUSTEXT carries on the wire (NULs stripped)."""
    p.pack(M.MAVLink(None, 1, 1))
    raw = p.get_payload() + bytes(54 - len(p.get_payload()))
    return bytes(raw[1:51]).rstrip(b"\0")  # wire layout "<B50sHB": severity, text, id, seq


def test_schedule_keeps_the_rate_on_jittery_samples() -> None:
    rng = random.Random(1)
    sched = S.StreamSchedule({T.ATTITUDE: 10.0, T.VFR_HUD: 4.0, T.SCALED_IMU: 0.0})
    counts = {T.ATTITUDE: 0, T.VFR_HUD: 0, T.SCALED_IMU: 0}
    t = 0.0
    for _ in range(1000):  # 100 s of 10 Hz frames with +-20 % timing jitter
        t += 0.1 * rng.uniform(0.8, 1.2)
        for m in sched.due_on_sample(counts, t):
            counts[m] += 1
    assert 940 <= counts[T.ATTITUDE] <= 1000  # equal rates: (almost) every frame goes out
    assert 390 <= counts[T.VFR_HUD] <= 410
    assert counts[T.SCALED_IMU] == 0  # off


def test_schedule_overrides_and_clock_streams() -> None:
    sched = S.StreamSchedule({T.SYS_STATUS: 2.0, T.ATTITUDE: 10.0})
    assert sched.rate(T.HEARTBEAT) == 1.0 and sched.interval_us(T.ATTITUDE) == 100_000
    sent = {T.HEARTBEAT: 0, T.SYS_STATUS: 0}
    t = 0.0
    while t < 10.0:  # no samples at all: clock streams go on
        for m in sched.due_on_clock(t):
            sent[m] += 1
        t = max(t + 0.01, sched.next_clock_due(t))
    assert 10 <= sent[T.HEARTBEAT] <= 11 and 20 <= sent[T.SYS_STATUS] <= 21
    assert T.ATTITUDE not in sched.due_on_clock(20.0)  # sample streams never go by the clock
    sched.set_override(T.ATTITUDE, 0.0)
    assert sched.interval_us(T.ATTITUDE) == -1 and sched.due_on_sample([T.ATTITUDE], 30.0) == []
    sched.set_override(T.ATTITUDE, None)
    assert sched.rate(T.ATTITUDE) == 10.0
    with pytest.raises(ValueError):
        sched.set_base(T.ATTITUDE, math.nan)


def test_autopilot_version_and_capabilities() -> None:
    m = decode(T.autopilot_version("0.1.0", "2.1.0", "GMR-000417", uid=42))  # C-cast default
    assert m.flight_sw_version == (0 << 24 | 1 << 16 | 0 << 8 | 255)
    assert m.middleware_sw_version == (2 << 24 | 1 << 16 | 0 << 8 | 255)
    assert m.capabilities & M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert m.capabilities & M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
    assert not m.capabilities & M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    assert bytes(m.uid2).rstrip(b"\0") == b"GMR-000417" and m.uid == 42
