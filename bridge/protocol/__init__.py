"""Serial protocol codecs: pure, no I/O.

* :mod:`bridge.protocol.framing` -- ``$...*CS\\r\\n`` line splitter, checksum, drop counters.
* :mod:`bridge.protocol.gmr` -- the GMR compass sentences (``$PGMR*``).
* :mod:`bridge.protocol.heading` -- heading-only compasses (NMEA HDT/HDG/HDM, ``$PTNTHPR``,
  OceanServer ``$C``).
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
