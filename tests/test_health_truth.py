"""Health tells the truth: a compass that answers every command but streams no attitude frame
is reported as not streaming on every surface -- MAVLink HEARTBEAT, Zenoh ``link.state``,
the systemd STATUS, ``compass-bridge status`` (its exit code) and ``monitor`` -- without
lost / restored flapping; and once it streams again, every surface says so.

The daemon is a real ``compass-bridge run`` subprocess under a fake service manager; the
compass is the simulated firmware on a pty (its sampling switched off, its main loop still
answering); the ground station a UDP listener; the fleet side real Zenoh sessions.
"""

from __future__ import annotations

import io
import json
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh
from service_harness import (
    DaemonProcess,
    FakeServiceManager,
    GroundStation,
    free_port,
    status_text,
    toml_config,
    wait_for,
)
from zenoh_rig import peer_config

from bridge.sim.firmware import make_firmware
from bridge.sim.pty import PtyCompass
from bridge.tools.status import run_status
from bridge.zenoh.monitor import MonitorOptions, run_monitor

pytestmark = [pytest.mark.integration, pytest.mark.slow]

ACTIVE, CRITICAL = 4, 5  # MAV_STATE


class FleetTap:
    """A zenoh session on the bridge's listener: every status document and event under it."""

    def __init__(self, endpoint: str, prefix: str) -> None:
        self.lock = threading.Lock()
        self.status: list[tuple[float, dict[str, Any]]] = []
        self.events: list[str] = []
        self.session = zenoh.open(peer_config(connect=[endpoint]))  # no scouting
        self.subs = [
            self.session.declare_subscriber(f"{prefix}/status", self._on_status),
            self.session.declare_subscriber(f"{prefix}/events", self._on_event),
        ]

    def _on_status(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.status.append((time.monotonic(), json.loads(sample.payload.to_bytes())))

    def _on_event(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.events.append(json.loads(sample.payload.to_bytes())["kind"])

    def states(self, since: float) -> list[str]:
        with self.lock:
            return [d["link"]["state"] for t, d in self.status if t >= since]

    def close(self) -> None:
        self.session.close()


def surfaces(endpoint: str, prefix: str) -> tuple[int, str, str]:
    """``status`` (exit code, text) and ``monitor --once`` (text), as an operator runs them."""
    opts = MonitorOptions(keyexpr=prefix, connect=(endpoint,), once=True, duration=2.5, tty=False)
    out = io.StringIO()
    code = run_status(opts, out, timeout=3.0)
    mon = io.StringIO()
    run_monitor(opts, mon)
    return code, out.getvalue(), mon.getvalue()


def test_a_compass_that_answers_but_streams_nothing_is_not_ok_anywhere(
    tmp_path: Path, manager: FakeServiceManager
) -> None:
    zport = free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    prefix = f"test/silent{zport}"
    fw = make_firmware(21)
    fw.streaming = False  # its sampling died; its main loop still answers every command
    gcs = GroundStation()
    with PtyCompass(fw, tmp_path / "compass") as sim:
        cfg = tmp_path / "bridge.toml"
        extra = (
            f'[zenoh]\nenabled = true\nmode = "peer"\nlisten = ["{endpoint}"]\n'
            f'key_prefix = "{prefix}"\nmulticast_scouting = false\n\n'
        )
        text = toml_config(
            str(sim.link_path), tmp_path / "state", mavlink=[f"udpout:127.0.0.1:{gcs.port}"]
        )
        cfg.write_text(text.replace("[zenoh]\nenabled = false\n\n", extra))
        d = DaemonProcess(cfg, manager, tmp_path / "daemon.log")
        tap: FleetTap | None = None
        try:
            manager.wait_for(lambda m: "answers commands" in status_text(m), proc=d)
            wait_for(lambda: gcs.count("HEARTBEAT", 0.0) >= 2, "HEARTBEATs")
            tap = FleetTap(endpoint, prefix)
            t0 = time.monotonic()
            wait_for(lambda: len(tap.states(t0)) >= 4, "status documents")
            code, status_out, monitor_out = surfaces(endpoint, prefix)
            t1 = time.monotonic()
            # -- silent: every surface says so, the whole time
            assert code == 1 and "NOT OK" in status_out, status_out
            assert "streaming" not in monitor_out and "stale" in monitor_out, monitor_out
            assert set(tap.states(t0)) <= {"stale", "opening"}, tap.states(t0)
            statuses = [status_text(m) for m in manager.messages if "STATUS" in m]
            assert not any(s.startswith("streaming") for s in statuses), statuses
            hb = gcs.last("HEARTBEAT")
            assert hb is not None and hb.system_status == CRITICAL
            # READY=1 only as the service manager's timeout one (the daemon must not be
            # killed for a silent compass: READY_TIMEOUT_S), and then saying why not --
            # never as a streaming compass's READY (a slow machine reaches the timeout here)
            readies = [status_text(m) for m in manager.messages if m.get("READY") == "1"]
            assert all(s.startswith("started without a streaming compass") for s in readies), (
                readies
            )
            with tap.lock:
                assert "link.lost" not in tap.events and "link.restored" not in tap.events

            # -- it streams again: every surface follows
            fw.streaming = True
            manager.wait_for(lambda m: status_text(m).startswith("streaming"), proc=d)
            if not readies:  # else READY went out at the timeout, and is not sent twice
                manager.wait_for(lambda m: m.get("READY") == "1", proc=d)
            wait_for(lambda: "streaming" in tap.states(time.monotonic() - 0.5), "zenoh streaming")
            code, status_out, monitor_out = surfaces(endpoint, prefix)
            # streaming: healthy; the unit carries no calibration, which `status` says apart
            # (exit 3, docs/tools.md), no longer "NOT OK"
            assert code == 3 and "NOT OK" not in status_out, status_out
            assert "UNCALIBRATED" in status_out and "streaming" in status_out, status_out
            assert "streaming" in monitor_out, monitor_out
            wait_for(
                lambda: getattr(gcs.last("HEARTBEAT"), "system_status", None) == ACTIVE,
                "HEARTBEAT ACTIVE",
            )
            assert t1 - t0 >= 3.0  # silent for seconds, not an instant
            assert d.stop() == 0
            assert "Traceback" not in d.log()
        finally:
            d.kill()
            if tap is not None:
                tap.close()
            gcs.close()
