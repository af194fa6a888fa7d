"""When the compass link's reader ends a hold (``serial_link.hold_end``): with the compass's
rhythm known, shortly before the due frame is expected (so the due frame is read as it
comes, right after the held ones, and every frame before it comes with them instead of
costing a wake-up of its own); without one, shortly before the due time. Where the rhythm
comes from (``serial_link.frames_phase``), and how the read after a hold is stamped when
the thread woke after the due time (``serial_link._held``). Pure: in memory."""

from __future__ import annotations

import math
import threading

import pytest

from bridge.link.serial_link import (
    AFTER_FRAME_S,
    BURST_LEAD_S,
    FIRST_BURST_S,
    RHYTHM_READS,
    WARM_MARGIN_S,
    Wake,
    _held,
    burst_estimate,
    frames_phase,
    held_count,
    hold_end,
)
from bridge.protocol.device import Received
from bridge.protocol.gmr import AttitudeFrame, Flags

RATE_HZ = 100
PERIOD = 1.0 / RATE_HZ
LEAD = FIRST_BURST_S + WARM_MARGIN_S  # the reader's lead before it has timed a burst


def frames_at(phase: float) -> list[float]:
    return [phase + k * PERIOD for k in range(-20, 20)]


def reads_per_due_time(phase: float, end: float) -> int:
    """Reads a due time (0.0) costs with frames at ``phase + k * PERIOD`` and the hold
    ending at ``end``: the held frames (one read), each frame that comes after the hold's
    end and before the due time (read on its own, not due yet), then the due frame."""
    return 2 + sum(end < a < 0.0 for a in frames_at(phase))


@pytest.mark.parametrize("step", range(100))
def test_every_phase_costs_two_reads(step: int) -> None:
    phase = -PERIOD + step * PERIOD / 100  # the frames' phase against the due time
    arrived = phase - 7 * PERIOD  # a frame read on its own, 70 ms ago
    end = hold_end(0.0, arrived, RATE_HZ, LEAD)
    last = max(a for a in frames_at(phase) if a < 0.0)
    due_frame = last + PERIOD
    assert reads_per_due_time(phase, end) == 2
    assert last < end < due_frame  # the reader is awake and reading when the due frame comes
    # ... and has just put the held frames through: the due frame comes the lead after
    # the hold's end (AFTER_FRAME_S after the frame before it, at the least) ...
    assert end == pytest.approx(max(due_frame - LEAD, last + AFTER_FRAME_S))
    assert due_frame - end <= LEAD + 1e-12
    # ... never earlier than a lead before the due time: every frame the lead alone held
    # is held still.
    assert end >= -BURST_LEAD_S
    # The lead alone: a frame in it costs a third read.
    assert reads_per_due_time(phase, -BURST_LEAD_S) == (3 if last > -BURST_LEAD_S else 2)


def test_the_lead_alone_cost_a_third_read_in_four_phases_of_ten() -> None:
    phases = [-PERIOD + i * PERIOD / 1000 for i in range(1000)]
    lead_only = sum(reads_per_due_time(p, -BURST_LEAD_S) > 2 for p in phases)
    with_rhythm = sum(
        reads_per_due_time(p, hold_end(0.0, p - 7 * PERIOD, RATE_HZ, LEAD)) > 2 for p in phases
    )
    assert lead_only == pytest.approx(1000 * BURST_LEAD_S / PERIOD, abs=2)
    assert with_rhythm == 0


@pytest.mark.parametrize(
    ("due", "arrived", "rate"),
    [
        (10.0, None, RATE_HZ),  # no frame read on its own yet
        (10.0, 9.0, RATE_HZ),  # nor in the last second
        (10.0, 9.9975, None),  # no rate asked (a heading-only compass)
        (10.0, 9.9975, 0),
        (10.0, 10.5, RATE_HZ),  # a due time already past the frame
    ],
)
def test_without_a_rhythm_the_lead_alone(due: float, arrived: float | None, rate: int) -> None:
    assert hold_end(due, arrived, rate, LEAD) == due - BURST_LEAD_S


