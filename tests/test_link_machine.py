"""The link machine in memory (tests/harness.py): a scripted device or the simulated firmware
on its other end, one manual clock, no threads, no sleeps.

Streaming and its counters, garbage, sequence gaps across the wrap, device resets, silence
and staleness, command retries, time-outs, rejections, the datasheet's deadlines, late
answers, heading-only compasses, and the simulated firmware's handshake, rate and RESET.
"""

from __future__ import annotations

import itertools
from typing import Any

import pytest
from harness import (
    PARAMS,
    VERSION,
    LinkHarness,
    ScriptedCompass,
    attitude_line,
    default_reply,
)

from bridge.protocol.device import (
    CommandLate,
    CommandNotSupported,
    CommandRejected,
    CommandTimeout,
    LinkDown,
    LinkState,
)
from bridge.protocol.framing import render_line
from bridge.protocol.gmr import AckFrame, AttitudeFrame, Flags, ParamsFrame, encode
from bridge.protocol.heading import HeadingFrame
from bridge.protocol.heading import encode as encode_heading
from bridge.protocol.link import LinkMachine
from bridge.sim.firmware import make_firmware


def scripted(**kw: Any) -> tuple[LinkHarness, ScriptedCompass]:
    kw.setdefault("stale_after", 0.5)
    dev = ScriptedCompass()
    return LinkHarness(dev, **kw), dev


def handshake_done(dev: ScriptedCompass) -> bool:
    return len(dev.received("PAR,GET")) >= 1


def streaming(h: LinkHarness) -> bool:
    return h.state is LinkState.STREAMING


# ---------------------------------------------------------------------------- streaming


def test_streams_frames_runs_handshake_and_counts() -> None:
    h, dev = scripted(rate_hz=20)
    col = h.collector
    assert h.run_until(lambda: streaming(h), 5.0)
    assert h.run_until(lambda: handshake_done(dev) and h.machine.params is not None, 5.0)
    assert h.run_until(lambda: len(col.seqs()) >= 30, 5.0)
    assert [c.key for c in dev.received()][:3] == ["VER", "RATE", "PAR,GET"]
    assert dev.received("RATE")[0].args == ("20",)
    assert h.machine.version == VERSION
    assert h.machine.params == PARAMS
    c = h.counters
    assert c.lost_frames == 0 and c.device_resets == 0 and c.bad_lines_total == 0
    assert c.attitude_frames >= 30
    assert c.frames == c.attitude_frames + 3  # + $PGMRV, $PGMRK,RATE, $PGMRP
    assert c.command_retries == 0 and c.late_answers == 0 and c.unsolicited_answers == 0
    seqs = col.seqs()
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # in order, none missing
    assert col.states[0] == (LinkState.ABSENT, LinkState.OPENING)
    assert (LinkState.OPENING, LinkState.STREAMING) in col.states
    # Each frame carries the instant its last byte was read.
    times = [i.t for i in col.items if isinstance(i.frame, AttitudeFrame)]
    assert times == sorted(times) and times[-1] - times[0] == pytest.approx(
        (len(times) - 1) * dev.period
    )


def test_quiet_only_while_streaming_with_no_command_in_flight() -> None:
    # What a driver reading in bursts asks before it lets bytes wait in the port's buffer.
    h, dev = scripted(rate_hz=20)
    assert not h.machine.quiet  # not streaming yet
    assert h.run_until(lambda: streaming(h), 5.0)
    assert h.run_until(lambda: handshake_done(dev) and h.machine.params is not None, 5.0)
    assert h.machine.quiet
    dev.handlers["PAR,GET"] = lambda cmd, n: [(0.2, encode(PARAMS))]  # answered 0.2 s later
    command = h.submit("PAR", "GET")
    assert not h.machine.quiet  # a command in flight: its answer must not wait
    assert h.run_until(lambda: command.done, 5.0) and command.result() == PARAMS
    assert h.machine.quiet
    dev.streaming = False
    assert h.run_until(lambda: h.machine.state is LinkState.STALE, 5.0)
    assert not h.machine.quiet


def test_the_second_attitude_frame_makes_a_stream_answers_do_not() -> None:
    dev = ScriptedCompass()
    dev.streaming = False
    h = LinkHarness(dev, rate_hz=None, stale_after=0.5)
    assert h.run_until(lambda: handshake_done(dev) and h.machine.params is not None, 0.3)
    assert h.state is LinkState.OPENING  # answers are not a stream
    dev.send(attitude_line(1))
    h.run_for(0.01)
    assert h.state is LinkState.OPENING  # one frame is not a stream either
    dev.send(attitude_line(2))
    h.run_for(0.01)
    assert h.state is LinkState.STREAMING


