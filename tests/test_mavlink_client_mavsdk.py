"""MAVSDK (PyPI ``mavsdk`` 4.x: the C++ library in process, through ctypes) against the bridge.

MAVSDK's Calibration plugin works only with a system whose HEARTBEAT says
``MAV_AUTOPILOT_PX4`` (``CalibrationImpl``: anything else is UNSUPPORTED at
once), sends PREFLIGHT_CALIBRATION to component 1 with the parameters it does
not set as NaN (``MavlinkCommandSender::maybe_reserved``), and follows PX4's
``[cal]`` STATUSTEXT lines. So the bridge runs with ``[mavlink] autopilot =
"px4"``; MAVSDK decodes that flavour's parameters bytewise (INT32 / REAL32),
which its ``get_param_int`` / ``get_param_float`` need.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mavsdk
import pytest
from mavlink_clients import new_value, writable
from mavsdk import Autopilot, ComponentType, Configuration, Mavsdk
from mavsdk.plugins.calibration.calibration import Calibration as CalibrationPlugin
from mavsdk.plugins.calibration.calibration import CalibrationResult
from mavsdk.plugins.param.param import Param
from mavsdk.plugins.telemetry.telemetry import Telemetry
from test_mavlink_calibration import (
    FIELD,
    LEAD_S,
    assert_heading_within_targets,
    lead_in,
)
from test_mavlink_rig import DEADLINE_S, Rig, wait_until

from bridge.app.paramspec import REAL32
from bridge.core.calibration import Calibration
from bridge.mavlink import telemetry as T  # noqa: N812 - short
from bridge.sim.motion import SixFaces, Still, Tumble

pytestmark = pytest.mark.integration  # real sockets, processes or threads

CAL_DEADLINE_S = 60.0
PX4 = {"autopilot": "px4"}


@dataclass
class Run:
    """One calibration's callbacks: progress, instructions, and the final result."""

    progress: list[float] = field(default_factory=list)
    texts: list[str] = field(default_factory=list)
    result: CalibrationResult | None = None
    done: threading.Event = field(default_factory=threading.Event)

    def __call__(self, result: CalibrationResult, data: Any, _user: Any) -> None:
        if result is CalibrationResult.NEXT:
            if data.has_progress:
                self.progress.append(float(data.progress))
            if data.has_status_text:
                self.texts.append(data.status_text)
            return
        self.result = result
        self.done.set()

    def wait(self) -> CalibrationResult:
        assert self.done.wait(CAL_DEADLINE_S), f"no result; progress {self.progress[-3:]}"
        assert self.result is not None
        return self.result


@pytest.fixture
def connect(rigs: Callable[..., Rig]) -> Iterator[Callable[[Rig], Any]]:
    """MAVSDK as a ground station on a rig's udpin port -> the discovered autopilot system.
    Every instance is destroyed before the rigs stop; MAVSDK's log is kept for failures."""
    made: list[Mavsdk] = []
    log: list[str] = []

    def on_log(level: Any, message: str, _file: Any, _line: int) -> bool:
        log.append(f"{level.name}: {message}")
        return True

    mavsdk.log_subscribe(on_log)

    def start(rig: Rig) -> Any:
        m = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        made.append(m)
        m.add_any_connection(f"udpout://127.0.0.1:{rig.udp_port}")
        system = m.first_autopilot(DEADLINE_S)
        assert system is not None, "\n".join(log)
        return system

    yield start
    for m in made:
        m.destroy()
    mavsdk.log_unsubscribe()


