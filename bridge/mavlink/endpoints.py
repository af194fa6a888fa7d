"""MAVLink endpoints: UDP, TCP and serial links, each on its own thread, never blocking anyone.

Every configured endpoint (``mavlink.endpoints``, pymavlink connection-string
syntax) becomes one :class:`Endpoint` running one thread around ``select()``
on non-blocking sockets (or a non-blocking tty). An endpoint has one or more
:class:`Link` objects -- the peers it talks to -- each with

* a bounded queue of :class:`~bridge.mavlink.wire.Packet` (encoded once by
  the producer): :meth:`Link.send` appends and returns at once; when the
  queue is full the *oldest* packet is dropped and counted (telemetry ages,
  the newest is worth most);
* its own :class:`~bridge.mavlink.wire.Framer` (sequence number, signature),
  framing at the moment of writing;
* :meth:`Link.send_many` for packets that belong together (one frame's
  telemetry): a UDP peer gets them framed back to back in one datagram (at
  most :data:`MAX_DATAGRAM_BYTES`, more datagrams otherwise), as ArduPilot
  packs its UDP link; every MAVLink parser reads all the messages of a datagram;
* its own pymavlink parser for what the peer sends; every message goes to the
  ``on_message(msg, link)`` callback, in this endpoint's thread (the callback
  must hand it on quickly).

So a dead or slow peer costs only its own queue: a TCP client that stops
reading fills its socket buffer, then its queue, then drops; a serial radio
at 57600 baud drops what it cannot carry; nothing waits on them.

Kinds (as pymavlink spells them):

=================  ===================================================================
``udpout:H:P``     send to H:P from an ephemeral port; answers come back to that port
``udpin:H:P``      listen on H:P; every address heard from (last 60 s, up to 16) is a peer
``udp:H:P``        same as ``udpin`` (pymavlink's historical spelling)
``tcp:H:P``        connect to H:P; reconnect with backoff (0.5 s doubling to 5 s)
``tcpin:H:P``      listen on H:P; up to 8 clients, each its own link
``/dev/X[,BAUD]``  serial port (default 57600 baud, telemetry radios); reopened if it goes
=================  ===================================================================
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import select
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any

from bridge.config import MavlinkEndpoint, parse_mavlink_endpoint
from bridge.mavlink.dialect import IFLAG_SIGNED, MAGIC_V2, mavlink
from bridge.mavlink.signing import Signing
from bridge.mavlink.wire import Framer, Packet

log = logging.getLogger(__name__)

MessageHandler = Callable[[Any, "Link"], None]

DEFAULT_SERIAL_BAUD = 57600
DEFAULT_QUEUE_PACKETS = 64
UDP_PEER_TIMEOUT_S = 60.0
MAX_UDP_PEERS = 16
MAX_TCP_CLIENTS = 8
CONNECT_TIMEOUT_S = 5.0
BACKOFF_INITIAL_S = 0.5
BACKOFF_MAX_S = 5.0
_MAX_WAIT_S = 0.5  # select() timeout: bounds how late close() and timers are noticed
_READ_BYTES = 65536
_PENDING_LOW_WATER = 8192  # stream links: refill the byte buffer below this
#: UDP: at most this many packets per _DIRECT_WINDOW_S go out from the sender's thread
#: (a frame's telemetry); a larger burst (a parameter list) is queued for the endpoint's
#: thread, so a sender's time per call stays bounded and bursts keep their old pacing.
_DIRECT_BURST = 16
_DIRECT_WINDOW_S = 0.01
#: UDP: several packets sent together share a datagram up to this size. Below the
#: Ethernet MTU (1500 - 28 bytes of IP and UDP headers) with room for a tunnel's
#: overhead (VPN, WireGuard), so no datagram is ever fragmented; a MAVLink 2 packet is
#: at most 280 bytes, so every datagram holds at least one whole packet.
MAX_DATAGRAM_BYTES = 1400
_monotonic = time.monotonic  # the direct-send window's clock (a test steps it)


@dataclass(slots=True)
class EndpointCounters:
    """Per-endpoint counters (cumulative); read them with :meth:`Endpoint.counters`."""

    packets_sent: int = 0
    bytes_sent: int = 0
    packets_dropped: int = 0  #: queue overflow (slow or stuck peer)
    packets_unsent: int = 0  #: offered while no peer was there (not connected, nobody heard yet)
    packets_received: int = 0
    bad_packets: int = 0  #: CRC / framing errors on input
    connects: int = 0  #: successful opens / connections / accepted clients
    errors: int = 0  #: socket or port errors

    def snapshot(self) -> EndpointCounters:
        """A copy."""
        return EndpointCounters(**{f.name: getattr(self, f.name) for f in fields(self)})


class Link:
    """One peer of an endpoint: queue, framer, parser.

    :meth:`send` may be called from any thread; everything else belongs to the
    endpoint's thread.
    """

    __slots__ = (
        "address",
        "closed",
        "endpoint",
        "framer",
        "last_heard",
        "limit",
        "name",
        "parser",
        "pending",
        "queue",
        "sock",
    )

    def __init__(
        self,
        endpoint: Endpoint,
        name: str,
        *,
        address: Any = None,
        sock: socket.socket | None = None,
    ) -> None:
        self.endpoint = endpoint
        self.name = name
        self.address = address
        self.sock = sock
        self.framer = endpoint.make_framer()
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True  # garbage becomes bad_data, never an exception
        self.queue: deque[Packet] = deque()
        self.limit = endpoint.queue_packets
        self.pending = bytearray()
        self.last_heard = time.monotonic()
        self.closed = False

    def send(self, packet: Packet) -> None:
        """Queue ``packet`` for this peer; never blocks (drops the oldest when full).

        A UDP endpoint with nothing queued sends it at once from the calling
        thread instead (a non-blocking ``sendto``): no wake-up of the endpoint's
        thread for every telemetry message.
        """
        if self.closed:
            self.endpoint.count_unsent()
            return
        q = self.queue
        if not q and self.endpoint.send_now(self, packet):
            return
        if len(q) >= self.limit:
            try:
                q.popleft()
            except IndexError:  # the endpoint thread emptied it meanwhile
                pass
            else:
                self.endpoint.count_dropped()
        q.append(packet)
        self.endpoint.wake()

    def send_many(self, packets: Sequence[Packet]) -> None:
        """Queue ``packets`` for this peer, in order, as :meth:`send` does each; never blocks.

        A UDP endpoint with nothing queued sends them at once from the calling
        thread, framed back to back in as few datagrams as fit
        (:data:`MAX_DATAGRAM_BYTES`): one ``sendto`` for a frame's telemetry
        instead of one per message. What it cannot send directly (the burst
        window is used up) is queued behind, as :meth:`send` would queue it.
        """
        if self.closed:
            self.endpoint.count_unsent(len(packets))
            return
        q = self.queue
        done = self.endpoint.send_now_many(self, packets) if not q else 0
        if done >= len(packets):
            return
        limit, dropped = self.limit, 0
        for p in packets[done:]:
            if len(q) >= limit:
                try:
                    q.popleft()
                except IndexError:  # the endpoint thread emptied it meanwhile
                    pass
                else:
                    dropped += 1
            q.append(p)
        if dropped:
            self.endpoint.count_dropped(dropped)
        self.endpoint.wake()

    def __repr__(self) -> str:
        return f"<Link {self.name}>"


class Endpoint:
    """Base of the endpoint kinds: the thread, the wake-up pipe, links and counters."""

    kind = "?"

    def __init__(
        self,
        spec: MavlinkEndpoint,
        *,
        system_id: int,
        component_id: int,
        on_message: MessageHandler,
        signing: Signing | None = None,
        link_id: int = 0,
        queue_packets: int = DEFAULT_QUEUE_PACKETS,
    ) -> None:
        if queue_packets < 1:
            raise ValueError("queue_packets must be >= 1")
        self.spec = spec
        self.name = spec.text
        self.system_id = system_id
        self.component_id = component_id
        self.on_message = on_message
        self.signing = signing
        self.link_id = link_id & 0xFF
        self.queue_packets = queue_packets
        self._counters = EndpointCounters()
        self._count_lock = threading.Lock()
        # Never changed in place, only replaced (one reference store): broadcast() in any
        # thread iterates the list it read without copying it.
        self._links: list[Link] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._wake_pending = False
        self._backoff = BACKOFF_INITIAL_S
        self._retry_at = 0.0
        self._last_error = ""

    # ------------------------------------------------------------------ public

    def send_now(self, link: Link, packet: Packet) -> bool:
        """Send ``packet`` to ``link`` from the calling thread if that cannot block; True if done.

        False (the default) means "queue it for the endpoint's thread".
        """
        return False

    def send_now_many(self, link: Link, packets: Sequence[Packet]) -> int:
        """Send a leading part of ``packets`` to ``link`` from the calling thread if that
        cannot block; how many were taken (sent, left in ``link.pending`` for the
        endpoint's thread, or lost to a socket error, as :meth:`send_now` counts them).

        0 (the default) means "queue them all for the endpoint's thread".
        """
        return 0

    def make_framer(self) -> Framer:
        """A new framer for a link of this endpoint (our ids, signing, link id)."""
        return Framer(self.system_id, self.component_id, signing=self.signing, link_id=self.link_id)

    @property
    def links(self) -> list[Link]:
        """The current peers (a snapshot)."""
        return list(self._links)

    def counters(self) -> EndpointCounters:
        """A snapshot of the counters."""
        with self._count_lock:
            return self._counters.snapshot()

    def broadcast(self, packet: Packet) -> None:
        """Queue ``packet`` for every current peer (counted as unsent when there is none)."""
        links = self._links  # replaced, never changed in place: no copy needed
        if not links:
            self.count_unsent()
            return
        for link in links:
            link.send(packet)

    def broadcast_many(self, packets: Sequence[Packet]) -> None:
        """Queue ``packets`` (in order, together: see :meth:`Link.send_many`) for every peer."""
        links = self._links  # replaced, never changed in place: no copy needed
        if not links:
            self.count_unsent(len(packets))
            return
        for link in links:
            link.send_many(packets)

    def start(self) -> Endpoint:
        """Start the endpoint's thread."""
        if self._thread is not None:
            raise RuntimeError(f"{self.name} already started")
        self._thread = threading.Thread(target=self._run, name=f"mavlink-{self.kind}", daemon=True)
        self._thread.start()
        return self

    def close(self, timeout: float = 2.0) -> None:
        """Stop the thread and close everything within about ``timeout`` seconds."""
        self._stop.set()
        self.wake()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("mavlink %s: thread did not stop within %.1f s", self.name, timeout)
                return  # it still owns the sockets; do not close them under it
        self._shutdown()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)

    # ------------------------------------------------------------------ counting (any thread)

    def wake(self) -> None:
        """Make the thread look at its queues (cheap when it is already due to)."""
        if self._wake_pending:
            return
        self._wake_pending = True
        with contextlib.suppress(OSError):  # full pipe: already awake; closed: stopping
            os.write(self._wake_w, b"\0")

    def count_dropped(self, n: int = 1) -> None:
        """Packets lost to a full queue."""
        with self._count_lock:
            self._counters.packets_dropped += n

    def count_unsent(self, n: int = 1) -> None:
        """Packets offered while there was nobody to send them to."""
        with self._count_lock:
            self._counters.packets_unsent += n

    def _count(self, name: str, n: int = 1) -> None:
        with self._count_lock:
            setattr(self._counters, name, getattr(self._counters, name) + n)

    # ------------------------------------------------------------------ the thread

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if not self._is_open() and now >= self._retry_at:
                    self._try_open()
                rlist, wlist = self._select_sets()
                timeout = min(_MAX_WAIT_S, max(0.0, self._next_timer(now) - now))
                try:
                    r, w, _ = select.select([self._wake_r, *rlist], wlist, [], timeout)
                except (OSError, ValueError):
                    # A socket closed under select (peer reset): rebuild the sets next round.
                    self._prune_closed()
                    continue
                if self._wake_r in r:
                    with contextlib.suppress(OSError):
                        os.read(self._wake_r, 4096)
                    # Cleared *before* the queues are looked at: a send() after this
                    # point writes the pipe again, so none is missed.
                    self._wake_pending = False
                for obj in r:
                    if obj != self._wake_r:
                        self._readable(obj)
                for obj in w:
                    self._writable(obj)
                self._flush()
                self._housekeeping(time.monotonic())
        except Exception:
            log.exception("mavlink %s: endpoint thread crashed", self.name)
        finally:
            self._shutdown()

    def _try_open(self) -> None:
        try:
            self._open()
        except OSError as e:
            self._count("errors")
            msg = f"{type(e).__name__}: {e}"
            if msg != self._last_error:  # say it once per distinct failure, not every retry
                log.warning("mavlink %s: cannot open (%s); retrying", self.name, msg)
                self._last_error = msg
            self._close_transport()
            self._retry_at = time.monotonic() + self._backoff
            self._backoff = min(2 * self._backoff, BACKOFF_MAX_S)

    def _opened(self) -> None:
        """Subclasses call this when the transport is up."""
        self._count("connects")
        self._backoff = BACKOFF_INITIAL_S
        if self._last_error:
            log.info("mavlink %s: open again", self.name)
        self._last_error = ""

    def _lost(self, why: str) -> None:
        """The transport failed: close it and retry later."""
        self._count("errors")
        if why != self._last_error:
            log.warning("mavlink %s: %s; reconnecting", self.name, why)
            self._last_error = why
        self._close_transport()
        self._retry_at = time.monotonic() + self._backoff
        self._backoff = min(2 * self._backoff, BACKOFF_MAX_S)

    def _deliver(self, link: Link, data: bytes) -> None:
        """Parse bytes from ``link``'s peer and hand each message on."""
        link.last_heard = time.monotonic()
        try:
            msgs = link.parser.parse_buffer(data) or []
        except Exception:  # a parser bug must not kill the endpoint
            self._count("bad_packets")
            link.parser = mavlink.MAVLink(None)
            link.parser.robust_parsing = True
            return
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self._count("bad_packets")
                continue
            self._count("packets_received")
            try:
                self.on_message(msg, link)
            except Exception:
                log.exception("mavlink %s: message handler failed", self.name)

    def _drop_link(self, link: Link) -> None:
        link.closed = True
        n = len(link.queue)
        link.queue.clear()
        if n:
            self.count_unsent(n)
        if link in self._links:
            self._links = [lk for lk in self._links if lk is not link]

    def _fill(self, link: Link) -> None:
        """Stream links: frame queued packets into the byte buffer."""
        q, buf, frame = link.queue, link.pending, link.framer.frame
        n = 0
        while q and len(buf) < _PENDING_LOW_WATER:
            try:
                p = q.popleft()
            except IndexError:
                break
            buf += frame(p)
            n += 1
        if n:
            self._count("packets_sent", n)

    def _prune_closed(self) -> None:
        for link in list(self._links):
            if link.sock is not None and link.sock.fileno() < 0:
                self._drop_link(link)

    # ------------------------------------------------------------------ hooks

    def _is_open(self) -> bool:
        raise NotImplementedError

    def _open(self) -> None:
        raise NotImplementedError

    def _select_sets(self) -> tuple[list[Any], list[Any]]:
        raise NotImplementedError

    def _readable(self, obj: Any) -> None:
        raise NotImplementedError

    def _writable(self, obj: Any) -> None:
        raise NotImplementedError

    def _flush(self) -> None:
        """Write what can be written without waiting (called every round)."""

    def _next_timer(self, now: float) -> float:
        return self._retry_at if not self._is_open() else now + _MAX_WAIT_S

    def _housekeeping(self, now: float) -> None:
        """Timers: peer expiry, connect timeouts."""

    def _close_transport(self) -> None:
        raise NotImplementedError

    def _shutdown(self) -> None:
        self._close_transport()


