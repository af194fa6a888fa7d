"""The daemon's configuration: TOML -> frozen, validated dataclasses.

This file is a contract: other tools start the daemon with a TOML file, so
every key has one name, one type, one default and one documented range, and an
invalid file is refused at start with a message naming the key and the reason::

    config error: device.baud: must be one of 4800, 9600, ..., got 1234

Layering is the python-can one: built-in defaults < file < command-line
overrides (``--set device.port=sim``). Everything is validated once, after the
layers are merged, by one generic loader that walks the dataclasses below.

Adding a key is ONE line in a section dataclass::

    rate_hz: int = setting(10, one_of(1, 2, 5, 10, 20, 50, 100), "output rate asked of the device", "Hz")

The annotation gives the TOML type, :func:`setting` the default, the rule (a
:class:`Rule`: range, choices, shape) and the text the docs use. Checks that
span keys live in the section's ``finish()`` hook.
"""

from __future__ import annotations

import dataclasses
import difflib
import ipaddress
import math
import os
import re
import socket
import tomllib
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

HOSTNAME_PLACEHOLDER = "<hostname>"
#: The service's state directory (calibration, parameters) unless configured or given by systemd.
DEFAULT_STATE_DIR = "/var/lib/compass-bridge"

# The device's fixed set of output rates (datasheet, RATE command).
DEVICE_RATES_HZ = (1, 2, 5, 10, 20, 50, 100)
# Standard RS-232 rates a USB adapter and the compasses we speak to support.
BAUD_RATES = (4800, 9600, 19200, 38400, 57600, 115200, 230400)
PROTOCOLS = ("gmr", "nmea", "os5000")


class ConfigError(ValueError):
    """An invalid configuration: ``key`` is the dotted key (or file), ``reason`` why."""

    def __init__(self, key: str, reason: str) -> None:
        super().__init__(f"{key}: {reason}")
        self.key = key
        self.reason = reason


# ---------------------------------------------------------------------------
# Rules: one value in, the (normalised) value out, ValueError(reason) if bad.
# ---------------------------------------------------------------------------


class _ItemError(ValueError):
    """A list element failed its rule; carries the index so the key can name it."""

    def __init__(self, index: int, reason: str) -> None:
        super().__init__(reason)
        self.index = index


@dataclass(frozen=True, slots=True)
class Rule:
    """A validation rule: ``text`` describes the allowed values (docs, messages)."""

    text: str
    check: Callable[[Any], Any]

    def __call__(self, value: Any) -> Any:
        """Return the accepted (possibly normalised) value or raise ``ValueError``."""
        return self.check(value)


def _fmt(v: Any) -> str:
    return f'"{v}"' if isinstance(v, str) else str(v)


def one_of(*choices: Any) -> Rule:
    """Value must equal one of ``choices``."""
    text = "one of " + ", ".join(_fmt(c) for c in choices)

    def check(v: Any) -> Any:
        if v not in choices:
            raise ValueError(f"must be {text}, got {_fmt(v)}")
        return v

    return Rule(text, check)


def between(lo: float, hi: float, *, lo_open: bool = False) -> Rule:
    """Numeric value must lie in ``[lo, hi]`` (or ``(lo, hi]`` with ``lo_open``)."""
    text = f"{'(' if lo_open else '['}{_num(lo)}, {_num(hi)}]"

    def check(v: Any) -> Any:
        if not ((lo < v) if lo_open else (lo <= v)) or not v <= hi:
            raise ValueError(f"must be in {text}, got {_num(v)}")
        return v

    return Rule(text, check)


def _num(v: float) -> str:
    return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else str(v)


def each(rule: Rule) -> Rule:
    """Every element of a list must pass ``rule``."""

    def check(values: tuple[Any, ...]) -> tuple[Any, ...]:
        out = []
        for i, v in enumerate(values):
            try:
                out.append(rule(v))
            except ValueError as e:
                raise _ItemError(i, str(e)) from None
        return tuple(out)

    return Rule(f"each {rule.text}", check)


def _rule(text: str) -> Callable[[Callable[[Any], Any]], Rule]:
    """Decorator turning a check function into a :class:`Rule` with docs text."""

    def wrap(fn: Callable[[Any], Any]) -> Rule:
        return Rule(text, fn)

    return wrap


