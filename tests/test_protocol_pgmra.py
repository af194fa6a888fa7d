"""The ``$PGMRA`` decoder on valid, unusual and damaged input, checked against an oracle.

The oracle (:func:`reference_frames`) is written here from the datasheet and the
codec's documented readings, independently of :mod:`bridge.protocol`: a line is
``$`` up to the next ``\\n`` (a new ``$`` cuts it), printable ASCII, at most 96
bytes, with a right ``*HH`` checksum and eleven fields in range. Every test feeds
:class:`GmrDecoder` and compares what is observable -- the frames (values *and*
field types), the bytes/frames counters, drops by reason, ``last_error`` -- with
the oracle and with the same stream decoded in one piece ("offline"), or a byte at a
time (then every line goes through the splitter, not the one-match route for the
whole lines a read opens with).

The property tests at the end are the fast suite's share of the fuzzing: random,
truncated and corrupted chunks with valid frames mixed in give no false frame,
lose no valid one, and leave counters that do not depend on how the stream was cut.
"""

from __future__ import annotations

import functools
import operator
import re
from dataclasses import fields
from unittest.mock import patch

import codec_props as props
import pytest
from helpers import examples
from hypothesis import given
from hypothesis import strategies as st

from bridge.protocol.framing import DecodeError, DropReason, LineSplitter
from bridge.protocol.gmr import AttitudeFrame, Flags, GmrDecoder, GmrFrame, encode, encode_body

EXAMPLES = examples(250)
DATASHEET_PGMRA = b"$PGMRA,1024,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950,06*50\r\n"


def xor_cs(body: bytes) -> int:
    return functools.reduce(operator.xor, body, 0)


def line(body: str, *, cr: bool = True, lower_cs: bool = False) -> bytes:
    """``$body*CS`` with a checksum computed here, independently of the codec."""
    cs = f"{xor_cs(body.encode('latin-1')):02X}"
    cs = cs.lower() if lower_cs else cs
    return b"$" + body.encode("latin-1") + b"*" + cs.encode() + (b"\r\n" if cr else b"\n")


# --------------------------------------------------------------------------- the oracle

_INT = re.compile(r"-?[0-9]+")
_DEC = re.compile(r"-?[0-9]+(?:\.[0-9]+)?")
_HEX2 = re.compile(r"[0-9A-Fa-f]{2}")
_PRINTABLE = re.compile(rb"[\x20-\x7e]*")


def reference_attitude(body: str) -> AttitudeFrame | None:
    """The frame a checksum-verified ``PGMRA`` body stands for, or None if it is invalid."""
    parts = body.split(",")
    if parts[0] != "PGMRA" or len(parts) != 12:
        return None
    f = parts[1:]
    if not all(_INT.fullmatch(t) for t in (f[0], *f[4:10])) or not _HEX2.fullmatch(f[10]):
        return None
    if not all(_DEC.fullmatch(t) for t in f[1:4]):
        return None
    seq, adc, flags = int(f[0]), [int(t) for t in f[4:10]], int(f[10], 16)
    hdg, pitch, roll = (float(t) for t in f[1:4])
    if hdg == 360.0:
        hdg = 0.0  # the tolerated rounding artefact
    if not (0 <= seq <= 65535 and all(0 <= a <= 4095 for a in adc) and flags < 0x20):
        return None
    if not (0.0 <= hdg < 360.0 and -90.0 <= pitch <= 90.0 and -180.0 <= roll <= 180.0):
        return None
    mx, my, mz, ax, ay, az = adc
    return AttitudeFrame(seq, hdg, pitch, roll, mx, my, mz, ax, ay, az, Flags(flags))


def reference_frames(stream: bytes) -> list[AttitudeFrame]:
    """Every valid ``$PGMRA`` line of ``stream``, in order (the datasheet's framing)."""
    out: list[AttitudeFrame] = []
    for m in re.finditer(rb"\$([^$\n]*)\n", stream):
        content = m.group(1)
        if content.endswith(b"\r"):
            content = content[:-1]
        if not _PRINTABLE.fullmatch(content) or len(content) > 93:
            continue
        body, star, cs = content.rpartition(b"*")
        if not star or b"*" in body or not _HEX2.fullmatch(cs.decode("latin-1")):
            continue
        if xor_cs(body) != int(cs, 16) or len(body) > 90:
            continue
        frame = reference_attitude(body.decode("ascii"))
        if frame is not None:
            out.append(frame)
    return out


