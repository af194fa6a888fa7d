"""compass-bridge: GMR compass to MAVLink and Zenoh.

The package is layered so that the structure explains itself (docs/architecture.md):

* ``bridge.protocol``, ``bridge.core`` -- pure serial codecs; pure attitude maths, sensor
  transfer functions, the World Magnetic Model
* ``bridge.calibration`` -- pure: the calibration type and its views, the fits, the
  calibration sessions, drift's estimator and judge
* ``bridge.device``, ``bridge.documents`` -- what the application asks of the compass and of
  the state directory; ``bridge.types`` -- the shared type aliases
* ``bridge.sim``         -- the simulated compass (physics, motion scripts, firmware, pty server)
* ``bridge.app``         -- the running bridge's state and its owners (``bridge.app.calibration``:
  the calibration controller, store and drift monitor)
* ``bridge.link``, ``bridge.mavlink``, ``bridge.zenoh``, ``bridge.systemd``, ``bridge.console``,
  ``bridge.storage`` -- one adapter per outside world
* ``bridge.daemon``      -- the one place that wires everything into the running daemon
* ``bridge.cli``         -- the ``compass-bridge`` command line (``bridge.tools``: its tools)
"""

__version__ = "0.1.0"
