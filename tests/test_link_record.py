"""Recording format (writer/reader, damage tolerance) and the record() tap on a real pty."""

from __future__ import annotations

import contextlib
import os
import signal
import struct
import threading
import time
import tty
import zlib
from collections.abc import Callable
from pathlib import Path

import pytest
from waiting import wait_until

from bridge.link.record import (
    MAGIC,
    Chunk,
    Kind,
    RecordingFormatError,
    RecordingReader,
    RecordingWriter,
)
from bridge.link.recorder import record
from bridge.link.serial_link import CompassLink, LinkState, Received
from bridge.link.transport import ReplayTransport, SerialTransport
from bridge.protocol.gmr import AttitudeFrame, CommandFrame, GmrDecoder, GmrFrame, encode
from bridge.protocol.heading import HeadingFrame
from bridge.sim.firmware import make_firmware
from bridge.sim.pty import PtyCompass

CHUNKS = [
    Chunk(0.0, Kind.RX, b"$PGMRV,2.1.0,B3,GMR-000417*47\r\n"),
    Chunk(0.013, Kind.TX, b"$PGMRQ,VER*56\r\n"),
    Chunk(0.1, Kind.RX, bytes(range(256))),  # any bytes, line noise included
    Chunk(12345.678901234, Kind.RX, b"x"),
]


def write(path: Path, chunks: list[Chunk] = CHUNKS) -> None:
    with RecordingWriter(path, "/dev/ttyUSB0", 115200, 1_763_700_000.25) as w:
        for c in chunks:
            w.write(c.t, c.data, c.kind)


def read(path: Path, kinds: frozenset[Kind] | None = None) -> tuple[list[Chunk], bool]:
    with RecordingReader(path) as r:
        chunks = list(r.chunks(kinds))
        return chunks, r.truncated


def test_round_trip_header_and_chunks(tmp_path: Path) -> None:
    path = tmp_path / "a.cbrec"
    write(path)
    with RecordingReader(path) as r:
        assert (r.header.port, r.header.baud, r.header.version) == ("/dev/ttyUSB0", 115200, 1)
        assert r.header.start_wall == 1_763_700_000.25
        assert [c.data for c in r.chunks()] == [CHUNKS[0].data, CHUNKS[2].data, b"x"]  # RX only
        assert not r.truncated
    got, truncated = read(path)
    assert not truncated
    assert [(c.kind, c.data) for c in got] == [(c.kind, c.data) for c in CHUNKS]
    for g, c in zip(got, CHUNKS, strict=True):
        assert abs(g.t - c.t) < 1e-9  # nanosecond timestamps
    assert path.read_bytes().startswith(MAGIC)


def test_big_writes_are_split_and_existing_files_kept(tmp_path: Path) -> None:
    path = tmp_path / "big.cbrec"
    blob = os.urandom(150_000)
    write(path, [Chunk(1.0, Kind.RX, blob)])
    got, _ = read(path)
    assert len(got) == 3 and b"".join(c.data for c in got) == blob
    with pytest.raises(FileExistsError):
        RecordingWriter(path, "sim", 0, 0.0)
    assert read(path)[0] == got  # untouched


def test_cut_tail_replays_up_to_the_cut(tmp_path: Path) -> None:
    path = tmp_path / "a.cbrec"
    write(path)
    full = path.read_bytes()
    last_record = 16 + len(CHUNKS[-1].data)
    # Power lost at every possible byte of the last record.
    for cut in range(len(full) - last_record, len(full)):
        path.write_bytes(full[:cut])
        got, truncated = read(path)
        assert [c.data for c in got] == [c.data for c in CHUNKS[:-1]]
        assert truncated == (cut != len(full) - last_record)


def test_zero_filled_or_corrupt_tail_stops_cleanly(tmp_path: Path) -> None:
    path = tmp_path / "a.cbrec"
    write(path)
    full = path.read_bytes()
    path.write_bytes(full + bytes(4096))  # blocks allocated but never written
    got, truncated = read(path)
    assert len(got) == len(CHUNKS) and truncated
    # A flipped bit inside the third record's data: replay stops before it.
    third = full.find(bytes(range(256)))
    damaged = bytearray(full)
    damaged[third + 100] ^= 0x40
    path.write_bytes(bytes(damaged))
    got, truncated = read(path)
    assert [c.data for c in got] == [CHUNKS[0].data, CHUNKS[1].data] and truncated


