"""Motion scripts: the simulated unit's attitude as a function of time (ground truth).

A script maps time ``t`` (seconds since the script started) to ``R``, the body -> NED
rotation. Angles are radians unless a name says ``_deg``. Before 0 a script holds
its first attitude and after ``duration`` its last one, so a finished script is a
unit left lying still. Scripts are pure functions of ``t``: any time can be asked
for, in any order, and a seeded script gives the same answer every run.

``linear_acc_ned_g(t)`` is the body's linear acceleration in g (NED) for scripts
that shake (:class:`Shaken`, a vibration; :class:`HandShake`, a person holding the
unit); the attitude scripts here return zero (human-rate rotations about the
sensor produce well under 0.01 g).
"""

from __future__ import annotations

import itertools
import math
from bisect import bisect_right
from collections.abc import Iterable
from collections.abc import Sequence as SequenceABC
from typing import Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from bridge.core.geometry import (
    axis_angle_to_dcm,
    dcm_to_euler,
    dcm_to_rotvec,
    euler_to_dcm,
    rotvec_to_dcm,
    wrap_degrees_360,
)
from bridge.sim.physics import default_field_ned_G
from bridge.types import FloatArray

Euler = tuple[float, float, float]

_ZERO3 = np.zeros(3)
_ZERO3.flags.writeable = False


@runtime_checkable
class Motion(Protocol):
    """What the firmware and the benchmarks need from a motion script.

    A script may also offer ``linear_acc_ned_g(t)`` (see :func:`linear_acc_of`).
    """

    @property
    def duration(self) -> float:
        """Length in seconds (``math.inf`` for an endless script)."""
        ...

    def attitude(self, t: float) -> FloatArray:
        """Body -> NED rotation matrix (3, 3) at time ``t``."""
        ...

    def heading_deg(self, t: float) -> float:
        """True heading (yaw from north, clockwise) in [0, 360) at ``t``."""
        ...

    def euler(self, t: float) -> Euler:
        """ZYX Euler angles (roll, pitch, yaw) in radians at ``t``."""
        ...

    def attitudes(self, times: npt.ArrayLike) -> FloatArray:
        """:meth:`attitude` at each time, as an (N, 3, 3) stack."""
        ...


def linear_acc_of(motion: Motion, t: float) -> FloatArray:
    """``motion.linear_acc_ned_g(t)`` if the script shakes, else zero (it is optional)."""
    f = getattr(motion, "linear_acc_ned_g", None)
    return _ZERO3 if f is None else np.asarray(f(t), dtype=np.float64)


def linear_accs_of(motion: Motion, times: npt.ArrayLike) -> FloatArray:
    """:func:`linear_acc_of` at each time, as an (N, 3) array: the script's own vectorised
    ``linear_accs_ned_g`` where it has one (the same numbers), else time by time."""
    ts = np.asarray(times, dtype=np.float64).reshape(-1)
    f = getattr(motion, "linear_accs_ned_g", None)
    if f is not None:
        return np.asarray(f(ts), dtype=np.float64).reshape(-1, 3)
    return np.array([linear_acc_of(motion, float(t)) for t in ts]).reshape(-1, 3)


class MotionBase:
    """Shared helpers; a script only implements :meth:`attitude` and ``duration``."""

    duration: float = math.inf

    def attitude(self, t: float) -> FloatArray:  # pragma: no cover - abstract
        """Body -> NED rotation matrix (3, 3) at time ``t``."""
        raise NotImplementedError

    def linear_acc_ned_g(self, t: float) -> FloatArray:
        """Zero: these scripts only rotate."""
        return _ZERO3

    def heading_deg(self, t: float) -> float:
        """True heading in [0, 360): yaw of :meth:`euler`."""
        return wrap_degrees_360(math.degrees(self.euler(t)[2]))

    def euler(self, t: float) -> Euler:
        """ZYX Euler angles (roll, pitch, yaw), radians."""
        return dcm_to_euler(self.attitude(t))

    def attitudes(self, times: npt.ArrayLike) -> FloatArray:
        """``attitude`` at each time, as an (N, 3, 3) stack (for the benchmarks)."""
        ts = np.asarray(times, dtype=np.float64).reshape(-1)
        return np.stack([self.attitude(float(t)) for t in ts]) if ts.size else np.empty((0, 3, 3))


