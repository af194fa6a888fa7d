"""The MAVLink output in the running daemon: telemetry, commands, parameters, roles, persistence.

Every test runs the real daemon on the simulated compass and talks to it with a
real pymavlink ground station over UDP or TCP on 127.0.0.1.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_mavlink_rig import (
    DEADLINE_S,
    GCS_COMPID,
    GCS_SYSID,
    LAT,
    LON,
    Gcs,
    M,
    Rig,
    connect_gcs,
    free_port,
    start_rig,
    wait_until,
)

from bridge.app import pipeline as pipeline_module
from bridge.core.calibration import Calibration
from bridge.core.mounting import Rotation
from bridge.core.wmm import earth_field
from bridge.sim.motion import Still

pytestmark = pytest.mark.integration  # real sockets, processes or threads


REAL32, INT8, INT32 = M.MAV_PARAM_TYPE_REAL32, M.MAV_PARAM_TYPE_INT8, M.MAV_PARAM_TYPE_INT32
ACCEPTED, DENIED, UNSUPPORTED = M.MAV_RESULT_ACCEPTED, M.MAV_RESULT_DENIED, M.MAV_RESULT_UNSUPPORTED


def rate(msgs: list[Any], mtype: str, seconds: float) -> float:
    return sum(1 for m in msgs if m.get_type() == mtype) / seconds


def collect_frames(rig: Rig, g: Gcs, seconds: float) -> tuple[list[Any], float]:
    """What ``g`` receives while the simulated compass sends ``seconds`` of its frames, and
    those seconds as the compass counts them (its frames over its rate): a rate measured
    on the device's own clock, which a busy machine delays but does not shorten."""
    hz = rig.cfg.device.rate_hz
    f0 = rig.fw.frames_sent
    msgs: list[Any] = []
    deadline = time.monotonic() + seconds + DEADLINE_S
    while rig.fw.frames_sent < f0 + round(seconds * hz):
        assert time.monotonic() < deadline, "the simulated compass stopped sending"
        msgs += g.collect(0.05)
    return msgs, (rig.fw.frames_sent - f0) / hz


# =====================================================================================
# telemetry
# =====================================================================================


