"""The per-frame fast path of the MAVLink output: it skips work, never behaviour.

``MavlinkOutput.publish`` returns after one comparison while no sample stream
can be due (``StreamSchedule.sample_due_at``). These tests hold that short cut
to the general schedule (a property test over random operations) and check,
on a started output with an injected clock and a real UDP ground station on
127.0.0.1, that every way a rate or the set of streams changes takes effect
with the very next sample.
"""

from __future__ import annotations

import contextlib
import math
import random
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import pytest
from harness import ManualClock
from helpers import examples
from hypothesis import given
from hypothesis import strategies as st
from test_mavlink_rig import DEADLINE_S, M, offline_daemon
from test_mavlink_telemetry import make_sample

from benchmarks.procstat import udp_socket
from bridge.app.sample import CompassSample
from bridge.core import pacing
from bridge.mavlink import schedule as S  # noqa: N812 - short
from bridge.mavlink import telemetry as T  # noqa: N812 - short
from bridge.mavlink.dialect import Message as Packet
from bridge.mavlink.output import MavlinkOutput, MavlinkSettings

SAMPLE_IDS = S.SAMPLE_STREAMS
REAL32, INT8 = M.MAV_PARAM_TYPE_REAL32, M.MAV_PARAM_TYPE_INT8
ACCEPTED = M.MAV_RESULT_ACCEPTED


# =====================================================================================
# the schedule: fast path == general path
# =====================================================================================

_rates = st.one_of(st.just(0.0), st.floats(0.1, 120.0), st.sampled_from([1.0, 10.0, 50.0, 100.0]))
_ops = st.one_of(
    st.tuples(st.just("sample"), st.floats(0.0, 0.3)),  # a sample after dt seconds
    st.tuples(st.just("sample"), st.sampled_from([0.0, 0.01, 0.02, 0.1])),
    st.tuples(st.just("base"), st.sampled_from((*SAMPLE_IDS, S.SYS_STATUS)), _rates),
    st.tuples(
        st.just("override"),
        st.sampled_from(SAMPLE_IDS),
        st.one_of(st.none(), _rates),
    ),
    st.tuples(
        st.just("streams"),
        st.lists(st.sampled_from((*SAMPLE_IDS, S.SYS_STATUS)), unique=True),
    ),
)


@examples(300)
@given(
    initial=st.dictionaries(st.sampled_from(SAMPLE_IDS), _rates),
    ops=st.lists(_ops, max_size=80),
)
def test_fast_path_gives_what_due_on_sample_gives(
    initial: dict[int, float], ops: list[tuple[Any, ...]]
) -> None:
    general, fast = S.StreamSchedule(initial), S.StreamSchedule(initial)
    ids: list[int] = list(SAMPLE_IDS)
    fast.set_sample_streams(ids)
    now = 1000.0
    for op in ops:
        kind = op[0]
        if kind == "sample":
            now += op[1]
            want = general.due_on_sample(ids, now)
            # what publish() does: one comparison, then the schedule's own loop
            got = [] if now < fast.sample_due_at else fast.due_samples(now)
            assert got == want, (now, op)
        elif kind == "base":
            general.set_base(op[1], op[2])
            fast.set_base(op[1], op[2])
        elif kind == "override":
            general.set_override(op[1], op[2])
            fast.set_override(op[1], op[2])
        else:
            ids = list(op[1])
            fast.set_sample_streams(ids)
    assert general.rate(S.ATTITUDE) == fast.rate(S.ATTITUDE)


def test_a_change_made_while_due_samples_runs_is_not_lost() -> None:
    # Another thread (the dispatcher) changes a rate between due_samples() reading the plan
    # and storing the next due time: the stored time must not hide the change.
    sched = S.StreamSchedule({S.ATTITUDE: 1.0})
    sched.set_sample_streams([S.ATTITUDE])
    assert sched.due_samples(10.0) == [S.ATTITUDE]
    real_rate = sched.rate

    def rate_then_change(msgid: int) -> float:
        hz = real_rate(msgid)
        sched.set_override(S.VFR_HUD, 5.0)  # any change, "meanwhile"
        return hz

    sched.rate = rate_then_change  # type: ignore[method-assign]  # instrumented on purpose
    sched.set_base(S.ATTITUDE, 1.0)  # a new plan is built on the next call
    sched.due_samples(10.5)
    assert sched.sample_due_at == float("-inf")  # ask again next time, not in a second
    sched.rate = real_rate  # type: ignore[method-assign]  # and restored
    sched.due_samples(10.6)
    assert sched.sample_due_at == pytest.approx(11.0 - pacing.early_s(1.0))


