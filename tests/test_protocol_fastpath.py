"""The ``$PGMRA`` fast path of GmrDecoder.feed is indistinguishable from the general path.

Every test feeds the same chunks to a normal decoder and to one forced onto the
general path (``_fast_path=False``) and compares everything observable: the
frames (values *and* field types), bytes/frames counters, drops by reason,
``last_error`` and the splitter's state. A spy on ``LineSplitter.feed`` (the
first step of the general path) shows which path a chunk took, so the tests
also fail if the fast path is never taken where it should be.
"""

from __future__ import annotations

import functools
import operator
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import fields
from unittest.mock import patch

import codec_props as props
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridge.protocol import gmr
from bridge.protocol.framing import DecodeError, DropReason, LineSplitter
from bridge.protocol.gmr import AttitudeFrame, Flags, GmrDecoder, GmrFrame, encode, encode_body

EXAMPLES = settings(max_examples=250, deadline=None)
DATASHEET_PGMRA = b"$PGMRA,1024,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950,06*50\r\n"


def xor_cs(body: bytes) -> int:
    return functools.reduce(operator.xor, body, 0)


def line(body: str, *, cr: bool = True, lower_cs: bool = False) -> bytes:
    """``$body*CS`` with a checksum computed here, independently of the codec."""
    cs = f"{xor_cs(body.encode('latin-1')):02X}"
    cs = cs.lower() if lower_cs else cs
    return b"$" + body.encode("latin-1") + b"*" + cs.encode() + (b"\r\n" if cr else b"\n")


@contextmanager
def general_path_calls() -> Iterator[list[LineSplitter]]:
    """Record the splitters whose ``feed`` runs, i.e. the decoders that took the general path."""
    calls: list[LineSplitter] = []
    real = LineSplitter.feed

    def spy(self: LineSplitter, data: bytes) -> list[str]:
        calls.append(self)
        return real(self, data)

    with patch.object(LineSplitter, "feed", spy):
        yield calls


def attitudes(out: list[GmrFrame]) -> list[AttitudeFrame]:
    assert all(isinstance(f, AttitudeFrame) for f in out), out
    return [f for f in out if isinstance(f, AttitudeFrame)]


def error_key(exc: DecodeError | None) -> tuple[object, ...] | None:
    return None if exc is None else (type(exc), exc.reason, str(exc))


def observable(dec: GmrDecoder, out: list[GmrFrame]) -> tuple[object, ...]:
    """Everything a caller (or the next feed) can see after a feed."""
    return (
        out,
        [repr(f) for f in out],  # tells -0.0 from 0.0, which == does not
        [(type(f), [type(getattr(f, x.name)) for x in fields(f)]) for f in out],
        dec.counters.bytes_in,
        dec.counters.frames,
        dec.counters.dropped.snapshot(),
        error_key(dec.last_error),
        dec._splitter._state,
        dec._splitter.buffered,
    )


class Pair:
    """A fast-path decoder and a general-path decoder fed the same chunks."""

    def __init__(self) -> None:
        self.fast = GmrDecoder()
        self.general = GmrDecoder(_fast_path=False)

    def feed(self, chunk: bytes) -> tuple[list[GmrFrame], bool]:
        """Feed both, assert they agree; return the frames and whether the fast path was taken."""
        with general_path_calls() as calls:
            out_fast = self.fast.feed(chunk)
        out_general = self.general.feed(chunk)
        assert observable(self.fast, out_fast) == observable(self.general, out_general)
        return out_fast, not any(s is self.fast._splitter for s in calls)


# --------------------------------------------------------------------------- strategies

# Any values in range, not only on the 0.1 grid: encode() rounds them (359.96 -> "0.0").
attitude_frames = st.builds(
    AttitudeFrame,
    st.integers(0, 65535),
    st.floats(0.0, 360.0, exclude_max=True),
    st.floats(-90.0, 90.0),
    st.floats(-180.0, 180.0),
    *[st.integers(0, 4095)] * 6,
    st.integers(0, 31).map(Flags),
)


def encoded(frame: AttitudeFrame, cr: bool) -> bytes:
    raw = encode(frame)
    return raw if cr else raw[:-2] + b"\n"