# --- shapes ---------------------------------------------------------------

_HOSTNAME_RE = re.compile(
    r"^(?=.{1,253}$)[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
    r"(?:\.[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$"
)


def _host(h: str) -> None:
    """Raise ValueError unless ``h`` is an IP address or a DNS host name."""
    if h.startswith("[") and h.endswith("]"):
        ipaddress.IPv6Address(h[1:-1])  # raises ValueError
        return
    try:
        ipaddress.ip_address(h)
        return
    except ValueError:
        pass
    if not _HOSTNAME_RE.match(h):
        raise ValueError(f"{h!r} is not an IP address or host name")


def _port(p: str) -> int:
    if not p.isdigit() or not 1 <= int(p) <= 65535:
        raise ValueError(f"port {p!r} is not a number in [1, 65535]")
    return int(p)


def _host_port(s: str) -> tuple[str, int]:
    host, sep, port = s.rpartition(":")
    if not sep or not host:
        raise ValueError("expected HOST:PORT")
    _host(host)
    return host.strip("[]"), _port(port)


@dataclass(frozen=True, slots=True)
class MavlinkEndpoint:
    """A parsed pymavlink connection string.

    ``kind`` is ``udpout``/``udpin``/``udp``/``tcp``/``tcpin`` (``host``,
    ``port`` set) or ``serial`` (``device``, ``baud`` set; ``baud`` is None
    when the string gave none). ``text`` is the original string.
    """

    text: str
    kind: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int | None = None


MAVLINK_NET_KINDS = ("udpout", "udpin", "udp", "tcp", "tcpin")


def parse_mavlink_endpoint(text: str) -> MavlinkEndpoint:
    """Parse ``udpout:HOST:PORT`` etc. or ``/dev/ttyX[,BAUD]``; ``ValueError`` if malformed."""
    kind, sep, rest = text.partition(":")
    if sep and kind in MAVLINK_NET_KINDS:
        try:
            host, port = _host_port(rest)
        except ValueError as e:
            raise ValueError(f"{text!r}: {e}") from None
        return MavlinkEndpoint(text, kind, host=host, port=port)
    if text.startswith("/"):
        device, comma, baud = text.partition(",")
        if comma:
            if not baud.isdigit() or int(baud) <= 0:
                raise ValueError(f"{text!r}: serial baud {baud!r} is not a positive integer")
            return MavlinkEndpoint(text, "serial", device=device, baud=int(baud))
        return MavlinkEndpoint(text, "serial", device=device)
    raise ValueError(
        f"{text!r} is not a MAVLink endpoint "
        f"({'/'.join(k + ':' for k in MAVLINK_NET_KINDS)}HOST:PORT or /dev/DEVICE[,BAUD])"
    )


@_rule("udpout:/udpin:/udp:/tcp:/tcpin:HOST:PORT or /dev/DEVICE[,BAUD]")
def mavlink_endpoint(v: str) -> str:
    parse_mavlink_endpoint(v)
    return v


ZENOH_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")


@_rule("PROTO/HOST:PORT (tcp, udp, tls, quic, ws) or unixsock-stream/PATH")
def zenoh_endpoint(v: str) -> str:
    # Zenoh locators may carry "?metadata" and "#config" suffixes; the address is before them.
    proto, sep, rest = v.partition("/")
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    if sep and proto == "unixsock-stream" and address.startswith("/"):
        return v
    if not sep or proto not in ZENOH_PROTOCOLS:
        raise ValueError(f"{v!r} is not a zenoh endpoint like tcp/192.168.1.10:7447")
    try:
        _host_port(address)
    except ValueError as e:
        raise ValueError(f"{v!r}: {e}") from None
    return v


def validate_key_expr(v: str) -> str:
    """A concrete zenoh key expression usable as a publication prefix."""
    if not v or v.startswith("/") or v.endswith("/") or "//" in v:
        raise ValueError(f"{v!r} is not a key expression (no empty chunks, no leading/trailing /)")
    bad = sorted(set(v) & set("*$?#"))
    if bad:
        raise ValueError(f"{v!r} must be concrete: {''.join(bad)!r} not allowed in a prefix")
    if re.search(r"\s", v):
        raise ValueError(f"{v!r} contains white space")
    return v


