"""UDP endpoints: ``udpout`` (a fixed destination) and ``udpin`` (listen; answer who spoke).

``udpin`` answers the peers it has heard a valid frame from (a validly signed one
when signing is on): a datagram from an unknown address is parsed on its own
(a datagram holds whole packets) and makes its sender a peer only if it holds
one; anything else is counted (``strangers_dropped``) and forgotten. With all
:data:`~bridge.mavlink.endpoints.base.MAX_UDP_PEERS` places taken, a newcomer
replaces the least recently heard peer that sends no HEARTBEAT, or is turned
away (``peers_refused``): a ground station's one HEARTBEAT a second keeps it a
peer whatever strangers send. The port is bound without ``SO_REUSEADDR``: on
Linux that option lets a second socket bind the same UDP port and take the
ground station's datagrams, so a second bridge (or any process) gets "address
in use" -- said in the log, retried -- instead of a share of the traffic.
"""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import threading
from collections.abc import Sequence
from typing import Any

from bridge.config import MavlinkEndpoint
from bridge.mavlink.dialect import IFLAG_SIGNED, MAGIC_V2, Message, mavlink
from bridge.mavlink.endpoints import base
from bridge.mavlink.endpoints.base import (
    _READ_BYTES,
    MAX_DATAGRAM_BYTES,
    MAX_UDP_PEERS,
    Endpoint,
    Link,
    _resolve,
    _whole_packets,
)

log = logging.getLogger(__name__)

_UDPIN_RCVBUF = 1 << 20


