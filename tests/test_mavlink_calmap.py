"""The calibrator's neutral state, reports and texts in MAVLink's terms (pure)."""

from __future__ import annotations

import math
from typing import Any

import pytest
from test_mavlink_telemetry import decode, wire_text

from bridge.calibration.fits.sanity import MagCalStatus
from bridge.calibration.model import ArduPilotView
from bridge.calibration.sessions import CalibratorSnapshot, Failure, Mode, Phase, SessionReport
from bridge.calibration.sessions.report import DeviceOutcome, FitQuality
from bridge.events import Event, Severity
from bridge.mavlink import calmap
from bridge.mavlink.commands import ONBOARD_REPORTS, TEXT_BURST, TEXT_RATE_HZ, CalibrationRelay
from bridge.mavlink.dialect import mavlink as M  # noqa: N812 - the generated module, short


@pytest.mark.parametrize(
    ("phase", "step", "failure", "status"),
    [
        (Phase.IDLE, 0, None, MagCalStatus.MAG_CAL_NOT_STARTED),
        (Phase.CANCELLED, 1, None, MagCalStatus.MAG_CAL_NOT_STARTED),
        (Phase.WAITING, 1, None, MagCalStatus.MAG_CAL_WAITING_TO_START),
        (Phase.COLLECTING, 1, None, MagCalStatus.MAG_CAL_RUNNING_STEP_ONE),
        (Phase.COLLECTING, 2, None, MagCalStatus.MAG_CAL_RUNNING_STEP_TWO),
        (Phase.FITTING, 2, None, MagCalStatus.MAG_CAL_RUNNING_STEP_TWO),
        (Phase.SUCCEEDED, 2, None, MagCalStatus.MAG_CAL_SUCCESS),
        (Phase.FAILED, 1, Failure.FAILED, MagCalStatus.MAG_CAL_FAILED),
        (Phase.FAILED, 2, Failure.ORIENTATION, MagCalStatus.MAG_CAL_FAILED_ORIENTATION),
        (Phase.FAILED, 1, Failure.RADIUS, MagCalStatus.MAG_CAL_FAILED_RADIUS),
        (Phase.FAILED, 2, Failure.OFFSETS, MagCalStatus.MAG_CAL_FAILED_OFFSETS),
        (Phase.FAILED, 2, Failure.SCALING, MagCalStatus.MAG_CAL_FAILED_DIAG_SCALING),
        (Phase.FAILED, 2, Failure.RESIDUALS, MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH),
    ],
)
def test_phases_map_to_mag_cal_status(
    phase: Phase, step: int, failure: Failure | None, status: MagCalStatus
) -> None:
    assert calmap.mag_cal_status(phase, step, failure) is status
    assert int(status) == getattr(M, status.name)  # pymavlink's wire code


def test_a_report_becomes_mag_cal_report() -> None:
    rep = SessionReport(
        Mode.MAG,
        "ellipsoid_aligned",
        failure=Failure.RESIDUALS,
        reason="fitness 20.00 mG above COMPASS_CAL_FIT 16.0",
        mag=ArduPilotView(
            (-100.0, 200.0, -50.0), (1.1, 0.9, 1.0), (0.01, -0.02, 0.0), 1.03, (0.0, 0.0, 0.035)
        ),
        fit=FitQuality(fitness_mG=20.0, orientation_confidence=7.5),
    )
    r = calmap.report_figures(rep)
    # code 10 is newer than many ground stations: sent as MAG_CAL_FAILED, as ArduPilot does
    assert r.cal_status == M.MAG_CAL_FAILED and calmap.report_status(rep) == 10
    m = rep.mag
    assert m is not None
    assert (r.fitness, r.ofs, r.diag, r.offdiag) == (20.0, m.ofs_mG, m.diag, m.offdiag)
    assert (r.scale_factor, r.orientation_confidence, r.autosaved) == (1.03, 7.5, False)
    assert r.old_orientation == r.new_orientation == 0  # ROTATION_NONE: never changed
    # a device's MAGCAL: its offsets and gains, no fitness (0 on the wire)
    dev = SessionReport(
        Mode.ONBOARD_MAG,
        "device MAGCAL",
        autosaved=True,
        mag=ArduPilotView((12.0, -3.0, 4.0), (1.0, 0.95, 1.02)),
        device=DeviceOutcome({"xoff": 2427.3}),
    )
    rd = calmap.report_figures(dev)
    assert rd.cal_status == M.MAG_CAL_SUCCESS and rd.autosaved and math.isnan(rd.fitness)


def test_only_magnetometer_sessions_send_mag_cal_report() -> None:
    level = SessionReport(Mode.LEVEL, "level_trim", autosaved=True)
    assert calmap.event_report({"mode": "level", "report": level.to_dict()}) is None
    mag = SessionReport(
        Mode.FIXED_YAW, "fixed_yaw", autosaved=True, mag=ArduPilotView((1.0, 2.0, 3.0))
    )
    r = calmap.event_report({"mode": "fixed_yaw", "report": mag.to_dict()})
    assert r is not None and r.ofs == (1.0, 2.0, 3.0) and r.cal_status == M.MAG_CAL_SUCCESS
    assert calmap.event_report({"mode": "mag", "report": {"mode": "nonsense"}}) is None


