"""The times the compass link stamps on the frames it reads, worked out in memory.

At 100 Hz with the outputs' 10 Hz streams the link holds the port until shortly before the
frame the next output falls due on, reads the frames that waited with one read (all
stamped with its time), then reads the due one as it comes
(:class:`bridge.link.serial_link.CompassLink`, ``_read_loop`` and ``_hold``).
:class:`LinkReads` takes the same decisions with the link's own rules -- when a hold ends
(:func:`~bridge.link.serial_link.hold_end`), the compass's rhythm
(:func:`~bridge.link.serial_link.frames_phase`), how many frames a hold holds
(:func:`~bridge.link.serial_link.held_count`), how a late read is stamped
(:func:`~bridge.link.serial_link._held`), the burst's lead
(:func:`~bridge.link.serial_link.burst_estimate`) -- on a simulated clock, with the due
time from a real :class:`~bridge.mavlink.schedule.StreamSchedule` fed the stamps as the
MAVLink output feeds it (:class:`Paced`, an output on the pipeline). No port, no thread:
the wake-ups are where the rules put them, plus a lateness the caller chooses (a busy
host).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterator, Sequence

from bridge.app.pipeline import Pipeline
from bridge.app.sample import CompassSample
from bridge.device import Received
from bridge.link.serial_link import (
    BURST_LEAD_S,
    FIRST_BURST_S,
    MAX_BURST_S,
    RHYTHM_READS,
    WARM_MARGIN_S,
    _held,
    burst_estimate,
    frames_phase,
    held_count,
    hold_end,
)
from bridge.mavlink.schedule import ATTITUDE, StreamSchedule
from bridge.protocol.gmr import AttitudeFrame


class Paced:
    """An output paced as the MAVLink output is: a 10 Hz ATTITUDE stream whose slots a
    sample takes by its own time (``sample.t``), ``due_at`` the schedule's next."""

    name = "paced"

    def __init__(self, rate_hz: float = 10.0) -> None:
        self.schedule = StreamSchedule({ATTITUDE: rate_hz})
        self.schedule.set_sample_streams([ATTITUDE])
        self.sent: list[float] = []  #: the times of the samples that took a slot

    def start(self) -> None:
        """Nothing to start."""

    def publish(self, sample: CompassSample) -> None:
        """The MAVLink output's pacing (``MavlinkOutput.publish``) without the encoding."""
        if sample.t < self.schedule.sample_due_at:
            return
        if self.schedule.due_samples(sample.t):
            self.sent.append(sample.t)

    @property
    def due_at(self) -> float:
        """When the stream next falls due."""
        return self.schedule.sample_due_at

    def close(self, timeout: float) -> None:
        """Nothing to stop."""


class LinkReads:
    """The link's reads of frames that come at ``comes[i]`` (the last byte of frame ``i``
    on the port), each read as a list of :class:`Received` stamped as the link stamps
    them. ``due_at`` is asked after each read's frames went through the pipeline (the
    link's ``due_at`` hook: :meth:`Pipeline.due_at_time`); ``late()`` is how late the
    thread wakes from a hold (0: on time); each frame takes ``per_frame_s`` through the
    pipeline."""

    def __init__(
        self,
        rate_hz: int,
        due_at: Callable[[], float],
        late: Callable[[], float] = lambda: 0.0,
        per_frame_s: float = 5e-5,
    ) -> None:
        self.rate_hz = rate_hz
        self.due_at = due_at
        self.late = late
        self.per_frame_s = per_frame_s
        self.bursts = 0  #: reads of more than one held frame
        self.late_reads = 0  #: reads after the due time (stamped by ``_held``)

    def reads(
        self, frames: Sequence[AttitudeFrame], comes: Sequence[float]
    ) -> Iterator[list[Received]]:
        """The reads, in order (the caller puts each through the pipeline before the next)."""
        arrived: deque[float] = deque(maxlen=RHYTHM_READS)  # reads of one frame each
        burst_s = FIRST_BURST_S
        held_for: float | None = None
        held_n: int | None = None
        now = -math.inf
        i, n = 0, len(frames)
        while i < n:
            # after a hold, what waited through it: read at once; else a blocking read,
            # which returns when the next frame has come
            read_at = now if held_for is not None else max(now, comes[i])
            j = i
            while j < n and comes[j] <= read_at:
                j += 1
            if j == i:  # the hold found nothing waiting: frames as they come from now on
                held_for = None
                continue
            received = [Received(frames[k], read_at) for k in range(i, j)]
            i = j
            burst = held_for is not None and len(received) > 1
            if held_for is not None:
                if read_at >= held_for:
                    received = _held(received, held_for, held_n)
                    self.late_reads += 1
                held_for = None
            elif len(received) == 1:
                arrived.append(read_at)
            self.bursts += burst
            yield received
            now = read_at + self.per_frame_s * len(received)
            if burst:
                burst_s = burst_estimate(burst_s, now - read_at)
            # the hold (CompassLink._hold)
            due = self.due_at()
            phase = frames_phase(arrived, self.rate_hz)
            end = hold_end(due, phase, self.rate_hz, burst_s + WARM_MARGIN_S)
            until = min(end, now + MAX_BURST_S)
            if until > now:
                rhythm = until == end != due - BURST_LEAD_S
                held_for = due
                held_n = held_count(due, phase, read_at, self.rate_hz) if rhythm else None
                now = until + self.late()


def feed_as_read(
    pipeline: Pipeline,
    frames: Sequence[AttitudeFrame],
    comes: Sequence[float],
    link: LinkReads | None,
    clock: Callable[[float], None] = lambda t: None,
) -> None:
    """``frames`` through ``pipeline`` as the link reads them (``link``), or each with the
    time it came (``None``: read as it comes, on time); ``clock(t)`` is told each frame's
    stamp before it goes in."""
    if link is None:
        for f, c in zip(frames, comes, strict=True):
            clock(c)
            pipeline.on_frame(Received(f, c))
        return
    for read in link.reads(frames, comes):
        for item in read:
            clock(item.t)
            pipeline.on_frame(item)
