"""The per-frame attitude path: raw counts -> calibrated vectors -> roll/pitch/heading/quaternion.

Pipeline for one ``$PGMRA`` frame (all pure, no I/O)::

    counts --nominal transfer (core.sensor)--> gauss / g
           --stored calibration (matrix @ (raw - offset))--> accelerometer axes
           --mounting rotation (core.mounting)--> vehicle body axes (x fwd, y right, z down)
           --> roll, pitch from gravity; tilt-compensated magnetic heading
           --> + declination = true heading; quaternion body->NED

The formulas are the datasheet's (the on-board ones), with the datasheet's
gravity-vector sign (level reads +1 g on z)::

    pitch = -asin(gx/|g|)            roll = atan2(gy, gz)
    X = Hx cos(pitch) + Hy sin(pitch) sin(roll) + Hz sin(pitch) cos(roll)
    Y = Hy cos(roll) - Hz sin(roll)
    heading = atan2(-Y, X), folded into [0, 360), clockwise from magnetic north

Under acceleration the accelerometer's gravity is not gravity: a *tilt policy*
(:class:`TiltPolicy`, set with :meth:`AttitudeEngine.set_tilt_policy`; the
application's :class:`~bridge.app.tilt.TiltSources`, the maths in
:mod:`bridge.core.tilt`) may then give the down to use instead -- the
autopilot's, or one held from the quiet frames and matched to the field -- and
the solution says which (``tilt_source``) and what heading error that tilt leaves
(``heading_sigma_deg``).

Near +-90 deg pitch roll is undefined (gravity lies along x); the outputs stay
finite (roll falls to whatever the tiny y/z components give, heading stays
consistent with it) and the solution is flagged ``degraded``.

:meth:`AttitudeEngine.solve_counts` is the daemon's per-frame path: the whole chain
is folded into two 3x3 matrices and two count offsets, evaluated with plain
floats and ``math`` (numpy on 3-vectors costs more than the arithmetic).
Configuration changes swap one immutable state object, so a reader thread can
keep calling ``solve_counts`` while another thread updates the position.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from bridge.core import sensor
from bridge.core.calibration import Calibration
from bridge.core.geometry import (
    euler_to_quaternion,
    wrap_degrees_360,
    wrap_radians_pi,
)
from bridge.core.mounting import Mounting
from bridge.core.quality import QualityLimits, QualityMonitor
from bridge.core.tilt import TiltEstimate, TiltSource
from bridge.core.wmm import EarthField, earth_field
from bridge.types import FloatArray, HeadingReference, Vec3

Quat = tuple[float, float, float, float]

_DEG = 180.0 / math.pi


class TiltPolicy(Protocol):
    """Gives a frame the down to compensate it with (see the module docstring)."""

    def tilt(self, mag: Vec3, accel: Vec3, t: float, *, field_ok: bool) -> TiltEstimate:
        """The down (vehicle axes) for a frame with calibrated ``mag`` and ``accel``
        (vehicle axes) that arrived at ``t``; ``field_ok``: the field is not disturbed."""
        ...


@dataclass(frozen=True, slots=True)
class FieldReference:
    """What the Earth's field should look like here: declination, total field, dip.

    Any part may be ``None`` (unknown): without a declination no true heading is
    produced; without total/dip no disturbance check is made on that quantity.
    ``source`` says where it came from ("wmm", "calibration", "config", ...).
    Without a position, a calibration's own figures serve for the quality check:
    ``FieldReference(total_G=report.radius_G, dip_deg=<fitted dip>, source="calibration")``.
    """

    declination_deg: float | None = None
    total_G: float | None = None
    dip_deg: float | None = None
    source: str = "config"

    def __post_init__(self) -> None:
        for name in ("declination_deg", "total_G", "dip_deg"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"{name} must be finite or None, got {v!r}")
        if self.total_G is not None and self.total_G <= 0.0:
            raise ValueError(f"total_G must be positive, got {self.total_G}")
        if self.dip_deg is not None and not -90.0 <= self.dip_deg <= 90.0:
            raise ValueError(f"dip_deg must be in [-90, 90], got {self.dip_deg}")

    @classmethod
    def from_earth_field(cls, field: EarthField) -> FieldReference:
        """From a WMM result (declination positive east, dip positive down)."""
        return cls(field.declination_deg, field.total_G, field.inclination_deg, "wmm")


def field_reference_at(
    latitude_deg: float,
    longitude_deg: float,
    altitude_m: float = 0.0,
    when: _dt.date | _dt.datetime | float | None = None,
) -> FieldReference:
    """WMM declination, total field and dip at a position (``ValueError`` on a bad position)."""
    return FieldReference.from_earth_field(
        earth_field(latitude_deg, longitude_deg, altitude_m, when)
    )


# Not frozen, on purpose: one is built for every frame, and a frozen dataclass's
# __init__ (object.__setattr__ per field) measured 2-3x the cost of plain slot stores when
# run cold at 100 Hz. Treat it as read-only: the same instance goes to every output thread.
@dataclass(slots=True)
class AttitudeSolution:
    """One frame's attitude, body (x fwd, y right, z down) relative to NED (read-only by contract).

    ``roll``/``pitch``/``yaw`` are radians (MAVLink ATTITUDE); ``yaw`` is the
    *published* heading in (-pi, pi], whose north ``heading_reference`` names
    ("magnetic" or "true"). ``heading_magnetic_deg`` is always there;
    ``heading_true_deg`` and ``declination_deg`` are ``None`` without a
    declination. ``quaternion`` is (w, x, y, z) body->NED with w >= 0 and uses
    the published yaw (:func:`~bridge.core.geometry.euler_to_quaternion` of
    ``roll``, ``pitch``, ``yaw``, made on first use). ``mag_G``/``accel_g`` are the calibrated vectors in
    vehicle axes; ``dip_deg`` is the measured inclination (positive down).

    ``tilt_source`` says where roll and pitch (and so the heading's tilt
    compensation) came from: ``"accelerometer"``, ``"autopilot"`` or
    ``"magnetometer"`` (:data:`bridge.core.tilt.TILT_SOURCES`);
    ``heading_sigma_deg`` is the heading error (1 sigma) that tilt's
    uncertainty leaves, None without a tilt policy. ``accelerating`` is the
    accelerometer's magnitude off 1 g (the quality flag; a turn's horizontal
    acceleration hardly changes it -- the tilt source says more).
    """

    roll: float
    pitch: float
    yaw: float
    heading_magnetic_deg: float
    heading_true_deg: float | None
    declination_deg: float | None
    heading_reference: HeadingReference
    mag_G: Vec3
    accel_g: Vec3
    field_strength_G: float
    dip_deg: float
    degraded: bool
    disturbed: bool
    accelerating: bool
    tilt_source: TiltSource = "accelerometer"
    heading_sigma_deg: float | None = None
    #: The engine configuration that solved it (:attr:`AttitudeEngine.generation`): a heading
    #: step is in the solutions of the generation that made it and later ones only.
    generation: int = 0
    #: The quaternion once made (see :attr:`quaternion`).
    _quaternion: Quat | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def quaternion(self) -> Quat:
        """(w, x, y, z) body->NED, w >= 0, of ``roll``, ``pitch`` and ``yaw``.

        Made on first use, not with the solution: a solution is made for every frame
        and the quaternion goes out at the rate of ATTITUDE_QUATERNION and Zenoh's
        ``attitude`` (one frame in ten at 100 Hz). The same function of the same three
        floats, so the same bits as before; two threads asking at once make the same
        tuple twice, and either is kept.
        """
        q = self._quaternion
        if q is None:
            q = self._quaternion = euler_to_quaternion(self.roll, self.pitch, self.yaw)
        return q

    @property
    def heading_deg(self) -> float:
        """The published heading in degrees, [0, 360)."""
        if self.heading_reference == "true" and self.heading_true_deg is not None:
            return self.heading_true_deg
        return self.heading_magnetic_deg

    @property
    def accel_norm_g(self) -> float:
        """|accel| in g (1.0 at rest)."""
        x, y, z = self.accel_g
        return math.sqrt(x * x + y * y + z * z)


@dataclass(frozen=True, slots=True)
class _State:
    """Everything ``solve_counts`` needs, precomputed and immutable (swapped atomically)."""

    mo: Vec3  # magnetometer count offsets (ADC zero + calibration offset, in counts)
    mm: tuple[float, ...]  # 9 entries: mounting @ cal.matrix / counts-per-gauss, row-major
    ao: Vec3
    am: tuple[float, ...]
    declination_deg: float | None
    total_G: float | None
    dip_deg: float | None
    publish_true: bool
    sin_degraded: float  # |sin(pitch)| above which the solution is degraded
    generation: int  # one more with every configuration built (AttitudeEngine.generation)


def _sensor_chain(
    offset: Vec3, matrix: FloatArray, mounting: FloatArray, zero: float, per_unit: float
) -> tuple[Vec3, tuple[float, ...]]:
    """Fold nominal transfer + calibration + mounting into ``M @ (counts - o)``."""
    m = (mounting @ matrix) / per_unit
    o = (zero + per_unit * offset[0], zero + per_unit * offset[1], zero + per_unit * offset[2])
    return o, tuple(float(v) for v in m.reshape(9))


class AttitudeEngine:
    """Calibrated, tilt-compensated attitude for a stream of raw GMR frames.

    ``reference`` (declination / expected field) may be ``None`` and set later
    with :meth:`update_reference` or :meth:`update_position`. With
    ``heading_reference="true"`` but no declination known yet the magnetic
    heading is published and *labelled* magnetic in the solution.
    """

    def __init__(
        self,
        calibration: Calibration | None = None,
        mounting: Mounting | None = None,
        reference: FieldReference | None = None,
        heading_reference: HeadingReference = "magnetic",
        limits: QualityLimits | None = None,
    ) -> None:
        if heading_reference not in ("magnetic", "true"):
            raise ValueError(
                f"heading_reference must be 'magnetic' or 'true', got {heading_reference!r}"
            )
        self._calibration = calibration if calibration is not None else Calibration()
        self._mounting = mounting if mounting is not None else Mounting()
        self._reference = reference
        self._heading_reference: HeadingReference = heading_reference
        self._limits = limits if limits is not None else QualityLimits()
        self._quality = QualityMonitor(self._limits)
        self._tilt: TiltPolicy | None = None
        self._generation = 0
        self._state = self._build()

    # -- configuration -------------------------------------------------------------

    def _build(self) -> _State:
        mount = self._mounting.matrix()
        cal = self._calibration
        mo, mm = _sensor_chain(
            cal.mag.offset,
            cal.mag.matrix_array,
            mount,
            sensor.ZERO_COUNTS,
            sensor.MAG_COUNTS_PER_GAUSS,
        )
        ao, am = _sensor_chain(
            cal.accel.offset,
            cal.accel.matrix_array,
            mount,
            sensor.ZERO_COUNTS,
            sensor.ACC_COUNTS_PER_G,
        )
        ref = self._reference
        declination_deg = ref.declination_deg if ref else None
        publish_true = self._heading_reference == "true"
        sin_degraded = math.sin(math.radians(self._limits.degraded_pitch_deg))
        self._generation += 1
        return _State(
            mo=mo,
            mm=mm,
            ao=ao,
            am=am,
            declination_deg=declination_deg,
            total_G=ref.total_G if ref else None,
            dip_deg=ref.dip_deg if ref else None,
            publish_true=publish_true,
            sin_degraded=sin_degraded,
            generation=self._generation,
        )

    @property
    def generation(self) -> int:
        """The configuration in use: one more with every change (calibration, mounting,
        reference, limits, heading reference). Each solution carries the generation that
        solved it, so what reads the solutions can tell the first one a change is in."""
        return self._state.generation

    @property
    def calibration(self) -> Calibration:
        """The calibration in use."""
        return self._calibration

    @property
    def mounting(self) -> Mounting:
        """The mounting in use."""
        return self._mounting

    @property
    def reference(self) -> FieldReference | None:
        """The field reference in use (``None`` = unknown)."""
        return self._reference

    @property
    def heading_reference(self) -> HeadingReference:
        """The configured published heading ("magnetic" or "true")."""
        return self._heading_reference

    def update_calibration(self, calibration: Calibration) -> None:
        """Switch to a new calibration (e.g. after a fit); clears the quality flags."""
        self._calibration = calibration
        self._quality.reset()
        self._state = self._build()

    def update_mounting(self, mounting: Mounting) -> None:
        """Switch to a new mounting (COMPASS_ORIENT / trim change)."""
        self._mounting = mounting
        self._state = self._build()

    @property
    def limits(self) -> QualityLimits:
        """The quality limits in use."""
        return self._limits

    def update_limits(self, limits: QualityLimits) -> None:
        """Switch to new quality limits (e.g. MAVLink BRG_* parameters); the flags restart clear."""
        self._limits = limits
        # A fresh monitor: a swap is one reference store, safe against the pipeline (reader thread).
        self._quality = QualityMonitor(limits)
        self._state = self._build()

    @property
    def tilt_policy(self) -> TiltPolicy | None:
        """Where frames given a time get their down from (None: their accelerometer)."""
        return self._tilt

    def set_tilt_policy(self, policy: TiltPolicy | None) -> None:
        """Use ``policy`` for the down of every frame solved with a time (one store)."""
        self._tilt = policy

    def update_reference(self, reference: FieldReference | None) -> None:
        """Set the declination / expected field (``None`` = unknown)."""
        self._reference = reference
        self._state = self._build()

    def update_position(
        self,
        latitude_deg: float,
        longitude_deg: float,
        altitude_m: float = 0.0,
        when: _dt.date | _dt.datetime | float | None = None,
    ) -> FieldReference:
        """Take declination and expected field from the WMM at a new position.

        Raises ``ValueError`` on a bad position and keeps the previous reference.
        """
        ref = field_reference_at(latitude_deg, longitude_deg, altitude_m, when)
        self.update_reference(ref)
        return ref

    def set_heading_reference(self, heading_reference: HeadingReference) -> None:
        """Publish magnetic or true heading from now on."""
        if heading_reference not in ("magnetic", "true"):
            raise ValueError(
                f"heading_reference must be 'magnetic' or 'true', got {heading_reference!r}"
            )
        self._heading_reference = heading_reference
        self._state = self._build()

    # -- the fast path -------------------------------------------------------------

    def solve_counts(
        self,
        mx: float,
        my: float,
        mz: float,
        ax: float,
        ay: float,
        az: float,
        t: float | None = None,
    ) -> AttitudeSolution:
        """One frame of raw ADC counts (as ``$PGMRA`` carries them) to an attitude.

        ``t`` is the frame's arrival time (monotonic seconds): with it, and a tilt
        policy set, the policy gives the down; without, the accelerometer does.
        Raises ``ValueError`` on non-finite input (the quality state is left untouched).
        """
        s = self._state  # one read: a concurrent update cannot mix two configurations
        # Each sensor's chain M @ (counts - o) (_sensor_chain: the nominal transfer, the
        # calibration's AffineCalibration.apply and the mounting folded into one map), written
        # out per sensor rather than through a helper: a call and a tuple each, every frame.
        # (The tuples unpacked at once rather than indexed entry by entry, for the same reason.)
        o0, o1, o2 = s.mo
        dx, dy, dz = mx - o0, my - o1, mz - o2
        m0, m1, m2, m3, m4, m5, m6, m7, m8 = s.mm
        hx = m0 * dx + m1 * dy + m2 * dz
        hy = m3 * dx + m4 * dy + m5 * dz
        hz = m6 * dx + m7 * dy + m8 * dz
        o0, o1, o2 = s.ao
        dx, dy, dz = ax - o0, ay - o1, az - o2
        m0, m1, m2, m3, m4, m5, m6, m7, m8 = s.am
        gx = m0 * dx + m1 * dy + m2 * dz
        gy = m3 * dx + m4 * dy + m5 * dz
        gz = m6 * dx + m7 * dy + m8 * dz
        if not math.isfinite(hx + hy + hz + gx + gy + gz):
            # The codec only passes 0..4095 integers; anything else is a caller bug.
            raise ValueError(f"non-finite frame: {(mx, my, mz, ax, ay, az)!r}")
        policy = self._tilt
        if policy is None or t is None:
            return self._finish(s, hx, hy, hz, gx, gy, gz)
        est = policy.tilt((hx, hy, hz), (gx, gy, gz), t, field_ok=not self._quality.disturbed)
        return self._finish(s, hx, hy, hz, gx, gy, gz, est)

    def solve_vectors(self, mag_G: npt.ArrayLike, accel_g: npt.ArrayLike) -> AttitudeSolution:
        """Same as :meth:`solve_counts` from nominal-transfer vectors (gauss, g)."""
        mg = np.asarray(mag_G, dtype=np.float64).reshape(3)
        ag = np.asarray(accel_g, dtype=np.float64).reshape(3)
        mc = sensor.gauss_to_mag_counts(mg)
        ac = sensor.g_to_acc_counts(ag)
        return self.solve_counts(
            float(mc[0]), float(mc[1]), float(mc[2]), float(ac[0]), float(ac[1]), float(ac[2])
        )

    def _finish(
        self,
        s: _State,
        hx: float,
        hy: float,
        hz: float,
        gx: float,
        gy: float,
        gz: float,
        est: TiltEstimate | None = None,
    ) -> AttitudeSolution:
        an = math.sqrt(gx * gx + gy * gy + gz * gz)  # the accelerometer's |g|
        if est is not None:
            accel = est.down  # the tilt policy's down replaces the accelerometer's
            gx, gy, gz = accel
            gn = math.sqrt(gx * gx + gy * gy + gz * gz)
        else:
            accel = (gx, gy, gz)
            gn = an  # the same down: its |g| is the one just taken
        bn = math.sqrt(hx * hx + hy * hy + hz * hz)
        degraded = False
        if gn > 1e-6:
            sp = -gx / gn
            if sp > 1.0:
                sp = 1.0
            elif sp < -1.0:
                sp = -1.0
            pitch = math.asin(sp)
            ryz = math.sqrt(gy * gy + gz * gz)
            if ryz > 0.0:
                roll = math.atan2(gy, gz)
                sr, cr = gy / ryz, gz / ryz
            else:
                roll, sr, cr = 0.0, 0.0, 1.0
            cp = ryz / gn
            if bn > 0.0:
                # sin(dip), clamped to [-1, 1] (min() and max() as comparisons: every frame)
                sd = (hx * gx + hy * gy + hz * gz) / (gn * bn)
                sd = sd if sd < 1.0 else 1.0
                dip = math.asin(sd if sd > -1.0 else -1.0) * _DEG
            else:
                dip = 0.0
            if abs(sp) > s.sin_degraded or an < 0.2:
                degraded = True
        else:
            # No gravity at all (free fall, dead accelerometer): level is a guess.
            pitch = roll = 0.0
            sp, cp, sr, cr = 0.0, 1.0, 0.0, 1.0
            dip = 0.0
            degraded = True
        # the datasheet's X, Y: the field de-rotated into the local horizontal plane
        xh = hx * cp + hy * sp * sr + hz * sp * cr
        yh = hy * cr - hz * sr
        horizontal_min = 0.02 * bn
        if bn == 0.0 or (xh * xh + yh * yh) < horizontal_min * horizontal_min:
            degraded = True  # field (nearly) along the vertical: heading undefined
        heading_mag = wrap_degrees_360(math.atan2(-yh, xh) * _DEG)
        decl = s.declination_deg
        heading_true = wrap_degrees_360(heading_mag + decl) if decl is not None else None
        if s.publish_true and heading_true is not None:
            published, label = heading_true, "true"
        else:
            published, label = heading_mag, "magnetic"
        yaw = wrap_radians_pi(math.radians(published))
        if est is None:
            disturbed, accelerating = self._quality.update(bn, dip, an, s.total_G, s.dip_deg)
            source: TiltSource = "accelerometer"
            heading_sigma: float | None = None
        else:
            source, heading_sigma = est.source, est.heading_sigma_deg
            # The dip says something about the field only against a down it was not
            # matched to: the accelerometer's while quiet, or the autopilot's.
            disturbed, accelerating = self._quality.update(
                bn,
                dip,
                an,
                s.total_G,
                s.dip_deg,
                down_trusted=source != "magnetometer"
                and not (source == "accelerometer" and est.manoeuvre),
            )
        return AttitudeSolution(
            roll,
            pitch,
            yaw,
            heading_mag,
            heading_true,
            decl,
            label,  # type: ignore[arg-type]
            (hx, hy, hz),
            accel,
            bn,
            dip,
            degraded,
            disturbed,
            accelerating,
            source,
            heading_sigma,
            s.generation,
        )


# -- vectorised forms (benchmarks, calibration reports) -------------------------------


def tilt_compensated_heading(
    mag: npt.ArrayLike, acc: npt.ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Datasheet formulas on (N, 3) arrays: ``(roll, pitch, heading_deg)``.

    ``mag`` and ``acc`` are calibrated vectors in body axes (gravity-vector sign:
    level = (0, 0, +1)); roll and pitch in radians, heading in [0, 360) degrees
    clockwise from the field's north. Zero-length accelerometer rows give a level
    attitude rather than NaN.
    """
    m = np.atleast_2d(np.asarray(mag, dtype=np.float64))
    g = np.atleast_2d(np.asarray(acc, dtype=np.float64))
    if m.shape != g.shape or m.shape[-1] != 3:
        raise ValueError(f"mag and acc must both be (N, 3), got {m.shape} and {g.shape}")
    gn = np.linalg.norm(g, axis=1)
    safe = np.where(gn > 1e-12, gn, 1.0)
    pitch = np.where(gn > 1e-12, -np.arcsin(np.clip(g[:, 0] / safe, -1.0, 1.0)), 0.0)
    roll = np.arctan2(g[:, 1], np.where(gn > 1e-12, g[:, 2], 1.0))
    sp, cp, sr, cr = np.sin(pitch), np.cos(pitch), np.sin(roll), np.cos(roll)
    X = m[:, 0] * cp + m[:, 1] * sp * sr + m[:, 2] * sp * cr
    Y = m[:, 1] * cr - m[:, 2] * sr
    heading = np.degrees(np.arctan2(-Y, X)) % 360.0
    heading = np.where(heading >= 360.0, 0.0, heading)
    return roll, pitch, heading


