"""The serial-link adapter: transports, the CompassLink reader, recording and replay."""
