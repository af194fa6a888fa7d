"""The calibrator: a pure session per calibration mode, and the controller that runs them.

MAVLink, zenoh and the CLI call :class:`CalibrationController` (start, accept,
cancel, fixed yaw, level, six faces) and map its :class:`~bridge.events.Event`
stream (``calibration.*``), its :class:`Outcome` answers and its
:class:`CalibratorSnapshot` (a neutral :class:`Phase`, a typed
:class:`SessionReport`) to their wire formats. See
:mod:`bridge.calibrator.controller` for the threads and routes and
:mod:`bridge.calibrator.session` for the sessions.
"""

from bridge.calibrator.controller import CalibrationController
from bridge.calibrator.onboard import INSTRUCTION_LEVEL_TURN, INSTRUCTION_SIDE_TURN
from bridge.calibrator.report import Failure, SessionReport
from bridge.calibrator.results import DeviceMagParams, device_params_for
from bridge.calibrator.session import EVENT_KINDS
from bridge.calibrator.snapshot import CalibrationTarget, CalibratorSnapshot
from bridge.calibrator.state import CalibratorSettings, Mode, Outcome, Phase, Result
from bridge.calibrator.store import (
    CALIBRATION_DOCUMENT,
    CalibrationStore,
    StoredCalibration,
)

__all__ = [
    "CALIBRATION_DOCUMENT",
    "EVENT_KINDS",
    "INSTRUCTION_LEVEL_TURN",
    "INSTRUCTION_SIDE_TURN",
    "CalibrationController",
    "CalibrationStore",
    "CalibrationTarget",
    "CalibratorSettings",
    "CalibratorSnapshot",
    "DeviceMagParams",
    "Failure",
    "Mode",
    "Outcome",
    "Phase",
    "Result",
    "SessionReport",
    "StoredCalibration",
    "device_params_for",
]