def test_garbage_is_counted_by_reason_and_frames_keep_flowing() -> None:
    h, dev = scripted()
    assert h.run_until(lambda: streaming(h) and handshake_done(dev), 5.0)
    before = len(h.collector.seqs())
    good = attitude_line(7)
    bad_cs = good[:-4] + (b"00" if good[-4:-2] != b"00" else b"11") + b"\r\n"
    dev.send(bad_cs)  # wrong checksum
    dev.send(b"\x00\xff\xfe binary junk \x01")  # noise
    dev.send(b"$PGMRA,1,2,3*" + b"\r\n")  # malformed checksum
    dev.send(render_line("PGMRA,5,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950"))  # fields
    dev.send(render_line("PGMRA,5,87.3,-1.2,0.4,3101,2470,3311,2470,2452,9999,06"))
    assert h.run_until(lambda: h.counters.bad_lines_total >= 5, 1.0)
    assert h.run_until(lambda: len(h.collector.seqs()) >= before + 20, 1.0)
    bad = h.counters.bad_lines
    assert bad["checksum"] == 1
    assert bad["noise"] == 1
    assert bad["no_checksum"] == 1
    assert bad["fields"] == 1
    assert bad["range"] == 1
    assert h.counters.lost_frames == 0  # garbage between frames loses no frame
    assert h.state is LinkState.STREAMING


def test_seq_gaps_count_lost_frames_across_wrap() -> None:
    dev = ScriptedCompass()
    dev.set_seq(65530)  # the gaps below straddle the 65535 -> 0 wrap
    h = LinkHarness(dev, stale_after=0.5)
    col = h.collector
    assert h.run_until(lambda: streaming(h) and handshake_done(dev) and len(col.seqs()) >= 3)
    dev.skip(4)
    n = len(col.seqs())
    assert h.run_until(lambda: len(col.seqs()) >= n + 3)
    dev.skip(11)
    n = len(col.seqs())
    assert h.run_until(lambda: len(col.seqs()) >= n + 3)
    seqs = col.seqs()
    assert sum((b - a - 1) % 65536 for a, b in itertools.pairwise(seqs)) == 15
    assert h.counters.lost_frames == 15
    assert 65535 in seqs or any(s < 100 for s in seqs)  # it did wrap
    assert h.counters.device_resets == 0


def test_one_lost_frame_at_the_wrap_is_a_loss_not_a_reset() -> None:
    """65500..65534, 65535 lost, 0..39 is a wrap with one frame lost (it was once read as a
    device reset, and the connect handshake ran again)."""
    dev = ScriptedCompass()
    dev.lose = {65535}
    dev.set_seq(65500)
    h = LinkHarness(dev, stale_after=0.5)
    assert h.run_until(lambda: 39 in h.collector.seqs())
    seqs = h.collector.seqs()
    assert seqs[: seqs.index(39) + 1] == [*range(65500, 65535), *range(40)]
    c = h.counters
    assert c.lost_frames == 1
    assert c.device_resets == 0 and c.seq_discontinuities == 0
    h.run_for(0.3)  # a re-run handshake would have sent its VER by now
    assert len(dev.received("VER")) == 1 and len(dev.received("PAR,GET")) == 1


def test_seq_restart_at_0_from_far_away_is_still_a_reset() -> None:
    """Next to the wrap rule: 0 after a frame well before 65535 is the reboot rule's."""
    dev = ScriptedCompass()
    dev.set_seq(65000)  # 535 frames before the wrap: not loss a streaming link shows
    h = LinkHarness(dev, stale_after=0.5)
    assert h.run_until(lambda: handshake_done(dev) and len(h.collector.seqs()) > 5)
    dev.set_seq(0)
    assert h.run_until(lambda: h.counters.device_resets == 1, 1.0)
    assert h.run_until(lambda: len(dev.received("PAR,GET")) == 2, 1.0)  # handshake again
    assert h.counters.lost_frames == 0


