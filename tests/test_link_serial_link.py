"""CompassLink over real pseudo-terminals: a scripted device peer driven by the test.

The peer is a real pty whose master end this test drives (the link opens the
slave through pyserial, exactly as it would a USB adapter). It streams
``$PGMRA`` frames and answers ``$PGMRQ`` commands according to a per-test
script, so retries, timeouts, late answers, seq gaps and resets can be staged
deterministically. Every wait is bounded by a deadline.
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import os
import select
import threading
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from bridge.link.serial_link import (
    CommandLate,
    CommandNotSupported,
    CommandRejected,
    CommandTimeout,
    CompassLink,
    LinkDown,
    LinkState,
    Received,
)
from bridge.link.transport import SerialTransport, SimTransport
from bridge.protocol.gmr import (
    AckFrame,
    AttitudeFrame,
    CommandFrame,
    Flags,
    GmrDecoder,
    ParamsFrame,
    VersionFrame,
    encode,
)
from bridge.protocol.heading import HeadingFrame
from bridge.protocol.heading import encode as encode_heading
from bridge.sim.firmware import make_firmware
from bridge.sim.pty import PtyCompass

# Every test but the in-process simulator's runs the link on a real pseudo-terminal.
pytestmark = pytest.mark.integration

VERSION = VersionFrame("2.1.0", "B3", "GMR-000417")
PARAMS = ParamsFrame(2460.5, 2455.0, 2470.0, 1.0, 1.0213, 0.9876, 2458.0, 2458.0, 2949.5)

Reply = list[tuple[float, bytes]]  # (delay after the command arrived, bytes to send)
Handler = Callable[[CommandFrame, int], Reply | None]  # (command, how many times seen) -> reply


def wait_until(pred: Callable[[], bool], timeout: float, step: float = 0.01) -> bool:
    """Poll ``pred`` until true or ``timeout`` s pass (bounded)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return pred()


def frame(seq: int) -> bytes:
    return encode(AttitudeFrame(seq, 87.3, -1.2, 0.4, 3101, 2470, 3311, 2470, 2452, 2950, Flags(6)))


def default_reply(cmd: CommandFrame) -> Reply:
    if cmd.command == "VER":
        return [(0.0, encode(VERSION))]
    if cmd.command == "RATE":
        return [(0.0, encode(AckFrame.rate_ok(int(cmd.args[0]))))]
    if cmd.key == "PAR,GET":
        return [(0.0, encode(PARAMS))]
    return [(0.0, encode(AckFrame.failure(cmd.command, "UNKNOWN")))]