def test_a_frame_period_too_short_for_the_rhythm_the_lead_alone() -> None:
    # 1 kHz: a frame every millisecond, not more than twice AFTER_FRAME_S.
    assert hold_end(10.0, 9.9975, 1000, LEAD) == 10.0 - BURST_LEAD_S


def test_no_due_time_holds_as_long_as_allowed() -> None:
    assert hold_end(math.inf, 5.0, RATE_HZ, LEAD) == math.inf
    assert hold_end(-math.inf, 5.0, RATE_HZ, LEAD) == -math.inf


def test_a_late_read_after_a_hold_passes_no_held_frame_for_due() -> None:
    due = 100.0
    frame = AttitudeFrame(1, 87.3, -1.2, 0.4, 3101, 2470, 3311, 2470, 2452, 2950, Flags(6))
    read = [Received(frame, due + 0.003) for _ in range(9)]
    # No rhythm: the newest may have come after the due time; it is the freshest there
    # is and stays due by its read. The rest: just before.
    kept = _held(read, due, None)
    assert [r.t < due for r in kept] == [True] * 8 + [False]
    assert [r.frame for r in kept] == [r.frame for r in read]
    assert _held(read[:1], due, None) == read[:1]
    # The rhythm put nine frames before the due time: none of these is due; the due frame
    # is the next to come, read as it comes.
    held = _held(read, due, 9)
    assert all(due - 1e-3 < r.t < due for r in held)
    # ... it put eight there: the thread woke after the due frame came, and that one, the
    # newest, is due by its read (hiding it would send the next frame a period late).
    late = _held(read, due, 8)
    assert [r.t < due for r in late] == [True] * 8 + [False]
    # ... none: a compass no faster than the stream, every frame read is due.
    assert _held(read[:2], due, 0) == read[:2]


def test_the_rhythm_counts_the_frames_a_hold_holds() -> None:
    phase = 100.0003  # the rhythm: frames at 100.0003 + k * PERIOD
    # The due frame read on its own at 100.0004; the next due time 75 ms after its slot's
    # grid point: nine frames come before it, the tenth is the due one.
    assert held_count(100.0754, phase, 100.0004, RATE_HZ) == 7
    assert held_count(100.0999, phase, 100.0004, RATE_HZ) == 9
    assert held_count(100.1003, phase, 100.0004, RATE_HZ) == 9  # the tenth comes at due
    assert held_count(100.1004, phase, 100.0004, RATE_HZ) == 10
    # A read late by most of a period: its newest frame is still the one at the phase.
    assert held_count(100.0999, phase, 100.0102, RATE_HZ) == 9
    # A compass at the stream's rate (10 Hz): none held.
    assert held_count(100.075, phase, 100.0004, 10) == 0
    assert held_count(100.075, None, 100.0004, RATE_HZ) == 0


def test_the_rhythm_is_the_earliest_of_the_last_reads() -> None:
    # Frames every 10 ms at phase 0.3 ms; reads come 0.05-0.4 ms after them, one 3 ms
    # late (a late wake-up): the rhythm is the earliest read's, moved to the newest.
    lateness = [0.0004, 0.0001, 0.003, 0.0002, 0.00005, 0.0003]
    reads = [100.0003 + 0.1 * k + late for k, late in enumerate(lateness)]
    assert frames_phase(reads, RATE_HZ) == pytest.approx(100.0003 + 0.5 + 0.00005)
    # The late read alone, newest: the rhythm stays where the earlier ones put it.
    reads.append(100.0003 + 0.6 + 0.003)
    assert frames_phase(reads, RATE_HZ) == pytest.approx(100.0003 + 0.6 + 0.00005)
    # A hold for a due time 25 ms after the next grid point ends the lead before the due
    # frame where it really comes, not where the late read would put it.
    due = 100.0003 + 0.6 + 0.075
    end = hold_end(due, frames_phase(reads, RATE_HZ), RATE_HZ, LEAD)
    assert end == pytest.approx(100.0003 + 0.68 + 0.00005 - LEAD)


