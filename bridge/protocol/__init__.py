"""Serial protocol codecs, and the compass link as a state machine: pure, no I/O.

* :mod:`bridge.protocol.framing` -- ``$...*CS\\r\\n`` line splitter, checksum, drop counters.
* :mod:`bridge.protocol.gmr` -- the GMR compass sentences (``$PGMR*``).
* :mod:`bridge.protocol.heading` -- heading-only compasses (NMEA HDT/HDG/HDM, ``$PTNTHPR``,
  OceanServer ``$C``).
* :mod:`bridge.protocol.link` -- the compass link as a sans-I/O state machine (bytes and
  ``now`` in; frames, state changes, bytes to write, the next deadline out).
* :mod:`bridge.protocol.transactions` -- its command transactions.
* :mod:`bridge.protocol.device` -- the compass as the application sees it
  (:class:`~bridge.protocol.device.DevicePort`), and the link's words every layer names:
  its state, counters, received frames and command errors.
"""

from bridge.protocol.framing import (
    CodecCounters,
    DecodeError,
    DropCounters,
    DropReason,
    LineSplitter,
    checksum,
    render_line,
)

__all__ = [
    "CodecCounters",
    "DecodeError",
    "DropCounters",
    "DropReason",
    "LineSplitter",
    "checksum",
    "render_line",
]