@pytest.mark.parametrize(("hz", "jitter"), [(50.0, 0.0), (30.0, 0.003), (7.0, 0.004), (100.0, 0.0)])
def test_the_average_rate_stays_exact(hz: float, jitter: float) -> None:
    rng = random.Random(int(hz))
    sched = S.StreamSchedule({S.ATTITUDE: hz, S.VFR_HUD: 4.0})
    sched.set_sample_streams([S.ATTITUDE, S.VFR_HUD])
    times = [50.0 + i * 0.01 + rng.uniform(-jitter, jitter) for i in range(6000)]  # 60 s, 100 Hz
    counts = {S.ATTITUDE: 0, S.VFR_HUD: 0}
    for now in times:
        if now >= sched.sample_due_at:
            for m in sched.due_samples(now):
                counts[m] += 1
    # The first goes with the first frame; the rest take the slots of the period's grid
    # from there on, a little early at most; a frame comes every 10 +- 3 ms, so none is
    # late by a period.
    assert counts[S.ATTITUDE] == expected_count(hz, times[0], times[-1])
    assert counts[S.VFR_HUD] == expected_count(4.0, times[0], times[-1])


def expected_count(hz: float, first: float, last: float) -> int:
    """Messages of an exact ``hz`` stream on frames from ``first`` to ``last`` (seconds):
    one with the first frame, then one per slot of the grid (the multiples of the
    period, from the first at least half a period after ``first``) opened by ``last``."""
    period = 1.0 / hz
    slot1 = (math.floor(first / period + 0.5) + 1) * period
    opened = last + pacing.early_s(period) - slot1
    return 1 + (math.floor(opened / period) + 1 if opened >= 0.0 else 0)


# =====================================================================================
# a started output: injected clock, taps, a real ground station on UDP
# =====================================================================================


class Peer:
    """A ground station on a plain UDP socket; pymavlink encodes and parses."""

    def __init__(self) -> None:
        self.sock = udp_socket(0.1)
        self.port = int(self.sock.getsockname()[1])
        self.mav = M.MAVLink(None, 255, 190)
        self.parser = M.MAVLink(None)
        self.to: Any = None  # the output endpoint's address (its ephemeral port)
        self.inbox: list[Any] = []  # everything received, in order (waits take from it)

    def send(self, msg: Any) -> None:
        self.sock.sendto(msg.pack(self.mav), self.to)

    def wait(self, mtype: str, pred: Callable[[Any], bool] = lambda m: True) -> Any:
        deadline = time.monotonic() + DEADLINE_S
        while True:
            for i, m in enumerate(self.inbox):
                if m.get_type() == mtype and pred(m):
                    return self.inbox.pop(i)
            if time.monotonic() > deadline:
                raise AssertionError(f"no {mtype} within {DEADLINE_S} s")
            with contextlib.suppress(TimeoutError):
                self.inbox += self.parser.parse_buffer(self.sock.recv(65535)) or []

    def command(self, command: int, *params: float) -> Any:
        """The command's final COMMAND_ACK (the one after IN_PROGRESS, if long work)."""
        p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
        self.send(self.mav.command_long_encode(1, 1, command, 0, *p))
        ack = self.wait("COMMAND_ACK", lambda m: m.command == command)
        if ack.result == M.MAV_RESULT_IN_PROGRESS:
            ack = self.wait("COMMAND_ACK", lambda m: m.command == command)
        return ack

    def set_param(self, name: str, value: float, ptype: int) -> Any:
        self.send(self.mav.param_set_encode(1, 1, name.encode(), value, ptype))
        return self.wait("PARAM_VALUE", lambda m: m.param_id == name)


