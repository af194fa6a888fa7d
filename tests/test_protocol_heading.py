"""Heading-only compasses: NMEA HDT/HDG/HDM, $PTNTHPR and OceanServer $C sentences."""

from __future__ import annotations

import codec_props as props
import pytest
from codec_props import assert_chunking_changes_nothing, line, only, stream_with_noise, xor_cs
from helpers import examples
from hypothesis import given
from hypothesis import strategies as st

from bridge.protocol.heading import (
    HPR_STATUS,
    HeadingDecoder,
    HeadingFrame,
    HeadingProtocol,
    encode,
)

FAST = examples(150)


# --------------------------------------------------------------------------- public examples

# HMR3000 user's guide, "Warning and Alarm Settings", and OceanServer OS5000 manual.
HMR3000_EXAMPLES = [
    "$PTNTHPR,59.6,N,-0.2,N,-3.0,N*0F",
    "$PTNTHPR,72.9,N,-1.6,N,-29.6,O*33",
    "$PTNTHPR,,N,-1.5,N,,P*03",
    "$PTNTHPR,,P,0.3,N,0.1,N*06",
]
OS5000_EXAMPLE = "$C320.5P0.2R-18.3T19.0*3C"


@pytest.mark.parametrize("example", [*HMR3000_EXAMPLES, OS5000_EXAMPLE])
def test_public_example_checksums(example: str) -> None:
    body, _, cs = example[1:].partition("*")
    assert int(cs, 16) == xor_cs(body.encode())


def test_hmr3000_examples_decode_with_status_visible() -> None:
    dec = HeadingDecoder("nmea")
    out = dec.feed(b"".join(e.encode() + b"\r\n" for e in HMR3000_EXAMPLES))
    only(dec.counters.dropped)
    assert [(f.heading_deg, f.pitch_deg, f.roll_deg, f.status) for f in out] == [
        (59.6, -0.2, -3.0, ("N", "N", "N")),
        (72.9, -1.6, -29.6, ("N", "N", "O")),
        (None, -1.5, None, ("N", "N", "P")),  # roll over the alarm level: values nulled
        (None, 0.3, 0.1, ("P", "N", "N")),  # magnetometer high alarm: heading nulled
    ]
    assert [f.status_ok for f in out] == [True, False, False, False]
    assert all(f.sentence == "HPR" and f.talker == "TNT" for f in out)
    assert all(f.reference == "magnetic" for f in out)
    # Re-encoding gives the manual's lines back byte for byte.
    assert [encode(f) for f in out] == [e.encode() + b"\r\n" for e in HMR3000_EXAMPLES]


def test_os5000_example_decodes() -> None:
    dec = HeadingDecoder("os5000")
    (f,) = dec.feed(OS5000_EXAMPLE.encode() + b"\r\n")
    assert (f.heading_deg, f.pitch_deg, f.roll_deg, f.temperature_c) == (320.5, 0.2, -18.3, 19.0)
    assert (f.sentence, f.talker, f.reference) == ("C", "", "magnetic")
    assert encode(f) == OS5000_EXAMPLE.encode() + b"\r\n"


def test_os5000_optional_fields() -> None:
    dec = HeadingDecoder("os5000")
    out = dec.feed(
        line("C212.4P2.5R-14.0T28.4Mx107977.90My-79422.00Mz173.27Ax0.045Ay-0.245Az0.977")
        + line("C10.5")
        + line("C10.5T-3.5")
    )
    only(dec.counters.dropped)
    assert out == [
        HeadingFrame.os5000(212.4, 2.5, -14.0, 28.4),
        HeadingFrame.os5000(10.5),
        HeadingFrame.os5000(10.5, temperature_c=-3.5),
    ]


# --------------------------------------------------------------------------- NMEA semantics


def test_hdg_reports_sensor_plus_deviation_and_variation_separately() -> None:
    dec = HeadingDecoder()
    (f,) = dec.feed(line("HCHDG,350.0,15.0,E,2.5,W"))
    assert f.heading_deg == 5.0  # 350 + 15 E, wrapped
    assert f.deviation_deg == 15.0
    assert f.variation_deg == -2.5  # W negative
    assert f.true_heading_deg == 2.5
    assert (f.reference, f.talker, f.sentence) == ("magnetic", "HC", "HDG")


