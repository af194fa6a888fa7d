"""GMR compass sentences: datasheet examples, strict validation, encode/decode round trip."""

from __future__ import annotations

import codec_props as props
import numpy as np
import pytest
from codec_props import assert_chunking_changes_nothing, line, only, stream_with_noise, xor_cs
from helpers import examples
from hypothesis import given
from hypothesis import strategies as st

from bridge.protocol.gmr import (
    RATES_HZ,
    AckFrame,
    AckReason,
    AttitudeFrame,
    CalProgressFrame,
    CommandFrame,
    Direction,
    Flags,
    GmrDecoder,
    GmrFrame,
    ParamsFrame,
    VersionFrame,
    encode,
)

FAST = examples(150)


# --------------------------------------------------------------------------- datasheet examples

DATASHEET_PGMRA = "$PGMRA,1024,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950,06*50"
DATASHEET_PGMRV = "$PGMRV,2.1.0,B3,GMR-000417*47"
EXAMPLE_ATTITUDE = AttitudeFrame(
    1024, 87.3, -1.2, 0.4, 3101, 2470, 3311, 2470, 2452, 2950, Flags.MAGOK | Flags.ACCOK
)
EXAMPLE_VERSION = VersionFrame("2.1.0", "B3", "GMR-000417")


@pytest.mark.parametrize("example", [DATASHEET_PGMRA, DATASHEET_PGMRV])
def test_datasheet_example_checksums_are_right(example: str) -> None:
    body, _, cs = example[1:].partition("*")
    assert int(cs, 16) == xor_cs(body.encode())


def test_datasheet_attitude_example_decodes() -> None:
    dec = GmrDecoder("host")
    (f,) = dec.feed(DATASHEET_PGMRA.encode() + b"\r\n")
    assert isinstance(f, AttitudeFrame)
    assert (f.seq, f.heading, f.pitch, f.roll) == (1024, 87.3, -1.2, 0.4)
    assert f.mag_counts == (3101, 2470, 3311)
    assert f.acc_counts == (2470, 2452, 2950)
    assert f.flags == Flags.MAGOK | Flags.ACCOK
    assert Flags.CAL not in f.flags
    assert f == EXAMPLE_ATTITUDE
    assert dec.counters.frames == 1
    only(dec.counters.dropped)


def test_datasheet_version_example_decodes() -> None:
    dec = GmrDecoder()
    assert dec.feed(DATASHEET_PGMRV.encode() + b"\r\n") == [EXAMPLE_VERSION]


def test_encode_reproduces_datasheet_lines() -> None:
    assert encode(EXAMPLE_ATTITUDE) == DATASHEET_PGMRA.encode() + b"\r\n"
    assert encode(EXAMPLE_VERSION) == DATASHEET_PGMRV.encode() + b"\r\n"


def test_factory_params_decode() -> None:
    body = "PGMRP,2458.0,2458.0,2458.0,1.0000,1.0000,1.0000,2458.0,2458.0,2949.5"
    (p,) = GmrDecoder().feed(line(body))
    assert p == ParamsFrame.factory()
    assert p.gzoff == 2949.5
    assert encode(p) == line(body)


# --------------------------------------------------------------------------- encoding format


def test_flags_are_two_uppercase_hex_digits() -> None:
    f = AttitudeFrame(0, 0.0, 0.0, 0.0, 0, 0, 0, 0, 0, 0, Flags(0x1F))
    assert encode(f).split(b",")[-1].startswith(b"1F*")
    g = AttitudeFrame(0, 0.0, 0.0, 0.0, 0, 0, 0, 0, 0, 0, Flags(0))
    assert encode(g).split(b",")[-1].startswith(b"00*")


def test_angles_one_decimal_no_negative_zero_no_360() -> None:
    f = AttitudeFrame(7, 359.96, -0.04, -179.99, 1, 2, 3, 4, 5, 6, Flags.SAT)
    assert encode(f) == line("PGMRA,7,0.0,0.0,-180.0,1,2,3,4,5,6,08")