class Peer:
    """A scripted GMR device on the master side of a real pty, reachable at ``path``."""

    def __init__(self, path: Path, rate_hz: float = 50.0) -> None:
        self.path = path
        self.period = 1.0 / rate_hz
        self.streaming = True
        self.seq = 0
        self.handlers: dict[str, Handler] = {}
        self.commands: list[tuple[float, CommandFrame]] = []
        self.sent_seqs: list[int] = []
        self.lose: set[int] = set()  #: seqs never sent (lost on the line)
        self._seen: dict[str, int] = {}
        self._decoder = GmrDecoder(direction="device")
        self._sched: list[tuple[float, int, bytes]] = []
        self._n = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._reboot_at: float | None = None
        self._master = -1
        self._slave = -1
        self._plug()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    # -- pty management
    def _plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        tmp = self.path.with_name(self.path.name + ".tmp")
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.path)
        with self._lock:
            self._master, self._slave = master, slave

    def unplug(self) -> None:
        """The adapter vanishes: both ends closed, the path removed."""
        with self._lock:
            master, slave = self._master, self._slave
            self._master = self._slave = -1
        os.close(master)
        os.close(slave)
        self.path.unlink()

    def replug(self) -> None:
        """A new pty (another /dev/pts/N) appears at the same path."""
        self._plug()

    # -- scripting
    def send(self, data: bytes, delay: float = 0.0) -> None:
        with self._lock:
            self._n += 1
            heapq.heappush(self._sched, (time.monotonic() + delay, self._n, data))

    def set_seq(self, seq: int) -> None:
        """The next frame carries ``seq`` (frames in between are "lost")."""
        with self._lock:
            self.seq = seq % 65536

    def skip(self, n: int) -> None:
        """Lose the next ``n`` frames."""
        with self._lock:
            self.seq = (self.seq + n) % 65536

    def reboot(self, silence: float = 0.3) -> None:
        """RESET as the datasheet has it: silence, then $PGMRV and frames from seq 0."""
        with self._lock:
            self._reboot_at = time.monotonic() + silence

    def received(self, key: str | None = None) -> list[CommandFrame]:
        with self._lock:
            return [c for _, c in self.commands if key is None or c.key == key]

    def _on_command(self, cmd: CommandFrame, now: float) -> None:
        with self._lock:
            self.commands.append((now, cmd))
            n = self._seen[cmd.key] = self._seen.get(cmd.key, 0) + 1
            handler = self.handlers.get(cmd.key)
        reply = handler(cmd, n) if handler is not None else default_reply(cmd)
        for delay, data in reply or []:
            self.send(data, delay)

    def _write(self, data: bytes) -> None:
        with self._lock:
            fd = self._master
        if fd < 0:
            return
        # Nobody reading (port closed) and the buffer full: the bytes are lost, as on a wire.
        with contextlib.suppress(OSError):
            os.write(fd, data)

    def _run(self) -> None:
        next_frame = time.monotonic()
        while not self._stop.is_set():
            with self._lock:
                fd = self._master
                due = self._sched[0][0] if self._sched else float("inf")
            now = time.monotonic()
            wait = max(0.0, min(0.02, due - now, next_frame - now if self.streaming else 0.02))
            if fd < 0:
                time.sleep(wait or 0.005)
                continue
            try:
                ready, _, _ = select.select([fd], [], [], wait)
                data = os.read(fd, 4096) if ready else b""
            except OSError:
                data = b""  # slave side closed (link reopening) or fd swapped under us
            now = time.monotonic()
            for cmd in self._decoder.feed(data):
                if isinstance(cmd, CommandFrame):
                    self._on_command(cmd, now)
            out = b""
            with self._lock:
                if self._reboot_at is not None and now >= self._reboot_at:
                    # Back from a reboot: $PGMRV first, then frames from seq 0.
                    self._reboot_at = None
                    out += encode(VERSION)
                    self.seq = 0
                    next_frame = now
                if self.streaming and self._reboot_at is None and now >= next_frame:
                    if self.seq in self.lose:
                        self.seq = (self.seq + 1) % 65536
                    self.sent_seqs.append(self.seq)
                    out += frame(self.seq)
                    self.seq = (self.seq + 1) % 65536
                    next_frame = max(next_frame + self.period, now)
                elif not self.streaming:
                    next_frame = now
            if out:
                self._write(out)
            while True:
                with self._lock:
                    if not self._sched or self._sched[0][0] > now:
                        break
                    _, _, out = heapq.heappop(self._sched)
                self._write(out)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        with self._lock:
            fds = [fd for fd in (self._master, self._slave) if fd >= 0]
            self._master = self._slave = -1
        for fd in fds:
            os.close(fd)


@pytest.fixture
def peer(tmp_path: Path) -> Iterator[Peer]:
    p = Peer(tmp_path / "ttyGMR")
    yield p
    p.close()


class Collector:
    """on_frame consumer that keeps everything (runs in the reader thread: appends only)."""

    def __init__(self) -> None:
        self.items: list[Received] = []
        self.states: list[tuple[LinkState, LinkState]] = []

    def on_frame(self, item: Received) -> None:
        self.items.append(item)

    def on_state(self, old: LinkState, new: LinkState) -> None:
        self.states.append((old, new))

    def seqs(self) -> list[int]:
        return [i.frame.seq for i in self.items if isinstance(i.frame, AttitudeFrame)]


def make_link(path: Path, col: Collector | None = None, **kw: object) -> CompassLink:
    kw.setdefault("stale_after", 0.5)
    return CompassLink(
        SerialTransport(str(path), 115200),
        on_frame=col.on_frame if col else None,
        on_state=col.on_state if col else None,
        **kw,  # type: ignore[arg-type]
    )


def handshake_done(peer: Peer) -> bool:
    return len(peer.received("PAR,GET")) >= 1


# ---------------------------------------------------------------------------- streaming


