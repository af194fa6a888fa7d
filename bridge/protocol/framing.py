"""NMEA-0183-style line framing shared by every serial codec: ``$<body>*<CS>\\r\\n``.

Pure and sans-I/O (in the manner of h11): :class:`LineSplitter` is fed byte
chunks split anywhere and hands back the bodies of complete lines whose
checksum is right; everything else is counted in :class:`DropCounters` by
reason and dropped, and the splitter resynchronises on the next ``$``.

Reading of the datasheet ("Framing") taken here, as a firmware engineer would:

* The checksum is *rendered* as two upper-case hex digits, but lower-case is
  *accepted* on input: the value check is just as strong and NMEA talkers that
  print lower-case exist (be liberal in what you accept).
* A bare ``\\n`` terminator is accepted as well as ``\\r\\n`` (USB bridges and
  loggers sometimes strip the CR; the checksum still guards the content). A
  lone ``\\r`` that is not followed by ``\\n`` is not a terminator.
* The 96-byte limit is on the line as the device sends it (``$`` to ``\\n``
  with ``\\r\\n``), i.e. a body of at most 90 bytes; a line terminated by a bare
  ``\\n`` is held to the same body limit.
* A line cut by a new ``$`` (dropout mid-line) has lost its ``*CS\\r\\n``
  trailer, so it is counted as ``no_checksum``.
* Bytes outside a line, and control / non-ASCII bytes inside one (which also
  kill that line), are ``noise``, counted once per run up to the next ``$``.
  Blank CR/LF between lines are ignored, not counted.
"""

from __future__ import annotations

import math
import numbers
import operator
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from enum import StrEnum

MAX_LINE_BYTES = 96  #: datasheet limit, including ``$`` and ``\r\n``
#: ``$`` + ``*HH`` + ``\r\n`` take 6 bytes of the 96.
MAX_BODY_BYTES = MAX_LINE_BYTES - 6
# What may be buffered after "$" before the terminator: body + "*HH" (the CR is tracked apart).
_MAX_CONTENT = MAX_BODY_BYTES + 3

_DOLLAR = 0x24
_CR = 0x0D
_LF = 0x0A
# The next byte that is not ordinary line content: "$", CR, LF, control or non-ASCII.
_SPECIAL = re.compile(rb"[^\x20-\x23\x25-\x7e]")
_HEX2 = re.compile(rb"[0-9A-Fa-f]{2}")
_BODY_OK = re.compile(r"[\x20-\x23\x25-\x29\x2b-\x7e]*")  # printable ASCII minus "$" and "*"


class DropReason(StrEnum):
    """Why a line (or run of bytes) was dropped; the keys of :class:`DropCounters`."""

    CHECKSUM = "checksum"  #: checksum present but wrong
    NO_CHECKSUM = "no_checksum"  #: ``*CS`` missing or malformed, or the line was cut short
    FIELDS = "fields"  #: a field missing or an extra one
    NUMBER = "number"  #: a numeric field that is not a plain decimal number
    RANGE = "range"  #: a value outside what the datasheet allows
    TOO_LONG = "too_long"  #: a line over :data:`MAX_LINE_BYTES`
    NOISE = "noise"  #: junk outside a line, or control/non-ASCII bytes inside one
    UNKNOWN_ID = "unknown_id"  #: a sentence this decoder does not accept


#: Every reason's key, in the enum's order: a decoder's counters start from these (iterating
#: the enum and reading each member's value cost ~30 k instructions a decoder).
_REASON_KEYS: tuple[str, ...] = tuple(r.value for r in DropReason)


class DropCounters(Mapping[str, int]):
    """Counts of dropped input per :class:`DropReason`, plus :attr:`total`.

    A read-only mapping (``counters["checksum"]``) whose keys are always all
    the reasons, zero until something is dropped. One instance is shared by a
    decoder and its :class:`LineSplitter` so that framing and sentence-level
    drops land in the same place.
    """

    __slots__ = ("_counts",)

    def __init__(self) -> None:
        self._counts: dict[str, int] = dict.fromkeys(_REASON_KEYS, 0)

    def add(self, reason: DropReason | str, n: int = 1) -> None:
        """Count ``n`` drops for ``reason`` (ValueError for an unknown reason)."""
        key = DropReason(reason).value
        self._counts[key] += n

    @property
    def total(self) -> int:
        """Sum over all reasons."""
        return sum(self._counts.values())

    def snapshot(self) -> dict[str, int]:
        """A plain-dict copy, e.g. for publishing or comparing before/after."""
        return dict(self._counts)

    def reset(self) -> None:
        """Zero every count."""
        for key in self._counts:
            self._counts[key] = 0

    def __getitem__(self, key: str) -> int:
        return self._counts[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._counts)

    def __len__(self) -> int:
        return len(self._counts)

    def __repr__(self) -> str:
        nonzero = {k: v for k, v in self._counts.items() if v}
        return f"DropCounters(total={self.total}, {nonzero})"


