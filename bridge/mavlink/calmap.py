"""The calibrator's neutral state and reports in MAVLink's terms.

The calibrator speaks of a :class:`~bridge.calibration.sessions.Phase` (with the
session's step), a :class:`~bridge.calibration.sessions.Failure` and a typed
:class:`~bridge.calibration.sessions.SessionReport`, and its event texts are plain
sentences. Here they become what ground stations read:

* MAG_CAL_STATUS (:func:`mag_cal_status`): waiting -> WAITING_TO_START;
  collecting or fitting -> RUNNING_STEP_ONE / RUNNING_STEP_TWO by step;
  succeeded -> SUCCESS; failed -> the failure's code (RADIUS 7, ORIENTATION 6,
  OFFSETS 8, DIAG_SCALING 9, RESIDUALS_HIGH 10, else FAILED 5); idle or
  cancelled -> NOT_STARTED;
* MAG_CAL_PROGRESS from a snapshot, MAG_CAL_REPORT from a report (codes 8-10
  sent as FAILED, as ArduPilot does, for the ground stations that predate
  them; COMPASS_ORIENT never changed: old = new = ROTATION_NONE, ArduPilot's
  COMPASS_AUTO_ROT=0);
* PX4's ``[cal]`` STATUSTEXT lines (:func:`px4_text`), each one message:
  QGroundControl parses single messages, so a longer line is cut there
  (:func:`cal_line`). Other texts go out whole, chunked as the MAVLink spec
  says (:func:`bridge.mavlink.telemetry.statustext`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from bridge.calibration.fits.sanity import MagCalStatus
from bridge.calibration.sessions import CalibratorSnapshot, Failure, Mode, Phase, SessionReport
from bridge.core.calibration import ArduPilotView
from bridge.events import Event
from bridge.mavlink.dialect import Message
from bridge.mavlink.telemetry import STATUSTEXT_LEN, MagCalReport, mag_cal_progress

#: PX4's calibration protocol version, which QGroundControl checks in "calibration started".
PX4_CAL_VERSION = 2

FAILURE_STATUS: Mapping[Failure, MagCalStatus] = {
    Failure.FAILED: MagCalStatus.MAG_CAL_FAILED,
    Failure.ORIENTATION: MagCalStatus.MAG_CAL_FAILED_ORIENTATION,
    Failure.RADIUS: MagCalStatus.MAG_CAL_FAILED_RADIUS,
    Failure.OFFSETS: MagCalStatus.MAG_CAL_FAILED_OFFSETS,
    Failure.SCALING: MagCalStatus.MAG_CAL_FAILED_DIAG_SCALING,
    Failure.RESIDUALS: MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH,
}
#: The sessions whose result is a magnetometer calibration (reported by MAG_CAL_REPORT).
MAG_MODES = frozenset({Mode.MAG.value, Mode.ONBOARD_MAG.value, Mode.FIXED_YAW.value})


def mag_cal_status(phase: Phase, step: int, failure: Failure | None = None) -> MagCalStatus:
    """MAG_CAL_STATUS of a session in ``phase`` (``step`` 1 or 2; ``failure`` when failed)."""
    if phase is Phase.WAITING:
        return MagCalStatus.MAG_CAL_WAITING_TO_START
    if phase in (Phase.COLLECTING, Phase.FITTING):
        if step >= 2:
            return MagCalStatus.MAG_CAL_RUNNING_STEP_TWO
        return MagCalStatus.MAG_CAL_RUNNING_STEP_ONE
    if phase is Phase.SUCCEEDED:
        return MagCalStatus.MAG_CAL_SUCCESS
    if phase is Phase.FAILED:
        return FAILURE_STATUS[failure or Failure.FAILED]
    return MagCalStatus.MAG_CAL_NOT_STARTED


def snapshot_status(snap: CalibratorSnapshot) -> MagCalStatus:
    """MAG_CAL_STATUS of the calibrator's current (or last) session."""
    return mag_cal_status(snap.phase, snap.step, snap.failure)


def report_status(report: SessionReport) -> MagCalStatus:
    """MAG_CAL_STATUS of a finished session's report."""
    return (
        MagCalStatus.MAG_CAL_SUCCESS if report.failure is None else FAILURE_STATUS[report.failure]
    )


def progress_message(snap: CalibratorSnapshot, compass_id: int) -> Message:
    """MAG_CAL_PROGRESS from a calibrator snapshot."""
    return mag_cal_progress(
        int(snapshot_status(snap)),
        snap.attempt,
        snap.completion_pct,
        snap.completion_mask,
        snap.direction,
        compass_id=compass_id,
    )


