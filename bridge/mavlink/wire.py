"""MAVLink 2 on the wire: payloads encoded once, framed per link.

A message is encoded once into a :class:`Packet` (message id, CRC extra,
payload with MAVLink 2's trailing zeros trimmed) and then *framed* by each
link with its own sequence number (and signature): a ground station counts
lost packets from sequence gaps, so every link needs its own counter, while
the payload -- the costly part -- is shared. :class:`Codec` packs a payload
from field values using pymavlink's generated layout (field order, array
lengths, struct format), so the bytes are exactly what pymavlink itself
would send; :class:`Framer` adds the 10-byte header, the CRC-16/MCRF4XX
(with the message's CRC extra) and, when signing, the 13-byte signature.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from bridge.mavlink.dialect import IFLAG_SIGNED, MAGIC_V2, mavlink, message_class
from bridge.mavlink.signing import Signing

_HEADER = struct.Struct("<BBBBBBBHB")


def _crc(data: bytes) -> int:
    # pymavlink's x25crc is CRC-16/MCRF4XX and uses the C ``fastcrc`` when installed.
    return int(mavlink.x25crc(data).crc)


@dataclass(frozen=True, slots=True)
class Packet:
    """An encoded, not yet framed, message."""

    msgid: int
    crc_extra: int
    payload: bytes


class Codec:
    """Encoder for one message type, built from pymavlink's generated class."""

    __slots__ = ("_chars", "_layout", "_names", "_struct", "crc_extra", "msgid", "name")

    def __init__(self, msgid: int) -> None:
        cls = message_class(msgid)
        self.msgid: int = cls.id
        self.name: str = cls.msgname
        self.crc_extra: int = cls.crc_extra
        self._struct: struct.Struct = cls.unpacker
        types = dict(zip(cls.fieldnames, cls.fieldtypes, strict=True))
        self._chars = frozenset(n for n, t in types.items() if t == "char")
        # (name, array length or 0), in wire order (largest types first, extensions last)
        self._layout: tuple[tuple[str, int], ...] = tuple(
            zip(cls.ordered_fieldnames, cls.array_lengths, strict=True)
        )
        # Scalar-only messages (ATTITUDE, SCALED_IMU, ...: the telemetry) take a fast path.
        simple = not self._chars and not any(n for _name, n in self._layout)
        self._names: tuple[str, ...] | None = (
            tuple(name for name, _n in self._layout) if simple else None
        )

    def payload(self, fields: Mapping[str, Any]) -> bytes:
        """Pack ``fields`` (every field by name; arrays as sequences, char fields as str/bytes).

        Raises ``KeyError`` for a missing field and ``struct.error`` for a value
        that does not fit its type.
        """
        names = self._names
        if names is not None:
            return trim(self._struct.pack(*[fields[name] for name in names]))
        values: list[Any] = []
        for name, n in self._layout:
            v = fields[name]
            if name in self._chars:
                values.append(v.encode("utf-8") if isinstance(v, str) else bytes(v))
            elif n:
                seq = list(v)
                if len(seq) != n:
                    raise ValueError(f"{self.name}.{name} needs {n} values, got {len(seq)}")
                values.extend(seq)
            else:
                values.append(v)
        return trim(self._struct.pack(*values))

    def packet(self, **fields: Any) -> Packet:
        """Encode one message."""
        return Packet(self.msgid, self.crc_extra, self.payload(fields))


def trim(payload: bytes) -> bytes:
    """MAVLink 2 payload truncation: trailing zero bytes dropped, at least one byte kept."""
    out = payload.rstrip(b"\0")  # in C: this runs for every message sent
    return out if out else payload[:1]


_CODECS: dict[int, Codec] = {}


def codec(msgid: int) -> Codec:
    """The (cached) :class:`Codec` for a message id."""
    c = _CODECS.get(msgid)
    if c is None:
        c = _CODECS[msgid] = Codec(msgid)
    return c


class Framer:
    """Frames packets for one link: its own sequence counter, our ids, optional signing.

    Not thread-safe: one framer belongs to one link and is used by that link's thread.
    """

    __slots__ = ("_signing", "component_id", "link_id", "seq", "system_id")

    def __init__(
        self, system_id: int, component_id: int, *, signing: Signing | None = None, link_id: int = 0
    ) -> None:
        self.system_id = system_id
        self.component_id = component_id
        self._signing = signing
        self.link_id = link_id
        self.seq = 0

    def frame(self, p: Packet) -> bytes:
        """The full packet bytes for ``p`` (0xFD header, payload, CRC, signature if signing)."""
        flags = IFLAG_SIGNED if self._signing is not None else 0
        head = _HEADER.pack(
            MAGIC_V2,
            len(p.payload),
            flags,
            0,
            self.seq,
            self.system_id,
            self.component_id,
            p.msgid & 0xFFFF,
            p.msgid >> 16,
        )
        self.seq = (self.seq + 1) & 0xFF
        body = head + p.payload
        crc = _crc(body[1:] + bytes((p.crc_extra,)))
        out = body + crc.to_bytes(2, "little")
        if self._signing is not None:
            out = self._signing.sign(out, self.link_id)
        return out