def test_streams_frames_runs_handshake_and_counts(peer: Peer) -> None:
    col = Collector()
    with make_link(peer.path, col, rate_hz=20) as link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: handshake_done(peer) and link.params is not None, 5.0)
        assert wait_until(lambda: len(col.seqs()) >= 30, 5.0)
        keys = [c.key for c in peer.received()]
        assert keys[:3] == ["VER", "RATE", "PAR,GET"]
        assert peer.received("RATE")[0].args == ("20",)
        assert link.version == VERSION
        assert link.params == PARAMS
        c = link.counters
        assert c.lost_frames == 0 and c.device_resets == 0 and c.bad_lines_total == 0
        assert c.attitude_frames >= 30
        assert c.frames == c.attitude_frames + 3  # + $PGMRV, $PGMRK,RATE, $PGMRP
        assert c.command_retries == 0 and c.late_answers == 0 and c.unsolicited_answers == 0
        seqs = col.seqs()
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # in order, none missing
        # The same frames are in the bounded queue, oldest first.
        first = link.get(timeout=1.0)
        assert first is not None and first.frame == col.items[0].frame
    assert (LinkState.OPENING, LinkState.STREAMING) in col.states
    assert col.states[0] == (LinkState.ABSENT, LinkState.OPENING)


def test_garbage_is_counted_by_reason_and_frames_keep_flowing(peer: Peer) -> None:
    col = Collector()
    with make_link(peer.path, col) as link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: handshake_done(peer), 5.0)
        before = len(col.seqs())
        good = frame(7)
        bad_cs = good[:-4] + (b"00" if good[-4:-2] != b"00" else b"11") + b"\r\n"
        peer.send(bad_cs)  # wrong checksum
        peer.send(b"\x00\xff\xfe binary junk \x01")  # noise
        peer.send(b"$PGMRA,1,2,3*" + b"\r\n")  # malformed checksum
        peer.send(encode_body_line("PGMRA,5,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950"))  # fields
        peer.send(encode_body_line("PGMRA,5,87.3,-1.2,0.4,3101,2470,3311,2470,2452,9999,06"))
        assert wait_until(lambda: link.counters.bad_lines_total >= 5, 5.0)
        assert wait_until(lambda: len(col.seqs()) >= before + 20, 5.0)
        bad = link.counters.bad_lines
        assert bad["checksum"] == 1
        assert bad["noise"] == 1
        assert bad["no_checksum"] == 1
        assert bad["fields"] == 1
        assert bad["range"] == 1
        assert link.counters.lost_frames == 0  # garbage between frames loses no frame
        assert link.state is LinkState.STREAMING


def encode_body_line(body: str) -> bytes:
    from bridge.protocol.framing import render_line

    return render_line(body)


def test_seq_gaps_count_lost_frames_across_wrap(peer: Peer) -> None:
    col = Collector()
    peer.set_seq(65530)  # the gaps below straddle the 65535 -> 0 wrap
    with make_link(peer.path, col) as link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: handshake_done(peer), 5.0)
        assert wait_until(lambda: len(col.seqs()) >= 3, 5.0)
        peer.skip(4)
        n = len(col.seqs())
        assert wait_until(lambda: len(col.seqs()) >= n + 3, 5.0)
        peer.skip(11)
        n = len(col.seqs())
        assert wait_until(lambda: len(col.seqs()) >= n + 3, 5.0)
        seqs = col.seqs()
        expected_lost = sum((b - a - 1) % 65536 for a, b in itertools.pairwise(seqs))
        assert expected_lost == 15
        assert link.counters.lost_frames == 15
        assert 65535 in seqs or any(s < 100 for s in seqs)  # it did wrap
        assert link.counters.device_resets == 0


def test_one_lost_frame_at_the_wrap_is_a_loss_not_a_reset(peer: Peer) -> None:
    """65500..65534, 65535 lost, 0..39 is a wrap with one frame lost (it was once read as a
    device reset, and the connect handshake ran again)."""
    col = Collector()
    peer.lose = {65535}
    peer.set_seq(65500)
    with make_link(peer.path, col) as link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: handshake_done(peer), 5.0)
        assert wait_until(lambda: 39 in col.seqs(), 5.0)
        seqs = col.seqs()
        first = seqs[0]
        assert 65500 <= first < 65534  # the link saw the frames before the wrap
        assert seqs[: seqs.index(39) + 1] == [*range(first, 65535), *range(40)]
        c = link.counters
        assert c.lost_frames == 1
        assert c.device_resets == 0 and c.seq_discontinuities == 0
        time.sleep(0.3)  # a re-run handshake would have sent its VER by now
        assert len(peer.received("VER")) == 1 and len(peer.received("PAR,GET")) == 1


