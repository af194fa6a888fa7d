"""When a rate-capped stream sends: the one rule MAVLink's stream schedule
(:class:`bridge.mavlink.schedule.StreamSchedule`) and Zenoh's rate caps
(:class:`bridge.zenoh.pacing.Decimator`) share. Pure: times come in.

A stream at ``hz`` has a slot every ``period = 1 / hz`` seconds; the first sample
in (or a little before) its slot goes out and books the next slot one period
later, so the average rate is exact whatever the frames' jitter, and a gap
longer than a period starts the stream anew rather than bursting to catch up.

Slots sit on a grid of the clock (the multiples of the period), not one period
after whichever sample happened to go first: so streams whose periods divide
one another -- 10 Hz ATTITUDE, 2 Hz IMU, Zenoh's 10 Hz -- fall due on the same
frames, and the compass link, which reads the port in bursts between due
samples (:meth:`bridge.app.pipeline.Pipeline.due_at_time`), wakes once for all
of them instead of once for each.

A stream of :data:`GRID_S` x 2 or longer whose period is not a multiple of
:data:`GRID_S` (VFR_HUD's 4 Hz) takes, for its k-th slot, the point of the
:data:`GRID_S` grid nearest to ``k * period``: every slot within half a grid
step (50 ms) of its exact time -- at most a fifth of a 4 Hz period, never more
than a quarter of any (the tolerance :func:`early_s` gives a sample too) -- so
the average rate stays exact and the intervals keep between ``period - GRID_S``
and ``period + GRID_S`` (4 Hz: 0.2 and 0.3 s in turn), while the link wakes
for the 10 Hz slots only. (PX4's own streams vary as much:
``MavlinkStream::update`` in src/modules/mavlink/mavlink_stream.cpp books the
next send one interval after the previous *booked* time as long as the actual
interval stays under 1.5 intervals, so one late send is followed by an early
one, and the average holds.) Faster streams, between 5 and 10 Hz, would move
by up to a third of their period and keep their own grid.

A sample may come :func:`early_s` before its slot and still take it: a quarter
period (a frame a millisecond early must not wait a whole period), but never
more than :data:`EARLY_MAX_S`, so that every stream at 10 Hz or slower opens
its slot at the same instant before the shared grid point.
"""

from __future__ import annotations

import math

#: The fraction of a period a sample may come early and still take its slot.
SLACK = 0.25
#: The shared grid (10 Hz, the shipped ATTITUDE and Zenoh rates): streams of twice
#: this period or longer take its points (see the module docstring).
GRID_S = 0.1
#: ... and at most this long (a quarter of a 10 Hz period): the slower streams open
#: their slots when the 10 Hz ones do.
EARLY_MAX_S = SLACK * GRID_S


def early_s(period: float) -> float:
    """How long before its slot a sample still takes it (seconds)."""
    return min(SLACK * period, EARLY_MAX_S)


def slot_time(k: int, period: float) -> float:
    """The time of a stream's ``k``-th slot (``k * period``, or for a period of two
    grid steps or more the :data:`GRID_S` grid point nearest to it)."""
    if period < 2.0 * GRID_S:
        return k * period
    # k * (period / GRID_S): exact for 4 Hz (2.5), so its halves round the same way
    # every time (0.3, 0.5, 0.8, 1.0, ...: 0.3 s and 0.2 s in turn).
    return math.floor(k * (period / GRID_S) + 0.5) * GRID_S


def next_slot(slot: float | None, now: float, period: float) -> float:
    """The slot to book after a sample at ``now`` took ``slot`` (None: the first).

    The next slot of the stream's grid (:func:`slot_time`); when ``now`` is more
    than a period past ``slot`` (a pause, a first sample), the first slot at
    least half a period after ``now`` (less half a grid step when snapped).
    """
    if slot is not None and now - slot <= period:
        # slot_time is within a quarter period of k * period: round() finds k again.
        return slot_time(round(slot / period) + 1, period)
    return slot_time(math.floor(now / period + 0.5) + 1, period)
