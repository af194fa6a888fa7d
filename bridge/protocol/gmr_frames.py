"""The GMR compass sentences (datasheet firmware 2.x) as validated frames, and their encoding.

The public names are re-exported by :mod:`bridge.protocol.gmr` (the codec); import them
from there. The decoder lives there too.

Device -> host: ``$PGMRA`` (attitude + raw), ``$PGMRV`` (version), ``$PGMRC``
(calibration progress), ``$PGMRP`` (flash parameters), ``$PGMRK`` (ack).
Host -> device: ``$PGMRQ`` (command).

Every frame is a frozen, slotted dataclass that validates itself on
construction with the *same* rules the decoder applies, so any frame that can
be built can be encoded, and ``decode(encode(f)) == f`` for every frame whose
numbers already sit on the datasheet's grid (angles and offsets to 0.1, gains
to 0.0001). Constructors raise :class:`DecodeError` (a ValueError) carrying the
drop reason the decoder would count for the same content.

Readings of the datasheet taken here:

* ``hdg`` "0.0-359.9": the decoder tolerates exactly ``360.0`` and reports it
  as 0.0 -- it is what a firmware rounding 359.95..359.99 to one decimal
  prints, and dropping it would blank the heading every time the vehicle
  points north. :func:`encode` never emits it (it wraps to ``0.0``).
* Numbers are accepted as plain decimals (``-?digits[.digits]``) with any
  number of decimals; ``+1``, ``1e3``, ``.5``, ``nan``, ``inf`` are ``number``.
  Encoding uses the datasheet's decimals. Flags accept lower-case hex.
* ``$PGMRP`` ranges: offsets 0-4095 (so the factory Gzoff = 2949.5 is
  legitimate) and gains 0.0977-10.2375, the span of what the flash can
  legitimately hold: PAR,SET's 0.1-10 *plus* what MAGCAL,END can write
  (span ratios with every span in 400..4095 counts). A stricter 0.1-10 check
  would lock the host out of reading a unit after an extreme calibration.
* ``$PGMRC`` requires min <= max per axis (an untracked axis reports 0,0).
* ``$PGMRK,...,OK`` is accepted only for commands that acknowledge OK with
  the datasheet's result fields (RATE 1, MAGCAL 0 or 6, ACCCAL 3, PAR/RESET 0);
  ``ERR`` is accepted for any command word (UNKNOWN echoes an unknown command)
  with exactly one of the six reasons.
* ``$PGMRQ`` decoding (device side) only requires a non-empty command word:
  the device must *answer* malformed commands (ERR,UNKNOWN / ERR,ARGS), so it
  has to see them; :meth:`CommandFrame.error` gives that answer.
"""

from __future__ import annotations

import numbers
import re
from dataclasses import dataclass
from enum import IntFlag, StrEnum
from typing import Literal, TypeAlias

from bridge.protocol.framing import (
    INT_RE,
    MAX_BODY_BYTES,
    DecodeError,
    DropReason,
    check_int,
    check_real,
    check_token,
    fmt_fixed,
    parse_decimal,
    parse_int,
    render_line,
)


class Flags(IntFlag):
    """``$PGMRA`` flag bits (bits 5-7 are always zero)."""

    CAL = 0x01  #: magnetometer calibration mode active
    MAGOK = 0x02  #: flash holds a magnetometer calibration
    ACCOK = 0x04  #: flash holds an accelerometer level reference
    SAT = 0x08  #: a channel of this frame is saturated
    FLASHERR = 0x10  #: the last flash write failed verification


class AckReason(StrEnum):
    """``$PGMRK,<command>,ERR,<reason>`` reasons."""

    UNKNOWN = "UNKNOWN"  #: no such command
    ARGS = "ARGS"  #: bad arguments
    STATE = "STATE"  #: not allowed in the current mode
    RANGE = "RANGE"  #: calibration saw too little rotation
    MOTION = "MOTION"  #: device not still
    FLASH = "FLASH"  #: flash write failed