def _smoothstep(s: float) -> float:
    """0 -> 1 with zero slope at both ends, so angular rate is continuous at handovers."""
    s = min(1.0, max(0.0, s))
    return s * s * (3.0 - 2.0 * s)


def _check_time(name: str, v: float, *, positive: bool = False) -> float:
    v = float(v)
    if not math.isfinite(v) or v < 0.0 or (positive and v == 0.0):
        raise ValueError(f"{name} must be finite and {'> 0' if positive else '>= 0'}, got {v!r}")
    return v


class Still(MotionBase):
    """Lying still at one attitude, forever."""

    def __init__(self, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> None:
        self.roll, self.pitch, self.yaw = float(roll), float(pitch), float(yaw)
        self._R = euler_to_dcm(self.roll, self.pitch, self.yaw)
        self._R.flags.writeable = False
        self.duration = math.inf

    @classmethod
    def from_deg(cls, roll_deg: float = 0.0, pitch_deg: float = 0.0, yaw_deg: float = 0.0) -> Still:
        """Convenience constructor in degrees."""
        return cls(math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg))

    def attitude(self, t: float) -> FloatArray:
        """The fixed attitude."""
        return self._R


class YawTurns(MotionBase):
    """Endless turns about the vertical at ``rate_dps`` (positive = clockwise seen from above).

    Roll and pitch stay fixed; yaw starts at ``yaw0``.
    """

    def __init__(
        self, rate_dps: float, roll: float = 0.0, pitch: float = 0.0, yaw0: float = 0.0
    ) -> None:
        if not math.isfinite(rate_dps):
            raise ValueError("rate_dps must be finite")
        self.rate_dps = float(rate_dps)
        self.roll, self.pitch, self.yaw0 = float(roll), float(pitch), float(yaw0)
        self.duration = math.inf

    def attitude(self, t: float) -> FloatArray:
        """Yaw grows linearly with ``t``."""
        yaw = self.yaw0 + math.radians(self.rate_dps) * max(0.0, t)
        return euler_to_dcm(self.roll, self.pitch, yaw)


