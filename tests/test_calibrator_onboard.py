"""The calibration controller driving the compass's own routines (BRG_CAL_ONBOARD = 1):
MAGCAL guided and ended by the bridge, ACCCAL, a cancel that aborts the device, a RANGE
failure. In memory on the harness (see test_calibrator.py), and once over a real pty.
"""

# ruff: noqa: F811 - the rigs fixture is imported from test_calibrator
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from test_calibrator import (
    DEADLINE_S,
    FAST,
    EventLog,
    Rig,
    _lead_in,
    _params,
    make_config,
    rigs,  # noqa: F401 - the fixture
)

from bridge.calibration.sessions import INSTRUCTION_LEVEL_TURN, INSTRUCTION_SIDE_TURN, Phase, Result
from bridge.daemon import build_daemon
from bridge.protocol.device import LinkState
from bridge.protocol.gmr import Flags
from bridge.sim.firmware import make_firmware
from bridge.sim.motion import (
    HandOnboardCalRotation,
    OnboardCalRotation,
    Still,
    Tumble,
    YawTurns,
    with_shake,
)
from bridge.sim.physics import DEFAULT_LOCATION
from bridge.sim.pty import PtyCompass

# =====================================================================================
# the compass's on-board routines (BRG_CAL_ONBOARD = 1)
# =====================================================================================