def test_seq_restart_at_0_from_far_away_is_still_a_reset(peer: Peer) -> None:
    """Next to the wrap rule: 0 after a frame well before 65535 is the reboot rule's."""
    col = Collector()
    peer.set_seq(65000)  # 535 frames before the wrap: not loss a streaming link shows
    with make_link(peer.path, col) as link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: handshake_done(peer), 5.0)
        assert wait_until(lambda: len(col.seqs()) > 5, 5.0)
        peer.set_seq(0)
        assert wait_until(lambda: link.counters.device_resets == 1, 5.0)
        assert wait_until(lambda: len(peer.received("PAR,GET")) == 2, 5.0)  # handshake again
        assert link.counters.lost_frames == 0


def test_device_reset_by_unasked_version_and_by_seq_restart(peer: Peer) -> None:
    col = Collector()
    with make_link(peer.path, col) as link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: handshake_done(peer), 5.0)
        time.sleep(1.3)  # past the window in which a $PGMRV may still answer our VER
        assert wait_until(lambda: len(col.seqs()) > 20, 5.0)
        # A reboot as the datasheet describes it: $PGMRV unasked, then seq from 0.
        peer.reboot(0.3)
        assert wait_until(lambda: link.counters.device_resets == 1, 5.0)
        # The rebooted device is back at 10 Hz: the link redoes VER/RATE/PAR,GET.
        assert wait_until(lambda: len(peer.received("PAR,GET")) == 2, 5.0)
        assert len(peer.received("RATE")) == 2
        time.sleep(1.3)
        # A reboot whose $PGMRV was lost on the line: seq restarts at 0 all the same.
        assert wait_until(lambda: peer.seq > 20, 5.0)
        peer.set_seq(0)
        assert wait_until(lambda: link.counters.device_resets == 2, 5.0)
        assert link.counters.lost_frames == 0  # restarts are not losses
        assert link.counters.unsolicited_answers == 0


# ---------------------------------------------------------------------------- loss, stale


def test_silent_port_goes_stale_then_recovers(peer: Peer) -> None:
    col = Collector()
    with make_link(peer.path, col, stale_after=0.4) as link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        peer.streaming = False
        assert link.wait_state(LinkState.STALE, 5.0)
        # The link closes and reopens a stale port: another open of the same path.
        assert wait_until(lambda: link.counters.reconnects >= 1, 5.0)
        t_resume = time.monotonic()
        peer.streaming = True
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert time.monotonic() - t_resume < 5.0
        assert link.counters.stale_events >= 1
    stale_changes = [s for s in col.states if s[1] is LinkState.STALE]
    # Reopening while still silent does not flap the state (each change logged once).
    assert len(stale_changes) == 1


def test_garbage_only_port_goes_stale(peer: Peer) -> None:
    with make_link(peer.path, stale_after=0.4) as link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        peer.streaming = False
        stop = time.monotonic() + 1.5
        while time.monotonic() < stop and link.state is not LinkState.STALE:
            peer.send(b"$PGMRA,garbage*00\r\n\x13\x37")
            time.sleep(0.05)
        assert link.state is LinkState.STALE
        assert link.counters.bad_lines_total > 0


def test_close_is_bounded_and_releases_the_port(peer: Peer) -> None:
    link = make_link(peer.path).start()
    assert link.wait_state(LinkState.STREAMING, 5.0)
    t0 = time.monotonic()
    link.close()
    assert time.monotonic() - t0 < 2.5
    assert not any(t.name.startswith("compass-link") for t in threading.enumerate())
    # The exclusive lock is gone: the port can be opened again.
    again = SerialTransport(str(peer.path), 115200)
    again.open()
    again.close()


def test_lagging_consumer_loses_oldest_frames_only(peer: Peer) -> None:
    col = Collector()
    with make_link(peer.path, col, queue_size=5) as link:
        assert wait_until(lambda: len(col.seqs()) >= 40, 5.0)
        delivered = len(col.items)
        drops = link.counters.consumer_drops
        queued = [link.get(timeout=0) for _ in range(5)]
    assert delivered - 5 <= drops <= len(col.items) - 5
    assert all(q is not None for q in queued)
    newest = [q.frame for q in queued if q is not None]
    # What is left is a run of the newest frames, in order.
    idx = [i.frame for i in col.items].index(newest[0])
    assert [i.frame for i in col.items[idx : idx + 5]] == newest


