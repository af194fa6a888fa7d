"""Publication pacing: rate caps per stream and a frame-rate meter. PURE (times come in)."""

from __future__ import annotations

import math
from collections import deque

from bridge.core.pacing import early_s, next_slot


class Decimator:
    """Lets samples through at most ``rate_hz`` (0 = every sample).

    Frames arrive with jitter (serial + USB + scheduling), so a strict
    ``t - last >= period`` would skip a frame that came a millisecond early
    and publish at two thirds of the asked rate. Instead each accepted sample
    books the next slot (:func:`bridge.core.pacing.next_slot`, the rule of
    MAVLink's streams too), and a sample a little early
    (:func:`~bridge.core.pacing.early_s`) still takes its slot; a gap longer
    than a period restarts the schedule (no burst to catch up).
    """

    def __init__(self, rate_hz: float) -> None:
        if not rate_hz >= 0.0:
            raise ValueError(f"rate_hz must be >= 0, got {rate_hz}")
        self.rate_hz = rate_hz
        self._period = 1.0 / rate_hz if rate_hz > 0 else 0.0
        self._early = early_s(self._period)
        self._due: float | None = None

    @property
    def opens_at(self) -> float:
        """The earliest time a sample is accepted: ``accept(t)`` is True exactly when
        ``t >= opens_at`` (``-inf`` when the next sample is taken whenever it comes)."""
        if self._period == 0.0 or self._due is None:
            return -math.inf
        # A restart (t > due + period) is also past this, so it is the one condition.
        return self._due - self._early

    def accept(self, t: float) -> bool:
        """Whether the sample at time ``t`` (seconds, monotonic) is published."""
        if self._period == 0.0:
            return True
        if self._due is not None and t < self._due - self._early:
            return False
        self._due = next_slot(self._due, t, self._period)
        return True


class RateMeter:
    """Frames per second from a cumulative counter, over a sliding window.

    ``add(t, count)`` records the counter's value at time ``t``; ``rate(t)``
    is the counter's growth over the last ``window`` seconds. A counter that
    goes backwards (a new link) restarts the window.
    """

    def __init__(self, window: float = 2.0) -> None:
        if not window > 0.0:
            raise ValueError(f"window must be positive, got {window}")
        self.window = window
        self._points: deque[tuple[float, int]] = deque()

    def add(self, t: float, count: int) -> None:
        """Record the cumulative ``count`` at time ``t``."""
        if self._points and count < self._points[-1][1]:
            self._points.clear()
        self._points.append((t, count))
        # Keep one point at or before the window's start so the span covers the whole window.
        while len(self._points) > 2 and self._points[1][0] <= t - self.window:
            self._points.popleft()

    def rate(self) -> float | None:
        """Counts per second over the window, or None before two points a moment apart."""
        if len(self._points) < 2:
            return None
        (t0, c0), (t1, c1) = self._points[0], self._points[-1]
        if t1 - t0 < 1e-3:
            return None
        return (c1 - c0) / (t1 - t0)


class StatusTiming:
    """When ``<prefix>/status`` goes out: at once at the start, then every ``period_s``,
    and at once when what it says changes (:func:`~bridge.zenoh.schema.change_key`: the
    link's and the calibration's state).

    The publisher sleeps until :attr:`next_look`. A change is looked for only when
    something may have changed: an event came or the link's state moved
    (:meth:`note_change`), so the status key -- a few snapshots -- is not read on a
    clock. ``poll_s`` is for a bridge that cannot say when its link's state moves:
    then the key is also looked at every ``poll_s``.
    """

    def __init__(self, period_s: float, poll_s: float | None = None) -> None:
        if not period_s > 0.0:
            raise ValueError(f"period_s must be positive, got {period_s}")
        if poll_s is not None and not poll_s > 0.0:
            raise ValueError(f"poll_s must be positive, got {poll_s}")
        self.period_s = period_s
        self.poll_s = poll_s
        self._next_status = -math.inf  # the first status goes out at once
        self._next_poll = math.inf if poll_s is None else -math.inf
        self._changed = False
        self._key: tuple[object, ...] | None = None

    @property
    def next_look(self) -> float:
        """When the publisher must look next without being woken (the period, a poll)."""
        return min(self._next_status, self._next_poll)

    def note_change(self) -> None:
        """Something the status says may have changed: look at the key at the next look."""
        self._changed = True

    def due(self, now: float) -> bool:
        """Whether the period has come round (publish without looking at the key)."""
        return now >= self._next_status

    def must_look(self, now: float) -> bool:
        """Whether to read the status key now (a change was noted, or a poll is due); the
        caller then reads it and hands it to :meth:`changed`. The note is taken here,
        before the key is read: a change noted while it is read is looked at again."""
        if not (self._changed or now >= self._next_poll):
            return False
        self._changed = False
        if self.poll_s is not None:
            self._next_poll = now + self.poll_s
        return True

    def changed(self, key: tuple[object, ...]) -> bool:
        """Whether ``key`` (read after :meth:`must_look`) differs from the last published."""
        return key != self._key

    def published(self, key: tuple[object, ...], now: float) -> None:
        """A status with ``key`` went out at ``now``: the next one a period later."""
        self._key = key
        self._next_status = now + self.period_s
        if self.poll_s is not None:
            self._next_poll = now + self.poll_s