@_rule(f'a zenoh key expression; "{HOSTNAME_PLACEHOLDER}" is replaced by the host name')
def key_prefix(v: str) -> str:
    left = v.replace(HOSTNAME_PLACEHOLDER, "x")
    if "<" in left or ">" in left:
        raise ValueError(f"{v!r}: the only placeholder is {HOSTNAME_PLACEHOLDER}")
    validate_key_expr(left)
    return v


@_rule('"sim", "replay:PATH" or an absolute serial device path like /dev/ttyUSB0')
def device_port(v: str) -> str:
    if v == "sim":
        return v
    if v.startswith("replay:"):
        path = v.removeprefix("replay:")
        if not path:
            raise ValueError('"replay:" needs a recording path, e.g. replay:/tmp/run.cbrec')
        if not Path(path).is_file():
            raise ValueError(f"recording {path!r} does not exist or is not a file")
        return v
    # A serial device is NOT required to exist at load: a USB adapter that
    # appears after boot is normal, and the link keeps retrying.
    if v.startswith("/"):
        return v
    raise ValueError(f'must be "sim", "replay:PATH" or an absolute device path, got {v!r}')


# ---------------------------------------------------------------------------
# Field declaration
# ---------------------------------------------------------------------------

_REQUIRED: Any = object()


def setting(
    default: Any,
    rule: Rule | None = None,
    doc: str = "",
    unit: str = "",
    *,
    required: bool = False,
) -> Any:
    """Declare one TOML key: default, validation rule, docs text and unit."""
    meta = {"rule": rule, "doc": doc, "unit": unit, "required": required}
    return field(default=default, metadata=meta)


def derived(default: Any, doc: str = "") -> Any:
    """A value computed at load (not a TOML key), e.g. the signing key read from its file."""
    return field(default=default, metadata={"derived": True, "doc": doc}, compare=False)


@dataclass(frozen=True, slots=True)
class LoadContext:
    """What a section's ``finish()`` may consult: the environment and the host name."""

    env: Mapping[str, str]
    hostname: str


class Section:
    """Mixin for section dataclasses: ``finish`` does cross-key checks and derived values."""

    __slots__ = ()

    def finish(self, ctx: LoadContext) -> Self:
        """Return the section, possibly with derived values set; raise ConfigError if bad."""
        return self


# ---------------------------------------------------------------------------
# The sections
# ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DeviceConfig(Section):
    """``[device]``: the compass on the serial port."""

    port: str = setting("/dev/ttyUSB0", device_port, "serial device, or sim / replay:PATH")
    baud: int = setting(115200, one_of(*BAUD_RATES), "serial baud rate (8N1)", "baud")
    protocol: str = setting("gmr", one_of(*PROTOCOLS), "sentence set the compass speaks")
    rate_hz: int = setting(
        10, one_of(*DEVICE_RATES_HZ), "output rate asked of a gmr device on connect", "Hz"
    )
    stale_after: float = setting(
        2.0,
        between(0.0, 60.0, lo_open=True),
        "no valid frame for this long -> stale, reconnect",
        "s",
    )
    replay_realtime: bool = setting(
        True, None, "replay:PATH at the recorded pace (false: as fast as it decodes)"
    )

    def finish(self, ctx: LoadContext) -> Self:
        """Require ``stale_after`` to span two frame periods at the requested rate."""
        # One lost frame must not look like a dead link; heading-only compasses
        # stream at their own rate, so the check applies to gmr only.
        if self.protocol == "gmr" and self.stale_after < 2.0 / self.rate_hz:
            raise ConfigError(
                "device.stale_after",
                f"must be at least two frame periods (2/rate_hz = {2.0 / self.rate_hz:g} s), "
                f"got {self.stale_after:g}",
            )
        return self


