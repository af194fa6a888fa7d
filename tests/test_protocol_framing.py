"""Line framing: checksum, render_line, the streaming splitter and its drop counters."""

from __future__ import annotations

import random

import codec_props as props
import pytest
from codec_props import feed_in_chunks, line, only, stream_with_noise, xor_cs
from helpers import examples
from hypothesis import given
from hypothesis import strategies as st

from bridge.protocol.framing import (
    MAX_BODY_BYTES,
    MAX_LINE_BYTES,
    DropCounters,
    DropReason,
    LineSplitter,
    checksum,
    render_line,
)

FAST = examples(150)


# --------------------------------------------------------------------------- checksum / render


def test_checksum_is_xor_of_body() -> None:
    body = b"PGMRA,1024,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950,06"
    assert checksum(body) == xor_cs(body)
    assert checksum(b"") == 0
    assert checksum(b"AA") == 0  # equal bytes cancel


def test_checksum_is_the_xor_of_every_byte_at_every_length() -> None:
    # The folded form must agree with the byte loop whatever the length, below, at and
    # past the lengths its folds cover (a body is at most 90 bytes; anything may be passed).
    # (Uniform random bytes by randbytes: a byte at a time through randrange was most of the
    # test's time, 135 000 calls.)
    rng = random.Random(5)
    for n in range(300):
        for _ in range(3):
            body = rng.randbytes(n)
            assert checksum(body) == xor_cs(body), (n, body)


def test_render_line_format() -> None:
    assert render_line("PGMRQ,VER") == line("PGMRQ,VER")
    # The checksum is always two upper-case hex digits, zero-padded.
    out = render_line("AB")
    assert out == b"$AB*03\r\n"


@pytest.mark.parametrize("bad", ["A$B", "A*B", "A\rB", "A\nB", "Aé", "A\x00B", "A\tB"])
def test_render_line_refuses_bad_bodies(bad: str) -> None:
    with pytest.raises(ValueError):
        render_line(bad)


def test_render_line_length_limit() -> None:
    assert len(render_line("X" * MAX_BODY_BYTES)) == MAX_LINE_BYTES
    with pytest.raises(ValueError, match="96"):
        render_line("X" * (MAX_BODY_BYTES + 1))


# --------------------------------------------------------------------------- splitter basics


def test_good_lines_come_out_in_order() -> None:
    sp = LineSplitter()
    assert sp.feed(line("A,1") + line("B,2")) == ["A,1", "B,2"]
    only(sp.counters)


def test_every_split_point_gives_the_same_lines() -> None:
    data = line("PGMRV,2.1.0,B3,GMR-000417") + line("X,1")
    for cut in range(len(data) + 1):
        for cut2 in range(cut, len(data) + 1, 7):
            sp = LineSplitter()
            out = sp.feed(data[:cut]) + sp.feed(data[cut:cut2]) + sp.feed(data[cut2:])
            assert out == ["PGMRV,2.1.0,B3,GMR-000417", "X,1"], (cut, cut2)
            only(sp.counters)


def test_byte_at_a_time_including_mid_crlf() -> None:
    sp = LineSplitter()
    out: list[str] = []
    for b in line("A,1") + line("B,2"):
        out += sp.feed(bytes([b]))
    assert out == ["A,1", "B,2"]


def test_lowercase_checksum_accepted() -> None:
    sp = LineSplitter()
    body = "PGMRQ,RATE,10"  # checksum 0x5A: has a letter digit
    assert any(c.isalpha() for c in f"{xor_cs(body.encode()):02X}")
    assert sp.feed(line(body, case="lower")) == [body]
    only(sp.counters)


def test_bare_lf_terminator_accepted() -> None:
    sp = LineSplitter()
    assert sp.feed(line("A,1", term=b"\n") + line("B,2")) == ["A,1", "B,2"]
    only(sp.counters)


def test_blank_crlf_between_lines_is_not_noise() -> None:
    sp = LineSplitter()
    assert sp.feed(b"\r\n\r\n" + line("A,1") + b"\n\r\n" + line("B,2")) == ["A,1", "B,2"]
    only(sp.counters)


def test_max_length_line_accepted() -> None:
    body = "Y" * MAX_BODY_BYTES
    data = line(body)
    assert len(data) == MAX_LINE_BYTES
    sp = LineSplitter()
    assert sp.feed(data) == [body]


# --------------------------------------------------------------------------- drop reasons


GOOD = line("GOOD,1")


@pytest.mark.parametrize(
    ("bad", "reason"),
    [
        (line("A,1", cs=0x00), "checksum"),
        (b"$A,1\r\n", "no_checksum"),  # no "*CS"
        (b"$A,1*\r\n", "no_checksum"),  # empty CS
        (b"$A,1*5\r\n", "no_checksum"),  # one digit
        (b"$A,1*5G\r\n", "no_checksum"),  # not hex
        (b"$A,1*505\r\n", "no_checksum"),  # three digits
        (b"$A*1*00\r\n", "no_checksum"),  # "*" in the body
        (b"$A,1*50", "no_checksum"),  # cut by the next "$" before its terminator
        (b"$A,1*50\r", "no_checksum"),  # cut between CR and LF
        (line("Z" * (MAX_BODY_BYTES + 1)), "too_long"),
        (line("Z" * (MAX_BODY_BYTES + 1), term=b"\n"), "too_long"),  # 96 bytes, body too long
        (line("Z" * 500), "too_long"),
        (b"garbage \x00\xff\xfe more junk\r\n", "noise"),
        (b"\x00", "noise"),
        (b"$A,\xff1*00\r\n", "noise"),  # non-ASCII inside a line
        (b"$A,\x071*00\r\n", "noise"),  # control byte inside a line
        (b"$A,1*50\rX\r\n", "noise"),  # CR not followed by LF
    ],
)
def test_each_drop_reason_counted_once_then_resync(bad: bytes, reason: str) -> None:
    sp = LineSplitter()
    assert sp.feed(bad + GOOD) == ["GOOD,1"]
    only(sp.counters, **{reason: 1})
    # And the same when the bad bytes arrive one by one.
    sp2 = LineSplitter()
    out: list[str] = []
    for b in bad + GOOD:
        out += sp2.feed(bytes([b]))
    assert out == ["GOOD,1"]
    only(sp2.counters, **{reason: 1})


