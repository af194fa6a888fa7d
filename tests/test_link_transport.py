"""Transports: pyserial on a real pty, replay of a recording, port-string parsing."""

from __future__ import annotations

import contextlib
import os
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from bridge.link.record import Kind, RecordingWriter
from bridge.link.transport import (
    EndOfRecording,
    ReplayTransport,
    SerialTransport,
    SimTransport,
    TransportError,
    open_transport,
)
from bridge.protocol.gmr import (
    AckFrame,
    AttitudeFrame,
    CommandFrame,
    GmrDecoder,
    GmrFrame,
    VersionFrame,
    encode,
)
from bridge.sim.firmware import make_firmware


@pytest.fixture
def pty_pair(tmp_path: Path) -> Iterator[tuple[int, Path]]:
    """A raw pty: (master fd, symlink to the slave). The slave stays open on our side too."""
    master, slave = os.openpty()
    tty.setraw(slave)
    link = tmp_path / "ttyTEST"
    link.symlink_to(os.ttyname(slave))
    yield master, link
    for fd in (master, slave):
        with contextlib.suppress(OSError):  # the test may have closed it already
            os.close(fd)


def read_all(t: SerialTransport, n: int, timeout: float = 3.0) -> bytes:
    out = b""
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        out += t.read(4096, 0.05)
    return out


@pytest.mark.integration
def test_serial_reads_writes_and_times_out(pty_pair: tuple[int, Path]) -> None:
    master, path = pty_pair
    t = SerialTransport(str(path), 115200)
    t.open()
    try:
        t0 = time.monotonic()
        assert t.read(100, 0.1) == b""  # silence: empty read after the timeout, no exception
        assert time.monotonic() - t0 < 2.0
        line = b"$PGMRV,2.1.0,B3,GMR-000417*47\r\n"
        os.write(master, line)
        assert read_all(t, len(line)) == line
        os.write(master, b"abcdefgh")
        got = b""
        for _ in range(20):  # max_bytes is honoured, the rest stays queued
            chunk = t.read(3 - len(got), 0.1)
            assert len(chunk) <= 3 - len(got)
            got += chunk
            if len(got) == 3:
                break
        assert got == b"abc"
        assert read_all(t, 5) == b"defgh"
        t.write(b"$PGMRQ,VER*56\r\n")
        got = b""
        deadline = time.monotonic() + 3.0
        while len(got) < 15 and time.monotonic() < deadline:
            os.set_blocking(master, False)
            try:
                got += os.read(master, 100)
            except BlockingIOError:
                time.sleep(0.01)
        assert got == b"$PGMRQ,VER*56\r\n"
    finally:
        t.close()


@pytest.mark.integration
def test_vanished_port_raises_instead_of_empty_reads(pty_pair: tuple[int, Path]) -> None:
    master, path = pty_pair
    t = SerialTransport(str(path), 115200)
    t.open()
    os.write(master, b"xyz")
    assert read_all(t, 3) == b"xyz"
    os.close(master)  # the "USB adapter" is gone
    with pytest.raises(TransportError):
        for _ in range(5):  # bounded: it must raise on the first read or so
            t.read(100, 0.05)
    with pytest.raises(TransportError):
        t.write(b"$PGMRQ,VER*56\r\n")
    t.close()
    t.close()  # idempotent


@pytest.mark.integration
def test_open_failures_are_transport_errors(pty_pair: tuple[int, Path], tmp_path: Path) -> None:
    _, path = pty_pair
    with pytest.raises(TransportError, match="cannot open"):
        SerialTransport(str(tmp_path / "no-such-tty"), 115200).open()
    first = SerialTransport(str(path), 115200)
    first.open()
    try:
        with pytest.raises(TransportError):  # exclusive: a second reader would steal bytes
            SerialTransport(str(path), 115200).open()
    finally:
        first.close()
    with pytest.raises(TransportError, match="not open"):
        first.read(10, 0.01)


class FakeClock:
    """A clock the test advances; sleeping advances it (deterministic pacing checks)."""

    def __init__(self) -> None:
        self.now = 1000.0
        self.slept: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        self.slept.append(s)
        self.now += s


def write_recording(path: Path, chunks: list[tuple[float, bytes]]) -> None:
    with RecordingWriter(path, "/dev/ttyUSB0", 115200, 1.7e9) as w:
        for t, data in chunks:
            w.write(t, data)
        w.write(0.55, b"$PGMRQ,VER*56\r\n", Kind.TX)  # host bytes are not replayed


CHUNKS = [(0.5, b"$PGMRV,2.1."), (0.52, b"0,B3,GMR-000417*47\r\n"), (1.5, b"tail")]


def test_replay_realtime_keeps_recorded_pace(tmp_path: Path) -> None:
    path = tmp_path / "r.cbrec"
    write_recording(path, CHUNKS)
    clock = FakeClock()
    r = ReplayTransport(str(path), realtime=True, clock=clock, sleep=clock.sleep)
    assert not r.interactive
    r.open()
    start = clock.now
    assert r.read(100, 0.1) == b"$PGMRV,2.1."  # the first chunk is due at once
    assert clock.now == start
    # The second is due 20 ms later: a read waits for it (within its timeout).
    assert r.read(100, 0.1) == b"0,B3,GMR-000417*47\r\n"
    assert clock.now == pytest.approx(start + 0.02)
    # The third is due 1.0 s after the first: a 0.3 s read times out empty.
    assert r.read(100, 0.3) == b""
    assert clock.now == pytest.approx(start + 0.32)
    assert r.read(100, 5.0) == b"tail"
    assert clock.now == pytest.approx(start + 1.0)
    with pytest.raises(EndOfRecording):
        r.read(100, 0.1)
    with pytest.raises(EndOfRecording):
        r.open()


