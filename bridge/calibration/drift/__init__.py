"""Hard-iron drift, pure: :mod:`~bridge.calibration.drift.estimator` fits the offset change
from windows of frames, :mod:`~bridge.calibration.drift.judge` decides when it is drift.
The running bridge's side (a thread, events, learned offsets applied and stored) is
:class:`bridge.app.calibration.drift.DriftMonitor`."""
