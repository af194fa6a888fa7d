"""Every parameter, every flavour: read and written as each ground station's own code does it.

QGroundControl and Mission Planner do not run here, so their handling of
PARAM_VALUE / PARAM_SET is written out below from their sources (MAVProxy and
MAVSDK run for real in ``test_mavlink_client_*.py``; their rules are here too,
for the companion role's matrix). The sources, as read:

* **QGroundControl** -- ``FirmwarePluginManager::firmwarePluginForAutopilot``
  asks the factory of the HEARTBEAT's autopilot; ``APMFirmwarePluginFactory``
  answers only for an ArduPilot copter / plane / VTOL / rover / boat / sub
  (anything else gets the generic plugin); ``PX4FirmwarePluginFactory`` for any
  PX4 vehicle. ``ParameterManager::_mavlinkParamUnionToVariant`` reads
  ``param_value`` through ``mavlink_param_union_t`` (its bytes, as the announced
  type); ``_fillMavlinkParamUnion`` writes a SET the same way, the remaining
  union bytes left uninitialised. Only the ArduPilot plugin translates
  (``APMFirmwarePlugin::_handleIncomingParamValue`` /
  ``_handleOutgoingParamSetThreadSafe``: C-cast), and only for a component whose
  own HEARTBEAT says ArduPilot (``_ardupilotComponentMap``).
* **MAVProxy** (``mavproxy_param.py``) -- bytewise when the system's autopilot
  (component 1's HEARTBEAT) is PX4, the float itself otherwise; sets REAL32 for a
  non-PX4 system.
* **Mission Planner** (``MAVLinkInterface.cs``) -- C-cast when the component's
  HEARTBEAT says ArduPilot (or it announces MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT),
  bytewise otherwise.
* **MAVSDK** (``mavlink_parameter_client.cpp``) -- C-cast for ArduPilot, bytewise otherwise.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import pytest

from bridge.app.paramspec import REAL32, SPECS, ParamSpec
from bridge.mavlink import telemetry as T  # noqa: N812 - short
from bridge.mavlink.dialect import mavlink as M  # noqa: N812 - the generated module
from bridge.mavlink.paramproto import FLAVOURS, Flavour, ParamEncoding

APM = int(M.MAV_AUTOPILOT_ARDUPILOTMEGA)
PX4 = int(M.MAV_AUTOPILOT_PX4)
INVALID = int(M.MAV_AUTOPILOT_INVALID)
_GARBAGE = 0xA5  # what QGroundControl's uninitialised union bytes may hold

#: The MAV_TYPEs APMFirmwarePluginFactory maps to an ArduPilot plugin (the VTOL types 19-25
#: under pymavlink's older names).
QGC_APM_TYPES = frozenset(
    int(getattr(M, name))
    for name in (
        "MAV_TYPE_QUADROTOR",
        "MAV_TYPE_HEXAROTOR",
        "MAV_TYPE_OCTOROTOR",
        "MAV_TYPE_TRICOPTER",
        "MAV_TYPE_COAXIAL",
        "MAV_TYPE_HELICOPTER",
        "MAV_TYPE_VTOL_DUOROTOR",
        "MAV_TYPE_VTOL_QUADROTOR",
        "MAV_TYPE_VTOL_TILTROTOR",
        "MAV_TYPE_VTOL_RESERVED2",
        "MAV_TYPE_VTOL_RESERVED3",
        "MAV_TYPE_VTOL_RESERVED4",
        "MAV_TYPE_VTOL_RESERVED5",
        "MAV_TYPE_FIXED_WING",
        "MAV_TYPE_GROUND_ROVER",
        "MAV_TYPE_SURFACE_BOAT",
        "MAV_TYPE_SUBMARINE",
    )
)

# struct formats of mavlink_param_union_t's members, by MAV_PARAM_TYPE (little endian)
_MEMBER = {
    int(M.MAV_PARAM_TYPE_UINT8): "<B",
    int(M.MAV_PARAM_TYPE_INT8): "<b",
    int(M.MAV_PARAM_TYPE_UINT16): "<H",
    int(M.MAV_PARAM_TYPE_INT16): "<h",
    int(M.MAV_PARAM_TYPE_UINT32): "<I",
    int(M.MAV_PARAM_TYPE_INT32): "<i",
    int(M.MAV_PARAM_TYPE_REAL32): "<f",
}


def f32(v: float) -> float:
    """``v`` rounded to a float32, as it travels."""
    return float(struct.unpack("<f", struct.pack("<f", v))[0])


def union_read(wire: float, ptype: int) -> float:
    """Read ``param_value``'s bytes as the union member of ``ptype``."""
    raw = struct.pack("<f", wire)
    fmt = _MEMBER[ptype]
    return float(struct.unpack_from(fmt, raw)[0])


def union_write(value: float, ptype: int) -> float:
    """Write ``value`` into the union member of ``ptype`` (other bytes uninitialised)."""
    fmt = _MEMBER[ptype]
    member = struct.pack(fmt, value if ptype == REAL32 else int(value))
    raw = member + bytes([_GARBAGE] * (4 - len(member)))
    return float(struct.unpack("<f", raw)[0])


