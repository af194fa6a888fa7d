"""The companion role beside an autopilot on one link: neither calibration touches the other.

Three parties share the link, as on a vehicle whose telemetry radio or router
joins them: the bridge (system 1, component 200), a stand-in ArduPilot
autopilot (system 1, component 1) and a ground station that behaves as
MAVProxy does. The stand-in follows ArduPilot's own rules for its compass 0
(``Compass::handle_mag_cal_command``): it takes commands for component 0 or
1, starts on a mask of 0 or with bit 0, and on DO_ACCEPT_MAG_CAL stops the
calibrator of every compass in the mask -- saving it if it succeeded, losing
it if it was still running. The ground station's ``magcal start`` is a
broadcast (target component 0, autosave), and on every MAG_CAL_REPORT it sends
DO_ACCEPT_MAG_CAL(1 << compass_id) to the system's component 0
(``mavproxy_calibration.py``, its target component left at 0).

Were the bridge to act on broadcasts, or to report its calibration as compass 0,
that automatic accept would stop the autopilot's compass-0 calibration halfway.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from test_mavlink_rig import DEADLINE_S, Gcs, M, Rig, connect_gcs

from bridge.mavlink.output import COMPANION_COMPASS_ID
from bridge.sim.motion import Still

pytestmark = pytest.mark.integration  # real sockets, processes or threads

AP = (1, 1)
BRIDGE = (1, 200)
ACCEPTED, FAILED = M.MAV_RESULT_ACCEPTED, M.MAV_RESULT_FAILED
TEMPORARILY_REJECTED = M.MAV_RESULT_TEMPORARILY_REJECTED
NOT_STARTED, RUNNING, SUCCESS = (
    M.MAG_CAL_NOT_STARTED,
    M.MAG_CAL_RUNNING_STEP_ONE,
    M.MAG_CAL_SUCCESS,
)


def source(m: Any) -> tuple[int, int]:
    return (m.get_srcSystem(), m.get_srcComponent())


class StandInAutopilot:
    """ArduPilot's compass-calibration behaviour for its compass 0, nothing else."""

    STEP_S = 0.6  #: progress +25 % per step: a calibration takes 2.4 s (two report repeats)

    def __init__(self, peer: Gcs, hub: Hub) -> None:
        self.peer, self.hub = peer, hub
        self.status = NOT_STARTED
        self.pct = 0
        self.saved = False
        self.handled: list[Any] = []  #: the commands it acted on
        self.param_sets: list[str] = []
        self._next_step = 0.0
        self._next_heartbeat = 0.0

    def tick(self, now: float) -> None:
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + 0.5
            hb = self.peer.mav.heartbeat_encode(
                M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, M.MAV_STATE_STANDBY
            )
            self.hub.send(self, hb)
        if now < self._next_step:
            return
        self._next_step = now + self.STEP_S
        mav = self.peer.mav
        if self.status == RUNNING:
            self.pct += 25
            if self.pct >= 100:
                self.status = SUCCESS
            else:
                self.hub.send(
                    self, mav.mag_cal_progress_encode(0, 1, RUNNING, 1, self.pct, [0] * 10, 0, 0, 0)
                )
        if self.status == SUCCESS:  # repeated while it waits, as send_mag_cal_report does
            report = mav.mag_cal_report_encode(
                0, 1, SUCCESS, int(self.saved), 1.5, 10, 20, 30, 1, 1, 1, 0, 0, 0
            )
            self.hub.send(self, report)

    def receive(self, m: Any) -> None:
        kind = m.get_type()
        if kind == "PARAM_SET" and (m.target_system, m.target_component) in ((1, 0), AP):
            self.param_sets.append(m.param_id)
            return
        if kind != "COMMAND_LONG" or m.target_system not in (0, 1):
            return
        if m.target_component not in (0, 1):
            return  # another component's
        mask = int(m.param1)
        ours = mask == 0 or bool(mask & 1)
        result = ACCEPTED
        if m.command == M.MAV_CMD_DO_START_MAG_CAL and ours:
            self.status, self.pct, self.saved = RUNNING, 0, False
        elif m.command == M.MAV_CMD_DO_ACCEPT_MAG_CAL and ours:
            if self.status == SUCCESS:
                self.saved = True
            else:
                result = FAILED
            self.status = NOT_STARTED  # _accept_calibration_mask: stop()
        elif m.command == M.MAV_CMD_DO_CANCEL_MAG_CAL and ours:
            self.status = NOT_STARTED
        elif m.command not in (
            M.MAV_CMD_DO_START_MAG_CAL,
            M.MAV_CMD_DO_ACCEPT_MAG_CAL,
            M.MAV_CMD_DO_CANCEL_MAG_CAL,
        ):
            return
        self.handled.append(m)
        ack = self.peer.mav.command_ack_encode(
            m.command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent()
        )
        self.hub.send(self, ack)