def test_the_rhythm_follows_a_compass_whose_frames_come_later_and_later() -> None:
    # A compass clock slower than ours by 0.1 % (ten times a crystal's): each read 0.1 ms
    # later against the rhythm; the rhythm lags the newest by what the window spans.
    reads = [100.0 + k * 0.1 * 1.001 for k in range(20)]
    phase = frames_phase(reads[-RHYTHM_READS:], RATE_HZ)
    assert phase is not None
    assert reads[-1] - RHYTHM_READS * 0.0001 < phase <= reads[-1]


def test_the_rhythm_ignores_reads_more_than_a_second_old() -> None:
    reads = [100.0 + 0.0001, 101.5 + 0.002]  # the first would put it 1.9 ms earlier
    assert frames_phase(reads, RATE_HZ) == pytest.approx(101.502)


def test_no_read_no_rhythm_and_without_a_rate_the_newest_read() -> None:
    assert frames_phase([], RATE_HZ) is None
    assert frames_phase([100.0001, 100.1005], None) == 100.1005
    assert frames_phase([100.0001, 100.1005], 0) == 100.1005


def test_the_lead_is_never_longer_than_the_lead_before_the_due_time() -> None:
    # A burst that took 10 ms (a busy machine): the hold still ends when the lead before
    # the due time would have ended it, at the latest BURST_LEAD_S before the due frame.
    arrived, due = 99.9995, 100.0  # the due frame expected at 100.0095
    assert hold_end(due, arrived, RATE_HZ, 0.010) == pytest.approx(100.0095 - BURST_LEAD_S)
    assert hold_end(due, arrived, RATE_HZ, 0.0005) == pytest.approx(100.0095 - 0.0005)


def test_a_longer_burst_lengthens_the_lead_at_once_a_shorter_one_a_little() -> None:
    assert burst_estimate(0.0007, 0.003) == 0.003  # the next due frame must not wait
    assert burst_estimate(0.003, 0.0007) == pytest.approx(0.003 - 0.25 * 0.0023)
    est = 0.003
    for _ in range(30):  # quick bursts from then on: back to what they take
        est = burst_estimate(est, 0.0007)
    assert est == pytest.approx(0.0007, abs=1e-5)


# -- the flag the reader's hold waits on -------------------------------------------------


def test_the_wake_flag_is_an_event_for_one_waiter() -> None:
    w = Wake()
    assert not w.is_set() and w.wait(0.0) is False
    w.set()
    w.set()  # idempotent
    assert w.is_set()
    assert w.wait(0.0) is True and w.wait(0.0) is True  # stays raised until cleared
    w.clear()
    assert not w.is_set() and w.wait(0.001) is False
    w.clear()  # clearing a clear flag: still clear
    assert w.wait(0.0) is False
    assert w.wait(-1.0) is False  # a deadline already past: at once, as Event.wait
    w.set()
    assert w.wait(-1.0) is True


def test_a_set_from_another_thread_ends_the_wait() -> None:
    w = Wake()
    waiting = threading.Event()
    got: list[bool] = []

    def waiter() -> None:
        waiting.set()
        got.append(w.wait(30.0))

    t = threading.Thread(target=waiter)
    t.start()
    assert waiting.wait(30.0)
    w.set()
    t.join(30.0)
    assert got == [True] and w.is_set()


def test_a_set_racing_the_waiters_put_back_leaves_the_flag_raised() -> None:
    """set() between the waiter taking the lock and putting it back: the put-back finds
    the lock already released; no error, and the flag stays raised."""
    w = Wake()
    real = threading.Lock()
    real.acquire()

    class Racing:
        def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
            got = real.acquire(blocking, timeout)
            if got:
                real.release()  # another thread's set() comes in right here
            return got

        def release(self) -> None:
            real.release()

        def locked(self) -> bool:
            return real.locked()

    w._lock = Racing()  # type: ignore[assignment]  # the racing stand-in, on purpose
    w.set()
    assert w.wait(0.0) is True
    assert w.is_set()
