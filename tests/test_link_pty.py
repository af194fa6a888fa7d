"""The link's driver (CompassLink) on real pseudo-terminals: a scripted device peer driven by
the test, or the simulated firmware behind a pty (and in process, through SimTransport).

What the link decides is tested in memory (test_link_machine.py, on tests/harness.py); these
few prove the driver on a real port: it opens the slave through pyserial as it would a USB
adapter, streams, runs the handshake and commands with their real deadlines, goes stale and
reopens, survives an unplugged adapter, and closes within its bound, releasing the port.
Every wait is bounded by a deadline.
"""

from __future__ import annotations

import contextlib
import heapq
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
from bridge.sim.firmware import make_firmware
from bridge.sim.pty import PtyCompass

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
    col = col or Collector()
    return CompassLink(
        SerialTransport(str(path), 115200),
        on_frame=col.on_frame,
        on_state=col.on_state,
        **kw,  # type: ignore[arg-type]
    )


def handshake_done(peer: Peer) -> bool:
    return len(peer.received("PAR,GET")) >= 1


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
    assert (LinkState.OPENING, LinkState.STREAMING) in col.states
    assert col.states[0] == (LinkState.ABSENT, LinkState.OPENING)


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


def test_a_failing_consumer_is_counted_and_a_waiting_command_ends_on_close(peer: Peer) -> None:
    """on_frame raising costs no frame (counted); close() ends a command still waiting."""
    errors: list[BaseException] = []
    seen: list[Received] = []

    def on_frame(item: Received) -> None:
        seen.append(item)
        try:
            link.command("VER")  # from the reader thread: refused, it would deadlock
        except RuntimeError as e:
            errors.append(e)
        raise ValueError("a consumer bug")

    peer.handlers["ACCCAL"] = lambda cmd, n: None
    link = CompassLink(SerialTransport(str(peer.path), 115200), on_frame=on_frame, stale_after=0.5)
    with link:
        assert wait_until(lambda: len(seen) >= 20, 5.0)
        assert link.counters.callback_errors >= 20
        assert errors and "reader thread" in str(errors[0])
        assert link.state is LinkState.STREAMING
        ended: list[BaseException] = []

        def waiter() -> None:
            try:
                link.command("ACCCAL", timeout=5.0, retries=0)
            except Exception as e:
                ended.append(e)

        th = threading.Thread(target=waiter)
        th.start()
        assert wait_until(lambda: len(peer.received("ACCCAL")) == 1, 5.0)
    th.join(3.0)
    assert not th.is_alive() and isinstance(ended[0], LinkDown)
