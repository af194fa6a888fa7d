"""Calibration sessions: one pure state machine per calibration mode -- frames and ticks in,
actions out (no thread, no clock, no device, no store).

The modes: the host's magnetometer, six faces, level and fixed yaw
(:mod:`~bridge.calibration.sessions.host`), and the compass's own MAGCAL and ACCCAL
(:mod:`~bridge.calibration.sessions.onboard`); what every session shares -- the
actions, the phase, the time-outs -- is :mod:`~bridge.calibration.sessions.base`. The
controller that runs them in the daemon (a worker thread, the engine, the store, the
flash) is :class:`bridge.app.calibration.CalibrationController`.

Front ends (MAVLink, Zenoh, the CLI) map the neutral words here -- a :class:`Phase`,
an :class:`Outcome`, a :class:`CalibratorSnapshot` with its typed :class:`SessionReport`
-- to their wire formats.
"""

from bridge.calibration.sessions.base import EVENT_KINDS
from bridge.calibration.sessions.onboard import INSTRUCTION_LEVEL_TURN, INSTRUCTION_SIDE_TURN
from bridge.calibration.sessions.report import Failure, SessionReport
from bridge.calibration.sessions.snapshot import CalibrationTarget, CalibratorSnapshot
from bridge.calibration.sessions.state import CalibratorSettings, Mode, Outcome, Phase, Result

__all__ = [
    "EVENT_KINDS",
    "INSTRUCTION_LEVEL_TURN",
    "INSTRUCTION_SIDE_TURN",
    "CalibrationTarget",
    "CalibratorSettings",
    "CalibratorSnapshot",
    "Failure",
    "Mode",
    "Outcome",
    "Phase",
    "Result",
    "SessionReport",
]
