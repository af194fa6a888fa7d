"""Calibration, pure (no I/O): what a calibration is, how it is fitted, how it is collected.

* :mod:`~bridge.calibration.model` -- :class:`~bridge.calibration.model.Calibration`, the
  one calibration type, with its ArduPilot parameter view and its device (flash) view;
* :mod:`bridge.calibration.fits` -- the fits: each method returns parameters and a report;
* :mod:`bridge.calibration.sessions` -- one session per calibration mode: frames in,
  actions out;
* :mod:`bridge.calibration.drift` -- hard-iron drift: the estimator and its judge.

Running them in the daemon (threads, storage, the flash) is :mod:`bridge.app.calibration`.
"""
