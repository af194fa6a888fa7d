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
import os
import threading
import time
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Any

import pytest
from harness import PARAMS, VERSION, Collector, ScriptedCompass, default_reply
from waiting import wait_until

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
    CommandFrame,
    ParamsFrame,
    encode,
)
from bridge.sim.firmware import Firmware, make_firmware
from bridge.sim.pty import PtyCompass

pytestmark = pytest.mark.integration


class Peer:
    """The harness's scripted compass (sans-I/O) served on a real pty at ``path``."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.dev = ScriptedCompass()
        self.handlers = self.dev.handlers
        self.sim = PtyCompass(self.dev, path).start()  # type: ignore[arg-type]  # the scripted compass as firmware: only receive/poll/next_event_at are called (no unplug, no garbage here)

    def received(self, key: str | None = None) -> list[CommandFrame]:
        with self.sim._lock:  # the serve thread owns the device
            return self.dev.received(key)

    @property
    def streaming(self) -> bool:
        return self.dev.streaming

    @streaming.setter
    def streaming(self, on: bool) -> None:
        with self.sim._lock:
            self.dev.streaming = on

    def close(self) -> None:
        self.sim.stop()


@pytest.fixture
def peer(tmp_path: Path) -> Iterator[Peer]:
    p = Peer(tmp_path / "ttyGMR")
    yield p
    p.close()


def make_link(path: Path, col: Collector | None = None, **kw: Any) -> CompassLink:
    kw.setdefault("stale_after", 0.5)
    col = col or Collector()
    return CompassLink(
        SerialTransport(str(path), 115200),
        on_frame=col.on_frame,
        on_state=col.on_state,
        **kw,
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
        # A command's caller is woken by its answer, not by a poll: ten answered at once
        # take nowhere near ten poll periods (a waiter once slept a second each).
        t0 = time.monotonic()
        for _ in range(10):
            assert link.command("PAR", "GET") == PARAMS
        assert time.monotonic() - t0 < 5.0
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
        n0 = len(col.seqs())
        assert wait_until(lambda: len(col.seqs()) >= n0 + 40, 5.0)  # (its pace: in memory)
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


@contextlib.contextmanager
def streaming_at_20hz(
    sim_path: Path, seed: int, col: Collector
) -> Iterator[tuple[Firmware, PtyCompass, CompassLink]]:
    """A simulated compass on a pty and a link to it (frames to ``col``), streaming at the
    20 Hz the link asked for: ``(firmware, pty compass, link)``."""
    fw = make_firmware(seed=seed)
    with (
        PtyCompass(fw, sim_path) as sim,
        make_link(sim_path, col, rate_hz=20, stale_after=1.0) as link,
    ):
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: link.params is not None and fw.rate_hz == 20, 5.0)
        yield fw, sim, link


def test_pty_compass_streams_and_survives_garbage(sim_path: Path) -> None:
    col = Collector()
    with streaming_at_20hz(sim_path, 6, col) as (fw, sim, link):
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
    col = Collector()
    with streaming_at_20hz(sim_path, 7, col) as (fw, sim, link):
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


def _open_files() -> list[str]:
    """What this process has open of the kind a serial link and the simulator open: ptys
    (the port, the simulator's side) and pipes (pyserial's, to cancel a read). Not the
    rest: in a pytest-xdist worker, what earlier tests left may close meanwhile."""
    out = []
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):  # the listing's own descriptor is gone by now
            target = os.readlink(f"/proc/self/fd/{fd}")
            if target.startswith(("/dev/pts/", "/dev/ptmx", "pipe:")):
                out.append(target)
    return sorted(out)


def test_an_adapter_that_drops_out_again_and_again_leaves_no_file_or_thread_behind(
    sim_path: Path,
) -> None:
    """A USB-serial adapter shaken loose in flight comes and goes many times: after each
    return the link is streaming again with the threads and open files it had after the
    first (a descriptor or a reader thread per reconnect would add up over a flight)."""
    col = Collector()
    with streaming_at_20hz(sim_path, 9, col) as (_fw, sim, link):

        def reconnected(times: int) -> bool:
            return link.counters.reconnects == times

        def frames_after(n: int) -> bool:
            return len(col.seqs()) >= n + 5

        counts: list[tuple[int, int]] = []
        for cycle in range(5):
            sim.unplug(0.3)
            assert link.wait_state(LinkState.ABSENT, 5.0)
            assert sim.wait_plugged(5.0) is not None
            assert link.wait_state(LinkState.STREAMING, 5.0)
            assert wait_until(partial(reconnected, cycle + 1), 5.0)
            assert wait_until(partial(frames_after, len(col.seqs())), 5.0)  # frames again
            counts.append((len(_open_files()), threading.active_count()))
        # none more than after the first return (fewer: an earlier test's, closed meanwhile)
        assert all(n <= counts[0][0] and k <= counts[0][1] for n, k in counts), (
            counts,
            _open_files(),
        )
        assert link.counters.lost_frames == 0


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