def test_device_reset_by_unasked_version_and_by_seq_restart() -> None:
    h, dev = scripted()
    assert h.run_until(lambda: streaming(h) and handshake_done(dev))
    h.run_for(2.3)  # past the window in which a $PGMRV may still answer our VER
    # A reboot as the datasheet describes it: $PGMRV unasked, then seq from 0.
    dev.reboot(0.3)
    assert h.run_until(lambda: h.counters.device_resets == 1, 1.0)
    assert h.collector.seqs()[-1] == 0
    # The rebooted device is back at 10 Hz: the link redoes VER/RATE/PAR,GET.
    assert h.run_until(lambda: len(dev.received("PAR,GET")) == 2, 1.0)
    assert len(dev.received("RATE")) == 2
    h.run_for(2.3)
    # A reboot whose $PGMRV was lost on the line: seq restarts at 0 all the same.
    dev.set_seq(0)
    assert h.run_until(lambda: h.counters.device_resets == 2, 1.0)
    assert h.counters.lost_frames == 0  # restarts are not losses
    assert h.counters.unsolicited_answers == 0


def test_an_unasked_version_with_frames_going_on_is_not_a_reset() -> None:
    h, dev = scripted(stale_after=2.0)
    assert h.run_until(lambda: streaming(h) and handshake_done(dev))
    h.run_for(2.5)  # past the window in which a $PGMRV may answer our VER
    dev.send(encode(VERSION))  # a late answer, or a chatty firmware: the stream goes on
    assert h.run_until(lambda: h.counters.unsolicited_answers == 1, 1.0)
    n = len(h.collector.seqs())
    assert h.run_until(lambda: len(h.collector.seqs()) >= n + 10, 1.0)
    assert h.counters.device_resets == 0 and h.counters.lost_frames == 0
    assert len(dev.received("VER")) == 1  # no handshake re-run
    # A real reboot still is one: $PGMRV, then seq from 0.
    dev.reboot(0.3)
    assert h.run_until(lambda: h.counters.device_resets == 1, 1.0)


def test_a_version_racing_our_ver_is_not_a_reset() -> None:
    """A power-up $PGMRV doubling the answer to the handshake's VER is not news."""
    h, dev = scripted()
    dev.handlers["VER"] = lambda cmd, n: [(0.0, encode(VERSION)), (0.05, encode(VERSION))]
    assert h.run_until(lambda: streaming(h) and handshake_done(dev))
    h.run_for(1.0)
    c = h.counters
    assert c.device_resets == 0 and c.unsolicited_answers == 0 and c.late_answers == 0
    assert len(dev.received("VER")) == 1


# ---------------------------------------------------------------------------- loss, stale


def test_silent_port_goes_stale_then_recovers() -> None:
    h, dev = scripted(stale_after=0.4)
    assert h.run_until(lambda: streaming(h))
    dev.streaming = False
    t_silent = h.now
    assert h.run_until(lambda: h.state is LinkState.STALE)
    assert h.now - t_silent == pytest.approx(0.4, abs=0.03)  # one frame period of slack
    # The link closes and reopens a stale port (after its backoff), and stays STALE.
    assert h.run_until(lambda: h.counters.reconnects >= 1, 1.0)
    assert h.state is LinkState.STALE
    h.run_for(3.0)  # reopened again and again while silent: STALE said once
    assert h.counters.stale_events >= 2
    t_resume = h.now
    dev.streaming = True
    assert h.run_until(lambda: streaming(h), 5.0)
    assert h.now - t_resume <= 2.0  # the backoff is capped at 2 s
    stale_changes = [s for s in h.collector.states if s[1] is LinkState.STALE]
    assert len(stale_changes) == 1


def test_garbage_only_port_goes_stale() -> None:
    h, dev = scripted(stale_after=0.4)
    assert h.run_until(lambda: streaming(h))
    dev.streaming = False
    for i in range(30):
        dev.send(b"$PGMRA,garbage*00\r\n\x13\x37", delay=0.05 * i)
    assert h.run_until(lambda: h.state is LinkState.STALE, 1.5)
    assert h.counters.bad_lines_total > 0


def test_a_compass_that_answers_but_streams_nothing_is_not_streaming() -> None:
    fw = make_firmware(seed=3)
    fw.streaming = False  # its sampling died; its main loop still answers
    h = LinkHarness(fw, rate_hz=10, stale_after=0.5)
    assert h.run_until(lambda: h.state is LinkState.STALE, 5.0)
    # It keeps answering the handshake of every reopen, and keeps not streaming.
    assert h.run_until(lambda: h.counters.reconnects >= 3, 10.0)
    assert h.machine.version == fw.version and h.counters.frames >= 3
    assert h.counters.attitude_frames == 0
    assert h.state is LinkState.STALE
    assert h.collector.new_states() == [LinkState.OPENING, LinkState.STALE]  # said once
    assert "the compass answers, but streams nothing" in h.reasons[-1]