# Field values around every boundary and format rule the two paths must agree on.
SEQ_TOKENS = ["0", "65535", "65536", "99999", "123456", "00", "007", "-0", "-1", "+1", "1.0", " 1"]
HDG_TOKENS = ["0.0", "359.9", "360.0", "360.1", "360.00", "359.99", "-0.0", "-0.1", "000.0"]
HDG_TOKENS += ["087.3", "87", "87.35", ".5", "5.", "1e2", "nan", "inf", "1000.0", "+1.0", "3600.0"]
PITCH_TOKENS = ["90.0", "90.1", "-90.0", "-90.1", "-0.0", "00.0", "-00.0", "9.", "-.5", "100.0"]
ROLL_TOKENS = ["180.0", "180.1", "-180.0", "-180.1", "-0.0", "-000.0", "999.9", "-1000.0"]
ADC_TOKENS = ["0", "4095", "4096", "9999", "10000", "0000", "04095", "-0", "-1", "1.0", "", "4e3"]
FLAG_TOKENS = ["00", "1F", "1f", "20", "FF", "0a", "0A", "6", "006", "-1", " 6", "+6", "0x", "G0"]
TOKENS = [SEQ_TOKENS, HDG_TOKENS, PITCH_TOKENS, ROLL_TOKENS, *[ADC_TOKENS] * 6, FLAG_TOKENS]
random_token = st.text(st.sampled_from("0123456789.-+eEaAfF x,*$"), max_size=7)


@st.composite
def mutated_lines(draw: st.DrawFn) -> bytes:
    """A $PGMRA line damaged in one of the ways a real link or a lax firmware would."""
    frame = draw(attitude_frames)
    parts = encode_body(frame).split(",")
    cr = draw(st.booleans())
    kind = draw(st.sampled_from(["field", "random_field", "count", "case", "raw", "body"]))
    if kind in ("field", "random_field"):  # one field replaced, checksum made right
        i = draw(st.integers(0, 10))
        tokens = TOKENS[i]
        parts[i + 1] = draw(st.sampled_from(tokens) if kind == "field" else random_token)
        return line(",".join(parts), cr=cr)
    if kind == "count":  # a field missing or an extra one
        if draw(st.booleans()):
            del parts[draw(st.integers(1, 11))]
        else:
            parts.insert(draw(st.integers(1, 12)), draw(st.sampled_from(["0", "", "06"])))
        return line(",".join(parts), cr=cr)
    if kind == "case":  # lower-case hex digits (the general path accepts them)
        parts[11] = parts[11].lower()
        return line(",".join(parts), cr=cr, lower_cs=draw(st.booleans()))
    raw = bytearray(line(",".join(parts), cr=cr))
    body_only = kind == "body"  # edit inside the body, then fix the checksum
    lo, hi = (1, len(raw) - (6 if cr else 5)) if body_only else (0, len(raw))
    at = draw(st.integers(lo, hi - 1))
    op = draw(st.sampled_from(["flip", "insert", "delete"]))
    byte = draw(st.integers(0, 255) | st.sampled_from(list(b"0123456789.,-*$\r\n")))
    if op == "flip":
        raw[at] = byte
    elif op == "insert":
        raw.insert(at, byte)
    else:
        del raw[at]
    if body_only:
        body = bytes(raw[1 : raw.rindex(b"*")])
        if b"*" in body or b"$" in body or b"\n" in body:
            return bytes(raw)  # the edit broke the framing itself: leave it as it is
        return line(body.decode("latin-1"), cr=cr)
    return bytes(raw)


# --------------------------------------------------------------------------- equivalence


@EXAMPLES
@given(
    st.lists(st.tuples(attitude_frames, st.booleans()), min_size=1, max_size=6),
    st.sampled_from(["one_chunk", "line_per_chunk", "random_cuts"]),
    st.data(),
)
def test_valid_lines_same_frames_and_counters_on_both_paths(
    items: list[tuple[AttitudeFrame, bool]], chunking: str, data: st.DataObject
) -> None:
    lines = [encoded(frame, cr) for frame, cr in items]
    if chunking == "one_chunk":
        chunks = [b"".join(lines)]
    elif chunking == "line_per_chunk":
        chunks = lines
    else:
        stream = b"".join(lines)
        cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
        chunks = [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True)]
    pair = Pair()
    got: list[GmrFrame] = []
    for chunk in chunks:
        out, fast = pair.feed(chunk)
        got += out
        if chunking != "random_cuts":
            # encode() writes exactly the datasheet's shape: whole lines must all go fast.
            assert fast, chunk
    assert len(got) == len(items)


