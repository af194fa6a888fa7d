"""Calibrations interrupted, refused or not saved: the device is left as found, nothing
implausible becomes a calibration, and what could not be saved is saved once it can be.

The application on the simulated compass, in memory (tests/harness.py, the rigs of
test_calibrator.py): a cable pulled (the device still powered, as a unit behind a
USB-serial adapter), a compass slower than its datasheet, storage that fails.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from helpers import load_calibration
from test_calibrator import (
    LAT,
    LON,
    Rig,
    make_config,
    rigs,  # noqa: F401 - the fixture
)

from bridge.app.calibration.keeper import RETRY_S
from bridge.calibration.sessions import Phase, Result
from bridge.core.calibration import AffineCalibration, Calibration
from bridge.sim.motion import Still, YawTurns
from bridge.systemd.status import calibration_words


def onboard_rig(tmp_path: Path, rigs: Callable[..., Rig]) -> Rig:  # noqa: F811
    """On-board calibrations routed; a short stale_after, as a pulled cable shows quickly."""
    cfg = make_config(tmp_path, device={"stale_after": 1.0}, calibration={"onboard": True})
    rig = rigs(tmp_path, YawTurns(10.0), seed=8, cfg=cfg)
    assert rig.daemon.link.params is not None
    return rig


def test_unplugged_during_an_onboard_magcal_the_device_is_aborted_on_return(
    tmp_path: Path,
    rigs: Callable[..., Rig],  # noqa: F811
) -> None:
    rig = onboard_rig(tmp_path, rigs)
    fw, ctl = rig.fw, rig.ctl
    assert ctl.start_mag().result is Result.IN_PROGRESS
    assert rig.until(lambda: fw.calibrating and ctl.snapshot().running)
    rig.h.unplug()  # the cable, not the power: it stays in MAGCAL
    rig.h.at(4.0, rig.h.replug)
    # No data: the session ended; its ABORT could not be heard.
    assert rig.wait(lambda s: s.phase is Phase.FAILED).phase is Phase.FAILED
    assert fw.calibrating
    # Back: its frames carry the CAL flag with no calibration of ours running -> aborted.
    assert rig.until(lambda: not fw.calibrating, 30.0)
    assert rig.h.counters.reconnects == 1
    n = fw.frames_sent
    assert rig.until(lambda: fw.frames_sent >= n + 10)
    assert not fw.flags() & 1  # every frame from now on without CAL
    assert ctl.snapshot().phase is Phase.FAILED


def test_a_left_over_calibration_mode_is_aborted_running_and_at_exit(
    tmp_path: Path,
    rigs: Callable[..., Rig],  # noqa: F811
) -> None:
    rig = onboard_rig(tmp_path, rigs)
    fw = rig.fw
    # A MAGCAL nobody runs (a crash of the last run, another tool): aborted within seconds.
    rig.daemon.link.command("MAGCAL", "START")
    assert fw.calibrating
    assert rig.until(lambda: not fw.calibrating, 10.0)
    # Again, and the bridge stops at once: it aborts the routine on its way out.
    rig.daemon.link.command("MAGCAL", "START")
    assert fw.calibrating
    rig.daemon.stop()
    assert not fw.calibrating


def test_a_slow_compass_fails_the_onboard_magcal_cleanly_and_is_left_as_found(
    tmp_path: Path,
    rigs: Callable[..., Rig],  # noqa: F811
) -> None:
    rig = onboard_rig(tmp_path, rigs)
    fw, ctl = rig.fw, rig.ctl
    fw.answer_delay_s = 0.6  # three times its 200 ms
    assert ctl.start_mag().result is Result.IN_PROGRESS
    snap = rig.wait(lambda s: s.phase is Phase.FAILED)
    assert snap.report is not None
    assert "too late" in snap.report.reason, snap.report.reason
    assert rig.until(lambda: not fw.calibrating, 10.0)  # its START ran once, and was undone
    c = rig.h.counters
    assert c.command_retries == 0 and c.device_resets == 0


def test_fixed_yaw_refuses_implausible_values(
    tmp_path: Path,
    rigs: Callable[..., Rig],  # noqa: F811
) -> None:
    rig = rigs(tmp_path, Still.from_deg(0.0, 0.0, 30.0))
    assert rig.until(lambda: len(rig.fw.truth) > 15)
    before = rig.daemon.engine.calibration
    for yaw, lat, lon, why in [
        (1e9, None, None, "bad yaw"),
        (10**400, None, None, "bad yaw"),
        (True, None, None, "bad yaw"),
        (30.0, 91.0, LON, "bad position"),
        (30.0, -89.9, LON, "implausible"),  # Antarctica, for a unit set up at Zurich
        (30.0, LAT, 10**400, "bad position"),
    ]:
        out = rig.ctl.fixed_yaw(yaw, latitude_deg=lat, longitude_deg=lon)
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
    rig = rigs(tmp_path, Still(), cfg=cfg)
    cal = Calibration(mag=AffineCalibration.from_arrays([0.01, -0.02, 0.03], np.eye(3)))
    out = rig.ctl.apply_calibration(cal, source="test")
    assert out.result is Result.ACCEPTED and "not saved" in out.message
    assert not rig.ctl.snapshot().calibration_saved
    rig.h.run_for(RETRY_S + 1.0)  # still unwritable: still not saved, and says so
    assert not rig.ctl.snapshot().calibration_saved and not rig.log.of("calibration.saved")
    blocker.unlink()  # space is back
    rig.log.wait("calibration.saved", timeout=RETRY_S + 5.0)
    assert rig.ctl.snapshot().calibration_saved
    stored, _ = load_calibration(str(blocker / "state"))
    assert stored == cal and math.isclose(stored.mag.offset[2], 0.03)


def test_a_paced_compass_set_that_storage_refuses_is_told_and_saved_once_it_can_be(
    tmp_path: Path,
    rigs: Callable[..., Rig],  # noqa: F811
) -> None:
    """COMPASS_* values set within a second of the last save are saved by the worker when
    the second is over: if storage refuses that save, it is said (calibration.storage_error),
    as a refused save at once is, and it is saved once storage takes it again."""
    rig = rigs(tmp_path, Still())
    state = tmp_path / "state"

    def offsets(x: float) -> Calibration:
        return Calibration(mag=AffineCalibration.from_arrays([x, 0.0, 0.0], np.eye(3)))

    out = rig.ctl.apply_calibration(offsets(0.01), source="parameters", paced=True)
    assert "and saved" in out.message and rig.ctl.snapshot().calibration_saved

    def words() -> str:
        return calibration_words(rig.ctl.snapshot(), calibrated=True, parameters_error="")

    assert words() == "parameters"
    out = rig.ctl.apply_calibration(offsets(0.02), source="parameters", paced=True)
    assert out.message == "calibration applied (saved within a second)"
    assert not rig.ctl.snapshot().calibration_saved and not rig.log.of("calibration.storage_error")
    assert rig.ctl.snapshot().calibration_saving and words() == "parameters, saving"
    for f in state.iterdir():  # storage goes: a file where the state directory was
        f.unlink()
    state.rmdir()
    state.write_text("not a directory\n")
    rig.log.wait("calibration.storage_error", timeout=3.0)  # the paced save, refused: said
    assert not rig.ctl.snapshot().calibration_saved and not rig.ctl.snapshot().calibration_saving
    assert words() == "parameters, NOT SAVED (storage error)"
    state.unlink()  # storage is back
    rig.log.wait("calibration.saved", timeout=RETRY_S + 5.0)
    assert rig.ctl.snapshot().calibration_saved and words() == "parameters"
    stored, _ = load_calibration(str(state))
    assert stored == offsets(0.02)
