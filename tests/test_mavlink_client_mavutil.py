"""pymavlink's ``mavutil`` helpers, as scripts use them, against the bridge.

``mavutil`` locks onto the first HEARTBEAT that ``probably_vehicle_heartbeat``
accepts (not a GCS, gimbal, ADS-B or onboard controller, and an autopilot other
than INVALID) and sends ``param_fetch_all`` and friends to it. A standalone
bridge must be such a vehicle whatever its flavour; a companion bridge must
not be (its HEARTBEAT is the IMU component's: autopilot INVALID), so scripts
lock onto the autopilot beside it.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from test_mavlink_rig import DEADLINE_S, GCS_COMPID, GCS_SYSID, M, Rig, mavutil

from bridge.mavlink.paramproto import FLAVOURS
from bridge.sim.motion import Still

pytestmark = pytest.mark.integration  # real sockets, processes or threads


@pytest.fixture
def connections() -> Iterator[list[Any]]:
    made: list[Any] = []
    yield made
    for c in made:
        c.close()


def connect(rig: Rig, made: list[Any]) -> Any:
    conn = mavutil.mavlink_connection(
        f"udpout:127.0.0.1:{rig.udp_port}",
        source_system=GCS_SYSID,
        source_component=GCS_COMPID,
        dialect="ardupilotmega",
    )
    made.append(conn)
    # a udpin endpoint learns a peer from its first datagram
    conn.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    return conn


def heartbeats(conn: Any, n: int) -> list[Any]:
    out: list[Any] = []
    deadline = time.monotonic() + DEADLINE_S
    while len(out) < n and time.monotonic() < deadline:
        m = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
        if m is not None:
            out.append(m)
    assert len(out) == n, "no HEARTBEAT"
    return out


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_mavutil_takes_the_standalone_bridge_for_a_vehicle_and_fetches_its_parameters(
    tmp_path: Path, rigs: Callable[..., Rig], connections: list[Any], flavour: str
) -> None:
    rig = rigs(tmp_path, ideal=True, motion=Still.from_deg(0, 0, 0), mavlink={"autopilot": flavour})
    conn = connect(rig, connections)
    hb = conn.wait_heartbeat(timeout=DEADLINE_S)
    assert hb is not None and conn.probably_vehicle_heartbeat(hb)
    # locked onto the bridge; target component 0 (all of the system's), which it answers
    assert (conn.target_system, conn.target_component) == (1, 0)

    conn.param_fetch_all()
    n = len(rig.daemon.bridge.params)
    deadline = time.monotonic() + DEADLINE_S
    while len(conn.params) < n and time.monotonic() < deadline:
        conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.5)
    assert len(conn.params) == n
    # mavutil keeps param_value as it travels: the value itself, except PX4's integers
    store = rig.daemon.bridge.params
    for spec in store.specs:
        raw = conn.params[spec.name]
        if flavour == "px4" and spec.ptype != M.MAV_PARAM_TYPE_REAL32:
            bits = struct.unpack("<i", struct.pack("<f", raw))[0]  # bytewise INT32
            assert bits == store.get(spec.name), spec.name
        else:
            assert raw == pytest.approx(store.get(spec.name), rel=1e-7), spec.name


def test_mavutil_does_not_take_a_companion_bridge_for_a_vehicle(
    tmp_path: Path, rigs: Callable[..., Rig], connections: list[Any]
) -> None:
    rig = rigs(tmp_path, ideal=True, motion=Still.from_deg(0, 0, 0), mavlink={"role": "companion"})
    conn = connect(rig, connections)
    for hb in heartbeats(conn, 2):
        assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 200)
        assert not conn.probably_vehicle_heartbeat(hb)
    assert conn.target_system == 0  # still waiting for the autopilot's HEARTBEAT
    # addressed explicitly, the companion's parameters are there
    conn.target_system, conn.target_component = 1, 200
    conn.param_fetch_one("BRG_SR_HUD")
    m = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=DEADLINE_S)
    assert m is not None and m.param_id == "BRG_SR_HUD" and m.get_srcComponent() == 200
