"""A ground station reaches the companion bridge through the real PX4's MAVLink router.

PX4 v1.16 SITL (SIH) from ``../shared/autopilots/px4``; the bridge as component
200 on PX4's onboard link, a ground station (pymavlink, then MAVSDK) on PX4's GCS
link. PX4 forwards between its links through a buffer of two messages per link,
and sends one forwarded message per loop (``Mavlink::pass_message``,
``task_main``); every message that did not fit counts in its "forwarding error"
perf counter, which the tests read with ``px4-perf`` before and after. One PX4
run serves the module:

* QGroundControl's initial load -- PARAM_REQUEST_LIST to component 0 -- gets the
  bridge's whole list beside PX4's, in the first round, in under 2 s;
* PARAM_REQUEST_READ to component 0, pymavlink's ``param_fetch_all`` and MAVSDK's
  Param plugin for component 200 get it too; commands keep their own-component rule;
* every other burst -- a storm of MESSAGE_INTERVAL requests, a long STATUSTEXT in
  chunks -- arrives whole;
* ... all of it unless PX4 itself counted a message as dropped: on two cores shared
  with the rest of the suite PX4's SITL loop now and then stalls and drops one paced
  message (:data:`ROUTER_LOSS_MAX` at most). Every message lost is one PX4 counted (or one
  the kernel dropped at the test's own ground station's socket, counted there), and a
  parameter the first round missed is asked for again by index, as QGroundControl
  (``ParameterManager::_waitingParamTimeout``) and MAVProxy (``fetch_check``) do; the
  bridge answers those too;
* a calibration asked of the bridge while PX4 runs its own gyro calibration is
  answered TEMPORARILY_REJECTED (busy), and the bridge starts nothing.
"""

from __future__ import annotations

import math
import re
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import companion_bridge as companion
import mavsdk
import pytest
from autopilots import Autopilot, M, check_all, start_px4
from companion_bridge import Bridge, start_bridge
from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.param.param import Param, ParamError, ParamResult, ProtocolVersion

pytestmark = [pytest.mark.integration, pytest.mark.slow]

HOME = (47.397742, 8.545594, 488.0)


@dataclass
class Seen:
    """What the ground station saw, and PX4's forwarding errors around it."""

    errors_before: int = -1
    errors_after: int = -1
    #: datagrams the kernel dropped at the ground station's own socket (its buffer full)
    gcs_drops_before: int = -1
    gcs_drops_after: int = -1
    list_seconds: float = 0.0
    list_first_round: set[int] = field(default_factory=set)
    list_complete: set[int] = field(default_factory=set)
    list_count: int = 0
    px4_params: int = 0
    read_answers: list[tuple[int, str]] = field(default_factory=list)
    fetch_all: set[int] = field(default_factory=set)
    fetch_complete: set[int] = field(default_factory=set)
    storm_acks: int = 0
    storm_intervals: int = 0
    text_chunks: list[Any] = field(default_factory=list)
    broadcast_command_acks: list[Any] = field(default_factory=list)
    busy: Any = None
    busy_started: bool = True
    mavsdk_names: set[str] = field(default_factory=set)
    bridge_params: int = 0


def forwarding_errors(ap: Autopilot) -> int:
    """The sum of PX4's "forwarding error" perf counters over its MAVLink links."""
    r = subprocess.run(
        [str(ap.workdir / "bin" / "px4-perf"), "--instance", str(ap.system_id - 1)],
        capture_output=True,
        text=True,
        timeout=20,
        cwd=ap.workdir / "rootfs",
    )
    found = re.findall(r"forwarding error: (\d+) events", r.stdout + r.stderr)
    assert found, r.stdout[-2000:] + r.stderr[-2000:]
    return sum(int(n) for n in found)