def c_cast(value: float, ptype: int) -> float:
    """``static_cast<type>(float)``: truncation toward zero for the integer types."""
    return value if ptype == REAL32 else float(math.trunc(value))


# ------------------------------------------------------------------------- the clients' rules


@dataclass(frozen=True)
class Vehicle:
    """What a ground station knows when it reads our parameters: the vehicle's HEARTBEAT
    (its component 1, which picks QGroundControl's plugin and MAVProxy's decoding) and
    our component's own HEARTBEAT autopilot."""

    vehicle_type: int
    vehicle_autopilot: int
    our_autopilot: int


def qgc_plugin(autopilot: int, mav_type: int) -> str:
    """The QGroundControl firmware plugin for a vehicle's HEARTBEAT."""
    if autopilot == PX4:
        return "px4"
    if autopilot == APM and mav_type in QGC_APM_TYPES:
        return "apm"
    return "generic"


def qgc_translates(v: Vehicle) -> bool:
    """QGroundControl's ArduPilot plugin C-casts our parameters."""
    return qgc_plugin(v.vehicle_autopilot, v.vehicle_type) == "apm" and v.our_autopilot == APM


def qgc_read(v: Vehicle, wire: float, ptype: int) -> float:
    if qgc_translates(v):  # _handleIncomingParamValue: C-cast into the union member
        wire = union_write(c_cast(wire, ptype), ptype)
    return union_read(wire, ptype)


def qgc_write(v: Vehicle, value: float, ptype: int) -> tuple[float, int]:
    wire = union_write(value, ptype)  # _fillMavlinkParamUnion
    if qgc_translates(v):  # _handleOutgoingParamSetThreadSafe: back to C-cast
        wire = union_read(wire, ptype)
    return wire, ptype


def mavproxy_read(v: Vehicle, wire: float, ptype: int) -> float:
    if ptype != REAL32 and v.vehicle_autopilot == PX4:
        return union_read(wire, ptype)
    return wire


def mavproxy_write(v: Vehicle, value: float, ptype: int) -> tuple[float, int]:
    if ptype != REAL32 and v.vehicle_autopilot == PX4:
        return union_write(value, ptype), ptype
    return f32(value), REAL32


def mission_planner_read(v: Vehicle, wire: float, ptype: int) -> float:
    if v.our_autopilot == APM:
        return c_cast(wire, ptype)
    return union_read(wire, ptype)


def mission_planner_write(v: Vehicle, value: float, ptype: int) -> tuple[float, int]:
    if v.our_autopilot == APM:
        return f32(value), ptype  # "always sent over the air as a float", its type named
    return union_write(value, ptype), ptype


def mavsdk_read(v: Vehicle, wire: float, ptype: int) -> float:
    return c_cast(wire, ptype) if v.our_autopilot == APM else union_read(wire, ptype)


def mavsdk_write(v: Vehicle, value: float, ptype: int) -> tuple[float, int]:
    if v.our_autopilot == APM:
        return f32(value), ptype
    return union_write(value, ptype), ptype


Reader = Callable[[Vehicle, float, int], float]
Writer = Callable[[Vehicle, float, int], tuple[float, int]]
CLIENTS: dict[str, tuple[Reader, Writer]] = {
    "QGroundControl": (qgc_read, qgc_write),
    "MAVProxy": (mavproxy_read, mavproxy_write),
    "Mission Planner": (mission_planner_read, mission_planner_write),
    "MAVSDK": (mavsdk_read, mavsdk_write),
}


# ------------------------------------------------------------------------- the bridge's side


def standalone(flavour: Flavour) -> tuple[Vehicle, ParamEncoding]:
    """A standalone bridge of ``flavour``: its own HEARTBEAT is the vehicle's."""
    hb = T.heartbeat(T.Identity(1, 1, "standalone", flavour), 0)
    return Vehicle(hb.type, hb.autopilot, hb.autopilot), ParamEncoding(flavour)


def values_of(spec: ParamSpec) -> list[float]:
    """Values worth carrying for ``spec``: its default and limits, and one in between that is
    not a whole number for a float (it would show a C-cast integer reading)."""
    vals = {spec.default, spec.minimum, spec.maximum}
    if spec.ptype == REAL32:
        vals.add(spec.minimum + 0.3 * (spec.maximum - spec.minimum))
        return [f32(v) for v in sorted(vals)]
    vals.add(math.floor((spec.minimum + spec.maximum) / 2))
    if spec.choices:
        vals.update(spec.choices)
    return sorted(float(v) for v in vals)


def on_the_wire(enc: ParamEncoding, spec: ParamSpec, value: float) -> Any:
    """The PARAM_VALUE for ``value``, packed and parsed back as a receiver gets it."""
    msg = enc.value_message(spec, value, len(SPECS), 0)
    sender = M.MAVLink(None, 1, 1)
    parser = M.MAVLink(None, 255, 190)
    return parser.decode(bytearray(msg.pack(sender)))