class Hub:
    """The shared link: every peer talks to the bridge over its own UDP connection, and
    what a peer sends also reaches the other peers (a router's job)."""

    def __init__(self, rig: Rig) -> None:
        def peer(sysid: int, compid: int) -> Gcs:
            g = connect_gcs(f"udpout:127.0.0.1:{rig.udp_port}", sysid=sysid, compid=compid)
            rig.gcss.append(g)
            return g

        self.gcs = peer(255, 190)
        self.ap = StandInAutopilot(peer(1, 1), self)
        #: (mask, the autopilot's status then) of every accept the ground station sent by itself
        self.auto_accepts: list[tuple[int, int]] = []
        self._answered: set[int] = set()

    def send(self, sender: Any, msg: Any) -> None:
        """``msg`` from ``sender`` (the ground station's Gcs or the autopilot) to everyone."""
        g = sender if isinstance(sender, Gcs) else sender.peer
        data = bytes(msg.pack(g.mav))
        g.conn.write(data)
        parsed = M.MAVLink(None).parse_buffer(data)[0]
        if g is self.gcs:
            self.ap.receive(parsed)
        else:
            self.gcs.inbox.append(parsed)

    def gcs_command(self, target: tuple[int, int], command: int, *params: float) -> None:
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        self.send(self.gcs, self.gcs.mav.command_long_encode(*target, command, 0, *p))

    def step(self) -> None:
        """Everyone reads what came; the autopilot works; the ground station accepts every
        report it sees, as MAVProxy does (to component 0 of the system)."""
        self.gcs.pump(0.02)
        self.ap.peer.pump(0.0)
        for m in self.ap.peer.inbox:
            self.ap.receive(m)
        self.ap.peer.inbox.clear()
        self.ap.tick(time.monotonic())
        for m in list(self.gcs.inbox):
            if m.get_type() == "MAG_CAL_REPORT" and id(m) not in self._answered:
                self._answered.add(id(m))
                mask = 1 << m.compass_id
                self.auto_accepts.append((mask, self.ap.status))
                self.gcs_command((1, 0), M.MAV_CMD_DO_ACCEPT_MAG_CAL, mask)

    def wait(self, cond: Callable[[], Any], timeout: float = DEADLINE_S) -> Any:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.step()
            got = cond()
            if got:
                return got
        pytest.fail("condition not met in time")

    def run(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.step()

    def from_bridge(self, mtype: str, cond: Callable[[Any], bool] | None = None) -> list[Any]:
        return [
            m
            for m in self.gcs.inbox
            if m.get_type() == mtype and source(m) == BRIDGE and (cond is None or cond(m))
        ]

    def ack(self, sender: tuple[int, int], command: int) -> Any:
        """Wait for (and take) the ground station's COMMAND_ACK for ``command`` from ``sender``."""

        def find() -> Any:
            for m in self.gcs.inbox:
                if m.get_type() == "COMMAND_ACK" and m.command == command and source(m) == sender:
                    self.gcs.inbox.remove(m)
                    return m
            return None

        return self.wait(find)


def test_ground_station_calibrating_the_autopilot_and_the_bridge_never_cross(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    rig = rigs(tmp_path, motion=Still.from_deg(2.0, -3.0, 40.0), mavlink={"role": "companion"})
    hub = Hub(rig)
    cal = rig.daemon.bridge.calibrator
    hub.wait(lambda: hub.from_bridge("HEARTBEAT"))

    # the bridge's own calibration, addressed to it: a result at once (a known true yaw)
    hub.gcs_command(BRIDGE, M.MAV_CMD_FIXED_MAG_CAL_YAW, 40.0, 0, 0, 0)
    assert hub.ack(BRIDGE, M.MAV_CMD_FIXED_MAG_CAL_YAW).result == ACCEPTED
    report = hub.wait(lambda: hub.from_bridge("MAG_CAL_REPORT"))[0]
    assert report.compass_id == COMPANION_COMPASS_ID and report.cal_status == SUCCESS
    assert report.cal_mask == 1 << COMPANION_COMPASS_ID
    # MAVProxy's `magcal start` is a broadcast: the autopilot's, not ours
    hub.gcs_command((1, 0), M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 1, 0)
    assert hub.ack(AP, M.MAV_CMD_DO_START_MAG_CAL).result == ACCEPTED
    assert hub.ap.status == RUNNING
    # while the autopilot calibrates, a calibration asked of the bridge is busy
    hub.wait(lambda: rig.out.autopilot.calibrating)
    hub.gcs_command(BRIDGE, M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 0, 0)
    assert hub.ack(BRIDGE, M.MAV_CMD_DO_START_MAG_CAL).result == TEMPORARILY_REJECTED
    # The ground station accepts the bridge's repeated report by itself (mask 1 << 7, to
    # component 0): the autopilot's compass 0 is not in that mask, so its calibration runs on
    hub.wait(lambda: ((1 << COMPANION_COMPASS_ID), RUNNING) in hub.auto_accepts)
    # ... to its own report, which the ground station accepts (mask 1): saved by the autopilot
    # (had that first accept stopped it, it would never have succeeded)
    hub.wait(lambda: hub.ap.saved)
    assert (1, SUCCESS) in hub.auto_accepts
    # and the bridge took none of those broadcast accepts: its report still waits
    assert not [m for m in hub.gcs.inbox if m.get_type() == "COMMAND_ACK" and source(m) == BRIDGE]
    hub.gcs.inbox.clear()
    hub.wait(lambda: hub.from_bridge("MAG_CAL_REPORT"))
    hub.gcs_command(BRIDGE, M.MAV_CMD_DO_ACCEPT_MAG_CAL, 1 << COMPANION_COMPASS_ID)
    assert hub.ack(BRIDGE, M.MAV_CMD_DO_ACCEPT_MAG_CAL).result == ACCEPTED
    autopilot_commands = len(hub.ap.handled)

    # the bridge calibrating: a ground station's broadcasts for the autopilot leave it alone
    hub.gcs_command(BRIDGE, M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 0, 0)
    assert hub.ack(BRIDGE, M.MAV_CMD_DO_START_MAG_CAL).result == ACCEPTED
    progress = hub.wait(lambda: hub.from_bridge("MAG_CAL_PROGRESS"))
    assert {(p.compass_id, p.cal_mask) for p in progress} == {(7, 1 << 7)}
    assert len(hub.ap.handled) == autopilot_commands  # nor did the start reach the autopilot
    for command in (M.MAV_CMD_DO_CANCEL_MAG_CAL, M.MAV_CMD_DO_ACCEPT_MAG_CAL):
        hub.gcs_command((1, 0), command, 0)
        hub.ack(AP, command)
    hub.gcs_command((1, 0), M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 1, 0)
    hub.ack(AP, M.MAV_CMD_DO_START_MAG_CAL)
    hub.run(0.5)
    assert cal.snapshot().running
    assert not [m for m in hub.gcs.inbox if m.get_type() == "COMMAND_ACK" and source(m) == BRIDGE]
    hub.gcs_command(BRIDGE, M.MAV_CMD_DO_CANCEL_MAG_CAL, 0)
    assert hub.ack(BRIDGE, M.MAV_CMD_DO_CANCEL_MAG_CAL).result == ACCEPTED
    assert not cal.snapshot().running

    # parameters: a SET or read for the autopilot is not ours
    before = rig.daemon.bridge.params.get("BRG_SR_HUD")
    hub.gcs.inbox.clear()
    hub.send(
        hub.gcs, hub.gcs.mav.param_set_encode(*AP, b"BRG_SR_HUD", 1.0, M.MAV_PARAM_TYPE_REAL32)
    )
    hub.send(hub.gcs, hub.gcs.mav.param_request_read_encode(*AP, b"BRG_SR_HUD", -1))
    hub.send(hub.gcs, hub.gcs.mav.param_request_list_encode(*AP))
    hub.run(1.0)
    assert hub.ap.param_sets == ["BRG_SR_HUD"]
    assert rig.daemon.bridge.params.get("BRG_SR_HUD") == before
    assert not hub.from_bridge("PARAM_VALUE")
    hub.send(
        hub.gcs, hub.gcs.mav.param_set_encode(*BRIDGE, b"BRG_SR_HUD", 1.0, M.MAV_PARAM_TYPE_REAL32)
    )
    echo = hub.wait(lambda: hub.from_bridge("PARAM_VALUE"))[0]
    assert echo.param_id == "BRG_SR_HUD" and echo.param_value == 1.0
    assert rig.daemon.bridge.params.get("BRG_SR_HUD") == 1.0
