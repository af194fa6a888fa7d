"""Shared pieces of the codec property tests (framing, GMR, heading decoders).

The three decoders share their framing, so their property tests feed streams
built the same way: noise *between* lines that never holds ``$`` (so it can
neither start nor cut a line), noise *inside* a line made of control and
non-ASCII bytes (which kills that line), and the same stream fed whole or cut
at arbitrary points.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, TypeVar

from hypothesis import strategies as st

T = TypeVar("T")
T_co = TypeVar("T_co", covariant=True)


class Feeder(Protocol[T_co]):
    """Anything with a streaming ``feed(bytes) -> frames``."""

    def feed(self, data: bytes) -> Sequence[T_co]: ...


def between_noise(max_size: int) -> st.SearchStrategy[bytes]:
    """Junk for between lines: any bytes but ``$``."""
    return st.binary(max_size=max_size).map(lambda b: b.replace(b"$", b""))


def inside_noise(max_size: int) -> st.SearchStrategy[bytes]:
    """Junk for inside a line: printable bytes and CR/LF are pushed into 0x80..0xFF."""
    return st.binary(min_size=1, max_size=max_size).map(
        lambda b: bytes(x | 0x80 if x in (0x0A, 0x0D) or 0x20 <= x <= 0x7E else x for x in b)
    )


def feed_in_chunks(decoder: Feeder[T], stream: bytes, cuts: Sequence[int]) -> list[T]:
    """Feed ``stream`` cut at the sorted positions ``cuts``; all frames out, in order."""
    got: list[T] = []
    prev = 0
    for c in [*cuts, len(stream)]:
        got += decoder.feed(stream[prev:c])
        prev = c
    return got


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