FLAGS_MASK = 0x1F
RATES_HZ: tuple[int, ...] = (1, 2, 5, 10, 20, 50, 100)
SEQ_MAX = 65535
#: PGMRC sample counter bound (a 32-bit firmware counter; keeps the line within 96 bytes).
SAMPLES_MAX = 2**32 - 1
ADC_MAX = 4095  #: a raw channel is 12 bits; 0 and ADC_MAX are its rails
ADC_RANGE = (0, ADC_MAX)
OFFSET_RANGE = (0.0, 4095.0)  #: Xoff/Yoff/Zoff, counts
ACC_OFFSET_RANGE = (0.0, 4095.0)  #: Gxoff/Gyoff/Gzoff, counts
PAR_SET_GAIN_RANGE = (0.1, 10.0)  #: what PAR,SET accepts
#: What the flash can hold: PAR,SET's range plus MAGCAL,END ratios of spans in 400..4095.
GAIN_RANGE = (400 / 4095, 4095 / 400)

_HEX2_RE = re.compile(r"[0-9A-Fa-f]{2}")
_ADC_NAMES = ("mx", "my", "mz", "ax", "ay", "az")
#: Flags by value: a tuple index per frame instead of the enum's call machinery.
_FLAGS_BY_VALUE: tuple[Flags, ...] = tuple(Flags(i) for i in range(FLAGS_MASK + 1))
_SAT = int(Flags.SAT)


def _f1(x: float) -> str:
    return fmt_fixed(x, 1)


def _f4(x: float) -> str:
    return fmt_fixed(x, 4)


#: Frozen dataclasses normalise their fields in __post_init__ (np.int64 -> int, int -> float).
_set = object.__setattr__


# --------------------------------------------------------------------------- frames


@dataclass(frozen=True, slots=True, init=False)
class AttitudeFrame:
    """``$PGMRA``: on-board attitude (degrees) and raw ADC counts, streamed at the output rate.

    ``heading`` is magnetic, clockwise from north, in [0, 360); ``pitch`` nose
    up positive in [-90, 90]; ``roll`` right wing down positive in [-180, 180].
    """

    seq: int
    heading: float
    pitch: float
    roll: float
    mx: int
    my: int
    mz: int
    ax: int
    ay: int
    az: int
    flags: Flags

    def __init__(
        self,
        seq: int,
        heading: float,
        pitch: float,
        roll: float,
        mx: int,
        my: int,
        mz: int,
        ax: int,
        ay: int,
        az: int,
        flags: Flags | int,
    ) -> None:
        # The one validation of a $PGMRA frame, whoever builds it. A decoded frame comes as
        # plain ints and floats within range: that case is one test and eleven stores (it
        # runs for every frame, up to 100 Hz). The benchmarks and the tests build theirs
        # with ``Flags`` (an int subclass: its comparisons and its index into
        # _FLAGS_BY_VALUE are the int's), ~70 000 frames a test tier: a Flags takes that
        # case too -- the frame check_int's ``operator.index`` would give, at half the cost.
        # Anything else (numpy numbers, a value out of range) goes through check_int /
        # check_real, which normalise it or raise with the drop reason the decoder counts.
        if (
            type(seq) is type(mx) is type(my) is type(mz) is int
            and type(ax) is type(ay) is type(az) is int
            and (type(flags) is int or type(flags) is Flags)
            and type(heading) is type(pitch) is type(roll) is float
            and 0 <= seq <= SEQ_MAX
            and 0 <= mx <= ADC_MAX and 0 <= my <= ADC_MAX and 0 <= mz <= ADC_MAX
            and 0 <= ax <= ADC_MAX and 0 <= ay <= ADC_MAX and 0 <= az <= ADC_MAX
            and 0.0 <= heading < 360.0 and -90.0 <= pitch <= 90.0 and -180.0 <= roll <= 180.0
            and 0 <= flags <= FLAGS_MASK
        ):  # fmt: skip
            heading += 0.0  # -0.0 -> 0.0, as check_real does
            pitch += 0.0
            roll += 0.0
        else:
            seq = check_int(seq, "seq", 0, SEQ_MAX)
            heading = check_real(heading, "heading", 0.0, 360.0, hi_open=True)
            pitch = check_real(pitch, "pitch", -90.0, 90.0)
            roll = check_real(roll, "roll", -180.0, 180.0)
            mx, my, mz, ax, ay, az = (
                check_int(v, n, 0, ADC_MAX)
                for v, n in zip((mx, my, mz, ax, ay, az), _ADC_NAMES, strict=True)
            )
            flags = check_int(flags, "flags", 0, 0xFF)
            if flags & ~FLAGS_MASK:
                raise DecodeError(DropReason.RANGE, f"flags 0x{flags:02X} has bits 5-7 set")
        _set(self, "seq", seq)
        _set(self, "heading", heading)
        _set(self, "pitch", pitch)
        _set(self, "roll", roll)
        _set(self, "mx", mx)
        _set(self, "my", my)
        _set(self, "mz", mz)
        _set(self, "ax", ax)
        _set(self, "ay", ay)
        _set(self, "az", az)
        _set(self, "flags", _FLAGS_BY_VALUE[flags])

    @property
    def sat_flag(self) -> bool:
        """The device's SAT flag: a channel at an ADC rail (the flags read as an int:
        ``Flags``'s own ``&`` is the enum module's Python code, and this is read every frame)."""
        return (int(self.flags) & _SAT) != 0

    @property
    def mag_counts(self) -> tuple[int, int, int]:
        """(mx, my, mz) raw magnetometer counts."""
        return (self.mx, self.my, self.mz)

    @property
    def acc_counts(self) -> tuple[int, int, int]:
        """(ax, ay, az) raw accelerometer counts."""
        return (self.ax, self.ay, self.az)


