"""Both calibration flows over MAVLink, end to end, on the simulated compass.

The ground station drives the flow exactly as Mission Planner / MAVProxy
(ArduPilot: DO_START_MAG_CAL -> MAG_CAL_PROGRESS -> MAG_CAL_REPORT ->
DO_ACCEPT_MAG_CAL) or QGroundControl on PX4 (PREFLIGHT_CALIBRATION and the
``[cal]`` STATUSTEXT lines) do, while the simulator tumbles or shows its faces
on a clock 20x real time. Truth is the simulator's physics.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import heading_errors, load_calibration, random_attitudes
from test_mavlink_rig import (
    ALT,
    LAT,
    LON,
    Gcs,
    M,
    Rig,
    wait_until,
)

from bridge.core.calibration import Calibration
from bridge.core.wmm import earth_field
from bridge.mavlink.commands import ONBOARD_REPORTS, REPORT_PERIOD_S
from bridge.protocol.gmr import ParamsFrame
from bridge.sim.firmware import Firmware
from bridge.sim.motion import (
    AttitudeList,
    Motion,
    OnboardCalRotation,
    Sequence,
    SixFaces,
    Still,
    Tumble,
)

pytestmark = pytest.mark.integration  # real sockets, processes or threads


FIELD = earth_field(LAT, LON, ALT)
ACCEPTED = M.MAV_RESULT_ACCEPTED
CAL_DEADLINE_S = 60.0  # real seconds for a whole calibration on the 20x clock


LEAD_S = 60.0  #: simulated seconds of level stillness before the motion (3 s real at 20x)


def lead_in(motion: Motion, seconds: float = LEAD_S) -> Motion:
    """Level and still first: the ground station starts just before the motion does."""
    return Sequence([AttitudeList([(0.0, 0.0, 0.0)], seconds, 0.0), motion])


def assert_heading_within_targets(fw: Firmware, cal: Calibration) -> None:
    """The engine's accuracy target: RMS and max error within 1.3x of what the true
    parameters of the unit reach, up to 60 deg of tilt; and far better than none."""
    truth = fw.sensor.errors.true_calibration()
    rng = np.random.default_rng(11)
    for tilt in (0.0, 30.0, 60.0):
        R = random_attitudes(rng, 800, tilt)
        err = heading_errors(fw, cal, R, seed=int(tilt) + 3, field=FIELD)
        floor = heading_errors(fw, truth, R, seed=int(tilt) + 3, field=FIELD)
        rms, frms = float(np.sqrt(np.mean(err**2))), float(np.sqrt(np.mean(floor**2)))
        assert rms <= 1.3 * frms, (tilt, rms, frms)
        assert float(np.max(np.abs(err))) <= 1.3 * float(np.max(np.abs(floor))), tilt
    err0 = heading_errors(fw, Calibration(), random_attitudes(rng, 300, 30.0), seed=99, field=FIELD)
    assert float(np.sqrt(np.mean(err0**2))) > 5.0


def texts(g: Gcs, until: str, timeout: float = CAL_DEADLINE_S) -> list[str]:
    """STATUSTEXT texts up to and including the first that starts with ``until``."""
    out: list[str] = []
    while True:
        m = g.wait("STATUSTEXT", timeout=timeout)
        out.append(m.text)
        if m.text.startswith(until):
            return out


# =====================================================================================
# ArduPilot flow (Mission Planner, MAVProxy magcal, QGroundControl on ArduPilot)
# =====================================================================================


def test_ardupilot_flow_end_to_end(tmp_path: Path, rigs: Callable[..., Rig]) -> None:
    rig = rigs(
        tmp_path, fast=True, motion=lead_in(Tumble(3, rate_dps=90.0, reference_ned=FIELD.ned_G))
    )
    g = rig.gcs("udp")
    truth = rig.fw.sensor.errors.true_calibration()
    before = rig.daemon.bridge.engine.calibration
    # mask 0 (all), no retry, no autosave, no delay
    assert g.command(M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 0, 0).result == ACCEPTED
    # meanwhile the HEARTBEAT says so (asked for now: the calibration is surely running)
    assert g.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HEARTBEAT).result == ACCEPTED
    hb = g.wait("HEARTBEAT", lambda m: m.system_status != M.MAV_STATE_ACTIVE)
    assert hb.system_status == M.MAV_STATE_CALIBRATING
    progress: list[Any] = []
    while True:
        m = g.wait(("MAG_CAL_PROGRESS", "MAG_CAL_REPORT"), timeout=CAL_DEADLINE_S)
        if m.get_type() == "MAG_CAL_REPORT":
            report = m
            break
        progress.append(m)
    assert len(progress) >= 3
    assert {p.cal_status for p in progress} <= {
        M.MAG_CAL_WAITING_TO_START,
        M.MAG_CAL_RUNNING_STEP_ONE,
        M.MAG_CAL_RUNNING_STEP_TWO,
    }
    assert M.MAG_CAL_RUNNING_STEP_TWO in {p.cal_status for p in progress}
    # the direction to turn to next: a unit vector, or zero once nothing is missing
    norms = [math.sqrt(p.direction_x**2 + p.direction_y**2 + p.direction_z**2) for p in progress]
    assert all(n == 0.0 or abs(n - 1.0) < 1e-5 for n in norms) and max(norms) > 0.99
    # ArduPilot's completion: step one fills a third, step two the rest. The ground station
    # is sent it about once a second of real time while the 20x clock runs the session
    # (10-50 % of it between two messages), so how far into step two the last one falls
    # is the phase of the two, not behaviour: what is checked is the split and the order.
    pct = [p.completion_pct for p in progress]
    assert pct == sorted(pct) and progress[-1].cal_status == M.MAG_CAL_RUNNING_STEP_TWO
    assert all(
        p.completion_pct <= 33 for p in progress if p.cal_status != M.MAG_CAL_RUNNING_STEP_TWO
    )
    assert all(
        p.completion_pct >= 33 for p in progress if p.cal_status == M.MAG_CAL_RUNNING_STEP_TWO
    )
    sections = sum(bin(b).count("1") for b in progress[-1].completion_mask)
    assert sections >= 40  # of ArduPilot's 80 sphere sections
    assert all(p.compass_id == 0 and p.cal_mask == 1 and p.attempt == 1 for p in progress)

    assert report.cal_status == M.MAG_CAL_SUCCESS and report.autosaved == 0
    assert 0.0 < report.fitness < 16.0
    true_ofs = -1000.0 * np.asarray(truth.mag.offset)
    assert np.allclose([report.ofs_x, report.ofs_y, report.ofs_z], true_ofs, atol=5.0)
    assert rig.daemon.bridge.engine.calibration == before  # nothing applied before accept
    # the report is repeated while it waits for the accept (a lost one is recovered)
    again = g.wait("MAG_CAL_REPORT", timeout=5.0)
    assert again.ofs_x == report.ofs_x

    assert g.command(M.MAV_CMD_DO_ACCEPT_MAG_CAL, 0).result == ACCEPTED
    accepted = rig.daemon.bridge.engine.calibration
    assert accepted != before
    st = g.wait("STATUSTEXT", lambda m: m.text.startswith("Calibration accepted"))
    assert st.text == "Calibration accepted and saved"
    # the new calibration shows as COMPASS_* parameters, to every ground station
    ofs_x = g.wait("PARAM_VALUE", lambda m: m.param_id == "COMPASS_OFS_X")
    assert ofs_x.param_value == pytest.approx(report.ofs_x, abs=1e-3)
    assert load_calibration(str(tmp_path / "state"))[0] == accepted  # persisted
    # ... and in the compass's flash (offsets and gains: what its model holds)
    g.wait("STATUSTEXT", lambda m: m.text == "Compass flash updated")
    page = rig.fw.flash.page
    assert page.magok
    assert page.xoff == pytest.approx(2458.0 + 2560.0 * accepted.mag.offset[0], abs=0.06)
    assert_heading_within_targets(rig.fw, accepted)


def test_cancel_and_fixed_yaw(tmp_path: Path, rigs: Callable[..., Rig]) -> None:
    yaw = 40.0
    rig = rigs(tmp_path, motion=Still.from_deg(3.0, -5.0, yaw))
    g = rig.gcs("tcp")
    assert g.command(M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 0, 0).result == ACCEPTED
    g.wait("MAG_CAL_PROGRESS")
    # a second start while one runs: not now
    assert g.command(M.MAV_CMD_DO_START_MAG_CAL, 0).result == M.MAV_RESULT_TEMPORARILY_REJECTED
    assert g.command(M.MAV_CMD_DO_CANCEL_MAG_CAL, 0).result == ACCEPTED
    g.wait("STATUSTEXT", lambda m: m.text == "Calibration cancelled")
    assert wait_until(lambda: not rig.daemon.bridge.calibrator.snapshot().running)
    # a mask without compass 0: not ours
    assert g.command(M.MAV_CMD_DO_START_MAG_CAL, 2).result == M.MAV_RESULT_FAILED

    # FIXED_MAG_CAL_YAW: the unit lies still at a known true yaw; the offsets make it so
    ack = g.command(M.MAV_CMD_FIXED_MAG_CAL_YAW, yaw, 0, 0, 0)
    assert ack.result == ACCEPTED
    rep = g.wait("MAG_CAL_REPORT")
    assert rep.cal_status == M.MAG_CAL_SUCCESS and rep.autosaved == 1
    samples = []
    for _ in range(10):
        f = rig.fw.truth[-1].frame
        samples.append(rig.daemon.bridge.engine.solve_counts(f.mx, f.my, f.mz, f.ax, f.ay, f.az))
    true_hdg = [s.heading_true_deg for s in samples]
    assert all(h is not None and abs((h - yaw + 180) % 360 - 180) < 1.0 for h in true_hdg)
    assert g.command(M.MAV_CMD_FIXED_MAG_CAL_YAW, math.nan).result == M.MAV_RESULT_FAILED


def test_a_lost_report_is_repeated_until_accepted_cancelled_or_restarted(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    """ArduPilot sends MAG_CAL_REPORT as long as a result waits (send_mag_cal_report while
    the calibrator's status is SUCCESS or FAILED); a ground station that missed the first
    one -- here one that only starts listening after it -- still gets it, about once a
    second, until DO_ACCEPT_MAG_CAL, DO_CANCEL_MAG_CAL or a new start answers it."""
    rig = rigs(tmp_path, motion=Still.from_deg(3.0, -5.0, 40.0))
    first = rig.gcs("udp")
    # a repetition is due within a period and the telemetry thread's half-second tick
    silent = 1.7 * REPORT_PERIOD_S

    def a_repeated_report(yaw: float, g: Gcs) -> Any:
        first.flush()
        assert first.command(M.MAV_CMD_FIXED_MAG_CAL_YAW, yaw, 0, 0, 0).result == ACCEPTED
        rep = first.wait("MAG_CAL_REPORT")
        g.flush()
        again = g.wait("MAG_CAL_REPORT", timeout=silent)
        assert again.cal_status == M.MAG_CAL_SUCCESS
        assert (again.ofs_x, again.ofs_y, again.ofs_z) == (rep.ofs_x, rep.ofs_y, rep.ofs_z)
        return again

    # the first report goes out before this ground station listens: it is lost to it
    assert first.command(M.MAV_CMD_FIXED_MAG_CAL_YAW, 40.0, 0, 0, 0).result == ACCEPTED
    assert first.wait("MAG_CAL_REPORT").cal_status == M.MAG_CAL_SUCCESS
    late = rig.gcs("tcp")
    again = late.wait("MAG_CAL_REPORT", timeout=2 * silent)
    assert again.cal_status == M.MAG_CAL_SUCCESS
    assert late.command(M.MAV_CMD_DO_ACCEPT_MAG_CAL, 0).result == ACCEPTED
    late.flush()
    late.nothing("MAG_CAL_REPORT", None, silent)

    a_repeated_report(41.0, late)
    assert late.command(M.MAV_CMD_DO_CANCEL_MAG_CAL, 0).result == ACCEPTED
    late.flush()
    late.nothing("MAG_CAL_REPORT", None, silent)

    a_repeated_report(40.0, late)
    assert late.command(M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 0, 0).result == ACCEPTED
    late.wait("MAG_CAL_PROGRESS")  # the new calibration runs (the unit lies still)
    late.flush()
    late.nothing("MAG_CAL_REPORT", None, silent)
    assert late.command(M.MAV_CMD_DO_CANCEL_MAG_CAL, 0).result == ACCEPTED


# =====================================================================================
# PX4 flow (QGroundControl on PX4): PREFLIGHT_CALIBRATION and the [cal] lines
# =====================================================================================

PROGRESS_RE = re.compile(r"^\[cal\] progress <(\d+)>$")


def test_px4_flow_magnetometer(tmp_path: Path, rigs: Callable[..., Rig]) -> None:
    rig = rigs(
        tmp_path, fast=True, motion=lead_in(Tumble(5, rate_dps=90.0, reference_ned=FIELD.ned_G))
    )
    g = rig.gcs("udp")
    before = rig.daemon.bridge.engine.calibration
    assert g.command(M.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 1).result == ACCEPTED
    lines = [t for t in texts(g, "[cal] calibration done") if t.startswith("[cal]")]
    assert lines[0] == "[cal] calibration started: 2 mag"
    assert lines[-1] == "[cal] calibration done: mag"
    pct = [int(m.group(1)) for t in lines if (m := PROGRESS_RE.match(t))]
    assert len(pct) >= 3 and pct == sorted(pct) and len(set(pct)) == len(pct)
    assert all(len(t) <= 50 for t in lines)
    # PX4 has no accept step: the result is in use and saved
    assert wait_until(lambda: rig.daemon.bridge.engine.calibration != before)
    assert wait_until(
        lambda: load_calibration(str(tmp_path / "state"))[0] == rig.daemon.bridge.engine.calibration
    )
    assert_heading_within_targets(rig.fw, rig.daemon.bridge.engine.calibration)


def test_px4_flow_six_faces_and_cancel(tmp_path: Path, rigs: Callable[..., Rig]) -> None:
    rig = rigs(tmp_path, fast=True, seed=8, motion=lead_in(SixFaces(dwell_s=6.0, transition_s=3.0)))
    g = rig.gcs("tcp")
    rig.wait_motion_time(LEAD_S - 3.0)
    assert g.command(M.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 0, 0, 0, 1).result == ACCEPTED
    lines = [t for t in texts(g, "[cal] calibration done") if t.startswith("[cal]")]
    assert lines[0] == "[cal] calibration started: 2 accel"
    order = ["down", "left", "right", "front", "back", "up"]
    detected = [t.split()[1] for t in lines if t.endswith("orientation detected")]
    done = [t.split()[1] for t in lines if t.endswith("side done, rotate to a different side")]
    assert detected == order and done == order
    assert lines[-1] == "[cal] calibration done: accel"
    assert wait_until(lambda: rig.daemon.bridge.engine.calibration.accel != Calibration().accel)

    # all-zero PREFLIGHT_CALIBRATION cancels a running calibration (QGC's cancel button)
    assert g.command(M.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 0, 0, 0, 1).result == ACCEPTED
    g.wait("STATUSTEXT", lambda m: m.text == "[cal] calibration started: 2 accel")
    assert g.command(M.MAV_CMD_PREFLIGHT_CALIBRATION).result == ACCEPTED
    g.wait("STATUSTEXT", lambda m: m.text == "[cal] calibration cancelled")


def test_px4_flow_level(tmp_path: Path, rigs: Callable[..., Rig]) -> None:
    rig = rigs(tmp_path, motion=Still.from_deg(1.5, -2.0, 10.0))
    g = rig.gcs("udp")
    assert g.command(M.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 0, 0, 0, 2).result == ACCEPTED
    lines = [t for t in texts(g, "[cal] calibration done", timeout=20.0) if t.startswith("[cal]")]
    assert lines[0] == "[cal] calibration started: 2 level"
    assert lines[-1] == "[cal] calibration done: level"
    g.flush()
    att = g.wait("ATTITUDE")
    assert abs(math.degrees(att.roll)) < 0.3 and abs(math.degrees(att.pitch)) < 0.3


# =====================================================================================
# the compass's own routines: BRG_CAL_ONBOARD = 1
# =====================================================================================


def test_onboard_route_ends_with_the_compass_flash_updated(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    motion = lead_in(OnboardCalRotation(turn_s=20.0, tip_s=3.0, yaw0=0.3))
    rig = rigs(tmp_path, fast=True, seed=9, motion=motion)
    g = rig.gcs("udp")
    g.set_param("BRG_CAL_ONBOARD", 1.0, M.MAV_PARAM_TYPE_INT8)
    assert rig.daemon.bridge.calibrator.onboard is True
    flash_before = rig.fw.flash.page
    host_before = rig.daemon.bridge.engine.calibration
    rig.wait_motion_time(LEAD_S - 3.0)
    assert g.command(M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 0, 0).result == ACCEPTED
    said = texts(g, "Calibration done")
    assert "Turn the compass one full turn, level" in said
    assert "Tip it 90 deg onto its side, turn one full turn" in said
    assert said.index("Turn the compass one full turn, level") < said.index(
        "Tip it 90 deg onto its side, turn one full turn"
    )
    rep = g.wait("MAG_CAL_REPORT")
    assert rep.cal_status == M.MAG_CAL_SUCCESS and rep.autosaved == 1
    page = rig.fw.flash.page
    assert page.magok and not flash_before.magok
    assert (page.xoff, page.yoff, page.zoff) != (
        flash_before.xoff,
        flash_before.yoff,
        flash_before.zoff,
    )
    truth = rig.fw.sensor.errors.true_calibration()
    true_counts = [2458.0 + 2560.0 * o for o in truth.mag.offset]
    # min/max (the device's method) is cruder than a fit: near the unit's true offsets
    assert np.allclose([page.xoff, page.yoff, page.zoff], true_counts, atol=40.0)
    # the report carries the device's answer in ArduPilot's terms (mG added to the field)
    assert rep.ofs_x == pytest.approx(-1000.0 * (page.xoff - 2458.0) / 2560.0, abs=1e-3)
    assert rep.diag_y == pytest.approx(page.ky, abs=1e-4)
    # the device's own calibration: the host's stays as it was
    assert rig.daemon.bridge.engine.calibration == host_before
    assert not rig.fw.calibrating
    # In the compass's flash already, nothing to accept: the report is not repeated forever
    # (it once was, at 1 Hz), a few times only, in case one datagram was lost.
    reports = [m for m in g.collect(5.0) if m.get_type() == "MAG_CAL_REPORT"]
    assert len(reports) <= ONBOARD_REPORTS - 1
    g.nothing("MAG_CAL_REPORT", None, 2.5)


def test_onboard_accept_too_early_fails_with_range(
    tmp_path: Path, rigs: Callable[..., Rig]
) -> None:
    rig = rigs(tmp_path, motion=Still.from_deg(0.0, 0.0, 0.0), calibration={"onboard": True})
    g = rig.gcs("tcp")
    assert g.param("BRG_CAL_ONBOARD").param_value == 1.0  # the configuration's default
    before = rig.fw.flash.page
    assert g.command(M.MAV_CMD_DO_START_MAG_CAL, 0).result == ACCEPTED
    g.wait("STATUSTEXT", lambda m: m.text == "Turn the compass one full turn, level")
    assert rig.fw.calibrating
    # accept = MAGCAL,END now: long work, IN_PROGRESS first, the device's answer last
    ack = g.command(M.MAV_CMD_DO_ACCEPT_MAG_CAL, 0)
    assert ack.result == M.MAV_RESULT_IN_PROGRESS
    final = g.wait("COMMAND_ACK", lambda m: m.command == M.MAV_CMD_DO_ACCEPT_MAG_CAL)
    assert final.result == M.MAV_RESULT_FAILED
    rep = g.wait("MAG_CAL_REPORT")
    assert rep.cal_status == M.MAG_CAL_FAILED
    # the whole reason, in chunks when it is longer than one STATUSTEXT
    first = g.wait("STATUSTEXT", lambda m: m.text.startswith("Calibration failed"))
    text = first.text
    if first.id:
        while len(text) % 50 == 0:
            text += g.wait("STATUSTEXT", lambda m: m.id == first.id).text
    assert text == "Calibration failed: MAGCAL,END: too little rotation (RANGE)"
    assert rig.fw.flash.page == before and not rig.fw.calibrating
    assert isinstance(rig.daemon.link.params, ParamsFrame)


def test_onboard_level_goes_to_the_device_acccal(tmp_path: Path, rigs: Callable[..., Rig]) -> None:
    rig = rigs(tmp_path, motion=Still.from_deg(1.0, 2.0, 0.0), calibration={"onboard": True})
    g = rig.gcs("udp")
    assert not rig.fw.flash.page.accok
    assert g.command(M.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 0, 0, 0, 2).result == ACCEPTED
    lines = [t for t in texts(g, "[cal] calibration done", timeout=20.0) if t.startswith("[cal]")]
    assert lines[0] == "[cal] calibration started: 2 level"
    assert lines[-1] == "[cal] calibration done: level"
    page = rig.fw.flash.page
    assert page.accok  # the device averaged its level reference into its own flash
    # it holds the unit's own reading at rest (the device averages its accelerometer)
    recent = list(rig.fw.truth)[-20:]
    for axis, off in (("ax", page.gxoff), ("ay", page.gyoff), ("az", page.gzoff)):
        assert off == pytest.approx(np.mean([getattr(t.frame, axis) for t in recent]), abs=3.0)
