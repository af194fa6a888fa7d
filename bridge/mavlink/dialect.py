"""The one MAVLink dialect the bridge speaks: ardupilotmega, MAVLink 2.

``pymavlink.mavutil`` picks MAVLink 1 unless ``MAVLINK20`` is set before it is
imported; the bridge never goes through ``mavutil``. It imports the generated
``dialects.v20.ardupilotmega`` module directly, whose wire protocol is fixed at
2.0 and which holds the ArduPilot messages a ground station expects from a
compass (MAG_CAL_PROGRESS, MAG_CAL_REPORT, the DO_*_MAG_CAL commands) on top
of the common set. Everything else in :mod:`bridge.mavlink` takes message ids,
CRC extras and enum values from here.
"""

from __future__ import annotations

from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as _dialect

#: The generated module (message classes, enums); typed loosely, pymavlink ships no stubs.
mavlink: Any = _dialect

if str(mavlink.WIRE_PROTOCOL_VERSION) != "2.0":  # pragma: no cover - a broken install
    raise ImportError(
        f"pymavlink's v20 ardupilotmega dialect reports wire protocol "
        f"{mavlink.WIRE_PROTOCOL_VERSION}, expected 2.0"
    )

MAGIC_V2 = 0xFD  #: first byte of every MAVLink 2 packet
MAGIC_V1 = 0xFE
IFLAG_SIGNED = 0x01  #: incompat_flags bit: a 13-byte signature follows the CRC
SIGNATURE_LEN = 13  #: link id (1) + timestamp (6) + signature (6)


#: A pymavlink message object (the generated classes are untyped).
Message = Any


def message(msgid: int, **fields: Any) -> Message:
    """A message to send: the dialect's class for ``msgid`` with ``fields`` (char fields as
    bytes, arrays as sequences). pymavlink frames it, per link, when it is sent."""
    return mavlink.mavlink_map[msgid](**fields)


def message_class(msgid: int) -> Any:
    """The pymavlink message class for ``msgid`` (``KeyError`` if the dialect lacks it)."""
    return mavlink.mavlink_map[msgid]