@dataclass(frozen=True, slots=True)
class VersionFrame:
    """``$PGMRV``: firmware version, hardware revision, serial number (at power-up and on VER)."""

    firmware: str
    hardware: str
    serial: str

    def __post_init__(self) -> None:
        for name in ("firmware", "hardware", "serial"):
            check_token(getattr(self, name), name)
        _check_length(self)


@dataclass(frozen=True, slots=True)
class CalProgressFrame:
    """``$PGMRC``: min/max counts tracked so far in magnetometer calibration (1 Hz).

    An axis not yet tracked reports ``0, 0``.
    """

    samples: int
    xmin: int
    xmax: int
    ymin: int
    ymax: int
    zmin: int
    zmax: int

    def __post_init__(self) -> None:
        _set(self, "samples", check_int(self.samples, "samples", 0, SAMPLES_MAX))
        for axis in "xyz":
            lo = check_int(getattr(self, axis + "min"), axis + "min", *ADC_RANGE)
            hi = check_int(getattr(self, axis + "max"), axis + "max", *ADC_RANGE)
            if lo > hi:
                raise DecodeError(DropReason.RANGE, f"{axis}min={lo} > {axis}max={hi}")
            _set(self, axis + "min", lo)
            _set(self, axis + "max", hi)

    def span(self, axis: Literal["x", "y", "z"]) -> int:
        """max - min counts seen on ``axis`` (MAGCAL,END needs >= 400 on every axis)."""
        lo: int = getattr(self, axis + "min")
        hi: int = getattr(self, axis + "max")
        return hi - lo


@dataclass(frozen=True, slots=True)
class ParamsFrame:
    """``$PGMRP``: the nine flash parameters (reply to PAR,GET; also PAR,SET's arguments).

    Offsets in counts (one decimal), gains dimensionless (four decimals).
    """

    xoff: float
    yoff: float
    zoff: float
    kx: float
    ky: float
    kz: float
    gxoff: float
    gyoff: float
    gzoff: float

    def __post_init__(self) -> None:
        for name in ("xoff", "yoff", "zoff"):
            _set(self, name, check_real(getattr(self, name), name, *OFFSET_RANGE))
        for name in ("kx", "ky", "kz"):
            _set(self, name, check_real(getattr(self, name), name, *GAIN_RANGE))
        for name in ("gxoff", "gyoff", "gzoff"):
            _set(self, name, check_real(getattr(self, name), name, *ACC_OFFSET_RANGE))

    @classmethod
    def factory(cls) -> ParamsFrame:
        """The datasheet's factory flash content."""
        return cls(2458.0, 2458.0, 2458.0, 1.0, 1.0, 1.0, 2458.0, 2458.0, 2949.5)

    def values(self) -> tuple[float, ...]:
        """The nine values in sentence order."""
        return tuple(getattr(self, n) for n in _PARAM_NAMES)

    def fields(self) -> tuple[str, ...]:
        """The nine values formatted as the datasheet says (offsets .1f, gains .4f)."""
        return tuple(
            _f4(v) if n.startswith("k") else _f1(v)
            for n, v in zip(_PARAM_NAMES, self.values(), strict=True)
        )


_PARAM_NAMES = ("xoff", "yoff", "zoff", "kx", "ky", "kz", "gxoff", "gyoff", "gzoff")