def test_params_offsets_one_decimal_gains_four() -> None:
    p = ParamsFrame(2400.04, 0.0, 4095.0, 1.23456, 0.1, 10.0, 2458.25, 2458.0, 2949.5)
    assert encode(p) == line("PGMRP,2400.0,0.0,4095.0,1.2346,0.1000,10.0000,2458.2,2458.0,2949.5")


@pytest.mark.parametrize(
    ("frame", "body"),
    [
        (CommandFrame.ver(), "PGMRQ,VER"),
        (CommandFrame.rate(50), "PGMRQ,RATE,50"),
        (CommandFrame.magcal_start(), "PGMRQ,MAGCAL,START"),
        (CommandFrame.magcal_end(), "PGMRQ,MAGCAL,END"),
        (CommandFrame.magcal_abort(), "PGMRQ,MAGCAL,ABORT"),
        (CommandFrame.acccal(), "PGMRQ,ACCCAL"),
        (CommandFrame.par_get(), "PGMRQ,PAR,GET"),
        (
            CommandFrame.par_set(
                ParamsFrame(2400.5, 2500, 2458, 1, 0.9876, 1.1, 2458, 2458, 2949.5)
            ),
            "PGMRQ,PAR,SET,2400.5,2500.0,2458.0,1.0000,0.9876,1.1000,2458.0,2458.0,2949.5",
        ),
        (CommandFrame.reset(), "PGMRQ,RESET"),
        (AckFrame.rate_ok(20), "PGMRK,RATE,OK,20"),
        (AckFrame.success("MAGCAL"), "PGMRK,MAGCAL,OK"),
        (
            AckFrame.magcal_ok(2400, 2500.5, 2458, 1, 0.98765, 1.1),
            "PGMRK,MAGCAL,OK,2400.0,2500.5,2458.0,1.0000,0.9877,1.1000",
        ),
        (AckFrame.acccal_ok(2458.26, 2457, 2949.5), "PGMRK,ACCCAL,OK,2458.3,2457.0,2949.5"),
        (AckFrame.success("PAR"), "PGMRK,PAR,OK"),
        (AckFrame.success("RESET"), "PGMRK,RESET,OK"),
        (AckFrame.failure("FOO", AckReason.UNKNOWN), "PGMRK,FOO,ERR,UNKNOWN"),
        (AckFrame.failure("MAGCAL", "RANGE"), "PGMRK,MAGCAL,ERR,RANGE"),
        (CalProgressFrame(12, 1800, 3100, 0, 0, 0, 0), "PGMRC,12,1800,3100,0,0,0,0"),
    ],
)
def test_every_sentence_encodes_as_the_datasheet_says(frame: GmrFrame, body: str) -> None:
    assert encode(frame) == line(body)
    direction: Direction = "device" if isinstance(frame, CommandFrame) else "host"
    assert GmrDecoder(direction).feed(line(body)) == [frame]


# --------------------------------------------------------------------------- accepted readings


@pytest.mark.parametrize(
    ("body", "check"),
    [
        # 360.0 is the one-decimal rounding of 359.95..: tolerated, reported as 0.0.
        ("PGMRA,1,360.0,0.0,0.0,1,1,1,1,1,1,00", lambda f: f.heading == 0.0),
        ("PGMRA,1,87,0,0,1,1,1,1,1,1,00", lambda f: f.heading == 87.0),  # no decimals
        ("PGMRA,1,87.35,0,0,1,1,1,1,1,1,00", lambda f: f.heading == 87.35),  # extra decimal
        ("PGMRA,1,1.0,0.0,0.0,1,1,1,1,1,1,1f", lambda f: f.flags == Flags(0x1F)),  # lower hex
        ("PGMRA,65535,359.9,90.0,-180.0,0,4095,0,4095,0,4095,00", lambda f: f.seq == 65535),
        ("PGMRA,0,0.0,-90.0,180.0,0,0,0,0,0,0,00", lambda f: f.roll == 180.0),
        ("PGMRC,0,0,0,0,0,0,0", lambda f: f.span("x") == 0),
        ("PGMRP,0.0,4095.0,1.5,0.0977,10.2375,1,0,0,4095", lambda f: f.kx == 0.0977),
        ("PGMRK,RATE,OK,100", lambda f: f.rate_hz == 100),
        ("PGMRK,ACCCAL,ERR,MOTION", lambda f: f.reason is AckReason.MOTION and not f.ok),
    ],
)
def test_accepted_edge_values(body: str, check: object) -> None:
    dec = GmrDecoder()
    out = dec.feed(line(body))
    assert len(out) == 1, dec.last_error
    assert callable(check) and check(out[0])
    only(dec.counters.dropped)


