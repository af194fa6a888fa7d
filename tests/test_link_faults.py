"""The compass link against misbehaving devices: what the device and the link do, seen from
outside (a real pty; the simulated firmware or a scripted peer on its other end).

* a compass that answers every command but streams no ``$PGMRA`` is not streaming, and
  says so once (no lost / restored flapping);
* a compass streaming in short bursts stays stale instead of flapping;
* a compass answering late (outside its 200 ms) is timing out, not resetting, and no
  command is sent again while its answer may still come;
* a ``$PGMRV`` nobody asked for, after which the frames carry on, is not a reset.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from test_link_serial_link import (
    VERSION,
    Collector,
    Peer,
    handshake_done,
    make_link,
    peer,  # noqa: F401 - the fixture
    wait_until,
)

from bridge.link.serial_link import CommandLate, LinkState
from bridge.protocol.gmr import AckFrame, encode
from bridge.sim.firmware import make_firmware
from bridge.sim.pty import PtyCompass

pytestmark = pytest.mark.integration


def test_a_compass_that_answers_but_streams_nothing_is_not_streaming(tmp_path: Path) -> None:
    fw = make_firmware(seed=3)
    fw.streaming = False  # its sampling died; its main loop still answers
    col = Collector()
    path = tmp_path / "ttySILENT"
    with PtyCompass(fw, path), make_link(path, col, rate_hz=10, stale_after=0.5) as link:
        assert link.wait_state(LinkState.STALE, 5.0)
        # It keeps answering the handshake of every reopen, and keeps not streaming.
        assert wait_until(lambda: link.counters.reconnects >= 3, 10.0)
        assert link.version == fw.version and link.counters.frames >= 3
        assert link.counters.attitude_frames == 0
        assert link.state is LinkState.STALE
    states = [new for _, new in col.states]
    assert LinkState.STREAMING not in states
    assert states == [LinkState.OPENING, LinkState.STALE]  # said once, not flapping


def test_a_compass_streaming_in_short_bursts_stays_stale(peer: Peer) -> None:  # noqa: F811
    col = Collector()
    stop = threading.Event()

    def stutter() -> None:  # 0.3 s of frames, 0.9 s of silence, again and again
        while not stop.is_set():
            peer.streaming = True
            stop.wait(0.3)
            peer.streaming = False
            stop.wait(0.9)

    with make_link(peer.path, col, rate_hz=None, stale_after=0.5) as link:
        th = threading.Thread(target=stutter, daemon=True)
        th.start()
        try:
            t_end = time.monotonic() + 10.0
            while time.monotonic() < t_end:
                time.sleep(0.1)
            bursts_seen = len({round(i.t) for i in col.items})
        finally:
            stop.set()
            th.join(2.0)
        restored = [s for s in col.states if s[1] is LinkState.STREAMING]
        assert bursts_seen >= 3  # frames did come through, burst after burst
        # Each short spell doubles the time frames must keep coming: two spells at most,
        # then the link stays stale through every burst.
        assert len(restored) <= 2, col.states
        assert link.state is not LinkState.STREAMING
        # Frames that keep coming bring it back.
        peer.streaming = True
        assert link.wait_state(LinkState.STREAMING, 5.0)


def test_a_late_compass_is_timing_out_not_resetting(tmp_path: Path) -> None:
    fw = make_firmware(seed=4)
    fw.answer_delay_s = 1.5  # 7.5 times its 200 ms
    col = Collector()
    path = tmp_path / "ttyLATE"
    with PtyCompass(fw, path), make_link(path, col, rate_hz=20, stale_after=1.0) as link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: link.counters.late_answers >= 1, 5.0)
        time.sleep(4.0)  # long enough for a wrong reading to have reset it a few times
        c = link.counters
        assert c.device_resets == 0 and c.seq_discontinuities == 0
        # The handshake's first command answered late timed out (the handshake stops
        # there, said once) and was not sent again; its late answer was still read.
        assert c.command_retries == 0 and c.command_timeouts == 1 and c.late_answers == 1
        assert c.commands_sent <= 2  # VER (its power-up $PGMRV may answer it), RATE
        assert link.version == fw.version
        assert link.state is LinkState.STREAMING


def test_a_slow_compass_runs_magcal_start_once_and_abort_leaves_it(tmp_path: Path) -> None:
    fw = make_firmware(seed=5)
    path = tmp_path / "ttySLOW"
    with PtyCompass(fw, path), make_link(path, rate_hz=None, stale_after=1.0) as link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: link.params is not None, 5.0)
        fw.answer_delay_s = 0.6
        with pytest.raises(CommandLate) as late:
            link.command("MAGCAL", "START", retries=1)
        assert late.value.answer == AckFrame.success("MAGCAL")  # it did start, once
        assert fw.calibrating and link.counters.command_retries == 0
        with pytest.raises(CommandLate):
            link.command("MAGCAL", "ABORT", retries=1)
        assert not fw.calibrating  # left as found
        assert link.counters.command_retries == 0 and link.counters.device_resets == 0


def test_an_unasked_version_with_frames_going_on_is_not_a_reset(peer: Peer) -> None:  # noqa: F811
    col = Collector()
    with make_link(peer.path, col) as link:
        assert link.wait_state(LinkState.STREAMING, 5.0)
        assert wait_until(lambda: handshake_done(peer), 5.0)
        time.sleep(2.5)  # past the window in which a $PGMRV may answer our VER
        peer.send(encode(VERSION))  # a late answer, or a chatty firmware: the stream goes on
        assert wait_until(lambda: link.counters.unsolicited_answers == 1, 5.0)
        n = len(col.seqs())
        assert wait_until(lambda: len(col.seqs()) >= n + 10, 5.0)
        assert link.counters.device_resets == 0 and link.counters.lost_frames == 0
        assert len(peer.received("VER")) == 1  # no handshake re-run
        # A real reboot still is one: $PGMRV, then seq from 0.
        peer.reboot(0.3)
        assert wait_until(lambda: link.counters.device_resets == 1, 5.0)
