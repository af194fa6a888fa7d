"""Calibration in the running bridge: the controller, the calibration in use, and drift.

* :mod:`~bridge.app.calibration.controller` -- :class:`CalibrationController`, the runner
  behind every calibration front end: it feeds the pure sessions
  (:mod:`bridge.calibration.sessions`) and carries out their actions in a worker thread;
* :mod:`~bridge.app.calibration.store` -- :class:`CalibrationStore`, the calibration
  document (one format, one loader);
* :mod:`~bridge.app.calibration.keeper` -- the calibration in use, saved again until
  storage takes it;
* :mod:`~bridge.app.calibration.flash` -- a host calibration written into the compass flash;
* :mod:`~bridge.app.calibration.drift` -- :class:`DriftMonitor`, the calibration watched
  while the vehicle works (the estimator and judge: :mod:`bridge.calibration.drift`).
"""

from bridge.app.calibration.controller import CalibrationController
from bridge.app.calibration.drift import DriftMonitor
from bridge.app.calibration.store import CALIBRATION_DOCUMENT, CalibrationStore, StoredCalibration

__all__ = [
    "CALIBRATION_DOCUMENT",
    "CalibrationController",
    "CalibrationStore",
    "DriftMonitor",
    "StoredCalibration",
]
