"""Codec for the GMR compass sentences (datasheet firmware 2.x): pure, no I/O.

Device -> host: ``$PGMRA`` (attitude + raw), ``$PGMRV`` (version), ``$PGMRC``
(calibration progress), ``$PGMRP`` (flash parameters), ``$PGMRK`` (ack).
Host -> device: ``$PGMRQ`` (command).

The frames and their encoding are :mod:`bridge.protocol.gmr_frames` (re-exported
here: import everything from this module); this module decodes. Every frame
validates itself on construction with the *same* rules the decoder applies --
:class:`AttitudeFrame` is the one validation of a ``$PGMRA`` frame, whoever builds
it (the decoder, the simulated firmware, a benchmark) -- so any frame that can be
built can be encoded, and ``decode(encode(f)) == f`` for every frame whose numbers
already sit on the datasheet's grid. The datasheet readings taken (tolerated
``360.0``, plain decimals, lower-case hex, ranges) are listed in
:mod:`bridge.protocol.gmr_frames`.

Decoding a read: whole ``$PGMRA`` lines at its start (what nearly every read holds at
100 Hz) are matched with one pattern -- the framing and the same field rules the body
decoder uses -- and built through the same code; everything else goes through the
byte-by-byte :class:`~bridge.protocol.framing.LineSplitter` and :func:`decode_body`,
which count what they drop. Both routes give the same frames and counters
(tests/test_protocol_pgmra.py); docs/performance.md has the measured reason for the first.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Literal

from bridge.protocol.framing import (
    DECIMAL_RE,
    INT_RE,
    MAX_BODY_BYTES,
    CodecCounters,
    DecodeError,
    DropReason,
    LineSplitter,
    checksum,
    parse_decimal,
    parse_int,
)
from bridge.protocol.gmr_frames import (
    _ADC_NAMES,
    _HEX2_RE,
    _PARAM_NAMES,
    ACC_OFFSET_RANGE,
    ADC_RANGE,
    FLAGS_MASK,
    GAIN_RANGE,
    OFFSET_RANGE,
    PAR_SET_GAIN_RANGE,
    RATES_HZ,
    SEQ_MAX,
    AckFrame,
    AckReason,
    AttitudeFrame,
    CalProgressFrame,
    CommandFrame,
    Flags,
    GmrFrame,
    ParamsFrame,
    VersionFrame,
    encode,
    encode_body,
)

__all__ = [
    "ACC_OFFSET_RANGE",
    "ADC_RANGE",
    "FLAGS_MASK",
    "GAIN_RANGE",
    "OFFSET_RANGE",
    "PAR_SET_GAIN_RANGE",
    "RATES_HZ",
    "SEQ_MAX",
    "AckFrame",
    "AckReason",
    "AttitudeFrame",
    "CalProgressFrame",
    "CommandFrame",
    "DecodeError",
    "Direction",
    "Flags",
    "GmrDecoder",
    "GmrFrame",
    "ParamsFrame",
    "VersionFrame",
    "decode_body",
    "encode",
    "encode_body",
]


def _expect_fields(fields: list[str], n: int, sentence: str) -> None:
    if len(fields) != n:
        raise DecodeError(DropReason.FIELDS, f"{sentence} needs {n} fields, got {len(fields)}")


# --------------------------------------------------------------------------- decode


# The eleven $PGMRA fields in one pattern, composed of the field rules every sentence uses
# (INT_RE, DECIMAL_RE, two hex digits): one match per frame instead of eleven calls. When it
# fails, the per-field parsers say which field and why.
_ATTITUDE_FIELDS_PATTERN = ",".join(
    [
        f"({INT_RE.pattern})",
        *[f"({DECIMAL_RE.pattern})"] * 3,
        *[f"({INT_RE.pattern})"] * 6,
        f"({_HEX2_RE.pattern})",
    ]
)
_ATTITUDE_FIELDS = re.compile(_ATTITUDE_FIELDS_PATTERN)
# A whole $PGMRA line as the splitter would hand it over: the same fields between "$PGMRA,"
# and "*HH" plus CRLF or LF. Groups: 1 the body, 2-12 the fields, 13 the checksum.
_ATTITUDE_LINE = re.compile(
    rb"\$(PGMRA," + _ATTITUDE_FIELDS_PATTERN.encode("ascii") + rb")\*([0-9A-Fa-f]{2})\r?\n"
)
_LINE_FIELDS = tuple(range(2, 13))


def _attitude_field_error(f: list[str]) -> DecodeError:
    for text, name in zip(f, ("seq", "heading", "pitch", "roll", *_ADC_NAMES), strict=False):
        (parse_decimal if name in ("heading", "pitch", "roll") else parse_int)(text, name)
    return DecodeError(DropReason.NUMBER, f"flags {f[10]!r} are not two hex digits")


def _attitude(*f: str | bytes) -> AttitudeFrame:
    """The frame of the eleven matched field texts; DecodeError when a value is out of range."""
    heading = float(f[1])
    if heading == 360.0:  # tolerated rounding artefact, see gmr_frames' docstring
        heading = 0.0
    return AttitudeFrame(
        int(f[0]), heading, float(f[2]), float(f[3]),
        int(f[4]), int(f[5]), int(f[6]), int(f[7]), int(f[8]), int(f[9]), int(f[10], 16),
    )  # fmt: skip


def _decode_attitude(f: list[str]) -> AttitudeFrame:
    _expect_fields(f, 11, "PGMRA")
    m = _ATTITUDE_FIELDS.fullmatch(",".join(f))
    if m is None:
        raise _attitude_field_error(f)
    return _attitude(*m.groups())


def _leading_attitude_lines(data: bytes, frames: list[GmrFrame]) -> int:
    """Decode the whole, valid ``$PGMRA`` lines that open ``data``; the offset after them.

    A read at 100 Hz is nearly always one such line. Taking it with one match (framing
    and field syntax together) and building it through the same :func:`_attitude`
    spares the byte-by-byte splitter; the first line that does not match, fails its
    checksum, is too long or out of range stops this, and the splitter and
    :func:`decode_body` take it from there -- they count and drop what is wrong.
    """
    pos = 0
    end = len(data)
    while pos < end and (m := _ATTITUDE_LINE.match(data, pos)):
        body = m.group(1)
        if len(body) > MAX_BODY_BYTES or checksum(body) != int(m.group(13), 16):
            break
        try:
            frames.append(_attitude(*m.group(*_LINE_FIELDS)))
        except DecodeError:
            break
        pos = m.end()
    return pos


def _decode_version(f: list[str]) -> VersionFrame:
    _expect_fields(f, 3, "PGMRV")
    return VersionFrame(*f)


def _decode_calprogress(f: list[str]) -> CalProgressFrame:
    _expect_fields(f, 7, "PGMRC")
    names = ("samples", "xmin", "xmax", "ymin", "ymax", "zmin", "zmax")
    return CalProgressFrame(*(parse_int(t, n) for t, n in zip(f, names, strict=True)))


def _decode_params(f: list[str]) -> ParamsFrame:
    _expect_fields(f, 9, "PGMRP")
    return ParamsFrame(*(parse_decimal(t, n) for t, n in zip(f, _PARAM_NAMES, strict=True)))


def _decode_ack(f: list[str]) -> AckFrame:
    if len(f) < 2:
        raise DecodeError(DropReason.FIELDS, "PGMRK needs a command and OK/ERR")
    status = f[1]
    if status not in ("OK", "ERR"):
        raise DecodeError(DropReason.RANGE, f"PGMRK status {status!r} is neither OK nor ERR")
    return AckFrame(f[0], status == "OK", tuple(f[2:]))


def _decode_command(f: list[str]) -> CommandFrame:
    if not f or not f[0]:
        raise DecodeError(DropReason.FIELDS, "PGMRQ without a command")
    return CommandFrame(f[0], tuple(f[1:]))


_HOST_PARSERS: dict[str, Callable[[list[str]], GmrFrame]] = {
    "PGMRA": _decode_attitude,
    "PGMRV": _decode_version,
    "PGMRC": _decode_calprogress,
    "PGMRP": _decode_params,
    "PGMRK": _decode_ack,
}
_DEVICE_PARSERS: dict[str, Callable[[list[str]], GmrFrame]] = {"PGMRQ": _decode_command}

Direction = Literal["host", "device"]


def decode_body(body: str, direction: Direction = "host") -> GmrFrame:
    """Decode one checksum-verified sentence body; DecodeError (with ``.reason``) if invalid.

    ``direction="host"`` accepts device->host sentences, ``"device"`` only ``$PGMRQ``.
    """
    ident, _, rest = body.partition(",")
    parsers = _HOST_PARSERS if direction == "host" else _DEVICE_PARSERS
    parser = parsers.get(ident)
    if parser is None:
        raise DecodeError(DropReason.UNKNOWN_ID, f"{ident!r} not accepted by a {direction} decoder")
    # "$PGMRQ" with no comma at all has no fields; "$PGMRQ," has one empty field.
    fields = rest.split(",") if "," in body else []
    return parser(fields)


# --------------------------------------------------------------------------- decoder


class GmrDecoder:
    """Sans-I/O decoder: ``feed(bytes) -> list[frame]``; drops are counted in ``counters``.

    ``direction="host"``: the decoder runs in the host and accepts device->host
    sentences; ``"device"``: it runs in the (simulated) device and accepts
    ``$PGMRQ`` only. Anything else is ``unknown_id``.
    """

    __slots__ = ("_direction", "_splitter", "counters", "last_error")

    def __init__(self, direction: Direction = "host") -> None:
        if direction not in ("host", "device"):
            raise ValueError(f"direction must be 'host' or 'device', got {direction!r}")
        self._direction: Direction = direction
        self.counters = CodecCounters()
        self._splitter = LineSplitter(self.counters.dropped)
        #: The last sentence-level rejection (for logs), None until one happens.
        self.last_error: DecodeError | None = None

    @property
    def direction(self) -> Direction:
        """``"host"`` or ``"device"``."""
        return self._direction

    def reset(self) -> None:
        """Forget a partial line (counters are kept), e.g. after the port was reopened."""
        self._splitter.reset()

    def feed(self, data: bytes) -> list[GmrFrame]:
        """Consume a chunk of bytes; return the frames it completed, in order."""
        self.counters.bytes_in += len(data)
        frames: list[GmrFrame] = []
        splitter = self._splitter
        if self._direction == "host" and not splitter.in_line:
            done = _leading_attitude_lines(data, frames)
            if done:
                splitter.reset()  # between lines, where the splitter would be after them
                if done == len(data):
                    self.counters.frames += len(frames)
                    return frames
                data = data[done:]
        for body in splitter.feed(data):
            try:
                frames.append(decode_body(body, self._direction))
            except DecodeError as exc:
                self.counters.dropped.add(exc.reason)
                self.last_error = exc
        self.counters.frames += len(frames)
        return frames
