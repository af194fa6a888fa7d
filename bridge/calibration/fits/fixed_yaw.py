"""ArduPilot's ``mag_cal_fixed_yaw``: magnetometer offsets from one known yaw (pure).

* :func:`fixed_yaw_calibration` -- offsets from one known yaw and the WMM field,
  keeping the current matrix;
* :func:`attitude_from_gravity` -- roll and pitch from a still accelerometer reading.

Nothing here does I/O or keeps time; the fixed-yaw session
(:class:`~bridge.calibration.sessions.host.FixedYawSession`) calls them.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from bridge.core.calibration import AffineCalibration, Calibration
from bridge.core.geometry import euler_to_dcm


def attitude_from_gravity(g: npt.ArrayLike) -> tuple[float, float]:
    """(roll, pitch) in radians from a gravity vector (datasheet sign: level = +z)."""
    v = np.asarray(g, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(v))
    if not (math.isfinite(n) and n > 0.0):
        raise ValueError("no gravity vector")
    pitch = -math.asin(max(-1.0, min(1.0, float(v[0]) / n)))
    roll = math.atan2(float(v[1]), float(v[2]))
    return roll, pitch


def fixed_yaw_calibration(
    mag_G_mean: npt.ArrayLike,
    acc_g_mean: npt.ArrayLike,
    yaw_deg: float,
    field_ned_G: npt.ArrayLike,
    calibration: Calibration,
    mounting: npt.ArrayLike | None = None,
) -> Calibration:
    """New magnetometer offsets from one known yaw (ArduPilot's ``mag_cal_fixed_yaw``).

    ``mag_G_mean``/``acc_g_mean`` are raw nominal readings (averaged while
    still); ``yaw_deg`` the vehicle's yaw in the frame of ``field_ned_G`` (true
    north with a WMM vector, which carries the declination); ``mounting`` the
    sensor-to-vehicle matrix (COMPASS_ORIENT + trim). Roll and pitch come from
    the accelerometer under ``calibration``; the expected sensor-frame field
    then fixes the offset: ``offset = mean - matrix^-1 @ expected``. Unlike
    ArduPilot, which resets COMPASS_DIA/ODI to identity, the current matrix is
    kept (it holds soft iron and alignment a single yaw cannot re-learn).
    Raises ``ValueError`` on a non-finite input or a zero gravity reading.
    """
    m = np.asarray(mag_G_mean, dtype=np.float64).reshape(3)
    a = np.asarray(acc_g_mean, dtype=np.float64).reshape(3)
    b_ned = np.asarray(field_ned_G, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(m)) and np.all(np.isfinite(a)) and np.all(np.isfinite(b_ned))):
        raise ValueError("fixed-yaw inputs must be finite")
    if not math.isfinite(yaw_deg):
        raise ValueError(f"yaw must be finite, got {yaw_deg!r}")
    mnt = np.eye(3) if mounting is None else np.asarray(mounting, dtype=np.float64).reshape(3, 3)
    g_vehicle = mnt @ calibration.accel.apply(a)
    roll, pitch = attitude_from_gravity(g_vehicle)
    R = euler_to_dcm(roll, pitch, math.radians(yaw_deg))
    expected_sensor = mnt.T @ (R.T @ b_ned)
    M = calibration.mag.matrix_array
    offset = m - np.linalg.solve(M, expected_sensor)
    return Calibration(mag=AffineCalibration.from_arrays(offset, M), accel=calibration.accel)