def test_mavsdk_discovery_telemetry_parameters_and_level(
    tmp_path: Path, rigs: Callable[..., Rig], connect: Callable[[Rig], Any]
) -> None:
    roll, pitch, yaw = 4.0, -7.0, 40.0
    rig = rigs(tmp_path, ideal=True, motion=Still.from_deg(roll, pitch, yaw), mavlink=PX4)
    system = connect(rig)
    assert system.autopilot_type() == Autopilot.PX4
    assert system.component_ids() == [1]

    # Telemetry: the attitude we publish (ATTITUDE_QUATERNION / ATTITUDE)
    telemetry = Telemetry(system)
    assert wait_until(lambda: telemetry.attitude_euler().timestamp_us > 0)
    seen = telemetry.attitude_euler()
    sample = rig.out.latest
    assert sample is not None
    ours = [math.degrees(a) for a in T.euler_of(sample)]
    assert seen.roll_deg == pytest.approx(ours[0], abs=0.3) == pytest.approx(roll, abs=0.5)
    assert seen.pitch_deg == pytest.approx(ours[1], abs=0.3) == pytest.approx(pitch, abs=0.5)
    assert (seen.yaw_deg - ours[2] + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=0.3)

    # Param: an integer and a float parameter, get and set
    param = Param(system)
    store = rig.daemon.bridge.params
    assert param.get_param_int("AHRS_ORIENTATION") == store.get("AHRS_ORIENTATION") == 0
    assert param.get_param_float("BRG_SR_HUD") == store.get("BRG_SR_HUD") == 4.0
    param.set_param_int("BRG_CAL_ONBOARD", 1)
    param.set_param_float("BRG_SR_HUD", 2.5)
    assert store.get("BRG_CAL_ONBOARD") == 1.0 and store.get("BRG_SR_HUD") == 2.5
    assert param.get_param_int("BRG_CAL_ONBOARD") == 1
    assert param.get_param_float("BRG_SR_HUD") == 2.5
    param.set_param_int("BRG_CAL_ONBOARD", 0)  # the host's level calibration below

    # Calibration: level, with progress, then the attitude reads level
    run = Run()
    calibration = CalibrationPlugin(system)  # kept: a plugin that is collected stops reporting
    calibration.calibrate_level_horizon_async(run)
    assert run.wait() is CalibrationResult.SUCCESS, run.texts
    assert run.progress and run.progress == sorted(run.progress) and run.progress[-1] <= 1.0
    assert wait_until(
        lambda: (
            abs(telemetry.attitude_euler().roll_deg) < 0.3
            and abs(telemetry.attitude_euler().pitch_deg) < 0.3
        )
    )

    # every parameter, set to a new value and read back (integers as INT32)
    for spec in writable():
        value = new_value(spec, store.get(spec.name))
        if spec.ptype == REAL32:
            param.set_param_float(spec.name, value)
            assert param.get_param_float(spec.name) == value == store.get(spec.name)
        else:
            param.set_param_int(spec.name, int(value))
            assert param.get_param_int(spec.name) == value == store.get(spec.name)


def test_mavsdk_calibrates_the_magnetometer_while_it_tumbles(
    tmp_path: Path, rigs: Callable[..., Rig], connect: Callable[[Rig], Any]
) -> None:
    rig = rigs(
        tmp_path,
        fast=True,
        motion=lead_in(Tumble(5, rate_dps=90.0, reference_ned=FIELD.ned_G)),
        mavlink=PX4,
    )
    system = connect(rig)
    before = rig.daemon.bridge.engine.calibration
    run = Run()
    calibration = CalibrationPlugin(system)
    calibration.calibrate_magnetometer_async(run)
    assert run.wait() is CalibrationResult.SUCCESS, run.texts
    assert len(run.progress) >= 5 and run.progress == sorted(run.progress)
    assert 0.0 <= run.progress[0] < 0.5 < run.progress[-1] <= 1.0
    # PX4 has no accept step: the result is in use, and good
    assert wait_until(lambda: rig.daemon.bridge.engine.calibration != before)
    assert_heading_within_targets(rig.fw, rig.daemon.bridge.engine.calibration)


def test_mavsdk_calibrates_the_accelerometer_on_six_faces(
    tmp_path: Path, rigs: Callable[..., Rig], connect: Callable[[Rig], Any]
) -> None:
    rig = rigs(
        tmp_path,
        fast=True,
        seed=8,
        motion=lead_in(SixFaces(dwell_s=6.0, transition_s=3.0)),
        mavlink=PX4,
    )
    system = connect(rig)
    rig.wait_motion_time(LEAD_S - 3.0)
    run = Run()
    calibration = CalibrationPlugin(system)
    calibration.calibrate_accelerometer_async(run)
    assert run.wait() is CalibrationResult.SUCCESS, run.texts
    assert run.progress and run.progress[-1] > 0.5
    assert wait_until(lambda: rig.daemon.bridge.engine.calibration.accel != Calibration().accel)
