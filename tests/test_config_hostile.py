"""Hostile and clumsy configurations: a clear error naming the file or key, at once.

Never a hang (devices, FIFOs), never unbounded memory, never a traceback, never a
value accepted that can only fail later in a worker thread.
"""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import pytest
from helpers import run_cli

from bridge.config import ConfigError, load_config, to_toml

ENV: dict[str, str] = {}


def refused(tmp_path: Path, text: str, *overrides: str) -> ConfigError:
    path = tmp_path / "c.toml"
    path.write_text(text)
    t0 = time.monotonic()
    with pytest.raises(ConfigError) as info:
        load_config(path, overrides, env=ENV, hostname="h")
    assert time.monotonic() - t0 < 5.0  # refused, not read until memory ran out
    assert "\n" not in str(info.value) and "\x00" not in str(info.value)
    return info.value


# --- files the configuration names ----------------------------------------------------------


@pytest.fixture
def specials(tmp_path: Path) -> dict[str, str]:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    (tmp_path / "dir").mkdir()
    (tmp_path / "big").write_bytes(b"a" * (2 << 20))
    return {
        "urandom": "/dev/urandom",
        "zero": "/dev/zero",
        "fifo": str(fifo),
        "dir": str(tmp_path / "dir"),
        "big": str(tmp_path / "big"),
    }


@pytest.mark.parametrize(
    ("which", "why"),
    [
        ("urandom", "character device"),
        ("zero", "character device"),
        ("fifo", "named pipe"),
        ("dir", "directory"),
        ("big", "byte limit"),
    ],
)
def test_signing_key_file_that_is_no_small_regular_file(
    tmp_path: Path, specials: dict[str, str], which: str, why: str
) -> None:
    """A device, a FIFO, a directory or a huge file: `config` and `run` once never returned
    (RSS grew ~170 MB/s)."""
    err = refused(tmp_path, f'[mavlink]\nsigning_key_file = "{specials[which]}"\n')
    assert err.key == "mavlink.signing_key_file"
    assert specials[which] in err.reason and why in err.reason


@pytest.mark.parametrize("which", ["zero", "fifo", "dir", "big"])
def test_config_file_that_is_no_small_regular_file(specials: dict[str, str], which: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(specials[which], env=ENV)
    assert info.value.key == specials[which] and "cannot read" in info.value.reason


@pytest.mark.parametrize("which", ["zero", "fifo", "dir"])
def test_zenoh_config_file_that_is_no_regular_file(
    tmp_path: Path, specials: dict[str, str], which: str
) -> None:
    err = refused(tmp_path, f'[zenoh]\nconfig_file = "{specials[which]}"\n')
    assert err.key == "zenoh.config_file" and specials[which] in err.reason


def test_signing_key_with_non_ascii_bytes(tmp_path: Path) -> None:
    (tmp_path / "key").write_bytes(b"\xff" * 64)
    err = refused(tmp_path, f'[mavlink]\nsigning_key_file = "{tmp_path / "key"}"\n')
    assert err.key == "mavlink.signing_key_file" and "non-ASCII" in err.reason


# --- the configuration file itself -------------------------------------------------------


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (b'[device]\nport = "/dev/tty\xff"\n', "not UTF-8 text: byte 0xff at offset 25"),
        ('[device]\nport = "sim"\n'.encode("utf-16"), "UTF-16"),
        (b"x = " + b"[" * 5000 + b"]" * 5000 + b"\n", "nested too deeply"),
        (b"a = " + b"{b = " * 3000 + b"1" + b"}" * 3000 + b"\n", "nested too deeply"),
    ],
    ids=["utf8", "utf16", "arrays", "tables"],
)
def test_file_level_errors_name_the_file(tmp_path: Path, data: bytes, why: str) -> None:
    """These once exited 1 with a bare codec / recursion message."""
    path = tmp_path / "c.toml"
    path.write_bytes(data)
    with pytest.raises(ConfigError) as info:
        load_config(path, env=ENV)
    assert info.value.key == str(path) and why in info.value.reason


def test_deeply_nested_override_names_the_key() -> None:
    with pytest.raises(ConfigError) as info:
        load_config(None, ["mavlink.endpoints=" + "[" * 5000 + "]" * 5000], env=ENV)
    assert info.value.key == "mavlink.endpoints"


