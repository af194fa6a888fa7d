"""Validation rules: one value in, the (normalised) value out, ``ValueError(reason)`` if bad.

A :class:`Rule` pairs the check with the text that describes the allowed values,
so the error messages and the generated configuration reference say the same
thing. Rules that look at the file system (a recording, a state directory) only
``stat`` paths: they never open or read them.
"""

from __future__ import annotations

import ipaddress
import os
import re
import reprlib
import stat
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

HOSTNAME_PLACEHOLDER = "<hostname>"

_short = reprlib.Repr()
_short.maxstring = 80
_short.maxother = 80
_short.maxlevel = 3


def short_repr(v: Any) -> str:
    """``repr`` bounded in length and depth: a value quoted in an error message."""
    return _short.repr(v)


class ItemError(ValueError):
    """A list element failed its rule; carries the index so the key can name it."""

    def __init__(self, index: int, reason: str) -> None:
        super().__init__(reason)
        self.index = index


@dataclass(frozen=True, slots=True)
class Rule:
    """A validation rule: ``text`` describes the allowed values (docs, messages)."""

    text: str
    check: Callable[[Any], Any]

    def __call__(self, value: Any) -> Any:
        """Return the accepted (possibly normalised) value or raise ``ValueError``."""
        return self.check(value)


def _fmt(v: Any) -> str:
    if isinstance(v, str):
        # Quoted as written when it is short and printable; bounded and escaped otherwise.
        return f'"{v}"' if len(v) <= 80 and v.isprintable() else short_repr(v)
    return short_repr(v)


def _num(v: float) -> str:
    return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else str(v)


def one_of(*choices: Any) -> Rule:
    """Value must equal one of ``choices``."""
    text = "one of " + ", ".join(_fmt(c) for c in choices)

    def check(v: Any) -> Any:
        if v not in choices:
            raise ValueError(f"must be {text}, got {_fmt(v)}")
        return v

    return Rule(text, check)


def between(lo: float, hi: float, *, lo_open: bool = False) -> Rule:
    """Numeric value must lie in ``[lo, hi]`` (or ``(lo, hi]`` with ``lo_open``)."""
    text = f"{'(' if lo_open else '['}{_num(lo)}, {_num(hi)}]"

    def check(v: Any) -> Any:
        if not ((lo < v) if lo_open else (lo <= v)) or not v <= hi:
            raise ValueError(f"must be in {text}, got {_num(v)}")
        return v

    return Rule(text, check)


def each(rule: Rule) -> Rule:
    """Every element of a list must pass ``rule``."""

    def check(values: tuple[Any, ...]) -> tuple[Any, ...]:
        out = []
        for i, v in enumerate(values):
            try:
                out.append(rule(v))
            except ValueError as e:
                raise ItemError(i, str(e)) from None
        return tuple(out)

    return Rule(f"each {rule.text}", check)


def rule(text: str) -> Callable[[Callable[[Any], Any]], Rule]:
    """Decorator turning a check function into a :class:`Rule` with docs text."""

    def wrap(fn: Callable[[Any], Any]) -> Rule:
        return Rule(text, fn)

    return wrap


# --- hosts and ports ------------------------------------------------------------------------

_HOSTNAME_RE = re.compile(
    r"(?=.{1,253}\Z)[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
    r"(?:\.[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*"
)
# A last label that is a number (decimal, or 0x hex as inet_aton reads it) makes the whole
# name an IPv4 address to every resolver (no top-level domain is numeric): 999.1.1.1 is a
# bad address, never a host name to look up.
_NUMERIC_LABEL_RE = re.compile(r"[0-9]+|0[xX][0-9A-Fa-f]*")
_ASCII_DIGITS_RE = re.compile(r"[0-9]+")