def test_every_stream_arrives_at_its_rate_with_consistent_values(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    rig = rigs(tmp_path, ideal=True)
    g = rig.gcs("udp")
    g.flush()
    msgs = g.collect(3.0)
    r = {t: rate(msgs, t, 3.0) for t in Counter(m.get_type() for m in msgs)}
    assert 7.0 <= r["ATTITUDE"] <= 11.0 and 7.0 <= r["ATTITUDE_QUATERNION"] <= 11.0
    assert 2.5 <= r["VFR_HUD"] <= 4.5
    for t in ("SCALED_IMU", "RAW_IMU", "HIGHRES_IMU"):
        assert 1.25 <= r[t] <= 2.5, t
    assert 0.5 <= r["HEARTBEAT"] <= 1.5 and 0.5 <= r["SYS_STATUS"] <= 1.5
    assert all(m.get_srcSystem() == 1 and m.get_srcComponent() == 1 for m in msgs)

    hb = next(m for m in msgs if m.get_type() == "HEARTBEAT")
    assert (hb.type, hb.autopilot) == (M.MAV_TYPE_GENERIC, M.MAV_AUTOPILOT_GENERIC)
    assert hb.system_status == M.MAV_STATE_ACTIVE
    ss = next(m for m in msgs if m.get_type() == "SYS_STATUS")
    mag_acc = M.MAV_SYS_STATUS_SENSOR_3D_MAG | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    assert ss.onboard_control_sensors_present == mag_acc
    # a perfect unit: fresh, not disturbed (and the sensors we do not have read healthy)
    assert ss.onboard_control_sensors_health & mag_acc == mag_acc
    assert ss.onboard_control_sensors_health & M.MAV_SYS_STATUS_GEOFENCE

    # The ideal unit turns level at 10 deg/s from north: the attitude follows the physics.
    atts = [m for m in msgs if m.get_type() == "ATTITUDE"]
    for a in atts:
        assert abs(a.roll) < math.radians(0.5) and abs(a.pitch) < math.radians(0.5)
    yaws = np.unwrap([a.yaw for a in atts])
    times = np.array([a.time_boot_ms for a in atts]) / 1000.0
    slope = np.polyfit(times, np.degrees(yaws), 1)[0]
    assert slope == pytest.approx(10.0, abs=0.5)  # deg/s, from the stamps we sent
    # every message of one sample agrees with the others
    hud = next(m for m in msgs if m.get_type() == "VFR_HUD")
    assert 0 <= hud.heading <= 359
    si = next(m for m in msgs if m.get_type() == "SCALED_IMU")
    assert (
        si.zacc == pytest.approx(-1000, abs=15) and abs(si.xacc) < 15
    )  # level: -1 g specific force
    field_mG = math.sqrt(si.xmag**2 + si.ymag**2 + si.zmag**2)
    assert field_mG == pytest.approx(1000 * earth_field(LAT, LON).total_G, rel=0.02)
    raw = next(m for m in msgs if m.get_type() == "RAW_IMU")
    assert all(0 < v < 4095 for v in (raw.xmag, raw.ymag, raw.zmag, raw.xacc, raw.yacc, raw.zacc))
    assert raw.zacc == pytest.approx(2458 + 491.5, abs=3)  # +1 g on z in the device's counts
    hr = next(m for m in msgs if m.get_type() == "HIGHRES_IMU")
    assert hr.zacc == pytest.approx(-9.80665, abs=0.15) and hr.fields_updated == 0x1C7


def test_message_interval_and_request_message(tmp_path: Path, rigs: Callable[..., Rig]) -> None:
    rig = rigs(tmp_path)
    g = rig.gcs("tcp")
    att = M.MAVLINK_MSG_ID_ATTITUDE
    assert g.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, att, 500_000).result == ACCEPTED
    g.command(M.MAV_CMD_GET_MESSAGE_INTERVAL, att)
    assert g.wait("MESSAGE_INTERVAL").interval_us == 500_000
    g.flush()
    msgs, secs = collect_frames(rig, g, 3.0)
    assert 1.0 <= rate(msgs, "ATTITUDE", secs) <= 3.0  # 2 Hz now
    assert g.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, att, -1).result == ACCEPTED
    g.flush()
    assert rate(g.collect(1.5), "ATTITUDE", 1.5) == 0.0  # off
    g.command(M.MAV_CMD_GET_MESSAGE_INTERVAL, att)
    assert g.wait("MESSAGE_INTERVAL").interval_us == -1
    assert g.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, att, 0).result == ACCEPTED  # default
    g.command(M.MAV_CMD_GET_MESSAGE_INTERVAL, att)
    assert g.wait("MESSAGE_INTERVAL").interval_us == 100_000
    # not a stream of ours, or faster than the compass can go: refused
    hb_rate = M.MAVLINK_MSG_ID_AUTOPILOT_VERSION
    assert g.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, hb_rate, 1_000_000).result == DENIED
    assert g.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, att, 1_000).result == DENIED

    # REQUEST_MESSAGE: ACK, then the message, to the asker
    g.flush()
    assert g.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_SCALED_IMU).result == ACCEPTED
    g.wait("SCALED_IMU")
    assert g.command(M.MAV_CMD_REQUEST_MESSAGE, 9999).result == DENIED
    ack = g.command(M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1)
    assert ack.result == ACCEPTED
    av = g.wait("AUTOPILOT_VERSION")
    assert bytes(av.uid2).rstrip(b"\0") == b"GMR-000417"  # the simulated unit's serial
    assert av.middleware_sw_version >> 8 == (2 << 16 | 1 << 8 | 0)  # its firmware 2.1.0
    assert av.capabilities & M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST


def test_command_addressing(tmp_path: Path, rigs: Callable[..., Rig]) -> None:
    rig = rigs(tmp_path)
    g = rig.gcs("udp")
    # COMMAND_INT works like COMMAND_LONG
    ack = g.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, use_int=True)
    assert ack.result == ACCEPTED
    # anything else: UNSUPPORTED, addressed or broadcast (standalone: we are the system)
    assert g.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == UNSUPPORTED
    assert g.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1, target=(0, 0)).result == UNSUPPORTED
    assert g.command(M.MAV_CMD_PREFLIGHT_CALIBRATION, 1).result == UNSUPPORTED  # gyro: none here
    # for another component or system: not ours to answer
    g.flush()
    g.mav.command_long_send(1, 99, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    g.mav.command_long_send(2, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    g.nothing("COMMAND_ACK", None, 1.0)
    # DO_CANCEL_MAG_CAL when idle: ACCEPTED (QGroundControl probes with it)
    assert g.command(M.MAV_CMD_DO_CANCEL_MAG_CAL, 0).result == ACCEPTED
    # TIMESYNC (PX4 asks a companion): our time in tc1, theirs echoed in ts1
    g.mav.timesync_send(0, 123_456_789)
    ts = g.wait("TIMESYNC")
    assert ts.ts1 == 123_456_789 and ts.tc1 > 0
    # addressed to the asker (MAVLink 2's extension fields, after tc1 and ts1)
    raw = bytes(ts.get_msgbuf())
    assert raw[10 + 16 : 10 + 18] == bytes([GCS_SYSID, GCS_COMPID]), raw.hex()
    # our time is the feed's: the wall clock (Unix epoch), not seconds since start
    assert abs(ts.tc1 / 1e9 - time.time()) < 5.0
    g.mav.timesync_send(ts.tc1, 5)  # an answer (tc1 != 0) is not answered again
    g.nothing("TIMESYNC", lambda m: m.ts1 == 5, 0.5)


# =====================================================================================
# parameters
# =====================================================================================


def test_parameter_protocol(
    tmp_path: Path, rigs: Callable[..., Rig], caplog: pytest.LogCaptureFixture
) -> None:
    # ArduPilot's flavour: every value travels as itself (REAL32), which QGroundControl's
    # generic plugin, MAVProxy and Mission Planner all read alike (docs/mavlink.md)
    rig = rigs(tmp_path, mavlink={"autopilot": "ardupilot"})
    g, other = rig.gcs("udp"), rig.gcs("tcp")
    n = len(rig.daemon.bridge.params)
    g.mav.param_request_list_send(1, 1)
    values: dict[int, Any] = {}
    deadline = time.monotonic() + DEADLINE_S
    while len(values) < n and time.monotonic() < deadline:
        m = g.wait("PARAM_VALUE")
        values[m.param_index] = m
    assert sorted(values) == list(range(n))
    assert {m.param_count for m in values.values()} == {n}
    names = {m.param_id: m for m in values.values()}
    assert len(names) == n
    assert {m.param_type for m in values.values()} == {REAL32}
    assert names["COMPASS_DEV_ID"].param_value == rig.daemon.bridge.params.get("COMPASS_DEV_ID") > 0
    assert names["AHRS_ORIENTATION"].param_value == rig.daemon.bridge.params.get("AHRS_ORIENTATION")
    assert names["BRG_SR_ATT"].param_value == 10.0  # configuration default

    # read by index and by name
    idx = names["COMPASS_SCALE"].param_index
    g.mav.param_request_read_send(1, 1, b"", idx)
    assert g.wait("PARAM_VALUE").param_id == "COMPASS_SCALE"
    assert g.param("BRG_SR_HUD").param_index == names["BRG_SR_HUD"].param_index

    # SET: echoed with the new value, on every link
    other.flush()
    echo = g.set_param("BRG_SR_HUD", 2.0, REAL32)
    assert echo.param_value == 2.0 and echo.param_index == names["BRG_SR_HUD"].param_index
    assert echo.param_count == n
    assert other.wait("PARAM_VALUE", lambda m: m.param_id == "BRG_SR_HUD").param_value == 2.0
    assert g.param("BRG_SR_HUD").param_value == 2.0

    # The type a SET names is not the parameter's: ArduPilot reads the value by the
    # parameter's own type (MAVProxy names REAL32 for everything), so do we.
    assert g.set_param("BRG_SR_HUD", 3.0, INT8).param_value == 3.0
    assert g.set_param("AHRS_ORIENTATION", 0.0, REAL32).param_value == 0.0
    g.set_param("BRG_SR_HUD", 2.0, REAL32)
    # refused SETs: the echo shows the unchanged value, and the journal says why
    caplog.set_level(logging.WARNING, logger="bridge.mavlink.output")
    for value, ptype in ((math.nan, REAL32), (math.inf, REAL32), (999.0, REAL32)):
        assert g.set_param("BRG_SR_HUD", value, ptype).param_value == 2.0
    refusals = [r.getMessage() for r in caplog.records if "BRG_SR_HUD" in r.getMessage()]
    assert len(refusals) == 3 and all("refused" in m and "stays 2" in m for m in refusals)
    assert "not finite" in refusals[0] and "not finite" in refusals[1]
    assert "outside [0, 50]" in refusals[2]
    assert g.set_param("AHRS_ORIENTATION", 2.5, INT8).param_value == 0.0  # not whole
    assert (
        g.set_param("COMPASS_DEV_ID", 1.0, INT32).param_value == names["COMPASS_DEV_ID"].param_value
    )
    assert rig.out.counters.param_sets_refused == 5
    # a SET for another system changes nothing
    g.mav.param_set_send(7, 1, b"BRG_SR_HUD", 1.0, REAL32)
    g.nothing("PARAM_VALUE", lambda m: m.param_id == "BRG_SR_HUD", 0.5)
    assert rig.daemon.bridge.params.get("BRG_SR_HUD") == 2.0
    # the new rate is in force
    g.flush()
    msgs, secs = collect_frames(rig, g, 2.0)
    assert 1.0 <= rate(msgs, "VFR_HUD", secs) <= 3.0


def test_compass_parameters_are_the_calibration_the_engine_applies(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    rig = rigs(tmp_path, ideal=True, motion=Still.from_deg(0.0, 0.0, 40.0))
    g = rig.gcs("udp")
    engine = rig.daemon.bridge.engine
    heading0 = rig.daemon.bridge.engine.calibration
    assert heading0 == Calibration()
    g.set_param("COMPASS_OFS_X", 100.0, REAL32)  # mG, added to the raw field
    assert wait_until(lambda: engine.calibration.mag.offset[0] == pytest.approx(-0.1))
    stored = json.loads((tmp_path / "state" / "calibration.json").read_text())
    assert stored["payload"]["calibration"]["mag"]["offset"][0] == pytest.approx(-0.1)
    # A 100 mG offset on x swings a 0.21 G horizontal field's heading: the ATTITUDE shows it.
    g.flush()
    yaw = math.degrees(g.wait("ATTITUDE").yaw)
    expected = math.degrees(
        math.atan2(-(0.21 * math.sin(math.radians(40))), 0.21 * math.cos(math.radians(40)) + 0.1)
    )
    assert abs(((-yaw) - expected + 180) % 360 - 180) < 5.0 and abs(yaw - 40.0) > 5.0
    g.set_param("COMPASS_OFS_X", 0.0, REAL32)
    assert wait_until(lambda: engine.calibration.mag.offset[0] == 0.0)
    # a singular matrix is refused: the echo keeps the old value, the engine its calibration
    before = engine.calibration
    g.set_param("COMPASS_DIA_X", 0.5, REAL32)
    g.set_param("COMPASS_DIA_Y", 0.5, REAL32)
    assert g.set_param("COMPASS_ODI_X", 0.5, REAL32).param_value == 0.0
    assert engine.calibration.mag.matrix[0][1] == 0.0 and before is not engine.calibration
    # mounting: upside down, the ATTITUDE rolls over
    g.set_param("AHRS_ORIENTATION", float(Rotation.ROTATION_ROLL_180), INT8)
    assert wait_until(lambda: engine.mounting.orientation is Rotation.ROTATION_ROLL_180)
    g.flush()
    assert abs(math.degrees(g.wait("ATTITUDE").roll)) == pytest.approx(180.0, abs=1.0)
    # quality limits and declination
    g.set_param("BRG_FIELD_TOL", 0.3, REAL32)
    assert engine.limits.field_tolerance == 0.3
    g.set_param("COMPASS_AUTODEC", 0.0, INT8)
    g.set_param("COMPASS_DEC", math.radians(10.0), REAL32)
    assert wait_until(
        lambda: (
            engine.reference is not None
            and engine.reference.declination_deg == pytest.approx(10.0, abs=1e-4)
        )
    )
    g.set_param("COMPASS_AUTODEC", 1.0, INT8)
    wmm = earth_field(LAT, LON).declination_deg
    assert wait_until(
        lambda: (
            engine.reference is not None
            and engine.reference.declination_deg == pytest.approx(wmm, abs=0.01)
        )
    )
    assert math.degrees(g.param("COMPASS_DEC").param_value) == pytest.approx(wmm, abs=0.01)


def test_parameters_survive_a_restart(tmp_path: Path) -> None:
    rig = start_rig(tmp_path)
    try:
        g = rig.gcs("udp")
        g.set_param("BRG_SR_HUD", 1.0, REAL32)
        g.set_param("AHRS_ORIENTATION", 2.0, INT8)
        g.set_param("COMPASS_OFS_Y", 55.5, REAL32)
        g.set_param("COMPASS_DIA_Z", 1.1, REAL32)
        g.set_param("BRG_CAL_ONBOARD", 1.0, INT8)
        cal = rig.daemon.bridge.engine.calibration
    finally:
        rig.stop()
    rig2 = start_rig(tmp_path)
    try:
        g = rig2.gcs("tcp")
        assert g.param("BRG_SR_HUD").param_value == 1.0
        assert g.param("AHRS_ORIENTATION").param_value == 2.0
        assert g.param("COMPASS_OFS_Y").param_value == pytest.approx(55.5)
        # the value as set, not a renormalised view of the matrix
        assert g.param("COMPASS_DIA_Z").param_value == pytest.approx(1.1, abs=1e-6)
        assert g.param("BRG_CAL_ONBOARD").param_value == 1.0
        assert rig2.daemon.bridge.engine.calibration == cal
        assert rig2.daemon.bridge.engine.mounting.orientation is Rotation.ROTATION_YAW_90
        assert rig2.daemon.bridge.calibrator.onboard is True
        assert g.param("BRG_SR_ATT").param_value == 10.0  # never set: the configuration's
    finally:
        rig2.stop()
    # a damaged parameter file is reported and ignored, not fatal
    (tmp_path / "state" / "params.json").write_text("{broken")
    (tmp_path / "state" / "params.json.prev").unlink(missing_ok=True)
    rig3 = start_rig(tmp_path)
    try:
        assert rig3.gcs("udp").param("BRG_SR_HUD").param_value == 4.0  # the default again
    finally:
        rig3.stop()


def test_preflight_storage(tmp_path: Path, rigs: Callable[..., Rig]) -> None:
    rig = rigs(tmp_path)
    g = rig.gcs("udp")
    storage = M.MAV_CMD_PREFLIGHT_STORAGE
    g.set_param("BRG_SR_HUD", 1.0, REAL32)
    g.set_param("COMPASS_OFS_X", 80.0, REAL32)
    g.set_param("COMPASS_OFS_Z", -40.0, REAL32)
    # 1 = write: parameters, calibration file and the compass flash (long work: IN_PROGRESS)
    g.mav.command_long_send(1, 1, storage, 0, 1, 0, 0, 0, 0, 0, 0)
    first = g.wait("COMMAND_ACK", lambda m: m.command == storage)
    assert first.result == M.MAV_RESULT_IN_PROGRESS
    final = g.wait("COMMAND_ACK", lambda m: m.command == storage)
    assert final.result == ACCEPTED
    page = rig.fw.flash.page
    assert page.xoff == pytest.approx(2458 - 2560 * 0.080, abs=0.06)
    assert page.zoff == pytest.approx(2458 + 2560 * 0.040, abs=0.06)
    # 2 = reset to defaults: the bridge's parameters, not the calibration (ACCEPTED once
    # params.json holds them: IN_PROGRESS first if the last write was less than a second ago)
    assert g.command(storage, 2, final=True).result == ACCEPTED
    stored = json.loads((tmp_path / "state" / "params.json").read_text())["payload"]["set"]
    assert "BRG_SR_HUD" not in stored
    assert g.param("BRG_SR_HUD").param_value == 4.0
    assert g.param("COMPASS_OFS_X").param_value == pytest.approx(80.0)
    # 3 = reset the calibration
    assert g.command(storage, 3).result == ACCEPTED
    assert wait_until(lambda: rig.daemon.bridge.engine.calibration == Calibration())
    assert wait_until(lambda: rig.daemon.bridge.params.get("COMPASS_OFS_X") == 0.0)
    g.wait("PARAM_VALUE", lambda m: m.param_id == "COMPASS_OFS_X" and m.param_value == 0.0)
    # 0 = read back what is stored
    g.set_param("BRG_SR_SIMU", 5.0, REAL32)
    assert g.command(storage, 0).result == ACCEPTED
    assert g.param("BRG_SR_SIMU").param_value == 5.0
    assert g.command(storage, 7).result == DENIED


# =====================================================================================
# roles, position, heading feed, events
# =====================================================================================


def test_companion_role_takes_the_autopilots_position(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    rig = rigs(tmp_path, mavlink={"role": "companion"})
    g = rig.gcs("udp")
    hb = g.wait("HEARTBEAT", lambda m: m.get_srcSystem() == 1)
    assert hb.get_srcComponent() == M.MAV_COMP_ID_IMU and hb.type == M.MAV_TYPE_IMU
    assert g.command(M.MAV_CMD_GET_MESSAGE_INTERVAL, 30, target=(1, 200)).result == ACCEPTED
    # a broadcast command we do not know is the autopilot's to answer
    g.flush()
    g.mav.command_long_send(1, 0, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    g.nothing("COMMAND_ACK", None, 1.0)
    # the autopilot (system 1, component 1) reports the vehicle in Sydney
    ap = connect_gcs(f"udpout:127.0.0.1:{rig.udp_port}", sysid=1, compid=1)
    rig.gcss.append(ap)
    here = rig.daemon.bridge.engine.reference
    assert here is not None
    sydney = earth_field(-33.86, 151.21, 30.0)
    ap.mav.global_position_int_send(1000, int(-33.86e7), int(151.21e7), 30_000, 5000, 0, 0, 0, 0)
    assert wait_until(
        lambda: (
            rig.daemon.bridge.engine.reference is not None
            and rig.daemon.bridge.engine.reference.declination_deg
            == pytest.approx(sydney.declination_deg, abs=0.05)
        )
    )
    # the calibrator hears of it right after the engine
    assert wait_until(
        lambda: (
            rig.daemon.bridge.calibrator.field is not None
            and rig.daemon.bridge.calibrator.field.total_G
            == pytest.approx(sydney.total_G, rel=1e-3)
        )
    )
    dec = g.param("COMPASS_DEC", target=(1, 200)).param_value
    assert math.degrees(dec) == pytest.approx(sydney.declination_deg, abs=0.05)
    # another system's position is not ours
    other = connect_gcs(f"udpout:127.0.0.1:{rig.udp_port}", sysid=9)
    rig.gcss.append(other)
    other.mav.global_position_int_send(1000, int(40e7), int(-100e7), 0, 0, 0, 0, 0, 0)
    time.sleep(0.5)
    ref = rig.daemon.bridge.engine.reference
    assert ref is not None and ref.declination_deg == pytest.approx(
        sydney.declination_deg, abs=0.05
    )
    # VFR_HUD shows the autopilot's altitude
    g.flush()
    assert g.wait("VFR_HUD").alt == pytest.approx(30.0)
    # GPS_RAW_INT: used with a fix, ignored without one
    reykjavik = earth_field(64.15, -21.94, 20.0)
    ap.mav.gps_raw_int_send(0, 1, int(64.15e7), int(-21.94e7), 20_000, 0, 0, 0, 0, 0)  # no fix
    time.sleep(0.5)
    ref = rig.daemon.bridge.engine.reference
    assert ref is not None and ref.declination_deg == pytest.approx(
        sydney.declination_deg, abs=0.05
    )
    ap.mav.gps_raw_int_send(0, 3, int(64.15e7), int(-21.94e7), 20_000, 0, 0, 0, 0, 9)  # 3D fix
    assert wait_until(
        lambda: (
            rig.daemon.bridge.engine.reference is not None
            and rig.daemon.bridge.engine.reference.declination_deg
            == pytest.approx(reykjavik.declination_deg, abs=0.05)
        )
    )


@pytest.mark.parametrize("feed", ["px4_odometry", "ardupilot_vision"])
def test_heading_feed_for_the_autopilot(
    tmp_path: Path, rigs: Callable[..., Rig], feed: str
) -> None:
    # Beside the autopilot (component 200): from component 1 the autopilot would drop it.
    rig = rigs(tmp_path, ideal=True, mavlink={"heading_feed": feed, "role": "companion"})
    g = rig.gcs("udp")
    mtype = "ODOMETRY" if feed == "px4_odometry" else "VISION_POSITION_ESTIMATE"
    g.flush()
    msgs, secs = collect_frames(rig, g, 2.0)
    assert 7.0 <= rate(msgs, mtype, secs) <= 11.5
    decl = earth_field(LAT, LON).declination_deg
    atts = {m.time_boot_ms: m for m in msgs if m.get_type() == "ATTITUDE"}
    # The feed's time stamps are wall-clock (Unix epoch) microseconds, ATTITUDE's are
    # milliseconds since start: the same sample is (epoch of the start) apart.
    start_ms = rig.out.epoch_us(rig.out.clock() - rig.out.time_boot_ms(rig.out.clock()) / 1000.0)
    pairs = 0
    for m in msgs:
        if m.get_type() != mtype:
            continue
        t_us = m.time_usec if mtype == "ODOMETRY" else m.usec
        assert abs(t_us / 1e6 - time.time()) < 5.0  # the wall clock
        k = round((t_us - start_ms) / 1000)
        a = atts.get(k) or atts.get(k - 1) or atts.get(k + 1)
        if a is None:
            continue  # from a sample ATTITUDE did not go out with
        if mtype == "ODOMETRY":
            w, x, y, z = m.q
            yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
            # BRG_YAW_SIGMA (2 deg) with the heading error of the sample's tilt in quadrature:
            # an ideal unit turning level has its accelerometer's tilt, near-perfect.
            sigma_deg = math.degrees(math.sqrt(m.pose_covariance[20]))
            assert 2.0 - 1e-6 <= sigma_deg <= 2.5
            assert (m.x, m.y, m.z) == (0.0, 0.0, 0.0)
        else:
            yaw = m.yaw
            # ArduPilot's angErr = cbrt(c15^2 + c18^2 + c20^2) is the sigma itself: the
            # same sigma as PX4's, BRG_YAW_SIGMA (2 deg) with the tilt's heading error
            c = m.covariance
            ang_err = (c[15] ** 2 + c[18] ** 2 + c[20] ** 2) ** (1.0 / 3.0)
            assert 2.0 - 1e-4 <= math.degrees(ang_err) <= 2.5
        # ATTITUDE is magnetic (what the daemon publishes); the feed is true: + declination
        diff = (math.degrees(yaw - a.yaw) + 180.0) % 360.0 - 180.0
        assert diff == pytest.approx(decl, abs=0.01)
        pairs += 1
    assert pairs >= 10
    # COMPASS_USE = 0: the autopilot gets nothing from us
    g.set_param("COMPASS_USE", 0.0, INT8, target=(1, 200))
    g.flush()
    assert rate(g.collect(1.5), mtype, 1.5) == 0.0


def test_link_and_disturbance_events_become_statustext(
    tmp_path: Path, rigs: Callable[..., Rig], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(pipeline_module, "DISTURBANCE_EVENT_MIN_S", 0.2)
    rig = rigs(tmp_path, pty=True, device={"stale_after": 1.0})
    g = rig.gcs("udp")
    assert rig.pty is not None
    # The uncalibrated unit reads a field 10-20 % off the WMM's: loosen, then tighten the limit.
    g.set_param("BRG_FIELD_TOL", 1.0, REAL32)
    g.set_param("BRG_DIP_TOL", 45.0, REAL32)
    assert wait_until(lambda: not rig.daemon.bridge.pipeline._disturbed)
    g.flush()
    g.set_param("BRG_FIELD_TOL", 0.01, REAL32)
    st = g.wait("STATUSTEXT", lambda m: "disturbance" in m.text)
    assert (
        st.text == "Magnetic disturbance: heading unreliable"
        and st.severity == M.MAV_SEVERITY_WARNING
    )
    ss = g.wait("SYS_STATUS")
    assert not ss.onboard_control_sensors_health & M.MAV_SYS_STATUS_SENSOR_3D_MAG
    assert ss.onboard_control_sensors_health & M.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    # pull the cable: link lost, nothing healthy, HEARTBEAT critical; plug back: restored
    rig.pty.unplug(2.5)
    lost = g.wait("STATUSTEXT", lambda m: m.text.startswith("Compass link lost"))
    assert lost.severity == M.MAV_SEVERITY_ERROR
    mag_acc = M.MAV_SYS_STATUS_SENSOR_3D_MAG | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    assert g.wait("SYS_STATUS", lambda m: m.onboard_control_sensors_health & mag_acc == 0)
    assert g.wait("HEARTBEAT", lambda m: m.system_status == M.MAV_STATE_CRITICAL)
    g.wait("STATUSTEXT", lambda m: m.text == "Compass link restored")
    assert g.wait("HEARTBEAT", lambda m: m.system_status == M.MAV_STATE_ACTIVE)


def test_the_ground_station_ids_come_back_in_every_answer(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    rig = rigs(tmp_path, mavlink={"system_id": 42})
    g = rig.gcs("tcp")
    ack = g.command(M.MAV_CMD_GET_MESSAGE_INTERVAL, 0, target=(42, 1))
    assert ack.result == ACCEPTED and (ack.target_system, ack.target_component) == (
        GCS_SYSID,
        GCS_COMPID,
    )
    assert g.wait("ATTITUDE").get_srcSystem() == 42
    g.flush()
    g.mav.command_long_send(1, 1, M.MAV_CMD_GET_MESSAGE_INTERVAL, 0, 0, 0, 0, 0, 0, 0, 0)
    g.nothing("COMMAND_ACK", None, 0.7)  # system 1 is not us any more


def test_a_dead_and_a_stuck_endpoint_do_not_slow_the_others(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    import socket

    dead = f"tcp:127.0.0.1:{free_port(socket.SOCK_STREAM)}"  # nobody will ever listen there
    rig = rigs(tmp_path, extra_endpoints=(dead, "udpout:192.0.2.1:14550"))  # TEST-NET: a black hole
    stuck = socket.create_connection(("127.0.0.1", rig.tcp_port), timeout=DEADLINE_S)
    stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # connected, never reads
    try:
        g = rig.gcs("udp")
        samples0 = rig.daemon.bridge.pipeline.samples
        g.flush()
        msgs, secs = collect_frames(rig, g, 3.0)
        assert 7.0 <= rate(msgs, "ATTITUDE", secs) <= 11.0  # the compass's 10 Hz, all of it
        assert rig.daemon.bridge.pipeline.samples - samples0 >= 25  # the pipeline never waited
        counters = rig.out.endpoint_counters()
        assert counters[dead].errors >= 1 and counters[dead].packets_unsent > 0
        assert counters["udpout:192.0.2.1:14550"].packets_sent > 0  # into the void, unblocked
        # (the stuck client's queue overflow itself: test_mavlink_endpoints)
    finally:
        stuck.close()