# Result fields of "$PGMRK,<command>,OK,...": allowed field counts per command word.
_OK_RESULT_COUNTS: dict[str, tuple[int, ...]] = {
    "RATE": (1,),
    "MAGCAL": (0, 6),
    "ACCCAL": (3,),
    "PAR": (0,),
    "RESET": (0,),
}


def _check_ok_results(command: str, fields: tuple[str, ...]) -> None:
    counts = _OK_RESULT_COUNTS.get(command)
    if counts is None:
        raise DecodeError(DropReason.RANGE, f"{command!r} never acknowledges OK")
    if len(fields) not in counts:
        raise DecodeError(
            DropReason.FIELDS, f"{command},OK needs {counts} result fields, got {len(fields)}"
        )
    if command == "RATE":
        hz = parse_int(fields[0], "rate")
        if hz not in RATES_HZ:
            raise DecodeError(DropReason.RANGE, f"rate {hz} Hz not one of {RATES_HZ}")
    elif command == "MAGCAL" and fields:
        for i, text in enumerate(fields):
            name = ("xoff", "yoff", "zoff", "kx", "ky", "kz")[i]
            rng = GAIN_RANGE if i >= 3 else OFFSET_RANGE
            check_real(parse_decimal(text, name), name, *rng)
    elif command == "ACCCAL":
        for name, text in zip(("gxoff", "gyoff", "gzoff"), fields, strict=True):
            check_real(parse_decimal(text, name), name, *ACC_OFFSET_RANGE)


@dataclass(frozen=True, slots=True)
class AckFrame:
    """``$PGMRK``: command acknowledgement.

    ``fields`` holds the OK result fields as sent, or ``(reason,)`` on ERR.
    Build them with :meth:`success`, :meth:`failure`, :meth:`rate_ok`,
    :meth:`magcal_ok`, :meth:`acccal_ok`.
    """

    command: str
    ok: bool
    fields: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        check_token(self.command, "command")
        if not isinstance(self.ok, bool):
            raise DecodeError(DropReason.RANGE, f"ok must be a bool, got {self.ok!r}")
        fields = tuple(self.fields)
        for f in fields:
            check_token(f, "result field")
        if self.ok:
            _check_ok_results(self.command, fields)
        else:
            if len(fields) != 1:
                raise DecodeError(DropReason.FIELDS, f"ERR needs one reason, got {fields!r}")
            if fields[0] not in AckReason.__members__:
                raise DecodeError(DropReason.RANGE, f"unknown ERR reason {fields[0]!r}")
        _set(self, "fields", fields)
        _check_length(self)

    @classmethod
    def success(cls, command: str, fields: tuple[str, ...] = ()) -> AckFrame:
        """``$PGMRK,<command>,OK[,<fields>]``."""
        return cls(command, True, fields)

    @classmethod
    def failure(cls, command: str, reason: AckReason | str) -> AckFrame:
        """``$PGMRK,<command>,ERR,<reason>``."""
        return cls(command, False, (AckReason(reason).value,))

    @classmethod
    def rate_ok(cls, hz: int) -> AckFrame:
        """``$PGMRK,RATE,OK,<hz>``."""
        return cls("RATE", True, (str(check_int(hz, "rate", 1, 100)),))

    @classmethod
    def magcal_ok(
        cls, xoff: float, yoff: float, zoff: float, kx: float, ky: float, kz: float
    ) -> AckFrame:
        """``$PGMRK,MAGCAL,OK,<xoff>,<yoff>,<zoff>,<kx>,<ky>,<kz>`` (the MAGCAL,END answer)."""
        offs = [_f1(check_real(v, "offset", *OFFSET_RANGE)) for v in (xoff, yoff, zoff)]
        gains = [_f4(check_real(v, "gain", *GAIN_RANGE)) for v in (kx, ky, kz)]
        return cls("MAGCAL", True, (*offs, *gains))

    @classmethod
    def acccal_ok(cls, gxoff: float, gyoff: float, gzoff: float) -> AckFrame:
        """``$PGMRK,ACCCAL,OK,<gxoff>,<gyoff>,<gzoff>``."""
        return cls(
            "ACCCAL",
            True,
            tuple(
                _f1(check_real(v, "level offset", *ACC_OFFSET_RANGE)) for v in (gxoff, gyoff, gzoff)
            ),
        )

    @property
    def reason(self) -> AckReason | None:
        """The ERR reason, or None when ``ok``."""
        return None if self.ok else AckReason(self.fields[0])

    @property
    def values(self) -> tuple[float, ...]:
        """The OK result fields as numbers (empty on ERR or when there are none)."""
        return tuple(float(f) for f in self.fields) if self.ok else ()

    @property
    def rate_hz(self) -> int | None:
        """The rate confirmed by ``RATE,OK``, else None."""
        return int(self.fields[0]) if self.ok and self.command == "RATE" else None