def test_unknown_record_kinds_are_skipped(tmp_path: Path) -> None:
    path = tmp_path / "a.cbrec"
    write(path, CHUNKS[:1])
    head = struct.pack("<BBHQ", 7, 0, 3, 5)  # a kind from a later version
    rec = head + struct.pack("<I", zlib.crc32(b"new", zlib.crc32(head))) + b"new"
    with path.open("ab") as f:
        f.write(rec)
    write(tmp_path / "b.cbrec", CHUNKS[2:3])
    with path.open("ab") as f:
        f.write((tmp_path / "b.cbrec").read_bytes()[-(16 + 256) :])
    got, truncated = read(path)
    assert [c.data for c in got] == [CHUNKS[0].data, CHUNKS[2].data] and not truncated


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (b"", "shorter"),
        (b"PK\x03\x04 a zip file, not a recording", "magic"),
        (MAGIC + struct.pack("<HH", 2, 14) + bytes(18), "version"),
        (MAGIC + struct.pack("<HH", 1, 14) + bytes(4), "truncated"),
    ],
)
def test_foreign_files_are_refused_clearly(tmp_path: Path, content: bytes, match: str) -> None:
    path = tmp_path / "x.cbrec"
    path.write_bytes(content)
    with pytest.raises(RecordingFormatError, match=match):
        RecordingReader(path)


def test_damaged_header_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "a.cbrec"
    write(path)
    data = bytearray(path.read_bytes())
    data[14] ^= 0x01  # inside start_wall
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingFormatError, match="CRC"):
        RecordingReader(path)


