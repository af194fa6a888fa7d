"""When a rate-capped stream sends: the one rule MAVLink's stream schedule
(:class:`bridge.mavlink.schedule.StreamSchedule`) and Zenoh's rate caps
(:class:`bridge.zenoh.pacing.Decimator`) share. Pure: times come in.

A stream at ``hz`` has a slot every ``period = 1 / hz`` seconds; the first sample
in (or a little before) its slot goes out and books the next slot one period
later, so the average rate is exact whatever the frames' jitter, and a gap
longer than a period starts the stream anew rather than bursting to catch up.

Slots sit on a grid of the clock (the multiples of the period), not one period
after whichever sample happened to go first: so streams whose periods divide
one another -- 10 Hz ATTITUDE, 4 Hz VFR_HUD, 2 Hz IMU, Zenoh's 10 Hz -- fall
due on the same frames, and the compass link, which reads the port in bursts
between due samples (:meth:`bridge.app.pipeline.Pipeline.due_at_time`), wakes
once for all of them instead of once for each.

A sample may come :func:`early_s` before its slot and still take it: a quarter
period (a frame a millisecond early must not wait a whole period), but never
more than :data:`EARLY_MAX_S`, so that every stream at 10 Hz or slower opens
its slot at the same instant before the shared grid point.
"""

from __future__ import annotations

import math

#: The fraction of a period a sample may come early and still take its slot.
SLACK = 0.25
#: ... and at most this long (a quarter of a 10 Hz period): the slower streams open
#: their slots when the 10 Hz ones do.
EARLY_MAX_S = 0.025


def early_s(period: float) -> float:
    """How long before its slot a sample still takes it (seconds)."""
    return min(SLACK * period, EARLY_MAX_S)


def next_slot(slot: float | None, now: float, period: float) -> float:
    """The slot to book after a sample at ``now`` took ``slot`` (None: the first).

    One period on from the slot taken; when ``now`` is more than a period past it
    (a pause, a first sample), the grid point of ``period`` at least half a period
    after ``now``.
    """
    if slot is not None and now - slot <= period:
        return slot + period
    return (math.floor(now / period + 0.5) + 1.0) * period
