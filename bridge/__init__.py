"""compass-bridge: GMR compass to MAVLink and Zenoh.

The package is layered so that the structure explains itself (docs/architecture.md):

* ``bridge.protocol`` -- pure serial codecs, the compass link as a state machine, and what
  the application asks of the compass (``bridge.protocol.device``)
* ``bridge.core`` -- pure attitude maths, sensor transfer functions, the calibration type and
  its views, the World Magnetic Model
* ``bridge.calibration`` -- pure: the fits, the calibration sessions, drift's estimator and
  judge
* ``bridge.documents`` -- what the application asks of the state directory;
  ``bridge.types`` -- the shared type aliases
* ``bridge.sim``         -- the simulated compass (physics, motion scripts, firmware, pty server)
* ``bridge.app``         -- the running bridge's state and its owners (``bridge.app.calibration``:
  the calibration controller, store and drift monitor)
* ``bridge.link``, ``bridge.mavlink``, ``bridge.zenoh``, ``bridge.systemd``, ``bridge.console``,
  ``bridge.storage`` -- one adapter per outside world
* ``bridge.daemon``      -- the one place that wires everything into the running daemon
* ``bridge.cli``         -- the ``compass-bridge`` command line (``bridge.tools``: its tools)
"""

__version__ = "0.1.0"