def report_figures(report: SessionReport) -> MagCalReport:
    """A magnetometer session's report as MAG_CAL_REPORT's figures."""
    m = report.mag if report.mag is not None else ArduPilotView((0.0, 0.0, 0.0))
    fit = report.fit
    fitness = fit.fitness_mG if fit is not None else math.nan
    confidence = fit.orientation_confidence if fit is not None else math.nan
    return MagCalReport(
        # Codes 8-10 are newer than many ground stations; ArduPilot sends FAILED for them.
        cal_status=int(report_status(report).legacy),
        autosaved=report.autosaved,
        fitness=fitness,
        ofs=m.ofs_mG,
        diag=m.diag,
        offdiag=m.offdiag,
        orientation_confidence=confidence,
        old_orientation=0,  # ROTATION_NONE: the bridge never changes COMPASS_ORIENT itself
        new_orientation=0,
        scale_factor=m.scale,
    )


def event_report(data: Mapping[str, Any]) -> MagCalReport | None:
    """MAG_CAL_REPORT's figures of a ``calibration.done`` / ``failed`` event of a
    magnetometer session (None for other sessions, or a report that is not one)."""
    rep = data.get("report")
    if str(data.get("mode", "")) not in MAG_MODES or not isinstance(rep, Mapping):
        return None
    try:
        return report_figures(SessionReport.from_dict(rep))
    except (ValueError, TypeError, KeyError, IndexError):
        return None


# ---------------------------------------------------------------------------- PX4's [cal] lines


def cal_line(text: str) -> str:
    """A ``[cal]`` line that fits one STATUSTEXT (QGroundControl parses single messages)."""
    line = "[cal] " + text
    data = line.encode("utf-8")
    if len(data) <= STATUSTEXT_LEN:
        return line
    return data[:STATUSTEXT_LEN].decode("utf-8", errors="ignore")


def _px4_sensor(data: Mapping[str, Any]) -> str:
    """PX4's sensor word: "mag", "accel" or "level"."""
    if str(data.get("mode", "")) in (Mode.LEVEL.value, Mode.ONBOARD_LEVEL.value):
        return "level"
    return str(data.get("sensor", "mag"))


def px4_text(event: Event) -> str | None:
    """The PX4 ``[cal]`` line for a calibration event (None: no PX4 equivalent)."""
    d = event.data
    k = event.kind
    if k == "calibration.started":
        return f"[cal] calibration started: {PX4_CAL_VERSION} {_px4_sensor(d)}"
    if k == "calibration.progress":
        pct = d.get("completion_pct")
        if not isinstance(pct, int | float) or not math.isfinite(pct):
            return None
        return f"[cal] progress <{max(0, min(100, int(pct)))}>"
    if k == "calibration.face_detected":
        return f"[cal] {d.get('side', '?')} orientation detected"
    if k == "calibration.face_done":
        return f"[cal] {d.get('side', '?')} side done, rotate to a different side"
    if k == "calibration.done":
        return f"[cal] calibration done: {_px4_sensor(d)}"
    if k == "calibration.failed":
        return cal_line(f"calibration failed: {d.get('reason', 'unknown')}")
    if k == "calibration.cancelled":
        return "[cal] calibration cancelled"
    if k in ("calibration.instruction", "calibration.motion"):
        return cal_line(event.text)
    return None


#: Outside the PX4 flow, a STATUSTEXT says how far a calibration is every this many per cent
#: (MAVProxy's console shows no MAG_CAL_PROGRESS; PX4 sends its "[cal] progress <N>").
PROGRESS_TEXT_STEP = 20


def progress_step(data: Mapping[str, Any]) -> int | None:
    """The last whole step of :data:`PROGRESS_TEXT_STEP` a progress event has reached."""
    pct = data.get("completion_pct")
    if not isinstance(pct, int | float) or not math.isfinite(pct):
        return None
    return int(max(0.0, min(100.0, pct)) // PROGRESS_TEXT_STEP) * PROGRESS_TEXT_STEP


def progress_text(data: Mapping[str, Any], step: int) -> str:
    """The STATUSTEXT for a progress step ("Mag calibration 40%: keep turning it")."""
    sensor = _px4_sensor(data)
    text = f"{sensor.capitalize()} calibration {step}%"
    return text + ": keep turning it" if sensor == "mag" else text
