"""Endpoints on real sockets and a real pseudo-terminal: every kind, and nobody stalls anybody."""

from __future__ import annotations

import contextlib
import os
import socket
import threading
import time
import tty
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from test_mavlink_rig import DEADLINE_S, M, free_port, mavutil, recv_udp, wait_until

from benchmarks.fuzz_hostile import heartbeat
from bridge.mavlink.dialect import Message, message
from bridge.mavlink.endpoints import (
    Endpoint,
    Link,
    SerialEndpoint,
    TcpServerEndpoint,
    UdpEndpoint,
    open_endpoint,
)
from bridge.mavlink.endpoints import base as E  # noqa: N812 - short
from bridge.mavlink.signing import Signing

pytestmark = pytest.mark.integration  # real sockets, processes or threads

KEY = bytes(range(32))


class Inbox:
    """An ``on_message`` handler that keeps (message, link) pairs."""

    def __init__(self) -> None:
        self.items: list[tuple[Any, Link]] = []
        self._lock = threading.Lock()

    def __call__(self, msg: Any, link: Link) -> None:
        with self._lock:
            self.items.append((msg, link))

    def of(self, mtype: str) -> list[tuple[Any, Link]]:
        with self._lock:
            return [(m, lk) for m, lk in self.items if m.get_type() == mtype]


def ping(i: int) -> Message:
    """A small numbered packet (SYSTEM_TIME, time_boot_ms = i)."""
    return message(M.MAVLINK_MSG_ID_SYSTEM_TIME, time_unix_usec=i, time_boot_ms=i)


def heartbeat_bytes(sysid: int = 255, compid: int = 190) -> bytes:
    return heartbeat(M.MAVLink(None, sysid, compid))


@pytest.fixture
def endpoints() -> Iterator[Callable[..., Endpoint]]:
    made: list[Endpoint] = []

    def make(text: str, inbox: Inbox | None = None, **kw: Any) -> Endpoint:
        ep = open_endpoint(
            text, system_id=1, component_id=1, on_message=inbox or Inbox(), **kw
        ).start()
        made.append(ep)
        return ep

    yield make
    for ep in made:
        ep.close(2.0)


def local_address(ep: Endpoint) -> Any:
    """The address a UDP endpoint or a TCP server bound (None until it has)."""
    assert isinstance(ep, UdpEndpoint | TcpServerEndpoint), ep
    return ep.local_address


def parse_all(data: bytes, key: bytes | None = None) -> list[Any]:
    mav = M.MAVLink(None)
    if key:
        mav.signing.secret_key = key
    return [m for m in (mav.parse_buffer(data) or []) if m.get_type() != "BAD_DATA"]


@pytest.mark.integration
def test_udpout_sends_and_hears_replies(endpoints: Callable[..., Endpoint]) -> None:
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    inbox = Inbox()
    ep = endpoints(f"udpout:127.0.0.1:{peer.getsockname()[1]}", inbox)
    try:
        assert wait_until(lambda: bool(ep.links))
        for i in range(5):
            ep.broadcast(ping(i))
        got = recv_udp(peer, 5)
        msgs = [parse_all(d)[0] for d in got]
        assert [m.time_boot_ms for m in msgs] == [0, 1, 2, 3, 4]
        assert [m.get_seq() for m in msgs] == [0, 1, 2, 3, 4]
        # the GCS answers to where the packets came from
        src = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        peer.sendto(heartbeat_bytes(), ("127.0.0.1", local_address(ep)[1]))
        assert wait_until(lambda: bool(inbox.of("HEARTBEAT")))
        msg, link = inbox.of("HEARTBEAT")[0]
        assert msg.get_srcSystem() == 255 and link is ep.links[0]
        src.close()
    finally:
        peer.close()
    c = ep.counters()
    assert c.packets_sent == 5 and c.packets_received == 1 and c.errors == 0