def error_key(exc: DecodeError | None) -> tuple[object, ...] | None:
    return None if exc is None else (type(exc), exc.reason, str(exc))


def observable(dec: GmrDecoder, out: list[GmrFrame]) -> tuple[object, ...]:
    """Everything a caller can see after feeding a stream."""
    return (
        out,
        [repr(f) for f in out],  # tells -0.0 from 0.0, which == does not
        [(type(f), [type(getattr(f, x.name)) for x in fields(f)]) for f in out],
        dec.counters.bytes_in,
        dec.counters.frames,
        dec.counters.dropped.snapshot(),
        error_key(dec.last_error),
    )


def decode_checked(*chunks: bytes) -> tuple[list[GmrFrame], GmrDecoder]:
    """Feed ``chunks``; check frames against the oracle and against one-piece decoding."""
    dec = GmrDecoder()
    out: list[GmrFrame] = []
    for chunk in chunks:
        out += dec.feed(chunk)
    stream = b"".join(chunks)
    offline = GmrDecoder()
    assert observable(dec, out) == observable(offline, offline.feed(stream))
    reference = reference_frames(stream)
    assert out == reference
    assert [repr(f) for f in out] == [repr(f) for f in reference]
    for f in attitudes(out):
        assert type(f.seq) is int and type(f.heading) is float and type(f.flags) is Flags
        assert "-0.0" not in repr(f) and 0.0 <= f.heading < 360.0
    assert dec.counters.frames == len(out) and dec.counters.bytes_in == len(stream)
    return out, dec


def attitudes(out: list[GmrFrame]) -> list[AttitudeFrame]:
    assert all(isinstance(f, AttitudeFrame) for f in out), out
    return [f for f in out if isinstance(f, AttitudeFrame)]


# --------------------------------------------------------------------------- strategies

# Any values in range, not only on the 0.1 grid: encode() rounds them (359.96 -> "0.0").
# The flags are sampled from the 32 values rather than mapped from integers(0, 31): the
# same one integer choice in 0..31 (no boundary weights below 128 values), one strategy
# layer less for Hypothesis to draw through (a layer costs about half a choice).
FLAG_VALUES = tuple(Flags(i) for i in range(32))
attitude_frames = st.builds(
    AttitudeFrame,
    st.integers(0, 65535),
    st.floats(0.0, 360.0, exclude_max=True),
    st.floats(-90.0, 90.0),
    st.floats(-180.0, 180.0),
    *[st.integers(0, 4095)] * 6,
    st.sampled_from(FLAG_VALUES),
)


def encoded(frame: AttitudeFrame, cr: bool) -> bytes:
    raw = encode(frame)
    return raw if cr else raw[:-2] + b"\n"


# A valid line, CR LF or bare LF: the frame's choices, then the terminator's.
valid_lines = st.builds(encoded, attitude_frames, st.booleans())


# Field values around every boundary and format rule of the datasheet and the codec.
SEQ_TOKENS = ["0", "65535", "65536", "99999", "123456", "00", "007", "-0", "-1", "+1", "1.0", " 1"]
HDG_TOKENS = ["0.0", "359.9", "360.0", "360.1", "360.00", "359.99", "-0.0", "-0.1", "000.0"]
HDG_TOKENS += ["087.3", "87", "87.35", ".5", "5.", "1e2", "nan", "inf", "1000.0", "+1.0", "3600.0"]
PITCH_TOKENS = ["90.0", "90.1", "-90.0", "-90.1", "-0.0", "00.0", "-00.0", "9.", "-.5", "100.0"]
ROLL_TOKENS = ["180.0", "180.1", "-180.0", "-180.1", "-0.0", "-000.0", "999.9", "-1000.0"]
ADC_TOKENS = ["0", "4095", "4096", "9999", "10000", "0000", "04095", "-0", "-1", "1.0", "", "4e3"]
FLAG_TOKENS = ["00", "1F", "1f", "20", "FF", "0a", "0A", "6", "006", "-1", " 6", "+6", "0x", "G0"]
TOKENS = [SEQ_TOKENS, HDG_TOKENS, PITCH_TOKENS, ROLL_TOKENS, *[ADC_TOKENS] * 6, FLAG_TOKENS]
random_token = st.text(st.sampled_from("0123456789.-+eEaAfF x,*$"), max_size=7)
# The constant choices of mutated_lines, built once (the same draws as building them inline).
_KINDS = st.sampled_from(("field", "random_field", "count", "case", "raw", "body", "truncate"))
_TOKEN_CHOICES = [st.sampled_from(tuple(tokens)) for tokens in TOKENS]
_EXTRA_FIELD = st.sampled_from(("0", "", "06"))
_EDIT = st.sampled_from(("flip", "insert", "delete"))
_EDIT_BYTE = st.integers(0, 255) | st.sampled_from(tuple(b"0123456789.,-*$\r\n"))


