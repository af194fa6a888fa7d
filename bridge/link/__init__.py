"""The serial-link adapter: transports, the CompassLink driver, recording and replay.

``open_transport(port, baud)`` turns a configured port string into a
:class:`Transport` (a serial device, ``"sim"``, or ``"replay:PATH"``);
:class:`CompassLink` runs the sans-I/O link machine
(:mod:`bridge.protocol.link`: state, handshake, command transactions) on it,
on one reader thread; :func:`record`
(:mod:`~bridge.link.recorder`) taps a port into a recording
(:mod:`~bridge.link.record`, the file format) that ``replay:PATH`` plays back.
"""

from bridge.link.record import (
    RecordingFormatError,
    RecordingHeader,
    RecordingReader,
    RecordingWriter,
)
from bridge.link.recorder import RecordSummary, record
from bridge.link.serial_link import (
    CommandError,
    CommandLate,
    CommandNotSupported,
    CommandRejected,
    CommandTimeout,
    CompassLink,
    LinkCounters,
    LinkDown,
    LinkState,
    Received,
)
from bridge.link.transport import (
    EndOfRecording,
    ReplayTransport,
    SerialTransport,
    SimTransport,
    Transport,
    TransportError,
    open_transport,
)

__all__ = [
    "CommandError",
    "CommandLate",
    "CommandNotSupported",
    "CommandRejected",
    "CommandTimeout",
    "CompassLink",
    "EndOfRecording",
    "LinkCounters",
    "LinkDown",
    "LinkState",
    "Received",
    "RecordSummary",
    "RecordingFormatError",
    "RecordingHeader",
    "RecordingReader",
    "RecordingWriter",
    "ReplayTransport",
    "SerialTransport",
    "SimTransport",
    "Transport",
    "TransportError",
    "open_transport",
    "record",
]