@pytest.mark.parametrize(
    ("body", "heading", "deviation", "variation"),
    [
        ("HCHDG,0.2,0.1,E,,", 0.3, 0.1, None),  # exact decimal sum, not 0.30000000000000004
        ("HCHDG,5.0,10.0,W,,", 355.0, -10.0, None),
        ("HCHDG,10.0,,,,", 10.0, None, None),
        ("HCHDG,10.0,,,3.0,E", 10.0, None, 3.0),
        ("HCHDG,359.9,0.1,E,0.0,W", 0.0, 0.1, 0.0),
        ("HCHDG,360.0,,,,", 0.0, None, None),
    ],
)
def test_hdg_arithmetic(
    body: str, heading: float, deviation: float | None, variation: float | None
) -> None:
    (f,) = HeadingDecoder().feed(line(body))
    assert (f.heading_deg, f.deviation_deg, f.variation_deg) == (heading, deviation, variation)


@pytest.mark.parametrize("talker", ["HC", "HE", "II", "GP", "U1", "AG"])
def test_any_talker(talker: str) -> None:
    dec = HeadingDecoder()
    out = dec.feed(line(f"{talker}HDT,123.4,T") + line(f"{talker}HDM,120.0,M"))
    assert out == [HeadingFrame.hdt(123.4, talker), HeadingFrame.hdm(120.0, talker)]
    assert out[0].reference == "true" and out[1].reference == "magnetic"
    assert out[0].true_heading_deg == 123.4 and out[1].true_heading_deg is None


def test_reference_option_for_sentences_that_do_not_say() -> None:
    (f,) = HeadingDecoder("nmea", reference="true").feed(line("PTNTHPR,10.0,N,0.0,N,0.0,N"))
    assert f.reference == "true" and f.true_heading_deg == 10.0
    (g,) = HeadingDecoder("os5000", reference="true").feed(line("C10.0"))
    assert g.reference == "true"


def test_heading_360_tolerated_as_zero_and_never_encoded() -> None:
    (f,) = HeadingDecoder().feed(line("HEHDT,360.0,T"))
    assert f.heading_deg == 0.0
    assert encode(HeadingFrame.hdt(359.97)) == line("HEHDT,0.0,T")
    assert encode(HeadingFrame.os5000(359.96, -0.04)) == line("C0.0P0.0")


@pytest.mark.parametrize(
    ("frame", "body"),
    [
        (HeadingFrame.hdt(87.3), "HEHDT,87.3,T"),
        (HeadingFrame.hdm(87.3, "II"), "IIHDM,87.3,M"),
        (HeadingFrame.hdg(5.0, 15.0, -2.5), "HCHDG,350.0,15.0,E,2.5,W"),
        (HeadingFrame.hdg(5.0), "HCHDG,5.0,,,,"),
        (HeadingFrame.hpr(None, 1.0, None, ("L", "N", "P")), "PTNTHPR,,L,1.0,N,,P"),
        (HeadingFrame.os5000(1.0, 2.0, 3.0, 4.0), "C1.0P2.0R3.0T4.0"),
        (HeadingFrame.os5000(1.0, roll_deg=-3.0), "C1.0R-3.0"),
    ],
)
def test_encoders(frame: HeadingFrame, body: str) -> None:
    assert encode(frame) == line(body)


# --------------------------------------------------------------------------- drop reasons

NMEA_GOOD = line("HEHDT,1.0,T")
NMEA_CASES: list[tuple[str, str]] = [
    ("HCHDT,10.0", "fields"),
    ("HCHDT,10.0,T,X", "fields"),
    ("HCHDT,,T", "fields"),
    ("HCHDT", "fields"),
    ("HCHDG,10.0,1.0,,,", "fields"),
    ("HCHDG,10.0,,E,,", "fields"),
    ("HCHDG,10.0,1.0,E,2.0", "fields"),
    ("HCHDG,,1.0,E,,", "fields"),
    ("PTNTHPR,1.0,N,2.0,N,3.0", "fields"),
    ("PTNTHPR,1.0,,2.0,N,3.0,N", "fields"),
    ("HCHDT,abc,T", "number"),
    ("HCHDT,nan,T", "number"),
    ("HCHDM,inf,M", "number"),
    ("HCHDT,1e2,T", "number"),
    ("HCHDG,10.0,x,E,,", "number"),
    ("PTNTHPR,1.0,N,1e1,N,0.0,N", "number"),
    ("HCHDT,360.1,T", "range"),
    ("HCHDT,-1.0,T", "range"),
    ("HCHDT,10.0,M", "range"),
    ("HCHDM,10.0,T", "range"),
    ("HCHDG,10.0,1.0,X,,", "range"),
    ("HCHDG,10.0,-1.0,E,,", "range"),
    ("HCHDG,10.0,,,181.0,E", "range"),
    ("HCHDG,10.0,181.0,E,,", "range"),
    ("HCHDG,360.5,,,,", "range"),
    ("PTNTHPR,1.0,Q,0.0,N,0.0,N", "range"),
    ("PTNTHPR,1.0,N,91.0,N,0.0,N", "range"),
    ("PTNTHPR,1.0,N,0.0,N,181.0,N", "range"),
    ("GPGGA,1,2,3", "unknown_id"),
    ("HCHDX,1.0", "unknown_id"),
    ("PGHDT,1.0,T", "unknown_id"),  # "P" starts a proprietary sentence, not a talker
    ("hchdt,1.0,T", "unknown_id"),
    ("HHDT,1.0,T", "unknown_id"),
    ("C320.5P0.2", "unknown_id"),  # OS5000 on an NMEA decoder
    ("PTNTXYZ,1", "unknown_id"),
    ("PGMRA,1,2", "unknown_id"),
]


