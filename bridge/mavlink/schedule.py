"""Which MAVLink streams go out, and when (pure: the caller passes the time).

Sample streams (ATTITUDE, the IMU messages, the heading feed) go out with the
first sample in their slot -- slots on a grid of the clock, a sample a little
early still taking its slot (:mod:`bridge.core.pacing`, the rule Zenoh's rate
caps follow too); clock streams (HEARTBEAT, SYS_STATUS) go out on time whether or
not samples come. Rates come from the BRG_SR_* parameters
(:data:`bridge.app.paramspec.STREAM_RATES`), overridden per message by
MAV_CMD_SET_MESSAGE_INTERVAL.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from bridge.app.paramspec import STREAM_RATES
from bridge.core.pacing import early_s, next_slot

# The message ids, by name (one list, telemetry's): re-exported for the schedule's users.
from bridge.mavlink.telemetry import (
    ATTITUDE,
    ATTITUDE_QUATERNION,
    HEARTBEAT,
    HIGHRES_IMU,
    ODOMETRY,
    RAW_IMU,
    SCALED_IMU,
    SYS_STATUS,
    VFR_HUD,
    VISION_POSITION_ESTIMATE,
)


@dataclass(frozen=True, slots=True)
class StreamSpec:
    """One configurable stream: its message, the parameter holding its rate, its pacing."""

    msgid: int
    param: str  #: the BRG_SR_* parameter holding its rate (Hz, 0 = off)
    clock: bool  #: sent on time (True) or when a new sample arrives (False)

    @property
    def default_hz(self) -> float:
        """The parameter's built-in default."""
        return _RATES[self.param].default_hz

    @property
    def config_key(self) -> str:
        """The ``[mavlink]`` key giving the parameter's default."""
        return _RATES[self.param].config_key


_RATES = {r.param: r for r in STREAM_RATES}

#: The configurable streams. The heading feed's message depends on BRG_HDG_FEED.
STREAMS: tuple[StreamSpec, ...] = (
    StreamSpec(ATTITUDE, "BRG_SR_ATT", False),
    StreamSpec(ATTITUDE_QUATERNION, "BRG_SR_QUAT", False),
    StreamSpec(VFR_HUD, "BRG_SR_HUD", False),
    StreamSpec(SCALED_IMU, "BRG_SR_SIMU", False),
    StreamSpec(RAW_IMU, "BRG_SR_RIMU", False),
    StreamSpec(HIGHRES_IMU, "BRG_SR_HIMU", False),
    StreamSpec(SYS_STATUS, "BRG_SR_SYS", True),
    StreamSpec(ODOMETRY, "BRG_SR_FEED", False),
)
#: The streams sent when a sample arrives (the rest go on the clock), in STREAMS' order.
SAMPLE_STREAMS: tuple[int, ...] = tuple(s.msgid for s in STREAMS if not s.clock)
#: The sample streams at the head of the plan that leave first, in a datagram of their own,
#: when others fall due on the same frame (VFR_HUD, the IMU streams, the heading feed: about
#: half the due frames at the shipped rates): the attitude is what an autopilot or a ground
#: station waits for, and it no longer waits for up to five more messages to be encoded and
#: framed (docs/performance-history.md, "The due frame's tail"). The order stays; the rest
#: follow in one datagram; a frame with nothing else due still sends everything in one.
ATTITUDE_FIRST: frozenset[int] = frozenset((ATTITUDE, ATTITUDE_QUATERNION))
#: VISION_POSITION_ESTIMATE shares the feed's rate (only one of the two is ever on).
FEED_MSGIDS = (ODOMETRY, VISION_POSITION_ESTIMATE)
HEARTBEAT_HZ = 1.0
#: Messages whose interval MAV_CMD_SET_MESSAGE_INTERVAL may change.
STREAMABLE: frozenset[int] = frozenset(
    {s.msgid for s in STREAMS} | {HEARTBEAT, VISION_POSITION_ESTIMATE}
)


def schedule_id(msgid: int) -> int:
    """The schedule slot of a message: VISION_POSITION_ESTIMATE shares the heading feed's."""
    return ODOMETRY if msgid == VISION_POSITION_ESTIMATE else msgid


def stream_for(msgid: int) -> StreamSpec | None:
    """The :class:`StreamSpec` of a message (the feed's for VISION_POSITION_ESTIMATE)."""
    if msgid == VISION_POSITION_ESTIMATE:
        msgid = ODOMETRY
    for s in STREAMS:
        if s.msgid == msgid:
            return s
    return None


