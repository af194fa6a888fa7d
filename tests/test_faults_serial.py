"""Serial faults the running daemon survives (a subprocess, fake service manager, real ptys):
the USB adapter unplugged and back, the compass rebooting mid-stream, bursts of line noise,
and a wrong baud rate (nothing decodes: said in STATUS, no crash, the watchdog still fed).
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import threading
import time
import tty
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as apm
from service_harness import (
    DaemonProcess,
    FakeServiceManager,
    GroundStation,
    status_text,
    streaming_rate,
    toml_config,
)

from bridge.sim.firmware import make_firmware
from bridge.sim.pty import PtyCompass

WATCHDOG_USEC = 1_000_000


def _start(tmp: Path, manager: FakeServiceManager, port: Path, **cfg: Any) -> DaemonProcess:
    path = tmp / "bridge.toml"
    path.write_text(toml_config(str(port), tmp / "state", **cfg))
    return DaemonProcess(path, manager, tmp / "daemon.log", watchdog_usec=WATCHDOG_USEC)


@pytest.mark.integration
def test_usb_unplug_and_return(tmp_path: Path, manager: FakeServiceManager) -> None:
    with (
        PtyCompass(make_firmware(5), tmp_path / "compass") as sim,
        _start(tmp_path, manager, sim.link_path) as d,
    ):
        i, _ = manager.wait_for(lambda m: streaming_rate(m) > 0, proc=d)
        sim.unplug(2.5)  # the pty vanishes, the symlink too; a new one after 2.5 s
        j, _ = manager.wait_for(
            lambda m: "waiting for" in status_text(m) or "no attitude frame" in status_text(m),
            after=i,
            proc=d,
        )
        manager.pings_continue(d)  # a reader retrying an absent port is alive
        assert sim.wait_plugged(10.0) is not None
        _, back = manager.wait_for(lambda m: streaming_rate(m) > 0, after=j, proc=d)
        assert re.search(r"\b1 reconnects\b", status_text(back)), status_text(back)
        assert not d.exited
        assert d.stop() == 0


@pytest.mark.integration
def test_compass_reboots_mid_stream(tmp_path: Path, manager: FakeServiceManager) -> None:
    with (
        PtyCompass(make_firmware(6), tmp_path / "compass") as sim,
        _start(tmp_path, manager, sim.link_path, rate_hz=20) as d,
    ):
        fw = sim.firmware
        # Streaming, at the 20 Hz the handshake asked for (the device's own setting: no
        # wall-clock rate window).
        i, _ = manager.wait_for(lambda m: streaming_rate(m) > 0 and fw.rate_hz == 20, proc=d)
        # A brown-out behind a self-powered adapter: the port stays, the device reboots
        # (output stops ~300 ms, $PGMRV, seq from 0, back at its 10 Hz power-up rate).
        with sim._lock:  # the serve thread owns the firmware; take its lock
            sim.firmware.power_off(time.monotonic())
        time.sleep(0.2)
        with sim._lock:
            sim.firmware.power_on(time.monotonic())
        k, _ = manager.wait_for(lambda m: "1 resets" in status_text(m), after=i, proc=d)
        # The daemon notices the reset and asks for its 20 Hz again (connect handshake).
        manager.wait_for(
            lambda m: "1 resets" in status_text(m) and streaming_rate(m) > 0 and fw.rate_hz == 20,
            after=k,
            proc=d,
        )
        assert "device reset detected" in d.log()
        manager.pings_continue(d)
        assert d.stop() == 0


@pytest.mark.integration
def test_garbage_bursts_are_counted_not_fatal(tmp_path: Path, manager: FakeServiceManager) -> None:
    with (
        PtyCompass(make_firmware(8), tmp_path / "compass") as sim,
        _start(tmp_path, manager, sim.link_path) as d,
    ):
        i, _ = manager.wait_for(lambda m: streaming_rate(m) > 0, proc=d)
        for _ in range(8):
            sim.garbage(3000)  # line noise in the middle of the frames
            time.sleep(0.1)
        k, _ = manager.wait_for(
            lambda m: re.search(r"\b\d+ bad\b", status_text(m)) is not None, after=i, proc=d
        )
        # Still streaming at the device's rate, still pinging, nothing crashed.
        manager.wait_for(lambda m: streaming_rate(m) > 0, after=k + 1, proc=d)
        manager.pings_continue(d)
        assert "Traceback" not in d.log()
        assert d.stop() == 0


def uart_as_read_at(data: bytes, tx_baud: int, rx_baud: int) -> bytes:
    """The bytes a UART at ``rx_baud`` makes of ``data`` sent 8N1 at ``tx_baud``.

    The receiver hunts for a falling edge (start bit), samples the middle of each of
    its own bit times, and delivers the 8 data bits -- what a host with the wrong baud
    rate configured really reads: a trickle of plausible-looking but meaningless bytes.
    """
    bits: list[int] = []
    for b in data:
        bits += [0] + [(b >> i) & 1 for i in range(8)] + [1]
    t_bit, r_bit = 1.0 / tx_baud, 1.0 / rx_baud

    def level(t: float) -> int:
        i = int(t / t_bit)
        return bits[i] if i < len(bits) else 1

    out = bytearray()
    t, end, step, prev = 0.0, len(bits) * t_bit, t_bit / 4, 1
    while t < end:
        cur = level(t)
        if prev == 1 and cur == 0 and level(t + 0.5 * r_bit) == 0:
            out.append(sum(level(t + (1.5 + k) * r_bit) << k for k in range(8)))
            t += 9.5 * r_bit  # the middle of the stop bit: hunt for the next edge from there
            prev = level(t)
            continue
        prev = cur
        t += step
    return bytes(out)


def test_uart_model_is_identity_at_the_right_rate() -> None:
    line = b"$PGMRA,1024,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950,06*50\r\n"
    assert uart_as_read_at(line, 115200, 115200) == line
    wrong = uart_as_read_at(line * 10, 115200, 9600)
    assert wrong and b"$" not in wrong and b"\n" not in wrong


class WrongBaudCompass:
    """A compass streaming at 115200 into a port the host opened at 9600 (on a pty)."""

    def __init__(self, link: Path) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.link = link
        link.symlink_to(os.ttyname(self.slave))
        fw = make_firmware(9)
        now = time.monotonic()
        chunks = b"".join(fw.poll(now + k * 0.1) for k in range(40))  # 4 s of frames
        self.noise = uart_as_read_at(chunks, 115200, 9600)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        k = 0
        while not self._stop.wait(0.05):
            piece = self.noise[k : k + 16] or self.noise[:16]
            k = (k + 16) % len(self.noise)
            with contextlib.suppress(BlockingIOError, OSError):
                os.write(self.master, piece)
            with contextlib.suppress(BlockingIOError, OSError):
                os.read(self.master, 4096)  # whatever the host sends goes nowhere

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        for fd in (self.master, self.slave):
            os.close(fd)


@pytest.mark.integration
def test_wrong_baud_rate_is_reported_not_fatal(tmp_path: Path, manager: FakeServiceManager) -> None:
    dev = WrongBaudCompass(tmp_path / "compass")
    gcs = GroundStation()
    d = _start(tmp_path, manager, dev.link, baud=9600, mavlink=[f"udpout:127.0.0.1:{gcs.port}"])
    try:
        # READY comes after the bounded wait, and STATUS names the problem.
        _, ready = manager.wait_for(lambda m: "READY" in m, timeout=25.0, proc=d)
        assert "without a streaming compass" in status_text(ready)
        _, st = manager.wait_for(lambda m: "NO VALID FRAMES" in status_text(m), proc=d)
        assert str(dev.link) in status_text(st) and "wrong baud rate" in status_text(st)
        # MAVLink says it too: SYS_STATUS has the compass present but not healthy, and
        # HEARTBEAT is not ACTIVE.
        end = time.monotonic() + 10.0
        while gcs.last("SYS_STATUS") is None and time.monotonic() < end:
            time.sleep(0.1)
        sys_status: Any = gcs.last("SYS_STATUS")
        hb: Any = gcs.last("HEARTBEAT")
        assert sys_status is not None and hb is not None
        mag = apm.MAV_SYS_STATUS_SENSOR_3D_MAG
        assert sys_status.onboard_control_sensors_present & mag
        assert not sys_status.onboard_control_sensors_health & mag
        assert hb.system_status != apm.MAV_STATE_ACTIVE
        manager.pings_continue(d)
        assert "Traceback" not in d.log()
        assert d.stop() == 0
    finally:
        d.kill()
        dev.close()
        gcs.close()


@pytest.mark.integration
def test_sigterm_while_port_absent_is_quick(tmp_path: Path, manager: FakeServiceManager) -> None:
    with _start(tmp_path, manager, tmp_path / "never-there") as d:
        manager.wait_for(lambda m: m.get("WATCHDOG") == "1", proc=d)
        t0 = time.monotonic()
        d.signal(signal.SIGTERM)
        assert d.wait(10.0) == 0
        assert time.monotonic() - t0 < 5.0
