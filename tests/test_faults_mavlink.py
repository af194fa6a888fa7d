"""MAVLink faults of the running daemon (subprocess, fake service manager, simulated compass
on a pty, real UDP/TCP sockets on 127.0.0.1): endpoints that lead nowhere, and a peer
flooding commands. The telemetry a healthy ground station receives keeps its rate.
"""

from __future__ import annotations

import contextlib
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as apm
from service_harness import (
    DaemonProcess,
    FakeServiceManager,
    GroundStation,
    free_port,
    streaming_rate,
    toml_config,
    wait_for,
)

from bridge.sim.firmware import make_firmware
from bridge.sim.pty import PtyCompass

pytestmark = pytest.mark.integration  # real sockets, processes or threads

DEADLINE_S = 20.0


def attitudes_per_frames(sim: PtyCompass, gcs: GroundStation, frames: int) -> tuple[int, int]:
    """Wait for ``frames`` more frames from the compass; (frames sent, ATTITUDE the ground
    station got meanwhile, with 2 s for the last ones in flight)."""
    f0, a0 = sim.firmware.frames_sent, gcs.count("ATTITUDE", 0.0)
    wait_for(lambda: sim.firmware.frames_sent >= f0 + frames, "the compass's frames")
    sent = sim.firmware.frames_sent - f0
    with contextlib.suppress(AssertionError):
        wait_for(lambda: gcs.count("ATTITUDE", 0.0) - a0 >= sent, "ATTITUDE", 2.0)
    return sent, gcs.count("ATTITUDE", 0.0) - a0


@pytest.fixture
def gcs() -> Iterator[GroundStation]:
    g = GroundStation()
    yield g
    g.close()


def test_unreachable_endpoints_do_not_slow_the_others(
    tmp_path: Path, manager: FakeServiceManager, gcs: GroundStation
) -> None:
    closed_udp, closed_tcp = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
    endpoints = [
        f"udpout:127.0.0.1:{closed_udp}",  # nobody listens: ICMP port unreachable
        f"tcp:127.0.0.1:{closed_tcp}",  # connection refused, retried
        "tcp:192.0.2.1:5760",  # TEST-NET-1: never answers (or unreachable)
        f"udpout:127.0.0.1:{gcs.port}",  # the one ground station that is there
    ]
    with PtyCompass(make_firmware(21), tmp_path / "compass") as sim:
        cfg = tmp_path / "bridge.toml"
        cfg.write_text(toml_config(str(sim.link_path), tmp_path / "state", mavlink=endpoints))
        with DaemonProcess(cfg, manager, tmp_path / "daemon.log") as d:
            manager.wait_for(lambda m: 8.0 <= streaming_rate(m) <= 12.0, proc=d)
            wait_for(lambda: gcs.count("ATTITUDE", 0.0) > 5, "ATTITUDE at the ground station")
            # 4 s of the compass's own frames (counted, not slept: a busy machine delays
            # them, it does not change how many there are), an ATTITUDE for each.
            t0 = time.monotonic()
            frames, n = attitudes_per_frames(sim, gcs, 40)
            print(f"ATTITUDE at the live endpoint beside 3 dead ones: {n} for {frames} frames")
            assert 0.8 * frames <= n <= 1.2 * frames + 2, n  # not throttled, not doubled
            assert gcs.count("HEARTBEAT", t0) >= 3
            manager.pings_continue(d)
            assert "Traceback" not in d.log()
            assert d.stop() == 0


def test_a_command_flood_does_not_starve_telemetry(
    tmp_path: Path, manager: FakeServiceManager, gcs: GroundStation
) -> None:
    cmd_port = free_port(socket.SOCK_DGRAM)
    endpoints = [f"udpin:127.0.0.1:{cmd_port}", f"udpout:127.0.0.1:{gcs.port}"]
    with PtyCompass(make_firmware(22), tmp_path / "compass") as sim:
        cfg = tmp_path / "bridge.toml"
        cfg.write_text(toml_config(str(sim.link_path), tmp_path / "state", mavlink=endpoints))
        d = DaemonProcess(cfg, manager, tmp_path / "daemon.log")
        flooder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            manager.wait_for(lambda m: 8.0 <= streaming_rate(m) <= 12.0, proc=d)
            wait_for(lambda: gcs.count("ATTITUDE", 0.0) > 5, "ATTITUDE at the ground station")
            # A peer hammering COMMAND_LONGs addressed to us (a command we do not support,
            # so each costs the dispatcher a COMMAND_ACK), ~2000 a second for 4 s.
            mav = apm.MAVLink(None, srcSystem=255, srcComponent=190)
            pkt = mav.command_long_encode(1, 1, 183, 0, 1, 1500, 0, 0, 0, 0, 0).pack(mav)
            sent = 0
            f0, a0 = sim.firmware.frames_sent, gcs.count("ATTITUDE", 0.0)
            t0 = time.monotonic()
            while time.monotonic() - t0 < 4.0:
                for _ in range(50):
                    flooder.sendto(pkt, ("127.0.0.1", cmd_port))
                    sent += 1
                time.sleep(0.025)
            t1 = time.monotonic()
            # telemetry kept the compass's 10 Hz: an ATTITUDE for each of its frames meanwhile
            # (counted against the compass's own frames, so a busy machine cannot fail it;
            # 2 s for the last ones in flight)
            frames = sim.firmware.frames_sent - f0
            wait_for(lambda: gcs.count("ATTITUDE", 0.0) - a0 >= 0.8 * frames, "ATTITUDE", 2.0)
            n = gcs.count("ATTITUDE", 0.0) - a0
            print(f"flood: {sent / (t1 - t0):.0f} COMMAND_LONG/s; {n} ATTITUDE for {frames} frames")
            assert sent > 4000
            assert n <= 1.2 * (sim.firmware.frames_sent - f0) + 2, n
            flooder.settimeout(0.5)
            acks = apm.MAVLink(None)
            got: list[Any] = []
            for _ in range(20):  # the flooder was answered too (not a dead dispatcher)
                try:
                    got += acks.parse_buffer(flooder.recv(65536)) or []
                except TimeoutError:
                    break
            assert any(m.get_type() == "COMMAND_ACK" and m.command == 183 for m in got)
            mark = len(manager.messages)
            manager.wait_for(lambda m: 8.0 <= streaming_rate(m) <= 12.0, after=mark, proc=d)
            assert not d.exited and "Traceback" not in d.log()
            assert d.stop() == 0
        finally:
            flooder.close()
            d.kill()