def _whole_packets(buf: bytearray, limit: int) -> tuple[int, int]:
    """(length, count) of the longest run of whole framed packets at the start of ``buf``
    that fits in ``limit`` bytes -- at least one packet, however long.

    ``buf`` holds packets our own :class:`~bridge.mavlink.wire.Framer` made
    (MAVLink 2: 10-byte header, payload, 2-byte CRC, 13-byte signature when the
    incompat flag says so). Bytes that are not such a packet (never expected)
    are taken whole as one, so they still leave rather than wedge the link.
    """
    size, end, k = len(buf), 0, 0
    while end < size:
        if buf[end] == MAGIC_V2 and end + 3 <= size:
            nxt = end + 12 + buf[end + 1] + (13 if buf[end + 2] & IFLAG_SIGNED else 0)
        else:
            nxt = size
        if k and nxt > limit:
            break
        end, k = min(nxt, size), k + 1
    return end, k


def _resolve(host: str, port: int, kind: int) -> tuple[int, Any]:
    """(family, sockaddr) of the first address for host:port."""
    infos = socket.getaddrinfo(host, port, 0, kind)
    if not infos:  # pragma: no cover - getaddrinfo raises instead
        raise OSError(errno.EADDRNOTAVAIL, f"no address for {host}:{port}")
    family, _type, _proto, _canon, addr = infos[0]
    return family, addr