def test_a_compass_streaming_in_short_bursts_stays_stale() -> None:
    h, dev = scripted(rate_hz=None, stale_after=0.5)

    def burst(on: bool) -> None:  # 0.3 s of frames, 0.9 s of silence, again and again
        dev.streaming = on
        h.at(0.3 if on else 0.9, lambda: burst(not on))

    burst(True)
    h.run_for(10.0)
    bursts_seen = len({round(i.t) for i in h.collector.items})
    restored = [s for s in h.collector.states if s[1] is LinkState.STREAMING]
    assert bursts_seen >= 3  # frames did come through, burst after burst
    # Each short spell doubles the time frames must keep coming: two spells at most,
    # then the link stays stale through every burst.
    assert len(restored) <= 2, h.collector.states
    assert h.state is not LinkState.STREAMING
    # Frames that keep coming bring it back.
    h.clear_timers()
    dev.streaming = True
    assert h.run_until(lambda: streaming(h), 5.0)


def test_unplugged_port_is_absent_retried_quietly_and_back() -> None:
    h, dev = scripted(rate_hz=20, stale_after=1.0)
    assert h.run_until(lambda: streaming(h) and handshake_done(dev))
    h.unplug()
    assert h.state is LinkState.ABSENT
    h.run_for(1.0)
    failures = h.counters.open_failures
    assert failures >= 3  # retried with backoff, 0.1 s doubling
    h.replug()
    assert h.run_until(lambda: streaming(h), 5.0)
    assert h.run_until(lambda: len(dev.received("PAR,GET")) == 2, 1.0)  # handshake again
    c = h.counters
    assert c.reconnects == 1 and c.device_resets == 0
    changes = h.collector.new_states()
    i = changes.index(LinkState.ABSENT)
    assert changes[i:] == [LinkState.ABSENT, LinkState.OPENING, LinkState.STREAMING]


# ---------------------------------------------------------------------------- commands


def test_lost_command_is_retried() -> None:
    dev = ScriptedCompass()
    dev.handlers["VER"] = lambda cmd, n: None if n in (1, 2) else default_reply(cmd)
    h = LinkHarness(dev, rate_hz=None, stale_after=0.5)
    assert h.run_until(lambda: streaming(h) and handshake_done(dev), 10.0)
    assert len(dev.received("VER")) == 3
    assert h.machine.version == VERSION
    assert h.counters.command_retries == 2
    dev.handlers["MAGCAL,START"] = lambda cmd, n: (
        None if n == 1 else [(0.0, encode(AckFrame.success("MAGCAL")))]
    )
    ans = h.command("MAGCAL", "START", timeout=0.3, retries=1)
    assert ans == AckFrame.success("MAGCAL")
    assert len(dev.received("MAGCAL,START")) == 2
    assert h.counters.command_retries == 3
    # The retry went out only when the first attempt's answer could no longer come.
    (t1, _), (t2, _) = [(t, c) for t, c in dev.commands if c.key == "MAGCAL,START"]
    assert t2 - t1 == pytest.approx(0.3 + 2.0)


def test_command_times_out_after_all_attempts() -> None:
    h, dev = scripted(late_answer_window=0.1)
    dev.handlers["ACCCAL"] = lambda cmd, n: None
    assert h.run_until(lambda: handshake_done(dev))
    t0 = h.now
    with pytest.raises(CommandTimeout):
        h.command("ACCCAL", timeout=0.15, retries=2)
    assert h.now - t0 == pytest.approx(3 * 0.15 + 2 * 0.1)
    assert len(dev.received("ACCCAL")) == 3
    assert h.counters.command_timeouts == 1
    assert h.state is LinkState.STREAMING  # frames kept flowing


def test_err_answer_raises_rejected_without_retry() -> None:
    h, dev = scripted()
    dev.handlers["MAGCAL,END"] = lambda cmd, n: [(0.0, encode(AckFrame.failure("MAGCAL", "RANGE")))]
    assert h.run_until(lambda: handshake_done(dev))
    with pytest.raises(CommandRejected) as err:
        h.command("MAGCAL", "END")
    assert err.value.reason == "RANGE"
    assert len(dev.received("MAGCAL,END")) == 1
    assert h.counters.command_rejections == 1