@st.composite
def mutated_lines(draw: st.DrawFn) -> bytes:
    """A $PGMRA line damaged in one of the ways a real link or a lax firmware would."""
    frame = draw(attitude_frames)
    parts = encode_body(frame).split(",")
    cr = draw(st.booleans())
    kind = draw(_KINDS)
    if kind in ("field", "random_field"):  # one field replaced, checksum made right
        i = draw(st.integers(0, 10))
        parts[i + 1] = draw(_TOKEN_CHOICES[i] if kind == "field" else random_token)
        return line(",".join(parts), cr=cr)
    if kind == "count":  # a field missing or an extra one
        if draw(st.booleans()):
            del parts[draw(st.integers(1, 11))]
        else:
            parts.insert(draw(st.integers(1, 12)), draw(_EXTRA_FIELD))
        return line(",".join(parts), cr=cr)
    if kind == "case":  # lower-case hex digits (accepted: be liberal in what you accept)
        parts[11] = parts[11].lower()
        return line(",".join(parts), cr=cr, lower_cs=draw(st.booleans()))
    raw = bytearray(line(",".join(parts), cr=cr))
    if kind == "truncate":  # cut anywhere: the rest never comes
        return bytes(raw[: draw(st.integers(0, len(raw) - 1))])
    body_only = kind == "body"  # edit inside the body, then fix the checksum
    lo, hi = (1, len(raw) - (6 if cr else 5)) if body_only else (0, len(raw))
    at = draw(st.integers(lo, hi - 1))
    op = draw(_EDIT)
    byte = draw(_EDIT_BYTE)
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


def chunked(stream: bytes, cuts: list[int]) -> list[bytes]:
    cuts = sorted(cuts)
    return [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True)]


# --------------------------------------------------------------------------- valid input


