"""Traffic a ground station did not send never starves it: endpoints on real sockets.

* ``udpin``: junk, CRC-broken, unsigned (with signing on), wrongly signed and replayed
  datagrams from many ports make nobody a peer; a peer whose HEARTBEATs keep coming is
  never dropped for strangers; the port is not shared (no SO_REUSEADDR);
* ``tcpin``: idle clients, however many, do not lock a newcomer out: it is served within
  seconds; a client sending HEARTBEATs keeps its place.
"""

from __future__ import annotations

import contextlib
import random
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from mavlink_clients import signed_mav
from test_mavlink_endpoints import (  # noqa: F401
    Inbox,
    endpoints,
    heartbeat_bytes,
    local_address,
    ping,
)
from test_mavlink_rig import DEADLINE_S, M, free_port, recv_udp, wait_until

from benchmarks.fuzz_hostile import heartbeat, idle_clients
from bridge.mavlink.endpoints import Endpoint
from bridge.mavlink.endpoints import base as E  # noqa: N812 - short
from bridge.mavlink.signing import Signing

pytestmark = pytest.mark.integration

KEY = bytes(range(32))


def spray(port: int, datagrams: list[bytes]) -> None:
    """Each datagram from a port of its own (a socket made for it, closed at once)."""
    for d in datagrams:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(d, ("127.0.0.1", port))


def junk(rng: random.Random, n: int) -> list[bytes]:
    """Random bytes, bytes behind a MAVLink 2 magic, and HEARTBEATs with a broken CRC."""
    out = []
    for i in range(n):
        kind = i % 3
        if kind == 0:
            out.append(rng.randbytes(rng.randint(1, 200)))
        elif kind == 1:
            out.append(b"\xfd" + rng.randbytes(rng.randint(10, 120)))
        else:
            bad = bytearray(heartbeat_bytes())
            bad[-1] ^= 0xFF
            out.append(bytes(bad))
    return out


def _udpin(endpoints: Callable[..., Endpoint], **kw: Any) -> tuple[Endpoint, int]:  # noqa: F811
    port = free_port()
    ep = endpoints(f"udpin:127.0.0.1:{port}", **kw)
    assert wait_until(lambda: local_address(ep) is not None)
    return ep, port


def test_junk_from_many_ports_makes_no_peer(endpoints: Callable[..., Endpoint]) -> None:  # noqa: F811
    ep, port = _udpin(endpoints)
    datagrams = junk(random.Random(1), 600)
    for i in range(0, 600, 50):  # paced: the kernel's buffer is not what is tested here
        spray(port, datagrams[i : i + 50])

        def sprayed_dropped(n: int = i + 50) -> bool:
            return ep.counters().strangers_dropped == n

        assert wait_until(sprayed_dropped)
    assert ep.links == [] and ep.counters().packets_received == 0
    # A real HEARTBEAT does make one.
    spray(port, [heartbeat_bytes()])
    assert wait_until(lambda: len(ep.links) == 1)


def test_with_signing_only_a_valid_fresh_signature_makes_a_peer(
    endpoints: Callable[..., Endpoint],  # noqa: F811
) -> None:
    ep, port = _udpin(endpoints, signing=Signing(KEY))
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        mav = signed_mav(KEY, 255)
        first = heartbeat(mav)
        wrong = signed_mav(bytes(32), 7)
        strangers = [heartbeat_bytes(sysid=9)] * 100 + [heartbeat(wrong) for _ in range(100)]
        spray(port, strangers)  # unsigned, and signed with another key
        assert wait_until(lambda: ep.counters().strangers_dropped == 200)
        assert ep.links == []
        gcs.sendto(first, ("127.0.0.1", port))
        assert wait_until(lambda: len(ep.links) == 1)
        spray(port, [first] * 50)  # its packet, replayed from other ports
        assert wait_until(lambda: ep.counters().strangers_dropped == 250)
        assert len(ep.links) == 1
    finally:
        gcs.close()


def test_a_peer_sending_heartbeats_is_never_dropped_for_strangers(
    endpoints: Callable[..., Endpoint],  # noqa: F811
) -> None:
    ep, port = _udpin(endpoints)
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", 0))
    stop = threading.Event()

    def beat() -> None:  # the ground station: one HEARTBEAT a second
        while not stop.is_set():
            gcs.sendto(heartbeat_bytes(), ("127.0.0.1", port))
            stop.wait(1.0)

    th = threading.Thread(target=beat, daemon=True)
    th.start()
    try:
        assert wait_until(lambda: len(ep.links) == 1)
        mine = gcs.getsockname()
        # 600 strangers with *valid* frames (no HEARTBEAT): they take and swap the free places.
        other = M.MAVLink(None, 42, 1)
        frame = bytes(other.param_request_list_encode(1, 1).pack(other))
        for _ in range(3):
            spray(port, [frame] * 200)
            time.sleep(0.2)
        assert wait_until(lambda: ep.counters().connects >= 2 + E.MAX_UDP_PEERS)
        addresses = [lk.address for lk in ep.links]
        assert len(addresses) == E.MAX_UDP_PEERS and mine in addresses
        assert ep.counters().peers_evicted > 0
        # ... and it is still answered.
        ep.broadcast(ping(7))
        assert recv_udp(gcs, 1, timeout=DEADLINE_S)
    finally:
        stop.set()
        th.join(2.0)
        gcs.close()


