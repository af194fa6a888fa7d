"""compass-bridge: GMR compass to MAVLink and Zenoh.

The package is layered so that the structure explains itself:

* ``bridge.protocol``    -- pure serial codecs (bytes in, frames out; frames in, bytes out)
* ``bridge.core``        -- pure attitude maths, sensor transfer functions, the World Magnetic Model
* ``bridge.calibration`` -- pure calibration fits and their quality reports
* ``bridge.sim``         -- the simulated compass (physics, motion scripts, firmware, pty server)
* ``bridge.link``        -- the serial-link adapter (pyserial, in-process simulator, replay)
* ``bridge.daemon``      -- the one place that wires everything into the running daemon
* ``bridge.cli``         -- the ``compass-bridge`` command line
"""

__version__ = "0.1.0"