_COMMAND_WORDS = ("VER", "RATE", "MAGCAL", "ACCCAL", "PAR", "RESET")


@dataclass(frozen=True, slots=True)
class CommandFrame:
    """``$PGMRQ,<command>[,<arg>...]``: a host command.

    The dataclass accepts any well-formed command (the device must be able to
    receive a bad one to answer ERR); the classmethod constructors build only
    valid ones. :meth:`error` says what the device answers it.
    """

    command: str
    args: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        check_token(self.command, "command")
        args = tuple(self.args)
        for a in args:
            check_token(a, "argument", empty_ok=True)
        _set(self, "args", args)
        _check_length(self)

    @classmethod
    def ver(cls) -> CommandFrame:
        """``VER``: answered by ``$PGMRV``."""
        return cls("VER")

    @classmethod
    def rate(cls, hz: int) -> CommandFrame:
        """``RATE,<hz>`` with hz one of 1, 2, 5, 10, 20, 50, 100 (ValueError otherwise)."""
        if isinstance(hz, bool) or not isinstance(hz, numbers.Integral) or hz not in RATES_HZ:
            raise ValueError(f"rate must be one of {RATES_HZ} Hz, got {hz!r}")
        return cls("RATE", (str(int(hz)),))

    @classmethod
    def magcal_start(cls) -> CommandFrame:
        """``MAGCAL,START``: enter magnetometer calibration mode."""
        return cls("MAGCAL", ("START",))

    @classmethod
    def magcal_end(cls) -> CommandFrame:
        """``MAGCAL,END``: compute, write flash, leave calibration mode."""
        return cls("MAGCAL", ("END",))

    @classmethod
    def magcal_abort(cls) -> CommandFrame:
        """``MAGCAL,ABORT``: leave calibration mode, flash unchanged."""
        return cls("MAGCAL", ("ABORT",))

    @classmethod
    def acccal(cls) -> CommandFrame:
        """``ACCCAL``: average 1 s of accelerometer samples as the level reference."""
        return cls("ACCCAL")

    @classmethod
    def par_get(cls) -> CommandFrame:
        """``PAR,GET``: answered by ``$PGMRP``."""
        return cls("PAR", ("GET",))

    @classmethod
    def par_set(cls, params: ParamsFrame) -> CommandFrame:
        """``PAR,SET`` with the nine values; gains must lie in 0.1-10 as the device requires."""
        for name in ("kx", "ky", "kz"):
            check_real(getattr(params, name), name, *PAR_SET_GAIN_RANGE)
        return cls("PAR", ("SET", *params.fields()))

    @classmethod
    def reset(cls) -> CommandFrame:
        """``RESET``: reboot the device."""
        return cls("RESET")

    @property
    def key(self) -> str:
        """Command word plus sub-command where there is one, e.g. ``"MAGCAL,END"``."""
        if self.command in ("MAGCAL", "PAR") and self.args:
            return f"{self.command},{self.args[0]}"
        return self.command

    def rate_hz(self) -> int:
        """The rate of a valid ``RATE`` command (ValueError otherwise)."""
        if self.command != "RATE" or self.error() is not None:
            raise ValueError(f"not a valid RATE command: {self}")
        return int(self.args[0])

    def params(self) -> ParamsFrame:
        """The nine values of a valid ``PAR,SET`` (ValueError otherwise)."""
        if self.key != "PAR,SET" or self.error() is not None:
            raise ValueError(f"not a valid PAR,SET command: {self}")
        return ParamsFrame(*(float(a) for a in self.args[1:]))

    def error(self) -> AckReason | None:
        """What the device answers for the command *itself*: UNKNOWN, ARGS, or None if valid.

        Mode-dependent refusals (STATE) are the firmware's business, not the codec's.
        """
        cmd, args = self.command, self.args
        if cmd not in _COMMAND_WORDS:
            return AckReason.UNKNOWN
        if cmd in ("VER", "ACCCAL", "RESET"):
            return None if not args else AckReason.ARGS
        if cmd == "RATE":
            if len(args) == 1 and INT_RE.fullmatch(args[0]) and int(args[0]) in RATES_HZ:
                return None
            return AckReason.ARGS
        if cmd == "MAGCAL":
            return None if args in (("START",), ("END",), ("ABORT",)) else AckReason.ARGS
        # PAR
        if args == ("GET",):
            return None
        if len(args) != 10 or args[0] != "SET":
            return AckReason.ARGS
        try:
            values = [parse_decimal(a, "PAR,SET") for a in args[1:]]
            for i, v in enumerate(values):
                rng = PAR_SET_GAIN_RANGE if 3 <= i < 6 else OFFSET_RANGE
                check_real(v, _PARAM_NAMES[i], *rng)
        except DecodeError:
            return AckReason.ARGS
        return None

    def is_answer(self, frame: GmrFrame) -> bool:
        """Whether ``frame`` answers this command (``$PGMRK,<command>``, or PGMRV/PGMRP)."""
        if isinstance(frame, AckFrame):
            return frame.command == self.command
        if isinstance(frame, VersionFrame):
            return self.command == "VER"
        if isinstance(frame, ParamsFrame):
            return self.key == "PAR,GET"
        return False

    def ack_ok(self, fields: tuple[str, ...] = ()) -> AckFrame:
        """The ``$PGMRK,<command>,OK`` answer (for the simulated firmware)."""
        return AckFrame(self.command, True, fields)

    def ack_err(self, reason: AckReason | str) -> AckFrame:
        """The ``$PGMRK,<command>,ERR,<reason>`` answer (for the simulated firmware)."""
        return AckFrame.failure(self.command, reason)