@dataclass(slots=True)
class CodecCounters:
    """What a decoder has seen: bytes fed, frames yielded, and drops by reason."""

    bytes_in: int = 0
    frames: int = 0
    dropped: DropCounters = field(default_factory=DropCounters)


def checksum(body: bytes) -> int:
    """NMEA checksum: XOR of every byte between ``$`` and ``*`` (both excluded)."""
    cs = 0
    for b in body:
        cs ^= b
    return cs


def render_line(body: str) -> bytes:
    """Render ``$<body>*<CS>\\r\\n`` with an upper-case hex checksum.

    Raises ValueError for a body holding ``$``, ``*``, CR, LF, any other control
    character or non-ASCII (the splitter would never hand such a body back), or
    one that would make the line longer than :data:`MAX_LINE_BYTES`.
    """
    if not _BODY_OK.fullmatch(body):
        raise ValueError(f"line body must be printable ASCII without '$' or '*': {body[:40]!r}")
    if len(body) > MAX_BODY_BYTES:
        raise ValueError(
            f"line would be {len(body) + 6} bytes, over the {MAX_LINE_BYTES}-byte limit"
        )
    raw = body.encode("ascii")
    return b"$" + raw + b"*" + f"{checksum(raw):02X}".encode("ascii") + b"\r\n"


class _State:
    IDLE = 0  # between lines: expecting "$" (CR/LF ignored)
    LINE = 1  # inside a line, buffering after "$"
    SKIP = 2  # discarding up to the next "$" (junk run or the rest of a dropped line)


_IDLE, _SKIP = _State.IDLE, _State.SKIP


class LineSplitter:
    """Streaming splitter: bytes in, checksum-verified line bodies (``str``) out.

    Memory is bounded whatever the input: at most one line's content
    (:data:`MAX_BODY_BYTES` + 3 bytes) is buffered between calls.
    """

    __slots__ = ("_buf", "_counters", "_cr", "_state")

    def __init__(self, counters: DropCounters | None = None) -> None:
        self._counters = counters if counters is not None else DropCounters()
        self._buf = bytearray()
        self._state = _State.IDLE
        self._cr = False  # the previous byte of the current line was CR

    @property
    def counters(self) -> DropCounters:
        """The drop counters this splitter writes to."""
        return self._counters

    @property
    def buffered(self) -> int:
        """Bytes of the current partial line held between calls (never over MAX_BODY_BYTES + 3)."""
        return len(self._buf)

    @property
    def in_line(self) -> bool:
        """A line has started and not ended yet (its bytes so far are buffered)."""
        return self._state == _State.LINE

    def reset(self) -> None:
        """Forget any partial line without counting it (e.g. after the port is reopened)."""
        self._buf.clear()
        self._state = _State.IDLE
        self._cr = False

    def _start_line(self) -> None:
        self._buf.clear()
        self._cr = False
        self._state = _State.LINE

    def _drop(self, reason: DropReason, then: int) -> None:
        self._counters.add(reason)
        self._buf.clear()
        self._cr = False
        self._state = then

    def feed(self, data: bytes) -> list[str]:
        """Consume a chunk; return the bodies of the lines it completed, in order."""
        out: list[str] = []
        buf = self._buf
        i = 0
        n = len(data)
        while i < n:
            state = self._state
            if state == _SKIP:
                j = data.find(b"$", i)
                if j < 0:
                    break
                i = j + 1
                self._start_line()
            elif state == _IDLE:
                b = data[i]
                if b == _DOLLAR:
                    i += 1
                    self._start_line()
                elif b in (_CR, _LF):
                    i += 1
                else:
                    # First byte of a junk run: count it once, swallow the run in SKIP.
                    self._drop(DropReason.NOISE, _SKIP)
            elif self._cr:  # the line's CR ended the previous chunk
                b = data[i]
                if b == _LF:
                    i += 1
                    self._finish(bytes(buf), out)
                elif b == _DOLLAR:
                    i += 1
                    self._counters.add(DropReason.NO_CHECKSUM)  # cut before its LF
                    self._start_line()
                else:
                    self._drop(DropReason.NOISE, _SKIP)
            else:
                m = _SPECIAL.search(data, i)
                end = m.start() if m is not None else n
                if len(buf) + (end - i) > _MAX_CONTENT:
                    # Resync on the next "$" without buffering the rest of the line.
                    self._drop(DropReason.TOO_LONG, _SKIP)
                    i = end
                    continue
                if m is None:
                    buf += data[i:end]
                    break
                b = data[end]
                if b == _LF or (b == _CR and data[end + 1 : end + 2] == b"\n"):
                    # The terminator (CR LF both in this chunk: one step, the common case).
                    self._finish(bytes(buf) + data[i:end] if buf else data[i:end], out)
                    i = end + (1 if b == _LF else 2)
                    continue
                buf += data[i:end]
                i = end + 1
                if b == _CR:
                    self._cr = True  # its LF comes with the next chunk (or not)
                elif b == _DOLLAR:
                    self._counters.add(DropReason.NO_CHECKSUM)  # the partial line was cut
                    self._start_line()
                else:
                    self._drop(DropReason.NOISE, _SKIP)
        return out

    def _finish(self, content: bytes, out: list[str]) -> None:
        """A terminator arrived: verify ``body*HH``; the body goes to ``out``, or the drop is counted."""
        self._buf.clear()
        self._cr = False
        self._state = _IDLE
        star = content.find(b"*")
        if star < 0 or not _HEX2.fullmatch(content, star + 1):
            self._counters.add(DropReason.NO_CHECKSUM)
            return
        body = content[:star]
        if len(body) > MAX_BODY_BYTES:
            self._counters.add(DropReason.TOO_LONG)
            return
        if checksum(body) != int(content[star + 1 :], 16):
            self._counters.add(DropReason.CHECKSUM)
            return
        out.append(body.decode("ascii"))


