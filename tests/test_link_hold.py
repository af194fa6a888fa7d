"""When the compass link's reader ends a hold (``serial_link.hold_end``): shortly before the
due time, or just after a frame the compass's rhythm puts in the lead before it, so that
frame comes with the held ones instead of costing a wake-up of its own; and how the read
after a hold is stamped when the thread woke after the due time (``serial_link._held``).
Pure: in memory."""

from __future__ import annotations

import math

import pytest

from bridge.device import Received
from bridge.link.serial_link import AFTER_FRAME_S, BURST_LEAD_S, _held, hold_end

RATE_HZ = 100
PERIOD = 1.0 / RATE_HZ


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
    end = hold_end(0.0, arrived, RATE_HZ)
    last = max(a for a in frames_at(phase) if a < 0.0)
    due_frame = last + PERIOD
    assert reads_per_due_time(phase, end) == 2
    assert last < end < due_frame  # the reader is awake and reading when the due frame comes
    if last + AFTER_FRAME_S > -BURST_LEAD_S:
        assert end == pytest.approx(last + AFTER_FRAME_S)  # the frame in the lead: held
    else:
        assert end == -BURST_LEAD_S  # no frame in the lead: the lead, as before
    # The lead alone: a frame in it costs a third read.
    assert reads_per_due_time(phase, -BURST_LEAD_S) == (3 if last > -BURST_LEAD_S else 2)


def test_the_lead_alone_cost_a_third_read_in_four_phases_of_ten() -> None:
    phases = [-PERIOD + i * PERIOD / 1000 for i in range(1000)]
    lead_only = sum(reads_per_due_time(p, -BURST_LEAD_S) > 2 for p in phases)
    with_rhythm = sum(
        reads_per_due_time(p, hold_end(0.0, p - 7 * PERIOD, RATE_HZ)) > 2 for p in phases
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
    assert hold_end(due, arrived, rate) == due - BURST_LEAD_S


def test_no_due_time_holds_as_long_as_allowed() -> None:
    assert hold_end(math.inf, 5.0, RATE_HZ) == math.inf
    assert hold_end(-math.inf, 5.0, RATE_HZ) == -math.inf


def test_a_late_read_after_a_hold_passes_no_held_frame_for_due() -> None:
    due = 100.0
    read = [Received(object(), due + 0.003) for _ in range(9)]  # type: ignore[arg-type]
    # The hold ended at the lead: the newest may have come after the due time; it is
    # the freshest there is and stays due by its read. The rest: just before.
    kept = _held(read, due, keep_newest=True)
    assert [r.t < due for r in kept] == [True] * 8 + [False]
    assert [r.frame for r in kept] == [r.frame for r in read]
    # The hold ended after a frame expected before the due time: the due frame is the
    # next to come, read as it comes; none of these is due.
    held = _held(read, due, keep_newest=False)
    assert all(due - 1e-3 < r.t < due for r in held)
    assert _held(read[:1], due, keep_newest=True) == read[:1]