def test_default_timeouts_follow_the_datasheet() -> None:
    # ACCCAL may take 1.5 s: an answer after 0.9 s is on time, no retry.
    h, dev = scripted()
    acccal = AckFrame.acccal_ok(2458.0, 2459.0, 2949.5)
    dev.handlers["ACCCAL"] = lambda cmd, n: [(0.9, encode(acccal))]
    col = h.collector
    assert h.run_until(lambda: handshake_done(dev))
    n0 = len(col.seqs())
    assert h.command("ACCCAL") == acccal
    assert len(dev.received("ACCCAL")) == 1
    assert len(col.seqs()) - n0 >= 44  # 45 frames at 50 Hz arrived meanwhile
    # A plain command has 200 ms: an answer after 0.9 s is too late -- a time-out --
    # and, since it could still come, the command is not sent a second time.
    dev.handlers["VER"] = lambda cmd, n: [(0.9, encode(VERSION))]
    with pytest.raises(CommandLate) as late:
        h.command("VER", retries=1)
    assert late.value.answer == VERSION and late.value.late_s > 0.5
    assert len(dev.received("VER")) == 2  # handshake + 1 attempt
    assert h.counters.command_timeouts == 1 and h.counters.device_resets == 0


def test_default_timeout_adds_the_line_times_at_the_baud() -> None:
    m = LinkMachine()
    from bridge.protocol.gmr import CommandFrame

    ver = CommandFrame("VER", ())
    assert m.default_timeout(ver) == pytest.approx(0.2)
    slow = m.default_timeout(ver, 4800)
    assert 0.2 + 0.05 < slow < 0.2 + 2.0  # two full lines at 4800 baud
    assert m.default_timeout(CommandFrame("ACCCAL", ())) == pytest.approx(1.5)


def test_late_answer_is_not_taken_for_a_later_command_with_the_same_word() -> None:
    # MAGCAL,START's OK arrives after the link gave up; the next MAGCAL command's own
    # answer is ERR,STATE. Taking the late OK for it would report a false success.
    h, dev = scripted()
    dev.handlers["MAGCAL,START"] = lambda cmd, n: [(0.35, encode(AckFrame.success("MAGCAL")))]
    dev.handlers["MAGCAL,ABORT"] = lambda cmd, n: [
        (0.0, encode(AckFrame.failure("MAGCAL", "STATE")))
    ]
    assert h.run_until(lambda: handshake_done(dev))
    with pytest.raises(CommandTimeout):
        h.command("MAGCAL", "START", timeout=0.2, retries=0)
    with pytest.raises(CommandRejected) as err:
        h.command("MAGCAL", "ABORT", timeout=0.2, retries=0)
    assert err.value.reason == "STATE"
    assert h.counters.late_answers == 1
    # ABORT went out only after START's answer was accounted for.
    t_abort = next(t for t, c in dev.commands if c.key == "MAGCAL,ABORT")
    t_start = next(t for t, c in dev.commands if c.key == "MAGCAL,START")
    assert t_abort - t_start >= 0.35


def test_a_command_waits_for_a_late_answer_of_its_word_only_while_it_may_come() -> None:
    h, dev = scripted(late_answer_window=0.5)
    dev.handlers["MAGCAL,START"] = lambda cmd, n: None  # lost: never answered
    dev.handlers["MAGCAL,ABORT"] = lambda cmd, n: [(0.0, encode(AckFrame.success("MAGCAL")))]
    assert h.run_until(lambda: handshake_done(dev))
    with pytest.raises(CommandTimeout):
        h.command("MAGCAL", "START", timeout=0.2, retries=0)
    t0 = h.now
    assert h.command("MAGCAL", "ABORT", timeout=0.2, retries=0) == AckFrame.success("MAGCAL")
    t_abort = next(t for t, c in dev.commands if c.key == "MAGCAL,ABORT")
    assert t_abort - t0 == pytest.approx(0.5)  # the slot's late window, then it went


def test_late_answer_to_another_command_is_absorbed() -> None:
    h, dev = scripted(rate_hz=None)
    dev.handlers["RATE"] = lambda cmd, n: [(0.3, encode(AckFrame.rate_ok(int(cmd.args[0]))))]
    dev.handlers["PAR,GET"] = lambda cmd, n: [(0.1, encode(PARAMS))]
    assert h.run_until(lambda: handshake_done(dev) and h.machine.params is not None)
    with pytest.raises(CommandTimeout):
        h.command("RATE", 50, timeout=0.2, retries=0)
    # The RATE ack lands while PAR,GET is pending: it is neither its answer nor lost.
    assert h.command("PAR", "GET", timeout=0.5, retries=0) == PARAMS
    assert h.run_until(lambda: h.counters.late_answers == 1, 2.0)
    assert h.counters.unsolicited_answers == 0