# --------------------------------------------------------------------------- every drop reason

GOOD = line("PGMRV,2.1.0,B3,GMR-000417")
HOST_CASES: list[tuple[str, str]] = [
    # fields: missing or extra
    ("PGMRA,1024,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950", "fields"),
    ("PGMRA,1024,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950,06,7", "fields"),
    ("PGMRA", "fields"),
    ("PGMRV,2.1.0,B3", "fields"),
    ("PGMRV,2.1.0,B3,GMR-1,X", "fields"),
    ("PGMRV,2.1.0,,GMR-1", "fields"),
    ("PGMRC,1,2,3,4,5,6", "fields"),
    ("PGMRP,2458.0,2458.0,2458.0,1.0,1.0,1.0,2458.0,2458.0", "fields"),
    ("PGMRK,RATE", "fields"),
    ("PGMRK,RATE,OK", "fields"),
    ("PGMRK,PAR,OK,1", "fields"),
    ("PGMRK,PAR,ERR", "fields"),
    ("PGMRK,PAR,ERR,ARGS,X", "fields"),
    ("PGMRK,MAGCAL,OK,2458.0,2458.0,2458.0", "fields"),
    ("PGMRK,,OK", "fields"),
    # number: not a plain decimal
    ("PGMRA,1,abc,0.0,0.0,1,1,1,1,1,1,00", "number"),
    ("PGMRA,1,nan,0.0,0.0,1,1,1,1,1,1,00", "number"),
    ("PGMRA,1,inf,0.0,0.0,1,1,1,1,1,1,00", "number"),
    ("PGMRA,1,-inf,0.0,0.0,1,1,1,1,1,1,00", "number"),
    ("PGMRA,1,1e2,0.0,0.0,1,1,1,1,1,1,00", "number"),
    ("PGMRA,1,+5.0,0.0,0.0,1,1,1,1,1,1,00", "number"),
    ("PGMRA,1,.5,0.0,0.0,1,1,1,1,1,1,00", "number"),
    ("PGMRA,1,5.,0.0,0.0,1,1,1,1,1,1,00", "number"),
    ("PGMRA,1, 5.0,0.0,0.0,1,1,1,1,1,1,00", "number"),
    ("PGMRA,1,1_0.0,0.0,0.0,1,1,1,1,1,1,00", "number"),
    ("PGMRA,1,,0.0,0.0,1,1,1,1,1,1,00", "number"),
    ("PGMRA,10.0,1.0,0.0,0.0,1,1,1,1,1,1,00", "number"),
    ("PGMRA,1,1.0,0.0,0.0,3101.0,1,1,1,1,1,00", "number"),
    ("PGMRA,1,1.0,0.0,0.0,1,1,1,1,1,1,6", "number"),
    ("PGMRA,1,1.0,0.0,0.0,1,1,1,1,1,1,0G", "number"),
    ("PGMRA,1,1.0,0.0,0.0,1,1,1,1,1,1,006", "number"),
    ("PGMRC,x,0,0,0,0,0,0", "number"),
    ("PGMRP,nan,2458.0,2458.0,1.0,1.0,1.0,2458.0,2458.0,2949.5", "number"),
    ("PGMRK,RATE,OK,ten", "number"),
    ("PGMRK,ACCCAL,OK,2458.0,inf,2949.5", "number"),
    # range
    ("PGMRA,65536,1.0,0.0,0.0,1,1,1,1,1,1,00", "range"),
    ("PGMRA,-1,1.0,0.0,0.0,1,1,1,1,1,1,00", "range"),
    ("PGMRA,1,360.1,0.0,0.0,1,1,1,1,1,1,00", "range"),
    ("PGMRA,1,-0.1,0.0,0.0,1,1,1,1,1,1,00", "range"),
    ("PGMRA,1,1.0,90.1,0.0,1,1,1,1,1,1,00", "range"),
    ("PGMRA,1,1.0,-90.1,0.0,1,1,1,1,1,1,00", "range"),
    ("PGMRA,1,1.0,0.0,180.1,1,1,1,1,1,1,00", "range"),
    ("PGMRA,1,1.0,0.0,-180.1,1,1,1,1,1,1,00", "range"),
    ("PGMRA,1,1.0,0.0,0.0,4096,1,1,1,1,1,00", "range"),
    ("PGMRA,1,1.0,0.0,0.0,1,1,1,1,1,-1,00", "range"),
    ("PGMRA,1,1.0,0.0,0.0,1,1,1,1,1,1,20", "range"),
    ("PGMRA,1,1.0,0.0,0.0,1,1,1,1,1,1,FF", "range"),
    ("PGMRC,5,3000,2000,0,0,0,0", "range"),
    ("PGMRC,5,0,4096,0,0,0,0", "range"),
    ("PGMRC,-5,0,0,0,0,0,0", "range"),
    ("PGMRP,4095.1,2458.0,2458.0,1.0,1.0,1.0,2458.0,2458.0,2949.5", "range"),
    ("PGMRP,-1.0,2458.0,2458.0,1.0,1.0,1.0,2458.0,2458.0,2949.5", "range"),
    ("PGMRP,2458.0,2458.0,2458.0,10.3,1.0,1.0,2458.0,2458.0,2949.5", "range"),
    ("PGMRP,2458.0,2458.0,2458.0,1.0,0.09,1.0,2458.0,2458.0,2949.5", "range"),
    ("PGMRP,2458.0,2458.0,2458.0,1.0,1.0,1.0,2458.0,2458.0,4096.0", "range"),
    ("PGMRK,RATE,OK,7", "range"),
    ("PGMRK,PAR,ERR,FOO", "range"),
    ("PGMRK,PAR,MAYBE", "range"),
    ("PGMRK,VER,OK", "range"),
    ("PGMRK,MAGCAL,OK,2458.0,2458.0,2458.0,1.0,11.0,1.0", "range"),
    # unknown_id
    ("GPGGA,1,2,3", "unknown_id"),
    ("PGMRQ,VER", "unknown_id"),  # the other direction
    ("PGMRX,1", "unknown_id"),
    ("pgmra,1024,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950,06", "unknown_id"),
    ("", "unknown_id"),
]


