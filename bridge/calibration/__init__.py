"""Calibration, pure (no I/O): how a calibration is fitted, how it is collected.

What a calibration is -- :class:`~bridge.core.calibration.Calibration`, the one
calibration type, with its ArduPilot parameter view and its device (flash) view -- is
maths the attitude engine applies, so it lives beside it in :mod:`bridge.core`.

* :mod:`bridge.calibration.fits` -- the fits: each method returns parameters and a report;
* :mod:`bridge.calibration.sessions` -- one session per calibration mode: frames in,
  actions out;
* :mod:`bridge.calibration.drift` -- hard-iron drift: the estimator and its judge.

Running them in the daemon (threads, storage, the flash) is :mod:`bridge.app.calibration`.
"""
