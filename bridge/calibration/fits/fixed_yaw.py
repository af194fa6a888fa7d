"""Pure helpers behind the calibration controller: reports, device parameters, fixed yaw.

Nothing here does I/O or keeps time; the sessions hand these to the
controller's worker thread as fits to run, or call them directly.

* :func:`orientation_confidence` -- ArduPilot's ``calculate_orientation`` figure
  of merit: how much better the fitted orientation explains the samples than
  the runner-up among the ArduPilot rotations;
* :func:`device_params_for` -- what of a host calibration the GMR flash can hold
  (offsets and per-axis gains, ``H = K * (m - off)`` in counts);
* :func:`fixed_yaw_calibration` -- ArduPilot's ``mag_cal_fixed_yaw``: offsets
  from one known yaw and the WMM field, keeping the current matrix.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bridge.calibration.fits.sanity import (
    MagCalStatus,
)
from bridge.calibration.model import (
    AffineCalibration,
    Calibration,
)
from bridge.core import sensor
from bridge.core.geometry import euler_to_dcm
from bridge.core.mounting import Rotation, rotation_matrix
from bridge.protocol.gmr import OFFSET_RANGE, PAR_SET_GAIN_RANGE, ParamsFrame
from bridge.types import FloatArray

SUCCESS = MagCalStatus.MAG_CAL_SUCCESS.name
RESIDUALS_HIGH = MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH.name

#: Rotations a wrongly set COMPASS_ORIENT can produce (ArduPilot's table, custom ones
#: excluded); every one is at least 45 deg from the identity except the identity itself.
_CANDIDATES: tuple[FloatArray, ...] = tuple(
    m
    for m in (
        rotation_matrix(r) for r in Rotation if not r.is_custom and r is not Rotation.ROTATION_NONE
    )
    if math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(m)) - 1.0) / 2.0)))) >= 44.0
)


def _unit_rows(v: FloatArray) -> FloatArray:
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return np.asarray(v / np.where(n > 0.0, n, 1.0), dtype=np.float64)


def orientation_confidence(mag_corrected: npt.ArrayLike, gravity: npt.ArrayLike) -> float:
    """Runner-up variance over best variance of the gravity-field angle (ArduPilot's confidence).

    With the right orientation the angle between gravity and the field is the
    same in every sample (90 deg + dip); each candidate rotation of
    COMPASS_ORIENT's table makes it vary. ``mag_corrected`` and ``gravity`` are
    calibrated (N, 3) vectors of the same frames. Returns the variance of the
    best *other* candidate divided by that of the fitted orientation: 1 means
    "cannot tell", ArduPilot accepts an orientation from about 2 on. NaN with
    fewer than 10 samples.
    """
    m = _unit_rows(np.asarray(mag_corrected, dtype=np.float64).reshape(-1, 3))
    g = _unit_rows(np.asarray(gravity, dtype=np.float64).reshape(-1, 3))
    if m.shape[0] < 10 or m.shape != g.shape:
        return math.nan
    best = float(np.var(np.sum(g * m, axis=1)))
    others = min(float(np.var(np.sum(g * (m @ R.T), axis=1))) for R in _CANDIDATES)
    # A floor keeps a noise-free (simulated) unit finite: 1e-12 is far below any real spread.
    return others / max(best, 1e-12)


@dataclass(frozen=True, slots=True)
class DeviceMagParams:
    """The magnetometer half of the GMR flash page: Xoff..Zoff (counts) and Kx..Kz."""

    xoff: float
    yoff: float
    zoff: float
    kx: float
    ky: float
    kz: float

    def with_level_reference(self, current: ParamsFrame) -> ParamsFrame:
        """The nine PAR,SET values: these six plus the device's own Gxoff/Gyoff/Gzoff."""
        return ParamsFrame(
            self.xoff,
            self.yoff,
            self.zoff,
            self.kx,
            self.ky,
            self.kz,
            current.gxoff,
            current.gyoff,
            current.gzoff,
        )

    def to_dict(self) -> dict[str, float]:
        """JSON-ready form."""
        return {
            "xoff": self.xoff,
            "yoff": self.yoff,
            "zoff": self.zoff,
            "kx": self.kx,
            "ky": self.ky,
            "kz": self.kz,
        }


def device_params_for(mag: AffineCalibration) -> DeviceMagParams:
    """What the device's model ``H = K * (m - off)`` can hold of a host magnetometer calibration.

    Offsets: ``2458 + 2560 * offset`` counts (the nominal transfer inverted).
    Gains: the diagonal of the symmetric soft-iron part relative to x (the
    device's heading is scale-free, and MAGCAL,END itself sets Kx = 1); the
    rotation and the off-diagonal terms have no place in the device's model.
    Values are rounded to the flash's grid (0.1 count, 0.0001). Raises
    ``ValueError`` when an offset leaves 0-4095 counts or a gain leaves the
    0.1-10 that PAR,SET accepts.
    """
    view = mag.ardupilot_view()
    d = view.diag
    if not all(math.isfinite(v) and v > 0.0 for v in d):
        raise ValueError(f"calibration diagonal {d} cannot be expressed as device gains")
    offs = [round(sensor.ZERO_COUNTS + sensor.MAG_COUNTS_PER_GAUSS * o, 1) for o in mag.offset]
    gains = [round(v / d[0], 4) for v in d]
    lo, hi = OFFSET_RANGE
    for axis, o in zip("XYZ", offs, strict=True):
        if not lo <= o <= hi:
            raise ValueError(f"{axis}off {o:.1f} counts outside the device's {lo:.0f}-{hi:.0f}")
    glo, ghi = PAR_SET_GAIN_RANGE
    for axis, k in zip("xyz", gains, strict=True):
        if not glo <= k <= ghi:
            raise ValueError(f"K{axis} {k:.4f} outside the device's {glo}-{ghi}")
    return DeviceMagParams(offs[0], offs[1], offs[2], gains[0], gains[1], gains[2])


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
