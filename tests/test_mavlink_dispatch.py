"""Command parameters as ArduPilot and PX4 read them: NaN is "not given", integers truncate.

ArduPilot C-casts (``uint8_t mag_mask = packet.param1``, ``!is_zero(packet.param2)``
for a flag: AP_Compass_Calibration.cpp); PX4's commander C-casts too
(``(int)cmd.param2 == 1``). MAVSDK fills every parameter a command does not set
with NaN for a non-ArduPilot autopilot (``MavlinkCommandSender::maybe_reserved``),
so a PX4-flavoured bridge receives PREFLIGHT_CALIBRATION with param6 = param7 = NaN.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from harness import ManualClock
from test_mavlink_rig import M, Rig, Sent, offline_daemon, wait_until

from bridge.events import Event
from bridge.mavlink.commands import Command
from bridge.mavlink.dispatch import PendingAcks, _mask, flag_param, given, int_param
from bridge.mavlink.output import MavlinkOutput, MavlinkSettings
from bridge.sim.motion import Still

NAN = math.nan
ACCEPTED = M.MAV_RESULT_ACCEPTED


@pytest.mark.parametrize(
    "value,expected",
    [
        (1.0, 1),
        (1.9999, 1),  # truncated, not rounded: (int)1.9999f is 1
        (-1.9999, -1),  # toward zero
        (0.4, 0),
        (-0.0, 0),
        (2.0**31 - 128, 2**31 - 128),  # the largest float below 2^31
        (-(2.0**31) + 128, -(2**31) + 128),
    ],
)
def test_int_param_truncates_toward_zero(value: float, expected: int) -> None:
    assert int_param(value) == expected


def test_int_param_nan_is_not_given_and_the_unrepresentable_is_refused() -> None:
    assert int_param(NAN) == 0 and int_param(NAN, default=-1) == -1
    for bad in (math.inf, -math.inf, 2.0**31, -(2.0**31), 1e20):
        assert int_param(bad) is None, bad
    assert not given(NAN) and given(0.0) and given(math.inf)


@pytest.mark.parametrize(
    "value,expected",
    [(NAN, False), (0.0, False), (-0.0, False), (1.0, True), (0.5, True), (-1.0, True)],
)
def test_flag_param_is_not_zero_and_nan_is_no(value: float, expected: bool) -> None:
    assert flag_param(value) is expected


@pytest.mark.parametrize(
    "value,expected",
    [
        (0.0, 0),
        (NAN, 0),
        (1.0, 1),
        (1.9, 1),
        (254.5, 254),
        (255.0, 255),
        (255.5, None),  # ArduPilot: param1 > 255 is FAILED, before any cast
        (-0.5, None),  # param1 < 0 likewise
        (256.0, None),
        (math.inf, None),
    ],
)
def test_a_compass_mask_is_checked_then_uint8_cast(value: float, expected: int | None) -> None:
    assert _mask(value) == expected


@pytest.mark.integration
def test_mavsdk_style_commands_with_nan_parameters(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    """The PX4 calibration as MAVSDK sends it (params 6 and 7 NaN), PX4's cancel (params 1-6
    zero, 7 NaN), and ArduPilot's start with NaN flags and a mask that needs truncating."""
    rig = rigs(tmp_path, motion=Still.from_deg(0.0, 0.0, 30.0), mavlink={"autopilot": "px4"})
    g = rig.gcs("udp")
    ack = g.command(M.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 1, 0, 0, 0, NAN, NAN)
    assert ack.result == ACCEPTED
    g.wait("STATUSTEXT", lambda m: m.text == "[cal] calibration started: 2 mag")
    assert rig.daemon.bridge.calibrator.snapshot().running
    # PX4's cancel: params 1-6 all zero, whatever param 7 holds
    assert g.command(M.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 0, 0, 0, 0, 0, NAN).result == ACCEPTED
    g.wait("STATUSTEXT", lambda m: m.text == "[cal] calibration cancelled")
    assert wait_until(lambda: not rig.daemon.bridge.calibrator.snapshot().running)
    # every parameter NaN: nothing given, read as zeros: the cancel again (nothing runs)
    g.flush()
    ack = g.command(M.MAV_CMD_PREFLIGHT_CALIBRATION, NAN, NAN, NAN, NAN, NAN, NAN, NAN)
    assert ack.result == ACCEPTED
    assert not rig.daemon.bridge.calibrator.snapshot().running
    # level as MAVSDK asks for it: param5 = 2, the rest 0 or NaN
    ack = g.command(M.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 0, 0, 0, 2, NAN, NAN)
    assert ack.result == ACCEPTED
    g.wait("STATUSTEXT", lambda m: m.text == "[cal] calibration started: 2 level")
    g.wait("STATUSTEXT", lambda m: m.text.startswith("[cal] calibration done"), timeout=20.0)
    # ArduPilot's start: mask 1.9 is compass 0 ((uint8_t)1.9f), NaN flags are "no"
    ack = g.command(M.MAV_CMD_DO_START_MAG_CAL, 1.9, NAN, NAN, NAN, NAN, NAN, NAN)
    assert ack.result == ACCEPTED
    progress = g.wait("MAG_CAL_PROGRESS")
    assert progress.compass_id == 0 and progress.cal_mask == 1
    assert g.command(M.MAV_CMD_DO_CANCEL_MAG_CAL, NAN).result == ACCEPTED  # NaN mask: all
    assert wait_until(lambda: not rig.daemon.bridge.calibrator.snapshot().running)
    # a mask that cannot be an uint8 fails, as in ArduPilot, rather than naming another compass
    assert g.command(M.MAV_CMD_DO_START_MAG_CAL, 256.0).result == M.MAV_RESULT_FAILED
    assert not rig.daemon.bridge.calibrator.snapshot().running
    assert g.command(M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 0, 0).result == ACCEPTED
    assert g.command(M.MAV_CMD_DO_CANCEL_MAG_CAL, -1.0).result == M.MAV_RESULT_FAILED
    assert rig.daemon.bridge.calibrator.snapshot().running  # and nothing was cancelled
    assert g.command(M.MAV_CMD_DO_CANCEL_MAG_CAL, 0).result == ACCEPTED


