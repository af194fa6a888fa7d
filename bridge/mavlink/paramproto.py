"""The MAVLink parameter protocol, encoded as the ground stations of a flavour decode it.

The values live in the application's parameter store
(:class:`~bridge.app.params.ParamStore`); this module only puts them on the
wire and takes them off it. How an integer parameter travels in
``PARAM_VALUE.param_value`` (a float field) is where the ground stations
disagree (docs/mavlink.md, "Parameters"):

* QGroundControl reads the float's *bytes* as the announced type
  (``ParameterManager::_mavlinkParamUnionToVariant``) unless its ArduPilot
  firmware plugin translates (C-cast) -- and that plugin is loaded only for an
  ArduPilot *copter, plane, rover or sub* (``APMFirmwarePluginFactory``), never
  for the bridge's ``MAV_TYPE_GENERIC``, nor for a component whose own
  HEARTBEAT is not ArduPilot's (the companion role);
* MAVProxy reads it bytewise when the system's autopilot is PX4, C-cast otherwise;
* Mission Planner C-cast when the component's HEARTBEAT says ArduPilot,
  bytewise otherwise; MAVSDK C-cast for ArduPilot, bytewise otherwise.

A REAL32 value is the same number under every reading, so:

==============  ====================  ===================================================
flavour         types on the wire     integer values
==============  ====================  ===================================================
``px4``         INT32 and REAL32      bytewise (the int32's bytes in the float), as PX4:
                                      every client decodes a PX4 vehicle so (and MAVSDK's
                                      Param plugin needs INT32 for ``get_param_int``)
``ardupilot``   REAL32 for every      the value itself: ArduPilot's INT8/INT32 types
                parameter             C-cast would read wrong in QGroundControl, which
                                      shows the bridge with its generic plugin
``generic``     REAL32 for every      the value itself
                parameter
==============  ====================  ===================================================

The companion role announces REAL32 whatever the flavour (the autopilot beside
decides how MAVProxy decodes the whole system; QGroundControl decodes our
component bytewise).

A SET is decoded by the type it names when that type is an integer and the
encoding is bytewise (PX4 reads it so); otherwise the float is the value, read
by the parameter's own type, as ArduPilot's GCS_Param::handle_param_set does
(MAVProxy names REAL32 for every non-PX4 vehicle).

Bulk replies are rate-limited per peer (see :class:`ListLimiter`): a
PARAM_REQUEST_LIST of 14 bytes brings back every parameter (~1.3 KB), which on
an open ``udpin`` port is an amplifier for anyone who can spoof an address.
"""

from __future__ import annotations

import struct
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Literal

from bridge.app.params import ParamStore
from bridge.app.paramspec import INT8, INT16, INT32, REAL32, ParamSpec
from bridge.mavlink.dialect import Message
from bridge.mavlink.dialect import mavlink as M  # noqa: N812 - the generated module, short
from bridge.mavlink.telemetry import param_value

Flavour = Literal["generic", "px4", "ardupilot"]
FLAVOURS: tuple[Flavour, ...] = ("generic", "px4", "ardupilot")

_INT_TYPES = frozenset(
    {
        INT8,
        INT16,
        INT32,
        int(M.MAV_PARAM_TYPE_UINT8),
        int(M.MAV_PARAM_TYPE_UINT16),
        int(M.MAV_PARAM_TYPE_UINT32),
    }
)
_F32 = struct.Struct("<f")
_I32 = struct.Struct("<i")
_U32 = struct.Struct("<I")

#: A peer gets at most one whole parameter list per this many seconds ...
LIST_INTERVAL_S = 2.0
#: ... and all peers together at most this many per LIST_INTERVAL_S.
LISTS_PER_INTERVAL = 8


def param_name(raw: bytes | str) -> str:
    """A received param_id as text (NUL-terminated unless 16 characters long)."""
    if isinstance(raw, bytes):
        raw = raw.split(b"\0", 1)[0].decode("ascii", "replace")
    return raw.split("\0", 1)[0]


class ParamEncoding:
    """Parameter values to and from ``param_value`` for one flavour (see the module docstring).

    ``companion``: the bridge is a component beside an autopilot, whose own flavour
    decides how ground stations decode the system: every value travels as REAL32.
    """

    def __init__(self, flavour: Flavour, *, companion: bool = False) -> None:
        if flavour not in FLAVOURS:
            raise ValueError(f"flavour must be one of {FLAVOURS}, got {flavour!r}")
        self.flavour = flavour
        self.companion = companion

    @property
    def bytewise(self) -> bool:
        """Integers travel as their bytes (PX4), not as their value."""
        return self.flavour == "px4" and not self.companion

    @property
    def capability(self) -> int:
        """The AUTOPILOT_VERSION capability bit that announces this encoding."""
        if self.bytewise:
            return int(M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE)
        return int(M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST)

    def wire_type(self, spec: ParamSpec) -> int:
        """The MAV_PARAM_TYPE a parameter is announced with."""
        return INT32 if self.bytewise and spec.ptype != REAL32 else REAL32

    def encode(self, spec: ParamSpec, value: float) -> float:
        """``value`` as it goes in ``param_value``."""
        if self.wire_type(spec) != REAL32:
            return float(_F32.unpack(_I32.pack(int(value)))[0])
        return float(value)

    def decode(self, wire_value: float, wire_type: int) -> float:
        """The number a PARAM_SET carries (NaN when it carries none)."""
        if wire_type in _INT_TYPES and self.bytewise:
            raw = _U32.unpack(_F32.pack(wire_value))[0]  # NaN and inf patterns are ints too
            return float(_as_signed(raw, wire_type))
        return float(wire_value)

    def value_message(self, spec: ParamSpec, value: float, count: int, index: int) -> Message:
        """The PARAM_VALUE for one parameter."""
        return param_value(spec.name, self.encode(spec, value), self.wire_type(spec), count, index)


