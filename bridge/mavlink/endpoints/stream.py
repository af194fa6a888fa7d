"""Stream endpoints: ``tcp`` (connect, reconnect), ``tcpin`` (listen, many clients), serial."""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import socket
import time
from typing import Any

from bridge.config import MavlinkEndpoint
from bridge.mavlink.endpoints.base import (
    _READ_BYTES,
    CONNECT_TIMEOUT_S,
    DEFAULT_SERIAL_BAUD,
    MAX_TCP_CLIENTS,
    PEER_PROTECT_S,
    Endpoint,
    Link,
    _resolve,
)

log = logging.getLogger(__name__)

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


#: A client this freshly accepted is not dropped for a newcomer yet (time for its first
#: HEARTBEAT); with every place held and nobody droppable, newcomers wait in the backlog.
TCP_GRACE_S = 0.5
#: Connections the kernel holds for us while every place is taken (their SYNs are not lost).
_LISTEN_BACKLOG = 64
_ACCEPTS_PER_ROUND = 16
_CLIENT_SNDBUF = 64 * 1024


class TcpServerEndpoint(Endpoint):
    """``tcpin:HOST:PORT``: listen; every client is its own link.

    At most :data:`~bridge.mavlink.endpoints.base.MAX_TCP_CLIENTS` clients. When
    they are all there, a newcomer takes the place of the longest-connected
    client that is *droppable* -- no valid (signed, with signing on) HEARTBEAT
    for :data:`~bridge.mavlink.endpoints.base.PEER_PROTECT_S`, or bytes left
    unread for half that -- and not accepted in the last :data:`TCP_GRACE_S`.
    With none droppable yet, newcomers wait in the listen backlog (not refused)
    until one is: idle clients cannot lock a ground station out.
    """

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
            srv.listen(_LISTEN_BACKLOG)
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
        # Full with nobody droppable: newcomers wait in the backlog (no busy loop on them).
        room = len(self._clients) < MAX_TCP_CLIENTS or self._victim(time.monotonic()) is not None
        r: list[Any] = [self._server, *self._clients] if room else list(self._clients)
        w = [s for s, link in self._clients.items() if link.pending or link.queue]
        return r, w

    def _victim(self, now: float) -> socket.socket | None:
        """The client a newcomer replaces (the longest connected droppable one), if any."""
        old = [
            (link.opened_at, s)
            for s, link in self._clients.items()
            if now - link.opened_at >= TCP_GRACE_S and self._evictable(link, now)
        ]
        return min(old, key=lambda x: x[0])[1] if old else None

    def _next_timer(self, now: float) -> float:
        if self._server is None or len(self._clients) < MAX_TCP_CLIENTS:
            return super()._next_timer(now)
        # Full: look again when the first client may become droppable.
        soonest = min(
            max(link.opened_at + TCP_GRACE_S, link.last_heartbeat + PEER_PROTECT_S)
            for link in self._clients.values()
        )
        return min(super()._next_timer(now), max(now, soonest))

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
        for _ in range(_ACCEPTS_PER_ROUND):  # bounded: the clients must get their turn
            if self._server is None:
                return
            if len(self._clients) >= MAX_TCP_CLIENTS:
                victim = self._victim(time.monotonic())
                if victim is None:
                    return  # the newcomer waits in the backlog until one is droppable
                link = self._clients[victim]
                why = "stopped reading" if link.stalled_since is not None else "idle"
                self._drop_client(victim, f"dropped ({why}) to make room for a newcomer")
                self._count("peers_evicted")
            try:
                conn, addr = self._server.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:
                self._count("errors")
                log.warning("mavlink %s: accept: %s", self.name, e)
                return
            self._add_client(conn, addr)

    def _add_client(self, conn: socket.socket, addr: Any) -> None:
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        # Seconds of telemetry, not the kernel's megabytes: a client that stops reading is
        # seen (stalled) soon, and what it cannot take is dropped from its own queue.
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _CLIENT_SNDBUF)
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
        now = time.monotonic()
        for sock, link in list(self._clients.items()):
            self._fill(link)
            if link.pending:
                try:
                    n = sock.send(link.pending)
                except (BlockingIOError, InterruptedError):
                    n = 0
                except OSError as e:
                    self._drop_client(sock, f"lost ({e})")
                    continue
                del link.pending[:n]
                self._count("bytes_sent", n)
            # Bytes its socket would not take: the client is not reading (droppable soon).
            if not link.pending:
                link.stalled_since = None
            elif link.stalled_since is None:
                link.stalled_since = now

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
