"""The daemon's configuration: TOML -> frozen, validated dataclasses.

This file is a contract: other tools start the daemon with a TOML file, so
every key has one name, one type, one default and one documented range, and an
invalid file is refused at start with a message naming the key and the reason::

    config error: device.baud: must be one of 4800, 9600, ..., got 1234

Layering is the python-can one: built-in defaults < file < command-line
overrides (``--set device.port=sim``). Everything is validated once, after the
layers are merged, by one generic loader (:mod:`bridge.configkit.loader`) that
walks the section dataclasses below; a path or endpoint that can never work
(a NUL byte, ``999.1.1.1``, a device where a file belongs) is refused there
too, so nothing fails later in a worker thread.

Adding a key is ONE line in a section dataclass::

    rate_hz: int = setting(10, one_of(1, 2, 5, 10, 20, 50, 100), "output rate asked of the device", "Hz")

The annotation gives the TOML type, :func:`setting` the default, the rule (a
:class:`Rule`: range, choices, shape) and the text the docs use
(``docs/configuration.md`` is generated from them: ``compass-bridge config --docs``).
Checks that span keys live in the section's ``finish()`` hook.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import socket
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Self

from bridge.configkit import loader
from bridge.configkit.rules import (
    HOSTNAME_PLACEHOLDER,
    MAVLINK_NET_KINDS,
    ZENOH_PROTOCOLS,
    MavlinkEndpoint,
    Rule,
    between,
    device_port,
    directory_path,
    each,
    key_prefix,
    mavlink_endpoint,
    one_of,
    parse_mavlink_endpoint,
    rule,
    validate_key_expr,
    writable_file_path,
    zenoh_endpoint,
)
from bridge.configkit.schema import (
    ConfigError,
    LoadContext,
    Section,
    derived,
    setting,
    settings_of,
    type_name,
)
from bridge.files import FileRefused, read_regular_file
from bridge.types import HEADING_REFERENCES, LEARN_MODES

#: The service's state directory (calibration, parameters) unless configured or given by systemd.
DEFAULT_STATE_DIR = "/var/lib/compass-bridge"

__all__ = [
    "BAUD_RATES",
    "DEVICE_RATES_HZ",
    "HOSTNAME_PLACEHOLDER",
    "MAVLINK_NET_KINDS",
    "PROTOCOLS",
    "SIM_MOTIONS",
    "ZENOH_PROTOCOLS",
    "CalibrationConfig",
    "Config",
    "ConfigError",
    "DeviceConfig",
    "HeadingConfig",
    "LoadContext",
    "LocationConfig",
    "MavlinkConfig",
    "MavlinkEndpoint",
    "Rule",
    "Section",
    "SimConfig",
    "StorageConfig",
    "ZenohConfig",
    "between",
    "config_from_mapping",
    "derived",
    "each",
    "load_config",
    "merge_overrides",
    "one_of",
    "parse_mavlink_endpoint",
    "read_toml",
    "section_types",
    "setting",
    "settings_of",
    "to_toml",
    "type_name",
    "validate_key_expr",
    "zenoh_endpoint",
]

# The device's fixed set of output rates (datasheet, RATE command).
DEVICE_RATES_HZ = (1, 2, 5, 10, 20, 50, 100)
# Standard RS-232 rates a USB adapter and the compasses we speak to support.
BAUD_RATES = (4800, 9600, 19200, 38400, 57600, 115200, 230400)
PROTOCOLS = ("gmr", "nmea", "os5000")
#: The signing key file holds 64 hex characters and a newline; a few kB is already a mistake.
MAX_KEY_FILE_BYTES = 4096
#: A zenoh JSON5 configuration (TLS, access control) is a few kB.
MAX_ZENOH_CONFIG_BYTES = 1 << 20

#: ``[heading] tilt``: where the tilt compensation's roll and pitch come from.
TILT_MODES: tuple[str, ...] = ("auto", "accelerometer")
#: MAV_AUTOPILOT flavours of the standalone HEARTBEAT.
AUTOPILOTS = ("generic", "px4", "ardupilot")


@rule('an existing regular file of at most 1 MiB, read at start; "" = none')
def _zenoh_config_file(v: str) -> str:
    return v


@rule('a file holding 64 hex characters (a 32-byte key), read at start; "" = unsigned')
def _signing_key_file(v: str) -> str:
    return v


def _read_config_file(key: str, path: str, max_bytes: int) -> bytes:
    """A file a key names, read safely (regular, bounded, non-blocking); ConfigError if not."""
    try:
        return read_regular_file(path, max_bytes)
    except FileRefused as e:
        raise ConfigError(key, f"{loader.show_path(path)}: {e}") from None


# ---------------------------------------------------------------------------
# The sections
# ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DeviceConfig(Section):
    """``[device]``: the compass on the serial port."""

    port: str = setting(
        "/dev/ttyUSB0",
        device_port,
        'an absolute serial device path; "sim" = the built-in simulated compass; '
        '"replay:PATH" = play a recording made by `compass-bridge record` (must exist). '
        "A device path need not exist at start: the link keeps retrying",
    )
    baud: int = setting(
        115200, one_of(*BAUD_RATES), "serial baud rate (8N1, no flow control)", "baud"
    )
    protocol: str = setting(
        "gmr",
        one_of(*PROTOCOLS),
        'sentence set the compass speaks: "gmr" (raw vectors, calibrated on the host), '
        '"nmea" (HDT/HDG/HDM, $PTNTHPR) or "os5000" (OceanServer); the last two are '
        "heading-only: forwarded, not calibrated",
    )
    rate_hz: int = setting(
        10, one_of(*DEVICE_RATES_HZ), "output rate asked of a gmr device on every connect", "Hz"
    )
    stale_after: float = setting(
        2.0,
        between(0.0, 60.0, lo_open=True),
        "no attitude frame for this long -> stale, reconnect; for gmr at least 2 / rate_hz",
        "s",
    )
    replay_realtime: bool = setting(
        True, None, "replay:PATH at the recorded pace (false: as fast as it decodes)"
    )
    read_bursts: bool = setting(
        True,
        None,
        "read the port in bursts between the outputs' due times: one wake-up for the frames "
        "no output sends (less CPU), the one an output sends read as it comes; false: every "
        "frame as it arrives (so is a replay without replay_realtime)",
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
class HeadingConfig(Section):
    """``[heading]``: which heading the bridge publishes.

    Magnetic is what the compass measures and what ArduPilot's and PX4's compass
    drivers expect; true needs the declination, from the World Magnetic Model at
    ``[location]`` (or, in companion role, at the autopilot's position). Until a
    declination is known the magnetic heading is published, labelled magnetic.
    Both headings are always given side by side where known (Zenoh ``heading``).
    """

    reference: str = setting(
        "magnetic",
        one_of(*HEADING_REFERENCES),
        'north of the published heading (MAVLink ATTITUDE yaw, VFR_HUD, Zenoh "heading_deg"): '
        '"magnetic" or "true" (magnetic + declination)',
    )
    tilt: str = setting(
        "auto",
        one_of(*TILT_MODES),
        'where roll and pitch for the tilt compensation come from: "auto" (the accelerometer '
        "while the vehicle is quiet; while it accelerates the autopilot's attitude in the "
        "companion role, else the tilt held and matched to the field: docs/tilt.md) or "
        '"accelerometer" (always the accelerometer\'s, frame by frame)',
    )


@dataclass(frozen=True, slots=True)
class MavlinkConfig(Section):
    """``[mavlink]``: where MAVLink goes and who we are on it."""

    endpoints: tuple[str, ...] = setting(
        ("udpout:127.0.0.1:14550",),
        each(mavlink_endpoint),
        "pymavlink connection strings: udpout:/udpin:/udp:/tcp:/tcpin:HOST:PORT "
        "(HOST an IP address or a DNS name) or /dev/DEVICE[,BAUD]",
    )
    system_id: int = setting(
        1, between(1, 255), "MAVLink system id of the vehicle (ArduPilot SYSID_THISMAV)"
    )
    component_id: int = setting(1, between(1, 255), "MAVLink component id of the bridge")
    signing_key_file: str = setting(
        "",
        _signing_key_file,
        "file holding the MAVLink 2 signing key as 64 hex characters (32 bytes), read and "
        'checked at start (a regular file: never a device or a pipe); "" = unsigned',
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
        one_of(*AUTOPILOTS),
        "the autopilot a standalone bridge presents itself as (HEARTBEAT.autopilot), which "
        "ground stations follow: px4 for MAVSDK and QGroundControl's calibration pages, "
        "ardupilot for Mission Planner, generic otherwise (docs/mavlink.md); not used in "
        "the companion role (the autopilot announces itself)",
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
        shown = loader.show_path(self.signing_key_file)
        data = _read_config_file(key, self.signing_key_file, MAX_KEY_FILE_BYTES)
        try:
            text = data.decode("ascii").strip()
        except UnicodeDecodeError:
            raise ConfigError(
                key, f"{shown} must hold 64 hex characters, found non-ASCII bytes"
            ) from None
        if not re.fullmatch(r"[0-9A-Fa-f]{64}", text):
            raise ConfigError(
                key,
                f"{shown} must hold exactly 64 hex characters "
                f"(a 32-byte key), found {len(text)} characters",
            )
        return dataclasses.replace(self, signing_key=bytes.fromhex(text))

    @property
    def parsed_endpoints(self) -> tuple[MavlinkEndpoint, ...]:
        """``endpoints`` parsed into their parts."""
        return tuple(parse_mavlink_endpoint(e) for e in self.endpoints)


@dataclass(frozen=True, slots=True)
class ZenohConfig(Section):
    """``[zenoh]``: the Zenoh session and where we publish.

    With ``listen = []`` a peer listens on tcp/127.0.0.1:7447 only (loopback; if
    that port is taken, e.g. by a zenohd, it runs without a listener). A client
    never listens.
    """

    enabled: bool = setting(True, None, "publish on Zenoh")
    mode: str = setting("peer", one_of("peer", "client"), "zenoh session mode")
    connect: tuple[str, ...] = setting(
        (), each(zenoh_endpoint), "endpoints to connect to, e.g. tcp/192.168.1.10:7447"
    )
    listen: tuple[str, ...] = setting(
        (), each(zenoh_endpoint), "endpoints to listen on (same shape as connect)"
    )
    key_prefix: str = setting(
        f"fleet/{HOSTNAME_PLACEHOLDER}/compass",
        key_prefix,
        "key expression prefix of everything the bridge publishes (no wildcards, no empty chunks)",
    )
    multicast_scouting: bool = setting(
        False, None, "multicast scouting (224.0.0.224:7446); off = explicit endpoints only"
    )
    config_file: str = setting(
        "",
        _zenoh_config_file,
        "zenoh JSON5 file used as the base (TLS, user/password, access control); "
        "the keys above are applied on top",
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
        """Check the base file now, substitute the host name into ``key_prefix``."""
        if self.config_file:
            # zenoh reads it itself later; a device or FIFO here would hang the start.
            _read_config_file("zenoh.config_file", self.config_file, MAX_ZENOH_CONFIG_BYTES)
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
    """``[storage]``: where the bridge keeps its state (calibration, parameters).

    Each document is written atomically (temp file, fsync, rename, fsync of the
    directory) and the previous good copy is kept beside it; a failed write
    (read-only or full disk) keeps the new values in memory and reports it.
    """

    dir: str = setting(
        "",
        directory_path,
        f'state directory; "" = $STATE_DIRECTORY (systemd StateDirectory=), else {DEFAULT_STATE_DIR}',
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
    """``[calibration]``: how calibrations run (``bridge.app.calibration``)."""

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
    learn: str = setting(
        "detect",
        one_of(*LEARN_MODES),
        'while running, between calibrations: "off" = trust the stored calibration; '
        '"detect" = watch whether it still fits the measured field and report when it '
        'no longer does (it is never changed); "learn" = also refine it in the '
        "background and store the result",
    )


@dataclass(frozen=True, slots=True)
class LocationConfig(Section):
    """``[location]``: where the vehicle is, for declination and the expected field (WMM).

    Optional and all-or-nothing: latitude and longitude together (altitude
    defaults to 0). With it the daemon computes the declination and the
    expected field from the World Magnetic Model (bundled, nothing downloaded)
    at start, adds a true heading, and the quality flags compare the measured
    field against the expected one. The simulated compass is placed there too,
    else in Zurich.
    """

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
    calibrated: bool = setting(
        False,
        None,
        "with no calibration stored, start with the unit's true calibration (what a good "
        "calibration gives) instead of none; run --simulate turns it on",
    )
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
    heading: HeadingConfig = field(default_factory=HeadingConfig)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    storage: StorageConfig = field(default_factory=StorageConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    location: LocationConfig | None = None
    sim: SimConfig = field(default_factory=SimConfig)


#: Path checks kept out of the section classes (SimConfig stays a plain declaration).
_PATH_RULES: tuple[tuple[str, str, Rule], ...] = (("sim", "flash_file", writable_file_path),)


def _check_paths(cfg: Config) -> Config:
    for section, name, path_rule in _PATH_RULES:
        try:
            path_rule(getattr(getattr(cfg, section), name))
        except ValueError as e:
            raise ConfigError(f"{section}.{name}", str(e)) from None
    # A heading feed sent with the autopilot's own system *and* component id is dropped by
    # ArduPilot; which ids the autopilot has is known only when it is heard, so the MAVLink
    # output checks it then (bridge.mavlink.autopilot) and withholds the feed.
    return cfg


# ---------------------------------------------------------------------------
# Loading (the generic machinery is bridge.configkit.loader)
# ---------------------------------------------------------------------------


def section_types() -> dict[str, type[Section]]:
    """Section name -> its dataclass, in file order."""
    from bridge.configkit.schema import section_types as of

    return of(Config)


def read_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a TOML file safely; any failure is a :class:`ConfigError` naming the file."""
    return loader.read_toml(path)


def merge_overrides(raw: Mapping[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Apply ``SECTION.KEY=VALUE`` overrides (values parsed as TOML, else strings) to ``raw``."""
    return loader.merge_overrides(Config, raw, overrides)


def _context(env: Mapping[str, str] | None, hostname: str | None) -> LoadContext:
    return LoadContext(
        env=os.environ if env is None else env,
        hostname=socket.gethostname() if hostname is None else hostname,
    )


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
    ``zenoh.key_prefix``. Raises :class:`ConfigError` naming the file or the
    bad key; never blocks on a file (see :func:`bridge.files.read_regular_file`).
    """
    cfg: Config = loader.load(Config, path, overrides, _context(env, hostname))
    return _check_paths(cfg)


def config_from_mapping(
    raw: Mapping[str, Any],
    *,
    env: Mapping[str, str] | None = None,
    hostname: str | None = None,
) -> Config:
    """Validate an already-parsed TOML document (see :func:`load_config`)."""
    cfg: Config = loader.build(Config, raw, _context(env, hostname))
    return _check_paths(cfg)


def to_toml(cfg: Config) -> str:
    """The effective configuration as TOML (derived values omitted), e.g. for ``config``."""
    return loader.to_toml(cfg)


REFERENCE_INTRO = """
TOML, loaded once at start (and again on SIGHUP). Layering: built-in defaults <
the `--config` file < `--set SECTION.KEY=VALUE` overrides. Every key is
validated: an unknown key, a wrong type, an out-of-range value, a path or an
endpoint that can never work refuses the start with exit code 2 and one line
naming the key (or the file):

```
config error: device.baud: must be one of 4800, 9600, 19200, 38400, 57600, 115200, 230400, got 1234
```

`compass-bridge config --config FILE` checks a file and prints the configuration
in effect, each value with where it comes from (a parameter set over MAVLink and
stored wins over the file: "Parameters" below); `config/compass-bridge.toml` is
the commented example with every key at its default. Relative paths are relative to the working directory
(`/` under systemd): use absolute paths. Files the configuration names (the
signing key, the zenoh base configuration) must be regular files: a device, a
pipe or a directory is refused, never read. Strings may not hold NUL bytes;
ports and baud rates are ASCII digits; a host that looks like an IPv4 address
must be one (`999.1.1.1` is refused, not looked up in DNS).
"""


def reference_markdown() -> str:
    """The configuration reference (``docs/configuration.md``), from the declarations above."""
    from bridge.configkit.docs import render_reference

    return render_reference(Config, title="Configuration reference", intro=REFERENCE_INTRO) + "\n"