def _as_signed(raw: int, wire_type: int) -> int:
    """The low bytes of a bytewise value as the integer type names them."""
    if wire_type == INT8:
        v = raw & 0xFF
        return v - 0x100 if v & 0x80 else v
    if wire_type == INT16:
        v = raw & 0xFFFF
        return v - 0x10000 if v & 0x8000 else v
    if wire_type == INT32:
        return raw - 0x1_0000_0000 if raw & 0x8000_0000 else raw
    if wire_type == int(M.MAV_PARAM_TYPE_UINT8):
        return raw & 0xFF
    if wire_type == int(M.MAV_PARAM_TYPE_UINT16):
        return raw & 0xFFFF
    return raw


class ListLimiter:
    """Whole parameter lists, rate-limited: at most one per peer per ``interval_s`` (what a
    ground station needs on connect and on refresh), and at most ``total`` per
    ``interval_s`` for all peers together (a flood of spoofed source addresses, each a
    new "peer" on a ``udpin`` port, cannot multiply it). Requests over either limit are
    dropped and counted."""

    def __init__(
        self,
        interval_s: float = LIST_INTERVAL_S,
        total: int = LISTS_PER_INTERVAL,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.interval_s = interval_s
        self.total = total
        self._clock = clock
        self._last: dict[Any, float] = {}
        self._recent: deque[float] = deque()
        self.refused = 0

    def allow(self, peer: Any) -> bool:
        """Whether ``peer`` may have a whole list now (and count it as having had one)."""
        now = self._clock()
        recent = self._recent
        while recent and now - recent[0] >= self.interval_s:
            recent.popleft()
        last = self._last.get(peer)
        if (last is not None and now - last < self.interval_s) or len(recent) >= self.total:
            self.refused += 1
            return False
        if len(self._last) > 256:  # forget peers long gone
            self._last = {p: t for p, t in self._last.items() if now - t < self.interval_s}
        self._last[peer] = now
        recent.append(now)
        return True


class ParamProtocol:
    """PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET against the parameter store.

    ``send(message)`` answers the asking link; ``broadcast(message)`` tells every
    link (a SET's echo: other ground stations learn the new value too).
    """

    def __init__(self, params: ParamStore, encoding: ParamEncoding) -> None:
        self.params = params
        self.encoding = encoding
        self.lists = ListLimiter()
        self.sets_refused = 0

    def value_at(self, index: int) -> Message:
        """The PARAM_VALUE of the parameter at ``index``."""
        spec, value = self.params.by_index(index)
        return self.encoding.value_message(spec, value, len(self.params), index)

    def value_of(self, name: str) -> Message:
        """The PARAM_VALUE of ``name`` (``KeyError`` if unknown)."""
        return self.value_at(self.params.index(name))

    def all_values(self) -> list[Message]:
        """Every PARAM_VALUE, in index order."""
        return [self.value_at(i) for i in range(len(self.params))]

    def request_list(self, peer: Any) -> list[Message]:
        """The answer to PARAM_REQUEST_LIST from ``peer`` (empty when rate-limited)."""
        return self.all_values() if self.lists.allow(peer) else []

    def answer_read(self, msg: Any, peer: Any) -> list[Message] | None:
        """The answer to PARAM_REQUEST_LIST or PARAM_REQUEST_READ from ``peer`` (None: a list
        refused by the rate limit; empty: an unknown name or index)."""
        if msg.get_type() == "PARAM_REQUEST_LIST":
            return self.request_list(peer) or None
        answer = self.request_read(msg)
        return [answer] if answer is not None else []

    def request_read(self, msg: Any) -> Message | None:
        """The answer to PARAM_REQUEST_READ (None for an unknown name or index)."""
        idx = int(msg.param_index)
        if idx >= 0:
            return self.value_at(idx) if idx < len(self.params) else None
        name = param_name(msg.param_id)
        return self.value_of(name) if self.params.spec(name) is not None else None

    def set(self, msg: Any, source: str = "PARAM_SET") -> tuple[str, str, Message | None]:
        """Apply a PARAM_SET: (name, refusal reason or "", the echo to broadcast).

        Every SET of a known parameter is answered by the value now in force; an
        unknown name gets no answer (as ArduPilot).
        """
        name = param_name(msg.param_id)
        spec = self.params.spec(name)
        if spec is None:
            self.sets_refused += 1
            return name, "unknown parameter", None
        value = self.encoding.decode(float(msg.param_value), int(msg.param_type))
        outcome = self.params.set(name, value, source=source)
        if outcome.reason:
            self.sets_refused += 1
        return name, outcome.reason, self.value_of(name)