class Tumble(MotionBase):
    """A calibration tumble: smooth, endless, at human rates, sweeping the whole sphere.

    The unit is turned so that a reference direction (default: the Earth field at
    the simulator's default site; pass the field you simulate) runs over the body
    sphere on a spiral, pole to pole and back, at a constant ``rate_dps``. The turn
    axis is always perpendicular to that direction plus a slow spin about it
    (``spin_frac`` of the rate), so the gravity direction in body axes moves too.
    One pole-to-pole sweep is about 2100 deg of turning: 47 s at the default
    45 deg/s, after which the field direction has visited every section of a
    geodesic grid as fine as ArduPilot's 80 MAG_CAL_PROGRESS sections.

    Construction (ZYZ angles of the body sphere, all closed-form or tabulated once):
    ``R.T = Rz(a) @ Ry(b) @ Rz(c) @ Q`` with ``Q`` taking the reference direction to
    body z, so the direction reads ``Rz(a) @ Ry(b) @ z``; ``b = 90 - 80 cos(a/m)`` deg
    puts ``spacing_deg`` between turns at the equator, and ``c' = -a' cos b + spin``
    cancels the twist about the direction. Time is tabulated per cycle from the
    speed condition; ``seed`` picks the start azimuth, the twist about the
    reference, the turning sense and a small change of ``m`` so that later cycles
    fall between the earlier rings.
    """

    _AMPLITUDE = math.radians(80.0)  # b sweeps 10 .. 170 deg: the poles fall inside the first ring

    def __init__(
        self,
        seed: int = 0,
        rate_dps: float = 45.0,
        *,
        reference_ned: npt.ArrayLike | None = None,
        spacing_deg: float = 24.0,
        spin_frac: float = 0.25,
    ) -> None:
        if not (math.isfinite(rate_dps) and rate_dps > 0.0):
            raise ValueError("rate_dps must be finite and > 0")
        if not (math.isfinite(spacing_deg) and 1.0 <= spacing_deg <= 90.0):
            raise ValueError("spacing_deg must lie in [1, 90]")
        if reference_ned is None:
            reference_ned = default_field_ned_G()
        r = np.asarray(reference_ned, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(r)) and np.linalg.norm(r) > 0.0):
            raise ValueError("reference_ned must be a finite non-zero vector")
        rng = np.random.default_rng(seed)
        self.seed = seed
        self.rate_dps = float(rate_dps)
        v = math.radians(self.rate_dps)
        # m: a-radians per radian of the cos() argument; equator spacing = 2 pi A / m
        m = 2.0 * math.pi * self._AMPLITUDE / math.radians(spacing_deg)
        self._m = m * rng.uniform(0.97, 1.03)
        self._sense = float(rng.choice([-1.0, 1.0]))
        self._a_off = rng.uniform(0.0, 2.0 * math.pi)
        spin = spin_frac * v * float(rng.choice([-1.0, 1.0]))
        # Q: reference -> body z, then a random twist about it
        z = np.array([0.0, 0.0, 1.0])
        rn = r / np.linalg.norm(r)
        ax = np.cross(rn, z)
        ang = math.atan2(float(np.linalg.norm(ax)), float(rn @ z))
        Q = axis_angle_to_dcm(ax if np.linalg.norm(ax) > 1e-12 else [1.0, 0.0, 0.0], ang)
        self._Q = axis_angle_to_dcm(z, rng.uniform(0.0, 2.0 * math.pi)) @ Q
        # tabulate one full cycle (pole -> pole -> pole) of a against time
        a = np.linspace(0.0, 2.0 * math.pi * self._m, 40001)
        b = self._b_of(a)
        db_da = self._AMPLITUDE / self._m * np.sin(a / self._m)
        dt_da = np.sqrt(np.sin(b) ** 2 + db_da**2) / v
        t = np.concatenate(([0.0], np.cumsum(0.5 * (dt_da[1:] + dt_da[:-1]) * np.diff(a))))
        dc_da = -np.cos(b) + spin * dt_da
        c = np.concatenate(([0.0], np.cumsum(0.5 * (dc_da[1:] + dc_da[:-1]) * np.diff(a))))
        self._a_tab, self._t_tab, self._c_tab = a, t, c
        self.cycle_s = float(t[-1])
        self.sweep_s = float(np.interp(math.pi * self._m, a, t))  #: one pole-to-pole sweep
        self.duration = math.inf

    def _b_of(self, a: FloatArray) -> FloatArray:
        return 0.5 * math.pi - self._AMPLITUDE * np.cos(a / self._m)

    def attitude(self, t: float) -> FloatArray:
        """Attitude at ``t`` (periodic tables, advanced by whole cycles)."""
        return self.attitudes(np.array([t]))[0]

    def attitudes(self, times: npt.ArrayLike) -> FloatArray:
        """``attitude`` at each time, as an (N, 3, 3) stack: the one formula, vectorised
        (a recording of thousands of frames is simulated in one pass, not frame by frame)."""
        t = np.maximum(np.asarray(times, dtype=np.float64).reshape(-1), 0.0)
        k, tau = np.divmod(t, self.cycle_s)
        a = np.interp(tau, self._t_tab, self._a_tab)
        c = np.interp(tau, self._t_tab, self._c_tab) + k * float(self._c_tab[-1])
        b = self._b_of(a)
        az = self._sense * (a + k * float(self._a_tab[-1])) + self._a_off
        Rt = _rz(az) @ _ry(b) @ _rz(self._sense * c) @ self._Q
        return np.swapaxes(Rt, 1, 2)