class StreamSchedule:
    """Which streams are due (pure; ``now`` is any monotonic time in seconds).

    ``rates`` maps message id -> Hz (0 = off). A rate set with
    :meth:`set_override` (MAV_CMD_SET_MESSAGE_INTERVAL) wins over the base rate
    until cleared; base rates come from the BRG_SR_* parameters.

    The per-sample fast path: :meth:`set_sample_streams` names the sample
    streams the owner sends, :meth:`due_samples` is :meth:`due_on_sample` over
    them, and :attr:`sample_due_at` is the earliest time any of them can next
    fall due (``-inf``: unknown, ask :meth:`due_samples`; ``+inf``: none is on).
    At 100 Hz frames and a 50 Hz ATTITUDE half the frames carry no due stream:
    ``now < schedule.sample_due_at`` tells the caller so with one comparison
    instead of a rate lookup per stream. Every change of a rate, an override
    or the set of sample streams resets it to ``-inf``.
    """

    def __init__(self, rates: Mapping[int, float]) -> None:
        self._base: dict[int, float] = {}
        self._override: dict[int, float] = {}
        self._next: dict[int, float] = {}
        self._clock: set[int] = {HEARTBEAT} | {s.msgid for s in STREAMS if s.clock}
        self._sample_ids: tuple[int, ...] = ()
        # Bumped by every change. due_samples() notices a change made (by another thread)
        # while it ran, and then leaves sample_due_at at -inf rather than a stale value.
        self._generation = 0
        # (generation it was built for, ((msgid, period, early_s(period)), ...)) of the sample
        # streams that are on: rebuilt when the generation moved on.
        self._plan: tuple[int, tuple[tuple[int, float, float], ...]] = (-1, ())
        #: Earliest time a sample stream can be due (see the class docstring).
        self.sample_due_at = -math.inf
        for msgid, hz in rates.items():
            self.set_base(msgid, hz)
        self._base.setdefault(HEARTBEAT, HEARTBEAT_HZ)

    def _changed(self) -> None:
        # Order matters for a due_samples() running in another thread: the generation
        # first, then the cached time (see due_samples).
        self._generation += 1
        self.sample_due_at = -math.inf

    def set_base(self, msgid: int, hz: float) -> None:
        """The configured rate of a stream (Hz, 0 = off)."""
        if not (math.isfinite(hz) and hz >= 0.0):
            raise ValueError(f"rate must be a finite number >= 0, got {hz!r}")
        self._base[msgid] = float(hz)
        self._changed()

    def set_override(self, msgid: int, hz: float | None) -> None:
        """A temporary rate (``None``: back to the configured one)."""
        if hz is None:
            self._override.pop(msgid, None)
        else:
            if not (math.isfinite(hz) and hz >= 0.0):
                raise ValueError(f"rate must be a finite number >= 0, got {hz!r}")
            self._override[msgid] = float(hz)
        self._next.pop(msgid, None)  # start the new rhythm with the next opportunity
        self._changed()

    def set_sample_streams(self, msgids: Iterable[int]) -> None:
        """The sample streams :meth:`due_samples` looks at, in the order it reports them."""
        self._sample_ids = tuple(m for m in dict.fromkeys(msgids) if m not in self._clock)
        self._changed()

    @property
    def sample_streams(self) -> tuple[int, ...]:
        """The streams set with :meth:`set_sample_streams` (clock streams left out)."""
        return self._sample_ids

    def rate(self, msgid: int) -> float:
        """The rate in effect (Hz, 0 = off)."""
        return self._override.get(msgid, self._base.get(msgid, 0.0))

    def interval_us(self, msgid: int) -> int:
        """MESSAGE_INTERVAL's interval: microseconds, -1 when off."""
        hz = self.rate(msgid)
        return -1 if hz <= 0.0 else round(1e6 / hz)

    def _due(self, msgid: int, now: float) -> bool:
        hz = self.rate(msgid)
        if hz <= 0.0:
            return False
        period = 1.0 / hz
        nxt = self._next.get(msgid)
        if nxt is not None and now < nxt - early_s(period):
            return False
        self._next[msgid] = next_slot(nxt, now, period)  # bridge.core.pacing: the one rule
        return True

    def due_on_sample(self, msgids: Iterable[int], now: float) -> list[int]:
        """The sample streams among ``msgids`` to send with a sample arriving at ``now``."""
        # It moves the streams' next times: the fast path's cached time must be worked out anew.
        self.sample_due_at = -math.inf
        return [m for m in msgids if m not in self._clock and self._due(m, now)]

    def due_samples(self, now: float) -> list[int]:
        """:meth:`due_on_sample` over :meth:`set_sample_streams`'s streams; updates
        :attr:`sample_due_at`.

        The same arithmetic as :meth:`_due`, with each stream's period worked out
        once per rate change instead of on every sample.
        """
        # The generation is read before anything it guards: a plan built from rates read
        # after it carries it, so a change made meanwhile makes the plan stale, never wrong.
        generation = self._generation
        built_for, plan = self._plan
        if built_for != generation:
            rate = self.rate
            plan = tuple(
                (m, 1.0 / hz, early_s(1.0 / hz)) for m in self._sample_ids if (hz := rate(m)) > 0.0
            )
            self._plan = (generation, plan)
        nexts = self._next
        due: list[int] = []
        earliest = math.inf
        for m, period, early in plan:
            nxt = nexts.get(m)
            if nxt is None or now >= nxt - early:
                nxt = nexts[m] = next_slot(nxt, now, period)
                due.append(m)
            if nxt - early < earliest:
                earliest = nxt - early
        self.sample_due_at = earliest
        if self._generation != generation:
            # Changed meanwhile (another thread): the value just stored may predate the
            # change, whose own reset may have come before it. Reset again.
            self.sample_due_at = -math.inf
        return due

    def due_on_clock(self, now: float) -> list[int]:
        """The clock streams due at ``now``."""
        return [m for m in sorted(self._clock) if self._due(m, now)]

    def next_clock_due(self, now: float) -> float:
        """When the next clock stream falls due (``now + 1`` when none is on)."""
        times = [
            self._next.get(m, now) - early_s(1.0 / self.rate(m))
            for m in self._clock
            if self.rate(m) > 0.0
        ]
        return min(times) if times else now + 1.0