def _failed(reason: str) -> Event:
    rep = SessionReport(Mode.ONBOARD_MAG, "onboard_mag", failure=Failure.FAILED, reason=reason)
    data: dict[str, Any] = {
        "mode": "onboard_mag",
        "sensor": "mag",
        "failure": "failed",
        "reason": reason,
        "report": rep.to_dict(),
    }
    return Event("calibration.failed", f"Calibration failed: {reason}", Severity.ERROR, data)


def test_whole_sentences_go_out_chunked_and_px4_lines_stay_single() -> None:
    reason = (
        "MAGCAL,END: too little rotation (RANGE) -- turn it one full turn, level and on its side"
    )
    event = _failed(reason)
    assert len(event.text) > 50  # the calibrator does not cut it
    # ArduPilot flow: MAG_CAL_REPORT, then the sentence in spec chunks that join back whole
    relay = CalibrationRelay()
    relay.begin("ardupilot")
    packets = relay.packets(event)
    assert packets[0].get_msgId() == M.MAVLINK_MSG_ID_MAG_CAL_REPORT
    texts = [p for p in packets if p.get_msgId() == M.MAVLINK_MSG_ID_STATUSTEXT]
    chunks = [wire_text(p) for p in texts]
    assert len(chunks) >= 2 and all(len(c) == 50 for c in chunks[:-1]) and len(chunks[-1]) < 50
    assert b"".join(chunks).decode() == event.text
    assert len({decode(p).id for p in texts}) == 1
    # PX4 flow: the [cal] line QGroundControl parses is one message, cut; the whole follows
    relay.begin("px4")
    packets = relay.packets(event)
    lines = [decode(p) for p in packets if p.get_msgId() == M.MAVLINK_MSG_ID_STATUSTEXT]
    assert lines[0].id == 0 and lines[0].text.startswith("[cal] calibration failed: MAGCAL,END")
    assert len(lines[0].text.encode()) == 50
    rest = b"".join(wire_text(p) for p in packets[2:]).decode()
    assert rest == event.text
    # a cut never leaves half a UTF-8 character
    assert calmap.cal_line("é" * 40).encode().decode() == "[cal] " + "é" * 22


def test_px4_lines_for_each_event() -> None:
    def line(kind: str, text: str = "", **data: Any) -> str | None:
        return calmap.px4_text(Event(kind, text, Severity.INFO, data))

    assert line("calibration.started", mode="level", sensor="level") == (
        "[cal] calibration started: 2 level"
    )
    assert line("calibration.progress", completion_pct=41.7) == "[cal] progress <41>"
    assert line("calibration.done", mode="onboard_level", sensor="level") == (
        "[cal] calibration done: level"
    )
    assert line("calibration.face_done", side="up") == (
        "[cal] up side done, rotate to a different side"
    )
    assert line("calibration.cancelled") == "[cal] calibration cancelled"
    assert line("calibration.accepted") is None


def _started() -> Event:
    data = {"mode": "mag", "sensor": "mag", "onboard": False, "attempt": 1}
    return Event("calibration.started", "Calibration started: mag", Severity.INFO, data)


def test_event_statustexts_of_a_command_flood_are_paced() -> None:
    """Every calibration command sent its STATUSTEXTs to every ground station, unthrottled:
    1000 start/cancel pairs were 2000 STATUSTEXTs. A token bucket keeps a burst, then 2 a
    second; progress lines (once per percent anyway) are not counted."""
    now = [100.0]
    relay = CalibrationRelay(clock=lambda: now[0])
    cancelled = Event("calibration.cancelled", "Calibration cancelled", Severity.NOTICE, {})
    sent = 0
    for _ in range(1000):
        for e in (_started(), cancelled):
            sent += sum(p.get_msgId() == M.MAVLINK_MSG_ID_STATUSTEXT for p in relay.packets(e))
    assert sent == TEXT_BURST and relay.throttled == 2000 - TEXT_BURST
    now[0] += 5.0  # five seconds later: ten more
    more = sum(len(relay.packets(_started())) for _ in range(50))
    assert more == int(5 * TEXT_RATE_HZ)
    relay.begin("px4")
    progress = Event("calibration.progress", "", Severity.INFO, {"completion_pct": 42.0})
    assert relay.packets(progress)  # the bucket is empty; progress still goes


def _onboard_done() -> Event:
    rep = SessionReport(
        Mode.ONBOARD_MAG, "device MAGCAL", autosaved=True, mag=ArduPilotView((1.0, 2.0, 3.0))
    )
    data = {"mode": "onboard_mag", "sensor": "mag", "onboard": True, "autosaved": True,
            "report": rep.to_dict()}  # fmt: skip
    return Event("calibration.done", "Calibration done: mag", Severity.INFO, data)


def test_the_compass_own_magcal_report_is_sent_three_times_not_forever() -> None:
    now = [0.0]
    relay = CalibrationRelay(clock=lambda: now[0])
    relay.begin("ardupilot")
    first = [
        p
        for p in relay.packets(_onboard_done())
        if p.get_msgId() == M.MAVLINK_MSG_ID_MAG_CAL_REPORT
    ]
    assert len(first) == 1  # MAG_CAL_REPORT
    snapshot = CalibratorSnapshot.of(
        None, onboard=True, calibration_source="", calibration_age_s=None, calibration_saved=True
    )
    repeats = 0
    for _ in range(20):  # 20 s of keep-alive ticks
        now[0] += 1.0
        repeats += len(relay.keepalive(now[0], lambda: snapshot))
    assert 1 + repeats == ONBOARD_REPORTS