def test_without_a_queue_every_frame_goes_to_on_frame_only(peer: Peer) -> None:
    """queue_size=0 (the daemon's set-up): the reader hands frames to on_frame and keeps
    no queue, so nothing is ever counted as dropped for want of a consumer."""
    with pytest.raises(ValueError, match="on_frame"):
        make_link(peer.path, None, queue_size=0)
    col = Collector()
    with make_link(peer.path, col, queue_size=0) as link:
        assert wait_until(lambda: len(col.seqs()) >= 40, 5.0)
        assert link.get(timeout=0.05) is None
        assert link.get(timeout=None) is None  # would block forever with a queue
        assert link.counters.consumer_drops == 0
    seqs = col.seqs()
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # in order, none lost


# ---------------------------------------------------------------------------- commands


def test_lost_command_is_retried(peer: Peer) -> None:
    peer.handlers["VER"] = lambda cmd, n: None if n in (1, 2) else default_reply(cmd)
    with make_link(peer.path, rate_hz=None) as link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        # The handshake's VER was the first two; wait for it to settle.
        assert wait_until(lambda: handshake_done(peer), 5.0)
        assert len(peer.received("VER")) == 3
        assert link.version == VERSION
        assert link.counters.command_retries == 2
        peer.handlers["MAGCAL,START"] = lambda cmd, n: (
            None if n == 1 else [(0.0, encode(AckFrame.success("MAGCAL")))]
        )
        ans = link.command("MAGCAL", "START", timeout=0.3, retries=1)
        assert ans == AckFrame.success("MAGCAL")
        assert len(peer.received("MAGCAL,START")) == 2
        assert link.counters.command_retries == 3


def test_command_times_out_after_all_attempts(peer: Peer) -> None:
    peer.handlers["ACCCAL"] = lambda cmd, n: None
    with make_link(peer.path) as link:
        assert wait_until(lambda: handshake_done(peer), 5.0)
        t0 = time.monotonic()
        with pytest.raises(CommandTimeout):
            link.command("ACCCAL", timeout=0.15, retries=2)
        assert time.monotonic() - t0 >= 0.45
        assert len(peer.received("ACCCAL")) == 3
        assert link.counters.command_timeouts == 1
        assert link.state is LinkState.STREAMING  # frames kept flowing


def test_err_answer_raises_rejected_without_retry(peer: Peer) -> None:
    peer.handlers["MAGCAL,END"] = lambda cmd, n: [
        (0.0, encode(AckFrame.failure("MAGCAL", "RANGE")))
    ]
    with make_link(peer.path) as link:
        assert wait_until(lambda: handshake_done(peer), 5.0)
        with pytest.raises(CommandRejected) as err:
            link.command("MAGCAL", "END")
        assert err.value.reason == "RANGE"
        assert len(peer.received("MAGCAL,END")) == 1
        assert link.counters.command_rejections == 1


def test_default_timeouts_follow_the_datasheet(peer: Peer) -> None:
    # ACCCAL may take 1.5 s: an answer after 0.9 s is on time, no retry.
    acccal = AckFrame.acccal_ok(2458.0, 2459.0, 2949.5)
    peer.handlers["ACCCAL"] = lambda cmd, n: [(0.9, encode(acccal))]
    col = Collector()
    with make_link(peer.path, col) as link:
        assert wait_until(lambda: handshake_done(peer), 5.0)
        n0 = len(col.seqs())
        assert link.command("ACCCAL") == acccal
        assert len(peer.received("ACCCAL")) == 1
        assert len(col.seqs()) - n0 >= 20  # ~45 frames at 50 Hz arrived meanwhile
        # A plain command has 200 ms: an answer after 0.9 s is too late -- a time-out --
        # and, since it could still come, the command is not sent a second time.
        peer.handlers["VER"] = lambda cmd, n: [(0.9, encode(VERSION))]
        with pytest.raises(CommandLate) as late:
            link.command("VER", retries=1)
        assert late.value.answer == VERSION and late.value.late_s > 0.5
        assert len(peer.received("VER")) == 2  # handshake + 1 attempt
        assert link.counters.command_timeouts == 1 and link.counters.device_resets == 0