@pytest.fixture(scope="module")
def seen(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Seen]:
    work = tmp_path_factory.mktemp("px4-companion")
    ap = start_px4(work / "px4", {})
    s = Seen()
    bridge: Bridge | None = None
    try:
        bridge = start_bridge(
            work / "bridge",
            f"udpin:127.0.0.1:{ap.companion_port}",
            feed="off",
            location=HOME,
            compass_at=HOME,
            yaw_deg=30.0,
            system_id=ap.system_id,
        )
        s.bridge_params = len(bridge.out.params.params)
        obs = ap.observer
        sysid = ap.system_id
        obs.wait("HEARTBEAT", companion.from_bridge)  # forwarded by PX4
        s.errors_before, s.gcs_drops_before = forwarding_errors(ap), obs.socket_drops()
        # QGroundControl's initial load: PARAM_REQUEST_LIST to every component
        t0 = time.monotonic()
        try:
            s.list_seconds, s.list_first_round, s.list_count = companion.load_parameters(
                obs, sysid, t0
            )
        except pytest.fail.Exception as e:  # PX4's own count of what its router dropped
            pytest.fail(f"{e}; PX4 forwarding errors {s.errors_before} before, "
                        f"{forwarding_errors(ap)} now")  # fmt: skip
        # ... and what QGroundControl then asks for again, by index
        s.list_complete = companion.fetch_missing(obs, sysid, s.list_first_round, s.list_count)
        time.sleep(3.0)
        s.px4_params = companion.autopilot_parameters(obs, since=t0)
        # PARAM_REQUEST_READ to every component: the bridge answers what it has
        t1 = time.monotonic()
        obs.mav.param_request_read_send(sysid, 0, b"BRG_YAW_SIGMA", -1)
        obs.wait("PARAM_VALUE", lambda m: m.param_id == "BRG_YAW_SIGMA", since=t1)
        time.sleep(0.5)
        s.read_answers = [
            (m.get_srcComponent(), m.param_id)
            for _, m in obs.history(
                "PARAM_VALUE", lambda m: m.param_id == "BRG_YAW_SIGMA", since=t1
            )
        ]
        # pymavlink's parameter fetch, aimed at component 200
        t2 = time.monotonic()
        obs.conn.target_system, obs.conn.target_component = sysid, 200
        obs.conn.param_fetch_all()
        fetched = obs.until_quiet(
            "PARAM_VALUE",
            companion.from_bridge,
            t2,
            companion.QGC_PARAM_TIMEOUT_S,
            lambda ms: len({m.param_index for m in ms}) >= s.bridge_params,
        )
        s.fetch_all = {m.param_index for _, m in fetched}
        # MAVProxy's param module then asks for what is missing, by index (fetch_check)
        s.fetch_complete = companion.fetch_missing(obs, sysid, s.fetch_all, s.bridge_params)
        # a storm of GET_MESSAGE_INTERVAL: every answer comes back
        s.storm_acks, s.storm_intervals = companion.message_interval_storm(obs, sysid)
        # a long status text, in chunks
        s.text_chunks = companion.send_long_status_text(bridge, obs)
        # commands keep their own-component rule: a broadcast is PX4's alone
        t5 = time.monotonic()
        obs.mav.command_long_send(
            sysid, 0, M.MAV_CMD_GET_MESSAGE_INTERVAL, 0, M.MAVLINK_MSG_ID_ATTITUDE, 0, 0, 0, 0, 0, 0
        )
        time.sleep(1.0)
        s.broadcast_command_acks = [
            m for _, m in obs.history("COMMAND_ACK", companion.from_bridge, since=t5)
        ]
        s.errors_after, s.gcs_drops_after = forwarding_errors(ap), obs.socket_drops()
        # MAVSDK as a ground station on another of PX4's forwarding links (its GCS link
        # answers only the first peer it heard, the pymavlink one): the gimbal link, which
        # sends to 13280 + N; its Param plugin for component 200.
        s.mavsdk_names = _mavsdk_params(13280 + ap.system_id - 1)
        # PX4's own gyro calibration, and a magnetometer calibration asked of the bridge
        ack = obs.command(ap.target, M.MAV_CMD_PREFLIGHT_CALIBRATION, 1, 0, 0, 0, 0, 0, 0)
        assert ack.result in (M.MAV_RESULT_ACCEPTED, M.MAV_RESULT_IN_PROGRESS), ack
        obs.wait(
            "HEARTBEAT",
            lambda m: m.get_srcComponent() == 1 and m.system_status == M.MAV_STATE_CALIBRATING,
            timeout=10.0,
        )
        deadline = time.monotonic() + 5.0  # PX4's next HEARTBEAT on the onboard link
        while not bridge.out.autopilot.calibrating and time.monotonic() < deadline:
            time.sleep(0.05)
        s.busy = obs.command((sysid, 200), M.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 1, 0, 0, 0, 0, 0)
        s.busy_started = bridge.daemon.bridge.calibrator.snapshot().running
    finally:
        if bridge is not None:
            bridge.stop()
        ap.stop()
    yield s


#: The most messages PX4's router may drop over the whole run, each one counted by PX4
#: itself ("forwarding error"). In SITL on two cores shared with the suite's other
#: processes, a stalled PX4 loop now and then drops one paced message; without the pacer one
#: parameter list lost 24 of its 38 (docs/mavlink.md, "Through a router").
ROUTER_LOSS_MAX = 3
#: STATUSTEXT carries 50 characters a chunk.
TEXT_CHUNKS = math.ceil(len(companion.LONG_TEXT.encode()) / 50)


def lost_in_bursts(seen: Seen) -> int:
    """The bursts' messages that did not arrive at the ground station: parameters missing
    from the first round of each load, the MESSAGE_INTERVAL storm's (a command lost on
    the way in costs both its answers: counted once) and STATUSTEXT chunks."""
    n = seen.bridge_params
    storm = max(30 - seen.storm_acks, 30 - seen.storm_intervals)
    return (
        (n - len(seen.list_first_round))
        + (n - len(seen.fetch_all))
        + storm
        + (TEXT_CHUNKS - len(seen.text_chunks))
    )