def test_replay_fast_plays_everything_at_once_and_discards_writes(tmp_path: Path) -> None:
    path = tmp_path / "r.cbrec"
    write_recording(path, CHUNKS)
    clock = FakeClock()
    r = ReplayTransport(str(path), realtime=False, clock=clock, sleep=clock.sleep)
    r.open()
    r.write(b"$PGMRQ,VER*56\r\n")
    r.write(b"x")
    got = b""
    with pytest.raises(EndOfRecording):
        for _ in range(100):
            got += r.read(7, 0.1)  # small reads split chunks; nothing is lost
    assert got == b"".join(d for _, d in CHUNKS)
    assert clock.slept == []
    assert (r.writes_discarded, r.bytes_discarded) == (2, 16)


def test_replay_resumes_after_close_and_handles_bad_files(tmp_path: Path) -> None:
    path = tmp_path / "r.cbrec"
    write_recording(path, CHUNKS)
    r = ReplayTransport(str(path), realtime=False)
    r.open()
    assert r.read(11, 0.1) == b"$PGMRV,2.1."
    r.close()
    with pytest.raises(TransportError):
        r.read(10, 0.1)
    r.open()
    assert r.read(100, 0.1).startswith(b"0,B3")
    with pytest.raises(EndOfRecording):  # missing file: retrying cannot help
        ReplayTransport(str(tmp_path / "missing"), realtime=False).open()
    foreign = tmp_path / "foreign.bin"
    foreign.write_bytes(b"not a recording at all")
    with pytest.raises(EndOfRecording, match="magic"):
        ReplayTransport(str(foreign), realtime=False).open()


def test_open_transport_parses_port_strings(tmp_path: Path) -> None:
    t = open_transport("/dev/ttyUSB7", 9600, seed=3)  # sim options are ignored for a device
    assert isinstance(t, SerialTransport) and (t.port, t.baud) == ("/dev/ttyUSB7", 9600)
    r = open_transport(f"replay:{tmp_path}/x.cbrec", 115200, realtime=False)
    assert isinstance(r, ReplayTransport) and r.path == f"{tmp_path}/x.cbrec" and not r.realtime
    assert r.name == f"replay:{tmp_path}/x.cbrec"
    assert isinstance(open_transport("replay:y", 115200), ReplayTransport)
    for bad in ("", "   ", "replay:"):
        with pytest.raises(ValueError):
            open_transport(bad, 115200)
    with pytest.raises(ValueError):
        SerialTransport("/dev/ttyUSB0", 0)


# ---------------------------------------------------------------------------- simulator


def decode_until(
    t: SimTransport, pred: Callable[[list[GmrFrame]], bool], timeout: float, clock: FakeClock
) -> list[GmrFrame]:
    """Read ``t`` until ``pred`` holds or ``timeout`` passes on its (simulated) ``clock``."""
    dec = GmrDecoder(direction="host")
    frames: list[GmrFrame] = []
    deadline = clock() + timeout
    while not pred(frames) and clock() < deadline:
        frames += dec.feed(t.read(4096, 0.05))
    assert dec.counters.dropped.total == 0
    return frames


def test_sim_transport_paces_frames_on_a_simulated_clock() -> None:
    clock = FakeClock()
    t = SimTransport(make_firmware(seed=2), clock=clock, sleep=clock.sleep)
    t.open()
    dec = GmrDecoder(direction="host")
    start = clock.now
    got: list[tuple[float, GmrFrame]] = []
    for _ in range(200):
        for f in dec.feed(t.read(4096, 0.5)):
            got.append((clock.now - start, f))
        if len(got) >= 6:
            break
    assert isinstance(got[0][1], VersionFrame) and got[0][0] == 0.0  # power-up banner
    frames = [(ts, f) for ts, f in got if isinstance(f, AttitudeFrame)]
    assert [f.seq for _, f in frames] == list(range(len(frames)))
    # 10 Hz after power-up: frame k leaves at (k + 1) / 10 s, and read() slept until then.
    for k, (ts, _) in enumerate(frames):
        assert ts == pytest.approx((k + 1) * 0.1, abs=1e-9)
    assert max(clock.slept) <= SimTransport.MAX_WAIT_S + 1e-12  # bounded waits


def test_sim_transport_answers_commands_without_waiting_for_a_frame() -> None:
    made = open_transport("sim", 115200, seed=5)
    assert isinstance(made, SimTransport) and made.interactive and made.name == "sim"
    # The firmware the port string made, on a simulated clock: no real time passes, and
    # how long the answer took is exact.
    clock = FakeClock()
    t = SimTransport(made.firmware, clock=clock, sleep=clock.sleep)
    t.open()
    try:
        frames = decode_until(
            t, lambda fs: any(isinstance(f, AttitudeFrame) for f in fs), 3.0, clock
        )
        assert isinstance(frames[0], VersionFrame)
        t.write(encode(CommandFrame.rate(1)))
        frames = decode_until(t, lambda fs: AckFrame.rate_ok(1) in fs, 3.0, clock)
        assert AckFrame.rate_ok(1) in frames
        # At 1 Hz the next frame is up to a second away; the VER answer must not wait for it.
        asked = clock.now
        t.write(encode(CommandFrame.ver()))
        frames = decode_until(
            t, lambda fs: any(isinstance(f, VersionFrame) for f in fs), 3.0, clock
        )
        assert isinstance(frames[-1], VersionFrame)
        assert not any(isinstance(f, AttitudeFrame) for f in frames)
        assert clock.now - asked < 0.5
    finally:
        t.close()
    with pytest.raises(TransportError):
        t.read(10, 0.01)
    with pytest.raises(TransportError):
        t.write(b"$PGMRQ,VER*56\r\n")