def test_late_answer_is_not_taken_for_a_later_command_with_the_same_word(peer: Peer) -> None:
    # MAGCAL,START's OK arrives after the link gave up; the next MAGCAL command's own
    # answer is ERR,STATE. Taking the late OK for it would report a false success.
    peer.handlers["MAGCAL,START"] = lambda cmd, n: [(0.35, encode(AckFrame.success("MAGCAL")))]
    peer.handlers["MAGCAL,ABORT"] = lambda cmd, n: [
        (0.0, encode(AckFrame.failure("MAGCAL", "STATE")))
    ]
    with make_link(peer.path) as link:
        assert wait_until(lambda: handshake_done(peer), 5.0)
        with pytest.raises(CommandTimeout):
            link.command("MAGCAL", "START", timeout=0.2, retries=0)
        with pytest.raises(CommandRejected) as err:
            link.command("MAGCAL", "ABORT", timeout=0.2, retries=0)
        assert err.value.reason == "STATE"
        assert link.counters.late_answers == 1
        # ABORT went out only after START's answer was accounted for.
        t_abort = next(t for t, c in peer.commands if c.key == "MAGCAL,ABORT")
        t_start = next(t for t, c in peer.commands if c.key == "MAGCAL,START")
        assert t_abort - t_start >= 0.35


def test_late_answer_to_another_command_is_absorbed(peer: Peer) -> None:
    peer.handlers["RATE"] = lambda cmd, n: [(0.3, encode(AckFrame.rate_ok(int(cmd.args[0]))))]
    peer.handlers["PAR,GET"] = lambda cmd, n: [(0.1, encode(PARAMS))]
    with make_link(peer.path, rate_hz=None) as link:
        assert wait_until(lambda: handshake_done(peer), 5.0)
        assert wait_until(lambda: link.params is not None, 5.0)
        with pytest.raises(CommandTimeout):
            link.command("RATE", 50, timeout=0.2, retries=0)
        # The RATE ack lands while PAR,GET is pending: it is neither its answer nor lost.
        assert link.command("PAR", "GET", timeout=0.5, retries=0) == PARAMS
        assert wait_until(lambda: link.counters.late_answers == 1, 2.0)
        assert link.counters.unsolicited_answers == 0


def test_a_late_answer_is_a_timeout_and_the_command_is_not_sent_twice(peer: Peer) -> None:
    # Answered 0.3 s after a 0.2 s deadline: a time-out carrying the answer, not resent
    # (the device ran it once); the straggling echo confuses no later RATE.
    peer.handlers["RATE"] = lambda cmd, n: [(0.3, encode(AckFrame.rate_ok(int(cmd.args[0]))))]
    with make_link(peer.path, rate_hz=None) as link:
        assert wait_until(lambda: handshake_done(peer), 5.0)
        with pytest.raises(CommandLate) as late:
            link.command("RATE", 20, timeout=0.2, retries=1)
        assert late.value.answer == AckFrame.rate_ok(20)
        assert len(peer.received("RATE")) == 1
        assert link.counters.late_answers == 1 and link.counters.command_retries == 0
        peer.handlers["RATE"] = lambda cmd, n: [(0.0, encode(AckFrame.rate_ok(int(cmd.args[0]))))]
        assert link.command("RATE", 5) == AckFrame.rate_ok(5)
        assert link.counters.unsolicited_answers == 0


def test_command_argument_and_protocol_errors(peer: Peer) -> None:
    with make_link(peer.path) as link, pytest.raises(ValueError):
        link.command("PAR", "SET*1")  # would corrupt the sentence
    link = make_link(peer.path)
    with pytest.raises(LinkDown):  # not started: no port
        link.command("VER")


def test_heading_only_compass_streams_without_commands(peer: Peer) -> None:
    peer.streaming = False
    col = Collector()
    with make_link(peer.path, col, protocol="nmea", stale_after=1.0) as link:
        with pytest.raises(CommandNotSupported):
            link.command("VER")
        for i in range(10):
            peer.send(encode_heading(HeadingFrame.hdm(100.0 + i)), delay=0.05 * i)
        peer.send(encode(AttitudeFrame(1, 1.0, 0.0, 0.0, 1, 1, 1, 1, 1, 1, Flags(0))))
        assert wait_until(lambda: len(col.items) == 10, 5.0)
        # Its heading sentences are its stream (kept up for a quarter of stale_after).
        assert link.state is LinkState.STREAMING
        assert link.counters.attitude_frames == 10
        headings = [i.frame.heading_deg for i in col.items if isinstance(i.frame, HeadingFrame)]
        assert headings == [100.0 + i for i in range(10)]
        assert wait_until(lambda: link.counters.bad_lines["unknown_id"] == 1, 2.0)
    assert peer.received() == []  # no handshake sent to a heading-only compass