def test_a_late_answer_is_a_timeout_and_the_command_is_not_sent_twice() -> None:
    # Answered 0.3 s after a 0.2 s deadline: a time-out carrying the answer, not resent
    # (the device ran it once); the straggling echo confuses no later RATE.
    h, dev = scripted(rate_hz=None)
    dev.handlers["RATE"] = lambda cmd, n: [(0.3, encode(AckFrame.rate_ok(int(cmd.args[0]))))]
    assert h.run_until(lambda: handshake_done(dev))
    with pytest.raises(CommandLate) as late:
        h.command("RATE", 20, timeout=0.2, retries=1)
    assert late.value.answer == AckFrame.rate_ok(20)
    assert len(dev.received("RATE")) == 1
    assert h.counters.late_answers == 1 and h.counters.command_retries == 0
    dev.handlers["RATE"] = lambda cmd, n: [(0.0, encode(AckFrame.rate_ok(int(cmd.args[0]))))]
    assert h.command("RATE", 5) == AckFrame.rate_ok(5)
    assert h.counters.unsolicited_answers == 0


def test_an_unasked_ack_is_counted_unsolicited() -> None:
    h, dev = scripted()
    assert h.run_until(lambda: handshake_done(dev))
    h.run_for(2.5)
    dev.send(encode(AckFrame.success("MAGCAL")))
    assert h.run_until(lambda: h.counters.unsolicited_answers == 1, 1.0)
    assert h.counters.late_answers == 0


def test_commands_run_one_at_a_time_in_order() -> None:
    h, dev = scripted()
    assert h.run_until(lambda: handshake_done(dev))
    dev.handlers["MAGCAL,START"] = lambda cmd, n: [(0.1, encode(AckFrame.success("MAGCAL")))]
    first = h.submit("MAGCAL", "START")
    second = h.submit("PAR", "GET")
    assert h.run_until(lambda: first.done and second.done, 2.0)
    assert first.result() == AckFrame.success("MAGCAL") and second.result() == PARAMS
    t_start = next(t for t, c in dev.commands if c.key == "MAGCAL,START")
    t_get = [t for t, c in dev.commands if c.key == "PAR,GET"][-1]
    assert t_get - t_start >= 0.1  # PAR,GET went after START's answer


def test_command_argument_and_protocol_errors() -> None:
    h, _ = scripted()
    with pytest.raises(ValueError):
        h.command("PAR", "SET*1")  # would corrupt the sentence
    m = LinkMachine()
    from bridge.protocol.gmr import CommandFrame

    # Not started: no port, so the command ends at once.
    txn = m.submit(CommandFrame("VER", ()), 0.0, 0.2)
    assert txn.done
    with pytest.raises(LinkDown):
        txn.result()


def test_a_closing_link_ends_waiting_commands() -> None:
    h, dev = scripted()
    dev.handlers["ACCCAL"] = lambda cmd, n: None
    assert h.run_until(lambda: handshake_done(dev))
    txn = h.submit("ACCCAL")
    queued = h.submit("VER")
    h.run_for(0.1)
    h.machine.close(h.now)
    assert txn.done and queued.done
    for t in (txn, queued):
        with pytest.raises(LinkDown):
            t.result()


def test_a_port_lost_mid_command_fails_its_retry() -> None:
    h, dev = scripted(late_answer_window=0.1)
    dev.handlers["ACCCAL"] = lambda cmd, n: None
    assert h.run_until(lambda: handshake_done(dev))
    txn = h.submit("ACCCAL", timeout=0.2, retries=2)
    h.run_for(0.05)
    h.unplug()
    assert h.run_until(lambda: txn.done, 1.0)
    with pytest.raises(LinkDown):
        txn.result()
    assert len(dev.received("ACCCAL")) == 1