def test_onboard_magcal_guided_and_ended_by_the_controller(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    motion = _lead_in(OnboardCalRotation(turn_s=20.0, tip_s=3.0, yaw0=0.3), seconds=10.0)
    rig = rigs(tmp_path, motion, settings=FAST, onboard=True, seed=9)
    truth = rig.fw.sensor.errors.true_calibration()
    flash_before = _params(rig.fw)
    host_before = rig.daemon.engine.calibration

    ended_at: list[float] = []
    rig.daemon.events.subscribe(
        lambda e: ended_at.append(rig.clock()) if e.kind == "calibration.done" else None
    )
    assert rig.ctl.start_mag().result is Result.IN_PROGRESS  # routed by onboard=True
    rig.log.wait("calibration.instruction")
    assert rig.fw.calibrating  # MAGCAL,START reached the device
    snap = rig.finished()
    assert snap.phase is Phase.SUCCEEDED, rig.log.kinds()
    assert not rig.fw.calibrating

    texts = [e.text for e in rig.log.of("calibration.instruction")]
    assert texts == [INSTRUCTION_LEVEL_TURN, INSTRUCTION_SIDE_TURN]
    # END went out only after both turns: the side turn ends at 10 + 20 + 3 + 20 = 53 s
    # (simulated); the controller needs the full turn plus two $PGMRC reports
    epoch = rig.fw.motion_epoch
    assert epoch is not None and len(ended_at) == 1
    assert ended_at[0] - epoch >= 50.0
    prog = [e.data for e in rig.log.of("calibration.progress")]
    assert prog[-1]["completion_pct"] >= 85.0 and prog[-1]["spans"][2] >= 400
    assert any(p["step"] == 2 for p in prog)

    done = rig.log.wait("calibration.done")[0]
    rep = done.data["report"]
    assert done.data["onboard"] is True and rep["autosaved"] is True
    # the device's flash holds what it answered, and PAR,GET (the link's view) agrees
    page = rig.fw.flash.page
    assert page.magok and _params(rig.fw) != flash_before
    dev = rep["device"]
    assert (dev["xoff"], dev["yoff"], dev["zoff"]) == (page.xoff, page.yoff, page.zoff)
    assert rig.daemon.link.params is not None
    assert rig.daemon.link.params.values() == _params(rig.fw)
    # min/max offsets land near the unit's true ones (counts; min/max is cruder than a fit)
    true_counts = [2458.0 + 2560.0 * o for o in truth.mag.offset]
    assert np.allclose([page.xoff, page.yoff, page.zoff], true_counts, atol=40.0)
    # the host's own calibration is untouched (the result lives in the device)
    assert rig.daemon.engine.calibration == host_before


def test_onboard_magcal_at_hand_pace_is_ended_by_the_bridge(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    # The datasheet's two-step motion done by hand -- a level turn in about 15 s,
    # tipped 90 deg to the right in 3 s, a turn on the side in about 15 s, wobbling and
    # shaking as a hand does. The bridge ends MAGCAL itself: nobody accepts.
    lead = 10.0
    hand = HandOnboardCalRotation(turn_s=15.0, tip_s=3.0, yaw0=0.3, seed=7)
    motion = _lead_in(with_shake(hand, 0.05, seed=7), seconds=lead)
    rig = rigs(tmp_path, motion, settings=FAST, onboard=True, seed=7)
    truth = rig.fw.sensor.errors.true_calibration()
    ended_at: list[float] = []
    rig.daemon.events.subscribe(
        lambda e: ended_at.append(rig.clock()) if e.kind == "calibration.done" else None
    )
    assert rig.ctl.start_mag().result is Result.IN_PROGRESS
    rig.log.wait("calibration.instruction")
    epoch = rig.fw.motion_epoch
    assert epoch is not None and rig.clock() - epoch < lead  # started before the turn
    snap = rig.finished()
    assert snap.phase is Phase.SUCCEEDED, rig.log.kinds()
    assert not rig.fw.calibrating  # MAGCAL,END reached the device
    texts = [e.text for e in rig.log.of("calibration.instruction")]
    assert texts == [INSTRUCTION_LEVEL_TURN, INSTRUCTION_SIDE_TURN]
    # END went out near the end of the side turn: past 300 deg of it, within 3 s after it
    t_end = ended_at[0] - epoch - lead
    assert hand.side_turned_deg(t_end) >= 300.0 and t_end <= hand.duration + 3.0
    rep = rig.log.wait("calibration.done")[0].data["report"]
    assert rep["method"] == "device MAGCAL" and rep["autosaved"] is True
    page = rig.fw.flash.page
    assert page.magok
    # min/max near the unit's true offsets (counts): x and y as in the slow routine; z
    # looser -- on its side the 1100-count vertical field leaks into z through a few
    # degrees of the unit's misalignment and the hand's wobble (1100 sin 3 deg = 58)
    true_counts = [2458.0 + 2560.0 * o for o in truth.mag.offset]
    assert np.allclose([page.xoff, page.yoff], true_counts[:2], atol=40.0)
    assert abs(page.zoff - true_counts[2]) < 70.0
    assert rig.ctl.accept().result is Result.ACCEPTED  # nothing left to accept


@pytest.mark.integration
def test_onboard_range_failure_over_a_real_pty(tmp_path: Path) -> None:
    fw = make_firmware(11, motion=Still(), location=DEFAULT_LOCATION)
    link_path = tmp_path / "ttyGMR"
    with PtyCompass(fw, str(link_path)):
        cfg = make_config(tmp_path, device={"port": str(link_path)}, calibration={"onboard": True})
        daemon = build_daemon(cfg)
        log = EventLog()
        daemon.bridge.events.subscribe(log)
        daemon.start()
        try:
            assert daemon.link.wait_state(LinkState.STREAMING, DEADLINE_S)
            before = _params(fw)
            assert daemon.bridge.calibrator.start_mag().ok
            log.wait("calibration.instruction")  # the device is in MAGCAL now
            # the unit is never turned; the operator accepts anyway -> MAGCAL,END -> ERR,RANGE
            assert daemon.bridge.calibrator.accept().result is Result.IN_PROGRESS
            failed = log.wait("calibration.failed")[0]
            assert failed.data["report"]["device_error"] == "RANGE"
            assert "RANGE" in failed.data["reason"]
            assert daemon.bridge.calibrator.snapshot().phase is Phase.FAILED
            assert _params(fw) == before and not fw.calibrating
        finally:
            daemon.stop()


def test_onboard_cancel_aborts_the_device(tmp_path: Path, rigs: Callable[..., Rig]) -> None:
    rig = rigs(tmp_path, YawTurns(30.0), onboard=True)
    before = _params(rig.fw)
    assert rig.ctl.start_mag().ok
    rig.log.wait("calibration.instruction")
    assert rig.fw.calibrating
    assert rig.until(lambda: bool(rig.fw.truth[-1].frame.flags & Flags.CAL))
    assert rig.ctl.cancel().result is Result.ACCEPTED
    rig.log.wait("calibration.cancelled")
    assert rig.until(lambda: not rig.fw.calibrating), "MAGCAL,ABORT did not reach the device"
    assert rig.until(lambda: not rig.fw.truth[-1].frame.flags & Flags.CAL)
    assert _params(rig.fw) == before
    assert "calibration.failed" not in rig.log.kinds()


def test_onboard_level_acccal_success_and_motion_failure(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    still = rigs(tmp_path / "a", Still.from_deg(1.0, 2.0, 0.0), onboard=True)
    assert still.ctl.start_level().result is Result.IN_PROGRESS
    snap = still.finished(within=200.0)
    assert snap.phase is Phase.SUCCEEDED
    rep = still.log.wait("calibration.done")[0].data["report"]
    page = still.fw.flash.page
    assert page.accok and tuple(rep["device"][k] for k in ("gxoff", "gyoff", "gzoff")) == (
        page.gxoff,
        page.gyoff,
        page.gzoff,
    )
    assert rep["device_params"]["gzoff"] == page.gzoff  # refreshed with PAR,GET

    moving = rigs(tmp_path / "b", Tumble(1), onboard=True)
    before = _params(moving.fw)
    assert moving.ctl.start_level().ok
    snap = moving.finished(within=200.0)
    assert snap.phase is Phase.FAILED
    failed = moving.log.wait("calibration.failed")[0]
    assert failed.data["report"]["device_error"] == "MOTION"
    assert "moved" in failed.data["reason"]
    assert _params(moving.fw) == before