# ---------------------------------------------------------------------------- simulated device


def test_in_process_sim_handshake_rate_and_reset() -> None:
    fw = make_firmware(seed=4)
    col = Collector()
    link = CompassLink(SimTransport(fw), rate_hz=50, stale_after=1.0, on_frame=col.on_frame)
    with link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: link.params is not None, 5.0)
        assert link.version == fw.version
        assert link.params == ParamsFrame.factory()
        assert wait_until(lambda: fw.rate_hz == 50, 2.0)
        n0, t0 = len(col.seqs()), time.monotonic()
        assert wait_until(lambda: len(col.seqs()) >= n0 + 40, 5.0)
        assert time.monotonic() - t0 < 2.0  # 40 frames at 50 Hz, not at the 10 Hz power-up rate
        ack = link.command("RESET")
        assert ack == AckFrame.success("RESET")
        assert wait_until(lambda: link.counters.device_resets == 1, 5.0)
        # After the reboot the link re-applies its rate (the device came back at 10 Hz).
        assert wait_until(lambda: fw.rate_hz == 50 and link.counters.commands_sent >= 7, 5.0)
        assert link.counters.lost_frames == 0
        assert link.counters.bad_lines_total == 0
        assert wait_until(lambda: len(col.seqs()) - col.seqs().index(0, 1) >= 5, 5.0)
        seqs = col.seqs()
        restart = seqs.index(0, 1)
        assert seqs[restart - 1] != 65535 and seqs[restart:][:5] == [0, 1, 2, 3, 4]


@pytest.fixture
def sim_path(tmp_path: Path) -> Path:
    return tmp_path / "ttySIM"


def test_pty_compass_streams_and_survives_garbage(sim_path: Path) -> None:
    fw = make_firmware(seed=6)
    col = Collector()
    with (
        PtyCompass(fw, sim_path) as sim,
        make_link(sim_path, col, rate_hz=20, stale_after=1.0) as link,
    ):
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: link.params is not None and fw.rate_hz == 20, 5.0)
        assert link.version == fw.version
        n0 = len(col.seqs())
        for _ in range(5):
            sim.garbage(200)
            time.sleep(0.05)
        assert wait_until(lambda: len(col.seqs()) >= n0 + 20, 5.0)
        c = link.counters
        assert c.bad_lines_total >= 5  # at least one drop per burst of noise
        assert c.lost_frames == 0  # noise between lines costs no frame
        assert link.state is LinkState.STREAMING
        seqs = col.seqs()
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))


@pytest.mark.parametrize("power_cycle", [False, True])
def test_pty_compass_unplug_replug(sim_path: Path, power_cycle: bool) -> None:
    fw = make_firmware(seed=7)
    col = Collector()
    with (
        PtyCompass(fw, sim_path) as sim,
        make_link(sim_path, col, rate_hz=20, stale_after=1.0) as link,
    ):
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: link.params is not None and fw.rate_hz == 20, 5.0)
        sim.unplug(1.0, power_cycle=power_cycle)
        assert link.wait_state(LinkState.ABSENT, 5.0)
        assert sim.wait_plugged(5.0) is not None
        t_replug = time.monotonic()
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert time.monotonic() - t_replug < 5.0
        # VER, RATE, PAR,GET again: a power-cycled unit is back at 10 Hz until told.
        assert wait_until(
            lambda: link.counters.commands_sent - link.counters.command_retries == 6, 5.0
        )
        assert wait_until(lambda: fw.rate_hz == 20, 5.0)
        c = link.counters
        assert c.reconnects == 1
        assert c.device_resets == 0 and c.lost_frames == 0  # nothing seen across the gap
    # Absent for a second, retrying quietly: each change once, no flapping.
    changes = [new for _, new in col.states]
    i = changes.index(LinkState.ABSENT)
    assert changes[i:] == [LinkState.ABSENT, LinkState.OPENING, LinkState.STREAMING]
    assert c.open_failures >= 1