@dataclass
class Bench:
    out: MavlinkOutput
    peer: Peer
    clock: ManualClock
    sent: list[Packet]  # every broadcast packet (the output's tap)
    sample: CompassSample

    def frame(self, dt: float = 0.01) -> set[int]:
        """One sample ``dt`` after the last; the per-sample message ids it sent."""
        self.clock.t += dt
        before = len(self.sent)
        self.out.publish(replace(self.sample, t=self.clock.t))
        return {p.get_msgId() for p in self.sent[before:] if p.get_msgId() in SAMPLE_IDS + FEEDS}


FEEDS = (S.VISION_POSITION_ESTIMATE,)


@pytest.fixture
def bench(tmp_path: Path) -> Iterator[Callable[..., Bench]]:
    made: list[tuple[MavlinkOutput, Peer]] = []

    def make(**mavlink: Any) -> Bench:
        peer = Peer()
        cfg, daemon = offline_daemon(
            tmp_path, "fastpath", endpoints=[f"udpout:127.0.0.1:{peer.port}"], **mavlink
        )
        clock = ManualClock(100.0)
        out = MavlinkOutput(MavlinkSettings.from_config(cfg), daemon.bridge.services, clock=clock)
        sent: list[Packet] = []
        daemon.bridge.mavlink_tap.subscribe(lambda m: sent.append(m.message))
        out.start()
        made.append((out, peer))
        # The ground station answers where our HEARTBEAT came from (the clock stands still
        # here, so the telemetry thread's first one may have gone before the socket was open).
        deadline = time.monotonic() + DEADLINE_S
        while not out.endpoints[0].links and time.monotonic() < deadline:
            time.sleep(0.01)
        out.broadcast(T.heartbeat(out.identity, M.MAV_STATE_ACTIVE))
        while peer.to is None and time.monotonic() < deadline:
            with contextlib.suppress(TimeoutError):
                _data, peer.to = peer.sock.recvfrom(65535)
        assert peer.to is not None
        del sent[:]
        return Bench(out, peer, clock, sent, make_sample(t=clock.t))

    yield make
    for out, peer in made:
        out.close(2.0)
        peer.sock.close()


ALL_OFF = {
    "rate_attitude_hz": 0.0,
    "rate_attitude_quaternion_hz": 0.0,
    "rate_vfr_hud_hz": 0.0,
    "rate_scaled_imu_hz": 0.0,
    "rate_raw_imu_hz": 0.0,
    "rate_highres_imu_hz": 0.0,
}


@pytest.mark.integration
def test_half_the_frames_do_no_mavlink_work(bench: Callable[..., Bench]) -> None:
    b = bench(**{**ALL_OFF, "rate_attitude_hz": 50.0})
    calls = 0
    due_samples = b.out.schedule.due_samples

    def counting(now: float) -> list[int]:
        nonlocal calls
        calls += 1
        return due_samples(now)

    b.out.schedule.due_samples = counting  # type: ignore[method-assign]  # instrumented on purpose
    sent = [b.frame() for _ in range(200)]
    assert sum(S.ATTITUDE in s for s in sent) == 100  # 50 Hz of 100 Hz frames, exactly
    assert calls == 100  # the other 100 frames stopped at the comparison


@pytest.mark.integration
def test_the_average_rate_through_the_output(bench: Callable[..., Bench]) -> None:
    b = bench(**{**ALL_OFF, "rate_attitude_hz": 30.0, "rate_vfr_hud_hz": 4.0})
    rng = random.Random(3)
    sent = [b.frame(0.01 + rng.uniform(-0.003, 0.003)) for _ in range(3000)]
    first = b.sample.t + 0.01 + 0.0  # frame() stepped the clock before the first sample
    assert sum(S.ATTITUDE in s for s in sent) == expected_count(30.0, first, b.clock.t)
    assert sum(S.VFR_HUD in s for s in sent) == expected_count(4.0, first, b.clock.t)
    # what reached the ground station is what the tap saw, framed by pymavlink's rules
    assert b.peer.wait("ATTITUDE").get_srcSystem() == 1