@dataclass(frozen=True, slots=True)
class MavlinkConfig(Section):
    """``[mavlink]``: where MAVLink goes and who we are on it."""

    endpoints: tuple[str, ...] = setting(
        ("udpout:127.0.0.1:14550",), each(mavlink_endpoint), "pymavlink connection strings"
    )
    system_id: int = setting(1, between(1, 255), "MAVLink system id of the vehicle")
    component_id: int = setting(1, between(1, 255), "MAVLink component id of the bridge")
    signing_key_file: str = setting(
        "", None, 'file holding the 32-byte signing key as 64 hex characters; "" = unsigned'
    )
    role: str = setting(
        "standalone",
        one_of("standalone", "companion"),
        "standalone: the bridge is the vehicle (component 1, QGroundControl draws it); "
        "companion: beside an autopilot of the same system_id (component 200 = "
        "MAV_COMP_ID_IMU when component_id is left at 1), position taken from the autopilot",
    )
    autopilot: str = setting(
        "generic",
        one_of("generic", "px4", "ardupilot"),
        "the autopilot a standalone bridge presents itself as (HEARTBEAT.autopilot), which "
        "ground stations follow: px4 for MAVSDK and QGroundControl's PX4 pages, ardupilot for "
        "QGroundControl's ArduPilot pages and MAVProxy; it also sets the parameter encoding",
    )
    heading_feed: str = setting(
        "off",
        one_of("off", "px4_odometry", "ardupilot_vision"),
        "heading for the autopilot's estimator: PX4 ODOMETRY or ArduPilot "
        "VISION_POSITION_ESTIMATE; parameter BRG_HDG_FEED",
    )
    heading_feed_sigma_deg: float = setting(
        2.0, between(0.1, 90.0), "yaw standard deviation sent with the heading feed", "deg"
    )
    rate_attitude_hz: float = setting(
        10.0, between(0.0, 50.0), "ATTITUDE rate, 0 = off; parameter BRG_SR_ATT", "Hz"
    )
    rate_attitude_quaternion_hz: float = setting(
        10.0, between(0.0, 50.0), "ATTITUDE_QUATERNION rate; parameter BRG_SR_QUAT", "Hz"
    )
    rate_vfr_hud_hz: float = setting(
        4.0, between(0.0, 50.0), "VFR_HUD rate; parameter BRG_SR_HUD", "Hz"
    )
    rate_scaled_imu_hz: float = setting(
        2.0, between(0.0, 50.0), "SCALED_IMU rate; parameter BRG_SR_SIMU", "Hz"
    )
    rate_raw_imu_hz: float = setting(
        2.0, between(0.0, 50.0), "RAW_IMU rate; parameter BRG_SR_RIMU", "Hz"
    )
    rate_highres_imu_hz: float = setting(
        2.0, between(0.0, 50.0), "HIGHRES_IMU rate; parameter BRG_SR_HIMU", "Hz"
    )
    rate_sys_status_hz: float = setting(
        1.0, between(0.0, 50.0), "SYS_STATUS rate; parameter BRG_SR_SYS", "Hz"
    )
    rate_heading_feed_hz: float = setting(
        10.0, between(0.0, 50.0), "heading feed rate; parameter BRG_SR_FEED", "Hz"
    )
    signing_key: bytes | None = derived(None, "the key read from signing_key_file at load")

    def finish(self, ctx: LoadContext) -> Self:
        """Read and check the signing key now, so a bad key refuses the start."""
        if not self.signing_key_file:
            return self
        key = "mavlink.signing_key_file"
        try:
            text = Path(self.signing_key_file).read_text(encoding="ascii").strip()
        except FileNotFoundError:
            raise ConfigError(key, f"{self.signing_key_file!r} does not exist") from None
        except (OSError, UnicodeDecodeError) as e:
            raise ConfigError(key, f"cannot read {self.signing_key_file!r}: {e}") from None
        if not re.fullmatch(r"[0-9A-Fa-f]{64}", text):
            raise ConfigError(
                key,
                f"{self.signing_key_file!r} must hold exactly 64 hex characters "
                f"(a 32-byte key), found {len(text)} characters",
            )
        return dataclasses.replace(self, signing_key=bytes.fromhex(text))

    @property
    def parsed_endpoints(self) -> tuple[MavlinkEndpoint, ...]:
        """``endpoints`` parsed into their parts."""
        return tuple(parse_mavlink_endpoint(e) for e in self.endpoints)