def assert_round_trip(v: Vehicle, enc: ParamEncoding, client: str) -> None:
    read, write = CLIENTS[client]
    for spec in SPECS:
        for value in values_of(spec):
            pv = on_the_wire(enc, spec, value)
            assert read(v, pv.param_value, pv.param_type) == value, (client, spec.name, value)
            wire, ptype = write(v, value, pv.param_type)
            assert enc.decode(f32(wire), ptype) == value, (client, spec.name, value)


# ------------------------------------------------------------------------- the tests


@pytest.mark.parametrize("client", sorted(CLIENTS))
@pytest.mark.parametrize("flavour", FLAVOURS)
def test_every_parameter_reads_and_sets_right_in_every_client(
    flavour: Flavour, client: str
) -> None:
    v, enc = standalone(flavour)
    assert_round_trip(v, enc, client)


@pytest.mark.parametrize("client", sorted(CLIENTS))
@pytest.mark.parametrize(
    "autopilot", [("ArduCopter", "MAV_TYPE_QUADROTOR", APM), ("PX4", "MAV_TYPE_QUADROTOR", PX4)]
)
@pytest.mark.parametrize("flavour", FLAVOURS)
def test_companion_parameters_read_right_beside_either_autopilot(
    flavour: Flavour, autopilot: tuple[str, str, int], client: str
) -> None:
    """Beside an autopilot the system's HEARTBEAT is the autopilot's; ours says INVALID."""
    ours = T.heartbeat(T.Identity(1, 200, "companion", flavour), 0)
    assert ours.autopilot == INVALID
    v = Vehicle(int(getattr(M, autopilot[1])), autopilot[2], ours.autopilot)
    enc = ParamEncoding(flavour, companion=True)
    assert_round_trip(v, enc, client)


def test_the_clients_disagree_on_integers_which_is_why_only_px4_announces_them() -> None:
    """The readings above can fail: an INT8 1 C-cast (ArduPilot's own way) reads 0 in
    QGroundControl's generic plugin, and the bytewise INT32 1 reads 1.4e-45 in MAVProxy
    unless the system is PX4."""
    bridge_apm = Vehicle(int(M.MAV_TYPE_GENERIC), APM, APM)
    assert qgc_plugin(APM, int(M.MAV_TYPE_GENERIC)) == "generic"
    assert qgc_read(bridge_apm, 1.0, int(M.MAV_PARAM_TYPE_INT8)) == 0.0
    assert mavproxy_read(bridge_apm, 1.0, int(M.MAV_PARAM_TYPE_INT8)) == 1.0
    copter = Vehicle(int(M.MAV_TYPE_QUADROTOR), APM, APM)
    assert qgc_read(copter, 1.0, int(M.MAV_PARAM_TYPE_INT8)) == 1.0  # the plugin translates
    bytewise_one = union_write(1, int(M.MAV_PARAM_TYPE_INT32))
    generic = Vehicle(int(M.MAV_TYPE_GENERIC), int(M.MAV_AUTOPILOT_GENERIC), 0)
    assert 0.0 < mavproxy_read(generic, bytewise_one, int(M.MAV_PARAM_TYPE_INT32)) < 1e-44
    # and so: integers are announced as integers only to a PX4 ground station
    for flavour in FLAVOURS:
        _, enc = standalone(flavour)
        types = {enc.wire_type(s) for s in SPECS}
        assert types == ({REAL32, int(M.MAV_PARAM_TYPE_INT32)} if flavour == "px4" else {REAL32})
        companion = ParamEncoding(flavour, companion=True)
        assert {companion.wire_type(s) for s in SPECS} == {REAL32}


def test_the_announced_encoding_matches_the_wire() -> None:
    for flavour in FLAVOURS:
        _, enc = standalone(flavour)
        bit = enc.capability
        if flavour == "px4":
            assert bit == M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
        else:
            assert bit == M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
    assert (
        ParamEncoding("px4", companion=True).capability
        == M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
    )


@pytest.mark.parametrize(
    "ptype,value",
    [
        (int(M.MAV_PARAM_TYPE_INT8), -128),
        (int(M.MAV_PARAM_TYPE_INT8), 127),
        (int(M.MAV_PARAM_TYPE_UINT8), 255),
        (int(M.MAV_PARAM_TYPE_INT16), -32768),
        (int(M.MAV_PARAM_TYPE_UINT16), 65535),
        (int(M.MAV_PARAM_TYPE_INT32), -(2**31)),
        (int(M.MAV_PARAM_TYPE_INT32), 4_653_062),
        (int(M.MAV_PARAM_TYPE_UINT32), 2**31 + 5),
    ],
)
def test_a_bytewise_set_is_read_from_the_low_bytes_of_its_type(ptype: int, value: int) -> None:
    """A PX4 ground station's SET of any integer type, with whatever sits in the bytes the
    type does not use (QGroundControl leaves them uninitialised)."""
    enc = ParamEncoding("px4")
    assert enc.decode(union_write(value, ptype), ptype) == value
    # a non-bytewise flavour reads the float itself, by the parameter's own type
    assert ParamEncoding("ardupilot").decode(float(value), ptype) == float(value)