# --------------------------------------------------------------------------- field primitives
# Shared by the sentence codecs so that every codec parses numbers the same strict way.

INT_RE = re.compile(r"-?[0-9]+")
#: "Plain decimal": optional minus, digits, optional fraction. No "+", exponent, ".5", nan, inf.
DECIMAL_RE = re.compile(r"-?[0-9]+(?:\.[0-9]+)?")
_TOKEN_RE = re.compile(r"[\x20-\x23\x25-\x29\x2b\x2d-\x7e]*")  # printable minus "$" "*" ","


class DecodeError(ValueError):
    """A sentence (or frame content) the datasheet does not allow; ``reason`` is the drop reason."""

    def __init__(self, reason: DropReason, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def check_int(value: object, name: str, lo: int, hi: int | None) -> int:
    """An integer (any Integral, not bool) in lo..hi (hi None: unbounded), else DecodeError."""
    if type(value) is int:  # the decoders' case: no bool/ABC checks needed (per-frame path)
        v = value
    else:
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise DecodeError(DropReason.NUMBER, f"{name} must be an integer, got {value!r}")
        v = operator.index(value)
    if v < lo or (hi is not None and v > hi):
        raise DecodeError(DropReason.RANGE, f"{name}={v} outside {lo}..{hi}")
    return v


def check_real(value: object, name: str, lo: float, hi: float, *, hi_open: bool = False) -> float:
    """A finite real in [lo, hi] (or [lo, hi) with ``hi_open``) as float, else DecodeError."""
    if type(value) is float:  # the decoders' case: no bool/ABC checks needed (per-frame path)
        v = value
    else:
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise DecodeError(DropReason.NUMBER, f"{name} must be a number, got {value!r}")
        v = float(value)
    if not math.isfinite(v):
        raise DecodeError(DropReason.NUMBER, f"{name} must be finite, got {v!r}")
    if v < lo or v > hi or (hi_open and v >= hi):
        raise DecodeError(DropReason.RANGE, f"{name}={v} outside {lo}..{hi}")
    return v + 0.0  # -0.0 -> 0.0 so equality and rendering agree


def check_token(value: object, name: str, *, empty_ok: bool = False) -> str:
    """A field string: printable ASCII without ``$``, ``*``, ``,`` (non-empty unless allowed)."""
    if not isinstance(value, str) or not _TOKEN_RE.fullmatch(value):
        raise DecodeError(
            DropReason.NUMBER if not isinstance(value, str) else DropReason.RANGE,
            f"{name} must be printable ASCII without '$', '*' or ',': {value!r}",
        )
    if not value and not empty_ok:
        raise DecodeError(DropReason.FIELDS, f"{name} is empty")
    return value


def parse_int(text: str, name: str) -> int:
    """Parse a plain decimal integer field (``number`` error otherwise)."""
    if not INT_RE.fullmatch(text):
        raise DecodeError(DropReason.NUMBER, f"{name}: {text!r} is not an integer")
    return int(text)


def parse_decimal(text: str, name: str) -> float:
    """Parse a plain decimal field (``number`` error otherwise, including nan/inf/exponents)."""
    if not DECIMAL_RE.fullmatch(text):
        raise DecodeError(DropReason.NUMBER, f"{name}: {text!r} is not a plain decimal")
    return float(text)


def fmt_fixed(x: float, decimals: int) -> str:
    """Fixed-point rendering that never prints a negative zero (``-0.0`` -> ``0.0``)."""
    s = f"{x:.{decimals}f}"
    return s[1:] if s.startswith("-") and not s.strip("-0.") else s