def check_host(h: str) -> None:
    """Raise ValueError unless ``h`` is an IP address (``[v6]`` too) or a DNS host name."""
    if h.startswith("[") and h.endswith("]"):
        try:
            ipaddress.IPv6Address(h[1:-1])
        except ValueError:
            raise ValueError(f"{short_repr(h)} is not a valid IPv6 address") from None
        return
    try:
        ipaddress.ip_address(h)
        return
    except ValueError:
        pass
    if _NUMERIC_LABEL_RE.fullmatch(h.rstrip(".").rpartition(".")[2]):
        raise ValueError(f"{short_repr(h)} is not a valid IPv4 address")
    if not _HOSTNAME_RE.fullmatch(h):
        raise ValueError(f"{short_repr(h)} is not an IP address or host name")


def ascii_int(text: str, what: str, lo: int, hi: int) -> int:
    """``text`` as an int of ASCII digits only, in [lo, hi] (``str.isdigit`` also takes
    fullwidth and Arabic-Indic digits, which no socket or serial API accepts)."""
    if (
        not _ASCII_DIGITS_RE.fullmatch(text)
        or len(text) > len(str(hi))
        or not lo <= int(text) <= hi
    ):
        raise ValueError(f"{what} {short_repr(text)} is not a number in [{lo}, {hi}]")
    return int(text)


def check_port(p: str) -> int:
    """A TCP/UDP port number in [1, 65535], ASCII digits."""
    return ascii_int(p, "port", 1, 65535)


def host_port(s: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT``) -> (host without brackets, port); ValueError if bad."""
    host, sep, port = s.rpartition(":")
    if not sep or not host:
        raise ValueError("expected HOST:PORT")
    check_host(host)
    return host.strip("[]"), check_port(port)


# --- MAVLink endpoints ---------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class MavlinkEndpoint:
    """A parsed pymavlink connection string.

    ``kind`` is ``udpout``/``udpin``/``udp``/``tcp``/``tcpin`` (``host``,
    ``port`` set) or ``serial`` (``device``, ``baud`` set; ``baud`` is None
    when the string gave none). ``text`` is the original string.
    """

    text: str
    kind: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int | None = None


MAVLINK_NET_KINDS = ("udpout", "udpin", "udp", "tcp", "tcpin")
#: Highest serial baud accepted in a MAVLink serial endpoint (USB adapters reach 12 Mbaud).
MAX_SERIAL_BAUD = 20_000_000


def parse_mavlink_endpoint(text: str) -> MavlinkEndpoint:
    """Parse ``udpout:HOST:PORT`` etc. or ``/dev/ttyX[,BAUD]``; ``ValueError`` if malformed."""
    kind, sep, rest = text.partition(":")
    if sep and kind in MAVLINK_NET_KINDS:
        try:
            host, port = host_port(rest)
        except ValueError as e:
            raise ValueError(f"{short_repr(text)}: {e}") from None
        return MavlinkEndpoint(text, kind, host=host, port=port)
    if text.startswith("/"):
        device, comma, baud = text.partition(",")
        if comma:
            try:
                rate = ascii_int(baud, "serial baud", 1, MAX_SERIAL_BAUD)
            except ValueError as e:
                raise ValueError(f"{short_repr(text)}: {e}") from None
            return MavlinkEndpoint(text, "serial", device=device, baud=rate)
        return MavlinkEndpoint(text, "serial", device=device)
    raise ValueError(
        f"{short_repr(text)} is not a MAVLink endpoint "
        f"({'/'.join(k + ':' for k in MAVLINK_NET_KINDS)}HOST:PORT or /dev/DEVICE[,BAUD])"
    )


@rule("udpout:/udpin:/udp:/tcp:/tcpin:HOST:PORT or /dev/DEVICE[,BAUD]")
def mavlink_endpoint(v: str) -> str:
    """A pymavlink connection string (see :func:`parse_mavlink_endpoint`)."""
    parse_mavlink_endpoint(v)
    return v


# --- zenoh -----------------------------------------------------------------------------------

ZENOH_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")


@rule("PROTO/HOST:PORT (tcp, udp, tls, quic, ws) or unixsock-stream/PATH")
def zenoh_endpoint(v: str) -> str:
    """A zenoh locator; ``?metadata`` and ``#config`` suffixes pass through."""
    proto, sep, rest = v.partition("/")
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    if sep and proto == "unixsock-stream" and address.startswith("/"):
        return v
    if not sep or proto not in ZENOH_PROTOCOLS:
        raise ValueError(f"{short_repr(v)} is not a zenoh endpoint like tcp/192.168.1.10:7447")
    try:
        host_port(address)
    except ValueError as e:
        raise ValueError(f"{short_repr(v)}: {e}") from None
    return v


