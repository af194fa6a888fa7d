"""The MAVLink adapter: telemetry, parameters, commands and calibration over MAVLink 2.

:class:`MavlinkOutput` plugs into the daemon like every output, built on the
application's :class:`~bridge.app.services.BridgeServices`; the modules:

* :mod:`~bridge.mavlink.dialect`    -- pymavlink's ardupilotmega dialect, MAVLink 2 only
* :mod:`~bridge.mavlink.signing`    -- MAVLink 2 signing and replay protection
* :mod:`~bridge.mavlink.endpoints`  -- udpout/udpin/tcp/tcpin/serial links, one thread each
* :mod:`~bridge.mavlink.schedule`   -- which streams are due, and when (pure)
* :mod:`~bridge.mavlink.telemetry`  -- what is sent, in which units (pure)
* :mod:`~bridge.mavlink.paramproto` -- the parameter protocol, encoded per autopilot flavour
* :mod:`~bridge.mavlink.commands`   -- commands and calibration events mapped to MAVLink (pure)
* :mod:`~bridge.mavlink.calmap`     -- the calibrator's phases, reports and texts in MAVLink terms
* :mod:`~bridge.mavlink.dispatch`   -- the command handlers, the autopilot's position
* :mod:`~bridge.mavlink.output`     -- the output: threads, publishing, notifications
"""

from bridge.mavlink.output import MavlinkOutput, MavlinkSettings

__all__ = ["MavlinkOutput", "MavlinkSettings"]