def test_heading_only_compass_streams_without_commands() -> None:
    dev = ScriptedCompass()
    dev.streaming = False
    h = LinkHarness(dev, protocol="nmea", stale_after=1.0)
    with pytest.raises(CommandNotSupported):
        h.command("VER")
    for i in range(10):
        dev.send(encode_heading(HeadingFrame.hdm(100.0 + i)), delay=0.05 * i)
    dev.send(encode(AttitudeFrame(1, 1.0, 0.0, 0.0, 1, 1, 1, 1, 1, 1, Flags(0))))
    assert h.run_until(lambda: len(h.collector.items) == 10, 1.0)
    # Its heading sentences are its stream.
    assert h.state is LinkState.STREAMING
    assert h.counters.attitude_frames == 10
    items = h.collector.items
    headings = [i.frame.heading_deg for i in items if isinstance(i.frame, HeadingFrame)]
    assert headings == [100.0 + i for i in range(10)]
    assert h.counters.bad_lines["unknown_id"] == 1
    assert dev.received() == []  # no handshake sent to a heading-only compass
    h.run_for(1.2)
    assert h.state is LinkState.STALE


def test_a_replay_gets_no_handshake_and_ends_absent_for_good() -> None:
    dev = ScriptedCompass()
    h = LinkHarness(dev, interactive=False, stale_after=1.0)
    assert h.run_until(lambda: streaming(h))
    h.run_for(0.5)
    assert dev.received() == []  # writes would go nowhere: none are made
    h.end("end of recording")
    assert h.state is LinkState.ABSENT and h.machine.ended
    assert h.machine.next_deadline() is None and not h.machine.open_due(h.now + 10)


def test_set_rate_is_asked_by_the_next_handshake() -> None:
    h, dev = scripted(rate_hz=10)
    assert h.run_until(lambda: handshake_done(dev))
    h.machine.set_rate(50, stale_after=1.0)
    assert h.machine.stale_after == 1.0
    with pytest.raises(ValueError):
        h.machine.set_rate(33)
    assert h.machine.rate_hz == 50
    h.unplug()
    h.replug()
    assert h.run_until(lambda: len(dev.received("RATE")) == 2, 2.0)
    assert dev.received("RATE")[-1].args == ("50",)


def test_machine_settings_are_checked() -> None:
    with pytest.raises(ValueError):
        LinkMachine(protocol="nmea2000")  # type: ignore[arg-type]  # not a protocol: refused
    with pytest.raises(ValueError):
        LinkMachine(stale_after=0)
    with pytest.raises(ValueError):
        LinkMachine(rate_hz=7)
    with pytest.raises(ValueError):
        LinkMachine(backoff_initial=3.0, backoff_max=2.0)
    m = LinkMachine()
    m.start(0.0)
    with pytest.raises(RuntimeError):
        m.start(0.0)


# ---------------------------------------------------------------------------- the firmware


def test_simulated_firmware_handshake_rate_and_reset() -> None:
    fw = make_firmware(seed=4)
    h = LinkHarness(fw, rate_hz=50, stale_after=1.0)
    col = h.collector
    assert h.run_until(lambda: streaming(h) and h.machine.params is not None and fw.rate_hz == 50)
    assert h.machine.version == fw.version
    assert h.machine.params == ParamsFrame.factory()
    n0, t0 = len(col.seqs()), h.now
    assert h.run_until(lambda: len(col.seqs()) >= n0 + 40, 2.0)
    assert h.now - t0 == pytest.approx(40 / 50, abs=0.03)  # 50 Hz, not the 10 Hz power-up rate
    assert h.command("RESET") == AckFrame.success("RESET")
    assert h.run_until(lambda: h.counters.device_resets == 1, 2.0)
    # After the reboot the link re-applies its rate (the device came back at 10 Hz).
    assert h.run_until(lambda: fw.rate_hz == 50 and h.counters.commands_sent >= 7, 2.0)
    assert h.counters.lost_frames == 0
    assert h.counters.bad_lines_total == 0
    assert h.run_until(lambda: len(col.seqs()) - col.seqs().index(0, 1) >= 5, 2.0)
    seqs = col.seqs()
    restart = seqs.index(0, 1)
    assert seqs[restart - 1] != 65535 and seqs[restart:][:5] == [0, 1, 2, 3, 4]


def test_simulated_firmware_garbage_costs_no_frame() -> None:
    fw = make_firmware(seed=6)
    h = LinkHarness(fw, rate_hz=20, stale_after=1.0)
    assert h.run_until(lambda: streaming(h) and fw.rate_hz == 20)
    n0 = len(h.collector.seqs())
    for i in range(5):
        h.at(0.05 * i, lambda: fw.inject_garbage(200))
    assert h.run_until(lambda: len(h.collector.seqs()) >= n0 + 20, 2.0)
    c = h.counters
    assert c.bad_lines_total >= 5  # at least one drop per burst of noise
    assert c.lost_frames <= 5  # noise glued to a frame may cost that frame, nothing more
    assert h.state is LinkState.STREAMING