@EXAMPLES
@given(
    st.lists(
        st.one_of(
            mutated_lines(),
            st.tuples(attitude_frames, st.booleans()).map(lambda t: encoded(*t)),
            props.between_noise(12),
        ),
        min_size=1,
        max_size=4,
    ),
    st.sampled_from(["one_chunk", "per_item"]),
)
def test_mutated_lines_same_frames_counters_and_reasons_on_both_paths(
    items: list[bytes], chunking: str
) -> None:
    """Damaged lines, valid ones and noise, alone or together in one chunk."""
    pair = Pair()
    for chunk in [b"".join(items)] if chunking == "one_chunk" else items:
        pair.feed(chunk)
    # Whatever state the damage left behind, the next valid line is decoded the same way.
    pair.feed(DATASHEET_PGMRA)


def test_every_token_in_every_field_same_on_both_paths() -> None:
    """Each boundary/format token in each field, alone and before a valid line."""
    template = DATASHEET_PGMRA[1:-5].decode().split(",")
    tried = 0
    for i, tokens in enumerate(TOKENS):
        for token in tokens:
            parts = list(template)
            parts[i + 1] = token
            for cr in (True, False):
                bad = line(",".join(parts), cr=cr)
                Pair().feed(bad)
                Pair().feed(bad + DATASHEET_PGMRA)
                tried += 1
    assert tried == 2 * sum(map(len, TOKENS))


@pytest.mark.parametrize(
    ("field", "token", "reason"),
    [
        (0, "65536", "range"),
        *[(i, "4096", "range") for i in range(4, 10)],
        (1, "360.1", "range"),
        (2, "90.1", "range"),
        (3, "-180.1", "range"),
        (10, "20", "range"),
        (10, "E0", "range"),
        (1, "1e2", "number"),
        (4, "-0.5", "number"),
        (10, "6", "number"),
    ],
)
def test_rejections_fall_back_with_the_general_reason(field: int, token: str, reason: str) -> None:
    parts = DATASHEET_PGMRA[1:-5].decode().split(",")
    parts[field + 1] = token
    pair = Pair()
    out, fast = pair.feed(line(",".join(parts)) + DATASHEET_PGMRA)
    assert not fast
    assert [f.seq for f in attitudes(out)] == [1024]
    assert pair.fast.counters.dropped[reason] == 1
    assert pair.fast.last_error is not None and pair.fast.last_error.reason == reason


def test_bad_checksum_in_a_multiline_chunk_falls_back_for_the_whole_chunk() -> None:
    bad = DATASHEET_PGMRA.replace(b"*50", b"*51")
    pair = Pair()
    out, fast = pair.feed(DATASHEET_PGMRA + bad + DATASHEET_PGMRA)
    assert not fast
    assert len(out) == 2
    assert pair.fast.counters.dropped.snapshot()[DropReason.CHECKSUM] == 1
    assert pair.fast.counters.frames == 2


# --------------------------------------------------------------------------- path taken