@pytest.mark.parametrize(("body", "reason"), HOST_CASES)
def test_host_drop_reasons_counted_once_then_next_frame(body: str, reason: str) -> None:
    dec = GmrDecoder("host")
    assert dec.feed(line(body) + GOOD) == [EXAMPLE_VERSION]
    only(dec.counters.dropped, **{reason: 1})
    assert dec.last_error is not None and dec.last_error.reason == reason
    assert dec.counters.frames == 1


DEVICE_CASES: list[tuple[str, str]] = [
    ("PGMRA,1024,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950,06", "unknown_id"),
    ("PGMRK,PAR,OK", "unknown_id"),
    ("PGMRQ", "fields"),
    ("PGMRQ,", "fields"),
]


@pytest.mark.parametrize(("body", "reason"), DEVICE_CASES)
def test_device_drop_reasons(body: str, reason: str) -> None:
    dec = GmrDecoder("device")
    assert dec.feed(line(body) + line("PGMRQ,VER")) == [CommandFrame.ver()]
    only(dec.counters.dropped, **{reason: 1})


def test_framing_drops_land_in_the_same_counters() -> None:
    dec = GmrDecoder()
    bad_cs = DATASHEET_PGMRA[:-2].encode() + b"51\r\n"
    data = b"\xff\xfejunk" + bad_cs + b"$PGMRA,1,2" + GOOD + b"$" + b"9" * 200 + b"\r\n" + GOOD
    assert dec.feed(data) == [EXAMPLE_VERSION, EXAMPLE_VERSION]
    only(dec.counters.dropped, noise=1, checksum=1, no_checksum=1, too_long=1)
    assert dec.counters.bytes_in == len(data)


