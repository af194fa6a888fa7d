"""Calibration fits (pure numpy): every method returns ``CalibrationResult(calibration, report)``.

:mod:`~bridge.calibration.fits.methods` names them (``minmax``, ``twelve_position``,
``scalar``, ``ellipsoid``, ``best`` ...); one module per method, and what they share:
frame series, coverage, sample acceptance, ArduPilot's sanity checks, the acceptance rule.
"""
