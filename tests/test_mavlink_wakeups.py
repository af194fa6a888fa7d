"""When the MAVLink output's telemetry thread wakes: for what is due, not on a clock of its own.

It slept at most half a second whatever was due (HEARTBEAT and SYS_STATUS at 1 Hz, the
calibration keep-alive asking the calibrator twice a second whether a magnetometer
calibration ran): three wake-ups a second at rest. Now it sleeps until
:meth:`MavlinkOutput.next_look`, and whatever makes something due earlier wakes it. In
memory: the output is built on a daemon that is never started, on a clock the test sets,
and its thread is not started (the test plays its rounds).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pytest
from harness import ManualClock
from test_mavlink_rig import M, Sent, offline_daemon

from bridge.app.params import ParamChange
from bridge.core.pacing import early_s
from bridge.events import Event, Severity
from bridge.mavlink import commands as C  # noqa: N812 - short
from bridge.mavlink.dispatch import FINAL_ACK_TIMEOUT_S
from bridge.mavlink.output import MavlinkOutput, MavlinkSettings

T0 = 100.0


@pytest.fixture
def out(tmp_path: Path) -> Iterator[MavlinkOutput]:
    cfg, daemon = offline_daemon(tmp_path, "wakeups")
    o = MavlinkOutput(
        MavlinkSettings.from_config(cfg), daemon.bridge.services, clock=ManualClock(T0)
    )
    o._apply_rates()  # what start() does first (BRG_SR_* into the schedule)
    yield o
    daemon.bridge.params.close()


def first_round(o: MavlinkOutput) -> None:
    """What the thread does on its first wake: the clock streams, a look for a calibration."""
    now = o.clock()
    assert o.next_look(now) <= now  # at once: HEARTBEAT, SYS_STATUS, the keep-alive's look
    assert o.schedule.due_on_clock(now)
    o.relay.keepalive(now, o.services.calibrator.snapshot)


def command(cmd: int, *params: float) -> C.Command:
    p = (*params, *(0.0,) * (7 - len(params)))
    assert len(p) == 7  # COMMAND_LONG's param1..7
    return C.Command(cmd, p, 1, 1, 255, 190)


def test_at_rest_it_sleeps_until_the_next_heartbeat(out: MavlinkOutput) -> None:
    first_round(out)
    # Nothing runs: not half a second (the keep-alive's old look), the next HEARTBEAT.
    assert out.next_look(T0) == pytest.approx(T0 + 1.0 - early_s(1.0))
    assert out.relay.keepalive_due == math.inf


def test_a_calibration_event_wakes_it_for_the_keepalive(out: MavlinkOutput) -> None:
    first_round(out)
    out._wake.clear()
    data = {"mode": "mag", "sensor": "mag", "onboard": False, "attempt": 1}
    out._on_event(Event("calibration.started", "Calibration started: mag", Severity.INFO, data))
    assert out._wake.is_set()  # the sleeping thread is told
    # It looks again within the keep-alive period (twice a second while one runs), not at
    # the next HEARTBEAT.
    assert out.next_look(T0) <= T0 + C.PROGRESS_PERIOD_S


def test_a_new_message_interval_wakes_it_to_plan_anew(out: MavlinkOutput) -> None:
    first_round(out)
    out._wake.clear()
    link = Sent()
    sys_status = M.MAVLINK_MSG_ID_SYS_STATUS
    out.dispatcher.handle(command(M.MAV_CMD_SET_MESSAGE_INTERVAL, sys_status, 100_000), link)
    assert link.messages[-1].result == M.MAV_RESULT_ACCEPTED
    assert out._wake.is_set()
    assert out.next_look(T0) <= T0 + 0.1  # SYS_STATUS at 10 Hz from now, not in a second
    # A parameter that sets a stream's rate does the same.
    out._wake.clear()
    out._on_params(ParamChange(("BRG_SR_SYS",), "test"))
    assert out._wake.is_set()


def test_a_command_in_progress_times_out_on_its_deadline(out: MavlinkOutput) -> None:
    first_round(out)
    link = Sent()
    cmd = command(M.MAV_CMD_DO_START_MAG_CAL)
    assert out.dispatcher.pending.due_at == math.inf
    out.dispatcher.pending.long_work(cmd, link, lambda _done: 1, ("calibration.done",), ())
    deadline = T0 + FINAL_ACK_TIMEOUT_S
    assert out.dispatcher.pending.due_at == deadline
    assert out.next_look(T0) <= deadline
    ManualClock.of(out.clock).t = deadline
    out.dispatcher.pending.expire(deadline)  # on it, not a look later
    assert link.messages[-1].result == M.MAV_RESULT_FAILED
    assert out.dispatcher.pending.due_at == math.inf
