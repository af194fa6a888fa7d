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
from collections.abc import Callable, Mapping, Sequence
from operator import itemgetter
from typing import Any, NamedTuple

from bridge.mavlink.dialect import IFLAG_SIGNED, MAGIC_V2, mavlink, message_class
from bridge.mavlink.signing import Signing

# The header after the magic byte: what the CRC covers (len, incompat, compat, seq, sys,
# comp, msgid low 16 bits, msgid high 8 bits).
_HEADER_CRC = struct.Struct("<BBBBBBHB")
_CRC16 = struct.Struct("<H")
_MAGIC_BYTE = bytes((MAGIC_V2,))
_BYTES = tuple(bytes((i,)) for i in range(256))  # the CRC extra byte, without a bytes() per frame


def _x25crc(data: bytes) -> int:
    # pymavlink's x25crc object: CRC-16/MCRF4XX, in pure Python without fastcrc.
    return int(mavlink.x25crc(data).crc)


try:
    # What pymavlink's x25crc calls when it can (pymavlink 2.4.50 requires fastcrc):
    # called directly, it saves the object and two Python calls per frame.
    from fastcrc.crc16 import mcrf4xx as _mcrf4xx
except ImportError:  # pragma: no cover - an older pymavlink without fastcrc
    _crc: Callable[[bytes], int] = _x25crc
else:
    _crc = _mcrf4xx


class Packet(NamedTuple):
    """An encoded, not yet framed, message (immutable: one packet is shared by every link).

    A named tuple rather than a frozen dataclass: it is made for every telemetry
    message, and a tuple is built in C (a frozen dataclass runs ``__init__`` with
    one ``object.__setattr__`` per field).
    """

    msgid: int
    crc_extra: int
    payload: bytes


_new_tuple = tuple.__new__  # Packet without its Python-level __new__ (see Codec.packer)


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
            values.extend(self._wire_values(name, n, fields[name]))
        return trim(self._struct.pack(*values))

    def _wire_values(self, name: str, n: int, v: Any) -> list[Any]:
        """The struct values of one field: a char field as bytes, an array's ``n`` items."""
        if name in self._chars:
            return [v.encode("utf-8") if isinstance(v, str) else bytes(v)]
        if n:
            seq = list(v)
            if len(seq) != n:
                raise ValueError(f"{self.name}.{name} needs {n} values, got {len(seq)}")
            return seq
        return [v]

    def packet(self, **fields: Any) -> Packet:
        """Encode one message."""
        return Packet(self.msgid, self.crc_extra, self.payload(fields))

    def packer(self, names: Sequence[str], **constants: Any) -> Callable[..., Packet]:
        """A positional encoder for a message sent often: ``packer(names, **constants)(*values)``
        is ``packet(**dict(zip(names, values)), **constants)``, the same bytes.

        ``names`` are the fields that vary, in the order the caller passes them
        (any order: the wire order, largest types first, is applied by one C-level
        ``itemgetter``); ``constants`` are the others, fixed once here. Every field
        must be in exactly one of the two; arrays and char fields only as constants.
        The per-call cost is a tuple concatenation, the itemgetter, the struct
        pack and the trim -- no dict of keyword arguments, no loop in Python.
        """
        variable = tuple(names)
        sizes = dict(self._layout)
        unknown = [n for n in (*variable, *constants) if n not in sizes]
        if unknown:
            raise KeyError(f"{self.name} has no field {', '.join(unknown)}")
        both = set(variable) & set(constants)
        if both or len(set(variable)) != len(variable):
            raise ValueError(f"{self.name}: a field named twice ({sorted(both) or variable})")
        missing = [n for n in sizes if n not in constants and n not in variable]
        if missing:
            raise KeyError(f"{self.name}: no value for {', '.join(missing)}")
        fixed: list[Any] = []
        order: list[int] = []  # index into values + fixed, in wire order
        for name, n in self._layout:
            if name in constants:
                for item in self._wire_values(name, n, constants[name]):
                    order.append(len(variable) + len(fixed))
                    fixed.append(item)
            elif n or name in self._chars:
                raise ValueError(f"{self.name}.{name}: arrays and text only as constants")
            else:
                order.append(variable.index(name))
        st = self._struct
        if len(st.unpack(bytes(st.size))) != len(order):  # pragma: no cover - pymavlink bug
            raise ValueError(f"{self.name}: the layout does not match {st.format!r}")
        consts = tuple(fixed)
        # itemgetter of one index gives the item, not a 1-tuple
        pick = itemgetter(*order) if len(order) > 1 else (lambda v, i=order[0]: (v[i],))
        pack, msgid, crc_extra = self._struct.pack, self.msgid, self.crc_extra

        def make(*values: Any) -> Packet:
            raw = pack(*pick(values + consts))
            # trim(), inlined: rstrip runs in C; an all-zero payload keeps one byte.
            return _new_tuple(Packet, (msgid, crc_extra, raw.rstrip(b"\0") or raw[:1]))

        return make


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

    __slots__ = ("_flags", "_signing", "component_id", "link_id", "seq", "system_id")

    def __init__(
        self, system_id: int, component_id: int, *, signing: Signing | None = None, link_id: int = 0
    ) -> None:
        self.system_id = system_id
        self.component_id = component_id
        self._signing = signing
        self._flags = IFLAG_SIGNED if signing is not None else 0
        self.link_id = link_id
        self.seq = 0

    def frame(self, p: Packet) -> bytes:
        """The full packet bytes for ``p`` (0xFD header, payload, CRC, signature if signing)."""
        # Runs for every packet on every link: one pack for the header, one CRC call over
        # header + payload + CRC extra, one pack for the CRC (a test holds the bytes equal
        # to pymavlink's own, signed and unsigned).
        payload, msgid, seq = p.payload, p.msgid, self.seq
        self.seq = (seq + 1) & 0xFF
        body = (
            _HEADER_CRC.pack(
                len(payload),
                self._flags,
                0,
                seq,
                self.system_id,
                self.component_id,
                msgid & 0xFFFF,
                msgid >> 16,
            )
            + payload
        )
        out = _MAGIC_BYTE + body + _CRC16.pack(_crc(body + _BYTES[p.crc_extra]))
        signing = self._signing
        if signing is not None:
            return signing.sign(out, self.link_id)
        return out
