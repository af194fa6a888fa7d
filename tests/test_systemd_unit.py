"""The shipped systemd files: the unit passes systemd 252's own checks, has what the
service needs, starts a command line the CLI accepts; the sysusers file makes the service
user.

Needs systemd-analyze and systemd-sysusers (Debian: ``apt-get install systemd``; CI installs
them itself).
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

from bridge.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
SYSTEMD = ROOT / "systemd"
UNIT = SYSTEMD / "compass-bridge.service"
SYSUSERS = SYSTEMD / "sysusers.d" / "compass-bridge.conf"
UDEV = SYSTEMD / "udev" / "99-compass-bridge.rules"
CHECK = SYSTEMD / "check-unit"
INSTALLED = "/opt/compass-bridge/venv/bin/compass-bridge"


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.fail(f"{name} is needed (Debian: apt-get install systemd)")
    return path


def _binary() -> Path:
    # The console script of the package under test, in the same environment as this Python.
    b = Path(sys.executable).parent / "compass-bridge"
    assert b.exists(), f"{b} missing: install the package (pip install .)"
    return b


def _parse(path: Path) -> dict[str, dict[str, list[str]]]:
    """Sections -> key -> values (keys may repeat), comments and continuations handled."""
    out: dict[str, dict[str, list[str]]] = defaultdict(lambda: defaultdict(list))
    section = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
            continue
        key, _, value = line.partition("=")
        out[section][key.strip()].append(value.strip())
    return out


def _check(unit: Path, *env: str) -> subprocess.CompletedProcess[str]:
    _tool("systemd-analyze")
    return subprocess.run(
        ["env", *env, "bash", str(CHECK), str(unit), str(_binary())],
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.integration
def test_unit_passes_verify_and_security_score() -> None:
    r = _check(UNIT)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "verify: clean" in r.stdout
    exposure = re.search(r"security exposure ([0-9.]+)", r.stdout)
    assert exposure is not None, r.stdout
    score = float(exposure.group(1))
    assert score <= 2.0


@pytest.mark.integration
def test_check_fails_on_a_bad_unit(tmp_path: Path) -> None:
    """The CI check can fail: an unknown directive, or a weaker sandbox, is caught."""
    bad = tmp_path / "compass-bridge.service"
    bad.write_text(UNIT.read_text().replace("[Service]\n", "[Service]\nNoSuchDirective=yes\n"))
    r = _check(bad)
    assert r.returncode != 0 and "NoSuchDirective" in r.stderr
    weak = tmp_path / "weak" / "compass-bridge.service"
    weak.parent.mkdir()
    text = "\n".join(
        ln
        for ln in UNIT.read_text().splitlines()
        if not ln.startswith(("SystemCallFilter", "ProtectSystem", "CapabilityBoundingSet"))
    )
    weak.write_text(text + "\n")
    r = _check(weak)
    assert r.returncode != 0 and "is over 2.0" in r.stderr


def test_unit_has_what_the_service_needs() -> None:
    u = _parse(UNIT)
    unit, svc = u["Unit"], u["Service"]
    assert unit["StartLimitIntervalSec"] == ["0"]
    for drv in ("usbserial", "cdc_acm"):
        assert f"modprobe@{drv}.service" in " ".join(unit["Wants"])
        assert f"modprobe@{drv}.service" in " ".join(unit["After"])
    assert svc["Type"] == ["notify"] and svc["NotifyAccess"] == ["main"]
    assert svc["Restart"] == ["on-failure"]
    assert svc["WatchdogSec"] and svc["StateDirectory"] == ["compass-bridge"]
    assert svc["ConfigurationDirectory"] == ["compass-bridge"]
    assert svc["ExecReload"] == ["/bin/kill -HUP $MAINPID"]
    assert svc["DevicePolicy"] == ["closed"]
    allowed = {v.split()[0] for v in svc["DeviceAllow"]}
    assert {"char-ttyUSB", "char-ttyACM", "char-ttyS"} <= allowed
    assert svc["ProtectSystem"] == ["strict"] and svc["NoNewPrivileges"] == ["yes"]
    families = set(" ".join(svc["RestrictAddressFamilies"]).split())
    assert families == {"AF_UNIX", "AF_INET", "AF_INET6", "AF_NETLINK"}
    # WatchdogSec must leave room for the daemon's own hang detection (4 s) + ping period.
    assert float(svc["WatchdogSec"][0].rstrip("s")) >= 8.0
    # The daemon exits by itself 5 s after SIGTERM; systemd must not SIGKILL it first.
    assert float(svc["TimeoutStopSec"][0].rstrip("s")) > 5.0


def test_exec_start_is_a_command_line_the_cli_accepts() -> None:
    (exec_start,) = _parse(UNIT)["Service"]["ExecStart"]
    argv = shlex.split(exec_start)
    assert argv[0] == INSTALLED
    args, rest = build_parser().parse_known_args(argv[1:])
    assert not rest and args.command == "run" and not args.simulate
    assert args.config == "/etc/compass-bridge/compass-bridge.toml"
    assert (ROOT / "config" / "compass-bridge.toml").exists()  # what gets installed there


@pytest.mark.integration
def test_sysusers_makes_a_service_user_in_dialout(tmp_path: Path) -> None:
    tool = _tool("systemd-sysusers")
    etc = tmp_path / "etc"
    etc.mkdir()
    (etc / "passwd").write_text("root:x:0:0:root:/root:/bin/sh\n")
    (etc / "group").write_text("root:x:0:\ndialout:x:20:\n")
    r = subprocess.run(
        [tool, f"--root={tmp_path}", str(SYSUSERS)], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0, r.stderr
    user = _parse(UNIT)["Service"]["User"][0]
    (pw,) = [
        ln.split(":")
        for ln in (etc / "passwd").read_text().splitlines()
        if ln.startswith(user + ":")
    ]
    assert int(pw[2]) < 1000  # a system user
    assert pw[5] == "/var/lib/compass-bridge" and pw[6] == "/usr/sbin/nologin"
    groups = {ln.split(":")[0]: ln.split(":")[3] for ln in (etc / "group").read_text().splitlines()}
    assert user in groups["dialout"].split(",")


def test_udev_rule_gives_the_stable_name_to_the_service_group() -> None:
    rules = [ln for ln in UDEV.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    assert len(rules) == 1
    pairs = re.findall(r'([A-Z_]+(?:\{[^}]+\})?)\s*(==|\+=|=)\s*"([^"]*)"', rules[0])
    assert ", ".join(f'{k}{op}"{v}"' for k, op, v in pairs) == rules[0].strip()  # nothing else
    d = {(k, op): v for k, op, v in pairs}
    assert d[("SUBSYSTEM", "==")] == "tty"
    assert d[("SYMLINK", "+=")] == "compass"
    assert d[("GROUP", "=")] == "dialout" and d[("MODE", "=")] == "0660"
    assert d[("ENV{ID_MM_DEVICE_IGNORE}", "=")] == "1"