# ---------------------------------------------------------------------------- UDP


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

    def _is_open(self) -> bool:
        return self._sock is not None

    def send_now(self, link: Link, packet: Packet) -> bool:
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
            data = link.framer.frame(packet)
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

    def send_now_many(self, link: Link, packets: Sequence[Packet]) -> int:
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
            frame = link.framer.frame
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
            if count >= _DIRECT_BURST:
                now = _monotonic()
                if now - self._direct_window < _DIRECT_WINDOW_S:
                    break
                self._direct_window, count = now, 0
            elif count == 0:
                self._direct_window = _monotonic()
            k = min(n - taken, _DIRECT_BURST - count)
            self._direct_count = count + k
            taken += k
        return taken

    def _open(self) -> None:
        family, addr = _resolve(self.spec.host, self.spec.port, socket.SOCK_DGRAM)
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.setblocking(False)
            if self.kind == "udpin":
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind(addr)
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
            self._deliver(self._link_for(addr), data)

    def _link_for(self, addr: Any) -> Link:
        if self.kind == "udpout":
            return self._links[0]
        link = self._by_addr.get(addr)
        if link is None:
            if len(self._by_addr) >= MAX_UDP_PEERS:
                oldest = min(self._by_addr.values(), key=lambda lk: lk.last_heard)
                self._forget(oldest)
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
                    data, end, k = link.framer.frame(p), 0, 1
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
            if now - link.last_heard > UDP_PEER_TIMEOUT_S:
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