def test_nul_in_the_config_path(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(str(tmp_path / "c") + "\x00.toml", env=ENV)
    assert "NUL" in info.value.reason and "\x00" not in str(info.value)


# --- values that can never work ------------------------------------------------------------


@pytest.mark.parametrize(
    ("line", "key"),
    [
        ('[storage]\ndir = "var\\u0000state"\n', "storage.dir"),
        ('[device]\nport = "/dev/ttyUSB0\\u0000"\n', "device.port"),
        ('[mavlink]\nendpoints = ["/dev/ttyACM0\\u0000,57600"]\n', "mavlink.endpoints[0]"),
        ('[zenoh]\nkey_prefix = "fleet/a\\u0000b"\n', "zenoh.key_prefix"),
        ('[zenoh]\nlisten = ["unixsock-stream//tmp/z\\u0000"]\n', "zenoh.listen[0]"),
        ('[zenoh]\nconfig_file = "/etc/z\\u0000.json5"\n', "zenoh.config_file"),
        ('[mavlink]\nsigning_key_file = "/etc/k\\u0000"\n', "mavlink.signing_key_file"),
        ('[sim]\nflash_file = "/tmp/f\\u0000"\n', "sim.flash_file"),
    ],
)
def test_nul_byte_in_any_string_is_refused(tmp_path: Path, line: str, key: str) -> None:
    """A NUL in storage.dir once killed the MAVLink dispatch thread later."""
    err = refused(tmp_path, line)
    assert err.key == key and "NUL" in err.reason


def test_nul_byte_through_an_override(tmp_path: Path) -> None:
    err = refused(tmp_path, "", "storage.dir=var\x00state")
    assert err.key == "storage.dir" and "NUL" in err.reason


@pytest.mark.parametrize(
    ("endpoint", "why"),
    [
        ("udpout:999.1.1.1:14550", "not a valid IPv4 address"),
        ("udpin:1.2.3.256:14550", "not a valid IPv4 address"),
        ("udp:10.1.2:14550", "not a valid IPv4 address"),
        ("tcp:host.123:5760", "not a valid IPv4 address"),
        ("udpout:127.0.0.1:\uff11\uff14\uff15\uff15\uff10", "not a number"),  # fullwidth
        ("udpout:127.0.0.1:\u0661\u0664\u0665\u0665\u0660", "not a number"),  # Arabic-Indic
        ("udpout:127.0.0.1:000014550", "not a number"),
        ("udpout:gcs.local\n:14550", "not an IP address or host name"),
        ("/dev/ttyACM0,\uff15\uff17\uff16\uff10\uff10", "serial baud"),
        ("/dev/ttyACM0,0", "serial baud"),
    ],
)
def test_mavlink_endpoints_that_can_never_work(tmp_path: Path, endpoint: str, why: str) -> None:
    """999.1.1.1 once went to DNS at run time and retried forever."""
    err = refused(tmp_path, "", f'mavlink.endpoints=["{endpoint}"]'.replace("\n", "\\n"))
    assert err.key == "mavlink.endpoints[0]" and why in err.reason, err


@pytest.mark.parametrize(
    "endpoint", ["tcp/999.1.1.1:7447", "udp/127.0.0.1:\uff17\uff14\uff14\uff17"]
)
def test_zenoh_endpoints_that_can_never_work(tmp_path: Path, endpoint: str) -> None:
    err = refused(tmp_path, f'[zenoh]\nconnect = ["{endpoint}"]\n')
    assert err.key == "zenoh.connect[0]"


def test_good_hosts_still_pass(tmp_path: Path) -> None:
    eps = [
        "udpout:192.168.1.10:14550",
        "udpout:gcs-1.example.org:14550",
        "udpout:10a.example:14550",
        "tcp:[fe80::1]:5760",
        "/dev/ttyACM0,921600",
    ]
    listed = ", ".join(f'"{e}"' for e in eps)
    cfg = load_config(None, [f"mavlink.endpoints=[{listed}]"], env=ENV)
    assert cfg.mavlink.endpoints == tuple(eps)


def test_fullwidth_baud_is_not_an_integer(tmp_path: Path) -> None:
    err = refused(tmp_path, "", "device.baud=\uff11\uff11\uff15\uff12\uff10\uff10")
    assert err.key == "device.baud" and "must be a integer" in err.reason


def test_paths_that_exist_as_the_wrong_kind(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")
    (tmp_path / "d").mkdir()
    assert refused(tmp_path, f'[storage]\ndir = "{tmp_path / "file"}"\n').key == "storage.dir"
    assert refused(tmp_path, f'[device]\nport = "{tmp_path / "d"}"\n').key == "device.port"
    err = refused(tmp_path, f'[sim]\nflash_file = "{tmp_path / "d"}"\n')
    assert err.key == "sim.flash_file" and "not a regular file" in err.reason
    err = refused(tmp_path, f'[sim]\nflash_file = "{tmp_path / "nodir" / "f"}"\n')
    assert err.key == "sim.flash_file" and "does not exist" in err.reason
    fifo = tmp_path / "rec"
    os.mkfifo(fifo)
    err = refused(tmp_path, f'[device]\nport = "replay:{fifo}"\n')
    assert err.key == "device.port" and "not a file" in err.reason
    # ... while what is fine stays fine: a missing state dir is created later.
    cfg = load_config(
        None,
        [f"storage.dir={tmp_path / 'new'}", f"sim.flash_file={tmp_path / 'flash.json'}"],
        env=ENV,
    )
    assert cfg.storage.dir == str(tmp_path / "new")


def test_effective_toml_escapes_what_toml_needs(tmp_path: Path) -> None:
    odd = 'a"b\\c\x7fd\te\u00e9'
    cfg = load_config(None, [f"storage.dir={odd}", "zenoh.key_prefix=fleet/\u00e9t\u00e9"], env=ENV)
    path = tmp_path / "again.toml"
    path.write_text(to_toml(cfg), encoding="utf-8")
    assert load_config(path, env=ENV) == cfg


# --- through the command line: exit 2, one line, at once ------------------------------------


def _cli(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return run_cli(tmp_path, *args, timeout=60)


@pytest.mark.integration
@pytest.mark.parametrize("command", ["config", "run"])
@pytest.mark.integration
def test_cli_refuses_a_device_as_signing_key(tmp_path: Path, command: str) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text('[device]\nport = "sim"\n[mavlink]\nsigning_key_file = "/dev/urandom"\n')
    res = _cli(tmp_path, command, "--config", str(cfg))
    assert res.returncode == 2
    assert res.stderr.strip() == (
        "config error: mavlink.signing_key_file: /dev/urandom: "
        "a character device, not a regular file"
    )
    assert res.stdout == ""


@pytest.mark.integration
@pytest.mark.parametrize(
    ("data", "why"),
    [
        (None, "cannot read: a character device, not a regular file"),
        (b"\xff\xfe[\x00", "not UTF-8 text"),
        (b"x = " + b"[" * 5000 + b"]" * 5000, "nested too deeply"),
    ],
)
@pytest.mark.integration
def test_cli_file_level_errors_exit_2_in_one_line(
    tmp_path: Path, data: bytes | None, why: str
) -> None:
    path = "/dev/zero"
    if data is not None:
        (tmp_path / "c.toml").write_bytes(data)
        path = str(tmp_path / "c.toml")
    res = _cli(tmp_path, "run", "--config", path)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"config error: {path}: "), lines
    assert why in lines[0] and "Traceback" not in res.stderr


@pytest.mark.integration
def test_cli_bad_endpoint_exits_2_naming_the_key(tmp_path: Path) -> None:
    res = _cli(tmp_path, "config", "--set", 'mavlink.endpoints=["udpout:999.1.1.1:14550"]')
    assert res.returncode == 2
    assert res.stderr.startswith("config error: mavlink.endpoints[0]: ")
    assert "not a valid IPv4 address" in res.stderr and len(res.stderr.splitlines()) == 1


@pytest.mark.integration
@pytest.mark.parametrize("feed", ["px4_odometry", "ardupilot_vision"])
@pytest.mark.integration
def test_a_heading_feed_is_not_refused_for_ids_the_autopilot_may_not_have(
    tmp_path: Path, feed: str
) -> None:
    """ArduPilot drops only what carries its own system *and* component id, and which ids
    the autopilot has is known only when it is heard (the output then withholds the feed:
    test_autopilot_ardupilot.py): no configuration is refused for it at start."""
    cfg = tmp_path / "feed.toml"
    for extra in ("", "system_id = 2", 'role = "companion"', "component_id = 42"):
        cfg.write_text(f'[mavlink]\nheading_feed = "{feed}"\n{extra}\n')
        r = _cli(tmp_path, "config", "--config", str(cfg))
        assert r.returncode == 0, r.stderr
