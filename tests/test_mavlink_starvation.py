"""A signed ground station is never starved by traffic it did not send.

A real ``compass-bridge run`` (subprocess) on the simulated compass (pty), signing on,
``udpin`` and ``tcpin``. A signed ground station on ``udpin`` sends one HEARTBEAT a
second and counts the ATTITUDE it gets. Then, from another process, 1 000 datagrams a
second, each from a port of its own -- random junk, unsigned HEARTBEATs, HEARTBEATs signed
with another key, replays of the ground station's own packets -- and 50 TCP clients that
connect and never send nor read. The ground station's ATTITUDE stays at its set rate
(>= 95 %), and a new TCP client is still served within 5 s.

The rate is counted on the bridge's own clock (ATTITUDE.time_boot_ms), so what is measured
is what the bridge sent, not how promptly this loaded test process read it.
"""

from __future__ import annotations

import socket
import subprocess
import time
from pathlib import Path

import pytest
from mavlink_clients import signed_mav
from service_harness import (
    DaemonProcess,
    free_port,
    free_udp_port,
    toml_config,
    wait_for,
)

from benchmarks.fuzz_hostile import (
    Gcs,
    end_attack,
    heartbeat,
    idle_clients,
    in_window,
    start_flood,
)
from bridge.sim.firmware import make_firmware
from bridge.sim.pty import PtyCompass

pytestmark = pytest.mark.integration

KEY = bytes.fromhex("5a" * 32)
ATT_HZ = 10.0  #: BRG_SR_ATT's default
WINDOW_MS = 8000
JUNK_PER_S = 1000
IDLE_TCP = 50


def rate_in_window(stamps: list[int], start_ms: int) -> float:
    return in_window(stamps, start_ms, WINDOW_MS) / (WINDOW_MS / 1000)


def test_junk_from_1000_ports_and_50_idle_tcp_clients_leave_the_gcs_its_attitude(
    tmp_path: Path,
) -> None:
    udp, tcp = free_udp_port(), free_port()
    key_file = tmp_path / "mavlink.key"
    key_file.write_text(KEY.hex() + "\n")
    with PtyCompass(make_firmware(31), tmp_path / "compass") as sim:
        cfg = tmp_path / "bridge.toml"
        text = toml_config(
            str(sim.link_path),
            tmp_path / "state",
            mavlink=[f"udpin:127.0.0.1:{udp}", f"tcpin:127.0.0.1:{tcp}"],
            rate_hz=20,
        )
        cfg.write_text(text.replace("[mavlink]\n", f'[mavlink]\nsigning_key_file = "{key_file}"\n'))
        d = DaemonProcess(cfg, None, tmp_path / "daemon.log", watchdog_usec=None)
        gcs = Gcs(udp, KEY)
        idle: list[socket.socket] = []
        flood: subprocess.Popen[str] | None = None
        try:
            wait_for(lambda: len(gcs.attitude_boot_ms()) >= 20, "ATTITUDE at the signed GCS")
            # What an attacker has: junk, its own packets, and copies of the GCS's.
            flood = start_flood(udp, JUNK_PER_S, 14, gcs.sent[:3])
            idle += idle_clients(tcp, IDLE_TCP)
            time.sleep(2.0)  # the flood is on, the crowd connected
            start_ms = max(gcs.attitude_boot_ms())
            # A newcomer on tcpin, meanwhile, is served within 5 s.
            t0 = time.monotonic()
            with socket.create_connection(("127.0.0.1", tcp), timeout=10.0) as c:
                c.sendall(heartbeat(signed_mav(KEY, 250, 3)))
                c.settimeout(10.0)
                assert c.recv(4096)
            served_s = time.monotonic() - t0
            wait_for(
                lambda: max(gcs.attitude_boot_ms()) >= start_ms + WINDOW_MS, "the window", 30.0
            )
            rate = rate_in_window(gcs.attitude_boot_ms(), start_ms)
            out, _ = flood.communicate(timeout=30.0)
            junk_rate = float(out.strip())
            assert junk_rate >= 0.9 * JUNK_PER_S, junk_rate  # the flood did run
            assert rate >= 0.95 * ATT_HZ, f"ATTITUDE {rate:.2f} Hz under the flood"
            assert served_s < 5.0, served_s
            assert not d.exited and "Traceback" not in d.log()
            assert d.stop() == 0
        finally:
            end_attack(flood, idle)
            gcs.close()
            d.kill()
