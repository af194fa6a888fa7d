"""The MAVLink front end: telemetry, parameters, commands and calibration over MAVLink 2.

:class:`MavlinkOutput` plugs into the daemon like every output; the modules:

* :mod:`~bridge.mavlink.dialect`   -- pymavlink's ardupilotmega dialect, MAVLink 2 only
* :mod:`~bridge.mavlink.wire`      -- payloads encoded once, framed per link
* :mod:`~bridge.mavlink.signing`   -- MAVLink 2 signing and replay protection
* :mod:`~bridge.mavlink.endpoints` -- udpout/udpin/tcp/tcpin/serial links, one thread each
* :mod:`~bridge.mavlink.telemetry` -- what is sent, in which units, how often (pure)
* :mod:`~bridge.mavlink.params`    -- the parameter table and the calibration it describes (pure)
* :mod:`~bridge.mavlink.commands`  -- commands and calibration events mapped to MAVLink (pure)
* :mod:`~bridge.mavlink.output`    -- the output: threads, dispatch, persistence
"""

from bridge.mavlink.output import BridgeServices, MavlinkOutput, MavlinkSettings

__all__ = ["BridgeServices", "MavlinkOutput", "MavlinkSettings"]
