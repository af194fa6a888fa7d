"""Calibrations interrupted, refused or not saved: the device is left as found, nothing
implausible becomes a calibration, and what could not be saved is saved once it can be.

A real daemon on the simulated compass: served on a real pty where a cable is pulled
(device still powered, as a unit behind a USB-serial adapter), in process otherwise.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from helpers import load_calibration
from test_calibrator import (
    LAT,
    LON,
    EventLog,
    Rig,
    _wait,
    make_config,
    rigs,  # noqa: F401 - the fixture
)

from bridge.app.calibration.keeper import RETRY_S
from bridge.calibration.model import AffineCalibration, Calibration
from bridge.calibration.sessions import Phase, Result
from bridge.daemon import Daemon, build_daemon
from bridge.link.serial_link import LinkState
from bridge.sim.firmware import make_firmware
from bridge.sim.motion import Still, YawTurns
from bridge.sim.physics import DEFAULT_LOCATION
from bridge.sim.pty import PtyCompass

pytestmark = pytest.mark.integration

DEADLINE_S = 30.0


@pytest.fixture
def pty_rig(tmp_path: Path) -> Iterator[tuple[Daemon, PtyCompass, EventLog]]:
    """A daemon reading the simulated compass on a real pty, on-board calibrations routed."""
    fw = make_firmware(8, motion=YawTurns(10.0), location=DEFAULT_LOCATION)
    sim = PtyCompass(fw, tmp_path / "compass").start()
    cfg = make_config(
        tmp_path,
        device={"port": str(sim.link_path), "stale_after": 1.0},
        calibration={"onboard": True},
    )
    daemon = build_daemon(cfg)
    log = EventLog()
    daemon.bridge.events.subscribe(log)
    daemon.start()
    try:
        assert daemon.link.wait_state(LinkState.STREAMING, DEADLINE_S)
        assert _wait(lambda: daemon.link.params is not None)
        yield daemon, sim, log
    finally:
        daemon.stop()
        sim.stop()


def test_unplugged_during_an_onboard_magcal_the_device_is_aborted_on_return(
    pty_rig: tuple[Daemon, PtyCompass, EventLog],
) -> None:
    daemon, sim, _log = pty_rig
    fw, ctl = sim.firmware, daemon.bridge.calibrator
    assert ctl.start_mag().result is Result.IN_PROGRESS
    assert _wait(lambda: fw.calibrating and ctl.snapshot().running)
    sim.unplug(4.0, power_cycle=False)  # the cable, not the power: it stays in MAGCAL
    snap = ctl.wait_for(lambda s: s.phase is Phase.FAILED, DEADLINE_S)
    assert snap is not None  # no data: the session ended; its ABORT could not be heard
    assert fw.calibrating
    assert sim.wait_plugged(DEADLINE_S) is not None
    # Back: its frames carry the CAL flag with no calibration of ours running -> aborted.
    assert _wait(lambda: not fw.calibrating, DEADLINE_S)
    n = fw.frames_sent
    assert _wait(lambda: fw.frames_sent >= n + 10)
    assert not fw.flags() & 1  # every frame from now on without CAL
    assert ctl.snapshot().phase is Phase.FAILED


def test_a_left_over_calibration_mode_is_aborted_running_and_at_exit(
    pty_rig: tuple[Daemon, PtyCompass, EventLog],
) -> None:
    daemon, sim, _log = pty_rig
    fw = sim.firmware
    # A MAGCAL nobody runs (a crash of the last run, another tool): aborted within seconds.
    daemon.link.command("MAGCAL", "START")
    assert fw.calibrating
    assert _wait(lambda: not fw.calibrating, 10.0)
    # Again, and the bridge stops at once: it aborts the routine on its way out.
    daemon.link.command("MAGCAL", "START")
    assert fw.calibrating
    daemon.stop()
    assert not fw.calibrating


def test_a_slow_compass_fails_the_onboard_magcal_cleanly_and_is_left_as_found(
    pty_rig: tuple[Daemon, PtyCompass, EventLog],
) -> None:
    daemon, sim, _log = pty_rig
    fw, ctl = sim.firmware, daemon.bridge.calibrator
    fw.answer_delay_s = 0.6  # three times its 200 ms
    assert ctl.start_mag().result is Result.IN_PROGRESS
    snap = ctl.wait_for(lambda s: s.phase is Phase.FAILED, DEADLINE_S)
    assert snap is not None and snap.report is not None
    assert "too late" in snap.report.reason, snap.report.reason
    assert _wait(lambda: not fw.calibrating, 10.0)  # its START ran once, and was undone
    c = daemon.link.counters
    assert c.command_retries == 0 and c.device_resets == 0


def test_fixed_yaw_refuses_implausible_values(
    tmp_path: Path,
    rigs: Callable[..., Rig],  # noqa: F811
) -> None:
    rig = rigs(tmp_path, Still.from_deg(0.0, 0.0, 30.0), fast=False)
    assert _wait(lambda: len(rig.fw.truth) > 15)
    before = rig.daemon.bridge.engine.calibration
    for yaw, lat, lon, why in [
        (1e9, None, None, "bad yaw"),
        (10**400, None, None, "bad yaw"),
        (True, None, None, "bad yaw"),
        (30.0, 91.0, LON, "bad position"),
        (30.0, -89.9, LON, "implausible"),  # Antarctica, for a unit set up at Zurich
        (30.0, LAT, 10**400, "bad position"),
    ]:
        out = rig.ctl.fixed_yaw(yaw, latitude_deg=lat, longitude_deg=lon)  # type: ignore[arg-type]
        assert out.result is Result.FAILED and why in out.message, (yaw, lat, out)
        assert len(out.message) < 300
    assert rig.daemon.bridge.engine.calibration == before  # nothing applied
    near = rig.ctl.fixed_yaw(30.0, latitude_deg=LAT + 0.2, longitude_deg=LON - 0.3)
    assert near.result is Result.ACCEPTED, near  # a plausible one still works


def test_a_calibration_not_saved_is_saved_once_storage_is_back(
    tmp_path: Path,
    rigs: Callable[..., Rig],  # noqa: F811
) -> None:
    blocker = tmp_path / "blocked"
    blocker.write_text("a file where the state directory's parent should be\n")
    cfg = make_config(tmp_path, storage={"dir": str(blocker / "state")})
    rig = rigs(tmp_path, Still(), fast=False, cfg=cfg)
    cal = Calibration(mag=AffineCalibration.from_arrays([0.01, -0.02, 0.03], np.eye(3)))
    out = rig.ctl.apply_calibration(cal, source="test")
    assert out.result is Result.ACCEPTED and "not saved" in out.message
    assert not rig.ctl.snapshot().calibration_saved
    time.sleep(RETRY_S + 1.0)  # still unwritable: still not saved, and says so
    assert not rig.ctl.snapshot().calibration_saved and not rig.log.of("calibration.saved")
    blocker.unlink()  # space is back
    rig.log.wait("calibration.saved", timeout=RETRY_S + 5.0)
    assert rig.ctl.snapshot().calibration_saved
    stored, _ = load_calibration(str(blocker / "state"))
    assert stored == cal and math.isclose(stored.mag.offset[2], 0.03)
