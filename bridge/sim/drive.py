"""A vehicle driving: the simulated unit's motion in service (turns, road roll and pitch,
the vehicle's own accelerations), for the drift monitor's tests and benchmark.

Separate from :mod:`bridge.sim.motion` (the calibration motions) only by size; it is a
motion script like those: a pure, seeded function of time.
"""

from __future__ import annotations

import math

import numpy as np

from bridge.core.geometry import euler_to_dcm
from bridge.sim.motion import MotionBase
from bridge.types import FloatArray


class Drive(MotionBase):
    """A vehicle driving: straights and turns, rolling and pitching, with the acceleration it feels.

    Heading: straight stretches (``straight_s``, uniform) alternate with turns of
    ``turn_deg`` (uniform; the side is random, kept with probability 0.6, so the
    vehicle sometimes circles) at up to ``turn_rate_dps``, with a raised-cosine
    rate profile (no jerk). Roll and pitch: road camber and slope, three slow tones
    each (periods 20-120 s), peaks bounded by ``max_roll_deg`` / ``max_pitch_deg``.
    Speed: ``speed_mps`` varying +-25 % over a minute or so.

    ``linear_acc_ned_g`` is what a car's accelerometer feels besides gravity: the
    along-track speed change plus the centripetal ``v * yaw_rate`` across the
    track (0.27 g in a 15 deg/s turn at 10 m/s -- a tilt error of 15 deg for an
    accelerometer that takes it for gravity). The schedule is drawn from ``seed``
    lazily, in order, so the script is a pure function of ``t`` however it is asked.
    """

    _CHUNK = 64  # segments drawn at a time
    _G0 = 9.80665

    def __init__(
        self,
        seed: int = 0,
        *,
        speed_mps: float = 10.0,
        turn_rate_dps: float = 15.0,
        straight_s: tuple[float, float] = (4.0, 20.0),
        turn_deg: tuple[float, float] = (30.0, 180.0),
        max_roll_deg: float = 15.0,
        max_pitch_deg: float = 15.0,
    ) -> None:
        for name, v in (("speed_mps", speed_mps), ("turn_rate_dps", turn_rate_dps)):
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        for name, (lo, hi) in (("straight_s", straight_s), ("turn_deg", turn_deg)):
            if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= hi):
                raise ValueError(f"{name} must be 0 < low <= high, got {(lo, hi)!r}")
        for name, v in (("max_roll_deg", max_roll_deg), ("max_pitch_deg", max_pitch_deg)):
            if not (math.isfinite(v) and 0.0 <= v < 80.0):
                raise ValueError(f"{name} must lie in [0, 80), got {v!r}")
        self.seed = seed
        self.speed_mps = float(speed_mps)
        self.duration = math.inf
        self._rate = math.radians(turn_rate_dps)
        self._straight = (float(straight_s[0]), float(straight_s[1]))
        self._turn = (math.radians(turn_deg[0]), math.radians(turn_deg[1]))
        self._rng = np.random.default_rng([seed, 0xD21E])
        tones = np.random.default_rng([seed, 0x7A1])
        self._tilt = [self._tones(tones, math.radians(m)) for m in (max_roll_deg, max_pitch_deg)]
        self._speed_phase = tones.uniform(0.0, 2.0 * math.pi, size=2)
        # segments: start time, length, yaw at the start, yaw change (0 on a straight)
        self._t0: list[float] = [0.0]
        self._len: list[float] = []
        self._yaw0: list[float] = [float(self._rng.uniform(0.0, 2.0 * math.pi))]
        self._dyaw: list[float] = []
        self._side = 1.0
        self._extend(0.0)

    @staticmethod
    def _tones(rng: np.random.Generator, peak: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        w = rng.uniform(0.5, 1.0, size=3)
        omega = 2.0 * math.pi / rng.uniform(20.0, 120.0, size=3)
        return peak * w / w.sum(), omega, rng.uniform(0.0, 2.0 * math.pi, size=3)

    def _extend(self, t: float) -> None:
        """Draw segments until the schedule covers ``t`` (always in the same order)."""
        while self._t0[-1] <= t:
            for _ in range(self._CHUNK):
                straight = len(self._len) % 2 == 0
                if straight:
                    length, dyaw = float(self._rng.uniform(*self._straight)), 0.0
                else:
                    if self._rng.uniform() > 0.6:
                        self._side = -self._side
                    dyaw = self._side * float(self._rng.uniform(*self._turn))
                    length = 2.0 * abs(dyaw) / self._rate  # the peak rate of the raised cosine
                self._len.append(length)
                self._dyaw.append(dyaw)
                self._t0.append(self._t0[-1] + length)
                self._yaw0.append(self._yaw0[-1] + dyaw)

    def _yaw(self, t: float) -> tuple[float, float]:
        """(yaw, yaw rate) at ``t``."""
        t = max(0.0, t)
        self._extend(t)
        i = int(np.searchsorted(self._t0, t, side="right")) - 1
        tau, length, dyaw = t - self._t0[i], self._len[i], self._dyaw[i]
        if dyaw == 0.0:
            return self._yaw0[i], 0.0
        x = 2.0 * math.pi * tau / length
        return (
            self._yaw0[i] + dyaw * (tau / length - math.sin(x) / (2.0 * math.pi)),
            dyaw / length * (1.0 - math.cos(x)),
        )

    def _angle(self, which: int, t: float) -> float:
        amp, omega, phase = self._tilt[which]
        return float(np.sum(amp * np.sin(omega * t + phase)))

    def speed(self, t: float) -> tuple[float, float]:
        """(speed m/s, its rate m/s^2) at ``t``."""
        p1, p2 = self._speed_phase
        w1, w2 = 2.0 * math.pi / 67.0, 2.0 * math.pi / 23.0
        v = self.speed_mps * (1.0 + 0.2 * math.sin(w1 * t + p1) + 0.05 * math.sin(w2 * t + p2))
        dv = self.speed_mps * (0.2 * w1 * math.cos(w1 * t + p1) + 0.05 * w2 * math.cos(w2 * t + p2))
        return v, dv

    def yaw_rate_dps(self, t: float) -> float:
        """The turn rate at ``t`` (deg/s, clockwise positive)."""
        return math.degrees(self._yaw(t)[1])

    def attitude(self, t: float) -> FloatArray:
        """Roll and pitch of the road, yaw of the track."""
        t = max(0.0, t)
        return euler_to_dcm(self._angle(0, t), self._angle(1, t), self._yaw(t)[0])

    def linear_acc_ned_g(self, t: float) -> FloatArray:
        """Along-track speed change plus the centripetal acceleration of the turn (g, NED)."""
        t = max(0.0, t)
        yaw, rate = self._yaw(t)
        v, dv = self.speed(t)
        c, s = math.cos(yaw), math.sin(yaw)
        lat = v * rate
        return np.array([dv * c - lat * s, dv * s + lat * c, 0.0]) / self._G0
