"""Shared pieces of the codec tests (framing, GMR, heading decoders).

Lines are built here by hand (:func:`line`, its checksum by :func:`xor_cs`), never with
the codec's own renderer, so the tests check the codec and not itself.

The three decoders share their framing, so their property tests feed streams
built the same way: noise *between* lines that never holds ``$`` (so it can
neither start nor cut a line), noise *inside* a line made of control and
non-ASCII bytes (which kills that line), and the same stream fed whole or cut
at arbitrary points.
"""

from __future__ import annotations

import functools
import operator
from collections.abc import Callable, Sequence
from typing import Protocol, TypeVar

from hypothesis import strategies as st

from bridge.protocol.framing import CodecCounters, DropCounters, DropReason

T = TypeVar("T")
T_co = TypeVar("T_co", covariant=True)


class Feeder(Protocol[T_co]):
    """Anything with a streaming ``feed(bytes) -> frames``."""

    def feed(self, data: bytes) -> Sequence[T_co]: ...


class Decoder(Feeder[T_co], Protocol[T_co]):
    """A decoder that counts what it drops (``GmrDecoder``, ``HeadingDecoder``)."""

    counters: CodecCounters


def xor_cs(body: bytes) -> int:
    """Independent checksum: fold XOR over the body."""
    return functools.reduce(operator.xor, body, 0)


def line(body: str, *, cs: int | None = None, term: bytes = b"\r\n", case: str = "upper") -> bytes:
    """Build a line by hand (not with render_line) so the tests check the codec, not itself."""
    value = xor_cs(body.encode()) if cs is None else cs
    text = f"{value:02X}" if case == "upper" else f"{value:02x}"
    return b"$" + body.encode() + b"*" + text.encode() + term


def only(counters: DropCounters, **expected: int) -> None:
    """Assert the counters hold exactly ``expected`` and zero elsewhere."""
    want = {r.value: 0 for r in DropReason} | expected
    assert counters.snapshot() == want
    assert counters.total == sum(expected.values())


def between_noise(max_size: int) -> st.SearchStrategy[bytes]:
    """Junk for between lines: any bytes but ``$``."""
    return st.binary(max_size=max_size).map(lambda b: b.replace(b"$", b""))


def inside_noise(max_size: int) -> st.SearchStrategy[bytes]:
    """Junk for inside a line: printable bytes and CR/LF are pushed into 0x80..0xFF."""
    return st.binary(min_size=1, max_size=max_size).map(
        lambda b: bytes(x | 0x80 if x in (0x0A, 0x0D) or 0x20 <= x <= 0x7E else x for x in b)
    )


def noisy_frames(
    frames: st.SearchStrategy[T],
) -> st.SearchStrategy[list[tuple[T, bytes, tuple[int, bytes] | None]]]:
    """Up to six ``(frame, between, inside)`` items for :func:`stream_with_noise`: junk of
    up to 30 bytes before each frame, and maybe up to 4 bytes spliced into it."""
    return st.lists(
        st.tuples(
            frames, between_noise(30), st.none() | st.tuples(st.integers(0, 200), inside_noise(4))
        ),
        max_size=6,
    )


def feed_in_chunks(decoder: Feeder[T], stream: bytes, cuts: Sequence[int]) -> list[T]:
    """Feed ``stream`` cut at the sorted positions ``cuts``; all frames out, in order."""
    got: list[T] = []
    prev = 0
    for c in [*cuts, len(stream)]:
        got += decoder.feed(stream[prev:c])
        prev = c
    return got


def assert_chunking_changes_nothing(
    new_decoder: Callable[[], Decoder[T]], stream: bytes, cuts: Sequence[int]
) -> None:
    """``stream`` fed whole to one new decoder and cut at ``cuts`` to another gives the same
    frames and the same drop counters."""
    whole = new_decoder()
    expected = whole.feed(stream)
    chunked = new_decoder()
    got = feed_in_chunks(chunked, stream, cuts)
    assert got == expected
    assert chunked.counters.dropped.snapshot() == whole.counters.dropped.snapshot()


def stream_with_noise(
    items: Sequence[tuple[T, bytes, tuple[int, bytes] | None]], encode: Callable[[T], bytes]
) -> tuple[bytes, list[T]]:
    """Encoded frames with noise between (and maybe inside) them, and the frames that survive.

    Each item is ``(frame, between, inside)``: ``between`` goes before the frame;
    ``inside`` (``(position, junk)``) is spliced into the frame's line, killing it.
    """
    stream = b""
    expected: list[T] = []
    for frame, between, inside in items:
        raw = encode(frame)
        if inside is None:
            expected.append(frame)
        else:
            at = 1 + inside[0] % (len(raw) - 1)
            raw = raw[:at] + inside[1] + raw[at:]
        stream += between + raw
    return stream, expected