def storage_command() -> Command:
    return Command(M.MAV_CMD_PREFLIGHT_STORAGE, (1.0,) + (0.0,) * 6, 1, 1, 255, 190)


@pytest.mark.integration
def test_an_outcome_from_another_thread_during_the_work_neither_blocks_nor_reorders() -> None:
    """The work (the calibration controller) emits events from its own threads; waiting for
    them must not block on the dispatcher (it deadlocked a live accept), and the final ack
    still follows the IN_PROGRESS one."""
    acks, link = PendingAcks(), Sent()
    cmd = Command(M.MAV_CMD_DO_ACCEPT_MAG_CAL, (0.0,) * 7, 1, 1, 255, 190)

    def work(_done: Callable[[bool], None]) -> int:
        t = threading.Thread(target=acks.on_event, args=(Event("calibration.done", "done"),))
        t.start()
        t.join(5.0)
        assert not t.is_alive(), "the event thread blocked on the dispatcher"
        return 1

    assert acks.long_work(cmd, link, work, ("calibration.done",), ("calibration.failed",))
    assert link.results == [M.MAV_RESULT_IN_PROGRESS, M.MAV_RESULT_ACCEPTED]


@pytest.mark.parametrize("order", ["call, event", "event, call", "call during the work, event"])
def test_long_work_of_two_outcomes_is_accepted_when_both_came_in_whatever_order(
    order: str,
) -> None:
    """PREFLIGHT_STORAGE write: the paced params.json write (told by a call) and the compass
    flash's PAR,SET (told by an event) -- one final ack, after both, whichever comes first,
    before or after the IN_PROGRESS ack."""
    flash = Event("calibration.device_updated", "written")
    acks, link = PendingAcks(), Sent()
    told: list[Callable[[bool], None]] = []

    def work(done: Callable[[bool], None]) -> int:
        told.append(done)
        if order.startswith("call during"):
            done(True)
        return 2

    assert acks.long_work(storage_command(), link, work, (flash.kind,), ("x.error",))
    assert link.results == [M.MAV_RESULT_IN_PROGRESS]
    if order == "call, event":
        told[0](True)
        assert link.results == [M.MAV_RESULT_IN_PROGRESS]  # the flash still to come
        acks.on_event(flash)
    elif order == "event, call":
        acks.on_event(flash)
        assert link.results == [M.MAV_RESULT_IN_PROGRESS]
        told[0](True)
    else:
        acks.on_event(flash)
    assert link.results == [M.MAV_RESULT_IN_PROGRESS, M.MAV_RESULT_ACCEPTED]
    told[0](True)  # anything after the final ack is not answered again
    acks.on_event(flash)
    assert len(link.messages) == 2 and acks.due_at == math.inf


