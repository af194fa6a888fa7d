"""Heading under acceleration, live: a real daemon on a simulated compass that stands 8 s, then
drives a turn at 0.29 g and a stop at 0.18 g, its MAVLink heard by a ground station over UDP.

* **companion**: a stand-in autopilot (system 1, component 1, its own UDP peer) streams its
  ATTITUDE unasked -- the vehicle's true roll and pitch with an EKF's noise (0.1 deg white,
  0.2 deg wandering), its gyro rates, stamped on its boot clock 40 ms before they are sent
  -- and answers the bridge's TIMESYNC requests. The bridge's ATTITUDE (component 200)
  must stay within 1 deg RMS of the truth while the vehicle accelerates, each with a
  TILT_SRC of 1 (autopilot);
* **standalone**: no autopilot; within 5 deg RMS, TILT_SRC 2 (magnetometer) while it
  brakes and turns.

Beside each, what the accelerometer's own tilt gives on the same attitudes (computed from
the simulator's truth): far worse, so the test could fail.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_mavlink_rig import M, Rig, connect_gcs, mavutil

from bridge.core.attitude import AttitudeEngine
from bridge.core.calibration import Calibration
from bridge.core.wmm import earth_field
from bridge.sim.autopilot import AutopilotAttitude
from bridge.sim.drive import ManoeuvreDrive
from bridge.sim.motion import MotionBase
from bridge.sim.physics import DEFAULT_LOCATION, SensorModel, UnitErrors

SEED = 13  #: its drive: a 0.29 g turn from 4 to 15 s, a 0.18 g stop from 22 to 32 s
LEAD_S = 8.0  #: standing first: the bridge learns how the boards sit and the local dip
END_S = LEAD_S + 32.0  #: collect until the motion's clock reads this
LATENCY_S = 0.04
DECLINATION = earth_field(*DEFAULT_LOCATION).declination_deg


class StandingFirst(MotionBase):
    """The drive after ``LEAD_S`` s standing at its first attitude (as a bridge in service
    has seen its vehicle quiet before; the benchmark scores after 60 s)."""

    def __init__(self, drive: ManoeuvreDrive) -> None:
        self.drive = drive
        self.duration = drive.duration + LEAD_S

    def attitude(self, t: float) -> np.ndarray:
        return self.drive.attitude(max(0.0, t - LEAD_S))

    def linear_acc_ned_g(self, t: float) -> np.ndarray:
        return self.drive.linear_acc_ned_g(t - LEAD_S) if t >= LEAD_S else np.zeros(3)

    def manoeuvre_acc_ned_g(self, t: float) -> np.ndarray:
        return self.drive.manoeuvre_acc_ned_g(t - LEAD_S) if t >= LEAD_S else np.zeros(3)


def drive_of(seed: int) -> StandingFirst:
    return StandingFirst(ManoeuvreDrive(seed, END_S + 30.0))


class StandInAutopilot(threading.Thread):
    """An autopilot on the link: ATTITUDE at 20 Hz of the vehicle the compass rides in, late
    by ``LATENCY_S`` (stamped on its boot clock), HEARTBEAT at 1 Hz, TIMESYNC answered."""

    BOOT_S = 321.0

    def __init__(self, rig: Rig, drive: StandingFirst) -> None:
        super().__init__(daemon=True)
        self.rig = rig
        self.model = AutopilotAttitude(drive, seed=SEED, latency_s=0.0, jitter_s=0.0)
        self.conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{rig.udp_port}", source_system=1, source_component=1
        )
        self.stop = threading.Event()
        self.timesyncs = 0
        self.sent = 0

    def run(self) -> None:
        mav = self.conn.mav
        next_att = next_hb = time.monotonic()
        last_tm = -1.0
        while not self.stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                next_hb = now + 1.0
                mav.heartbeat_send(
                    M.MAV_TYPE_GROUND_ROVER, M.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, M.MAV_STATE_ACTIVE
                )
            if now >= next_att:
                next_att += 0.05
                tm = self.rig.motion_time() - LATENCY_S  # what it estimated 40 ms ago
                if tm > last_tm and tm >= 0.0:
                    last_tm = tm
                    m = self.model.message(tm)
                    mav.attitude_send(
                        int((tm + self.BOOT_S) * 1000), m.roll, m.pitch, m.yaw, *m.rates
                    )
                    self.sent += 1
            msg = self.conn.recv_match(blocking=True, timeout=0.01)
            while msg is not None:
                if msg.get_type() == "TIMESYNC" and msg.tc1 == 0:
                    tc1 = int((self.rig.motion_time() + self.BOOT_S) * 1e9)
                    mav.timesync_send(tc1, msg.ts1)
                    self.timesyncs += 1
                msg = self.conn.recv_match(blocking=False)

    def close(self) -> None:
        self.stop.set()
        self.join(5.0)
        self.conn.close()


def fly(rig: Rig, drive: StandingFirst) -> list[tuple[float, float, int | None]]:
    """Collect the bridge's ATTITUDE (and its TILT_SRC) until the drive reaches END_S:
    (drive time, heading error deg, tilt source)."""
    g = connect_gcs(f"udpout:127.0.0.1:{rig.udp_port}")
    rig.gcss.append(g)
    ours = (rig.out.identity.system_id, rig.out.identity.component_id)
    atts: dict[int, Any] = {}
    srcs: dict[int, int] = {}
    deadline = time.monotonic() + END_S + 30.0
    while rig.motion_time() < END_S:
        assert time.monotonic() < deadline, "the drive's clock is stuck"
        for m in g.collect(0.5):
            if (m.get_srcSystem(), m.get_srcComponent()) != ours:
                continue
            if m.get_type() == "ATTITUDE":
                atts[m.time_boot_ms] = m
            elif m.get_type() == "NAMED_VALUE_INT" and m.name == "TILT_SRC":
                srcs[m.time_boot_ms] = m.value
    epoch = rig.fw.motion_epoch
    assert epoch is not None
    out = []
    src: int | None = None  # TILT_SRC comes on a change (and once a second): the last one holds
    for ms, a in sorted(atts.items()):
        src = srcs.get(ms, src)
        tm = rig.out._t0 + ms / 1000.0 - epoch  # the frame's instant on the drive's clock
        yaw = math.degrees(dcm_yaw(drive.attitude(tm))) - DECLINATION
        err = (math.degrees(a.yaw) - yaw + 180.0) % 360.0 - 180.0
        out.append((tm, err, src))
    return out


def dcm_yaw(R: np.ndarray) -> float:
    return math.atan2(R[1, 0], R[0, 0])


def accelerating(drive: StandingFirst, rows: list[tuple[float, float, int | None]]) -> list:
    return [r for r in rows if np.linalg.norm(drive.manoeuvre_acc_ned_g(r[0])) >= 0.05]


def accelerometer_tilt_rms(drive: StandingFirst, times: list[float]) -> float:
    """What the accelerometer's own tilt gives on those attitudes (ideal unit, same engine)."""
    model = SensorModel.at_location(UnitErrors.ideal())
    engine = AttitudeEngine(Calibration())
    errs = []
    for tm in times:
        R = drive.attitude(tm)
        s = model.sample(R, np.random.default_rng(0), drive.linear_acc_ned_g(tm))
        a = engine.solve_counts(*s.mag_counts[0], *s.acc_counts[0])
        yaw = math.degrees(dcm_yaw(R)) - DECLINATION
        errs.append((a.heading_magnetic_deg - yaw + 180.0) % 360.0 - 180.0)
    return float(np.sqrt(np.mean(np.square(errs))))