def test_device_receives_malformed_commands_so_it_can_answer_err() -> None:
    dec = GmrDecoder("device")
    out = dec.feed(line("PGMRQ,FOO") + line("PGMRQ,RATE,7") + line("PGMRQ,PAR,SET,1,2"))
    commands = [c for c in out if isinstance(c, CommandFrame)]
    assert len(commands) == len(out) == 3
    assert [c.error() for c in commands] == [AckReason.UNKNOWN, AckReason.ARGS, AckReason.ARGS]
    only(dec.counters.dropped)


def test_bad_direction_rejected() -> None:
    with pytest.raises(ValueError):
        GmrDecoder("sideways")  # type: ignore[arg-type]  # not a direction: refused


# --------------------------------------------------------------------------- frame validation


def test_constructors_refuse_what_the_decoder_would_drop() -> None:
    with pytest.raises(ValueError):
        AttitudeFrame(0, 360.0, 0, 0, 0, 0, 0, 0, 0, 0, Flags(0))
    with pytest.raises(ValueError):
        AttitudeFrame(0, 0, 0, 0, 0, 0, 0, 0, 0, 0, Flags(0x20))
    with pytest.raises(ValueError):
        AttitudeFrame(0, 0, 0, 0, 3101.5, 0, 0, 0, 0, 0, Flags(0))  # type: ignore[arg-type]  # a fractional count: refused
    with pytest.raises(ValueError):
        AttitudeFrame(0, float("nan"), 0, 0, 0, 0, 0, 0, 0, 0, Flags(0))
    with pytest.raises(ValueError):
        VersionFrame("2,1", "B3", "X")
    with pytest.raises(ValueError):
        VersionFrame("2.1", "B3", "S" * 90)  # line would exceed 96 bytes
    with pytest.raises(ValueError):
        CalProgressFrame(1, 10, 5, 0, 0, 0, 0)
    with pytest.raises(ValueError):
        AckFrame("PAR", False, ("NOPE",))
    with pytest.raises(ValueError):
        CommandFrame("")
    with pytest.raises(ValueError):
        CommandFrame.rate(7)
    with pytest.raises(ValueError):  # flash may hold 10.1 (MAGCAL), but PAR,SET refuses it
        CommandFrame.par_set(ParamsFrame(2458, 2458, 2458, 10.1, 1, 1, 2458, 2458, 2949.5))


def test_numpy_numbers_are_normalised() -> None:
    c = np.array([1, 2, 3, 4, 5, 6])
    f = AttitudeFrame(
        np.int64(5),  # type: ignore[arg-type]  # numpy numbers, on purpose
        np.float64(10.0),
        0,
        0,
        c[0],
        c[1],
        c[2],
        c[3],
        c[4],
        c[5],
        Flags(0),
    )
    assert type(f.seq) is int and type(f.mx) is int and type(f.heading) is float
    assert type(f.pitch) is float


# --------------------------------------------------------------------------- command helpers