def attitude_matrix_from_vectors(mag: npt.ArrayLike, acc: npt.ArrayLike) -> FloatArray:
    """Body->NED matrices (N, 3, 3) (or one (3, 3)) from calibrated mag + gravity vectors.

    North is the field's horizontal direction (magnetic north for a raw field).
    Built directly from the vectors (down = g/|g|, east = down x B), so it has no
    Euler singularity; rows that are degenerate (B parallel to g, zero vectors)
    raise ``ValueError``.
    """
    m = np.asarray(mag, dtype=np.float64)
    g = np.asarray(acc, dtype=np.float64)
    single = m.ndim == 1
    m2, g2 = np.atleast_2d(m), np.atleast_2d(g)
    if m2.shape != g2.shape or m2.shape[-1] != 3:
        raise ValueError(f"mag and acc must both be (N, 3), got {m2.shape} and {g2.shape}")
    gn = np.linalg.norm(g2, axis=1, keepdims=True)
    d = g2 / np.where(gn > 0, gn, 1.0)
    e = np.cross(d, m2)
    en = np.linalg.norm(e, axis=1, keepdims=True)
    bad = (gn[:, 0] <= 1e-12) | (en[:, 0] <= 1e-9 * np.maximum(np.linalg.norm(m2, axis=1), 1e-300))
    if np.any(bad):
        raise ValueError(f"{int(bad.sum())} rows have no gravity or a vertical field")
    e = e / en
    n = np.cross(e, d)
    # Rows of R are the NED axes expressed in body coordinates.
    R = np.stack([n, e, d], axis=1)
    return R[0] if single else R
