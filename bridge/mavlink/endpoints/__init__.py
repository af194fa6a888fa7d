"""MAVLink endpoints: UDP, TCP and serial links, each on its own thread, never blocking anyone.

Every configured endpoint (``mavlink.endpoints``, pymavlink connection-string
syntax) becomes one :class:`~bridge.mavlink.endpoints.base.Endpoint` running one
thread around ``select()`` on non-blocking sockets (or a non-blocking tty); see
:mod:`bridge.mavlink.endpoints.base` for links, queues and why these are not
pymavlink's ``mavutil`` connections (docs/mavlink.md has the measurements).

* :mod:`~bridge.mavlink.endpoints.base`   -- :class:`Link`, :class:`Endpoint`, counters
* :mod:`~bridge.mavlink.endpoints.udp`    -- ``udpout``, ``udpin``
* :mod:`~bridge.mavlink.endpoints.stream` -- ``tcp``, ``tcpin``, serial ports
"""

from __future__ import annotations

from typing import Any

from bridge.config import MavlinkEndpoint, parse_mavlink_endpoint
from bridge.mavlink.endpoints.base import (
    DEFAULT_QUEUE_PACKETS,
    MAX_DATAGRAM_BYTES,
    Endpoint,
    EndpointCounters,
    Link,
    MessageHandler,
)
from bridge.mavlink.endpoints.stream import SerialEndpoint, TcpClientEndpoint, TcpServerEndpoint
from bridge.mavlink.endpoints.udp import UdpEndpoint

__all__ = [
    "DEFAULT_QUEUE_PACKETS",
    "MAX_DATAGRAM_BYTES",
    "Endpoint",
    "EndpointCounters",
    "Link",
    "MessageHandler",
    "SerialEndpoint",
    "TcpClientEndpoint",
    "TcpServerEndpoint",
    "UdpEndpoint",
    "open_endpoint",
]


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
