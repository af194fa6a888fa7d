"""What a live magnetometer calibration keeps of the frames, and how it judges the motion.

Pure (no clock, no threads, no I/O): time comes in as ``now``.

* :class:`FrameSeries` -- every frame of a collection in order, with its time:
  the hand-held fits (:mod:`bridge.calibration.fits.handheld`) need consecutive
  frames, not only ArduPilot's thinned sample buffer.
* :class:`MotionJudge` -- the operator's feedback while turning: the linear
  acceleration of the last few seconds (:func:`bridge.calibration.fits.series.motion_rms_g`,
  the same measure the fit reports) against a limit, at most one warning per
  interval. A hand's usual shake (0.05 g RMS per axis) reads about 0.04 g and
  is averaged away by the fit; from about 0.1 g the fit loses accuracy, and a
  turn faster than ~90 deg/s reads high too -- both are worth a "slower /
  steadier".
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from bridge.calibration.fits.series import MOTION_WINDOW_S, frame_period_s, frames_for, motion_rms_g
from bridge.types import BoolArray, FloatArray, Vec3

#: Frames a series keeps (the newest): 6 minutes at 100 Hz, beyond any calibration's time-out.
SERIES_CAPACITY = 36_000
#: The operator's warning (one STATUSTEXT: at most 50 characters).
MOTION_TEXT = "Too much motion: turn slower / steadier"
MOTION_INSTRUCTION = "turn slower / steadier"
DEFAULT_MOTION_LIMIT_G = 0.09


class FrameSeries:
    """The raw frames of one collection with their times, oldest first (bounded ring)."""

    def __init__(self, capacity: int = SERIES_CAPACITY) -> None:
        if capacity < 2:
            raise ValueError(f"capacity must be at least 2, got {capacity}")
        self._buf = np.empty((capacity, 8), dtype=np.float64)  # t, mag 3, acc 3, saturated
        self._n = 0
        self._next = 0

    def __len__(self) -> int:
        return self._n

    def add(self, now: float, mag_G: Vec3, acc_g: Vec3, saturated: bool) -> None:
        """One frame (raw nominal gauss / g) received at ``now``."""
        # one assignment of the row (four slice assignments cost four conversions)
        self._buf[self._next] = (now, *mag_G, *acc_g, 1.0 if saturated else 0.0)
        self._next = (self._next + 1) % self._buf.shape[0]
        self._n = min(self._n + 1, self._buf.shape[0])

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
        """Copies ``(t (N,), mag (N, 3), acc (N, 3), saturated (N,))`` in time order."""
        cap = self._buf.shape[0]
        if self._n < cap:
            rows = self._buf[: self._n].copy()
        else:
            rows = np.concatenate([self._buf[self._next :], self._buf[: self._next]])
        return rows[:, 0], rows[:, 1:4], rows[:, 4:7], rows[:, 7] > 0.5


@dataclass(frozen=True, slots=True)
class MotionWarning:
    """A judgement worth telling the operator: the level seen and the limit (RMS per axis, g)."""

    level_g: float
    limit_g: float

    @property
    def text(self) -> str:
        """The operator's sentence (<= 50 characters)."""
        return MOTION_TEXT

    def data(self) -> dict[str, float | str]:
        """Event details (JSON-ready)."""
        return {
            "accel_rms_g": round(self.level_g, 4),
            "limit_g": self.limit_g,
            "instruction": MOTION_INSTRUCTION,
        }


class MotionJudge:
    """Judges the last ``span_s`` of accelerometer frames every ``every_s``; warns at most every ``interval_s``.

    :meth:`feed` every frame; it returns a :class:`MotionWarning` when the
    level is above ``limit_g`` and the last warning is at least
    ``interval_s`` old. ``peak_g`` is the highest level judged so far.
    """

    def __init__(
        self,
        limit_g: float = DEFAULT_MOTION_LIMIT_G,
        interval_s: float = 5.0,
        *,
        span_s: float = 2.0 * MOTION_WINDOW_S,
        every_s: float = 0.5,
    ) -> None:
        for name, v in (("limit_g", limit_g), ("interval_s", interval_s), ("span_s", span_s)):
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be positive and finite, got {v!r}")
        self.limit_g = float(limit_g)
        self.interval_s = float(interval_s)
        self.span_s = float(span_s)
        self.every_s = float(every_s)
        self._rows: deque[tuple[float, float, float, float]] = deque()
        self._next_judge: float | None = None
        self._last_warning: float = -math.inf
        self.level_g: float = math.nan  #: the last level judged
        self.peak_g: float = 0.0
        self.warnings = 0

    def feed(self, now: float, acc_g: Vec3, saturated: bool = False) -> MotionWarning | None:
        """One frame's raw accelerometer vector (nominal g) at ``now``."""
        x, y, z = acc_g
        if saturated or not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            return None
        self._rows.append((now, x, y, z))
        while self._rows and self._rows[0][0] < now - self.span_s:
            self._rows.popleft()
        if self._next_judge is None:
            self._next_judge = now + self.every_s
        if now < self._next_judge:
            return None
        self._next_judge = now + self.every_s
        level = self.judge()
        if not math.isfinite(level):
            return None
        self.level_g = level
        self.peak_g = max(self.peak_g, level)
        if level <= self.limit_g or now - self._last_warning < self.interval_s:
            return None
        self._last_warning = now
        self.warnings += 1
        return MotionWarning(level, self.limit_g)

    def judge(self) -> float:
        """The linear-acceleration level of the frames held (NaN: not enough of them yet)."""
        n_rows = len(self._rows)
        if n_rows < 5:
            return math.nan
        # The rows' numbers in one flat run: numpy builds an array from a sequence of
        # tuples element by element, at three times the cost (this runs every half second
        # of a collection, on a few hundred rows)
        flat = itertools.chain.from_iterable(self._rows)
        a = np.fromiter(flat, np.float64, 4 * n_rows).reshape(n_rows, 4)
        if a[-1, 0] - a[0, 0] < 0.9 * self.span_s:
            return math.nan
        n = frames_for(MOTION_WINDOW_S, frame_period_s(a[:, 0]), minimum=5)
        return motion_rms_g(a[-(a.shape[0] // n) * n :, 1:4], n) if a.shape[0] >= n else math.nan