@pytest.mark.parametrize(("body", "reason"), NMEA_CASES)
def test_nmea_drop_reasons(body: str, reason: str) -> None:
    dec = HeadingDecoder("nmea")
    assert dec.feed(line(body) + NMEA_GOOD) == [HeadingFrame.hdt(1.0)]
    only(dec.counters.dropped, **{reason: 1})
    assert dec.last_error is not None and dec.last_error.reason == reason


OS_GOOD = line("C1.0P2.0R3.0T4.0")
OS_CASES: list[tuple[str, str]] = [
    ("HEHDT,1.0,T", "unknown_id"),
    ("P1.0C2.0", "unknown_id"),
    ("c1.0", "unknown_id"),
    ("C1.0Q2.0", "fields"),
    ("C1.0P1.0P2.0", "fields"),
    ("C1.0P", "fields"),
    ("C", "fields"),
    ("Cx1.0", "unknown_id"),  # first tag must be exactly "C"
    ("Cnan", "number"),
    ("Cinf", "number"),
    ("C1.0P1.0.0", "number"),
    ("C1.0Mxabc", "number"),
    ("C1.0,P2.0", "number"),
    ("C360.5", "range"),
    ("C1.0P90.5", "range"),
    ("C1.0R-180.5", "range"),
    ("C1.0T200.0", "range"),
]


@pytest.mark.parametrize(("body", "reason"), OS_CASES)
def test_os5000_drop_reasons(body: str, reason: str) -> None:
    dec = HeadingDecoder("os5000")
    assert dec.feed(line(body) + OS_GOOD) == [HeadingFrame.os5000(1.0, 2.0, 3.0, 4.0)]
    only(dec.counters.dropped, **{reason: 1})


def test_framing_drops_counted_by_heading_decoder() -> None:
    dec = HeadingDecoder()
    data = b"\x00junk" + b"$HEHDT,1.0,T*00\r\n" + b"$HEHDT,1.0,T\r\n" + NMEA_GOOD
    assert dec.feed(data) == [HeadingFrame.hdt(1.0)]
    only(dec.counters.dropped, noise=1, checksum=1, no_checksum=1)
    assert dec.counters.frames == 1 and dec.counters.bytes_in == len(data)


def test_bad_constructor_arguments() -> None:
    with pytest.raises(ValueError):
        HeadingDecoder("gmr")  # type: ignore[arg-type]  # not a heading protocol: refused
    with pytest.raises(ValueError):
        HeadingDecoder("nmea", reference="grid")  # type: ignore[arg-type]  # not a reference: refused
    with pytest.raises(ValueError):
        HeadingFrame(10.0, "true", pitch_deg=1.0, talker="HE", sentence="HDT")
    with pytest.raises(ValueError):
        HeadingFrame(None, "true", talker="HE", sentence="HDT")
    with pytest.raises(ValueError):
        HeadingFrame.hdt(10.0, talker="H")
    with pytest.raises(ValueError):
        HeadingFrame.hdm(360.0)
    with pytest.raises(ValueError):
        HeadingFrame.hpr(1.0, 0.0, 0.0, ("N", "N", "X"))
    with pytest.raises(ValueError):
        HeadingFrame(1.0, "true", sentence="HDM", talker="HC")
    with pytest.raises(ValueError):
        HeadingFrame.os5000(1.0, temperature_c=300.0)


def test_status_letters_table() -> None:
    assert set(HPR_STATUS) == {"N", "O", "P", "M", "L", "C"}
    for letter in HPR_STATUS:
        f = HeadingFrame.hpr(1.0, 0.0, 0.0, ("N", letter, "N"))
        assert f.status_ok == (letter == "N")


