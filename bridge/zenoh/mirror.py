"""MAVLink messages as JSON on ``mavlink/<sys>/<comp>/<MSG>``, the bluerobotics/mavlink-server layout.

mavlink-server (BlueOS) publishes every message it routes on
``mavlink/<system_id>/<component_id>/<MESSAGE_NAME>`` as ``application/json``
in rust-mavlink's serde shape, the one mavlink2rest uses too::

    {"header": {"system_id": 1, "component_id": 1, "sequence": 42, "message_id": 30},
     "message": {"type": "ATTITUDE", "time_boot_ms": 1234, "roll": 0.01, ...}}

* ``message.type`` is the message name; the other keys are the MAVLink field names,
  except a field itself named ``type`` (HEARTBEAT), which rust-mavlink calls ``mavtype``;
* an enum field is an object ``{"type": "<ENTRY_NAME>"}``, a bitmask ``{"bits": <int>}``;
* ``char[]`` fields are strings, other arrays are JSON arrays; NaN is ``null``.

Fleet tools written for BlueOS therefore see the compass like any other
MAVLink component. The message layout (names, enums) comes from the bridge's
dialect (pymavlink's ardupilotmega, as :mod:`bridge.mavlink.dialect`). PURE: no I/O.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

MIRROR_ROOT = "mavlink"


@dataclass(frozen=True, slots=True)
class MirrorMessage:
    """A MAVLink message captured for mirroring: header, id and field values (a copy)."""

    system_id: int
    component_id: int
    sequence: int
    message_id: int
    fields: Mapping[str, Any]

    @classmethod
    def from_fields(
        cls,
        message_id: int,
        fields: Mapping[str, Any],
        *,
        system_id: int,
        component_id: int,
        sequence: int = 0,
    ) -> MirrorMessage:
        """From a message id and its field values (the bridge's encoder's input)."""
        return cls(int(system_id), int(component_id), int(sequence), int(message_id), dict(fields))

    @classmethod
    def from_packet(
        cls,
        message_id: int,
        payload: bytes,
        *,
        system_id: int,
        component_id: int,
        sequence: int = 0,
    ) -> MirrorMessage:
        """From an encoded MAVLink 2 payload (trailing zeros may be trimmed).

        Raises ``KeyError`` for an unknown message id and ``ValueError`` for a
        payload longer than the message.
        """
        mc = _message_class(message_id)
        size = mc.unpacker.size
        if len(payload) > size:
            raise ValueError(f"{mc.msgname}: payload of {len(payload)} bytes, at most {size}")
        raw = mc.unpacker.unpack(payload + bytes(size - len(payload)))
        types = dict(zip(mc.fieldnames, mc.fieldtypes, strict=True))
        fields: dict[str, Any] = {}
        i = 0
        for name, n in zip(mc.ordered_fieldnames, mc.array_lengths, strict=True):
            if types[name] == "char" or not n:  # a char[] unpacks as one bytes value
                fields[name] = raw[i]
                i += 1
            else:
                fields[name] = list(raw[i : i + n])
                i += n
        return cls(int(system_id), int(component_id), int(sequence), int(message_id), fields)

    @classmethod
    def capture(cls, msg: Any) -> MirrorMessage:
        """From a pymavlink message object (cheap: copies the values, no enum lookups)."""
        return cls(
            system_id=int(msg.get_srcSystem()),
            component_id=int(msg.get_srcComponent()),
            sequence=int(msg.get_seq()),
            message_id=int(msg.get_msgId()),
            fields={f: getattr(msg, f) for f in msg.get_fieldnames()},
        )

    @property
    def name(self) -> str:
        """The message name (``ATTITUDE``); ``KeyError`` if the dialect does not know the id."""
        return str(_message_class(self.message_id).msgname)

    def to_doc(self) -> dict[str, Any]:
        """The mavlink-server JSON document."""
        cls = _message_class(self.message_id)
        enums_of: Mapping[str, str] = cls.fieldenums_by_name
        displays: Mapping[str, str] = cls.fielddisplays_by_name
        message: dict[str, Any] = {"type": str(cls.msgname)}
        for name in cls.fieldnames:
            value = self.fields.get(name)
            enum = enums_of.get(name)
            if enum and isinstance(value, int) and not isinstance(value, bool):
                value = _enum_value(enum, value, bitmask=displays.get(name) == "bitmask")
            message["mavtype" if name == "type" else name] = _json_value(value)
        return {
            "header": {
                "system_id": self.system_id,
                "component_id": self.component_id,
                "sequence": self.sequence,
                "message_id": self.message_id,
            },
            "message": message,
        }

    def to_json(self) -> bytes:
        """:meth:`to_doc` as compact strict JSON."""
        return json.dumps(self.to_doc(), separators=(",", ":"), allow_nan=False).encode()


def mirror_key(m: MirrorMessage) -> str:
    """``mavlink/<sys>/<comp>/<MSG>``."""
    return f"{MIRROR_ROOT}/{m.system_id}/{m.component_id}/{m.name}"


def _dialect() -> Any:
    # pymavlink's ardupilotmega dialect, MAVLink 2: the one the MAVLink adapter sends with
    # (taken from pymavlink, not from that adapter: adapters do not import each other).
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega


def _message_class(message_id: int) -> Any:
    return _dialect().mavlink_map[message_id]


def _enum_value(enum: str, value: int, *, bitmask: bool) -> Any:
    if bitmask:
        return {"bits": value}
    entry = _dialect().enums.get(enum, {}).get(value)
    # An entry name looks like MAV_TYPE_GENERIC; an unknown value stays a number.
    return {"type": str(entry.name)} if entry is not None else value


def _json_value(v: Any) -> Any:
    if isinstance(v, bytes):
        return v.split(b"\0", 1)[0].decode("ascii", "replace")
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, list | tuple):
        return [_json_value(x) for x in v]
    return v