@pytest.mark.integration
def test_message_interval_takes_effect_on_the_next_sample(bench: Callable[..., Bench]) -> None:
    b = bench(**{**ALL_OFF, "rate_attitude_hz": 2.0})
    assert S.ATTITUDE in b.frame()
    assert S.ATTITUDE not in b.frame()  # 2 Hz: the next one in half a second
    att = M.MAVLINK_MSG_ID_ATTITUDE
    assert b.peer.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, att, 20_000).result == ACCEPTED
    assert S.ATTITUDE in b.frame()  # 50 Hz now: the very next sample
    assert sum(S.ATTITUDE in b.frame() for _ in range(100)) in (49, 50, 51)  # and 50 a second
    assert b.peer.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, att, -1).result == ACCEPTED
    assert not any(S.ATTITUDE in b.frame() for _ in range(50))  # off
    assert b.peer.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, att, 0).result == ACCEPTED
    assert S.ATTITUDE in b.frame()  # back to the configured 2 Hz, at once
    assert not any(S.ATTITUDE in b.frame() for _ in range(10))
    # a stream that was never on, switched on by an override
    hud = M.MAVLINK_MSG_ID_VFR_HUD
    assert b.peer.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, hud, 100_000).result == ACCEPTED
    assert S.VFR_HUD in b.frame()


@pytest.mark.integration
def test_a_rate_parameter_takes_effect_on_the_next_sample(bench: Callable[..., Bench]) -> None:
    b = bench(**ALL_OFF)  # every sample stream off: the output never needs to look again
    assert not any(b.frame() for _ in range(20))
    assert b.peer.set_param("BRG_SR_ATT", 20.0, REAL32).param_value == 20.0
    assert b.frame() == {S.ATTITUDE}
    assert b.peer.set_param("BRG_SR_RIMU", 50.0, REAL32).param_value == 50.0
    assert S.RAW_IMU in b.frame()
    assert b.peer.set_param("BRG_SR_ATT", 0.0, REAL32).param_value == 0.0
    assert b.peer.set_param("BRG_SR_RIMU", 0.0, REAL32).param_value == 0.0
    assert not any(b.frame(0.05) for _ in range(10))
    # PREFLIGHT_STORAGE 2: back to the defaults (ATTITUDE off here, VFR_HUD's 4 Hz default)
    assert b.peer.set_param("BRG_SR_HUD", 0.0, REAL32).param_value == 0.0
    assert b.peer.command(M.MAV_CMD_PREFLIGHT_STORAGE, 2).result == ACCEPTED
    assert b.out.services.params.get("BRG_SR_HUD") == 0.0  # the configuration's default: off
    b.out.schedule.set_base(S.HIGHRES_IMU, 1.0)  # the schedule's own API works directly too
    assert b.frame() == {S.HIGHRES_IMU}


@pytest.mark.integration
def test_the_heading_feed_switches_on_the_next_sample(bench: Callable[..., Bench]) -> None:
    b = bench(**ALL_OFF, rate_heading_feed_hz=10.0)
    assert not any(b.frame() for _ in range(20))  # feed off
    assert b.peer.set_param("BRG_HDG_FEED", 1.0, INT8).param_value == 1.0
    assert b.frame() == {S.ODOMETRY}
    assert b.peer.set_param("BRG_HDG_FEED", 2.0, INT8).param_value == 2.0
    got = [b.frame() for _ in range(10)]  # the slot keeps its rhythm: within one period
    assert {S.VISION_POSITION_ESTIMATE} in got and not any(S.ODOMETRY in s for s in got)
    assert b.peer.set_param("COMPASS_USE", 0.0, INT8).param_value == 0.0
    assert not any(b.frame() for _ in range(20))  # the autopilot gets nothing
    assert b.peer.set_param("COMPASS_USE", 1.0, INT8).param_value == 1.0
    assert any(b.frame() == {S.VISION_POSITION_ESTIMATE} for _ in range(10))
    assert b.peer.set_param("BRG_HDG_FEED", 0.0, INT8).param_value == 0.0
    assert not any(b.frame() for _ in range(20))
    b.peer.wait("VISION_POSITION_ESTIMATE")  # it went out on the wire too