# ---------------------------------------------------------------------------- TCP client


class TcpClientEndpoint(Endpoint):
    """``tcp:HOST:PORT``: connect, and reconnect with backoff whenever the connection goes."""

    kind = "tcp"

    def __init__(self, spec: MavlinkEndpoint, **kw: Any) -> None:
        super().__init__(spec, **kw)
        self._sock: socket.socket | None = None
        self._connecting_since: float | None = None
        self._link: Link | None = None

    def _is_open(self) -> bool:
        return self._sock is not None

    def _open(self) -> None:
        family, addr = _resolve(self.spec.host, self.spec.port, socket.SOCK_STREAM)
        sock = socket.socket(family, socket.SOCK_STREAM)
        sock.setblocking(False)
        err = sock.connect_ex(addr)
        if err not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK):
            sock.close()
            raise OSError(err, os.strerror(err))
        self._sock = sock
        self._connecting_since = time.monotonic()
        if err == 0:
            self._connected()

    def _connected(self) -> None:
        assert self._sock is not None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._connecting_since = None
        self._link = Link(self, self.name, sock=self._sock)
        self._links = [self._link]
        self._opened()
        log.info("mavlink %s: connected", self.name)

    def _select_sets(self) -> tuple[list[Any], list[Any]]:
        sock = self._sock
        if sock is None:
            return [], []
        if self._connecting_since is not None:
            return [], [sock]
        link = self._link
        want_write = link is not None and bool(link.pending or link.queue)
        return [sock], ([sock] if want_write else [])

    def _readable(self, obj: Any) -> None:
        sock, link = self._sock, self._link
        if sock is None or link is None:
            return
        try:
            data = sock.recv(_READ_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            self._lost(f"connection lost ({e})")
            return
        if not data:
            self._lost("connection closed by the peer")
            return
        self._deliver(link, data)

    def _writable(self, obj: Any) -> None:
        sock = self._sock
        if sock is None:
            return
        if self._connecting_since is not None:
            err = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
            if err:
                self._lost(f"connect failed ({os.strerror(err)})")
            else:
                self._connected()

    def _flush(self) -> None:
        sock, link = self._sock, self._link
        if sock is None or link is None or self._connecting_since is not None:
            return
        self._fill(link)
        if not link.pending:
            return
        try:
            n = sock.send(link.pending)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            self._lost(f"connection lost ({e})")
            return
        del link.pending[:n]
        self._count("bytes_sent", n)

    def _next_timer(self, now: float) -> float:
        if self._connecting_since is not None:
            return self._connecting_since + CONNECT_TIMEOUT_S
        return super()._next_timer(now)

    def _housekeeping(self, now: float) -> None:
        if self._connecting_since is not None and now - self._connecting_since > CONNECT_TIMEOUT_S:
            self._lost(f"connect timed out after {CONNECT_TIMEOUT_S:g} s")

    def _close_transport(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
        self._sock = None
        self._connecting_since = None
        if self._link is not None:
            self._drop_link(self._link)
        self._link = None
        self._links = []


# ---------------------------------------------------------------------------- TCP server


class TcpServerEndpoint(Endpoint):
    """``tcpin:HOST:PORT``: listen; every client is its own link."""

    kind = "tcpin"

    def __init__(self, spec: MavlinkEndpoint, **kw: Any) -> None:
        super().__init__(spec, **kw)
        self._server: socket.socket | None = None
        self._clients: dict[socket.socket, Link] = {}

    @property
    def local_address(self) -> Any:
        """The listening address (tests: an ephemeral port)."""
        return self._server.getsockname() if self._server is not None else None

    def _is_open(self) -> bool:
        return self._server is not None

    def _open(self) -> None:
        family, addr = _resolve(self.spec.host, self.spec.port, socket.SOCK_STREAM)
        srv = socket.socket(family, socket.SOCK_STREAM)
        try:
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            srv.bind(addr)
            srv.listen(MAX_TCP_CLIENTS)
            srv.setblocking(False)
        except OSError:
            srv.close()
            raise
        self._server = srv
        self._opened()
        log.info("mavlink %s: listening", self.name)

    def _select_sets(self) -> tuple[list[Any], list[Any]]:
        if self._server is None:
            return [], []
        r: list[Any] = [self._server, *self._clients]
        w = [s for s, link in self._clients.items() if link.pending or link.queue]
        return r, w

    def _readable(self, obj: Any) -> None:
        if obj is self._server:
            self._accept()
            return
        link = self._clients.get(obj)
        if link is None:
            return
        try:
            data = obj.recv(_READ_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            self._drop_client(obj, f"lost ({e})")
            return
        if not data:
            self._drop_client(obj, "closed by the client")
            return
        self._deliver(link, data)

    def _accept(self) -> None:
        assert self._server is not None
        try:
            conn, addr = self._server.accept()
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            self._count("errors")
            log.warning("mavlink %s: accept: %s", self.name, e)
            return
        if len(self._clients) >= MAX_TCP_CLIENTS:
            log.warning(
                "mavlink %s: refusing %s: %d clients already", self.name, addr, len(self._clients)
            )
            conn.close()
            return
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        link = Link(self, f"{self.name} <- {addr[0]}:{addr[1]}", address=addr, sock=conn)
        self._clients[conn] = link
        self._links = [*self._links, link]
        self._count("connects")
        log.info("mavlink %s: client %s:%s connected", self.name, addr[0], addr[1])

    def _drop_client(self, sock: socket.socket, why: str) -> None:
        link = self._clients.pop(sock, None)
        with contextlib.suppress(OSError):
            sock.close()
        if link is not None:
            log.info("mavlink %s: client %s %s", self.name, link.address, why)
            self._drop_link(link)

    def _writable(self, obj: Any) -> None:
        """Writes happen in :meth:`_flush`; writability just ends the wait."""

    def _flush(self) -> None:
        for sock, link in list(self._clients.items()):
            self._fill(link)
            if not link.pending:
                continue
            try:
                n = sock.send(link.pending)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError as e:
                self._drop_client(sock, f"lost ({e})")
                continue
            del link.pending[:n]
            self._count("bytes_sent", n)

    def _close_transport(self) -> None:
        for sock in list(self._clients):
            self._drop_client(sock, "closed (endpoint stopping)")
        if self._server is not None:
            with contextlib.suppress(OSError):
                self._server.close()
        self._server = None
        self._links = []


# ---------------------------------------------------------------------------- serial


class SerialEndpoint(Endpoint):
    """A serial port (telemetry radio, autopilot TELEM port): 8N1, no flow control."""

    kind = "serial"

    def __init__(self, spec: MavlinkEndpoint, **kw: Any) -> None:
        super().__init__(spec, **kw)
        self.baud = spec.baud or DEFAULT_SERIAL_BAUD
        self._ser: Any = None
        self._fd = -1
        self._link: Link | None = None

    def _is_open(self) -> bool:
        return self._ser is not None

    def _open(self) -> None:
        import serial  # pyserial; only serial endpoints need it

        try:
            ser = serial.Serial(self.spec.device, self.baud, timeout=0, write_timeout=0)
        except (serial.SerialException, ValueError) as e:
            raise OSError(errno.EIO, str(e)) from None
        fd = ser.fileno()
        # pyserial's write() spins on EAGAIN with write_timeout=0: write the fd ourselves.
        os.set_blocking(fd, False)
        self._ser, self._fd = ser, fd
        self._link = Link(self, self.name)
        self._links = [self._link]
        self._opened()
        log.info("mavlink %s: open at %d baud", self.name, self.baud)

    def _select_sets(self) -> tuple[list[Any], list[Any]]:
        if self._ser is None or self._link is None:
            return [], []
        want = bool(self._link.pending or self._link.queue)
        return [self._fd], ([self._fd] if want else [])

    def _readable(self, obj: Any) -> None:
        if self._link is None:
            return
        try:
            data = os.read(self._fd, _READ_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            self._lost(f"port lost ({e})")
            return
        if not data:
            self._lost("port closed")
            return
        self._deliver(self._link, data)

    def _writable(self, obj: Any) -> None:
        """Writes happen in :meth:`_flush`."""

    def _flush(self) -> None:
        link = self._link
        if link is None:
            return
        self._fill(link)
        if not link.pending:
            return
        try:
            n = os.write(self._fd, link.pending)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            self._lost(f"port lost ({e})")
            return
        del link.pending[:n]
        self._count("bytes_sent", n)

    def _close_transport(self) -> None:
        if self._ser is not None:
            with contextlib.suppress(Exception):
                self._ser.close()
        self._ser, self._fd = None, -1
        if self._link is not None:
            self._drop_link(self._link)
        self._link = None
        self._links = []


def open_endpoint(spec: MavlinkEndpoint | str, **kw: Any) -> Endpoint:
    """The :class:`Endpoint` for a connection string (not started)."""
    if isinstance(spec, str):
        spec = parse_mavlink_endpoint(spec)
    if spec.kind in ("udpout", "udpin", "udp"):
        return UdpEndpoint(spec, **kw)
    if spec.kind == "tcp":
        return TcpClientEndpoint(spec, **kw)
    if spec.kind == "tcpin":
        return TcpServerEndpoint(spec, **kw)
    if spec.kind == "serial":
        return SerialEndpoint(spec, **kw)
    raise ValueError(f"unknown MAVLink endpoint kind {spec.kind!r}")