@dataclass(frozen=True, slots=True)
class ZenohConfig(Section):
    """``[zenoh]``: the Zenoh session and where we publish."""

    enabled: bool = setting(True, None, "publish on Zenoh")
    mode: str = setting("peer", one_of("peer", "client"), "zenoh session mode")
    connect: tuple[str, ...] = setting((), each(zenoh_endpoint), "endpoints to connect to")
    listen: tuple[str, ...] = setting((), each(zenoh_endpoint), "endpoints to listen on")
    key_prefix: str = setting(
        f"fleet/{HOSTNAME_PLACEHOLDER}/compass", key_prefix, "key expression prefix"
    )
    multicast_scouting: bool = setting(
        False, None, "multicast scouting (224.0.0.224:7446); off = explicit endpoints only"
    )
    config_file: str = setting(
        "",
        None,
        'zenoh JSON5 file used as the base (TLS, user/password, access control); "" = none',
    )
    heading_rate_hz: float = setting(
        10.0, between(0.0, 100.0), "cap of <prefix>/heading; 0 = every frame", "Hz"
    )
    attitude_rate_hz: float = setting(
        10.0, between(0.0, 100.0), "cap of <prefix>/attitude; 0 = every frame", "Hz"
    )
    imu_rate_hz: float = setting(
        10.0, between(0.0, 100.0), "cap of <prefix>/imu; 0 = every frame", "Hz"
    )
    remote_calibration: bool = setting(
        False, None, "answer <prefix>/cmd/calibration/*; pair with zenoh access control"
    )
    mavlink_mirror: bool = setting(
        False, None, "also publish the MAVLink messages as JSON on mavlink/<sys>/<comp>/<MSG>"
    )

    def finish(self, ctx: LoadContext) -> Self:
        """Substitute the host name into ``key_prefix`` and re-check the result."""
        if self.config_file and not Path(self.config_file).is_file():
            raise ConfigError("zenoh.config_file", f"{self.config_file!r} does not exist")
        if HOSTNAME_PLACEHOLDER not in self.key_prefix:
            return self
        prefix = self.key_prefix.replace(HOSTNAME_PLACEHOLDER, ctx.hostname)
        try:
            validate_key_expr(prefix)
        except ValueError as e:
            raise ConfigError("zenoh.key_prefix", f"after host name substitution: {e}") from None
        return dataclasses.replace(self, key_prefix=prefix)


@dataclass(frozen=True, slots=True)
class StorageConfig(Section):
    """``[storage]``: where the bridge keeps its state (calibration)."""

    dir: str = setting(
        "", None, f'state directory; "" = $STATE_DIRECTORY, else {DEFAULT_STATE_DIR}'
    )

    def finish(self, ctx: LoadContext) -> Self:
        """Resolve the empty default the systemd way: $STATE_DIRECTORY first."""
        if self.dir:
            return self
        # systemd's StateDirectory= may list several, colon-separated; ours is the first.
        state = ctx.env.get("STATE_DIRECTORY", "").split(":")[0]
        return dataclasses.replace(self, dir=state or DEFAULT_STATE_DIR)


@dataclass(frozen=True, slots=True)
class CalibrationConfig(Section):
    """``[calibration]``: how calibrations run (``bridge.calibrator``)."""

    onboard: bool = setting(
        False,
        None,
        "run magnetometer and level calibrations in the compass itself (MAGCAL / ACCCAL, "
        "result in its flash) instead of on the host; MAVLink parameter BRG_CAL_ONBOARD",
    )
    timeout_s: float = setting(
        180.0,
        between(10.0, 3600.0),
        "a calibration not finished after this long fails (turn the unit faster)",
        "s",
    )


@dataclass(frozen=True, slots=True)
class LocationConfig(Section):
    """``[location]``: where the vehicle is, for declination and the expected field (WMM)."""

    latitude: float = setting(
        math.nan, between(-90.0, 90.0), "WGS-84 latitude", "deg", required=True
    )
    longitude: float = setting(
        math.nan, between(-180.0, 180.0), "WGS-84 longitude", "deg", required=True
    )
    altitude_m: float = setting(0.0, between(-1000.0, 850_000.0), "height above WGS-84", "m")


#: Motion scripts of the simulated compass (bridge.sim.pty.MOTIONS; a test keeps them equal).
SIM_MOTIONS = ("turns", "still", "tumble", "drive")