def check_a_parameter_load_for_every_component_brings_the_bridges_whole_list(
    seen: Seen,
) -> None:
    print(
        f"through PX4: PARAM_REQUEST_LIST to component 0 -> {len(seen.list_first_round)} of "
        f"{seen.list_count} bridge parameters in the first round, the last after "
        f"{seen.list_seconds:.2f} s; {len(seen.list_complete)} with QGroundControl's "
        f"re-requests; {seen.px4_params} from PX4 beside them"
    )
    assert seen.list_count == seen.bridge_params
    assert seen.list_complete == set(range(seen.list_count))
    if len(seen.list_first_round) == seen.list_count:  # else the re-requests came after 3 s
        assert seen.list_seconds < 2.0
    assert seen.px4_params > 100


def check_every_burst_arrives_whole_but_what_px4_counts_as_dropped(seen: Seen) -> None:
    errors = seen.errors_after - seen.errors_before
    gcs_drops = seen.gcs_drops_after - seen.gcs_drops_before
    lost = lost_in_bursts(seen)
    print(
        f"PX4 forwarding errors: {seen.errors_before} before, {seen.errors_after} after; "
        f"dropped at the ground station's socket: {gcs_drops}; "
        f"MESSAGE_INTERVAL storm: {seen.storm_acks} ACKs and {seen.storm_intervals} answers "
        f"of 30; status text chunks {len(seen.text_chunks)} of {TEXT_CHUNKS}; lost in the "
        f"bursts {lost}"
    )
    # Every message lost on the way is one PX4 counted as dropped, and there are few:
    # with none counted (the rule on a machine that keeps PX4's loop on time), every
    # burst arrived whole. (Or one the kernel dropped at the test's own ground station, its
    # socket full while the suite held the cores: counted there, never on a quiet machine.
    # A CI run lost 7 of the first round's 38 with PX4 counting none, before that socket
    # had room for seconds of PX4's telemetry and its drops were read.)
    assert lost <= errors + gcs_drops, (lost, errors, gcs_drops)
    assert errors <= ROUTER_LOSS_MAX
    assert seen.storm_acks <= 30 and seen.storm_intervals <= 30
    assert len(seen.text_chunks) <= TEXT_CHUNKS  # (none counted twice above)
    if len(seen.text_chunks) == TEXT_CHUNKS:
        assert companion.joined_text(seen.text_chunks) == companion.LONG_TEXT


def check_reads_for_every_component_are_answered_and_commands_keep_their_rule(seen: Seen) -> None:
    assert (200, "BRG_YAW_SIGMA") in seen.read_answers
    assert seen.fetch_complete == set(range(seen.bridge_params))
    assert not seen.broadcast_command_acks  # a broadcast command is PX4's business


def _mavsdk_params(port: int) -> set[str]:
    log: list[str] = []

    def on_log(_level: Any, message: str, _file: Any, _line: int) -> bool:
        log.append(message)
        return True  # handled: not printed by MAVSDK as well

    mavsdk.log_subscribe(on_log)
    m = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        m.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = m.first_autopilot(30.0)
        assert system is not None, log[-20:]
        deadline = time.monotonic() + 15.0
        while 200 not in system.component_ids() and time.monotonic() < deadline:
            time.sleep(0.1)  # the bridge's HEARTBEAT, forwarded by PX4
        param = Param(system)
        try:
            param.select_component(200, ProtocolVersion.V1)
        except ParamError as e:
            # MAVSDK 4.1's ParamImpl::select_component selects and then always returns
            # Result::Unknown, which the Python wrapper raises.
            assert e.result is ParamResult.UNKNOWN, e
        every = param.get_all_params()
        return {p.name for p in every.int_params} | {p.name for p in every.float_params}
    finally:
        m.destroy()
        mavsdk.log_unsubscribe()


def check_mavsdk_gets_the_companions_parameters_through_px4(seen: Seen) -> None:
    assert len(seen.mavsdk_names) == seen.bridge_params, sorted(seen.mavsdk_names)
    assert "BRG_YAW_SIGMA" in seen.mavsdk_names


def check_a_calibration_asked_while_px4_calibrates_is_answered_busy(seen: Seen) -> None:
    assert seen.busy.result == M.MAV_RESULT_TEMPORARILY_REJECTED, seen.busy
    assert not seen.busy_started


def test_the_companion_through_px4(seen: Any) -> None:
    """One run of the scenario, every check on it (see :func:`autopilots.check_all`)."""
    check_all(
        seen,
        [
            check_a_parameter_load_for_every_component_brings_the_bridges_whole_list,
            check_every_burst_arrives_whole_but_what_px4_counts_as_dropped,
            check_reads_for_every_component_are_answered_and_commands_keep_their_rule,
            check_mavsdk_gets_the_companions_parameters_through_px4,
            check_a_calibration_asked_while_px4_calibrates_is_answered_busy,
        ],
    )