# --------------------------------------------------------------------------- properties


def tenths(lo: int, hi: int) -> st.SearchStrategy[float]:
    return st.integers(lo, hi).map(lambda n: n / 10)


headings = tenths(0, 3599)
pitches = tenths(-900, 900)
rolls = tenths(-1800, 1800)
signed180 = tenths(-1800, 1800)
talkers = st.from_regex(r"[A-OQ-Z][A-Z0-9]", fullmatch=True)
status_letter = st.sampled_from(sorted(HPR_STATUS))

nmea_frames = st.one_of(
    st.builds(HeadingFrame.hdt, headings, talkers),
    st.builds(HeadingFrame.hdm, headings, talkers),
    st.builds(HeadingFrame.hdg, headings, st.none() | signed180, st.none() | signed180, talkers),
    st.builds(
        HeadingFrame.hpr,
        st.none() | headings,
        st.none() | pitches,
        st.none() | rolls,
        st.tuples(status_letter, status_letter, status_letter),
    ),
)
os5000_frames = st.builds(
    HeadingFrame.os5000,
    headings,
    st.none() | pitches,
    st.none() | rolls,
    st.none() | tenths(-550, 1250),
)


@FAST
@given(nmea_frames)
def test_round_trip_nmea(frame: HeadingFrame) -> None:
    dec = HeadingDecoder("nmea")
    assert dec.feed(encode(frame)) == [frame]
    only(dec.counters.dropped)


@FAST
@given(os5000_frames)
def test_round_trip_os5000(frame: HeadingFrame) -> None:
    dec = HeadingDecoder("os5000")
    assert dec.feed(encode(frame)) == [frame]
    only(dec.counters.dropped)


def _stream_case(protocol: HeadingProtocol) -> st.SearchStrategy[list[tuple[HeadingFrame, bytes]]]:
    frames = nmea_frames if protocol == "nmea" else os5000_frames
    return st.lists(st.tuples(frames, st.binary(max_size=20)), max_size=6)


@FAST
@given(st.sampled_from(["nmea", "os5000"]), st.data())
def test_any_chunking_gives_the_same_frames(protocol: HeadingProtocol, data: st.DataObject) -> None:
    items = data.draw(_stream_case(protocol))
    stream = b"".join(encode(f) + noise for f, noise in items)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    assert_chunking_changes_nothing(lambda: HeadingDecoder(protocol), stream, cuts)


@FAST
@given(props.noisy_frames(nmea_frames))
def test_noise_yields_exactly_the_frames_it_did_not_touch(
    items: list[tuple[HeadingFrame, bytes, tuple[int, bytes] | None]],
) -> None:
    stream, expected = stream_with_noise(items, encode)
    dec = HeadingDecoder("nmea")
    assert dec.feed(stream) == expected
    assert dec.counters.dropped.total == dec.counters.dropped["noise"]


@FAST
@given(st.binary(max_size=400), st.sampled_from(["nmea", "os5000"]))
def test_random_bytes_never_raise(blob: bytes, protocol: HeadingProtocol) -> None:
    dec = HeadingDecoder(protocol)
    out = dec.feed(blob)
    assert dec.counters.frames == len(out)


@FAST
@given(
    st.sampled_from(["HCHDT", "HCHDM", "HCHDG", "PTNTHPR", "C"]),
    st.lists(st.text(st.sampled_from("0123456789.-EWNTMPOLC"), max_size=6), max_size=7),
    st.sampled_from(["nmea", "os5000"]),
)
def test_checksummed_garbage_never_raises_and_accepted_frames_are_valid(
    ident: str, fields: list[str], protocol: HeadingProtocol
) -> None:
    sep = "" if ident == "C" else ","
    body = (ident + sep + ",".join(fields) if sep else ident + "".join(fields))[:90]
    dec = HeadingDecoder(protocol)
    out = dec.feed(line(body))
    assert len(out) + dec.counters.dropped.total == 1
    for f in out:
        # Accepted frames can always be rendered; rendering quantises to the
        # published one decimal, after which the round trip is exact.
        again = HeadingDecoder(protocol).feed(encode(f))
        assert len(again) == 1
        g = again[0]
        if f.heading_deg is not None:
            assert g.heading_deg is not None
            assert abs((g.heading_deg - f.heading_deg + 180.0) % 360.0 - 180.0) <= 0.05 + 1e-9
        assert HeadingDecoder(protocol).feed(encode(g)) == [g]