@pytest.mark.parametrize("failing", ["call", "event", "call during the work"])
def test_long_work_fails_at_its_first_failed_outcome_and_answers_once(failing: str) -> None:
    acks, link = PendingAcks(), Sent()
    told: list[Callable[[bool], None]] = []

    def work(done: Callable[[bool], None]) -> int:
        told.append(done)
        if failing == "call during the work":
            done(False)
        return 2

    acks.long_work(storage_command(), link, work, ("x.done",), ("x.error",))
    if failing == "call":
        told[0](False)
    elif failing == "event":
        acks.on_event(Event("x.error", "no"))
    assert link.results == [M.MAV_RESULT_IN_PROGRESS, M.MAV_RESULT_FAILED]
    acks.on_event(Event("x.done", "late"))
    told[0](True)
    assert len(link.messages) == 2


def test_work_that_answers_itself_sends_nothing_and_keeps_nothing() -> None:
    """Work that finished (0 outcomes to come) leaves the ack to its caller, even if an
    outcome was told meanwhile; a later event finds nothing waiting."""
    acks, link = PendingAcks(), Sent()

    def work(done: Callable[[bool], None]) -> int:
        done(False)
        return 0

    assert not acks.long_work(storage_command(), link, work, ("x.done",), ("x.error",))
    acks.on_event(Event("x.done", "late"))
    assert link.messages == [] and acks.due_at == math.inf


class Acks(Sent):
    """Sent, waited on: acks come from the params saver's thread too."""

    def __init__(self) -> None:
        super().__init__()
        self.came = threading.Condition()

    def send(self, packet: Any) -> None:
        with self.came:
            super().send(packet)
            self.came.notify_all()

    def result(self, n: int) -> int:
        """The ``n``-th ack's result (0-based), once it has come."""
        with self.came:
            assert self.came.wait_for(lambda: len(self.messages) > n, 5.0), f"no ack {n}"
            return int(self.messages[n].result)


@pytest.mark.integration
def test_preflight_storage_right_after_a_set_answers_in_progress_and_holds_nothing(
    tmp_path: Path,
) -> None:
    """A value set less than a second after the last params.json write is written when the
    pacing allows. PREFLIGHT_STORAGE write then answers IN_PROGRESS at once (the dispatch
    thread it runs on answers every other command and parameter request: it used to sleep
    there for the rest of the second) and ACCEPTED when the saver's write is done; reset
    alike. A daemon that is never started, its real parameter store and state directory."""
    cfg, daemon = offline_daemon(tmp_path, "storage")
    out = MavlinkOutput(
        MavlinkSettings.from_config(cfg), daemon.bridge.services, clock=ManualClock(100.0)
    )
    params = daemon.bridge.params
    link = Acks()
    storage = M.MAV_CMD_PREFLIGHT_STORAGE
    try:
        params.set("BRG_SR_HUD", 1.0)
        # the first write is due at once (the saver's, or this one's): nothing to wait for
        told: list[bool] = []
        assert params.save_then(told.append) is True
        writes = params.writes
        params.set("BRG_SR_HUD", 2.0)  # pending: written a second after the last write
        out.dispatcher.handle(Command(storage, (1.0,) + (0.0,) * 6, 1, 1, 255, 190), link)
        assert link.results == [M.MAV_RESULT_IN_PROGRESS]
        assert params.writes == writes and not params.saved  # answered before the write
        assert link.result(1) == M.MAV_RESULT_ACCEPTED
        assert params.saved and params.writes == writes + 1
        out.dispatcher.handle(Command(storage, (2.0,) + (0.0,) * 6, 1, 1, 255, 190), link)
        assert link.result(2) == M.MAV_RESULT_IN_PROGRESS  # reset: its write paced alike
        assert link.result(3) == M.MAV_RESULT_ACCEPTED
        assert len(link.messages) == 4 and params.writes == writes + 2
        assert told == []  # answered at once, never told again
    finally:
        params.close()
