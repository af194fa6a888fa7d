"""A ground station reaches the companion bridge through the real ArduPilot's MAVLink router.

ArduPilot Rover SITL from ``../shared/autopilots/ardupilot`` with its own (simulated)
compass; the bridge as component 200 on its SERIAL1, a pymavlink ground station on
SERIAL0 and MAVProxy on SERIAL2. ArduPilot's routing table learns the bridge from
its HEARTBEATs and forwards what is addressed to it (``MAVLink_routing.cpp``). One
ArduPilot run serves the module:

* PARAM_REQUEST_LIST to component 0 brings the bridge's whole list beside
  ArduPilot's, in the first round, in under 2 s; PARAM_REQUEST_READ to component 0
  too; a storm of MESSAGE_INTERVAL requests and a long STATUSTEXT arrive whole;
* MAVProxy aimed at component 200 (``--target-component=200``): ``param fetch``
  gets every parameter, ``param set`` sets one, ``long DO_START_MAG_CAL`` /
  ``long DO_CANCEL_MAG_CAL`` start and cancel the bridge's calibration (MAVProxy's
  ``magcal`` command is a broadcast, which stays ArduPilot's);
* while ArduPilot calibrates its own compass, a calibration asked of the bridge is
  answered TEMPORARILY_REJECTED.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import companion_bridge as companion
import pytest
from autopilots import ARDUPILOT_HOME, M, check_all, start_ardupilot
from companion_bridge import Bridge, start_bridge
from mavlink_clients import MavProxy

pytestmark = [pytest.mark.integration, pytest.mark.slow]

HOME = ARDUPILOT_HOME[:3]
#: ArduPilot with its own compass (for its own calibration), MAVLink 2 on SERIAL1.
PARAMS = {"SERIAL1_PROTOCOL": 2, "ARMING_CHECK": 0}


@dataclass
class Seen:
    """What the ground stations saw."""

    bridge_params: int = 0
    list_first_round: set[int] = field(default_factory=set)
    list_count: int = 0
    list_seconds: float = 0.0
    ardupilot_params: int = 0
    read_answers: list[int] = field(default_factory=list)
    storm_acks: int = 0
    storm_intervals: int = 0
    text_chunks: list[Any] = field(default_factory=list)
    mavproxy_received: str = ""
    mavproxy_set: float = 0.0
    magcal_started: bool = False
    magcal_cancelled: bool = False
    busy: Any = None
    busy_started: bool = True


@pytest.fixture(scope="module")
def seen(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Seen]:
    work = tmp_path_factory.mktemp("ardupilot-companion")
    ap = start_ardupilot(work / "ap", PARAMS, gcs2=True)
    s = Seen()
    bridge: Bridge | None = None
    mp: MavProxy | None = None
    try:
        bridge = start_bridge(
            work / "bridge",
            f"udpin:127.0.0.1:{ap.companion_port}",
            feed="off",
            location=HOME,
            compass_at=HOME,
            yaw_deg=30.0,
        )
        s.bridge_params = len(bridge.out.params.params)
        obs = ap.observer

        obs.wait("HEARTBEAT", companion.from_bridge)  # routed by ArduPilot
        t0 = time.monotonic()
        s.list_seconds, s.list_first_round, s.list_count = companion.load_parameters(obs, 1, t0)
        time.sleep(2.0)
        s.ardupilot_params = companion.autopilot_parameters(obs, since=t0)
        t1 = time.monotonic()
        obs.mav.param_request_read_send(1, 0, b"BRG_YAW_SIGMA", -1)
        obs.wait("PARAM_VALUE", lambda m: m.param_id == "BRG_YAW_SIGMA", since=t1)
        time.sleep(0.5)
        s.read_answers = [
            m.get_srcComponent()
            for _, m in obs.history(
                "PARAM_VALUE", lambda m: m.param_id == "BRG_YAW_SIGMA", since=t1
            )
        ]
        s.storm_acks, s.storm_intervals = companion.message_interval_storm(obs, 1)
        s.text_chunks = companion.send_long_status_text(bridge, obs)
        # MAVProxy on SERIAL2, aimed at the bridge's component
        mp = MavProxy(
            f"udpin:127.0.0.1:{ap.gcs2_port}",
            work,
            "--target-system=1",
            "--target-component=200",
        )
        mp.expect(r"Detected vehicle|online system", 30.0)
        mp.send("param fetch")
        _, s.mavproxy_received = mp.expect(r"Received \d+ parameters", 30.0)
        mp.send("param set BRG_SR_HUD 2")
        deadline = time.monotonic() + 10.0
        while bridge.daemon.bridge.params.get("BRG_SR_HUD") != 2.0 and time.monotonic() < deadline:
            time.sleep(0.05)
        s.mavproxy_set = bridge.daemon.bridge.params.get("BRG_SR_HUD")
        mp.send("long DO_START_MAG_CAL 0 0 1 0")
        deadline = time.monotonic() + 10.0
        while (
            not bridge.daemon.bridge.calibrator.snapshot().running and time.monotonic() < deadline
        ):
            time.sleep(0.05)
        s.magcal_started = bridge.daemon.bridge.calibrator.snapshot().running
        mp.send("long DO_CANCEL_MAG_CAL 0")
        deadline = time.monotonic() + 10.0
        while bridge.daemon.bridge.calibrator.snapshot().running and time.monotonic() < deadline:
            time.sleep(0.05)
        s.magcal_cancelled = not bridge.daemon.bridge.calibrator.snapshot().running
        # ArduPilot's own compass calibration, and one asked of the bridge meanwhile
        ack = obs.command(ap.target, M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 0, 0)
        assert ack.result == M.MAV_RESULT_ACCEPTED, ack
        deadline = time.monotonic() + 10.0
        while not bridge.out.autopilot.calibrating and time.monotonic() < deadline:
            time.sleep(0.05)
        s.busy = obs.command((1, 200), M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 0, 0)
        s.busy_started = bridge.daemon.bridge.calibrator.snapshot().running
        obs.command(ap.target, M.MAV_CMD_DO_CANCEL_MAG_CAL, 0)
    finally:
        if mp is not None:
            mp.close()
        if bridge is not None:
            bridge.stop()
        ap.stop()
    yield s


def check_the_bridges_parameters_come_through_ardupilot_for_every_component(seen: Seen) -> None:
    print(
        f"through ArduPilot: PARAM_REQUEST_LIST to component 0 -> {len(seen.list_first_round)} "
        f"of {seen.list_count} bridge parameters in the first round, the last after "
        f"{seen.list_seconds:.2f} s; {seen.ardupilot_params} from ArduPilot beside them; "
        f"MAVProxy: {seen.mavproxy_received!r}"
    )
    assert seen.list_count == seen.bridge_params
    assert seen.list_first_round == set(range(seen.list_count))
    assert seen.list_seconds < 2.0
    assert seen.ardupilot_params > 500
    assert 200 in seen.read_answers
    assert seen.mavproxy_received.endswith(f"Received {seen.bridge_params} parameters")
    assert seen.mavproxy_set == 2.0


def check_every_burst_arrives_whole_through_ardupilot(seen: Seen) -> None:
    print(
        f"through ArduPilot: MESSAGE_INTERVAL storm {seen.storm_acks} ACKs and "
        f"{seen.storm_intervals} answers of 30; status text chunks {len(seen.text_chunks)}"
    )
    assert seen.storm_acks == 30 and seen.storm_intervals == 30
    assert companion.joined_text(seen.text_chunks) == companion.LONG_TEXT


def check_mavproxy_starts_and_cancels_the_bridges_calibration_through_ardupilot(
    seen: Seen,
) -> None:
    assert seen.magcal_started and seen.magcal_cancelled


def check_a_calibration_asked_while_ardupilot_calibrates_is_answered_busy(seen: Seen) -> None:
    assert seen.busy.result == M.MAV_RESULT_TEMPORARILY_REJECTED, seen.busy
    assert not seen.busy_started


def test_the_companion_through_ardupilot(seen: Any) -> None:
    """One run of the scenario, every check on it (see :func:`autopilots.check_all`)."""
    check_all(
        seen,
        [
            check_the_bridges_parameters_come_through_ardupilot_for_every_component,
            check_every_burst_arrives_whole_through_ardupilot,
            check_mavproxy_starts_and_cancels_the_bridges_calibration_through_ardupilot,
            check_a_calibration_asked_while_ardupilot_calibrates_is_answered_busy,
        ],
    )
