"""Method 6: accelerometer six-face calibration, face detection and one-shot level trim.

Face names are PX4's (``detect_orientation_str`` in PX4's calibration_routines,
which QGroundControl parses from ``"[cal] <side> orientation detected"``):
"down" = level (right side up), "up" = upside down, "front" = nose down,
"back" = nose up (tail down), "left" / "right" = lying on that side. PX4's
accelerometer reports specific force (level = (0, 0, -g)); this device reports
the gravity vector (level = (0, 0, +1 g)), so every expected vector here is
PX4's with the sign flipped.

The six-face fit solves the full affine model ``g_face = M @ (raw - o)`` by
least squares over the six face means: 12 unknowns from 18 equations, so it
recovers offsets, gains, cross-axis terms and the accelerometer's rotation
relative to the faces the unit sat on (the case / vehicle axes).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from enum import Enum

import numpy as np
import numpy.typing as npt

from bridge.calibration.fits.scalar import failed_result, gravity_spread_mg
from bridge.core.calibration import (
    AffineCalibration,
    Calibration,
    CalibrationReport,
    CalibrationResult,
)
from bridge.core.geometry import euler_to_dcm
from bridge.types import FloatArray

DEFAULT_STILL_TOL_G = 0.02  #: per-axis std dev for "still" (PX4: 0.25 m/s^2)
DEFAULT_MAX_ANGLE_DEG = 20.0  #: how far from the face's axis a window may point
DEFAULT_NORM_TOL_G = 0.5  #: raw |g| of an uncalibrated unit is 1 +- 0.5 g (zeros +-100 counts, gains +-15 %); still catches free fall
MIN_WINDOW = 5  #: samples needed to judge stillness
MAX_LEVEL_TRIM_DEG = 10.0  #: ArduPilot limits AHRS_TRIM to 10 deg: beyond, the vehicle is not level


class Face(Enum):
    """The six rest orientations; the value is PX4's side name."""

    LEVEL = "down"
    UPSIDE_DOWN = "up"
    NOSE_DOWN = "front"
    NOSE_UP = "back"
    LEFT_SIDE = "left"
    RIGHT_SIDE = "right"

    @property
    def px4_side(self) -> str:
        """The name PX4/QGC use in ``[cal] <side> orientation detected``."""
        return self.value

    @property
    def gravity_body(self) -> tuple[float, float, float]:
        """The gravity vector (datasheet sign) a perfect unit reads on this face, in g."""
        return _GRAVITY[self]

    @property
    def label(self) -> str:
        """Human wording for prompts ("nose down", "on its left side", ...)."""
        return _LABELS[self]


_GRAVITY: dict[Face, tuple[float, float, float]] = {
    Face.LEVEL: (0.0, 0.0, 1.0),
    Face.UPSIDE_DOWN: (0.0, 0.0, -1.0),
    Face.NOSE_DOWN: (1.0, 0.0, 0.0),
    Face.NOSE_UP: (-1.0, 0.0, 0.0),
    Face.LEFT_SIDE: (0.0, -1.0, 0.0),
    Face.RIGHT_SIDE: (0.0, 1.0, 0.0),
}
_LABELS: dict[Face, str] = {
    Face.LEVEL: "level",
    Face.UPSIDE_DOWN: "upside down",
    Face.NOSE_DOWN: "nose down",
    Face.NOSE_UP: "nose up",
    Face.LEFT_SIDE: "on its left side",
    Face.RIGHT_SIDE: "on its right side",
}


def face_from_px4_side(side: str) -> Face:
    """The :class:`Face` for a PX4 side name ("down", "up", "front", ...); ``ValueError`` if none."""
    try:
        return Face(side.strip().lower())
    except ValueError:
        raise ValueError(f"unknown PX4 side {side!r}") from None


