"""A vehicle driving: the simulated unit's motion in service (turns, road roll and pitch,
the vehicle's own accelerations), for the drift monitor's tests and benchmark.

Separate from :mod:`bridge.sim.motion` (the calibration motions) only by size; it is a
motion script like those: a pure, seeded function of time.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from bridge.core.geometry import euler_to_dcm, euler_to_dcm_batch
from bridge.core.sensor import STANDARD_GRAVITY
from bridge.sim.motion import MotionBase
from bridge.types import FloatArray


def _raised_cosine(
    tau: Any, length: Any, dyaw: Any, sin: Callable[[Any], Any], cos: Callable[[Any], Any]
) -> tuple[Any, Any]:
    """A turn of ``dyaw`` over ``length`` seconds as a raised cosine of the rate: the yaw
    turned and the rate ``tau`` seconds in (floats with ``math``'s sin and cos, arrays with
    numpy's: one copy for a frame at a time and a drive's worth at once)."""
    x = 2.0 * math.pi * tau / length
    return dyaw * (tau / length - sin(x) / (2.0 * math.pi)), dyaw / length * (1.0 - cos(x))


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
        i = bisect_right(self._t0, t) - 1  # (np.searchsorted made an array of the list each call)
        tau, length, dyaw = t - self._t0[i], self._len[i], self._dyaw[i]
        if dyaw == 0.0:
            return self._yaw0[i], 0.0
        turned, rate = _raised_cosine(tau, length, dyaw, math.sin, math.cos)
        return self._yaw0[i] + turned, rate

    def _angle(self, which: int, t: float) -> float:
        amp, omega, phase = self._tilt[which]
        return float(np.sum(amp * np.sin(omega * t + phase)))

    def speed(self, t: float) -> tuple[float, float]:
        """(speed m/s, its rate m/s^2) at ``t``."""
        return self._speed(t, math.sin, math.cos)

    def _speed(self, t: Any, sin: Callable[[Any], Any], cos: Callable[[Any], Any]) -> Any:
        """:meth:`speed`'s formula, at a time (``math``'s sin and cos) or at an array of
        times (numpy's): one copy for the frame-by-frame path and the benchmarks' arrays."""
        p1, p2 = self._speed_phase
        w1, w2 = 2.0 * math.pi / 67.0, 2.0 * math.pi / 23.0
        v = self.speed_mps * (1.0 + 0.2 * sin(w1 * t + p1) + 0.05 * sin(w2 * t + p2))
        dv = self.speed_mps * (0.2 * w1 * cos(w1 * t + p1) + 0.05 * w2 * cos(w2 * t + p2))
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
        return np.array([dv * c - lat * s, dv * s + lat * c, 0.0]) / STANDARD_GRAVITY

    # -- whole streams at once (the same formulas on arrays, for the benchmarks) ------

    def _yaws(self, ts: FloatArray) -> tuple[FloatArray, FloatArray]:
        """:meth:`_yaw` at each of ``ts`` (already clamped at 0)."""
        if ts.size:
            self._extend(float(ts.max()))
        t0, length, dyaw = np.array(self._t0), np.array(self._len), np.array(self._dyaw)
        i = np.searchsorted(t0, ts, side="right") - 1
        tau, length, dyaw = ts - t0[i], length[i], dyaw[i]
        turned, rate = _raised_cosine(tau, length, dyaw, np.sin, np.cos)
        turning = dyaw != 0.0
        return np.array(self._yaw0)[i] + np.where(turning, turned, 0.0), np.where(
            turning, rate, 0.0
        )

    def _angles(self, which: int, ts: FloatArray) -> FloatArray:
        amp, omega, phase = self._tilt[which]
        return np.sum(amp * np.sin(omega * ts[:, None] + phase), axis=1)

    def attitudes(self, times: npt.ArrayLike) -> FloatArray:
        """:meth:`attitude` at each time, as an (N, 3, 3) stack."""
        ts = np.maximum(np.asarray(times, dtype=np.float64).reshape(-1), 0.0)
        return euler_to_dcm_batch(self._angles(0, ts), self._angles(1, ts), self._yaws(ts)[0])

    def linear_accs_ned_g(self, times: npt.ArrayLike) -> FloatArray:
        """:meth:`linear_acc_ned_g` at each time, as an (N, 3) array."""
        ts = np.maximum(np.asarray(times, dtype=np.float64).reshape(-1), 0.0)
        yaw, rate = self._yaws(ts)
        v, dv = self._speed(ts, np.sin, np.cos)
        c, s = np.cos(yaw), np.sin(yaw)
        lat = v * rate
        out = np.zeros((len(ts), 3))
        out[:, 0], out[:, 1] = dv * c - lat * s, dv * s + lat * c
        return out / STANDARD_GRAVITY


#: Kinds of :class:`ManoeuvreDrive` stretch, in the order :attr:`ManoeuvreDrive.KINDS` numbers them.
MANOEUVRES = ("cruise", "turn", "stop", "start", "waves")


class ManoeuvreDrive(MotionBase):
    """A vehicle's drive with real accelerations: turns, stops and starts, a wavy road.

    The path is built from seeded stretches, each after ``cruise_s`` (uniform) of
    straight, steady driving at ``speed_mps``:

    * **turn** -- ``turn_deg`` (uniform, either side) with a raised-cosine yaw rate
      whose peak gives a centripetal ``v * yaw_rate`` drawn in ``accel_g``;
    * **stop / start** -- braking to a standstill with a raised-cosine deceleration
      peaking in ``accel_g``, ``halt_s`` at rest, then driving off the same way;
    * **waves** -- a stretch of swell (``waves_s``): the road (or the sea) rises and
      falls under the vehicle, ``z = A sin(k s)`` along the track, crossing it at an
      angle, so the vehicle pitches and rolls with the slope while it heaves; the
      amplitude gives a vertical acceleration peaking in ``accel_g``.

    Under it all, the road's camber and grade (three slow tones each, peaks
    ``max_roll_deg`` / ``max_pitch_deg``) and vibration (``vibration_g`` RMS per
    axis, white at the frame rate; only while the vehicle moves).

    The vehicle's pitch is the road's slope and its roll the road's cross slope;
    its acceleration is the derivative of its velocity along that road
    (``v * [cos(slope) cos(yaw), cos(slope) sin(yaw), -sin(slope)]``), so turns,
    braking, grades and swell all give the accelerometer exactly what they would.
    Not modelled: a boat's sway in beam seas (a raft that follows the wave surface
    reads no tilt at all: no estimator without gyros can see that roll).

    The schedule is computed for ``duration_s`` on a ``grid_hz`` grid and
    interpolated; after ``duration_s`` the vehicle holds its last attitude, at
    rest. :meth:`kind_at` names the stretch a time falls in.
    """

    KINDS = MANOEUVRES

    def __init__(
        self,
        seed: int = 0,
        duration_s: float = 600.0,
        *,
        speed_mps: float = 10.0,
        accel_g: tuple[float, float] = (0.15, 0.3),
        cruise_s: tuple[float, float] = (3.0, 10.0),
        turn_deg: tuple[float, float] = (45.0, 180.0),
        halt_s: tuple[float, float] = (1.0, 4.0),
        waves_s: tuple[float, float] = (10.0, 25.0),
        wavelength_m: tuple[float, float] = (15.0, 40.0),
        max_roll_deg: float = 10.0,
        max_pitch_deg: float = 10.0,
        vibration_g: float = 0.01,
        grid_hz: float = 200.0,
    ) -> None:
        if not (math.isfinite(duration_s) and duration_s > 0.0):
            raise ValueError(f"duration_s must be finite and > 0, got {duration_s!r}")
        if not (math.isfinite(speed_mps) and speed_mps > 0.0):
            raise ValueError(f"speed_mps must be finite and > 0, got {speed_mps!r}")
        for name, (lo, hi) in (
            ("accel_g", accel_g),
            ("cruise_s", cruise_s),
            ("turn_deg", turn_deg),
            ("halt_s", halt_s),
            ("waves_s", waves_s),
            ("wavelength_m", wavelength_m),
        ):
            if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= hi):
                raise ValueError(f"{name} must be 0 < low <= high, got {(lo, hi)!r}")
        if not (math.isfinite(vibration_g) and vibration_g >= 0.0):
            raise ValueError(f"vibration_g must be finite and >= 0, got {vibration_g!r}")
        self.seed = seed
        self.duration = float(duration_s)
        self.speed_mps = float(speed_mps)
        rng = np.random.default_rng([seed, 0x5A1E])
        dt = 1.0 / grid_hz
        n = math.ceil(duration_s * grid_hz) + 3
        t = np.arange(n) * dt
        yaw_rate = np.zeros(n)  # rad/s
        dv = np.zeros(n)  # m/s^2 along the track
        wave_amp = np.zeros(n)  # m
        wave_k = np.full(n, 1.0)  # rad/m
        wave_cross = np.zeros(n)  # rad: angle between the crests' normal and the track
        kind = np.zeros(n, dtype=np.int64)
        v0 = self.speed_mps
        at = float(rng.uniform(*cruise_s))
        events = ("turn", "stop", "waves")
        while at < duration_s:
            what = events[int(rng.integers(len(events)))]
            a_peak = float(rng.uniform(*accel_g)) * STANDARD_GRAVITY
            if what == "turn":
                dyaw = math.radians(float(rng.uniform(*turn_deg))) * float(rng.choice([-1.0, 1.0]))
                rate = a_peak / v0  # the peak yaw rate giving that centripetal acceleration
                length = 2.0 * abs(dyaw) / rate
                i0, i1 = int(at / dt), min(n, int((at + length) / dt))
                x = (t[i0:i1] - at) / length
                yaw_rate[i0:i1] = dyaw / length * (1.0 - np.cos(2.0 * math.pi * x))
                kind[i0:i1] = MANOEUVRES.index("turn")
                at += length
            elif what == "stop":
                ramp = 2.0 * v0 / a_peak  # raised cosine: mean deceleration a_peak / 2
                for sign, name in ((-1.0, "stop"), (1.0, "start")):
                    i0, i1 = int(at / dt), min(n, int((at + ramp) / dt))
                    x = (t[i0:i1] - at) / ramp
                    dv[i0:i1] = sign * 0.5 * a_peak * (1.0 - np.cos(2.0 * math.pi * x))
                    kind[i0:i1] = MANOEUVRES.index(name)
                    at += ramp
                    if name == "stop":
                        halt = float(rng.uniform(*halt_s))
                        i0, i1 = int(at / dt), min(n, int((at + halt) / dt))
                        kind[i0:i1] = MANOEUVRES.index("stop")
                        at += halt
            else:
                length = float(rng.uniform(*waves_s))
                k = 2.0 * math.pi / float(rng.uniform(*wavelength_m))
                cross = float(rng.uniform(-0.6, 0.6))  # up to ~35 deg off the track
                kk = k * math.cos(cross)  # wavenumber along the track
                amp = a_peak / (kk * v0) ** 2  # heave acceleration amplitude = a_peak
                i0, i1 = int(at / dt), min(n, int((at + length) / dt))
                x = (t[i0:i1] - at) / length
                # Eased in and out over the stretch, so the road never steps.
                wave_amp[i0:i1] = amp * np.sin(math.pi * x) ** 2
                wave_k[i0:i1] = k
                wave_cross[i0:i1] = cross
                kind[i0:i1] = MANOEUVRES.index("waves")
                at += length
            at += float(rng.uniform(*cruise_s))
        speed = np.maximum(0.0, v0 + np.cumsum(dv) * dt)
        s = np.cumsum(speed) * dt  # distance along the track
        yaw = float(rng.uniform(0.0, 2.0 * math.pi)) + np.cumsum(yaw_rate) * dt
        tones = np.random.default_rng([seed, 0x70AD])

        def road(peak_deg: float) -> FloatArray:
            amp, omega, phase = Drive._tones(tones, math.radians(peak_deg))
            # A tone of the road is a function of distance, not of time: it stays put
            # while the vehicle stands.
            return np.asarray(
                np.sum(amp[:, None] * np.sin(omega[:, None] * s[None, :] / v0 + phase[:, None]), 0)
            )

        # The wave surface along the track and across it: slopes in both directions.
        # (Each cosine of a whole drive's grid taken once: they are most of this build.)
        cos_cross = np.cos(wave_cross)
        phase = wave_k * cos_cross * s
        cos_phase = np.cos(phase)
        slope_along = wave_amp * wave_k * cos_cross * cos_phase
        slope_across = wave_amp * wave_k * np.sin(wave_cross) * cos_phase
        pitch = road(max_pitch_deg) + np.arctan(slope_along)
        roll = road(max_roll_deg) + np.arctan(slope_across)
        # Velocity along the road (nose-up pitch climbs: NED down velocity negative).
        cos_pitch = np.cos(pitch)
        vel = speed[:, None] * np.stack(
            [cos_pitch * np.cos(yaw), cos_pitch * np.sin(yaw), -np.sin(pitch)], axis=1
        )
        acc = np.gradient(vel, dt, axis=0) / STANDARD_GRAVITY
        vib = np.random.default_rng([seed, 0x71B]).normal(0.0, vibration_g, size=(n, 3))
        moving = (speed > 0.05)[:, None]
        self._t = t
        self._dt = dt
        self._roll, self._pitch, self._yaw = roll, pitch, yaw
        self._acc = acc
        self._vib = vib * moving
        self._kind = kind
        self._speed = speed

    def _index(self, t: float) -> tuple[int, float]:
        x = min(max(0.0, t), self.duration) / self._dt
        i = min(int(x), len(self._t) - 2)
        return i, x - i

    def _lerp(self, a: FloatArray, t: float) -> float:
        i, f = self._index(t)
        return float(a[i] + f * (a[i + 1] - a[i]))

    def attitude(self, t: float) -> FloatArray:
        """The road's roll and pitch, the track's yaw."""
        return euler_to_dcm(
            self._lerp(self._roll, t), self._lerp(self._pitch, t), self._lerp(self._yaw, t)
        )

    def attitudes(self, times: npt.ArrayLike) -> FloatArray:
        """:meth:`attitude` at each time, as an (N, 3, 3) stack (the same interpolation,
        vectorised: the stand-in autopilot asks for a drive's worth at once)."""
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        x = np.minimum(np.maximum(0.0, t), self.duration) / self._dt
        i = np.minimum(x.astype(np.int64), len(self._t) - 2)
        f = x - i

        def lerp(a: FloatArray) -> FloatArray:
            return np.asarray(a[i] + f * (a[i + 1] - a[i]), dtype=np.float64)

        return euler_to_dcm_batch(lerp(self._roll), lerp(self._pitch), lerp(self._yaw))

    def linear_acc_ned_g(self, t: float) -> FloatArray:
        """The vehicle's acceleration (g, NED) plus vibration; zero after the drive."""
        if t > self.duration:
            return np.zeros(3)
        i, f = self._index(t)
        a = self._acc[i] + f * (self._acc[i + 1] - self._acc[i])
        # Vibration: the sample nearest in time (white at any frame rate, not smoothed).
        return np.asarray(a + self._vib[i if f < 0.5 else i + 1], dtype=np.float64)

    def manoeuvre_acc_ned_g(self, t: float) -> FloatArray:
        """The vehicle's acceleration without the vibration (what the benchmarks call
        "accelerating": the manoeuvres themselves)."""
        if t > self.duration:
            return np.zeros(3)
        i, f = self._index(t)
        return np.asarray(self._acc[i] + f * (self._acc[i + 1] - self._acc[i]), dtype=np.float64)

    def _indices(
        self, times: npt.ArrayLike
    ) -> tuple[FloatArray, npt.NDArray[np.int64], FloatArray]:
        """:meth:`_index` at each time (vectorised): the times, the indices, the fractions."""
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        x = np.minimum(np.maximum(0.0, t), self.duration) / self._dt
        i = np.minimum(x.astype(np.int64), len(self._t) - 2)
        return t, i, x - i

    def manoeuvre_accs_ned_g(self, times: npt.ArrayLike) -> FloatArray:
        """:meth:`manoeuvre_acc_ned_g` at each time, as an (N, 3) array (the same numbers)."""
        t, i, f = self._indices(times)
        a = self._lerp_acc(i, f)
        a[t > self.duration] = 0.0
        return a

    def _lerp_acc(self, i: npt.NDArray[np.int64], f: FloatArray) -> FloatArray:
        """The manoeuvres' acceleration between samples ``i`` and ``i + 1`` (fractions ``f``)."""
        return np.asarray(
            self._acc[i] + f[:, None] * (self._acc[i + 1] - self._acc[i]), dtype=np.float64
        )

    def linear_accs_ned_g(self, times: npt.ArrayLike) -> FloatArray:
        """:meth:`linear_acc_ned_g` at each time, as an (N, 3) array (the same numbers:
        a benchmark's frames ask for a drive's worth at once)."""
        t, i, f = self._indices(times)
        a = self._lerp_acc(i, f) + self._vib[np.where(f < 0.5, i, i + 1)]
        a[t > self.duration] = 0.0
        return a

    def kind_at(self, t: float) -> str:
        """The stretch ``t`` falls in: one of :data:`MANOEUVRES`."""
        i, _ = self._index(t)
        return MANOEUVRES[int(self._kind[i])]

    def kinds_at(self, times: npt.ArrayLike) -> npt.NDArray[np.str_]:
        """:meth:`kind_at` at each time, as an array of names (the same names: a benchmark
        asks for a drive's worth at once)."""
        _t, i, _f = self._indices(times)
        return np.array(MANOEUVRES)[self._kind[i]]

    def speed(self, t: float) -> float:
        """Speed along the track, m/s."""
        return self._lerp(self._speed, t)