def test_plain_line_never_touches_the_general_path() -> None:
    def boom(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("general path used")

    fast = GmrDecoder()
    general = GmrDecoder(_fast_path=False)
    with patch.object(LineSplitter, "feed", boom), patch.object(gmr, "decode_body", boom):
        out = fast.feed(DATASHEET_PGMRA)
        with pytest.raises(AssertionError, match="general path used"):
            general.feed(DATASHEET_PGMRA)  # the patches are effective
    assert out == [
        AttitudeFrame(1024, 87.3, -1.2, 0.4, 3101, 2470, 3311, 2470, 2452, 2950, Flags(6))
    ]
    (frame,) = attitudes(out)
    assert type(frame.flags) is Flags and type(frame.seq) is int
    assert (fast.counters.bytes_in, fast.counters.frames) == (len(DATASHEET_PGMRA), 1)


@pytest.mark.parametrize(
    "chunk",
    [
        line("PGMRA,1,87.3,-0.0,-0.0,1,1,1,1,1,1,00"),  # "-0.0" (printf of -0.04) -> 0.0
        line("PGMRA,1,360.0,0.0,0.0,1,1,1,1,1,1,00"),  # the tolerated 360.0 -> 0.0
        line("PGMRA,65535,359.9,90.0,-180.0,0,4095,0,4095,0,4095,1F"),  # every upper bound
        line("PGMRA,0,0.0,-90.0,180.0,0,0,0,0,0,0,00", cr=False),  # lower bounds, bare LF
        line("PGMRA,00007,087.3,01.5,001.5,0001,0002,0003,0004,0005,0006,00"),  # leading zeros
        DATASHEET_PGMRA * 3,  # what a USB adapter may deliver in one read
    ],
)
def test_edge_lines_take_the_fast_path(chunk: bytes) -> None:
    pair = Pair()
    out, fast = pair.feed(chunk)
    assert fast and out
    for f in attitudes(out):
        assert "-0.0" not in repr(f)  # normalised like check_real does
        assert 0.0 <= f.heading < 360.0


@pytest.mark.parametrize(
    "chunk",
    [
        line("PGMRA,1,87.3,0.0,0.0,1,1,1,1,1,1,0a"),  # lower-case flags
        line("PGMRA,8,87.3,0.0,0.0,1,1,1,1,1,1,00", lower_cs=True),  # lower-case checksum "4f"
        line("PGMRA,1,87,0.0,0.0,1,1,1,1,1,1,00"),  # no decimal
        line("PGMRA,1,87.35,0.0,0.0,1,1,1,1,1,1,00"),  # two decimals
        line("PGMRA,-0,87.3,0.0,0.0,1,1,1,1,1,1,00"),  # "-0" integer
        line("PGMRV,2.1.0,B3,GMR-000417") + DATASHEET_PGMRA,  # another sentence in the chunk
        DATASHEET_PGMRA + DATASHEET_PGMRA[:20],  # a partial line left over
        b"\r\n" + DATASHEET_PGMRA,  # blank line first
    ],
)
def test_valid_but_unusual_input_falls_back_and_decodes_the_same(chunk: bytes) -> None:
    pair = Pair()
    out, fast = pair.feed(chunk)
    assert not fast and out


def test_partial_line_then_rest_goes_general_then_fast_again() -> None:
    pair = Pair()
    assert pair.feed(DATASHEET_PGMRA[:30]) == ([], False)
    out, fast = pair.feed(DATASHEET_PGMRA[30:])  # completes a buffered line: general path
    assert not fast and len(out) == 1
    out, fast = pair.feed(DATASHEET_PGMRA)
    assert fast and len(out) == 1


@pytest.mark.parametrize("cut", [DATASHEET_PGMRA[:30], DATASHEET_PGMRA[:-1]])
def test_line_cut_short_then_a_whole_line_counts_the_cut_one(cut: bytes) -> None:
    pair = Pair()
    pair.feed(cut)
    out, fast = pair.feed(DATASHEET_PGMRA)  # its "$" ends the partial line: no_checksum
    assert not fast and len(out) == 1
    assert pair.fast.counters.dropped["no_checksum"] == 1


def test_after_noise_the_next_line_goes_fast_and_counts_the_same() -> None:
    pair = Pair()
    assert pair.feed(b"\xff\x00junk") == ([], False)  # leaves the splitter skipping to "$"
    out, fast = pair.feed(DATASHEET_PGMRA)
    assert fast and len(out) == 1
    assert pair.fast.counters.dropped["noise"] == 1


def test_device_decoder_never_takes_the_fast_path() -> None:
    dev = GmrDecoder("device")
    with general_path_calls() as calls:
        assert dev.feed(DATASHEET_PGMRA) == []
    assert calls == [dev._splitter]
    assert dev.counters.dropped["unknown_id"] == 1