def _wakeups(thread: threading.Thread) -> int:
    """How many times the kernel has woken ``thread`` from a sleep (Linux)."""
    with open(f"/proc/self/task/{thread.native_id}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("voluntary_ctxt"))


def test_an_idle_udp_endpoint_thread_sleeps_until_it_has_something_to_do(
    endpoints: Callable[..., Endpoint],
) -> None:
    """A UDP endpoint's thread woke twice a second with nothing to do (its select() timed
    out at 0.5 s): at 100 Hz, 0.03 % of a core. Nothing of a datagram socket is timed but a
    ``udpin`` peer's expiry: it sleeps until a datagram or a queued packet comes."""
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    try:
        out = endpoints(f"udpout:127.0.0.1:{peer.getsockname()[1]}")
        listen = endpoints(f"udpin:127.0.0.1:{free_port()}")
        assert wait_until(lambda: bool(out.links) and local_address(listen) is not None)
        threads = [t for ep in (out, listen) if (t := ep._thread) is not None]
        assert len(threads) == 2  # both running
        before = [_wakeups(t) for t in threads]
        time.sleep(1.6)  # three of the old timeouts
        assert [_wakeups(t) for t in threads] == before
        out.broadcast(ping(1))  # a packet still goes out at once (from this thread)
        assert [parse_all(d)[0].time_boot_ms for d in recv_udp(peer, 1)] == [1]
    finally:
        peer.close()


@pytest.mark.integration
def test_udpin_learns_peers_and_answers_each_on_its_own(
    endpoints: Callable[..., Endpoint], monkeypatch: pytest.MonkeyPatch
) -> None:
    port = free_port()
    inbox = Inbox()
    ep = endpoints(f"udpin:127.0.0.1:{port}", inbox)
    a, b = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
    try:
        assert wait_until(lambda: local_address(ep) is not None)
        ep.broadcast(ping(0))  # nobody yet: counted, not an error
        assert wait_until(lambda: ep.counters().packets_unsent == 1)
        for s, sysid in ((a, 10), (b, 11)):
            s.sendto(heartbeat_bytes(sysid), ("127.0.0.1", port))
        assert wait_until(lambda: len(ep.links) == 2)
        ep.broadcast(ping(1))
        assert [parse_all(d)[0].time_boot_ms for d in recv_udp(a, 1)] == [1]
        assert [parse_all(d)[0].time_boot_ms for d in recv_udp(b, 1)] == [1]
        # a reply goes to the link it came from only
        _, link_a = next((m, lk) for m, lk in inbox.of("HEARTBEAT") if m.get_srcSystem() == 10)
        link_a.send(ping(2))
        assert [parse_all(d)[0].time_boot_ms for d in recv_udp(a, 1)] == [2]
        assert recv_udp(b, 1, timeout=0.5) == []
        # garbage on the port is counted and dropped; the endpoint lives on
        a.sendto(b"\xfd\x09\x00garbage-garbage-garbage", ("127.0.0.1", port))
        assert wait_until(lambda: ep.counters().bad_packets >= 1)
        # a silent peer is forgotten: the endpoint sleeps until the first peer's limit
        # (planned on the 60 s one); shortened under it, it is woken to plan again
        monkeypatch.setattr(E, "UDP_PEER_TIMEOUT_S", 0.3)
        ep.wake()
        assert wait_until(lambda: len(ep.links) == 0, 5.0)
    finally:
        a.close()
        b.close()


@pytest.mark.integration
def test_tcp_client_reconnects_after_the_server_drops_it(
    endpoints: Callable[..., Endpoint],
) -> None:
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", 0))
    srv.listen(2)
    srv.settimeout(DEADLINE_S)
    inbox = Inbox()
    ep = endpoints(f"tcp:127.0.0.1:{srv.getsockname()[1]}", inbox)
    try:
        conn, _ = srv.accept()
        assert wait_until(lambda: bool(ep.links))
        ep.broadcast(ping(7))
        conn.settimeout(DEADLINE_S)
        first = parse_all(conn.recv(4096))
        assert first[0].time_boot_ms == 7 and first[0].get_seq() == 0
        conn.sendall(heartbeat_bytes())
        assert wait_until(lambda: bool(inbox.of("HEARTBEAT")))
        conn.close()  # the GCS goes away ...
        conn2, _ = srv.accept()  # ... and the endpoint comes back by itself
        assert wait_until(lambda: ep.counters().connects == 2)
        ep.broadcast(ping(8))
        conn2.settimeout(DEADLINE_S)
        again = parse_all(conn2.recv(4096))
        assert again[0].time_boot_ms == 8 and again[0].get_seq() == 0  # a new link, a new seq
        conn2.close()
    finally:
        srv.close()


@pytest.mark.integration
def test_tcp_to_nobody_never_blocks_the_sender(endpoints: Callable[..., Endpoint]) -> None:
    ep = endpoints(f"tcp:127.0.0.1:{free_port(socket.SOCK_STREAM)}")
    t0 = time.monotonic()
    for i in range(1000):
        ep.broadcast(ping(i))
    assert time.monotonic() - t0 < 5.0  # generous: the point is that it returns at all
    assert wait_until(lambda: ep.counters().errors >= 1)  # connection refused, retried
    assert ep.counters().packets_unsent >= 1000


@pytest.mark.integration
def test_tcpin_serves_several_clients_each_with_its_own_sequence(
    endpoints: Callable[..., Endpoint],
) -> None:
    port = free_port(socket.SOCK_STREAM)
    inbox = Inbox()
    ep = endpoints(f"tcpin:127.0.0.1:{port}", inbox)
    assert wait_until(lambda: local_address(ep) is not None)
    c1 = socket.create_connection(("127.0.0.1", port), timeout=DEADLINE_S)
    try:
        assert wait_until(lambda: len(ep.links) == 1)
        for i in range(3):
            ep.broadcast(ping(i))
        c2 = socket.create_connection(("127.0.0.1", port), timeout=DEADLINE_S)
        try:
            assert wait_until(lambda: len(ep.links) == 2)
            ep.broadcast(ping(3))
            got1 = _read_packets(c1, 4)
            got2 = _read_packets(c2, 1)
            assert [m.get_seq() for m in got1] == [0, 1, 2, 3]
            assert [(m.get_seq(), m.time_boot_ms) for m in got2] == [(0, 3)]
            c2.sendall(heartbeat_bytes(42))
            assert wait_until(lambda: bool(inbox.of("HEARTBEAT")))
        finally:
            c2.close()
        assert wait_until(lambda: len(ep.links) == 1)
    finally:
        c1.close()


def _read_packets(sock: socket.socket, n: int) -> list[Any]:
    mav = M.MAVLink(None)
    out: list[Any] = []
    deadline = time.monotonic() + DEADLINE_S
    while len(out) < n and time.monotonic() < deadline:
        out += [m for m in (mav.parse_buffer(sock.recv(4096)) or []) if m.get_type() != "BAD_DATA"]
    return out


@pytest.mark.integration
def test_a_stuck_tcp_client_costs_only_its_own_queue(endpoints: Callable[..., Endpoint]) -> None:
    tport = free_port(socket.SOCK_STREAM)
    stuck_ep = endpoints(f"tcpin:127.0.0.1:{tport}", queue_packets=32)
    udp_peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp_peer.bind(("127.0.0.1", 0))
    udp_peer.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    live_ep = endpoints(f"udpout:127.0.0.1:{udp_peer.getsockname()[1]}", queue_packets=100_000)
    assert wait_until(lambda: local_address(stuck_ep) is not None)
    stuck = socket.create_connection(("127.0.0.1", tport), timeout=DEADLINE_S)
    stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # and it never reads
    try:
        assert wait_until(lambda: len(stuck_ep.links) == 1 and len(live_ep.links) == 1)
        n = 20_000
        # The live peer reads while the producer sends, as a ground station does: a socket
        # buffer left to fill would drop datagrams however well the endpoint did.
        got: list[bytes] = []
        reader = threading.Thread(target=lambda: got.extend(recv_udp(udp_peer, n)))
        reader.start()
        t0 = time.monotonic()
        for i in range(n):
            stuck_ep.broadcast(ping(i))
            live_ep.broadcast(ping(i))
            if i % 100 == 99:
                # The reader is a thread of this process: without pauses it waits for the
                # GIL while this loop outruns it, and the kernel drops datagrams past the
                # socket buffer however well the endpoint did (as a ground station's
                # radio would pace a real producer).
                time.sleep(0.002)
        elapsed = time.monotonic() - t0
        assert elapsed < 10.0  # the producer never waited on the stuck client
        reader.join(DEADLINE_S + 1.0)
        assert len(got) >= 0.95 * n  # the live peer got (nearly) everything, in order
        seqs = [parse_all(d)[0].time_boot_ms for d in got]
        assert seqs == sorted(seqs)
        c = stuck_ep.counters()
        assert c.packets_dropped > 0.5 * n  # the stuck one: its queue overflowed, counted
        assert c.packets_sent + c.packets_dropped >= n - stuck_ep.queue_packets
    finally:
        stuck.close()
        udp_peer.close()


@pytest.mark.integration
def test_serial_endpoint_over_a_pty(endpoints: Callable[..., Endpoint]) -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    inbox = Inbox()
    try:
        ep = endpoints(f"{os.ttyname(slave)},115200", inbox)
        assert wait_until(lambda: bool(ep.links))
        assert isinstance(ep, SerialEndpoint) and ep.baud == 115200
        for i in range(3):
            ep.broadcast(ping(i))
        mav = M.MAVLink(None)
        got: list[Any] = []
        deadline = time.monotonic() + DEADLINE_S
        os.set_blocking(master, False)
        while len(got) < 3 and time.monotonic() < deadline:
            with contextlib.suppress(BlockingIOError):
                got += mav.parse_buffer(os.read(master, 4096)) or []
            time.sleep(0.01)
        assert [m.time_boot_ms for m in got] == [0, 1, 2]
        os.write(master, b"\x00noise\x01" + heartbeat_bytes())
        assert wait_until(lambda: bool(inbox.of("HEARTBEAT")))
    finally:
        os.close(master)
        os.close(slave)


def test_a_missing_serial_device_is_retried_quietly(
    endpoints: Callable[..., Endpoint], tmp_path: Any
) -> None:
    ep = endpoints(str(tmp_path / "ttyNOPE"))
    assert wait_until(lambda: ep.counters().errors >= 1)
    ep.broadcast(ping(1))
    assert wait_until(lambda: ep.counters().packets_unsent == 1)
    assert ep.links == []


@pytest.mark.integration
def test_signed_endpoint_output_verifies_in_pymavlink(endpoints: Callable[..., Endpoint]) -> None:
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    ep = endpoints(f"udpout:127.0.0.1:{peer.getsockname()[1]}", signing=Signing(KEY), link_id=3)
    try:
        assert wait_until(lambda: bool(ep.links))
        ep.broadcast(ping(5))
        (data,) = recv_udp(peer, 1)
    finally:
        peer.close()
    (msg,) = parse_all(data, KEY)
    assert msg._signed and msg._link_id == 3 and msg.time_boot_ms == 5
    with pytest.raises(M.MAVError):
        parse_all(data, bytes(32))


@contextlib.contextmanager
def paced_udp_endpoint(
    monkeypatch: pytest.MonkeyPatch,
) -> Iterator[tuple[list[float], Any, socket.socket]]:
    """A ``udpout`` endpoint to a UDP peer (1 MiB receive buffer) on a manual clock:
    ``(now, endpoint, peer)``, the clock ``now[0]`` starting at 500 s. Not started: the
    test plays the endpoint thread's part (``_flush``) itself."""
    now = [500.0]
    monkeypatch.setattr(E, "_monotonic", lambda: now[0])
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    peer.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    ep: Any = open_endpoint(
        f"udpout:127.0.0.1:{peer.getsockname()[1]}", system_id=1, component_id=1,
        on_message=Inbox(), queue_packets=1000,
    )  # fmt: skip
    try:
        ep._open()
        yield now, ep, peer
    finally:
        ep.close(1.0)
        peer.close()


@pytest.mark.integration
def test_udp_direct_sends_are_bounded_per_window_and_the_rest_queue_in_order(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """At most _DIRECT_BURST packets per _DIRECT_WINDOW_S go out from the sender's thread;
    the rest wait for the endpoint's thread, and nothing overtakes them."""
    burst = E._DIRECT_BURST
    with paced_udp_endpoint(monkeypatch) as (now, ep, peer):
        (link,) = ep.links
        direct = [ep.send_now(link, ping(i)) for i in range(burst)]
        assert direct == [True] * burst
        assert not ep.send_now(link, ping(999))  # one window's worth went out
        now[0] += E._DIRECT_WINDOW_S * 0.9
        assert not ep.send_now(link, ping(999))  # still the same window
        now[0] += E._DIRECT_WINDOW_S * 0.2
        # A new window: Link.send sends directly again, up to the limit, then queues.
        for i in range(burst, 3 * burst):
            link.send(ping(i))
        assert [p.time_boot_ms for p in link.queue] == [i for i in range(2 * burst, 3 * burst)]
        now[0] += 1.0
        link.send(ping(3 * burst))  # the window is over, but packets wait: behind them
        assert link.queue[-1].time_boot_ms == 3 * burst
        ep._flush()
        assert not link.queue
        n = 3 * burst + 1
        got = [parse_all(d)[0] for d in recv_udp(peer, n)]
        assert [m.time_boot_ms for m in got] == list(range(n))
        assert [m.get_seq() for m in got] == list(range(n))  # framed once each, in order
        c = ep.counters()
        assert c.packets_sent == n
        assert c.bytes_sent == sum(len(m.get_msgbuf()) for m in got)


# ------------------------------------------------------ what pymavlink's own links would do
# Why the endpoints are the bridge's own (docs/mavlink.md, "What pymavlink does and what the
# bridge does instead"). These pin pymavlink's behaviour: if one fails, pymavlink changed.


@pytest.mark.integration
def test_pymavlink_udpin_sends_every_packet_to_every_address_it_ever_heard(
    endpoints: Callable[..., Endpoint],
) -> None:
    """mavutil's ``udpin`` keeps every source address that ever sent a datagram (forever
    unless told a time-out, and without a bound) and sends every packet -- an answer meant
    for one ground station too -- to all of them. Ours answers the asker only
    (test_udpin_learns_peers_and_answers_each_on_its_own), forgets a silent peer, and keeps
    at most MAX_UDP_PEERS."""
    n = E.MAX_UDP_PEERS + 4
    port = free_port()
    srv = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1)
    peers = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
    try:
        for s in peers:
            s.sendto(heartbeat_bytes(), ("127.0.0.1", port))

        def heard_all() -> bool:
            while srv.recv_match(blocking=False) is not None:
                pass
            return len(srv.clients) == n

        assert wait_until(heard_all)
        # an answer to the first ground station's command ...
        srv.mav.command_ack_send(M.MAV_CMD_REQUEST_MESSAGE, 0)
        # ... reaches every one of them
        assert all(len(recv_udp(s, 1, timeout=2.0)) == 1 for s in peers)
        for s in peers[1:]:
            s.close()
        srv.mav.heartbeat_send(6, 8, 0, 0, 0)
        assert len(srv.clients) == n  # the gone ones are still sent to
    finally:
        for s in peers:
            s.close()
        srv.close()
    # ours, heard by as many: bounded
    ours = endpoints(f"udpin:127.0.0.1:{port}")
    peers = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
    try:
        assert wait_until(lambda: local_address(ours) is not None)
        for s in peers:
            s.sendto(heartbeat_bytes(), ("127.0.0.1", port))
        # the first MAX_UDP_PEERS send HEARTBEATs: none is dropped for the newcomers
        assert wait_until(lambda: ours.counters().peers_refused == n - E.MAX_UDP_PEERS)
        assert len(ours.links) == E.MAX_UDP_PEERS
        assert ours.counters().packets_received == E.MAX_UDP_PEERS
    finally:
        for s in peers:
            s.close()


@pytest.mark.integration
def test_pymavlink_tcp_loses_silently_what_a_slow_peer_cannot_take() -> None:
    """mavutil's ``tcp`` link never blocks (its socket is non-blocking), but every packet
    that does not fit the socket's buffers is dropped without an error or a count -- a
    ground station that stalls for a moment loses a stretch of the stream and nobody can
    tell. Ours queues per peer, drops the oldest when the queue is full and counts them
    (test_a_stuck_tcp_client_costs_only_its_own_queue)."""
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    conn = mavutil.mavlink_connection(
        f"tcp:127.0.0.1:{server.getsockname()[1]}", source_system=1, source_component=1
    )
    peer, _ = server.accept()
    try:
        conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        n = 3000
        for i in range(n):  # the peer reads nothing meanwhile
            conn.write(ping(i).pack(conn.mav))  # never raises, never waits
        peer.settimeout(0.5)
        data = b""
        with contextlib.suppress(TimeoutError):
            while chunk := peer.recv(65536):
                data += chunk
        got = [m.time_boot_ms for m in parse_all(data)]
        assert got == sorted(got) and len(got) < n // 2  # most of the stream is gone ...
        assert got[-1] - got[0] + 1 > len(got)  # ... in silent gaps
    finally:
        peer.close()
        conn.close()
        server.close()


@pytest.mark.integration
@pytest.mark.parametrize("kind", ["udpout", "udpin", "tcp", "tcpin"])
def test_every_network_kind_works_over_ipv6_loopback(
    endpoints: Callable[..., Endpoint], kind: str
) -> None:
    """``[::1]`` as the host: the endpoint sends to, hears and answers a peer on IPv6 alone
    (a companion computer's ground station link may be IPv6 only)."""
    inbox = Inbox()
    dgram = kind.startswith("udp")
    peer = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM if dgram else socket.SOCK_STREAM)
    try:
        if kind == "udpout":
            peer.bind(("::1", 0))
            ep = endpoints(f"udpout:[::1]:{peer.getsockname()[1]}", inbox)
        elif kind == "tcp":
            peer.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            peer.bind(("::1", 0))
            peer.listen(1)
            peer.settimeout(DEADLINE_S)
            ep = endpoints(f"tcp:[::1]:{peer.getsockname()[1]}", inbox)
            conn, _ = peer.accept()
            peer.close()
            peer = conn
        else:
            port = free_port(socket.SOCK_DGRAM if dgram else socket.SOCK_STREAM)
            ep = endpoints(f"{kind}:[::1]:{port}", inbox)
            assert wait_until(lambda: local_address(ep) is not None)
            assert local_address(ep)[0] == "::1"
            if dgram:
                peer.sendto(heartbeat_bytes(), ("::1", port))  # udpin learns its peer
            else:
                peer.connect(("::1", port))
        peer.settimeout(DEADLINE_S)
        assert wait_until(lambda: bool(ep.links))
        ep.broadcast(ping(5))
        data = peer.recvfrom(4096)[0] if dgram else peer.recv(4096)
        assert [m.time_boot_ms for m in parse_all(data)] == [5]
        if kind != "udpin":  # (udpin heard its peer's HEARTBEAT above)
            if dgram:
                peer.sendto(heartbeat_bytes(), ("::1", local_address(ep)[1]))
            else:
                peer.sendall(heartbeat_bytes())
        assert wait_until(lambda: bool(inbox.of("HEARTBEAT")))
        _, link = inbox.of("HEARTBEAT")[0]
        link.send(ping(6))  # the answer goes back over IPv6 to that peer
        data = peer.recvfrom(4096)[0] if dgram else peer.recv(4096)
        assert [m.time_boot_ms for m in parse_all(data)] == [6]
        assert ep.counters().errors == 0
    finally:
        peer.close()
