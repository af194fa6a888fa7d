"""The daemon as systemd runs it: a subprocess on a simulated compass behind a pty, with a
fake service manager (a real unix datagram socket as $NOTIFY_SOCKET, $WATCHDOG_USEC set).

It must say READY=1 once the compass streams, keep STATUS current, ping WATCHDOG=1 on
the monotonic clock only while its serial reader lives, answer SIGHUP with RELOADING=1
(+ MONOTONIC_USEC) ... READY=1 (refusing a bad file, keeping the old configuration), and
SIGTERM with STOPPING=1 and a clean exit within 5 s.
"""

from __future__ import annotations

import itertools
import re
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from service_harness import DaemonProcess, FakeServiceManager, Message, toml_config

from bridge.sim.firmware import make_firmware
from bridge.sim.pty import PtyCompass

pytestmark = pytest.mark.integration  # real sockets, processes or threads

WATCHDOG_USEC = 1_000_000  # pings due every 1/3 s


@pytest.fixture
def compass(tmp_path: Path) -> Iterator[PtyCompass]:
    with PtyCompass(make_firmware(7), tmp_path / "compass") as sim:
        yield sim


def _rate(msg: Message) -> float:
    m = re.search(r"at ([0-9.]+) Hz", msg.get("STATUS") or "")
    return float(m.group(1)) if m else -1.0


def _watchdogs(msgs: list[Message]) -> list[float]:
    return [m.t for m in msgs if m.get("WATCHDOG") == "1"]


def test_ready_status_watchdog_reload_and_stop(
    tmp_path: Path, manager: FakeServiceManager, compass: PtyCompass
) -> None:
    cfg = tmp_path / "bridge.toml"
    cfg.write_text(toml_config(str(compass.link_path), tmp_path / "state"))
    with DaemonProcess(cfg, manager, tmp_path / "daemon.log", watchdog_usec=WATCHDOG_USEC) as d:
        # READY once the compass streams, with a STATUS that says so.
        i, ready = manager.wait_for(lambda m: "READY" in m, proc=d)
        assert (ready.get("STATUS") or "").startswith(f"streaming {compass.link_path}")
        # STATUS follows with the frame rate and the heading.
        _, st = manager.wait_for(lambda m: 8.0 <= _rate(m) <= 12.0, after=i, proc=d)
        assert re.search(r"hdg \d+\.\d mag", st.get("STATUS") or "")
        assert "calibration none (identity)" in (st.get("STATUS") or "")

        # Periodic WATCHDOG=1: several, spaced well inside WatchdogSec.
        start = len(manager.messages)
        manager.wait_for(lambda m: len(_watchdogs(manager.since(start))) >= 6, after=start)
        times = _watchdogs(manager.since(start))
        gaps = [b - a for a, b in itertools.pairwise(times)]
        assert max(gaps) < WATCHDOG_USEC / 1e6 * 0.8

        # SIGHUP, file unchanged: RELOADING=1 with MONOTONIC_USEC, then READY=1.
        before = len(manager.messages)
        t_sent = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        d.signal(signal.SIGHUP)
        j, rel = manager.wait_for(lambda m: m.get("RELOADING") == "1", after=before, proc=d)
        assert int(rel.get("MONOTONIC_USEC") or 0) >= t_sent
        _, again = manager.wait_for(lambda m: "READY" in m, after=j, proc=d)
        assert "unchanged" in (again.get("STATUS") or "")

        # SIGHUP with an invalid file: refused with a log line, the old configuration kept.
        cfg.write_text(cfg.read_text().replace("baud = 115200", "baud = 1234"))
        before = len(manager.messages)
        d.signal(signal.SIGHUP)
        j, _ = manager.wait_for(lambda m: m.get("RELOADING") == "1", after=before, proc=d)
        _, refused = manager.wait_for(lambda m: "READY" in m, after=j, proc=d)
        assert "reload refused" in (refused.get("STATUS") or "")
        log = d.wait_log("reload refused")
        assert "device.baud" in log
        mark = len(manager.messages)
        manager.wait_for(lambda m: 8.0 <= _rate(m) <= 12.0, after=mark, proc=d)  # still streaming

        # A valid change of [device] reopens the port with it: 20 Hz asked on reconnect.
        cfg.write_text(toml_config(str(compass.link_path), tmp_path / "state", rate_hz=20))
        before = len(manager.messages)
        d.signal(signal.SIGHUP)
        j, _ = manager.wait_for(lambda m: m.get("RELOADING") == "1", after=before, proc=d)
        _, applied = manager.wait_for(lambda m: "READY" in m, after=j, proc=d)
        assert "reloaded [device]" in (applied.get("STATUS") or "")
        manager.wait_for(lambda m: 17.0 <= _rate(m) <= 23.0, after=j, proc=d)

        # SIGTERM: STOPPING=1, exit 0 within 5 s.
        before = len(manager.messages)
        t0 = time.monotonic()
        d.signal(signal.SIGTERM)
        code = d.wait(10.0)
        took = time.monotonic() - t0
        assert code == 0
        assert took < 5.0
        assert any("STOPPING" in m for m in manager.since(before))


