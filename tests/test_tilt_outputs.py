"""Every output says which tilt source a sample used: the console line, Zenoh's heading and
status documents, MAVLink (TILT_SRC beside ATTITUDE, the feed's yaw sigma) and ``status``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from zenoh_rig import status_of_a_streaming_bridge

from bridge.app.sample import CompassSample, DaemonStatus
from bridge.console import format_line
from bridge.core.attitude import AttitudeEngine, FieldReference
from bridge.core.calibration import Calibration
from bridge.core.geometry import euler_to_dcm
from bridge.core.tilt import TiltEstimate, TiltSource
from bridge.core.vectors import Vec3
from bridge.link.serial_link import LinkCounters, LinkState
from bridge.mavlink import telemetry as T  # noqa: N812 - short
from bridge.sim.physics import SensorModel, UnitErrors
from bridge.tools.status import BridgeAnswers, format_human, summarise
from bridge.zenoh import schema

FIELD_NED_G = (0.21, 0.02, 0.43)
TIMES = schema.SampleTimes(t_monotonic=12.5, t_unix=1_700_000_000.25)


class FixedTilt:
    """A tilt policy that always answers the same estimate (its down: level)."""

    def __init__(self, source: TiltSource, heading_sigma_deg: float, manoeuvre: bool) -> None:
        accel = (0.0, math.sin(math.radians(8.0)), math.cos(math.radians(8.0)))
        self.est = TiltEstimate((0.0, 0.0, 1.0), source, 1.0, heading_sigma_deg, accel, manoeuvre)

    def tilt(self, mag: Vec3, accel: Vec3, t: float, *, field_ok: bool) -> TiltEstimate:
        return self.est


def sample(policy: FixedTilt | None, lateral_g: float = 0.0) -> CompassSample:
    """A level ideal unit heading 100 deg, accelerating sideways by ``lateral_g``."""
    model = SensorModel(UnitErrors.ideal(), FIELD_NED_G)
    R = euler_to_dcm(0.0, 0.0, math.radians(100.0))
    lin = R @ np.array([0.0, lateral_g, 0.0])
    s = model.sample(R, np.random.default_rng(0), lin)
    engine = AttitudeEngine(Calibration(), reference=FieldReference(declination_deg=5.0))
    engine.set_tilt_policy(policy)
    (mx, my, mz), (ax, ay, az) = s.mag_counts[0], s.acc_counts[0]
    a = engine.solve_counts(mx, my, mz, ax, ay, az, 1.0)
    return CompassSample.from_solution(a, 12.5, seq=3)


def status() -> DaemonStatus:
    return DaemonStatus("sim", LinkState.STREAMING, LinkCounters(attitude_frames=9), 9, 0, "x")


def test_the_solution_uses_the_policys_down_and_says_so() -> None:
    raw = sample(None, 0.25)
    held = sample(FixedTilt("magnetometer", 3.2, True), 0.25)
    assert raw.tilt_source == "accelerometer" and raw.heading_sigma_deg is None
    assert raw.roll_deg is not None and abs(raw.roll_deg) > 10.0  # the accelerometer's, 0.25 g
    assert held.tilt_source == "magnetometer" and held.heading_sigma_deg == 3.2
    assert held.roll_deg == pytest.approx(0.0, abs=1e-9)
    # the heading with the right (level) tilt: the field's own bearing
    want = (100.0 - math.degrees(math.atan2(0.02, 0.21))) % 360.0
    assert held.heading_magnetic_deg == pytest.approx(want, abs=0.2)
    assert raw.heading_magnetic_deg is not None and abs(raw.heading_magnetic_deg - want) > 3.0


def test_console_line_names_the_tilt_source() -> None:
    assert "tilt accelerometer" in format_line(sample(None), status())
    line = format_line(sample(FixedTilt("autopilot", 0.43, False)), status())
    assert "tilt autopilot +-0.4" in line
    assert "tilt magnetometer +-3.2" in format_line(
        sample(FixedTilt("magnetometer", 3.2, True), 0.25), status()
    )


def test_heading_document_carries_the_tilt_source() -> None:
    s = sample(FixedTilt("magnetometer", 3.2, True), 0.25)
    doc = schema.parse(schema.dumps(schema.heading_doc(s, TIMES)), schema.HEADING)
    assert doc["tilt"] == {"source": "magnetometer", "heading_error_deg": 3.2}
    doc = schema.heading_doc(sample(None), TIMES)
    assert doc["tilt"] == {"source": "accelerometer", "heading_error_deg": None}


def test_mavlink_says_the_tilt_source_beside_attitude_and_in_the_feed_sigma() -> None:
    wire: tuple[tuple[TiltSource, int], ...] = (
        ("accelerometer", 0),
        ("autopilot", 1),
        ("magnetometer", 2),
    )
    for source, value in wire:
        m = T.tilt_source(sample(FixedTilt(source, 1.0, False)), 1234)
        assert (m.get_type(), m.name, m.value, m.time_boot_ms) == (
            "NAMED_VALUE_INT",
            "TILT_SRC",
            value,
            1234,
        )
    # sent beside an ATTITUDE when the source changes, else once a second
    note = T.TiltSourceNote()
    acc, mag = (
        sample(FixedTilt("accelerometer", 1.0, False)),
        sample(FixedTilt("magnetometer", 2.0, True)),
    )
    sent = [
        [m.value for m in note.due(s, t, int(t * 1000))]
        for t, s in ((0.0, acc), (0.02, acc), (0.5, acc), (0.52, mag), (0.54, mag), (1.6, mag))
    ]
    assert sent == [[0], [], [], [2], [], [2]]
    # the feed's yaw sigma: BRG_YAW_SIGMA with the tilt's heading error in quadrature ...
    held = sample(FixedTilt("magnetometer", 4.0, True), 0.25)
    assert math.degrees(T.feed_yaw_sigma_rad(held, 3.0)) == pytest.approx(5.0)
    # ... five times it only while accelerating with the accelerometer's own tilt
    raw = sample(None, 0.0)
    assert math.degrees(T.feed_yaw_sigma_rad(raw, 3.0)) == pytest.approx(3.0)


def test_status_summary_and_its_tilt_line() -> None:
    a = BridgeAnswers(
        "fleet/boat/compass",
        status={
            "link": {"state": "streaming", "frame_rate_hz": 10.0},
            "tilt": {
                "source": "autopilot",
                "autopilot": {
                    "heard": True,
                    "rate_hz": 19.8,
                    "clock": "timesync",
                    "residual_deg": 1.2,
                },
            },
        },
        heading={
            "flags": {"disturbed": False, "saturated": False},
            "tilt": {"source": "autopilot", "heading_error_deg": 0.4},
        },
    )
    rec = summarise(a)
    assert rec["tilt"]["source"] == "autopilot" and rec["tilt"]["heading_error_deg"] == 0.4
    text = format_human([rec])
    assert (
        "tilt         autopilot, heading error 0.4 deg; autopilot attitude heard at 20 Hz, "
        "clock by timesync, boards 1.2 deg apart" in text
    )
    bare = summarise(BridgeAnswers("fleet/x", status={"link": {"state": "streaming"}}))
    assert bare["tilt"] is None and "tilt " not in format_human([bare])


@pytest.mark.integration
def test_status_of_a_running_bridge_shows_its_tilt_source(tmp_path: Path) -> None:
    _, _, _, doc, human = status_of_a_streaming_bridge(tmp_path, "boat9")
    (rec,) = doc["bridges"]
    # a unit turning on the spot, standalone: the accelerometer's tilt, no autopilot
    assert rec["tilt"]["source"] == "accelerometer"
    assert rec["tilt"]["autopilot_heard"] is False
    assert rec["tilt"]["frames"]["accelerometer"] > 0
    assert "tilt         accelerometer" in human


def test_a_host_sample_carries_its_solution_field_by_field() -> None:
    """``from_solution`` fills the sample's fields by position: each lands where it belongs."""
    a = sample(None, 0.25).attitude  # rolled by the lateral pull: roll and pitch differ
    assert a is not None
    raw = (1, 2, 3, 4, 5, 6)
    s = CompassSample.from_solution(
        a, 42.0, seq=9, device_heading_deg=77.5, saturated=True, raw_counts=raw
    )
    assert (s.t, s.source, s.seq, s.device_heading_deg, s.saturated) == (
        42.0, "host", 9, 77.5, True,
    )  # fmt: skip
    assert s.raw_counts == raw and s.attitude is a
    assert s.heading_deg == a.heading_deg and s.heading_reference == a.heading_reference
    assert s.heading_magnetic_deg == a.heading_magnetic_deg
    assert s.heading_true_deg == a.heading_true_deg is not None
    assert s.declination_deg == a.declination_deg == 5.0
    assert s.pitch_deg == math.degrees(a.pitch) and s.roll_deg == math.degrees(a.roll)
    assert s.pitch_deg != s.roll_deg  # (so a swap of the two would show)
