"""The calibrator's neutral state, reports and texts in MAVLink's terms (pure)."""

from __future__ import annotations

import math
from typing import Any

import pytest
from test_mavlink_telemetry import decode, wire_text

from bridge.calibration.fits.sanity import MagCalStatus
from bridge.calibration.sessions import CalibratorSnapshot, Failure, Mode, Phase, SessionReport
from bridge.calibration.sessions.report import DeviceOutcome, FitQuality
from bridge.core.calibration import ArduPilotView
from bridge.events import Event, Severity
from bridge.mavlink import calmap
from bridge.mavlink.commands import (
    ONBOARD_REPORTS,
    PROGRESS_PERIOD_S,
    TEXT_BURST,
    TEXT_RATE_HZ,
    CalibrationRelay,
)
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


def _snap(*, running: bool) -> CalibratorSnapshot:
    return CalibratorSnapshot(
        mode="mag" if running else None, phase=Phase.COLLECTING if running else Phase.IDLE,
        step=1 if running else 0, running=running, attempt=1, completion_pct=10.0,
        completion_mask=bytes(10), direction=(0.0, 0.0, 1.0), onboard=False, faces_done=(),
        report=None, pending_accept=False, calibration_source="none (identity)",
        calibration_age_s=None, calibration_saved=True,
    )  # fmt: skip


def test_the_keepalive_sleeps_while_no_calibration_runs_and_wakes_for_one() -> None:
    """The telemetry thread woke twice a second to ask the calibrator whether a
    magnetometer calibration ran. Now a look that finds none running and no report to
    repeat puts the keep-alive to sleep (keepalive_due +inf) until a calibration event
    or a command (hurry) wakes it, and on_due tells the sleeping thread."""
    now = [10.0]
    relay = CalibrationRelay(clock=lambda: now[0])
    woken: list[float] = []
    relay.on_due = lambda: woken.append(now[0])
    assert relay.keepalive_due < math.inf  # at first it looks once (a run may be under way)
    assert relay.keepalive(now[0], lambda: _snap(running=False)) == []
    assert relay.keepalive_due == math.inf and woken == []
    relay.packets(_started())  # a calibration started (here, or from Zenoh, the CLI ...)
    assert woken == [10.0] and relay.keepalive_due == 10.0 + PROGRESS_PERIOD_S
    relay.packets(_started())  # already looking: no second wake-up
    assert woken == [10.0]
    sent = []
    for i in range(1, 5):  # progress twice a second while it runs
        now[0] = 10.0 + 0.5 * i
        assert relay.keepalive_due <= now[0]
        sent += relay.keepalive(now[0], lambda: _snap(running=True))
    assert [m.get_type() for m in sent] == ["MAG_CAL_PROGRESS"] * 4
    now[0] += 0.5
    relay.keepalive(now[0], lambda: _snap(running=False))  # it ended: asleep again
    assert relay.keepalive_due == math.inf
    relay.hurry()  # a command handled: the next look at once
    assert relay.keepalive_due == -math.inf and len(woken) == 2


def test_an_event_during_the_keepalive_look_keeps_it_awake() -> None:
    # The start's event comes while the look reads a snapshot taken before it: the look
    # must not put the keep-alive to sleep, or that calibration's progress never goes out.
    relay = CalibrationRelay(clock=lambda: 0.0)

    def snapshot_then_start() -> CalibratorSnapshot:
        snap = _snap(running=False)
        relay.packets(_started())
        return snap

    relay.keepalive(1.0, snapshot_then_start)
    assert relay.keepalive_due == 1.0 + PROGRESS_PERIOD_S


def test_a_report_waiting_for_an_answer_keeps_the_keepalive_awake() -> None:
    now = [0.0]
    relay = CalibrationRelay(clock=lambda: now[0])
    relay.begin("ardupilot")
    rep = SessionReport(Mode.MAG, "host fit", mag=ArduPilotView((1.0, 2.0, 3.0)))
    data = {"mode": "mag", "sensor": "mag", "onboard": False, "report": rep.to_dict()}
    relay.packets(Event("calibration.done", "Calibration done: mag", Severity.INFO, data))
    reports = 0
    for _ in range(5):
        now[0] += 1.0
        reports += len(relay.keepalive(now[0], lambda: _snap(running=False)))
        assert relay.keepalive_due < math.inf
    assert reports == 5  # once a second until answered
    relay.answered()
    now[0] += 1.0
    assert relay.keepalive(now[0], lambda: _snap(running=False)) == []
    assert relay.keepalive_due == math.inf


def test_a_compass_parameter_set_is_told_by_its_echo_not_a_statustext() -> None:
    """A PARAM_SET of COMPASS_*: saved at once or within the second (paced), its PARAM_VALUE
    echo says enough; one that storage refused is said (a warning)."""
    from bridge.app.calibration.keeper import applied

    relay = CalibrationRelay(clock=lambda: 0.0)
    for error, paced in (("", False), ("", True)):
        events, _ = applied("parameters", error, paced, stored=True)
        assert [relay.packets(e) for e in events] == [[]], (error, paced)
    events, _ = applied("parameters", "disk full", False, stored=True)
    texts = [m.text for e in events for m in relay.packets(e)]
    assert texts[0] == "Calibration applied, NOT saved"
    events, _ = applied("storage", "", False, stored=True)  # PREFLIGHT_STORAGE's: said
    assert [m.text for m in relay.packets(events[0])] == ["Calibration accepted and saved"]