@dataclass(frozen=True, slots=True)
class SimConfig(Section):
    """``[sim]``: the built-in simulated compass (``device.port = "sim"``)."""

    seed: int = setting(1, between(0, 2**32 - 1), "unit seed: the simulated unit's errors")
    motion: str = setting("turns", one_of(*SIM_MOTIONS), "motion script of the simulated unit")
    ideal: bool = setting(False, None, "a perfect, noise-free unit instead of a drawn one")
    shake_g: float = setting(
        0.0, between(0.0, 0.5), "hand-held shake of the unit: linear acceleration, g RMS per axis"
    )
    flash_file: str = setting(
        "", None, 'file keeping the simulated unit flash across runs; "" = in memory'
    )


@dataclass(frozen=True, slots=True)
class Config:
    """The whole configuration. ``location`` is None when ``[location]`` is absent."""

    device: DeviceConfig = field(default_factory=DeviceConfig)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    storage: StorageConfig = field(default_factory=StorageConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    location: LocationConfig | None = None
    sim: SimConfig = field(default_factory=SimConfig)


# ---------------------------------------------------------------------------
# The generic loader
# ---------------------------------------------------------------------------


def section_types() -> dict[str, type[Section]]:
    """Section name -> its dataclass, in file order."""
    hints = typing.get_type_hints(Config)
    out: dict[str, type[Section]] = {}
    for f in dataclasses.fields(Config):
        t = hints[f.name]
        args = [a for a in typing.get_args(t) if a is not type(None)]
        out[f.name] = args[0] if args else t
    return out


_HINTS: dict[type, dict[str, Any]] = {}


def _field_hints(cls: type) -> dict[str, Any]:
    # get_type_hints resolves the string annotations; cached because overrides call it per key.
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def settings_of(cls: type[Section]) -> list[dataclasses.Field[Any]]:
    """The TOML keys of a section (its fields that are not derived)."""
    return [f for f in dataclasses.fields(cls) if not f.metadata.get("derived")]  # type: ignore[arg-type]


def _type_name(t: Any) -> str:
    if typing.get_origin(t) is tuple:
        return f"list of {_type_name(typing.get_args(t)[0])}s"
    return {str: "string", int: "integer", float: "number", bool: "boolean"}.get(t, str(t))


def type_name(cls: type[Section], name: str) -> str:
    """Human name of a key's TOML type ("string", "integer", "list of strings")."""
    return _type_name(_field_hints(cls)[name])


def _toml_kind(v: Any) -> str:
    if isinstance(v, bool):
        return "boolean"
    if isinstance(v, int):
        return "integer"
    if isinstance(v, float):
        return "number"
    if isinstance(v, str):
        return "string"
    if isinstance(v, list):
        return "list"
    if isinstance(v, dict):
        return "table"
    return type(v).__name__


def _coerce(t: Any, v: Any) -> Any:
    """Check ``v``'s TOML type against annotation ``t``; ValueError(reason) if wrong."""
    want = _type_name(t)
    if typing.get_origin(t) is tuple:
        (item,) = typing.get_args(t)[:1]
        if not isinstance(v, list):
            raise ValueError(f"must be a {want}, got {_toml_kind(v)}")
        out = []
        for i, x in enumerate(v):
            try:
                out.append(_coerce(item, x))
            except ValueError as e:
                raise _ItemError(i, str(e)) from None
        return tuple(out)
    ok = {
        str: isinstance(v, str),
        bool: isinstance(v, bool),
        int: isinstance(v, int) and not isinstance(v, bool),
        # TOML distinguishes 2 from 2.0; a float key accepts both.
        float: isinstance(v, int | float) and not isinstance(v, bool),
    }.get(t)
    if ok is None:  # pragma: no cover - a programming error in a section declaration
        raise TypeError(f"unsupported setting type {t!r}")
    if not ok:
        raise ValueError(f"must be a {want}, got {_toml_kind(v)} {v!r}")
    if t is float:
        v = float(v)
        if not math.isfinite(v):
            raise ValueError(f"must be a finite number, got {v}")
    return v


def _unknown(key: str, name: str, known: Sequence[str], what: str = "key") -> ConfigError:
    close = difflib.get_close_matches(name, known, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return ConfigError(key, f"unknown {what}{hint}; known: {', '.join(known)}")


def _build_section(cls: type[Section], raw: Mapping[str, Any], name: str, ctx: LoadContext) -> Any:
    fields = settings_of(cls)
    known = [f.name for f in fields]
    for k in raw:
        if k not in known:
            raise _unknown(f"{name}.{k}", k, known)
    hints = _field_hints(cls)
    values: dict[str, Any] = {}
    for f in fields:
        key = f"{name}.{f.name}"
        if f.name not in raw:
            if f.metadata.get("required"):
                others = ", ".join(g.name for g in fields if g.metadata.get("required"))
                raise ConfigError(key, f"required when [{name}] is present ({others} go together)")
            continue
        rule: Rule | None = f.metadata.get("rule")
        try:
            v = _coerce(hints[f.name], raw[f.name])
            values[f.name] = rule(v) if rule is not None else v
        except _ItemError as e:
            raise ConfigError(f"{key}[{e.index}]", str(e)) from None
        except ValueError as e:
            raise ConfigError(key, str(e)) from None
    return cls(**values).finish(ctx)


def _build(raw: Mapping[str, Any], ctx: LoadContext) -> Config:
    sections = section_types()
    for k in raw:
        if k not in sections:
            raise _unknown(k, k, list(sections), "section")
    built: dict[str, Any] = {}
    for name, cls in sections.items():
        sub = raw.get(name)
        if sub is None:
            if name == "location":  # optional section: absent means "unknown place"
                continue
            sub = {}
        if not isinstance(sub, dict):
            raise ConfigError(name, f"must be a table [{name}], got {_toml_kind(sub)}")
        built[name] = _build_section(cls, sub, name, ctx)
    return Config(**built)


def _parse_override(item: str) -> tuple[str, str, Any]:
    key, eq, text = item.partition("=")
    key = key.strip()
    parts = key.split(".")
    if not eq or len(parts) != 2 or not all(parts):
        raise ConfigError(key or item, "an override must look like SECTION.KEY=VALUE")
    section, name = parts
    value: Any
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        value = text  # bare words are strings: --set device.port=sim
    cls = section_types().get(section)
    if cls is not None and name in _field_hints(cls) and _field_hints(cls)[name] is str:
        value = text if not isinstance(value, str) else value  # "--set x.y=007" stays a string
    return section, name, value


def merge_overrides(raw: Mapping[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Apply ``SECTION.KEY=VALUE`` overrides (values parsed as TOML, else strings) to ``raw``."""
    out: dict[str, Any] = {k: dict(v) if isinstance(v, dict) else v for k, v in raw.items()}
    for item in overrides:
        section, name, value = _parse_override(item)
        table = out.setdefault(section, {})
        if not isinstance(table, dict):
            raise ConfigError(section, f"must be a table [{section}], got {_toml_kind(table)}")
        table[name] = value
    return out


def read_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a TOML file; any failure is a :class:`ConfigError` naming the file."""
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except OSError as e:
        raise ConfigError(str(path), f"cannot read: {e.strerror or e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(str(path), f"not valid TOML: {e}") from None


def load_config(
    path: str | os.PathLike[str] | None = None,
    overrides: Sequence[str] = (),
    *,
    env: Mapping[str, str] | None = None,
    hostname: str | None = None,
) -> Config:
    """Defaults < the TOML file at ``path`` (if any) < ``overrides``; validated.

    ``env`` (default ``os.environ``) supplies ``STATE_DIRECTORY``; ``hostname``
    (default ``socket.gethostname()``) replaces ``<hostname>`` in
    ``zenoh.key_prefix``. Raises :class:`ConfigError` naming the bad key.
    """
    raw = read_toml(path) if path is not None else {}
    return config_from_mapping(merge_overrides(raw, overrides), env=env, hostname=hostname)


def config_from_mapping(
    raw: Mapping[str, Any],
    *,
    env: Mapping[str, str] | None = None,
    hostname: str | None = None,
) -> Config:
    """Validate an already-parsed TOML document (see :func:`load_config`)."""
    ctx = LoadContext(
        env=os.environ if env is None else env,
        hostname=socket.gethostname() if hostname is None else hostname,
    )
    return _build(raw, ctx)


def to_toml(cfg: Config) -> str:
    """The effective configuration as TOML (derived values omitted), e.g. for ``config``."""
    lines: list[str] = []
    for name in section_types():
        sec = getattr(cfg, name)
        if sec is None:
            continue
        lines.append(f"[{name}]")
        for f in settings_of(type(sec)):
            lines.append(f"{f.name} = {_toml_value(getattr(sec, f.name))}")
        lines.append("")
    return "\n".join(lines)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)