def validate_key_expr(v: str) -> str:
    """A concrete zenoh key expression usable as a publication prefix."""
    if not v or v.startswith("/") or v.endswith("/") or "//" in v:
        raise ValueError(
            f"{short_repr(v)} is not a key expression (no empty chunks, no leading/trailing /)"
        )
    bad = sorted(set(v) & set("*$?#"))
    if bad:
        raise ValueError(
            f"{short_repr(v)} must be concrete: {''.join(bad)!r} not allowed in a prefix"
        )
    if re.search(r"\s", v):
        raise ValueError(f"{short_repr(v)} contains white space")
    if not v.isprintable():
        raise ValueError(f"{short_repr(v)} contains control characters")
    return v


@rule(f'a zenoh key expression; "{HOSTNAME_PLACEHOLDER}" is replaced by the host name')
def key_prefix(v: str) -> str:
    """A key expression prefix that may hold the host name placeholder."""
    left = v.replace(HOSTNAME_PLACEHOLDER, "x")
    if "<" in left or ">" in left:
        raise ValueError(f"{short_repr(v)}: the only placeholder is {HOSTNAME_PLACEHOLDER}")
    validate_key_expr(left)
    return v


# --- paths -------------------------------------------------------------------------------------


def _stat(path: str) -> os.stat_result | None:
    """``os.stat`` or None when nothing is there (or the path cannot be looked at)."""
    try:
        return os.stat(path)
    except (OSError, ValueError):
        return None


@rule('"sim", "replay:PATH" or an absolute serial device path like /dev/ttyUSB0')
def device_port(v: str) -> str:
    """The compass port: ``sim``, ``replay:PATH`` (an existing file) or a device path."""
    if v == "sim":
        return v
    if v.startswith("replay:"):
        path = v.removeprefix("replay:")
        if not path:
            raise ValueError('"replay:" needs a recording path, e.g. replay:/tmp/run.cbrec')
        st = _stat(path)
        if st is None or not stat.S_ISREG(st.st_mode):
            raise ValueError(f"recording {short_repr(path)} does not exist or is not a file")
        return v
    if v.startswith("/"):
        # A serial device is NOT required to exist at load: a USB adapter that
        # appears after boot is normal, and the link keeps retrying. Something that
        # exists and can never be a serial port is refused now, not retried forever.
        st = _stat(v)
        if st is not None and stat.S_ISDIR(st.st_mode):
            raise ValueError(f"{short_repr(v)} is a directory, not a serial device")
        return v
    raise ValueError(
        f'must be "sim", "replay:PATH" or an absolute device path, got {short_repr(v)}'
    )


@rule('a directory path (created if missing); "" = the default')
def directory_path(v: str) -> str:
    """A directory the daemon writes into: absent is fine, anything but a directory is not."""
    st = _stat(v) if v else None
    if st is not None and not stat.S_ISDIR(st.st_mode):
        raise ValueError(f"{short_repr(v)} exists and is not a directory")
    return v


@rule('a file path (created if missing, in an existing directory); "" = none')
def writable_file_path(v: str) -> str:
    """A file the daemon keeps: a regular file or absent, in a directory that exists."""
    if not v:
        return v
    st = _stat(v)
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{short_repr(v)} exists and is not a regular file")
    parent = _stat(str(Path(v).parent))
    if parent is None or not stat.S_ISDIR(parent.st_mode):
        raise ValueError(f"the directory of {short_repr(v)} does not exist")
    return v
