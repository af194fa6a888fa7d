"""MAVLink endpoints: UDP, TCP and serial links, each on its own thread, never blocking anyone.

Every configured endpoint (``mavlink.endpoints``, pymavlink connection-string
syntax) becomes one :class:`Endpoint` running one thread around ``select()``
on non-blocking sockets (or a non-blocking tty). An endpoint has one or more
:class:`Link` objects -- the peers it talks to -- each with

* a bounded queue of messages (pymavlink message objects, made once by the
  producer): :meth:`Link.send` appends and returns at once; when the queue is
  full the *oldest* message is dropped and counted (telemetry ages, the newest
  is worth most);
* its own pymavlink ``MAVLink`` object, which frames each message at the
  moment of writing with the link's own sequence number (a ground station
  counts lost packets from gaps, per link) and signature;
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

**Who is a peer.** Only a valid MAVLink frame -- with a valid, fresh signature
when signing is on (:meth:`~bridge.mavlink.signing.Signing.fresh`) -- makes its
sender a ``udpin`` peer or keeps any peer alive (``last_heard``): junk, frames
that fail their CRC and unsigned or replayed frames count for nothing. A peer
whose valid HEARTBEATs keep coming (one within :data:`PEER_PROTECT_S`) is never
dropped to make room for a stranger; a ``tcpin`` client that sends nothing
valid, or stops reading, is (see each kind).

Kinds (as pymavlink spells them):

=================  ===================================================================
``udpout:H:P``     send to H:P from an ephemeral port; answers come back to that port
``udpin:H:P``      listen on H:P; every address a valid frame came from (last 60 s, up to
                   16) is a peer; the port is its alone (no SO_REUSEADDR sharing)
``udp:H:P``        same as ``udpin`` (pymavlink's historical spelling)
``tcp:H:P``        connect to H:P; reconnect with backoff (0.5 s doubling to 5 s)
``tcpin:H:P``      listen on H:P; up to 8 clients, each its own link; when full, an idle
                   or non-reading one makes room for a newcomer
``/dev/X[,BAUD]``  serial port (default 57600 baud, telemetry radios); reopened if it goes
=================  ===================================================================
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import select
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any

from bridge.config import MavlinkEndpoint
from bridge.mavlink.dialect import IFLAG_SIGNED, MAGIC_V2, Message, mavlink
from bridge.mavlink.signing import Signing, sign_outgoing

log = logging.getLogger(__name__)

MessageHandler = Callable[[Any, "Link"], None]

DEFAULT_SERIAL_BAUD = 57600
DEFAULT_QUEUE_PACKETS = 64
UDP_PEER_TIMEOUT_S = 60.0
MAX_UDP_PEERS = 16
MAX_TCP_CLIENTS = 8
#: A peer whose last valid HEARTBEAT is this recent is never dropped for a newcomer.
PEER_PROTECT_S = 5.0
CONNECT_TIMEOUT_S = 5.0
BACKOFF_INITIAL_S = 0.5
BACKOFF_MAX_S = 5.0
_MAX_WAIT_S = 0.5  # select() timeout of the stream kinds: bounds how late timers are noticed
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
_PACK_LOCK = threading.Lock()  # see Link.frame


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
    strangers_dropped: int = 0  #: datagrams from no peer that held no valid (signed) frame
    peers_refused: int = 0  #: newcomers turned away: every peer was protected
    peers_evicted: int = 0  #: peers dropped to make room (idle, not reading, no HEARTBEAT)

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
        "last_heard",
        "last_heartbeat",
        "limit",
        "mav",
        "name",
        "opened_at",
        "parser",
        "pending",
        "queue",
        "sock",
        "stalled_since",
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
        self.mav = endpoint.make_framer()
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True  # garbage becomes bad_data, never an exception
        self.queue: deque[Message] = deque()
        self.limit = endpoint.queue_packets
        self.pending = bytearray()
        self.opened_at = self.last_heard = time.monotonic()  #: last valid (signed) frame
        self.last_heartbeat = -float("inf")  #: last valid (signed) HEARTBEAT
        self.stalled_since: float | None = None  #: bytes waiting for the peer to read since
        self.closed = False

    def frame(self, message: Message) -> bytes:
        """``message`` framed for this peer: the next sequence number, our ids, the signature.

        The same message object goes to every peer and pymavlink's ``pack`` stores
        the framed bytes on it before returning them: packing is serialised so two
        threads framing one message for two peers cannot swap each other's bytes.
        """
        signing = self.endpoint.signing
        with _PACK_LOCK:
            if signing is not None:
                self.mav.signing.timestamp = max(self.mav.signing.timestamp, signing.floor())
            mav = self.mav
            data: bytes = message.pack(mav)
            mav.seq = (mav.seq + 1) & 0xFF  # MAVLink.send's bookkeeping: pack() leaves it
        return data

    def send(self, packet: Message) -> None:
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

    def send_many(self, packets: Sequence[Message]) -> None:
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
    #: The longest the thread sleeps in ``select()`` (seconds; ``inf``: until a socket, the
    #: wake-up pipe -- every queued packet and close() write it -- or :meth:`_next_timer`).
    max_wait_s = _MAX_WAIT_S

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

    def send_now(self, link: Link, packet: Message) -> bool:
        """Send ``packet`` to ``link`` from the calling thread if that cannot block; True if done.

        False (the default) means "queue it for the endpoint's thread".
        """
        return False

    def send_now_many(self, link: Link, packets: Sequence[Message]) -> int:
        """Send a leading part of ``packets`` to ``link`` from the calling thread if that
        cannot block; how many were taken (sent, left in ``link.pending`` for the
        endpoint's thread, or lost to a socket error, as :meth:`send_now` counts them).

        0 (the default) means "queue them all for the endpoint's thread".
        """
        return 0

    def make_framer(self) -> Any:
        """A pymavlink ``MAVLink`` that frames for one link of this endpoint (our ids, its
        own sequence numbers, signing with our key and this endpoint's link id)."""
        mav = mavlink.MAVLink(None, srcSystem=self.system_id, srcComponent=self.component_id)
        if self.signing is not None:
            sign_outgoing(mav, self.signing, self.link_id)
        return mav

    @property
    def links(self) -> list[Link]:
        """The current peers (a snapshot)."""
        return list(self._links)

    def counters(self) -> EndpointCounters:
        """A snapshot of the counters."""
        with self._count_lock:
            return self._counters.snapshot()

    def broadcast(self, packet: Message) -> None:
        """Queue ``packet`` for every current peer (counted as unsent when there is none)."""
        links = self._links  # replaced, never changed in place: no copy needed
        if not links:
            self.count_unsent()
            return
        for link in links:
            link.send(packet)

    def broadcast_many(self, packets: Sequence[Message]) -> None:
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
                timeout = min(self.max_wait_s, max(0.0, self._next_timer(now) - now))
                try:
                    r, w, _ = select.select(
                        [self._wake_r, *rlist], wlist, [], None if timeout == math.inf else timeout
                    )
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

    def _authentic(self, msg: Any) -> bool:
        """A valid frame that may make (or keep) its sender a peer: any, or with signing on
        one with a valid, fresh signature (see the module docstring)."""
        s = self.signing
        return s is None or s.fresh(msg.get_msgbuf(), msg.get_srcSystem(), msg.get_srcComponent())

    def _parse(self, parser: Any, data: bytes) -> list[tuple[Any, bool]] | None:
        """The valid messages in ``data`` with their authenticity (None: the parser broke)."""
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception:  # a parser bug must not kill the endpoint
            self._count("bad_packets")
            return None
        out = []
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self._count("bad_packets")
            else:
                out.append((msg, self._authentic(msg)))
        return out

    def _deliver(
        self, link: Link, data: bytes, parsed: list[tuple[Any, bool]] | None = None
    ) -> None:
        """Hand every message from ``link``'s peer on; only authentic ones keep it a peer."""
        if parsed is None:
            parsed = self._parse(link.parser, data)
            if parsed is None:
                link.parser = mavlink.MAVLink(None)
                link.parser.robust_parsing = True
                return
        now = time.monotonic()
        for msg, authentic in parsed:
            self._count("packets_received")
            if authentic:
                link.last_heard = now
                if msg.get_type() == "HEARTBEAT":
                    link.last_heartbeat = now
            try:
                self.on_message(msg, link)
            except Exception:
                log.exception("mavlink %s: message handler failed", self.name)

    def _evictable(self, link: Link, now: float) -> bool:
        """``link`` may be dropped for a newcomer: no valid HEARTBEAT lately, or its peer has
        left bytes unread for a while (it does not read what it is sent)."""
        if link.stalled_since is not None and now - link.stalled_since > PEER_PROTECT_S / 2:
            return True
        return now - link.last_heartbeat > PEER_PROTECT_S

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
        q, buf, frame = link.queue, link.pending, link.frame
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

    ``buf`` holds packets framed by :meth:`Link.frame`
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