class PtyFeeder:
    """Writes scripted bytes into the master of a real pty reachable at ``path``."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sent = bytearray()  #: every byte written
        self.scripted = bytearray()  #: the bytes written by feed(), probes left out
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        path.symlink_to(os.ttyname(self.slave))

    def feed(self, n: int, period: float = 0.01) -> None:
        for i in range(n):
            data = f"$LINE,{len(self.sent)},{i}\r\n".encode()
            os.write(self.master, data)
            self.sent += data
            self.scripted += data
            time.sleep(period)

    def probe_until(self, read: Callable[[], bytes], timeout: float) -> bool:
        """Writes a ``$PROBE`` line every 50 ms until ``read()`` (what the recording holds)
        has one of them: the recorder has the port open *and flushed*.

        pyserial empties the port's input at the end of ``open()``, after the descriptor
        exists: bytes written between the two are gone before the recorder reads, as a
        compass's are before anyone opened its port. On a loaded machine that gap
        outlasted 20 lines fed 10 ms apart (a CI run: nothing recorded in 15 s; the same
        failure with 0.5 s slept inside pyserial's ``_reconfigure_port``). Probes lost to
        it are not counted against the recording; everything fed after one arrived must
        be in it."""
        before = read().count(b"$PROBE")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            data = f"$PROBE,{len(self.sent)}\r\n".encode()
            os.write(self.master, data)
            self.sent += data
            if wait_until(lambda: read().count(b"$PROBE") > before, 0.05):
                return True
        return False

    def unplug(self) -> None:
        os.close(self.master)
        os.close(self.slave)
        self.path.unlink()

    def replug(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path.symlink_to(os.ttyname(self.slave))

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


def _header_written(path: Path) -> bool:
    """Whether the recorder has written the recording's header whole (the file exists from
    its open, a moment before the header is in it)."""
    try:
        with RecordingReader(path):
            return True
    except (OSError, RecordingFormatError):
        return False


def _recorded(path: Path) -> bytes:
    """The bytes a recording holds so far (a chunk being written is not counted yet)."""
    return b"".join(c.data for c in read(path)[0])


@pytest.mark.integration
def test_record_taps_a_pty_through_a_replug(tmp_path: Path) -> None:
    feeder = PtyFeeder(tmp_path / "ttyREC")
    out = tmp_path / "rec.cbrec"
    stop = threading.Event()
    result: list[object] = []

    def run() -> None:
        result.append(record(str(feeder.path), 115200, out, stop=stop, handle_signals=False))

    th = threading.Thread(target=run)
    th.start()
    try:
        assert wait_until(lambda: _header_written(out), 5.0)
        # (Bounds for a loaded machine: the recorder flushes as it reads, in well under one.)
        assert feeder.probe_until(lambda: _recorded(out), 15.0)
        feeder.feed(20)
        first = bytes(feeder.scripted)
        assert wait_until(lambda: _recorded(out).endswith(first), 15.0)
        feeder.unplug()
        time.sleep(0.3)  # unplugged for a while, as a cable is
        feeder.replug()
        assert feeder.probe_until(lambda: _recorded(out), 15.0)  # the backoff has reopened it
        feeder.feed(20)
        assert wait_until(
            lambda: _recorded(out).endswith(bytes(feeder.scripted[len(first) :])), 15.0
        )
    finally:
        stop.set()
        th.join(5.0)
        feeder.close()
    assert not th.is_alive()
    summary = result[0]
    got, truncated = read(out)
    data = b"".join(c.data for c in got)
    # every byte fed, in order, none twice; of the probes only those the opening's flush
    # left (each opening's first recorded bytes are a probe line)
    lines = data.splitlines(keepends=True)
    assert b"".join(ln for ln in lines if not ln.startswith(b"$PROBE")) == bytes(feeder.scripted)
    assert all(ln in feeder.sent for ln in lines) and lines[0].startswith(b"$PROBE")
    assert not truncated
    ts = [c.t for c in got]
    assert ts == sorted(ts) and ts[0] >= 0
    assert getattr(summary, "port_losses", None) == 1
    assert getattr(summary, "bytes", None) == len(data)
    with RecordingReader(out) as r:
        assert (r.header.port, r.header.baud) == (str(feeder.path), 115200)
        assert abs(r.header.start_wall - time.time()) < 60


@pytest.mark.integration
def test_record_stops_on_sigint_and_restores_the_handler(tmp_path: Path) -> None:
    feeder = PtyFeeder(tmp_path / "ttyREC")
    before = signal.getsignal(signal.SIGINT)
    timer = threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    try:
        t0 = time.monotonic()
        summary = record(str(feeder.path), 115200, tmp_path / "s.cbrec", duration=10.0)
        assert time.monotonic() - t0 < 5.0
    finally:
        timer.cancel()
        feeder.close()
    assert summary.seconds < 5.0
    assert signal.getsignal(signal.SIGINT) is before


def replay_through_link(path: Path, realtime: bool) -> tuple[list[GmrFrame], float, CompassLink]:
    frames: list[GmrFrame] = []

    def keep(item: Received) -> None:
        assert not isinstance(item.frame, HeadingFrame)
        frames.append(item.frame)

    link = CompassLink(
        ReplayTransport(str(path), realtime=realtime), stale_after=5.0, on_frame=keep
    )
    t0 = time.monotonic()
    with link:
        assert link.wait_ended(10.0)
        elapsed = time.monotonic() - t0
    return frames, elapsed, link


@pytest.mark.integration
def test_record_a_simulated_compass_and_replay_it(tmp_path: Path) -> None:
    dev = tmp_path / "ttySIM"
    out = tmp_path / "sim.cbrec"
    with PtyCompass(make_firmware(seed=9), dev) as sim:
        assert sim.wait_plugged(5.0)
        port = SerialTransport(str(dev), 115200)  # the recorder is passive: set 50 Hz first
        port.open()
        port.write(encode(CommandFrame.rate(50)))
        assert wait_until(lambda: sim.firmware.rate_hz == 50, 5.0)
        port.close()
        summary = record(str(dev), 115200, out, duration=1.2, handle_signals=False)
    assert summary.bytes > 0 and summary.port_losses == 0
    # What the recording holds, decoded independently of the link.
    with RecordingReader(out) as r:
        chunks = list(r.chunks())
    dec = GmrDecoder(direction="host")
    expected = dec.feed(b"".join(c.data for c in chunks))
    span = chunks[-1].t - chunks[0].t
    assert len([f for f in expected if isinstance(f, AttitudeFrame)]) >= 20
    assert span > 0.8

    fast, fast_s, link = replay_through_link(out, realtime=False)
    assert fast == expected
    assert link.state is LinkState.ABSENT and link.ended
    assert link.counters.commands_sent == 0  # a recording cannot answer: no handshake
    assert fast_s < span  # as fast as it can be read

    slow, slow_s, link = replay_through_link(out, realtime=True)
    assert slow == expected
    assert slow_s >= span - 0.05  # at the recorded pace
    assert link.counters.lost_frames == 0
