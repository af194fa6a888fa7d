"""Network faults of the running daemon (subprocess, fake service manager, simulated compass
on a pty): the Zenoh peer it connects to goes down and comes back. The serial side, STATUS
and the watchdog never notice; publishing resumes by itself.
"""

from __future__ import annotations

import contextlib
import threading
import time
from pathlib import Path

import pytest
import zenoh
from service_harness import (
    DaemonProcess,
    FakeServiceManager,
    free_port,
    streaming_rate,
    toml_config,
    wait_for,
)
from zenoh_rig import peer_config

from bridge.sim.firmware import make_firmware
from bridge.sim.pty import PtyCompass

pytestmark = pytest.mark.integration  # real sockets, processes or threads

DEADLINE_S = 20.0


class Peer:
    """The fleet's zenoh peer: listens on a fixed loopback port, counts headings it gets."""

    def __init__(self, port: int, key: str) -> None:
        self.lock = threading.Lock()
        self.headings: list[float] = []  # monotonic arrival times
        self.session = zenoh.open(peer_config(listen=[f"tcp/127.0.0.1:{port}"]))
        self.sub = self.session.declare_subscriber(key, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.headings.append(time.monotonic())

    def count(self) -> int:
        with self.lock:
            return len(self.headings)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.sub.undeclare()
        self.session.close()


def test_zenoh_peer_down_and_back(tmp_path: Path, manager: FakeServiceManager) -> None:
    zport = free_port()
    prefix = f"test/netfault{zport}"
    zsec = (
        f'[zenoh]\nenabled = true\nmode = "peer"\nconnect = ["tcp/127.0.0.1:{zport}"]\n'
        f'key_prefix = "{prefix}"\nmulticast_scouting = false\n\n'
    )
    with PtyCompass(make_firmware(12), tmp_path / "compass") as sim:
        cfg = tmp_path / "bridge.toml"
        text = toml_config(str(sim.link_path), tmp_path / "state")
        cfg.write_text(text.replace("[zenoh]\nenabled = false\n\n", zsec))
        peer = Peer(zport, f"{prefix}/heading")
        d = DaemonProcess(cfg, manager, tmp_path / "daemon.log")
        try:
            manager.wait_for(lambda m: 8.0 <= streaming_rate(m) <= 12.0, proc=d)
            wait_for(lambda: peer.count() >= 10, "headings at the peer")

            peer.close()  # the peer goes away
            t_down = time.monotonic()
            mark = len(manager.messages)
            # For 3 s without it: the compass side streams on, pings keep coming.
            manager.wait_for(lambda m: m.t - t_down > 3.0, after=mark, proc=d)
            down = manager.since(mark)
            assert sum(m.get("WATCHDOG") == "1" for m in down) >= 6
            rates = [streaming_rate(m) for m in down if "STATUS" in m]
            assert rates and min(rates) >= 8.0, rates

            peer = Peer(zport, f"{prefix}/heading")  # back, same endpoint
            t_back = time.monotonic()
            wait_for(lambda: peer.count() >= 5, "headings after the peer's return")
            first = peer.headings[0] - t_back
            assert first < 5.0  # re-joined by the daemon's own connect retry
            assert not d.exited and "Traceback" not in d.log()
            assert d.stop() == 0
        finally:
            d.kill()
            peer.close()
