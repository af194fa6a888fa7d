"""Codecs for heading-only compasses (``device.protocol = "nmea" | "os5000"``): pure, no I/O.

``"nmea"`` accepts, from any two-character talker (HC, HE, II, GP, U1, ...):

* ``$--HDT,<hdg>,T`` -- true heading;
* ``$--HDM,<hdg>,M`` -- magnetic heading;
* ``$--HDG,<sensor>,<dev>,<E|W>,<var>,<E|W>`` -- magnetic *sensor* heading with
  deviation and variation (E positive). The frame reports the magnetic
  heading ``sensor + deviation`` (summed exactly in decimal, so no float
  fuzz) and both corrections separately; empty dev/var pairs are ``None``;

and the Honeywell HMR3000 / True North ``$PTNTHPR,<hdg>,<s>,<pitch>,<s>,<roll>,<s>``
where each status letter is N normal, O high warning, P high alarm, M low
warning, L low alarm, C tuning the analogue circuit (True North). The device
leaves a value empty when its status is an alarm; such a sentence still
yields a frame, with that value ``None`` and the letters in ``status``
(``status_ok`` is False) -- dropping it would hide the alarm from the host.

``"os5000"`` accepts OceanServer ``$C<hdg>P<pitch>R<roll>T<temp>``. The
OS5000 family lets the user switch fields on and off, so only ``C`` (first) is
required; ``P``, ``R``, ``T`` are optional, and the optional tagged fields
``Mx My Mz Ax Ay Az`` (and ``D``, depth, of the OS5500) are checked as numbers
and then ignored. Unknown or repeated tags are ``fields``. Temperature is
taken as degrees Celsius (the factory setting).

Ranges: heading 0-360 with exactly 360.0 tolerated as 0.0 (the rounding
artefact of a firmware printing one decimal), pitch -90..90, roll -180..180,
deviation/variation magnitudes up to 180, temperature -55..125 °C (the die's
range; the OS5000 reading is the MCU's internal sensor).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from decimal import ROUND_HALF_EVEN, Decimal
from typing import Literal, TypeAlias

from bridge.protocol.framing import (
    CodecCounters,
    DecodeError,
    DropReason,
    LineSplitter,
    check_real,
    fmt_fixed,
    parse_decimal,
    render_line,
)
from bridge.types import HeadingReference

__all__ = [
    "HPR_STATUS",
    "HeadingDecoder",
    "HeadingFrame",
    "HeadingProtocol",
    "decode_body",
    "encode",
    "encode_body",
]

HeadingProtocol: TypeAlias = Literal["nmea", "os5000"]

#: ``$PTNTHPR`` status letters.
HPR_STATUS: dict[str, str] = {
    "N": "normal",
    "O": "high warning",
    "P": "high alarm",
    "M": "low warning",
    "L": "low alarm",
    "C": "tuning analog circuit",
}

_SENTENCES = ("HDT", "HDM", "HDG", "HPR", "C")
_TALKER_RE = re.compile(r"[A-OQ-Z][A-Z0-9]")  # "P..." is the proprietary prefix, not a talker
_OS5000_TAG_RE = re.compile(r"([A-Z][xyz]?)([^A-Z]*)")
_OS5000_IGNORED = frozenset({"Mx", "My", "Mz", "Ax", "Ay", "Az", "D"})
_TEMP_RANGE = (-55.0, 125.0)
_TENTH = Decimal("0.1")


def _heading(value: float, name: str = "heading") -> float:
    return check_real(value, name, 0.0, 360.0, hi_open=True)


def _parse_heading(text: str) -> float:
    v = parse_decimal(text, "heading")
    if v == 360.0:  # tolerated rounding artefact (see module docstring)
        return 0.0
    return _heading(v)


def _opt(value: float | None, name: str, lo: float, hi: float) -> float | None:
    return None if value is None else check_real(value, name, lo, hi)


@dataclass(frozen=True, slots=True)
class HeadingFrame:
    """One heading sentence from a heading-only compass.

    ``heading_deg`` is clockwise from north in [0, 360), relative to
    ``reference``; it is ``None`` only for a ``$PTNTHPR`` whose device nulled
    it (alarm). ``deviation_deg`` / ``variation_deg`` (E positive) come from
    HDG. ``status`` holds the three ``$PTNTHPR`` letters (heading/magnetometer,
    pitch, roll), else None. ``talker`` is the NMEA talker (``"HC"``), ``"TNT"``
    for ``$PTNTHPR`` and ``""`` for OS5000; ``sentence`` is ``"HDT"``,
    ``"HDM"``, ``"HDG"``, ``"HPR"`` or ``"C"``.
    """

    heading_deg: float | None
    reference: HeadingReference
    pitch_deg: float | None = None
    roll_deg: float | None = None
    deviation_deg: float | None = None
    variation_deg: float | None = None
    temperature_c: float | None = None
    talker: str = ""
    sentence: str = ""
    status: tuple[str, str, str] | None = None

    def __post_init__(self) -> None:
        s = self.sentence
        if s not in _SENTENCES:
            raise DecodeError(DropReason.RANGE, f"sentence must be one of {_SENTENCES}, got {s!r}")
        if self.reference not in ("magnetic", "true"):
            raise DecodeError(DropReason.RANGE, f"reference {self.reference!r}")
        if self.heading_deg is None:
            if s != "HPR":
                raise DecodeError(DropReason.FIELDS, f"{s} needs a heading")
        else:
            object.__setattr__(self, "heading_deg", _heading(self.heading_deg))
        checked = {
            "pitch_deg": _opt(self.pitch_deg, "pitch", -90.0, 90.0),
            "roll_deg": _opt(self.roll_deg, "roll", -180.0, 180.0),
            "deviation_deg": _opt(self.deviation_deg, "deviation", -180.0, 180.0),
            "variation_deg": _opt(self.variation_deg, "variation", -180.0, 180.0),
            "temperature_c": _opt(self.temperature_c, "temperature", *_TEMP_RANGE),
        }
        for name, value in checked.items():
            object.__setattr__(self, name, value)
        # Which optional quantities each sentence can carry, so that every frame is encodable.
        carried = {
            "HDT": (),
            "HDM": (),
            "HDG": ("deviation_deg", "variation_deg"),
            "HPR": ("pitch_deg", "roll_deg"),
            "C": ("pitch_deg", "roll_deg", "temperature_c"),
        }[s]
        extra = [n for n, v in checked.items() if v is not None and n not in carried]
        if extra:
            raise DecodeError(DropReason.FIELDS, f"{s} cannot carry {', '.join(extra)}")
        if s == "HDT" and self.reference != "true":
            raise DecodeError(DropReason.RANGE, "HDT is a true heading")
        if s in ("HDM", "HDG") and self.reference != "magnetic":
            raise DecodeError(DropReason.RANGE, f"{s} is a magnetic heading")
        if s == "HPR":
            st = self.status
            if st is None or len(st) != 3 or any(c not in HPR_STATUS for c in st):
                raise DecodeError(DropReason.RANGE, f"HPR status must be 3 of {list(HPR_STATUS)}")
            object.__setattr__(self, "status", tuple(st))
            if self.talker != "TNT":
                raise DecodeError(DropReason.RANGE, "HPR talker is 'TNT'")
        elif self.status is not None:
            raise DecodeError(DropReason.FIELDS, f"{s} has no status letters")
        if s == "C" and self.talker != "":
            raise DecodeError(DropReason.RANGE, "OS5000 sentences have no talker")
        if s in ("HDT", "HDM", "HDG") and not (
            isinstance(self.talker, str) and _TALKER_RE.fullmatch(self.talker)
        ):
            raise DecodeError(DropReason.UNKNOWN_ID, f"bad NMEA talker {self.talker!r}")

    # ---------------------------------------------------------------- constructors

    @classmethod
    def hdt(cls, heading_deg: float, talker: str = "HE") -> HeadingFrame:
        """``$--HDT``: true heading (``HE``: gyro talker by default)."""
        return cls(heading_deg, "true", talker=talker, sentence="HDT")

    @classmethod
    def hdm(cls, heading_deg: float, talker: str = "HC") -> HeadingFrame:
        """``$--HDM``: magnetic heading (``HC``: magnetic compass talker by default)."""
        return cls(heading_deg, "magnetic", talker=talker, sentence="HDM")

    @classmethod
    def hdg(
        cls,
        heading_deg: float,
        deviation_deg: float | None = None,
        variation_deg: float | None = None,
        talker: str = "HC",
    ) -> HeadingFrame:
        """``$--HDG`` for magnetic heading ``heading_deg`` (= sensor + deviation), E positive."""
        return cls(
            heading_deg,
            "magnetic",
            deviation_deg=deviation_deg,
            variation_deg=variation_deg,
            talker=talker,
            sentence="HDG",
        )

    @classmethod
    def hpr(
        cls,
        heading_deg: float | None,
        pitch_deg: float | None,
        roll_deg: float | None,
        status: tuple[str, str, str] = ("N", "N", "N"),
        reference: HeadingReference = "magnetic",
    ) -> HeadingFrame:
        """``$PTNTHPR`` (values None where the device nulls them)."""
        return cls(
            heading_deg,
            reference,
            pitch_deg=pitch_deg,
            roll_deg=roll_deg,
            talker="TNT",
            sentence="HPR",
            status=status,
        )

    @classmethod
    def os5000(
        cls,
        heading_deg: float,
        pitch_deg: float | None = None,
        roll_deg: float | None = None,
        temperature_c: float | None = None,
        reference: HeadingReference = "magnetic",
    ) -> HeadingFrame:
        """OceanServer ``$C<hdg>[P<pitch>][R<roll>][T<temp>]``."""
        return cls(
            heading_deg,
            reference,
            pitch_deg=pitch_deg,
            roll_deg=roll_deg,
            temperature_c=temperature_c,
            sentence="C",
        )

    # ---------------------------------------------------------------- helpers

    @property
    def status_ok(self) -> bool:
        """False when any ``$PTNTHPR`` status letter is not N (normal); True otherwise."""
        return self.status is None or all(c == "N" for c in self.status)

    @property
    def true_heading_deg(self) -> float | None:
        """Heading relative to true north when known (true reference, or magnetic + variation)."""
        if self.heading_deg is None:
            return None
        if self.reference == "true":
            return self.heading_deg
        if self.variation_deg is None:
            return None
        return _wrap(_dec(self.heading_deg) + _dec(self.variation_deg))


def _dec(x: float) -> Decimal:
    # repr() is the shortest decimal that round-trips, i.e. the number as it was written.
    return Decimal(repr(x))


def _wrap(d: Decimal) -> float:
    d = d % 360  # Decimal's % keeps the dividend's sign
    if d < 0:
        d += 360
    return float(d) + 0.0


# --------------------------------------------------------------------------- encode


def _ew(value: float | None) -> list[str]:
    if value is None:
        return ["", ""]
    return [fmt_fixed(abs(value), 1), "W" if value < 0 else "E"]


def _opt_f1(value: float | None) -> str:
    return "" if value is None else fmt_fixed(value, 1)


def _fmt_heading(value: float) -> str:
    # 359.95.. rounds to "360.0"; print the equivalent 0.0 as a firmware should.
    s = fmt_fixed(value, 1)
    return "0.0" if s == "360.0" else s


def _opt_heading(value: float | None) -> str:
    return "" if value is None else _fmt_heading(value)


def encode_body(frame: HeadingFrame) -> str:
    """The sentence body (between ``$`` and ``*``); one decimal everywhere."""
    s = frame.sentence
    if s == "C":
        out = "C" + _fmt_heading(_req(frame.heading_deg))
        for tag, v in (("P", frame.pitch_deg), ("R", frame.roll_deg), ("T", frame.temperature_c)):
            if v is not None:
                out += tag + fmt_fixed(v, 1)
        return out
    if s == "HPR":
        st = frame.status or ("N", "N", "N")
        return ",".join(
            (
                "PTNTHPR",
                _opt_heading(frame.heading_deg),
                st[0],
                _opt_f1(frame.pitch_deg),
                st[1],
                _opt_f1(frame.roll_deg),
                st[2],
            )
        )
    heading = _req(frame.heading_deg)
    if s == "HDT":
        return f"{frame.talker}HDT,{_fmt_heading(heading)},T"
    if s == "HDM":
        return f"{frame.talker}HDM,{_fmt_heading(heading)},M"
    # HDG carries the sensor heading: magnetic heading minus deviation.
    sensor = _dec(heading)
    if frame.deviation_deg is not None:
        sensor -= _dec(frame.deviation_deg)
    sensor_q = Decimal(repr(_wrap(sensor))).quantize(_TENTH, rounding=ROUND_HALF_EVEN)
    sensor_txt = "0.0" if sensor_q >= 360 else f"{sensor_q:.1f}"
    return ",".join(
        [f"{frame.talker}HDG", sensor_txt, *_ew(frame.deviation_deg), *_ew(frame.variation_deg)]
    )


def _req(value: float | None) -> float:
    if value is None:  # only HPR may lack a heading; __post_init__ guarantees it
        raise ValueError("frame has no heading")
    return value


def encode(frame: HeadingFrame) -> bytes:
    """The full line ``$<body>*<CS>\\r\\n`` for ``frame``."""
    return render_line(encode_body(frame))


# --------------------------------------------------------------------------- decode


def _signed(value: str, direction: str, name: str) -> float | None:
    if value == "" and direction == "":
        return None
    if value == "" or direction == "":
        raise DecodeError(DropReason.FIELDS, f"{name} needs both a value and E/W")
    if direction not in ("E", "W"):
        raise DecodeError(DropReason.RANGE, f"{name} direction {direction!r} is not E or W")
    v = parse_decimal(value, name)
    if v < 0:
        raise DecodeError(DropReason.RANGE, f"{name} magnitude {value} is negative")
    return -v if direction == "W" else v


def _expect(fields: list[str], n: int, what: str) -> None:
    if len(fields) != n:
        raise DecodeError(DropReason.FIELDS, f"{what} needs {n} fields, got {len(fields)}")


def _decode_nmea(body: str, reference: HeadingReference) -> HeadingFrame:
    ident, _, rest = body.partition(",")
    fields = rest.split(",") if "," in body else []
    if ident == "PTNTHPR":
        return _decode_hpr(fields, reference)
    talker, kind = ident[:2], ident[2:]
    if len(ident) != 5 or not _TALKER_RE.fullmatch(talker) or kind not in ("HDT", "HDM", "HDG"):
        raise DecodeError(DropReason.UNKNOWN_ID, f"{ident!r} is not HDT/HDM/HDG/PTNTHPR")
    if kind in ("HDT", "HDM"):
        _expect(fields, 2, kind)
        if fields[0] == "":
            raise DecodeError(DropReason.FIELDS, f"{kind} without a heading")
        marker = "T" if kind == "HDT" else "M"
        if fields[1] != marker:
            raise DecodeError(DropReason.RANGE, f"{kind} reference {fields[1]!r} is not {marker}")
        heading = _parse_heading(fields[0])
        return HeadingFrame(
            heading, "true" if kind == "HDT" else "magnetic", talker=talker, sentence=kind
        )
    _expect(fields, 5, "HDG")
    if fields[0] == "":
        raise DecodeError(DropReason.FIELDS, "HDG without a heading")
    sensor = parse_decimal(fields[0], "heading")
    check_real(sensor, "heading", 0.0, 360.0)
    deviation = _signed(fields[1], fields[2], "deviation")
    variation = _signed(fields[3], fields[4], "variation")
    # Sum in decimal so that e.g. 0.2 + 0.1 is exactly 0.3, as the sentence meant it.
    magnetic = Decimal(fields[0])
    if deviation is not None:
        magnetic += Decimal(fields[1]) * (-1 if fields[2] == "W" else 1)
    return HeadingFrame(
        _wrap(magnetic),
        "magnetic",
        deviation_deg=deviation,
        variation_deg=variation,
        talker=talker,
        sentence="HDG",
    )


def _decode_hpr(fields: list[str], reference: HeadingReference) -> HeadingFrame:
    _expect(fields, 6, "PTNTHPR")
    hdg, hs, pitch, ps, roll, rs = fields
    for letter in (hs, ps, rs):
        if letter == "":
            raise DecodeError(DropReason.FIELDS, "PTNTHPR status letter missing")
        if letter not in HPR_STATUS:
            raise DecodeError(DropReason.RANGE, f"PTNTHPR status {letter!r} unknown")
    return HeadingFrame.hpr(
        None if hdg == "" else _parse_heading(hdg),
        None if pitch == "" else parse_decimal(pitch, "pitch"),
        None if roll == "" else parse_decimal(roll, "roll"),
        status=(hs, ps, rs),
        reference=reference,
    )


def _decode_os5000(body: str, reference: HeadingReference) -> HeadingFrame:
    tags = [(m.group(1), m.group(2)) for m in _OS5000_TAG_RE.finditer(body)]
    if not body.startswith("C") or not tags or tags[0][0] != "C":
        raise DecodeError(DropReason.UNKNOWN_ID, f"{body[:8]!r} is not an OS5000 $C sentence")
    values: dict[str, float] = {}
    for tag, text in tags:
        if tag not in ("C", "P", "R", "T") and tag not in _OS5000_IGNORED:
            raise DecodeError(DropReason.FIELDS, f"unknown OS5000 field {tag!r}")
        if tag in values:
            raise DecodeError(DropReason.FIELDS, f"OS5000 field {tag!r} repeated")
        if text == "":
            raise DecodeError(DropReason.FIELDS, f"OS5000 field {tag!r} has no value")
        values[tag] = _parse_heading(text) if tag == "C" else parse_decimal(text, tag)
    return HeadingFrame.os5000(
        values["C"], values.get("P"), values.get("R"), values.get("T"), reference=reference
    )


def decode_body(
    body: str, protocol: HeadingProtocol = "nmea", reference: HeadingReference = "magnetic"
) -> HeadingFrame:
    """Decode one checksum-verified body; DecodeError (with ``.reason``) if invalid.

    ``reference`` applies to the sentences that do not state it (``$PTNTHPR``, OS5000).
    """
    if protocol == "nmea":
        return _decode_nmea(body, reference)
    return _decode_os5000(body, reference)


class HeadingDecoder:
    """Sans-I/O decoder for a heading-only compass: ``feed(bytes) -> list[HeadingFrame]``.

    Same shape as :class:`bridge.protocol.gmr.GmrDecoder` (``counters.dropped``
    with the same reasons). ``reference`` says what ``$PTNTHPR`` / OS5000
    headings are relative to ("true" when a declination is set in the device).
    """

    __slots__ = ("_protocol", "_reference", "_splitter", "counters", "last_error")

    def __init__(
        self, protocol: HeadingProtocol = "nmea", reference: HeadingReference = "magnetic"
    ) -> None:
        if protocol not in ("nmea", "os5000"):
            raise ValueError(f"protocol must be 'nmea' or 'os5000', got {protocol!r}")
        if reference not in ("magnetic", "true"):
            raise ValueError(f"reference must be 'magnetic' or 'true', got {reference!r}")
        self._protocol: HeadingProtocol = protocol
        self._reference: HeadingReference = reference
        self.counters = CodecCounters()
        self._splitter = LineSplitter(self.counters.dropped)
        #: The last sentence-level rejection (for logs), None until one happens.
        self.last_error: DecodeError | None = None

    @property
    def protocol(self) -> HeadingProtocol:
        """``"nmea"`` or ``"os5000"``."""
        return self._protocol

    def reset(self) -> None:
        """Forget a partial line (counters are kept)."""
        self._splitter.reset()

    def feed(self, data: bytes) -> list[HeadingFrame]:
        """Consume a chunk of bytes; return the frames it completed, in order."""
        self.counters.bytes_in += len(data)
        frames: list[HeadingFrame] = []
        for body in self._splitter.feed(data):
            try:
                frames.append(decode_body(body, self._protocol, self._reference))
            except DecodeError as exc:
                self.counters.dropped.add(exc.reason)
                self.last_error = exc
        self.counters.frames += len(frames)
        return frames