def detect_face(
    acc_g_window: npt.ArrayLike,
    still_tol: float = DEFAULT_STILL_TOL_G,
    *,
    max_angle_deg: float = DEFAULT_MAX_ANGLE_DEG,
    norm_tol_g: float = DEFAULT_NORM_TOL_G,
) -> Face | None:
    """Which face the unit rests on, from a window of (N, 3) accelerometer samples in g.

    ``None`` unless the window is still (every axis' standard deviation under
    ``still_tol``), its mean is 1 g within ``norm_tol_g`` and points within
    ``max_angle_deg`` of one face's gravity direction. A window with non-finite
    samples or fewer than 5 rows is not still. Raises ``ValueError`` on a
    non-(N, 3) array.
    """
    w = np.asarray(acc_g_window, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != 3:
        raise ValueError(f"acc_g_window must be (N, 3), got {w.shape}")
    if w.shape[0] < MIN_WINDOW or not np.all(np.isfinite(w)):
        return None
    if np.any(np.std(w, axis=0) >= still_tol):
        return None
    mean = w.mean(axis=0)
    n = float(np.linalg.norm(mean))
    if abs(n - 1.0) > norm_tol_g:
        return None
    u = mean / n
    cos_lim = math.cos(math.radians(max_angle_deg))
    for face in Face:
        if float(np.dot(u, face.gravity_body)) >= cos_lim:
            return face
    return None


def fit_six_face(face_means: Mapping[Face, npt.ArrayLike]) -> CalibrationResult:
    """Accelerometer offsets, gains and misalignment (full 3x3) from the six face means.

    ``face_means`` maps each :class:`Face` to the mean nominal-g reading (3,) taken
    at rest on it. All six are needed, and each must point roughly along its
    face (within 45 deg) -- a mislabelled face is an error, not a fit. The
    magnetometer part of the result is the identity. Failures (missing faces,
    non-finite or mislabelled means) give status MAG_CAL_FAILED, identity parameters.
    """
    missing = [f.px4_side for f in Face if f not in face_means]
    if missing:
        return failed_result(
            "accel_six_face", f"missing faces: {', '.join(missing)}", n_samples=len(face_means)
        )
    faces = list(Face)
    raw = np.empty((6, 3))
    for i, f in enumerate(faces):
        v = np.asarray(face_means[f], dtype=np.float64)
        if v.shape != (3,):
            raise ValueError(f"face mean for {f.px4_side} must be a 3-vector, got shape {v.shape}")
        if not np.all(np.isfinite(v)):
            return failed_result("accel_six_face", f"{f.px4_side}: non-finite mean", n_samples=6)
        raw[i] = v
    target = np.array([f.gravity_body for f in faces])
    # Sanity: each raw mean must point towards its face, else the faces are mixed up.
    for i, f in enumerate(faces):
        n = float(np.linalg.norm(raw[i]))
        if n == 0.0 or float(raw[i] @ target[i]) / n < math.cos(math.radians(45.0)):
            return failed_result(
                "accel_six_face",
                f"{f.px4_side}: mean {raw[i].round(3).tolist()} does not point {f.label}",
                n_samples=6,
            )
    D = np.column_stack([raw, np.ones(6)])
    X, *_ = np.linalg.lstsq(D, target, rcond=None)
    M = X[:3].T
    c = X[3]
    if not np.all(np.isfinite(X)) or abs(float(np.linalg.det(M))) < 1e-6:
        return failed_result(
            "accel_six_face", "face means do not determine the matrix", n_samples=6
        )
    offset = -np.linalg.solve(M, c)
    cal = AffineCalibration.from_arrays(offset, M)
    after = cal.apply(raw)
    b_hp, b_rms = gravity_spread_mg(raw)
    a_hp, a_rms = gravity_spread_mg(after)
    resid = float(np.sqrt(np.mean(np.sum((after - target) ** 2, axis=1))))
    report = CalibrationReport(
        method="accel_six_face",
        n_samples=6,
        gravity_spread_before_mg=b_hp,
        gravity_spread_after_mg=a_hp,
        gravity_rms_before_mg=b_rms,
        gravity_rms_after_mg=a_rms,
        notes=(f"face vector residual RMS {resid * 1000.0:.2f} mg",),
    )
    return CalibrationResult(Calibration(accel=cal), report)


def level_trim(acc_g_mean: npt.ArrayLike, calibration: Calibration) -> Calibration:
    """Fold a one-shot level trim into both sensors so the current mean reads level.

    ``acc_g_mean`` is the mean nominal-g reading of the vehicle standing level.
    Its roll and pitch under ``calibration`` define the trim rotation
    ``T = euler(roll, pitch, 0)``; ``T @ matrix`` for *both* the accelerometer and
    the magnetometer keeps them in one frame, so heading follows the trimmed
    level. Raises ``ValueError`` on a non-finite or zero mean, or a tilt over
    10 deg (ArduPilot's AHRS_TRIM limit: the vehicle is not level).
    """
    v = np.asarray(acc_g_mean, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"acc_g_mean must be a finite 3-vector, got {v!r}")
    g = calibration.accel.apply(v)
    n = float(np.linalg.norm(g))
    if n < 0.5:
        raise ValueError(f"|g| = {n:.3f} g: not a gravity reading")
    pitch = -math.asin(max(-1.0, min(1.0, float(g[0]) / n)))
    roll = math.atan2(float(g[1]), float(g[2]))
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(g[2]) / n))))
    if tilt > MAX_LEVEL_TRIM_DEG:
        raise ValueError(
            f"tilt {tilt:.1f} deg exceeds the {MAX_LEVEL_TRIM_DEG:.0f} deg level-trim limit"
        )
    T = _trim_rotation(roll, pitch)
    return Calibration(mag=calibration.mag.then_rotate(T), accel=calibration.accel.then_rotate(T))


def _trim_rotation(roll: float, pitch: float) -> FloatArray:
    """The rotation that maps a reading at (roll, pitch) onto level: ``euler(roll, pitch, 0)``.

    A body at attitude R reads ``R.T @ e_down``; multiplying by R gives ``e_down``.
    """
    return euler_to_dcm(roll, pitch, 0.0)