@pytest.mark.parametrize(
    ("cmd", "error"),
    [
        (CommandFrame.ver(), None),
        (CommandFrame("VER", ("X",)), AckReason.ARGS),
        (CommandFrame("RATE", ("100",)), None),
        (CommandFrame("RATE", ("3",)), AckReason.ARGS),
        (CommandFrame("RATE", ()), AckReason.ARGS),
        (CommandFrame("RATE", ("1.0",)), AckReason.ARGS),
        (CommandFrame("MAGCAL", ("GO",)), AckReason.ARGS),
        (CommandFrame("PAR", ()), AckReason.ARGS),
        (CommandFrame("PAR", ("SET", *("1",) * 9)), None),
        (
            CommandFrame("PAR", ("SET", "1", "1", "1", "0.05", "1", "1", "1", "1", "1")),
            AckReason.ARGS,
        ),
        (
            CommandFrame("PAR", ("SET", "1", "1", "4096", "1", "1", "1", "1", "1", "1")),
            AckReason.ARGS,
        ),
        (
            CommandFrame("PAR", ("SET", "1", "1", "nan", "1", "1", "1", "1", "1", "1")),
            AckReason.ARGS,
        ),
        (CommandFrame("ver"), AckReason.UNKNOWN),
    ],
)
def test_command_error(cmd: CommandFrame, error: AckReason | None) -> None:
    assert cmd.error() == error


def test_command_accessors_and_answers() -> None:
    assert CommandFrame.rate(20).rate_hz() == 20
    p = ParamsFrame(2400.5, 2500, 2458, 1, 0.9876, 1.1, 2458, 2458, 2949.5)
    assert CommandFrame.par_set(p).params() == p
    assert CommandFrame.par_set(p).key == "PAR,SET"
    assert CommandFrame.magcal_end().key == "MAGCAL,END"
    with pytest.raises(ValueError):
        CommandFrame.ver().rate_hz()
    assert CommandFrame.ver().is_answer(EXAMPLE_VERSION)
    assert not CommandFrame.rate(10).is_answer(EXAMPLE_VERSION)
    assert CommandFrame.par_get().is_answer(ParamsFrame.factory())
    assert not CommandFrame.par_set(p).is_answer(ParamsFrame.factory())
    assert CommandFrame.rate(10).is_answer(AckFrame.rate_ok(10))
    assert not CommandFrame.rate(10).is_answer(AckFrame.success("PAR"))
    assert not CommandFrame.rate(10).is_answer(EXAMPLE_ATTITUDE)
    assert CommandFrame.magcal_end().ack_err("RANGE") == AckFrame("MAGCAL", False, ("RANGE",))


def test_ack_accessors() -> None:
    ok = AckFrame.magcal_ok(2400, 2500.5, 2458, 1, 0.98765, 1.1)
    assert ok.reason is None
    assert ok.values == (2400.0, 2500.5, 2458.0, 1.0, 0.9877, 1.1)
    assert ok.rate_hz is None
    err = AckFrame.failure("ACCCAL", "MOTION")
    assert err.reason is AckReason.MOTION and err.values == ()


# --------------------------------------------------------------------------- properties


def tenths(lo: int, hi: int) -> st.SearchStrategy[float]:
    return st.integers(lo, hi).map(lambda n: n / 10)


counts = st.integers(0, 4095)
token = st.text(
    st.characters(min_codepoint=0x20, max_codepoint=0x7E, exclude_characters="$*,"),
    min_size=1,
    max_size=12,
)
offsets = tenths(0, 40950)
gains = st.integers(977, 102375).map(lambda n: n / 10000)


@st.composite
def calprogress(draw: st.DrawFn) -> CalProgressFrame:
    axes = [sorted((draw(counts), draw(counts))) for _ in range(3)]
    return CalProgressFrame(draw(st.integers(0, 2**32 - 1)), *(v for ax in axes for v in ax))