class UdpEndpoint(Endpoint):
    """``udpout`` (fixed destination) and ``udpin``/``udp`` (listen; reply to who spoke)."""

    def __init__(self, spec: MavlinkEndpoint, **kw: Any) -> None:
        super().__init__(spec, **kw)
        self.kind = "udpout" if spec.kind == "udpout" else "udpin"
        self._sock: socket.socket | None = None
        self._by_addr: dict[Any, Link] = {}
        # Framing (the per-link sequence number) and sendto happen in the endpoint's thread
        # (_flush) and in senders' threads (send_now): one at a time. packets_sent and
        # bytes_sent of a UDP endpoint are only ever written under this lock, so they are
        # counted there without the counters' own lock (counters() may see one of the two
        # already counted and not the other, as it could before).
        self._send_lock = threading.Lock()
        self._direct_window = 0.0  # start of the current direct-send window (monotonic)
        self._direct_count = 0  # packets sent directly in it

    #: Nothing of a datagram socket's is timed but a ``udpin`` peer's expiry and a reopen
    #: (:meth:`_next_timer`): the thread sleeps until a datagram, a queued packet or one of
    #: them -- not twice a second for nothing.
    max_wait_s = math.inf

    def _is_open(self) -> bool:
        return self._sock is not None

    def _next_timer(self, now: float) -> float:
        if self._sock is None:
            return self._retry_at
        if self.kind == "udpin" and self._by_addr:
            # The first peer to fall silent for good (a millisecond after, so the look
            # that wakes for it finds it past the limit, not on it).
            heard = min(link.last_heard for link in self._by_addr.values())
            return heard + base.UDP_PEER_TIMEOUT_S + 0.001
        return math.inf

    def send_now(self, link: Link, packet: Message) -> bool:
        """A datagram needs no waiting: frame and send it here, unless packets wait ahead of it."""
        lock = self._send_lock
        if not lock.acquire(blocking=False):
            return False  # the endpoint's thread is sending: queue behind it
        try:
            sock = self._sock
            if sock is None or link.closed or link.queue or link.pending:
                return False
            if not self._direct_budget(1):
                return False  # the burst window is used up: queue it
            data = link.frame(packet)
            try:
                n = sock.sendto(data, link.address)
            except (BlockingIOError, InterruptedError):
                link.pending[:] = data  # the endpoint's thread sends it when writable
                self.wake()
                return True
            except OSError as e:
                self._count("errors")
                log.debug("mavlink %s: sendto %s: %s", self.name, link.address, e)
                return True  # lost, as in _flush: the endpoint lives on
            c = self._counters  # under _send_lock: see __init__
            c.packets_sent += 1
            c.bytes_sent += n
            return True
        finally:
            lock.release()

    def send_now_many(self, link: Link, packets: Sequence[Message]) -> int:
        """Several packets in as few datagrams as :data:`MAX_DATAGRAM_BYTES` allows.

        The same rules as :meth:`send_now`, per packet: nothing overtakes what
        waits, the burst window counts packets, each packet is framed (its
        sequence number spent) once, in order. A datagram that would block goes
        to ``link.pending`` with every framed packet after it, for the endpoint's
        thread (:meth:`_flush_locked` cuts them into datagrams again).
        """
        lock = self._send_lock
        if not lock.acquire(blocking=False):
            return 0  # the endpoint's thread is sending: queue behind it
        try:
            sock = self._sock
            if sock is None or link.closed or link.queue or link.pending:
                return 0
            take = self._direct_budget(len(packets))
            if not take:
                return 0
            frame = link.frame
            frames = [frame(p) for p in packets[:take]]
            address, c = link.address, self._counters  # counters: under _send_lock
            i = 0
            while i < take:
                size, j = len(frames[i]), i + 1
                while j < take and size + len(frames[j]) <= MAX_DATAGRAM_BYTES:
                    size += len(frames[j])
                    j += 1
                data = frames[i] if j == i + 1 else b"".join(frames[i:j])
                try:
                    n = sock.sendto(data, address)
                except (BlockingIOError, InterruptedError):
                    link.pending[:] = b"".join(frames[i:])  # framed: their seqs are spent
                    self.wake()
                    return take
                except OSError as e:
                    self._count("errors")  # this datagram is lost, as in _flush
                    log.debug("mavlink %s: sendto %s: %s", self.name, address, e)
                else:
                    c.packets_sent += j - i
                    c.bytes_sent += n
                i = j
            return take
        finally:
            lock.release()

    def _direct_budget(self, n: int) -> int:
        """How many of ``n`` packets the burst window lets go out directly now (counted as
        gone). Under ``_send_lock``.

        The window needs the clock only once its count could matter: a frame's few
        packets never read it, a parameter list does from its 16th packet on.
        """
        taken = 0
        while taken < n:
            count = self._direct_count
            if count >= base._DIRECT_BURST:
                now = base._monotonic()
                if now - self._direct_window < base._DIRECT_WINDOW_S:
                    break
                self._direct_window, count = now, 0
            elif count == 0:
                self._direct_window = base._monotonic()
            k = min(n - taken, base._DIRECT_BURST - count)
            self._direct_count = count + k
            taken += k
        return taken

    def _open(self) -> None:
        family, addr = _resolve(self.spec.host, self.spec.port, socket.SOCK_DGRAM)
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.setblocking(False)
            if self.kind == "udpin":
                # Room for a burst of datagrams while this thread is busy (the kernel caps
                # it at net.core.rmem_max): a flood overflows into strangers, not the GCS.
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _UDPIN_RCVBUF)
                sock.bind(addr)  # alone: no SO_REUSEADDR (see the module docstring)
            else:
                # The GCS may be a broadcast address (udpout:192.168.1.255:14550).
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        except OSError:
            sock.close()
            raise
        self._sock = sock
        if self.kind == "udpout":
            link = Link(self, f"{self.name}", address=addr)
            self._links = [link]
            self._by_addr = {}
        self._opened()

    @property
    def local_address(self) -> Any:
        """The bound address (tests: the ephemeral port of ``udpout``)."""
        return self._sock.getsockname() if self._sock is not None else None

    def _select_sets(self) -> tuple[list[Any], list[Any]]:
        if self._sock is None:
            return [], []
        blocked = any(link.pending for link in self._links)
        return [self._sock], ([self._sock] if blocked else [])

    def _readable(self, obj: Any) -> None:
        sock = self._sock
        if sock is None:
            return
        for _ in range(64):  # bounded: the writer side must get its turn
            try:
                data, addr = sock.recvfrom(_READ_BYTES)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:
                # ICMP errors (port unreachable) surface here on Linux: not fatal for UDP.
                self._count("errors")
                log.debug("mavlink %s: recv: %s", self.name, e)
                return
            if self.kind == "udpout":
                self._deliver(self._links[0], data)
                continue
            link = self._by_addr.get(addr)
            if link is not None:
                self._deliver(link, data)
                continue
            parsed = self._stranger(data)
            if parsed is None:
                self._count("strangers_dropped")
                continue
            link = self._new_peer(addr)
            if link is not None:
                self._deliver(link, data, parsed)

    def _stranger(self, data: bytes) -> list[tuple[Any, bool]] | None:
        """What a datagram from an unknown address holds, if it may make a peer (None: not)."""
        if not data or data[0] not in (MAGIC_V2, 0xFE):
            return None  # a datagram starts with a packet: junk is dropped unparsed
        signed = data[0] == MAGIC_V2 and len(data) > 2 and bool(data[2] & IFLAG_SIGNED)
        if self.signing is not None and not signed:
            return None  # signing on: an unsigned packet makes nobody a peer
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        parsed = self._parse(parser, data)
        if not parsed or not any(authentic for _, authentic in parsed):
            return None
        return parsed

    def _new_peer(self, addr: Any) -> Link | None:
        """A link for a new peer, or None when every place is held by a protected peer."""
        if len(self._by_addr) >= MAX_UDP_PEERS:
            now = base._monotonic()
            idle = [lk for lk in self._by_addr.values() if self._evictable(lk, now)]
            if not idle:
                self._count("peers_refused")
                return None
            self._forget(min(idle, key=lambda lk: lk.last_heard))
            self._count("peers_evicted")
        host, port = addr[0], addr[1]
        link = Link(self, f"{self.name} <- {host}:{port}", address=addr)
        self._by_addr[addr] = link
        self._links = [*self._links, link]
        self._count("connects")
        log.info("mavlink %s: new peer %s:%s", self.name, host, port)
        return link

    def _forget(self, link: Link) -> None:
        self._by_addr.pop(link.address, None)
        self._drop_link(link)

    def _writable(self, obj: Any) -> None:
        """Writes happen in :meth:`_flush`; writability just ends the wait."""

    def _flush(self) -> None:
        with self._send_lock:
            self._flush_locked()

    def _flush_locked(self) -> None:
        sock = self._sock
        if sock is None:
            return
        for link in list(self._links):
            q = link.queue
            pending = link.pending
            while True:
                if pending:
                    # Framed before (their seqs are spent): resend them, whole packets,
                    # a datagram at a time.
                    end, k = _whole_packets(pending, MAX_DATAGRAM_BYTES)
                    data = bytes(pending[:end])
                else:
                    try:
                        p = q.popleft()
                    except IndexError:
                        break
                    data, end, k = link.frame(p), 0, 1
                try:
                    n = sock.sendto(data, link.address)
                except (BlockingIOError, InterruptedError):
                    if not pending:
                        pending[:] = data
                    return
                except OSError as e:
                    # Unreachable network/host, refused: the datagram is lost, the
                    # endpoint lives on (a GCS may come up later).
                    self._count("errors")
                    log.debug("mavlink %s: sendto %s: %s", self.name, link.address, e)
                    n = -1
                del pending[:end]
                if n >= 0:
                    c = self._counters  # under _send_lock: see __init__
                    c.packets_sent += k
                    c.bytes_sent += n

    def _housekeeping(self, now: float) -> None:
        if self.kind != "udpin":
            return
        for link in list(self._by_addr.values()):
            if now - link.last_heard > base.UDP_PEER_TIMEOUT_S:
                log.info("mavlink %s: peer %s silent, forgotten", self.name, link.address)
                self._forget(link)

    def _close_transport(self) -> None:
        with self._send_lock:  # not under a send_now() in another thread
            if self._sock is not None:
                with contextlib.suppress(OSError):
                    self._sock.close()
            self._sock = None
        for link in list(self._links):
            self._drop_link(link)
        self._by_addr = {}
