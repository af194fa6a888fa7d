"""docs/service.md's recipes, run as written: the signing key, the dry run on the simulator."""

from __future__ import annotations

import grp
import os
import re
import shlex
import stat
import subprocess
from pathlib import Path

import pytest
from helpers import run_cli
from service_harness import DaemonProcess, FakeServiceManager, free_port, free_udp_port

REPO = Path(__file__).resolve().parents[1]
DOC = (REPO / "docs" / "service.md").read_text()
UNIT = (REPO / "systemd" / "compass-bridge.service").read_text()


def _section(title: str) -> str:
    start = DOC.index(f"## {title}")
    end = DOC.find("\n## ", start + 1)
    return DOC[start : end if end >= 0 else None]


def _code(section: str, lang: str) -> str:
    m = re.search(rf"```{lang}\n(.*?)```", section, re.S)
    assert m is not None, f"no ```{lang} block in:\n{section}"
    return m.group(1)


def _config(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return run_cli(tmp_path, "config", *args, timeout=60)


@pytest.mark.integration
def test_the_signing_key_recipe_makes_a_0640_key_the_bridge_takes(tmp_path: Path) -> None:
    """The two lines, in a scratch directory instead of /etc/compass-bridge/, without sudo
    and with this user's group for compass-bridge (which need not exist here)."""
    script = _code(_section("A MAVLink signing key"), "sh")
    group = grp.getgrgid(os.getgid()).gr_name
    owner = "root" if os.getuid() == 0 else str(os.getuid())
    script = (
        script.replace("/etc/compass-bridge/", f"{tmp_path}/")
        .replace("sudo ", "")
        .replace("-o root -g compass-bridge", f"-o {shlex.quote(owner)} -g {shlex.quote(group)}")
    )
    res = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", script],
        capture_output=True,
        text=True,
        timeout=30,
        preexec_fn=lambda: os.umask(0o022),  # a usual umask: the recipe must not depend on it
    )
    assert res.returncode == 0, res.stderr
    key = tmp_path / "mavlink.key"
    st = key.stat()
    assert stat.S_IMODE(st.st_mode) == 0o640, oct(st.st_mode)
    assert st.st_gid == os.getgid()
    assert re.fullmatch(r"[0-9a-f]{64}", key.read_text())
    ok = _config(tmp_path, "--set", f"mavlink.signing_key_file={key}")
    assert ok.returncode == 0, ok.stderr
    assert "signing_key_file" not in ok.stderr  # no warning for a well-kept key
    key.chmod(0o644)  # what the old recipe made
    loose = _config(tmp_path, "--set", f"mavlink.signing_key_file={key}")
    assert loose.returncode == 0
    assert "readable by everyone (mode 0644): chmod 0640" in loose.stderr


@pytest.mark.integration
def test_the_dry_run_on_the_simulator_runs_as_the_unit_would(
    tmp_path: Path, manager: FakeServiceManager
) -> None:
    """The example configuration with the dry run's [device] port = "sim", started with the
    unit's own arguments: READY, a STATUS saying it streams uncalibrated, the WARNING."""
    toml = _code(_section("A dry run before the compass arrives"), "toml")
    assert toml.strip() == '[device]\nport = "sim"'
    example = (REPO / "config" / "compass-bridge.toml").read_text()
    cfg_text = example.replace('port = "/dev/ttyUSB0"', 'port = "sim"', 1)
    assert cfg_text != example
    # loopback ports of this test's own (the example sends to 14550, listens on 7447)
    cfg_text = cfg_text.replace("udpout:127.0.0.1:14550", f"udpout:127.0.0.1:{free_udp_port()}")
    cfg_text = re.sub(r"(?m)^listen = \[\]", f'listen = ["tcp/127.0.0.1:{free_port()}"]', cfg_text)
    cfg = tmp_path / "compass-bridge.toml"
    cfg.write_text(cfg_text)
    # ExecStart's arguments between the program and "run --config"
    exec_start = re.search(r"(?m)^ExecStart=(\S+) (.*) run --config (\S+)$", UNIT)
    assert exec_start is not None, "ExecStart is not '<program> [options] run --config FILE'"
    args = exec_start.group(2).split()
    env = dict(os.environ, STATE_DIRECTORY=str(tmp_path / "state"))  # StateDirectory=
    d = DaemonProcess(cfg, manager, tmp_path / "daemon.log", env=env, args=args)
    try:
        i, _ = manager.wait_for(lambda m: "READY" in m, proc=d)
        _, st = manager.wait_for(
            lambda m: re.match(r"streaming sim at .*; hdg", m.get("STATUS") or "") is not None,
            after=i,
            proc=d,
        )
        status = st.get("STATUS") or ""
        assert re.search(r"; hdg \d+\.\d mag; calibration none \(identity\), UNCALIBRATED", status)
        log = d.wait_log("WARNING")
        assert re.search(r"WARNING bridge\.daemon\.wiring: calibration: none in .*state", log), log
    finally:
        assert d.stop() == 0
