"""Sensor physics of the simulated GMR compass: Earth field, per-unit errors, noise, ADC.

Measurement model (body axes x forward, y right, z down; ``R`` rotates body -> NED)::

    mag_G      = soft_iron @ mag_rotation @ (R.T @ B_ned) + hard_iron_G + noise
    mag_counts = clip(round(2458 + mag_adc_zero + 2560 * mag_G), 0, 4095)
    acc_g      = acc_matrix @ (R.T @ ([0, 0, 1] - a_ned)) + acc_offset_g + noise
    acc_counts = clip(round(2458 + acc_adc_zero + 491.5 * acc_g), 0, 4095)

* ``soft_iron`` = diag(per-axis gain) @ non-orthogonality @ symmetric soft iron. The
  unit's true gain differing from the nominal 2560 counts/G is the diagonal factor,
  so the ADC step above always uses the nominal figure.
* ``mag_rotation`` is a proper rotation: how the magnetometer chips sit relative to
  the accelerometer (= body) axes. Non-orthogonality is lower-triangular (x defines
  the frame, y lies in its xy plane), so it never duplicates that rotation.
* ``a_ned`` is an optional linear acceleration in g (NED). The accelerometer reports
  the datasheet's *gravity vector* (level at rest = (0, 0, +1 g)), which is minus the
  specific force: ``g - a``.
* Noise is white and Gaussian, per sample and channel, applied before quantisation.

A channel at 0 or 4095 counts is saturated (datasheet); ``Sample.saturated`` flags it.

The default simulator site is PX4 SITL's home at Zurich (47.397742 N, 8.545594 E,
488 m): a well-known mid-latitude site (|B| about 0.48 G, dip about 63 deg).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from bridge.core.calibration import AffineCalibration, Calibration
from bridge.core.geometry import GRAVITY_NED, axis_angle_to_dcm
from bridge.core.sensor import ACC_COUNTS_PER_G, ADC_MAX, MAG_COUNTS_PER_GAUSS, ZERO_COUNTS
from bridge.core.wmm import earth_field
from bridge.types import BoolArray, FloatArray, IntArray

#: (latitude_deg, longitude_deg, altitude_m): PX4 SITL's default home, Zurich.
DEFAULT_LOCATION: tuple[float, float, float] = (47.397742, 8.545594, 488.0)


def _frozen_array(v: npt.ArrayLike, shape: tuple[int, ...], name: str) -> FloatArray:
    """Copy into a read-only float array of ``shape``; a frozen dataclass must stay frozen."""
    a = np.array(v, dtype=np.float64)
    if a.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite")
    a.flags.writeable = False
    return a


def default_field_ned_G(
    location: tuple[float, float, float] = DEFAULT_LOCATION,
) -> FloatArray:
    """WMM field (N, E, D) in gauss at ``(lat_deg, lon_deg, alt_m)``, today."""
    lat, lon, alt = location
    return earth_field(lat, lon, alt).ned_G


def _random_unit(rng: np.random.Generator) -> FloatArray:
    v = rng.normal(size=3)
    n = float(np.linalg.norm(v))
    # a zero draw has probability zero; fall back to x rather than divide by zero
    return np.array([1.0, 0.0, 0.0]) if n == 0.0 else v / n


def _nonorthogonality(rng: np.random.Generator, max_deg: float) -> FloatArray:
    """Rows = unit sensing axes; x exact, y tilted in the xy plane, z tilted freely."""
    a, b, c = np.radians(rng.uniform(-max_deg, max_deg, size=3))
    rows = np.array([[1.0, 0.0, 0.0], [math.tan(a), 1.0, 0.0], [math.tan(b), math.tan(c), 1.0]])
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


@dataclass(frozen=True, eq=False)
class UnitErrors:
    """Everything that makes one physical unit differ from the nominal datasheet figures.

    Arrays are stored read-only. See the module docstring for the measurement model.
    """

    hard_iron_G: FloatArray = field(default_factory=lambda: np.zeros(3))
    soft_iron: FloatArray = field(default_factory=lambda: np.eye(3))
    mag_rotation: FloatArray = field(default_factory=lambda: np.eye(3))
    mag_adc_zero: FloatArray = field(default_factory=lambda: np.zeros(3))
    acc_offset_g: FloatArray = field(default_factory=lambda: np.zeros(3))
    acc_matrix: FloatArray = field(default_factory=lambda: np.eye(3))
    acc_adc_zero: FloatArray = field(default_factory=lambda: np.zeros(3))
    mag_noise_G: float = 0.0
    acc_noise_g: float = 0.0

    def __post_init__(self) -> None:
        for name, shape in (
            ("hard_iron_G", (3,)),
            ("soft_iron", (3, 3)),
            ("mag_rotation", (3, 3)),
            ("mag_adc_zero", (3,)),
            ("acc_offset_g", (3,)),
            ("acc_matrix", (3, 3)),
            ("acc_adc_zero", (3,)),
        ):
            object.__setattr__(self, name, _frozen_array(getattr(self, name), shape, name))
        rot = self.mag_rotation
        if not (np.allclose(rot @ rot.T, np.eye(3), atol=1e-9) and np.linalg.det(rot) > 0):
            raise ValueError("mag_rotation must be a proper rotation matrix")
        for name in ("soft_iron", "acc_matrix"):
            if abs(float(np.linalg.det(getattr(self, name)))) < 1e-6:
                raise ValueError(f"{name} is singular")
        for name in ("mag_noise_G", "acc_noise_g"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
            object.__setattr__(self, name, v)

    @classmethod
    def ideal(cls) -> UnitErrors:
        """A perfect, noise-free unit: exactly the nominal transfer functions."""
        return cls()

    @classmethod
    def draw(
        cls,
        rng: np.random.Generator,
        *,
        hard_iron_frac: tuple[float, float] = (0.1, 0.3),
        field_G: float | None = None,
        gain_tol: float = 0.10,
        nonorth_deg: float = 3.0,
        misalign_deg: float = 2.0,
        soft_iron: float = 0.03,
        adc_zero_counts: float = 100.0,
        acc_offset_g: float = 0.02,
        acc_gain_tol: float = 0.05,
        acc_nonorth_deg: float = 1.0,
        mag_noise_G: float = 0.0005,
        acc_noise_g: float = 0.001,
    ) -> UnitErrors:
        """Draw a realistic unit.

        ``hard_iron_frac``: hard-iron magnitude as a fraction of ``field_G`` (default: |B|
        at :data:`DEFAULT_LOCATION`), uniform in the range, random direction.
        ``gain_tol``/``acc_gain_tol``: per-axis gains uniform in 1 +- tol (the datasheet
        allows 15 %). ``nonorth_deg``/``acc_nonorth_deg``: each axis-pair angle error
        uniform in +-. ``misalign_deg``: magnetometer-to-accelerometer rotation angle,
        uniform in [0, misalign_deg] about a random axis. ``soft_iron``: symmetric
        distortion, each element of (S - I) uniform in +-. ``adc_zero_counts`` and
        ``acc_offset_g``: per channel, uniform in +-.
        """
        if field_G is None:
            field_G = float(np.linalg.norm(default_field_ned_G()))
        lo, hi = hard_iron_frac
        hard = _random_unit(rng) * rng.uniform(lo, hi) * field_G
        gains = rng.uniform(1.0 - gain_tol, 1.0 + gain_tol, size=3)
        e = rng.uniform(-soft_iron, soft_iron, size=(3, 3))
        sym = np.eye(3) + (e + e.T) / 2.0
        soft = np.diag(gains) @ _nonorthogonality(rng, nonorth_deg) @ sym
        rot = axis_angle_to_dcm(_random_unit(rng), math.radians(rng.uniform(0.0, misalign_deg)))
        acc_gains = rng.uniform(1.0 - acc_gain_tol, 1.0 + acc_gain_tol, size=3)
        acc_m = np.diag(acc_gains) @ _nonorthogonality(rng, acc_nonorth_deg)
        return cls(
            hard_iron_G=hard,
            soft_iron=soft,
            mag_rotation=rot,
            mag_adc_zero=rng.uniform(-adc_zero_counts, adc_zero_counts, size=3),
            acc_offset_g=rng.uniform(-acc_offset_g, acc_offset_g, size=3),
            acc_matrix=acc_m,
            acc_adc_zero=rng.uniform(-adc_zero_counts, adc_zero_counts, size=3),
            mag_noise_G=mag_noise_G,
            acc_noise_g=acc_noise_g,
        )

    def true_calibration(self) -> Calibration:
        """The exact inverse of the model after the nominal transfer (``bridge.core.sensor``).

        ``matrix @ (nominal - offset)`` gives back ``R.T @ B_ned`` and ``R.T @ g``
        (noise-free, unquantised); this is what a perfect calibration would find.
        """
        mag = AffineCalibration.from_arrays(
            self.hard_iron_G + self.mag_adc_zero / MAG_COUNTS_PER_GAUSS,
            np.linalg.inv(self.soft_iron @ self.mag_rotation),
        )
        acc = AffineCalibration.from_arrays(
            self.acc_offset_g + self.acc_adc_zero / ACC_COUNTS_PER_G,
            np.linalg.inv(self.acc_matrix),
        )
        return Calibration(mag=mag, accel=acc)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (for benchmark reports)."""
        out: dict[str, Any] = {}
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            out[name] = v.tolist() if isinstance(v, np.ndarray) else v
        return out