def _rz(a: FloatArray) -> FloatArray:
    """Rotations about z by the angles ``a`` (N,): an (N, 3, 3) stack."""
    c, s = np.cos(a), np.sin(a)
    # (entries written into zeros: a frame at a time, stacking nine arrays cost more)
    out = np.zeros((len(a), 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1], out[:, 2, 2] = c, -s, s, c, 1.0
    return out


def _ry(a: FloatArray) -> FloatArray:
    """Rotations about y by the angles ``a`` (N,): an (N, 3, 3) stack."""
    c, s = np.cos(a), np.sin(a)
    out = np.zeros((len(a), 3, 3))
    out[:, 0, 0], out[:, 0, 2], out[:, 1, 1], out[:, 2, 0], out[:, 2, 2] = c, s, 1.0, -s, c
    return out


class AttitudeList(MotionBase):
    """Hold each ``(roll, pitch, yaw)`` for ``dwell_s``, then turn to the next in ``transition_s``.

    Transitions follow the shortest arc with a smooth-step speed profile.
    ``segment_at(t)`` says which attitude is held (``None`` while moving).
    """

    def __init__(
        self, attitudes: Iterable[Euler], dwell_s: float, transition_s: float = 2.0
    ) -> None:
        self.eulers: list[Euler] = [(float(r), float(p), float(y)) for r, p, y in attitudes]
        if not self.eulers:
            raise ValueError("AttitudeList needs at least one attitude")
        self.dwell_s = _check_time("dwell_s", dwell_s)
        self.transition_s = _check_time("transition_s", transition_s)
        self._Rs = [euler_to_dcm(*e) for e in self.eulers]
        # Each transition's whole turn, the shortest arc from one attitude to the next (a
        # rotation vector in the first one's axes), made once: not again every frame.
        self._turns = [dcm_to_rotvec(a.T @ b) for a, b in itertools.pairwise(self._Rs)]
        n = len(self._Rs)
        self.duration = n * self.dwell_s + (n - 1) * self.transition_s

    def _locate(self, t: float) -> tuple[int, float]:
        """(index, fraction of the transition after it; 0 while dwelling)."""
        period = self.dwell_s + self.transition_s
        t = min(max(0.0, t), self.duration)
        if period <= 0.0:
            return len(self._Rs) - 1, 0.0
        i = min(int(t // period), len(self._Rs) - 1)
        into = t - i * period
        if into <= self.dwell_s or i == len(self._Rs) - 1:
            return i, 0.0
        return i, (into - self.dwell_s) / self.transition_s

    def segment_at(self, t: float) -> int | None:
        """Index of the attitude held at ``t``, or ``None`` during a transition."""
        i, s = self._locate(t)
        return i if s == 0.0 else None

    def attitude(self, t: float) -> FloatArray:
        """Held attitude, or the interpolated one during a transition."""
        i, s = self._locate(t)
        if s == 0.0:
            return self._Rs[i]
        # a fraction of the turn along the shortest arc (slerp)
        return self._Rs[i] @ rotvec_to_dcm(_smoothstep(s) * self._turns[i])


class OnboardCalRotation(MotionBase):
    """The datasheet's MAGCAL routine: a level turn, tip onto the side, a turn on the side.

    Phase 1 (``turn_s``): level, yaw ``yaw0`` -> ``yaw0`` + 360 deg. Phase 2 (``tip_s``):
    roll 0 -> 90 deg (right side down), so body z becomes horizontal. Phase 3
    (``turn_s``): one full turn about the vertical while on the side (|gz| ~ 0).
    ``phase_at(t)`` names the phase: "level", "tip", "side".
    """

    def __init__(self, turn_s: float, tip_s: float = 3.0, yaw0: float = 0.0) -> None:
        self.turn_s = _check_time("turn_s", turn_s, positive=True)
        self.tip_s = _check_time("tip_s", tip_s)
        self.yaw0 = float(yaw0)
        self.duration = 2.0 * self.turn_s + self.tip_s

    def phase_at(self, t: float) -> str:
        """ "level", "tip" or "side"."""
        if t < self.turn_s:
            return "level"
        return "tip" if t < self.turn_s + self.tip_s else "side"

    def attitude(self, t: float) -> FloatArray:
        """Level turn, tip, side turn; held at the end."""
        t = min(max(0.0, t), self.duration)
        full = 2.0 * math.pi
        if t < self.turn_s:
            return euler_to_dcm(0.0, 0.0, self.yaw0 + full * t / self.turn_s)
        t2 = t - self.turn_s
        if t2 < self.tip_s:
            roll = 0.5 * math.pi * _smoothstep(t2 / self.tip_s)
            return euler_to_dcm(roll, 0.0, self.yaw0)
        t3 = t2 - self.tip_s
        # yaw about NED down with the unit on its side: Rz(yaw) @ Rx(90 deg)
        return euler_to_dcm(0.5 * math.pi, 0.0, self.yaw0 + full * t3 / self.turn_s)


class HandOnboardCalRotation(MotionBase):
    """The datasheet's MAGCAL routine as a person does it by hand.

    Like :class:`OnboardCalRotation` -- a level turn, a tip 90 deg onto the
    right side, a turn on the side -- but at a hand's pace and with a hand's
    imperfections: each turn (``level_turn_deg`` / ``side_turn_deg``, one full
    turn by default) takes ``turn_s`` seconds, starting and ending at rest
    with the rate peaking at twice the mean mid-turn; the unit is held
    ``pause_s`` before and after the tip (``tip_s``); and throughout it
    wobbles ``wobble_deg`` in roll and pitch at a fraction of a hertz (the
    hand never holds it exactly level, nor exactly on its side). Seeded: the
    wobble's frequencies and phases come from ``seed``. ``phase_at(t)`` names
    the phase: "level", "pause", "tip", "side", "held".
    """

    def __init__(
        self,
        turn_s: float = 15.0,
        tip_s: float = 3.0,
        yaw0: float = 0.0,
        *,
        level_turn_deg: float = 360.0,
        side_turn_deg: float = 360.0,
        pause_s: float = 1.0,
        wobble_deg: float = 3.0,
        seed: int = 0,
    ) -> None:
        self.turn_s = _check_time("turn_s", turn_s, positive=True)
        self.tip_s = _check_time("tip_s", tip_s, positive=True)
        self.pause_s = _check_time("pause_s", pause_s)
        self.yaw0 = float(yaw0)
        self.level_turn = math.radians(float(level_turn_deg))
        self.side_turn = math.radians(float(side_turn_deg))
        self.wobble = math.radians(_check_time("wobble_deg", wobble_deg))
        rng = np.random.default_rng([seed, 0x7A11])
        self._freq = rng.uniform(0.2, 0.7, size=2)  # Hz: a slow sway, not a tremor
        self._phase = rng.uniform(0.0, 2.0 * math.pi, size=2)
        # level turn, pause, tip, pause, side turn
        self._marks = np.cumsum([0.0, self.turn_s, self.pause_s, self.tip_s, self.pause_s])
        self.duration = float(self._marks[-1]) + self.turn_s

    def phase_at(self, t: float) -> str:
        """ "level", "pause", "tip", "side" or "held" (after the side turn)."""
        names = ("level", "pause", "tip", "pause", "side")
        if t >= self.duration:
            return "held"
        i = max(0, int(np.searchsorted(self._marks, t, side="right")) - 1)
        return names[i]

    @property
    def side_starts_at(self) -> float:
        """When the turn on the side begins (seconds into the script)."""
        return float(self._marks[-1])

    def side_turned_deg(self, t: float) -> float:
        """How far the turn on the side has gone at ``t`` (degrees)."""
        s = (t - self.side_starts_at) / self.turn_s
        return math.degrees(self.side_turn * self._ease(s))

    @staticmethod
    def _ease(s: float) -> float:
        """0 -> 1, at rest at both ends, fastest (twice the mean rate) half way."""
        s = min(1.0, max(0.0, s))
        return s - math.sin(2.0 * math.pi * s) / (2.0 * math.pi)

    def attitude(self, t: float) -> FloatArray:
        """The routine's attitude, tilted by the hand's wobble."""
        t = min(max(0.0, t), self.duration)
        m = self._marks
        w = self.wobble * np.sin(2.0 * math.pi * self._freq * t + self._phase)
        sway = euler_to_dcm(float(w[0]), float(w[1]), 0.0)
        if t < m[1]:
            base = euler_to_dcm(0.0, 0.0, self.yaw0 + self.level_turn * self._ease(t / self.turn_s))
        else:
            yaw = self.yaw0 + self.level_turn
            if t < m[2]:
                roll = 0.0
            elif t < m[3]:
                roll = 0.5 * math.pi * _smoothstep((t - m[2]) / self.tip_s)
            else:
                roll = 0.5 * math.pi
                yaw += self.side_turn * self._ease((t - m[4]) / self.turn_s)
            # yaw about NED down with the unit on its side: Rz(yaw) @ Rx(roll)
            base = euler_to_dcm(roll, 0.0, yaw)
        return sway @ base


#: ArduPilot's ACCELCAL_VEHICLE_POS order and the attitude of each face (roll, pitch, yaw).
SIX_FACES: tuple[tuple[str, Euler], ...] = (
    ("LEVEL", (0.0, 0.0, 0.0)),
    ("LEFT", (-0.5 * math.pi, 0.0, 0.0)),
    ("RIGHT", (0.5 * math.pi, 0.0, 0.0)),
    ("NOSEDOWN", (0.0, -0.5 * math.pi, 0.0)),
    ("NOSEUP", (0.0, 0.5 * math.pi, 0.0)),
    ("BACK", (math.pi, 0.0, 0.0)),
)


class SixFaces(AttitudeList):
    """The six faces for accelerometer calibration, in ArduPilot's ACCELCAL order.

    LEVEL, LEFT (left side down), RIGHT (right side down), NOSEDOWN, NOSEUP, BACK
    (upside down); ``face_at(t)`` gives the label, ``None`` while turning.
    """

    def __init__(self, dwell_s: float, transition_s: float = 3.0, yaw: float = 0.0) -> None:
        super().__init__([(r, p, yaw) for _, (r, p, _y) in SIX_FACES], dwell_s, transition_s)
        self.labels = tuple(name for name, _ in SIX_FACES)

    def face_at(self, t: float) -> str | None:
        """Label of the face the unit rests on at ``t``."""
        i = self.segment_at(t)
        return None if i is None else self.labels[i]


class Shaken(MotionBase):
    """Another script plus sinusoidal linear acceleration (vibration, a hand shaking).

    ``amplitude_g`` per NED axis, at ``freq_hz``; attitude is the base script's.
    """

    def __init__(self, base: Motion, amplitude_g: npt.ArrayLike, freq_hz: float = 3.0) -> None:
        self.base = base
        self.amplitude_g = np.broadcast_to(np.asarray(amplitude_g, dtype=np.float64), (3,)).copy()
        self.freq_hz = float(freq_hz)
        self.duration = base.duration
        # different phases per axis so the shake is not along one fixed line
        self._phase = np.array([0.0, 2.1, 4.2])

    def attitude(self, t: float) -> FloatArray:
        """The base script's attitude."""
        return self.base.attitude(t)

    def linear_acc_ned_g(self, t: float) -> FloatArray:
        """Sinusoidal acceleration on top of the base script's."""
        w = 2.0 * math.pi * self.freq_hz
        return linear_acc_of(self.base, t) + self.amplitude_g * np.sin(w * t + self._phase)


#: A hand's unintended linear acceleration: smooth, 0.4-2.5 Hz (below it the hand
#: would travel metres; above it is tremor, far weaker than this).
HAND_SHAKE_BAND_HZ: tuple[float, float] = (0.4, 2.5)


class HandShake(MotionBase):
    """Another script plus the linear acceleration of a hand that holds the unit.

    Per NED axis a sum of ``tones`` sinusoids, one at a log-uniform random
    frequency in each of ``tones`` equal (logarithmic) slices of ``band_hz``,
    with random phases and equal amplitudes ``rms_g * sqrt(2 / tones)``: the
    RMS per axis is ``rms_g`` and a peak never exceeds ``sqrt(2 tones)`` RMS
    (2.45x with the default three tones; a person's shake of 0.05 g RMS peaks
    at about 0.12 g). Smooth (no steps, its velocity and position stay
    bounded) and a pure function of ``t`` for a given ``seed``. The attitude
    is the base script's: a hand moves the unit, it does not turn it.
    """

    def __init__(
        self,
        base: Motion,
        rms_g: float,
        seed: int = 0,
        *,
        band_hz: tuple[float, float] = HAND_SHAKE_BAND_HZ,
        tones: int = 3,
    ) -> None:
        lo, hi = float(band_hz[0]), float(band_hz[1])
        if not (math.isfinite(rms_g) and rms_g >= 0.0):
            raise ValueError(f"rms_g must be finite and >= 0, got {rms_g!r}")
        if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo < hi):
            raise ValueError(f"band_hz must be 0 < low < high, got {band_hz!r}")
        if tones < 1:
            raise ValueError(f"tones must be at least 1, got {tones}")
        self.base = base
        self.rms_g = float(rms_g)
        self.band_hz = (lo, hi)
        self.duration = base.duration
        rng = np.random.default_rng([seed, 0x5A4B])
        edges = np.exp(np.linspace(math.log(lo), math.log(hi), tones + 1))
        u = rng.uniform(0.0, 1.0, size=(3, tones))
        freq = np.exp(np.log(edges[:-1]) + u * (np.log(edges[1:]) - np.log(edges[:-1])))
        self._omega = 2.0 * math.pi * freq  #: (3, tones) rad/s
        self._phase = rng.uniform(0.0, 2.0 * math.pi, size=(3, tones))
        self._amp = self.rms_g * math.sqrt(2.0 / tones)

    @property
    def peak_bound_g(self) -> float:
        """No axis ever exceeds this (all tones in phase)."""
        return float(self._amp * self._omega.shape[1])

    def attitude(self, t: float) -> FloatArray:
        """The base script's attitude."""
        return self.base.attitude(t)

    def shake_g(self, times: npt.ArrayLike) -> FloatArray:
        """The shake alone at each time: (N, 3) g, NED (vectorised, for the benchmarks)."""
        ts = np.asarray(times, dtype=np.float64).reshape(-1)
        arg = ts[:, None, None] * self._omega[None] + self._phase[None]
        return np.asarray(self._amp * np.sin(arg).sum(axis=2), dtype=np.float64)

    def linear_acc_ned_g(self, t: float) -> FloatArray:
        """The shake on top of the base script's own linear acceleration."""
        return linear_acc_of(self.base, t) + self.shake_g([t])[0]

    def linear_accs_ned_g(self, times: npt.ArrayLike) -> FloatArray:
        """:meth:`linear_acc_ned_g` at each time, as an (N, 3) array (the same numbers)."""
        return linear_accs_of(self.base, times) + self.shake_g(times)


def with_shake(motion: Motion, shake_g: float, seed: int = 0) -> Motion:
    """``motion`` held by a hand shaking ``shake_g`` RMS per axis (unchanged for 0)."""
    return motion if shake_g == 0.0 else HandShake(motion, shake_g, seed)


class Sequence(MotionBase):
    """Scripts one after another; only the last may be endless.

    No transition is inserted: put an :class:`AttitudeList` between two scripts
    that do not meet, or the unit jumps.
    """

    def __init__(self, parts: SequenceABC[Motion]) -> None:
        self.parts: tuple[Motion, ...] = tuple(parts)
        if not self.parts:
            raise ValueError("Sequence needs at least one motion")
        for p in self.parts[:-1]:
            if not math.isfinite(p.duration):
                raise ValueError("only the last part of a Sequence may be endless")
        # (a list of floats: found with bisect, as numpy's searchsorted would, without a
        # numpy call on every frame)
        self._starts: list[float] = np.cumsum(
            [0.0] + [p.duration for p in self.parts[:-1]]
        ).tolist()
        self.duration = self._starts[-1] + self.parts[-1].duration

    def _part(self, t: float) -> tuple[Motion, float]:
        i = bisect_right(self._starts, t) - 1
        i = max(0, i)
        return self.parts[i], t - self._starts[i]

    def attitude(self, t: float) -> FloatArray:
        """The attitude of the part running at ``t``."""
        p, tl = self._part(t)
        return p.attitude(tl)

    def linear_acc_ned_g(self, t: float) -> FloatArray:
        """The linear acceleration of the part running at ``t``."""
        p, tl = self._part(t)
        return linear_acc_of(p, tl)
