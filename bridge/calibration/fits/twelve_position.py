"""Method 2: the 12-parameter model from known attitudes, by linear least squares.

At attitude ``R_i`` a perfect sensor reads ``R_i.T @ B_ned``. The real one reads
``x_i``; the model ``R_i.T @ B_ned = M @ (x_i - o) = M @ x_i + c`` has 12
parameters -- 3 biases and a general 3x3 (3 scales, 6 cross terms: soft iron,
non-orthogonality *and* any rotation) -- and is linear in ``(M, c)``, so one
``lstsq`` on ``[x_i, 1]`` solves it; ``o = -M^-1 c``. The reference frame is the
body frame the attitudes are given in, so when the attitudes are true (a
turntable, a levelled jig) this also removes the magnetometer-to-accelerometer
misalignment, which no magnitude-only method can see.

``TWELVE_POSITIONS``: the unit is put on each of its six faces (the
accelerometer faces of method 6: level, upside down, nose down, nose up, left
side, right side) and on each face pointed north, then south. That gives every
axis the vertical field both ways and the horizontal field both ways, and it
also gives the accelerometer its six faces -- so the same 12 stops calibrate
both sensors (``acc_g``). The yaw of the two nose-vertical stops is the usual
ZYX value (the belly faces south at yaw 0).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import numpy.typing as npt

from bridge.calibration.fits.scalar import failed_result, field_report, gravity_spread_mg
from bridge.core.calibration import (
    AffineCalibration,
    Calibration,
    CalibrationResult,
)
from bridge.core.geometry import GRAVITY_NED, euler_to_dcm_batch
from bridge.types import FloatArray

_FACES_DEG = (  # (roll, pitch) of the six faces
    (0.0, 0.0),  # level
    (180.0, 0.0),  # upside down
    (0.0, -90.0),  # nose down
    (0.0, 90.0),  # nose up
    (-90.0, 0.0),  # on its left side
    (90.0, 0.0),  # on its right side
)

#: The 12 stops as (roll, pitch, yaw) in radians: six faces x headings north, south.
TWELVE_POSITIONS: list[tuple[float, float, float]] = [
    (math.radians(r), math.radians(p), math.radians(y)) for r, p in _FACES_DEG for y in (0.0, 180.0)
]

MAX_CONDITION = 1e6  #: design matrices worse than this cannot separate the 12 parameters


def twelve_position_attitudes() -> FloatArray:
    """The body->NED matrices (12, 3, 3) of :data:`TWELVE_POSITIONS`."""
    a = np.array(TWELVE_POSITIONS)
    return euler_to_dcm_batch(a[:, 0], a[:, 1], a[:, 2])


def _affine_lstsq(
    x: FloatArray, targets: FloatArray
) -> tuple[FloatArray, FloatArray, float] | None:
    """Solve ``targets ~ M @ x + c``; ``(M, offset, cond)`` or None if not determined."""
    D = np.column_stack([x, np.ones(x.shape[0])])
    # Scale columns so the condition number judges geometry, not units.
    scale = np.maximum(np.max(np.abs(D), axis=0), 1e-300)
    Ds = D / scale
    sv = np.linalg.svd(Ds, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    if not cond < MAX_CONDITION:
        return None
    X, *_ = np.linalg.lstsq(Ds, targets, rcond=None)
    X = X / scale[:, np.newaxis]
    M = X[:3].T
    c = X[3]
    if abs(float(np.linalg.det(M))) < 1e-9:
        return None
    return M, -np.linalg.solve(M, c), cond


def fit_twelve_position(
    mag_G: npt.ArrayLike,
    attitudes: npt.ArrayLike,
    field_ned_G: npt.ArrayLike,
    *,
    acc_g: npt.ArrayLike | None = None,
) -> CalibrationResult:
    """12-parameter calibration from samples at known attitudes.

    ``mag_G`` (N, 3) nominal gauss, ``attitudes`` (N, 3, 3) body->NED (any N >= 4
    stops that span 3-D; averaging several samples per stop first is fine),
    ``field_ned_G`` the local field (WMM). ``acc_g`` (N, 3), if given, gets the
    same treatment against gravity (needs stops whose gravity directions span 3-D,
    as :data:`TWELVE_POSITIONS` has); otherwise the accelerometer part is identity.
    Raises ``ValueError`` on mismatched shapes, non-rotation attitudes or a bad
    field; degenerate stops give status MAG_CAL_FAILED_ORIENTATION, identity parameters.
    """
    x = np.asarray(mag_G, dtype=np.float64)
    R = np.asarray(attitudes, dtype=np.float64)
    B = np.asarray(field_ned_G, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"mag_G must be (N, 3), got {x.shape}")
    if R.shape != (x.shape[0], 3, 3):
        raise ValueError(f"attitudes must be ({x.shape[0]}, 3, 3), got {R.shape}")
    if B.shape != (3,) or not np.all(np.isfinite(B)) or float(np.linalg.norm(B)) <= 0.0:
        raise ValueError(f"field_ned_G must be a finite non-zero 3-vector, got {B!r}")
    acc = None
    if acc_g is not None:
        acc = np.asarray(acc_g, dtype=np.float64)
        if acc.shape != x.shape:
            raise ValueError(f"acc_g must be {x.shape}, got {acc.shape}")
    finite = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(R), axis=(1, 2))
    if acc is not None:
        finite &= np.all(np.isfinite(acc), axis=1)
    dropped = int(x.shape[0] - int(finite.sum()))
    x, R = x[finite], R[finite]
    if acc is not None:
        acc = acc[finite]
    if x.shape[0] and not np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-6):
        raise ValueError("attitudes must be rotation matrices")
    if x.shape[0] < 4:
        return failed_result(
            "twelve_position",
            f"too few samples: {x.shape[0]} < 4",
            n_samples=x.shape[0],
            n_rejected=dropped,
        )
    Rt = np.swapaxes(R, 1, 2)
    target = Rt @ B
    sol = _affine_lstsq(x, target)
    if sol is None:
        res = failed_result(
            "twelve_position",
            "attitudes do not span 3-D: the 12 parameters are not determined",
            n_samples=x.shape[0],
            n_rejected=dropped,
        )
        return CalibrationResult(
            res.calibration, replace(res.report, status="MAG_CAL_FAILED_ORIENTATION")
        )
    M, offset, cond = sol
    mag_cal = AffineCalibration.from_arrays(offset, M)
    after = mag_cal.apply(x)
    radius = float(np.linalg.norm(B))
    vec_rms = float(np.sqrt(np.mean(np.sum((after - target) ** 2, axis=1))))
    notes = [f"vector residual RMS {vec_rms * 1000.0:.3f} mG; design condition {cond:.1f}"]

    acc_cal = AffineCalibration()
    g_stats = (math.nan, math.nan, math.nan, math.nan)
    if acc is not None:
        g_target = Rt @ GRAVITY_NED
        g_sol = _affine_lstsq(acc, g_target)
        if g_sol is None:
            notes.append("accelerometer not fitted: the stops' gravity directions do not span 3-D")
        else:
            acc_cal = AffineCalibration.from_arrays(g_sol[1], g_sol[0])
            g_after = acc_cal.apply(acc)
            g_stats = (*gravity_spread_mg(acc), *gravity_spread_mg(g_after))
            g_vec = float(np.sqrt(np.mean(np.sum((g_after - g_target) ** 2, axis=1))))
            notes.append(f"accelerometer vector residual RMS {g_vec * 1000.0:.2f} mg")
    report = field_report(
        "twelve_position",
        x,
        after,
        radius,
        n_samples=int(x.shape[0]),
        n_rejected=dropped,
        gravity_spread_before_mg=g_stats[0],
        gravity_rms_before_mg=g_stats[1],
        gravity_spread_after_mg=g_stats[2],
        gravity_rms_after_mg=g_stats[3],
        notes=tuple(notes),
    )
    return CalibrationResult(Calibration(mag=mag_cal, accel=acc_cal), report)