@dataclass(frozen=True, slots=True)
class Sample:
    """N simulated frames: ADC counts plus the truth they came from.

    ``mag_body_G`` / ``acc_body_g`` are the ideal body-axis vectors ``R.T @ B_ned`` and
    ``R.T @ (g - a)`` before any unit error: what a perfect calibration should recover.
    """

    mag_counts: IntArray  #: (N, 3)
    acc_counts: IntArray  #: (N, 3)
    saturated: BoolArray  #: (N,) any of the six channels at 0 or 4095
    mag_body_G: FloatArray  #: (N, 3)
    acc_body_g: FloatArray  #: (N, 3)


@dataclass(frozen=True, slots=True)
class Headroom:
    """Worst-case distance (counts) of each channel to the ADC rails over all attitudes.

    Negative or zero means the channel reaches a rail at some attitude.
    """

    mag_low: FloatArray  #: (3,) min count - 0
    mag_high: FloatArray  #: (3,) 4095 - max count
    acc_low: FloatArray
    acc_high: FloatArray

    @property
    def min_counts(self) -> float:
        """The smallest margin of all twelve."""
        return float(
            min(self.mag_low.min(), self.mag_high.min(), self.acc_low.min(), self.acc_high.min())
        )


#: counts per unit of the six channels side by side: three magnetometer (per gauss), three
#: accelerometer (per g)
_COUNTS_PER_UNIT = np.array([MAG_COUNTS_PER_GAUSS] * 3 + [ACC_COUNTS_PER_G] * 3)