def test_hung_reader_stops_the_pings_and_sigterm_still_stops(
    tmp_path: Path, manager: FakeServiceManager, compass: PtyCompass
) -> None:
    cfg = tmp_path / "bridge.toml"
    cfg.write_text(toml_config(str(compass.link_path), tmp_path / "state"))
    with DaemonProcess(
        cfg, manager, tmp_path / "daemon.log", watchdog_usec=WATCHDOG_USEC, hanging_reader=True
    ) as d:
        i, _ = manager.wait_for(lambda m: "READY" in m, proc=d)
        manager.wait_for(lambda m: m.get("WATCHDOG") == "1", after=i, proc=d)
        d.signal(signal.SIGUSR2)  # the stand-in's serial reader blocks in its next read
        d.wait_log("the serial reader hangs now")
        # Within the silence limit (4 s) the pings stop; STATUS says why.
        j, hung = manager.wait_for(
            lambda m: "NOT RESPONDING" in (m.get("STATUS") or ""), after=i, proc=d
        )
        assert "serial reader" in (hung.get("STATUS") or "")
        d.wait_log("watchdog: not pinging")
        mark = len(manager.messages)
        # While it stays hung, three ping periods pass (the notifier thread is alive: STATUS
        # keeps coming) without a single WATCHDOG=1.
        manager.wait_for(
            lambda m: m.t - manager.messages[mark - 1].t > 1.5, after=mark, timeout=10.0, proc=d
        )
        assert _watchdogs(manager.since(mark)) == []
        assert not any("WATCHDOG" in m and m.t > hung.t + 0.5 for m in manager.since(j))

        before = len(manager.messages)
        t0 = time.monotonic()
        d.signal(signal.SIGTERM)
        code = d.wait(10.0)
        assert code == 0 and time.monotonic() - t0 < 5.0
        assert any("STOPPING" in m for m in manager.since(before))


def test_ready_after_bounded_wait_without_a_compass(
    tmp_path: Path, manager: FakeServiceManager
) -> None:
    """No device at the port: READY=1 comes anyway (bounded), STATUS says it is waiting."""
    cfg = tmp_path / "bridge.toml"
    cfg.write_text(toml_config(str(tmp_path / "no-such-port"), tmp_path / "state"))
    with DaemonProcess(cfg, manager, tmp_path / "daemon.log", watchdog_usec=WATCHDOG_USEC) as d:
        _, ready = manager.wait_for(lambda m: "READY" in m, timeout=25.0, proc=d)
        status = ready.get("STATUS") or ""
        assert "without a streaming compass" in status
        assert f"waiting for {tmp_path / 'no-such-port'} (absent)" in status
        # The reader retrying an absent port is alive: pings keep coming.
        mark = len(manager.messages)
        manager.wait_for(lambda m: len(_watchdogs(manager.since(mark))) >= 3, after=mark)
        assert d.stop() == 0


def test_a_calibration_never_ours_to_save_is_no_storage_error(
    tmp_path: Path, manager: FakeServiceManager
) -> None:
    """The simulated compass's own calibration (its true errors) is in use and not in the
    state directory, and nothing refused it: STATUS names it and says nothing of saving
    (it said "NOT SAVED (storage error)", with the state directory fine)."""
    cfg = tmp_path / "bridge.toml"
    cfg.write_text(toml_config("sim", tmp_path / "state", extra="[sim]\ncalibrated = true\n"))
    with DaemonProcess(cfg, manager, tmp_path / "daemon.log", watchdog_usec=WATCHDOG_USEC) as d:
        _, st = manager.wait_for(lambda m: 8.0 <= _rate(m) <= 12.0, proc=d)
        status = st.get("STATUS") or ""
        assert "calibration simulator (the unit's true errors)" in status, status
        assert "NOT SAVED" not in status and "saving" not in status, status
        assert d.stop() == 0
