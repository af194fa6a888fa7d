"""Storage faults of the running daemon: a read-only or full state directory (the new
calibration is kept in memory, the error reported, nothing crashes) and kill -9 while it
saves (a restart always finds a valid calibration).

The daemon runs as a subprocess on a simulated compass behind a pty, under a fake service
manager; calibrations are triggered the way an operator would remotely: a fixed-yaw
calibration through the Zenoh command queryable (remote_calibration = true, loopback only).
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import random
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from helpers import run_cli
from service_harness import (
    DaemonProcess,
    FakeServiceManager,
    free_port,
    status_text,
    toml_config,
)

from bridge.core.calibration import AffineCalibration, Calibration
from bridge.sim.firmware import make_firmware
from bridge.sim.motion import Still
from bridge.sim.pty import PtyCompass
from bridge.storage import StateStore

pytestmark = pytest.mark.integration  # real sockets, processes or threads

DEADLINE_S = 20.0
PR_CAPBSET_DROP = 24
CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH = 1, 2


def _no_dac_override() -> None:
    """preexec_fn: drop the capabilities that let root ignore file modes.

    Under the unit the daemon runs as its own user with no capabilities at all
    (CapabilityBoundingSet= empty); a test run as root must not write into a
    0555 directory either. Dropped from the bounding set, they are gone after exec.
    """
    libc = ctypes.CDLL(None, use_errno=True)
    for cap in (CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH):
        if libc.prctl(PR_CAPBSET_DROP, cap, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


class Bridge:
    """A daemon with remote calibration on a loopback zenoh listener, and a client session."""

    def __init__(self, tmp: Path, manager: FakeServiceManager, link: Path, state: Path) -> None:
        self.port = free_port()
        self.prefix = f"test/storage{os.getpid()}x{self.port}"
        zenoh_section = (
            f'[zenoh]\nenabled = true\nlisten = ["tcp/127.0.0.1:{self.port}"]\n'
            f'key_prefix = "{self.prefix}"\nmulticast_scouting = false\n'
            "remote_calibration = true\n\n"
        )
        text = toml_config(str(link), state, extra="[location]\nlatitude = 47.4\nlongitude = 8.5\n")
        cfg = tmp / "bridge.toml"
        cfg.write_text(text.replace("[zenoh]\nenabled = false\n\n", zenoh_section))
        self.cfg, self.tmp, self.manager = cfg, tmp, manager
        self.daemon: DaemonProcess | None = None
        self.runs = 0

    def start(self) -> DaemonProcess:
        self.runs += 1
        preexec = _no_dac_override if os.geteuid() == 0 else None
        self.daemon = DaemonProcess(
            self.cfg, self.manager, self.tmp / f"daemon{self.runs}.log", preexec_fn=preexec
        )
        return self.daemon

    @contextlib.contextmanager
    def client(self) -> Iterator[zenoh.Session]:
        c = zenoh.Config()
        c.insert_json5("mode", '"client"')
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("scouting/gossip/enabled", "false")
        c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{self.port}"]))
        c.insert_json5("connect/timeout_ms", "10000")
        s = zenoh.open(c)
        try:
            yield s
        finally:
            s.close()

    def command(self, session: zenoh.Session, name: str, args: dict[str, Any]) -> dict[str, Any]:
        end = time.monotonic() + DEADLINE_S
        while time.monotonic() < end:
            for r in session.get(
                f"{self.prefix}/cmd/calibration/{name}",
                payload=json.dumps(args).encode(),
                timeout=3.0,
            ):
                if r.ok is not None:
                    doc: dict[str, Any] = json.loads(r.ok.payload.to_bytes())
                    return doc
            time.sleep(0.1)  # not connected yet
        raise AssertionError(f"no answer to cmd/calibration/{name}")


FIXED_YAW = {"what": "fixed_yaw", "yaw_deg": 0.0}


@pytest.fixture
def still_compass(tmp_path: Path) -> Iterator[PtyCompass]:
    # Fixed-yaw calibration wants the unit still.
    with PtyCompass(make_firmware(11, motion=Still()), tmp_path / "compass") as sim:
        yield sim


def _calibrate_and_expect_not_saved(
    bridge: Bridge, manager: FakeServiceManager, *, operator_tools: bool = False
) -> None:
    d = bridge.daemon
    assert d is not None
    i, _ = manager.wait_for(lambda m: " Hz" in status_text(m), proc=d)  # frames for the average
    with bridge.client() as s:
        doc = bridge.command(s, "start", FIXED_YAW)
    assert doc.get("ok") is True, doc.get("message")
    # Applied in memory, not saved: STATUS and the log say so; the daemon carries on.
    _, st = manager.wait_for(lambda m: "NOT SAVED" in status_text(m), after=i, proc=d)
    assert "streaming" in status_text(st)
    assert "not saved" in d.log().lower()
    if operator_tools:
        # The operator's own commands, over the bridge's Zenoh listener, say it too (they did
        # not: only the STATUS line did). They take seconds: only where the refusal lasts
        # past the retry 5 s on (a full disk's stand-in is gone once the first save's
        # clean-up removed it, and the retry then saves, as it should).
        where = ("--connect", f"tcp/127.0.0.1:{bridge.port}")
        status = run_cli(bridge.tmp, "status", f"{bridge.prefix}/status", *where)
        assert "NOT SAVED, lost at a restart until storage takes it" in status.stdout, status
        table = run_cli(bridge.tmp, "monitor", bridge.prefix, "--once", *where)
        assert "NOSAVE" in table.stdout, table
    manager.pings_continue(d)
    assert "Traceback" not in d.log()
    assert d.stop() == 0


def test_read_only_state_dir(
    tmp_path: Path, manager: FakeServiceManager, still_compass: PtyCompass
) -> None:
    state = tmp_path / "state"
    state.mkdir()
    state.chmod(0o555)
    bridge = Bridge(tmp_path, manager, still_compass.link_path, state)
    d = bridge.start()
    try:
        _calibrate_and_expect_not_saved(bridge, manager, operator_tools=True)
        assert list(state.iterdir()) == []  # nothing was written, not even a temp file
    finally:
        d.kill()
        state.chmod(0o755)


def test_full_state_dir(
    tmp_path: Path, manager: FakeServiceManager, still_compass: PtyCompass
) -> None:
    state = tmp_path / "state"
    state.mkdir()
    # Every save writes calibration.json.tmp first: pointed at /dev/full, the write gets
    # ENOSPC from the kernel, as on a full filesystem.
    (state / "calibration.json.tmp").symlink_to("/dev/full")
    bridge = Bridge(tmp_path, manager, still_compass.link_path, state)
    with bridge.start() as d:
        _calibrate_and_expect_not_saved(bridge, manager)
        assert not (state / "calibration.json").exists()
        assert "calibration.storage_error" in d.log()  # reported as an operator event


def test_kill_9_during_saves_never_loses_the_calibration(
    tmp_path: Path, manager: FakeServiceManager, still_compass: PtyCompass
) -> None:
    state = tmp_path / "state"
    bridge = Bridge(tmp_path, manager, still_compass.link_path, state)
    # A first calibration, saved normally.
    with bridge.start() as d:
        manager.wait_for(lambda m: " Hz" in status_text(m), proc=d)
        with bridge.client() as s:
            assert bridge.command(s, "start", FIXED_YAW).get("ok") is True
        manager.wait_for(
            lambda m: "calibration fixed" in status_text(m) or "stored" in status_text(m), proc=d
        )
        assert StateStore(state).load("calibration").payload is not None
    rng = random.Random(6)
    saves_seen = 0
    for _ in range(4):
        with bridge.start() as d:
            mark = len(manager.messages)
            _, ready = manager.wait_for(lambda m: "READY" in m, after=mark, proc=d)
            # The restart found a valid calibration (the current copy or the last good one).
            assert "calibration stored" in status_text(ready), status_text(ready)
            stop = threading.Event()
            sent = [0]

            def spam(stop: threading.Event = stop, sent: list[int] = sent) -> None:
                with bridge.client() as s:
                    while not stop.is_set():
                        with contextlib.suppress(Exception):
                            for r in s.get(
                                f"{bridge.prefix}/cmd/calibration/start",
                                payload=json.dumps(FIXED_YAW).encode(),
                                timeout=2.0,
                            ):
                                if r.ok is not None and json.loads(r.ok.payload.to_bytes())["ok"]:
                                    sent[0] += 1  # applied and saved

            th = threading.Thread(target=spam, daemon=True)
            th.start()
            end = time.monotonic() + DEADLINE_S
            while sent[0] < 2 and time.monotonic() < end:
                time.sleep(0.02)
            time.sleep(rng.uniform(0.0, 0.3))  # land the kill at varying points of a save
            d.kill()  # SIGKILL
            stop.set()
            th.join(10.0)
            saves_seen += sent[0]
        loaded = StateStore(state).load("calibration")
        assert loaded.payload is not None, loaded.problems
    assert saves_seen >= 8  # the daemon really was saving when it was killed


def test_corrupt_calibration_at_start_falls_back_and_says_so(
    tmp_path: Path, manager: FakeServiceManager, still_compass: PtyCompass
) -> None:
    state = tmp_path / "state"
    store = StateStore(state)
    good = Calibration(mag=AffineCalibration(offset=(0.01, 0.02, 0.03)))
    store.save("calibration", {"calibration": good.to_dict()})
    store.save("calibration", {"calibration": Calibration().to_dict()})  # the first becomes .prev
    current = state / "calibration.json"
    current.write_bytes(current.read_bytes()[: len(current.read_bytes()) // 2])  # torn write
    bridge = Bridge(tmp_path, manager, still_compass.link_path, state)
    with bridge.start() as d:
        _, ready = manager.wait_for(lambda m: "READY" in m, proc=d)
        assert "calibration stored (previous copy)" in status_text(ready), status_text(ready)
        log = d.log()
        assert "calibration.json: truncated or not JSON" in log  # reported, with the reason
        assert d.stop() == 0