def test_noise_counted_once_per_run_not_per_byte() -> None:
    sp = LineSplitter()
    assert sp.feed(b"x" * 1000 + GOOD + b"\xff" * 10 + b"abc" + GOOD) == ["GOOD,1", "GOOD,1"]
    only(sp.counters, noise=2)


def test_noise_run_split_across_feeds_counted_once() -> None:
    sp = LineSplitter()
    for _ in range(50):
        assert sp.feed(b"junk") == []
    assert sp.feed(GOOD) == ["GOOD,1"]
    only(sp.counters, noise=1)


def test_dollar_inside_partial_line_restarts() -> None:
    sp = LineSplitter()
    assert sp.feed(b"$PGMRA,1,2,3") == []
    assert sp.feed(b"$PGMRA,4" + b"$" + GOOD[1:]) == ["GOOD,1"]
    only(sp.counters, no_checksum=2)


def test_memory_bounded_on_endless_line() -> None:
    sp = LineSplitter()
    assert sp.feed(b"$") == []
    for _ in range(200):
        assert sp.feed(b"A" * 997) == []
        assert sp.buffered <= MAX_BODY_BYTES + 3
    assert sp.buffered == 0  # dropped: not buffering the rest
    assert sp.feed(b"\r\n" + GOOD) == ["GOOD,1"]
    only(sp.counters, too_long=1)


def test_reset_discards_partial_line_silently() -> None:
    sp = LineSplitter()
    sp.feed(b"$A,1*")
    sp.reset()
    assert sp.feed(b"50\r\n" + GOOD) == ["GOOD,1"]
    only(sp.counters, noise=1)  # the orphan "50" is outside any line


def test_shared_counters_object() -> None:
    counters = DropCounters()
    a, b = LineSplitter(counters), LineSplitter(counters)
    a.feed(line("A", cs=1))
    b.feed(line("B", cs=1))
    assert counters["checksum"] == 2


# --------------------------------------------------------------------------- DropCounters


def test_drop_counters_mapping() -> None:
    c = DropCounters()
    assert set(c) == {r.value for r in DropReason}
    assert len(c) == 8
    assert c.total == 0
    c.add("range")
    c.add(DropReason.RANGE, 2)
    c.add(DropReason.NOISE)
    assert c["range"] == 3
    assert c[DropReason.RANGE] == 3
    assert c.total == 4
    snap = c.snapshot()
    c.add("noise")
    assert snap["noise"] == 1  # a copy, not a view
    with pytest.raises(ValueError):
        c.add("bogus")
    c.reset()
    assert c.total == 0


# --------------------------------------------------------------------------- properties

body_chars = st.characters(min_codepoint=0x20, max_codepoint=0x7E, exclude_characters="$*")
bodies = st.text(body_chars, min_size=0, max_size=MAX_BODY_BYTES)
between_noise = props.between_noise(40)
inside_noise = props.inside_noise(5)


@FAST
@given(st.lists(st.tuples(bodies, between_noise), max_size=8), st.data())
def test_chunking_never_changes_the_result(
    items: list[tuple[str, bytes]], data: st.DataObject
) -> None:
    stream = b"".join(render_line(b) + n for b, n in items)
    whole = LineSplitter()
    expected = whole.feed(stream)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=12)))
    chunked = LineSplitter()
    got = feed_in_chunks(chunked, stream, cuts)
    assert got == expected
    assert chunked.counters.snapshot() == whole.counters.snapshot()
    # Noise between lines never contains "$", so every line survives.
    assert expected == [b for b, _ in items]


@FAST
@given(
    st.lists(
        st.tuples(
            bodies, between_noise, st.one_of(st.none(), st.tuples(st.integers(), inside_noise))
        ),
        max_size=8,
    )
)
def test_noise_yields_exactly_the_uncorrupted_lines(
    items: list[tuple[str, bytes, tuple[int, bytes] | None]],
) -> None:
    """Junk between lines (no "$") loses nothing; junk inside a line (control/non-ASCII
    bytes) kills exactly that line. So the output is exactly predictable."""
    stream, expected = stream_with_noise(items, render_line)
    sp = LineSplitter()
    assert sp.feed(stream) == expected
    assert sp.counters.total >= (1 if len(expected) < len(items) else 0)


@FAST
@given(st.binary(max_size=600))
def test_random_bytes_never_raise_and_only_yield_real_lines(blob: bytes) -> None:
    sp = LineSplitter()
    out = sp.feed(blob)
    for body in out:
        raw = body.encode()
        assert b"$" + raw + b"*" in blob
        assert len(raw) <= MAX_BODY_BYTES
    assert sp.buffered <= MAX_BODY_BYTES + 3