def rms(rows: list) -> float:
    return float(np.sqrt(np.mean([r[1] ** 2 for r in rows])))


@pytest.mark.integration
@pytest.mark.slow
def test_companion_takes_the_autopilots_attitude_while_it_accelerates(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    drive = drive_of(SEED)
    rig = rigs(tmp_path, motion=drive, ideal=True, mavlink={"role": "companion"})
    ap = StandInAutopilot(rig, drive)
    ap.start()
    try:
        rows = fly(rig, drive)
    finally:
        ap.close()
    acc = accelerating(drive, rows)
    raw = accelerometer_tilt_rms(drive, [r[0] for r in acc])
    print(f"companion: {rms(acc):.2f} deg RMS over {len(acc)} frames (accelerometer {raw:.2f})")
    assert len(acc) >= 100  # the turn and the stop, at 10 Hz
    assert rms(acc) <= 1.0, f"companion heading error {rms(acc):.2f} deg RMS"
    sources = [r[2] for r in acc]
    assert sources.count(1) >= 0.9 * len(sources)  # TILT_SRC: autopilot
    assert raw > 5.0
    # it asked the autopilot's clock, and lined its stamps up with it
    tilt = rig.daemon.bridge.services.tilt
    assert tilt is not None
    st = tilt.status()["autopilot"]
    assert ap.timesyncs >= 10 and st["clock"] == "timesync" and st["heard"]
    # (the rate it reports is a mean of arrival gaps, so the wall clock's jitter under load
    # is in it: tests/test_tilt.py checks it on set arrivals)
    assert st["messages"] >= 0.8 * ap.sent and st["rate_hz"] > 0.0


@pytest.mark.integration
@pytest.mark.slow
def test_standalone_holds_the_tilt_and_matches_the_field(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    drive = drive_of(SEED)
    rig = rigs(tmp_path, motion=drive, ideal=True)
    rows = fly(rig, drive)
    acc = accelerating(drive, rows)
    raw = accelerometer_tilt_rms(drive, [r[0] for r in acc])
    print(f"standalone: {rms(acc):.2f} deg RMS over {len(acc)} frames (accelerometer {raw:.2f})")
    assert len(acc) >= 100
    assert rms(acc) <= 5.0, f"standalone heading error {rms(acc):.2f} deg RMS"
    sources = [r[2] for r in acc]
    assert sources.count(2) >= 0.6 * len(sources)  # TILT_SRC: magnetometer
    assert raw > 2.0 * rms(acc)