class SensorModel:
    """One unit (``errors``) in a fixed Earth field ``field_ned_G`` (gauss, NED)."""

    def __init__(self, errors: UnitErrors, field_ned_G: npt.ArrayLike) -> None:
        self.errors = errors
        self.field_ned_G = _frozen_array(field_ned_G, (3,), "field_ned_G")
        # cached products: sample() is on the firmware's per-frame path
        self._mag_m = errors.soft_iron @ errors.mag_rotation
        self._mag_zero = ZERO_COUNTS + errors.mag_adc_zero
        self._acc_zero = ZERO_COUNTS + errors.acc_adc_zero
        # the six channels side by side (magnetometer, then accelerometer): sample() turns
        # them into counts in one pass of each operation rather than two
        self._zero6 = np.concatenate((self._mag_zero, self._acc_zero))
        # ... and as floats, with the field and the two matrices' transposes, for the
        # one-frame path (:meth:`_sample_one`)
        self._field3: tuple[float, float, float] = tuple(self.field_ned_G.tolist())
        self._zero6_f: list[float] = self._zero6.tolist()
        self._mag_mT = self._mag_m.T
        self._acc_mT = errors.acc_matrix.T
        self._offsets6: list[float] = [*errors.hard_iron_G.tolist(), *errors.acc_offset_g.tolist()]

    @classmethod
    def at_location(
        cls,
        errors: UnitErrors,
        location: tuple[float, float, float] = DEFAULT_LOCATION,
    ) -> SensorModel:
        """Model at ``(lat_deg, lon_deg, alt_m)`` with the WMM field of today."""
        return cls(errors, default_field_ned_G(location))

    def with_hard_iron_change(self, delta_G: npt.ArrayLike) -> SensorModel:
        """The same unit with ``delta_G`` more hard iron (sensor axes, gauss): a bracket
        bolted on, a battery moved. Its :meth:`UnitErrors.true_calibration` follows."""
        e = self.errors
        hard = e.hard_iron_G + _frozen_array(delta_G, (3,), "delta_G")
        return SensorModel(replace(e, hard_iron_G=hard), self.field_ned_G)

    def sample(
        self,
        R: npt.ArrayLike,
        rng: np.random.Generator,
        linear_acc_ned_g: npt.ArrayLike | None = None,
        extra_field_ned_G: npt.ArrayLike | None = None,
    ) -> Sample:
        """Sample at one attitude (3, 3) or a stack (N, 3, 3); always returns N rows.

        ``linear_acc_ned_g``: (3,) or (N, 3) acceleration of the body in g, NED.
        ``extra_field_ned_G``: (3,) or (N, 3) field added to the Earth's (a magnet going
        by, :func:`magnet_pass`); the ideal ``mag_body_G`` stays the Earth's alone.
        """
        Rs = np.asarray(R, dtype=np.float64)
        if Rs.shape == (3, 3):
            if extra_field_ned_G is None:
                lin1 = (
                    None
                    if linear_acc_ned_g is None
                    else np.asarray(linear_acc_ned_g, dtype=np.float64)
                )
                if lin1 is None or lin1.shape == (3,):
                    return self._sample_one(Rs, rng, lin1)
            Rs = Rs[np.newaxis]
        if Rs.ndim != 3 or Rs.shape[1:] != (3, 3):
            raise ValueError(f"R must be (3, 3) or (N, 3, 3), got {Rs.shape}")
        n = Rs.shape[0]
        Rt = Rs.swapaxes(1, 2)  # (the method: np.swapaxes is a wrapper around it)
        mag_body = Rt @ self.field_ned_G
        # One frame (the simulated firmware's per-frame path): the same differences
        # without broadcasting, which costs more than the arithmetic at this size.
        lin = None if linear_acc_ned_g is None else np.asarray(linear_acc_ned_g, dtype=np.float64)
        if n == 1 and (lin is None or lin.shape == (3,)):
            g_ned = (GRAVITY_NED if lin is None else GRAVITY_NED - lin).reshape(1, 3)
        else:
            g_ned = np.broadcast_to(GRAVITY_NED, (n, 3))
            if lin is not None:
                g_ned = g_ned - np.broadcast_to(lin, (n, 3))
        acc_body = np.einsum("nij,nj->ni", Rt, g_ned)
        e = self.errors
        seen = mag_body
        if extra_field_ned_G is not None:
            extra = np.broadcast_to(np.asarray(extra_field_ned_G, dtype=np.float64), (n, 3))
            seen = mag_body + np.einsum("nij,nj->ni", Rt, extra)
        mag_G = seen @ self._mag_m.T + e.hard_iron_G
        acc_g = acc_body @ e.acc_matrix.T + e.acc_offset_g
        if e.mag_noise_G > 0.0:
            mag_G = mag_G + rng.normal(0.0, e.mag_noise_G, size=(n, 3))
        if e.acc_noise_g > 0.0:
            acc_g = acc_g + rng.normal(0.0, e.acc_noise_g, size=(n, 3))
        # The six channels as one (N, 6) array: each step below is then one numpy call, not
        # two -- on the firmware's one-frame path the calls' dispatch, not the arithmetic, is
        # the cost. Element by element the same operations (zero + gain * value, rounded,
        # clipped as its two comparisons), so the same counts. any() as the array's method.
        counts = np.minimum(
            np.maximum(
                np.rint(self._zero6 + _COUNTS_PER_UNIT * np.concatenate((mag_G, acc_g), axis=1)),
                0,
            ),
            ADC_MAX,
        ).astype(np.int64)
        sat = ((counts == 0) | (counts == ADC_MAX)).any(axis=1)
        return Sample(counts[:, :3], counts[:, 3:], sat, mag_body, acc_body)

    def _sample_one(
        self, R: FloatArray, rng: np.random.Generator, lin: FloatArray | None
    ) -> Sample:
        """:meth:`sample` of one frame (the simulated firmware's per-frame path), its
        numbers in plain floats where they are the same: numpy's calls on 3-vectors cost
        far more than their arithmetic (this path takes about a third of the stack's time).

        The same numbers, bit for bit (every field of 16 500 frames of eleven units, and
        four simulated compasses' streams and truths, hashed the same before and after):
        ``R.T @ v`` as numpy sums it for a stack of C-ordered matrices (each row's three
        products added in order to a 0.0, no fused multiply-add; for any other layout,
        such as a Tumble's transposed view, numpy takes another path with other
        roundings, so there its own calls remain); the two unit matrices through numpy's
        own product (its BLAS kernel fuses and orders its products its own way: written
        out they differ in the last bit); the noise drawn by the same calls in the same
        order; rint as Python's round (both halves to even), the clip as its two
        comparisons; numpy's own rint and clip where a value is not finite.
        """
        gx, gy, gz = (0.0, 0.0, 1.0)
        if lin is not None:
            lx, ly, lz = lin.tolist()
            gx, gy, gz = gx - lx, gy - ly, gz - lz
        if R.flags.c_contiguous:
            (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
            fx, fy, fz = self._field3
            # (Each sum from 0.0, as numpy's loops start theirs: -0.0 terms sum to +0.0.)
            mag_body = np.array(
                [[0.0 + r00 * fx + r10 * fy + r20 * fz, 0.0 + r01 * fx + r11 * fy + r21 * fz,
                  0.0 + r02 * fx + r12 * fy + r22 * fz]]
            )  # fmt: skip
            acc_body = np.array(
                [[0.0 + r00 * gx + r10 * gy + r20 * gz, 0.0 + r01 * gx + r11 * gy + r21 * gz,
                  0.0 + r02 * gx + r12 * gy + r22 * gz]]
            )  # fmt: skip
        else:  # another layout: numpy's products, as the stack's
            Rt = R[np.newaxis].swapaxes(1, 2)
            mag_body = Rt @ self.field_ned_G
            acc_body = np.einsum("nij,nj->ni", Rt, np.array([[gx, gy, gz]]))
        e = self.errors
        hx, hy, hz, ox, oy, oz = self._offsets6
        ((mx, my, mz),) = (mag_body @ self._mag_mT).tolist()
        ((ax, ay, az),) = (acc_body @ self._acc_mT).tolist()
        mx, my, mz = mx + hx, my + hy, mz + hz
        ax, ay, az = ax + ox, ay + oy, az + oz
        if e.mag_noise_G > 0.0:
            ((nx, ny, nz),) = rng.normal(0.0, e.mag_noise_G, size=(1, 3)).tolist()
            mx, my, mz = mx + nx, my + ny, mz + nz
        if e.acc_noise_g > 0.0:
            ((nx, ny, nz),) = rng.normal(0.0, e.acc_noise_g, size=(1, 3)).tolist()
            ax, ay, az = ax + nx, ay + ny, az + nz
        z0, z1, z2, z3, z4, z5 = self._zero6_f
        try:
            raw = [
                round(z0 + MAG_COUNTS_PER_GAUSS * mx),
                round(z1 + MAG_COUNTS_PER_GAUSS * my),
                round(z2 + MAG_COUNTS_PER_GAUSS * mz),
                round(z3 + ACC_COUNTS_PER_G * ax),
                round(z4 + ACC_COUNTS_PER_G * ay),
                round(z5 + ACC_COUNTS_PER_G * az),
            ]
        except (ValueError, OverflowError):  # not finite: numpy's rint and clip as they are
            six = np.array([[mx, my, mz, ax, ay, az]])
            c6 = np.minimum(
                np.maximum(np.rint(self._zero6 + _COUNTS_PER_UNIT * six), 0), ADC_MAX
            ).astype(np.int64)
            sat = ((c6 == 0) | (c6 == ADC_MAX)).any(axis=1)
        else:
            clipped = [0 if c < 0 else (ADC_MAX if c > ADC_MAX else c) for c in raw]
            c6 = np.array([clipped], dtype=np.int64)
            sat = np.array([0 in clipped or ADC_MAX in clipped])
        return Sample(c6[:, :3], c6[:, 3:], sat, mag_body, acc_body)

    def headroom(self, *, accel_margin_g: float = 0.0, noise_sigmas: float = 0.0) -> Headroom:
        """Noise-free worst-case margins to the rails over *all* attitudes.

        Channel i reads ``zero_i + gain * (row_i . v + offset_i)`` with |v| fixed, so
        its extremes are ``offset_i +- |row_i| |v|``. ``accel_margin_g`` adds linear
        acceleration to |g|; ``noise_sigmas`` widens by that many noise sigmas.
        """
        e = self.errors
        b = float(np.linalg.norm(self.field_ned_G))
        mag_reach = np.linalg.norm(self._mag_m, axis=1) * b + noise_sigmas * e.mag_noise_G
        acc_reach = np.linalg.norm(e.acc_matrix, axis=1) * (1.0 + accel_margin_g)
        acc_reach = acc_reach + noise_sigmas * e.acc_noise_g
        mag_c = self._mag_zero + MAG_COUNTS_PER_GAUSS * e.hard_iron_G
        acc_c = self._acc_zero + ACC_COUNTS_PER_G * e.acc_offset_g
        # rint() maps x >= 4094.5 to the rail, so the usable span ends half a count early
        return Headroom(
            mag_low=mag_c - MAG_COUNTS_PER_GAUSS * mag_reach - 0.5,
            mag_high=(ADC_MAX - 0.5) - (mag_c + MAG_COUNTS_PER_GAUSS * mag_reach),
            acc_low=acc_c - ACC_COUNTS_PER_G * acc_reach - 0.5,
            acc_high=(ADC_MAX - 0.5) - (acc_c + ACC_COUNTS_PER_G * acc_reach),
        )

    def will_clip(self, *, accel_margin_g: float = 0.0, noise_sigmas: float = 0.0) -> bool:
        """True if some attitude drives a channel to 0 or 4095 (see :meth:`headroom`)."""
        return (
            self.headroom(accel_margin_g=accel_margin_g, noise_sigmas=noise_sigmas).min_counts
            <= 0.0
        )


def magnet_pass(
    times: npt.ArrayLike,
    at_s: float,
    peak_G: float,
    direction_ned: npt.ArrayLike = (1.0, 0.0, 0.0),
    *,
    closest_m: float = 1.0,
    speed_mps: float = 1.0,
) -> FloatArray:
    """The field of a magnet going by: (N, 3) gauss, NED, at ``times`` (seconds).

    A dipole passing at ``closest_m`` with ``speed_mps``, nearest at ``at_s``: its
    strength falls as the cube of the distance, ``peak_G * (d0 / d)^3``, along a fixed
    direction (a simplification: a real dipole's field also turns as it passes).
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    u = np.asarray(direction_ned, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(u))
    if not (n > 0.0 and math.isfinite(n)):
        raise ValueError("direction_ned must be a finite non-zero vector")
    d = np.hypot(closest_m, speed_mps * (t - at_s))
    return np.asarray(peak_G * (closest_m / d)[:, None] ** 3 * (u / n), dtype=np.float64)