# Flags sampled from their 32 values: the same integer choice in 0..31 as
# integers(0, 31).map(Flags), one strategy layer less to draw through.
FLAG_VALUES = tuple(Flags(i) for i in range(32))
attitude_frames = st.builds(
    AttitudeFrame,
    st.integers(0, 65535),
    tenths(0, 3599),
    tenths(-900, 900),
    tenths(-1800, 1800),
    counts,
    counts,
    counts,
    counts,
    counts,
    counts,
    st.sampled_from(FLAG_VALUES),
)
params_frames = st.builds(
    ParamsFrame, offsets, offsets, offsets, gains, gains, gains, offsets, offsets, offsets
)
ack_frames = st.one_of(
    st.sampled_from(RATES_HZ).map(AckFrame.rate_ok),
    st.builds(AckFrame.magcal_ok, offsets, offsets, offsets, gains, gains, gains),
    st.builds(AckFrame.acccal_ok, offsets, offsets, offsets),
    st.sampled_from(["MAGCAL", "PAR", "RESET"]).map(AckFrame.success),
    st.builds(AckFrame.failure, token, st.sampled_from(list(AckReason))),
)
host_frames: st.SearchStrategy[GmrFrame] = st.one_of(
    attitude_frames,
    st.builds(VersionFrame, token, token, token),
    calprogress(),
    params_frames,
    ack_frames,
)
command_frames = st.one_of(
    st.builds(
        CommandFrame,
        token,
        st.lists(token | st.just(""), max_size=5).map(tuple),
    ),
    st.sampled_from(RATES_HZ).map(CommandFrame.rate),
    params_frames.filter(lambda p: all(0.1 <= k <= 10 for k in (p.kx, p.ky, p.kz))).map(
        CommandFrame.par_set
    ),
)


@FAST
@given(host_frames)
def test_round_trip_host_frames(frame: GmrFrame) -> None:
    dec = GmrDecoder("host")
    assert dec.feed(encode(frame)) == [frame]
    only(dec.counters.dropped)


@FAST
@given(command_frames)
def test_round_trip_command_frames(frame: CommandFrame) -> None:
    dec = GmrDecoder("device")
    assert dec.feed(encode(frame)) == [frame]
    only(dec.counters.dropped)


@FAST
@given(st.lists(st.tuples(host_frames, st.binary(max_size=20)), max_size=6), st.data())
def test_any_chunking_gives_the_same_frames(
    items: list[tuple[GmrFrame, bytes]], data: st.DataObject
) -> None:
    # Noise here may hold "$" and corrupt frames: only whole-vs-chunked equality is asserted.
    stream = b"".join(encode(f) + noise for f, noise in items)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    assert_chunking_changes_nothing(GmrDecoder, stream, cuts)


@FAST
@given(props.noisy_frames(host_frames))
def test_noise_yields_exactly_the_frames_it_did_not_touch(
    items: list[tuple[GmrFrame, bytes, tuple[int, bytes] | None]],
) -> None:
    """Junk between frames never holds "$" (so it cannot start or cut a line); junk
    inside a frame is control/non-ASCII bytes (which kill that line). The output is
    therefore exactly the untouched frames, in order."""
    stream, expected = stream_with_noise(items, encode)
    dec = GmrDecoder()
    assert dec.feed(stream) == expected
    touched = len(items) - len(expected)
    assert dec.counters.dropped["noise"] >= (1 if touched else 0)
    assert dec.counters.dropped.total - dec.counters.dropped["noise"] == 0


@FAST
@given(st.binary(max_size=400), st.sampled_from(["host", "device"]))
def test_random_bytes_never_raise(blob: bytes, direction: Direction) -> None:
    dec = GmrDecoder(direction)
    out = dec.feed(blob)
    assert dec.counters.frames == len(out)
    assert dec.counters.bytes_in == len(blob)


field_text = st.text(st.sampled_from("0123456789.-+eEnaif AFZ"), max_size=7)


@FAST
@given(
    st.sampled_from(["PGMRA", "PGMRV", "PGMRC", "PGMRP", "PGMRK", "PGMRQ"]),
    st.lists(field_text | st.sampled_from(["OK", "ERR", "RATE", "PAR", "ARGS"]), max_size=12),
)
def test_checksummed_garbage_fields_never_raise_and_accepted_frames_are_valid(
    ident: str, fields: list[str]
) -> None:
    body = ",".join([ident, *fields])[:90]
    dec = GmrDecoder()
    out = dec.feed(line(body))
    assert len(out) + dec.counters.dropped.total == 1
    for f in out:  # anything accepted must re-encode and decode to itself
        assert GmrDecoder().feed(encode(f)) == [f]