@EXAMPLES
@given(
    st.lists(st.tuples(attitude_frames, st.booleans()), min_size=1, max_size=6),
    st.sampled_from(["one_chunk", "line_per_chunk", "random_cuts"]),
    st.data(),
)
def test_valid_lines_give_their_frames_whatever_the_chunking(
    items: list[tuple[AttitudeFrame, bool]], chunking: str, data: st.DataObject
) -> None:
    lines = [encoded(frame, cr) for frame, cr in items]
    stream = b"".join(lines)
    if chunking == "one_chunk":
        chunks = [stream]
    elif chunking == "line_per_chunk":
        chunks = lines
    else:
        chunks = chunked(stream, data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
    out, dec = decode_checked(*chunks)
    assert len(out) == len(items) and dec.counters.dropped.total == 0
    for got, (frame, _cr) in zip(attitudes(out), items, strict=True):
        # What was encoded comes back, on the datasheet's 0.1 grid.
        assert got == AttitudeFrame(*(getattr(got, x.name) for x in fields(got)))
        assert got.seq == frame.seq and got.mag_counts == frame.mag_counts
        assert got.acc_counts == frame.acc_counts and got.flags == frame.flags
        assert abs(got.pitch - frame.pitch) <= 0.05 + 1e-9
        assert (
            min(abs(got.heading - frame.heading), 360.0 - abs(got.heading - frame.heading))
            <= 0.05 + 1e-9
        )


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
def test_edge_lines_decode_normalised(chunk: bytes) -> None:
    out, dec = decode_checked(chunk)
    assert out and dec.counters.dropped.total == 0


def test_datasheet_line_decodes_to_its_values() -> None:
    out, _ = decode_checked(DATASHEET_PGMRA)
    assert out == [
        AttitudeFrame(1024, 87.3, -1.2, 0.4, 3101, 2470, 3311, 2470, 2452, 2950, Flags(6))
    ]


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
def test_valid_but_unusual_input_decodes(chunk: bytes) -> None:
    dec = GmrDecoder()
    out = dec.feed(chunk)
    assert out and dec.counters.dropped.total == 0
    assert attitudes([f for f in out if isinstance(f, AttitudeFrame)]) == reference_frames(chunk)


def _bytewise(chunk: bytes) -> tuple[object, ...]:
    dec = GmrDecoder()
    out = [f for i in range(len(chunk)) for f in dec.feed(chunk[i : i + 1])]
    return observable(dec, out)


def test_whole_lines_and_the_byte_by_byte_splitter_agree_on_every_edge() -> None:
    """A read that opens with whole $PGMRA lines takes them with one match each; fed a byte
    at a time, the same bytes go through the splitter. Both must give the same everything."""
    template = DATASHEET_PGMRA[1:-5].decode().split(",")
    chunks = [DATASHEET_PGMRA * 2, DATASHEET_PGMRA[:-2] + b"\n", b"$PGMRA,1*00\r\n"]
    for i, tokens in enumerate(TOKENS):
        for token in tokens:
            parts = list(template)
            parts[i + 1] = token
            chunks.append(line(",".join(parts)) + DATASHEET_PGMRA)
            chunks.append(DATASHEET_PGMRA + line(",".join(parts)))
    chunks.append(DATASHEET_PGMRA.replace(b"*50", b"*51") + DATASHEET_PGMRA)
    chunks.append(line("PGMRA," + ",".join(["0" * 12] * 11)))  # over 90 bytes: too long
    for chunk in chunks:
        dec = GmrDecoder()
        assert observable(dec, dec.feed(chunk)) == _bytewise(chunk), chunk


def test_a_read_of_whole_lines_skips_the_splitter_and_damage_does_not() -> None:
    calls: list[bytes] = []
    real = LineSplitter.feed

    def spy(self: LineSplitter, data: bytes) -> list[str]:
        calls.append(data)
        return real(self, data)

    dec = GmrDecoder()
    with patch.object(LineSplitter, "feed", spy):
        assert len(dec.feed(DATASHEET_PGMRA * 3)) == 3
        assert calls == []
        bad = DATASHEET_PGMRA.replace(b"*50", b"*51")
        assert len(dec.feed(DATASHEET_PGMRA + bad + DATASHEET_PGMRA)) == 2
    assert calls == [bad + DATASHEET_PGMRA]  # from the first line that needs it
    assert dec.counters.dropped["checksum"] == 1 and dec.counters.frames == 5


# --------------------------------------------------------------------------- damaged input


@EXAMPLES
@given(
    st.lists(
        st.one_of(
            mutated_lines(),
            valid_lines,
            props.between_noise(12),
        ),
        min_size=1,
        max_size=4,
    ),
    st.sampled_from(["one_chunk", "per_item"]),
)
def test_mutated_lines_give_exactly_the_oracles_frames(items: list[bytes], chunking: str) -> None:
    """Damaged lines, valid ones and noise, alone or together in one chunk."""
    chunks = [b"".join(items)] if chunking == "one_chunk" else items
    # Whatever state the damage left behind, the next valid line is decoded.
    out, _ = decode_checked(*chunks, DATASHEET_PGMRA)
    assert out[-1] == reference_frames(DATASHEET_PGMRA)[0]


def test_every_token_in_every_field_is_judged_as_the_oracle_does() -> None:
    """Each boundary/format token in each field, alone and before a valid line."""
    template = DATASHEET_PGMRA[1:-5].decode().split(",")
    tried = accepted = 0
    for i, tokens in enumerate(TOKENS):
        for token in tokens:
            parts = list(template)
            parts[i + 1] = token
            for cr in (True, False):
                bad = line(",".join(parts), cr=cr)
                out, dec = decode_checked(bad)
                accepted += len(out)
                assert len(out) + dec.counters.dropped.total == 1
                out, _ = decode_checked(bad + DATASHEET_PGMRA)
                assert attitudes(out)[-1].seq == 1024
                tried += 1
    assert tried == 2 * sum(map(len, TOKENS))
    assert 0 < accepted < tried  # both kinds are in the list


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
def test_rejections_count_their_reason_and_decoding_goes_on(
    field: int, token: str, reason: str
) -> None:
    parts = DATASHEET_PGMRA[1:-5].decode().split(",")
    parts[field + 1] = token
    out, dec = decode_checked(line(",".join(parts)) + DATASHEET_PGMRA)
    assert [f.seq for f in attitudes(out)] == [1024]
    assert dec.counters.dropped[reason] == 1 and dec.counters.dropped.total == 1
    assert dec.last_error is not None and dec.last_error.reason == reason


def test_bad_checksum_in_a_multiline_chunk_drops_only_that_line() -> None:
    bad = DATASHEET_PGMRA.replace(b"*50", b"*51")
    out, dec = decode_checked(DATASHEET_PGMRA + bad + DATASHEET_PGMRA)
    assert len(out) == 2
    assert dec.counters.dropped.snapshot()[DropReason.CHECKSUM] == 1
    assert dec.counters.frames == 2


def test_partial_line_then_rest() -> None:
    dec = GmrDecoder()
    assert dec.feed(DATASHEET_PGMRA[:30]) == []
    assert len(dec.feed(DATASHEET_PGMRA[30:])) == 1  # completes the buffered line
    assert len(dec.feed(DATASHEET_PGMRA)) == 1
    assert dec.counters.dropped.total == 0 and dec.counters.frames == 2


@pytest.mark.parametrize("cut", [DATASHEET_PGMRA[:30], DATASHEET_PGMRA[:-1]])
def test_line_cut_short_then_a_whole_line_counts_the_cut_one(cut: bytes) -> None:
    out, dec = decode_checked(cut, DATASHEET_PGMRA)  # its "$" ends the partial line
    assert len(out) == 1
    assert dec.counters.dropped["no_checksum"] == 1 and dec.counters.dropped.total == 1


def test_after_noise_the_next_line_decodes_and_noise_counts_once() -> None:
    out, dec = decode_checked(b"\xff\x00junk", DATASHEET_PGMRA)
    assert len(out) == 1
    assert dec.counters.dropped["noise"] == 1 and dec.counters.dropped.total == 1


def test_device_decoder_refuses_pgmra() -> None:
    dev = GmrDecoder("device")
    assert dev.feed(DATASHEET_PGMRA) == []
    assert dev.counters.dropped["unknown_id"] == 1


# --------------------------------------------------------------------------- fuzzing

FUZZ = examples(300)

chunk_kinds = st.one_of(
    st.binary(max_size=120),  # anything, "$" and line ends included
    mutated_lines(),  # truncated, corrupted, re-checksummed
    valid_lines,
    st.sampled_from([b"\r\n", b"$", b"*", b"\r", b"$PGMRA,", DATASHEET_PGMRA[:-2]]),
)


@FUZZ
@given(st.lists(chunk_kinds, max_size=12), st.data())
def test_fuzzed_stream_no_false_frame_no_lost_frame_counters_cut_independent(
    pieces: list[bytes], data: st.DataObject
) -> None:
    """Random, truncated and corrupted chunks with valid frames mixed in.

    The frames are exactly the valid ``$PGMRA`` lines the oracle finds in the bytes
    (none invented, none lost), and every counter is what decoding the stream in
    one piece gives, however the stream is cut into reads.
    """
    stream = b"".join(pieces)
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=16))
    decode_checked(*chunked(stream, cuts))


@FUZZ
@given(
    st.lists(
        st.tuples(
            valid_lines,
            st.lists(chunk_kinds, max_size=3).map(b"".join),
        ),
        min_size=1,
        max_size=8,
    ),
    st.data(),
)
def test_every_valid_frame_survives_the_junk_before_it(
    items: list[tuple[bytes, bytes]], data: st.DataObject
) -> None:
    """A valid line is decoded whatever came before it: its "$" resynchronises."""
    stream = b"".join(junk + valid for valid, junk in items)
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=16))
    out, _ = decode_checked(*chunked(stream, cuts))
    wanted = [reference_frames(valid)[0] for valid, _ in items]
    it = iter(out)
    assert all(any(w == f for f in it) for w in wanted)  # in order, as a subsequence


@examples(50)
@given(st.binary(min_size=1, max_size=64), st.integers(1, 64))
def test_byte_at_a_time_equals_one_piece(blob: bytes, repeat: int) -> None:
    stream = (blob + DATASHEET_PGMRA) * min(repeat, 8)
    decode_checked(*(stream[i : i + 1] for i in range(len(stream))))