def test_udpin_does_not_share_its_port(endpoints: Callable[..., Endpoint]) -> None:  # noqa: F811
    first, port = _udpin(endpoints)
    # Any process, even asking for SO_REUSEADDR, cannot bind it beside us.
    thief = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    thief.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    with pytest.raises(OSError):
        thief.bind(("127.0.0.1", port))
    thief.close()
    # A second bridge's udpin on it fails to open, says so, and keeps retrying.
    second = endpoints(f"udpin:127.0.0.1:{port}")
    assert wait_until(lambda: second.counters().errors >= 1)
    assert local_address(second) is None
    spray(port, [heartbeat_bytes()])
    assert wait_until(lambda: len(first.links) == 1)
    assert second.links == []


@contextlib.contextmanager
def pinging(ep: Endpoint, hz: float = 20.0) -> Iterator[None]:
    """The endpoint broadcasts a numbered ping at ``hz`` (telemetry stand-in)."""
    stop = threading.Event()

    def run() -> None:
        i = 0
        while not stop.is_set():
            ep.broadcast(ping(i))
            i += 1
            stop.wait(1.0 / hz)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    try:
        yield
    finally:
        stop.set()
        th.join(2.0)


def served_within(port: int, seconds: float, heartbeat: bool = True) -> float:
    """Connect, send a HEARTBEAT, and time the first byte the endpoint sends back."""
    t0 = time.monotonic()
    with socket.create_connection(("127.0.0.1", port), timeout=seconds) as c:
        if heartbeat:
            c.sendall(heartbeat_bytes())
        c.settimeout(seconds)
        assert c.recv(4096), "connection closed without a byte"
    return time.monotonic() - t0


def test_idle_tcp_clients_do_not_lock_a_newcomer_out(endpoints: Callable[..., Endpoint]) -> None:  # noqa: F811
    port = free_port(socket.SOCK_STREAM)
    ep = endpoints(f"tcpin:127.0.0.1:{port}")
    assert wait_until(lambda: local_address(ep) is not None)
    idle: list[socket.socket] = []
    with pinging(ep):
        try:
            # A ground station that sends HEARTBEATs, then 50 clients that send nothing.
            gcs = socket.create_connection(("127.0.0.1", port))
            idle.append(gcs)
            stop = threading.Event()

            def beat() -> None:
                while not stop.is_set():
                    with contextlib.suppress(OSError):
                        gcs.sendall(heartbeat_bytes())
                    stop.wait(1.0)

            th = threading.Thread(target=beat, daemon=True)
            th.start()
            idle += idle_clients(port, 50)
            took = served_within(port, 10.0)
            assert took < 5.0, took
            assert ep.counters().peers_evicted > 0
            # The ground station kept its place the whole time, and is still fed.
            gcs.settimeout(2.0)
            assert len(gcs.recv(65536)) > 0
            assert sum(1 for lk in ep.links if lk.address == gcs.getsockname()) == 1
            stop.set()
            th.join(2.0)
        finally:
            for s in idle:
                s.close()


def test_a_tcp_client_that_stops_reading_makes_room(endpoints: Callable[..., Endpoint]) -> None:  # noqa: F811
    port = free_port(socket.SOCK_STREAM)
    ep = endpoints(f"tcpin:127.0.0.1:{port}", queue_packets=8)
    assert wait_until(lambda: local_address(ep) is not None)
    clients: list[socket.socket] = []
    try:
        for _ in range(E.MAX_TCP_CLIENTS):
            c = socket.create_connection(("127.0.0.1", port))
            c.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            clients.append(c)
        assert wait_until(lambda: len(ep.links) == E.MAX_TCP_CLIENTS)
        # They send HEARTBEATs but never read: the endpoint's bytes pile up unread.
        stop = threading.Event()

        def beat() -> None:
            while not stop.is_set():
                for c in clients:
                    with contextlib.suppress(OSError):
                        c.sendall(heartbeat_bytes())
                stop.wait(0.5)

        th = threading.Thread(target=beat, daemon=True)
        th.start()
        filler = M.MAVLink(None, 1, 1)
        payload = filler.param_value_encode(b"X" * 16, 1.0, 9, 1, 0)
        t_end = time.monotonic() + DEADLINE_S
        while time.monotonic() < t_end and not any(lk.stalled_since is not None for lk in ep.links):
            for _ in range(200):
                ep.broadcast(payload)
            time.sleep(0.01)
        assert any(lk.stalled_since is not None for lk in ep.links)
        with pinging(ep):
            took = served_within(port, 10.0)
        assert took < 5.0, took
        assert ep.counters().peers_evicted >= 1
        stop.set()
        th.join(2.0)
    finally:
        for c in clients:
            c.close()
