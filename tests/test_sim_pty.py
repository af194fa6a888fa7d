"""The simulated compass on a real pseudo-terminal, read through pyserial like a USB adapter.

Every wait has a deadline; nothing depends on tight wall-clock timing.
"""

from __future__ import annotations

import functools
import operator
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import serial
from waiting import wait_until

from bridge.protocol.gmr import (
    AckFrame,
    AttitudeFrame,
    CommandFrame,
    GmrDecoder,
    GmrFrame,
    VersionFrame,
    encode,
)
from bridge.sim.firmware import Firmware, make_firmware
from bridge.sim.flash import Flash
from bridge.sim.motion import Still
from bridge.sim.physics import SensorModel, UnitErrors
from bridge.sim.pty import PtyCompass, run_simulator

pytestmark = pytest.mark.integration  # a real pty and its serving thread


class Reader:
    """A host: pyserial port + host decoder, with bounded waits."""

    def __init__(self, path: Path) -> None:
        self.port = serial.Serial(str(path), 115200, timeout=0.05)
        self.dec = GmrDecoder("host")
        self.frames: list[GmrFrame] = []

    def pump(self) -> None:
        data = self.port.read(4096)
        self.frames += self.dec.feed(data)

    def until(self, pred: object, timeout: float) -> GmrFrame:
        assert callable(pred)
        deadline = time.monotonic() + timeout
        seen = 0
        while time.monotonic() < deadline:
            self.pump()
            for f in self.frames[seen:]:
                if pred(f):
                    return f
            seen = len(self.frames)
        raise AssertionError(f"nothing matched within {timeout} s; got {self.frames[-3:]}")

    def drain(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.pump()

    def attitude(self) -> list[AttitudeFrame]:
        return [f for f in self.frames if isinstance(f, AttitudeFrame)]

    def close(self) -> None:
        self.port.close()


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@pytest.fixture
def link(tmp_path: Path) -> Path:
    return tmp_path / "gmr0"


@pytest.fixture
def sim(link: Path) -> Iterator[PtyCompass]:
    with PtyCompass(make_firmware(seed=5), link) as s:
        yield s


def test_frames_arrive_through_pyserial(sim: PtyCompass, link: Path) -> None:
    assert link.is_symlink() and os.readlink(link) == sim.device
    assert sim.device is not None and sim.device.startswith("/dev/pts/")
    r = Reader(link)
    try:
        r.until(lambda f: isinstance(f, AttitudeFrame) and len(r.attitude()) >= 5, 5.0)
        seqs = [f.seq for f in r.attitude()]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
        assert r.dec.counters.dropped.total == 0
    finally:
        r.close()


def test_a_command_gets_its_answer(sim: PtyCompass, link: Path) -> None:
    r = Reader(link)
    try:
        r.until(lambda f: isinstance(f, AttitudeFrame), 3.0)
        r.port.write(encode(CommandFrame.ver()))
        v = r.until(lambda f: isinstance(f, VersionFrame), 3.0)
        assert v == VersionFrame("2.1.0", "B3", "GMR-000417")
        # a line with a bad checksum is ignored; the good one after it is answered
        body = b"PGMRQ,RATE,20"
        cs = functools.reduce(operator.xor, body, 0)
        r.port.write(b"$" + body + b"*%02X\r\n" % (cs ^ 1) + b"$" + body + b"*%02X\r\n" % cs)
        ack = r.until(lambda f: isinstance(f, AckFrame), 3.0)
        assert ack == AckFrame("RATE", True, ("20",))
        r.drain(0.3)  # long enough for a second (wrong) answer to show up
        assert [f for f in r.frames if isinstance(f, AckFrame)] == [ack]
        assert sim.firmware.rate_hz == 20
        assert sim.firmware.decoder.counters.dropped["checksum"] == 1
    finally:
        r.close()


@pytest.mark.parametrize("power_cycle", [False, True])
def test_unplug_and_replug_at_the_same_path(link: Path, power_cycle: bool) -> None:
    fds, threads = open_fds(), threading.active_count()
    with PtyCompass(make_firmware(seed=6), link) as sim:
        first = sim.device
        r = Reader(link)
        try:
            r.until(lambda f: isinstance(f, AttitudeFrame) and f.seq >= 12, 5.0)
            last_seq = r.attitude()[-1].seq
            sim.unplug(0.6, power_cycle=power_cycle)
            assert sim.device is None and not os.path.lexists(link)
            # the open port fails: reads raise (or at the very least stop delivering)
            with pytest.raises(serial.SerialException):
                deadline = time.monotonic() + 3.0
                while time.monotonic() < deadline:
                    r.port.read(4096)
        finally:
            r.close()
        second = sim.wait_plugged(5.0)
        assert second is not None and second != first
        assert os.readlink(link) == second
        r = Reader(link)
        try:
            f = r.until(lambda f: isinstance(f, AttitudeFrame), 5.0)
            assert isinstance(f, AttitudeFrame)
            if power_cycle:
                assert f.seq < last_seq  # rebooted: counting again from 0
            else:
                assert f.seq > last_seq  # stayed powered: seq carried on
        finally:
            r.close()
    assert not os.path.lexists(link)
    assert wait_until(lambda: threading.active_count() <= threads, 5.0)
    assert open_fds() == fds


def test_garbage_is_counted_as_noise_and_frames_continue(sim: PtyCompass, link: Path) -> None:
    r = Reader(link)
    try:
        r.until(lambda f: isinstance(f, AttitudeFrame), 3.0)
        n = len(r.attitude())
        sim.garbage(400)
        r.until(lambda f: isinstance(f, AttitudeFrame) and len(r.attitude()) >= n + 5, 5.0)
        assert r.dec.counters.dropped.total >= 1
        seqs = [f.seq for f in r.attitude()]
        # the noise sits between lines: no frame was lost to it
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    finally:
        r.close()


def test_lifecycle_leaks_nothing(link: Path) -> None:
    fds, threads = open_fds(), threading.active_count()
    fw = Firmware(
        SensorModel(UnitErrors.ideal(), np.array([0.2, 0.0, 0.4])),
        Still(),
        Flash(),
        np.random.default_rng(0),
    )
    s = PtyCompass(fw, link)
    s.start()
    with pytest.raises(RuntimeError):
        s.start()
    assert s.running and open_fds() > fds
    for _ in range(3):
        s.unplug(0.0)
        assert s.wait_plugged(3.0) is not None
    s.stop()
    s.stop()  # idempotent
    assert not s.running and not os.path.lexists(link)
    assert wait_until(lambda: threading.active_count() <= threads, 5.0)
    assert open_fds() == fds
    with pytest.raises(RuntimeError):
        s.unplug(1.0)
    with pytest.raises(ValueError):
        PtyCompass(fw, link).unplug(-1.0)


def test_run_simulator_serves_until_sigterm(link: Path) -> None:
    previous = signal.getsignal(signal.SIGTERM)
    got: list[GmrFrame] = []

    def client(sim: PtyCompass) -> None:
        r = Reader(link)
        try:
            got.append(r.until(lambda f: isinstance(f, AttitudeFrame), 5.0))
        finally:
            r.close()
            os.kill(os.getpid(), signal.SIGTERM)

    threads: list[threading.Thread] = []

    def ready(sim: PtyCompass) -> None:
        t = threading.Thread(target=client, args=(sim,))
        threads.append(t)
        t.start()

    done = threading.Timer(20.0, lambda: os.kill(os.getpid(), signal.SIGINT))  # bound the test
    done.start()
    try:
        assert run_simulator(str(link), seed=3, motion="still", on_ready=ready) == 0
    finally:
        done.cancel()
        for t in threads:
            t.join(5.0)
    assert got and isinstance(got[0], AttitudeFrame)
    assert not os.path.lexists(link)
    assert signal.getsignal(signal.SIGTERM) == previous
    with pytest.raises(ValueError, match="motion"):
        run_simulator(str(link), motion="dance")
