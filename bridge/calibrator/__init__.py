"""The calibration controller: one state machine behind every calibration front end.

MAVLink, zenoh and the CLI call :class:`CalibrationController` (start, accept,
cancel, fixed yaw, level, six faces) and map its :class:`~bridge.events.Event`
stream (``calibration.*``) and :class:`Outcome` answers to their wire formats.
See :mod:`bridge.calibrator.controller` for the threads and routes.
"""

from bridge.calibrator.controller import (
    EVENT_KINDS,
    INSTRUCTION_LEVEL_TURN,
    INSTRUCTION_SIDE_TURN,
    CalibrationController,
    CalibratorSettings,
    CalibratorSnapshot,
    Mode,
    Outcome,
    Result,
)
from bridge.calibrator.results import DeviceMagParams, device_params_for
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
    "CalibratorSettings",
    "CalibratorSnapshot",
    "DeviceMagParams",
    "Mode",
    "Outcome",
    "Result",
    "StoredCalibration",
    "device_params_for",
]