@pytest.mark.parametrize("power_cycle", [False, True])
def test_simulated_firmware_unplug_replug(power_cycle: bool) -> None:
    fw = make_firmware(seed=7)
    h = LinkHarness(fw, rate_hz=20, stale_after=1.0)
    assert h.run_until(lambda: streaming(h) and h.machine.params is not None and fw.rate_hz == 20)
    h.unplug()
    if power_cycle:
        fw.power_off(h.now)
    assert h.state is LinkState.ABSENT
    h.run_for(1.0)
    if power_cycle:
        fw.power_on(h.now)
    h.replug()
    t_replug = h.now
    assert h.run_until(lambda: streaming(h), 5.0)
    assert h.now - t_replug < 2.5
    # VER, RATE, PAR,GET again: a power-cycled unit is back at 10 Hz until told.
    assert h.run_until(lambda: h.counters.commands_sent - h.counters.command_retries == 6, 2.0)
    assert h.run_until(lambda: fw.rate_hz == 20, 1.0)
    c = h.counters
    assert c.reconnects == 1
    assert c.device_resets == 0 and c.lost_frames == 0  # nothing seen across the gap
    changes = h.collector.new_states()
    i = changes.index(LinkState.ABSENT)
    assert changes[i:] == [LinkState.ABSENT, LinkState.OPENING, LinkState.STREAMING]
    assert c.open_failures >= 1


def test_a_late_compass_is_timing_out_not_resetting() -> None:
    fw = make_firmware(seed=4)
    fw.answer_delay_s = 1.5  # 7.5 times its 200 ms
    h = LinkHarness(fw, rate_hz=20, stale_after=1.0)
    assert h.run_until(lambda: streaming(h), 5.0)
    assert h.run_until(lambda: h.counters.late_answers >= 1, 5.0)
    h.run_for(4.0)  # long enough for a wrong reading to have reset it a few times
    c = h.counters
    assert c.device_resets == 0 and c.seq_discontinuities == 0
    # The handshake's first command answered late timed out (the handshake stops
    # there, said once) and was not sent again; its late answer was still read.
    assert c.command_retries == 0 and c.command_timeouts == 1 and c.late_answers == 1
    assert c.commands_sent <= 2  # VER (its power-up $PGMRV may answer it), RATE
    assert h.machine.version == fw.version
    assert h.state is LinkState.STREAMING


def test_a_slow_compass_runs_magcal_start_once_and_abort_leaves_it() -> None:
    fw = make_firmware(seed=5)
    h = LinkHarness(fw, rate_hz=None, stale_after=1.0)
    assert h.run_until(lambda: streaming(h) and h.machine.params is not None, 5.0)
    fw.answer_delay_s = 0.6
    with pytest.raises(CommandLate) as late:
        h.command("MAGCAL", "START", retries=1)
    assert late.value.answer == AckFrame.success("MAGCAL")  # it did start, once
    assert fw.calibrating and h.counters.command_retries == 0
    with pytest.raises(CommandLate):
        h.command("MAGCAL", "ABORT", retries=1)
    assert not fw.calibrating  # left as found
    assert h.counters.command_retries == 0 and h.counters.device_resets == 0


def test_a_wrong_baud_rate_is_noise_counted_never_a_stream() -> None:
    """A compass at 115200 read at 9600: a trickle of meaningless bytes -- counted as bad
    lines, the link STALE and reopening, no frame taken for real."""
    from harness import LinePlayer
    from test_faults_serial import uart_as_read_at

    line = attitude_line(1)
    garbled = uart_as_read_at(line * 4, 115200, 9600)
    assert garbled and b"\n" not in garbled
    dev = LinePlayer([garbled + b"\r\n"], period=0.05)  # and a line end now and then
    h = LinkHarness(dev, rate_hz=10, stale_after=1.0)
    h.run_for(5.0)
    c = h.counters
    assert c.bad_lines_total > 0 and c.attitude_frames == 0 and c.frames == 0
    assert h.state is LinkState.STALE and c.stale_events >= 2
    assert h.collector.new_states() == [LinkState.OPENING, LinkState.STALE]
    assert "no attitude frame for 1 s" in h.reasons[-1]