GmrFrame: TypeAlias = (
    AttitudeFrame | VersionFrame | CalProgressFrame | ParamsFrame | AckFrame | CommandFrame
)


# --------------------------------------------------------------------------- encode


def encode_body(frame: GmrFrame) -> str:
    """The sentence body (between ``$`` and ``*``) for ``frame``."""
    parts: list[str]
    if isinstance(frame, AttitudeFrame):
        hdg = _f1(frame.heading)
        if hdg == "360.0":  # 359.95.. rounds up: the datasheet's range stops at 359.9
            hdg = "0.0"
        # One f-string, not a list joined: the simulated firmware encodes every frame it
        # sends (the fields are validated ints and floats: "{x}" is str(x)).
        return (
            f"PGMRA,{frame.seq},{hdg},{_f1(frame.pitch)},{_f1(frame.roll)},"
            f"{frame.mx},{frame.my},{frame.mz},{frame.ax},{frame.ay},{frame.az},"
            f"{int(frame.flags):02X}"
        )
    if isinstance(frame, VersionFrame):
        parts = ["PGMRV", frame.firmware, frame.hardware, frame.serial]
    elif isinstance(frame, CalProgressFrame):
        parts = [
            "PGMRC",
            *(
                str(v)
                for v in (
                    frame.samples,
                    frame.xmin,
                    frame.xmax,
                    frame.ymin,
                    frame.ymax,
                    frame.zmin,
                    frame.zmax,
                )
            ),
        ]
    elif isinstance(frame, ParamsFrame):
        parts = ["PGMRP", *frame.fields()]
    elif isinstance(frame, AckFrame):
        parts = ["PGMRK", frame.command, "OK" if frame.ok else "ERR", *frame.fields]
    elif isinstance(frame, CommandFrame):
        parts = ["PGMRQ", frame.command, *frame.args]
    else:
        raise TypeError(f"not a GMR frame: {frame!r}")
    return ",".join(parts)


def encode(frame: GmrFrame) -> bytes:
    """The full line for ``frame``: ``$<body>*<CS>\\r\\n``."""
    return render_line(encode_body(frame))


def _check_length(frame: GmrFrame) -> None:
    # Only frames with free-form strings can outgrow a line; refuse them at construction
    # so that every constructible frame is encodable.
    n = len(encode_body(frame))
    if n > MAX_BODY_BYTES:
        raise DecodeError(DropReason.TOO_LONG, f"sentence body is {n} bytes, over {MAX_BODY_BYTES}")
