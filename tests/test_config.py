"""Configuration contract: defaults, layering, and a refusal naming the key for every bad input."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from bridge.config import (
    Config,
    ConfigError,
    LocationConfig,
    load_config,
    parse_mavlink_endpoint,
    section_types,
    settings_of,
    to_toml,
)

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "config" / "compass-bridge.toml"
# The configuration reference, generated from the declarations (tests/test_config_docs.py
# keeps it fresh); it replaced the README's former hand-kept table.
REFERENCE = REPO / "docs" / "configuration.md"
ENV: dict[str, str] = {}  # no $STATE_DIRECTORY unless a test sets one


def load_text(tmp_path: Path, text: str, *overrides: str, hostname: str = "boat7") -> Config:
    path = tmp_path / "c.toml"
    path.write_text(text)
    return load_config(path, overrides, env=ENV, hostname=hostname)


def refused(tmp_path: Path, text: str, *overrides: str) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        load_text(tmp_path, text, *overrides)
    return info.value


# --- defaults -----------------------------------------------------------------


def test_defaults_without_a_file() -> None:
    cfg = load_config(None, env=ENV, hostname="boat7")
    assert cfg.device.port == "/dev/ttyUSB0"
    assert cfg.device.baud == 115200  # the datasheet's default
    assert cfg.device.protocol == "gmr"
    assert cfg.device.rate_hz == 10  # the device's power-up rate
    assert cfg.device.stale_after == 2.0
    assert cfg.mavlink.endpoints == ("udpout:127.0.0.1:14550",)
    assert (cfg.mavlink.system_id, cfg.mavlink.component_id) == (1, 1)
    assert cfg.mavlink.signing_key is None
    assert cfg.zenoh.enabled and cfg.zenoh.mode == "peer"
    assert cfg.zenoh.connect == () and cfg.zenoh.listen == ()
    assert cfg.zenoh.key_prefix == "fleet/boat7/compass"
    assert cfg.storage.dir == "/var/lib/compass-bridge"
    assert cfg.location is None
    assert cfg.sim.seed == 1


def test_storage_dir_from_state_directory() -> None:
    env = {"STATE_DIRECTORY": "/run/state/a:/run/state/b"}
    assert load_config(None, env=env).storage.dir == "/run/state/a"
    explicit = load_config(None, ["storage.dir=/srv/cb"], env=env)
    assert explicit.storage.dir == "/srv/cb"


def test_hostname_substitution_and_literal_prefix(tmp_path: Path) -> None:
    cfg = load_text(tmp_path, '[zenoh]\nkey_prefix = "a/<hostname>/b/<hostname>"\n', hostname="h1")
    assert cfg.zenoh.key_prefix == "a/h1/b/h1"
    assert load_text(tmp_path, '[zenoh]\nkey_prefix = "x/y"\n').zenoh.key_prefix == "x/y"


def test_hostname_that_breaks_the_key_expression_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_text(tmp_path, "", hostname="bad*host")
    assert info.value.key == "zenoh.key_prefix" and "host name" in info.value.reason


# --- layering -------------------------------------------------------------------


def test_file_overrides_defaults_and_set_overrides_file(tmp_path: Path) -> None:
    text = '[device]\nport = "sim"\nbaud = 9600\n[sim]\nseed = 5\n'
    cfg = load_text(tmp_path, text)
    assert (cfg.device.port, cfg.device.baud, cfg.sim.seed) == ("sim", 9600, 5)
    assert cfg.device.protocol == "gmr"  # untouched keys keep their defaults
    cfg = load_text(
        tmp_path,
        text,
        "device.baud=57600",
        "device.port=/dev/ttyS3",
        "zenoh.enabled=false",
        'zenoh.connect=["tcp/10.0.0.2:7447"]',
        "location.latitude=52.5",
        "location.longitude=-4",
    )
    assert (cfg.device.baud, cfg.device.port) == (57600, "/dev/ttyS3")
    assert cfg.zenoh.enabled is False
    assert cfg.zenoh.connect == ("tcp/10.0.0.2:7447",)
    assert cfg.location == LocationConfig(latitude=52.5, longitude=-4.0, altitude_m=0.0)
    assert cfg.sim.seed == 5


def test_override_of_a_string_key_keeps_the_text(tmp_path: Path) -> None:
    # "0042" would parse as TOML integer 42 (invalid TOML in fact); a str key keeps the text.
    cfg = load_text(tmp_path, "", "storage.dir=0042")
    assert cfg.storage.dir == "0042"


@pytest.mark.parametrize("bad", ["device.baud", "devicebaud=1", "a.b.c=1", ".x=1"])
def test_malformed_override(tmp_path: Path, bad: str) -> None:
    err = refused(tmp_path, "", bad)
    assert "SECTION.KEY=VALUE" in err.reason


def test_override_errors_name_the_key(tmp_path: Path) -> None:
    err = refused(tmp_path, "", "device.rate_hz=7")
    assert err.key == "device.rate_hz"
    assert str(err) == "device.rate_hz: must be one of 1, 2, 5, 10, 20, 50, 100, got 7"


# --- refusals: each names the key and the reason --------------------------------


@pytest.mark.parametrize(
    ("text", "key", "reason"),
    [
        # unknown key at each level
        ("colour = 1\n", "colour", "unknown section"),
        ("[devices]\n", "devices", "unknown section (did you mean 'device'?)"),
        ("[device]\nbuad = 9600\n", "device.buad", "unknown key (did you mean 'baud'?)"),
        ("[mavlink]\nsysid = 1\n", "mavlink.sysid", "unknown key"),
        ("[zenoh]\nmodes = 'peer'\n", "zenoh.modes", "unknown key"),
        ("[storage]\npath = '/x'\n", "storage.path", "unknown key"),
        ("[location]\nlat = 1\n", "location.lat", "unknown key"),
        ("[sim]\nmotion = 'x'\nseedz = 2\n", "sim.", "unknown key"),
        # a section that is not a table
        ("device = 3\n", "device", "must be a table [device], got integer"),
        # wrong type
        ("[device]\nbaud = '9600'\n", "device.baud", "must be a integer, got string"),
        ("[device]\nbaud = 9600.0\n", "device.baud", "must be a integer, got number"),
        ("[device]\nport = 3\n", "device.port", "must be a string, got integer"),
        ("[device]\nstale_after = true\n", "device.stale_after", "must be a number, got boolean"),
        ("[device]\nstale_after = nan\n", "device.stale_after", "must be a finite number"),
        ("[zenoh]\nenabled = 1\n", "zenoh.enabled", "must be a boolean, got integer"),
        ("[zenoh]\nconnect = 'tcp/a:1'\n", "zenoh.connect", "must be a list of strings"),
        ("[zenoh]\nlisten = ['tcp/a:1', 2]\n", "zenoh.listen[1]", "must be a string"),
        # out of range / not one of
        ("[device]\nbaud = 1234\n", "device.baud", "must be one of 4800, 9600, 19200"),
        ("[device]\nprotocol = 'nmea2000'\n", "device.protocol", 'one of "gmr", "nmea", "os5000"'),
        ("[device]\nrate_hz = 3\n", "device.rate_hz", "got 3"),
        ("[device]\nstale_after = 0\n", "device.stale_after", "must be in (0, 60], got 0"),
        ("[device]\nstale_after = 61\n", "device.stale_after", "must be in (0, 60], got 61"),
        (
            "[device]\nrate_hz = 1\nstale_after = 1.5\n",
            "device.stale_after",
            "at least two frame periods",
        ),
        ("[mavlink]\nsystem_id = 0\n", "mavlink.system_id", "must be in [1, 255], got 0"),
        ("[mavlink]\ncomponent_id = 256\n", "mavlink.component_id", "got 256"),
        ("[zenoh]\nmode = 'router'\n", "zenoh.mode", 'must be one of "peer", "client"'),
        ("[location]\nlatitude = 91\nlongitude = 0\n", "location.latitude", "[-90, 90]"),
        ("[location]\nlatitude = 1\nlongitude = -181\n", "location.longitude", "[-180, 180]"),
        (
            "[location]\nlatitude = 1\nlongitude = 2\naltitude_m = -5000\n",
            "location.altitude_m",
            "",
        ),
        ("[sim]\nseed = -1\n", "sim.seed", "got -1"),
        ("[sim]\nshake_g = 0.6\n", "sim.shake_g", "must be in [0, 0.5], got 0.6"),
        ("[sim]\nshake_g = -0.01\n", "sim.shake_g", "got -0.01"),
        # location is all-or-nothing
        ("[location]\nlatitude = 10\n", "location.longitude", "required when [location]"),
        ("[location]\naltitude_m = 10\n", "location.latitude", "required when [location]"),
        # device port shape
        ("[device]\nport = 'ttyUSB0'\n", "device.port", "absolute device path"),
        ("[device]\nport = 'replay:'\n", "device.port", "needs a recording path"),
        ("[device]\nport = 'replay:/nonexistent/r.bin'\n", "device.port", "does not exist"),
        # zenoh key expression
        ("[zenoh]\nkey_prefix = 'a/**'\n", "zenoh.key_prefix", "must be concrete"),
        ("[zenoh]\nkey_prefix = '/a/b'\n", "zenoh.key_prefix", "leading/trailing"),
        ("[zenoh]\nkey_prefix = 'a//b'\n", "zenoh.key_prefix", "empty chunks"),
        ("[zenoh]\nkey_prefix = 'a/<host>/b'\n", "zenoh.key_prefix", "only placeholder"),
    ],
)
def test_refusal_names_key_and_reason(tmp_path: Path, text: str, key: str, reason: str) -> None:
    err = refused(tmp_path, text)
    assert err.key.startswith(key), err
    assert reason in err.reason, err
    assert str(err) == f"{err.key}: {err.reason}"


@pytest.mark.parametrize(
    ("endpoint", "why"),
    [
        ("udpout:127.0.0.1", "HOST:PORT"),
        ("udpout:127.0.0.1:0", "[1, 65535]"),
        ("udpin:0.0.0.0:70000", "[1, 65535]"),
        ("tcp:bad_host!:5760", "not an IP address or host name"),
        ("udpbcast:1.2.3.4:14550", "not a MAVLink endpoint"),
        ("ttyACM0", "not a MAVLink endpoint"),
        ("/dev/ttyACM0,fast", "baud"),
        ("", "not a MAVLink endpoint"),
    ],
)
def test_bad_mavlink_endpoint(tmp_path: Path, endpoint: str, why: str) -> None:
    text = f'[mavlink]\nendpoints = ["udp:127.0.0.1:14551", "{endpoint}"]\n'
    err = refused(tmp_path, text)
    assert err.key == "mavlink.endpoints[1]" and why in err.reason


def test_good_mavlink_endpoints_parse(tmp_path: Path) -> None:
    eps = [
        "udpout:127.0.0.1:14550",
        "udpin:0.0.0.0:14551",
        "udp:gcs.local:14552",
        "tcp:[::1]:5760",
        "tcpin:0.0.0.0:5761",
        "/dev/ttyAMA0,921600",
        "/dev/serial/by-id/usb-FTDI-if00",
    ]
    toml_list = ", ".join(f'"{e}"' for e in eps)
    cfg = load_text(tmp_path, f"[mavlink]\nendpoints = [{toml_list}]\n")
    parsed = cfg.mavlink.parsed_endpoints
    assert [p.kind for p in parsed] == [
        "udpout",
        "udpin",
        "udp",
        "tcp",
        "tcpin",
        "serial",
        "serial",
    ]
    assert (parsed[2].host, parsed[2].port) == ("gcs.local", 14552)
    assert (parsed[3].host, parsed[3].port) == ("::1", 5760)
    assert (parsed[5].device, parsed[5].baud) == ("/dev/ttyAMA0", 921600)
    assert parsed[6].baud is None
    assert parse_mavlink_endpoint("udpout:10.1.2.3:9").text == "udpout:10.1.2.3:9"


@pytest.mark.parametrize(
    "endpoint", ["tcp/localhost", "tcpx/1.2.3.4:7447", "1.2.3.4:7447", "udp/1.2.3.4:0"]
)
def test_bad_zenoh_endpoint(tmp_path: Path, endpoint: str) -> None:
    err = refused(tmp_path, f'[zenoh]\nconnect = ["{endpoint}"]\n')
    assert err.key == "zenoh.connect[0]"


def test_good_zenoh_endpoints(tmp_path: Path) -> None:
    eps = ["tcp/127.0.0.1:7447", "udp/[ff02::1]:7447", "quic/router.example:7447#iface=eth0"]
    toml_list = ", ".join(f'"{e}"' for e in eps)
    cfg = load_text(tmp_path, f"[zenoh]\nlisten = [{toml_list}]\nmode = 'client'\n")
    assert cfg.zenoh.listen == tuple(eps) and cfg.zenoh.mode == "client"


# --- signing key ------------------------------------------------------------------


def test_signing_key_is_read_at_load(tmp_path: Path) -> None:
    key = bytes(range(32))
    (tmp_path / "key").write_text(key.hex().upper() + "\n")
    cfg = load_text(tmp_path, f'[mavlink]\nsigning_key_file = "{tmp_path / "key"}"\n')
    assert cfg.mavlink.signing_key == key


@pytest.mark.parametrize(
    ("content", "why"),
    [
        (None, "does not exist"),
        ("ab" * 31, "exactly 64 hex characters"),
        ("ab" * 33, "exactly 64 hex characters"),
        ("zz" * 32, "exactly 64 hex characters"),
        ("", "found 0 characters"),
    ],
)
def test_bad_signing_key_file(tmp_path: Path, content: str | None, why: str) -> None:
    path = tmp_path / "key"
    if content is not None:
        path.write_text(content)
    err = refused(tmp_path, f'[mavlink]\nsigning_key_file = "{path}"\n')
    assert err.key == "mavlink.signing_key_file" and why in err.reason


def test_unreadable_or_invalid_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.toml")
    err = refused(tmp_path, "[device\nport = 1\n")
    assert err.key.endswith("c.toml") and "not valid TOML" in err.reason


def test_replay_port_accepts_an_existing_recording(tmp_path: Path) -> None:
    rec = tmp_path / "run.rec"
    rec.write_bytes(b"")
    assert load_text(tmp_path, f'[device]\nport = "replay:{rec}"\n').device.port == f"replay:{rec}"


def test_heading_only_protocol_skips_the_frame_period_check(tmp_path: Path) -> None:
    # rate_hz is only asked of a gmr device; an NMEA compass streams at its own rate.
    cfg = load_text(tmp_path, "[device]\nprotocol = 'nmea'\nrate_hz = 1\nstale_after = 0.5\n")
    assert cfg.device.stale_after == 0.5


def test_config_is_frozen() -> None:
    cfg = load_config(None, env=ENV)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.device.baud = 9600  # type: ignore[misc]  # frozen: the assignment is the test


def test_effective_toml_round_trips(tmp_path: Path) -> None:
    cfg = load_text(tmp_path, "", "location.latitude=1.5", "location.longitude=2", "sim.seed=9")
    again = load_text(tmp_path, to_toml(cfg))
    assert again == cfg


# --- the shipped example cannot drift ------------------------------------------------


def _example_keys(text: str) -> set[str]:
    """section.key for every key line in the file, commented out or not."""
    keys: set[str] = set()
    section = ""
    for line in text.splitlines():
        m = re.match(r"^#?\s*\[(\w+)\]\s*$", line)
        if m:
            section = m.group(1)
            continue
        m = re.match(r"^#? ?(\w+) = ", line)
        if m and section:
            keys.add(f"{section}.{m.group(1)}")
    return keys


def _declared_keys() -> set[str]:
    return {f"{s}.{f.name}" for s, cls in section_types().items() for f in settings_of(cls)}


def test_example_file_validates_and_lists_every_key(tmp_path: Path) -> None:
    text = EXAMPLE.read_text()
    cfg = load_config(EXAMPLE, env=ENV, hostname="boat7")
    assert cfg == load_config(None, env=ENV, hostname="boat7")  # it documents the defaults
    assert _example_keys(text) == _declared_keys()
    # The commented-out optional [location] must validate too once uncommented.
    uncommented = re.sub(r"(?m)^# (\[\w+\]$|\w+ = )", r"\1", text)
    cfg2 = load_text(tmp_path, uncommented)
    assert cfg2.location is not None


def test_reference_documents_every_key() -> None:
    reference = REFERENCE.read_text()
    missing = [k for k in sorted(_declared_keys()) if f"`{k}`" not in reference]
    assert not missing, f"docs/configuration.md lacks {missing}"
