"""The calibration: one type, :class:`Calibration`, with its ArduPilot and device views.

Every method, whatever its error model, ends as an *affine* correction per
sensor, applied after the nominal transfer (counts -> gauss or g)::

    corrected = matrix @ (raw - offset)

``offset`` is the hard-iron vector (magnetometer, gauss) or the zero-g bias
(accelerometer, g), *subtracted*; ``matrix`` holds gains, soft iron,
non-orthogonality and -- for the magnetometer -- the rotation that aligns it
to the accelerometer axes. A symmetric ``matrix`` is what ArduPilot/PX4 can
express (COMPASS_DIA_*, COMPASS_ODI_*); the polar decomposition
``matrix = rotation @ symmetric`` separates the rest (:meth:`AffineCalibration.ardupilot_view`).

ArduPilot's COMPASS_OFS_* are *added* to the raw field and are in milligauss,
so ``COMPASS_OFS = -1000 * offset``; see :meth:`AffineCalibration.ardupilot_view`.

:class:`Calibration` is the type the package passes around (the engine applies
it, the store saves it, a fit returns it); :class:`AffineCalibration` is one
sensor's half of it (``.mag``, ``.accel``), what a fit of one sensor makes.
Its two other forms are views of it, not copies:

* the ArduPilot view -- :meth:`Calibration.ardupilot_view` (an :class:`ArduPilotView`:
  COMPASS_OFS / DIA / ODI / SCALE and the rotation) and
  :meth:`Calibration.ardupilot_parameters` (the parameter group by name: those,
  COMPASS_ORIENT and BRG_ALIGN_*), back with :meth:`Calibration.from_ardupilot_parameters`;
* the device view -- :meth:`Calibration.device_page`: what the compass flash can hold
  of it (offsets in counts and per-axis gains, ``$PGMRP`` / ``PAR,SET``), and
  :meth:`ArduPilotView.of_device`: a flash page's magnetometer half in ArduPilot's terms.
  The wire frame itself is the codec's :class:`~bridge.protocol.gmr.ParamsFrame`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from bridge.core import sensor
from bridge.core.geometry import dcm_to_rotvec, rotvec_to_dcm
from bridge.core.mounting import ROTATION_EULER_DEG, Rotation, rotation_matrix
from bridge.protocol.gmr import OFFSET_RANGE, PAR_SET_GAIN_RANGE, ParamsFrame
from bridge.types import FloatArray, Mat3, Vec3

IDENTITY: Mat3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def _vec3(v: npt.ArrayLike) -> Vec3:
    # tolist: the same Python floats as float() of each item, in one call
    x, y, z = np.asarray(v, dtype=np.float64).reshape(3).tolist()
    return (x, y, z)


def _mat3(m: npt.ArrayLike) -> Mat3:
    (a, b, c), (d, e, f), (g, h, i) = np.asarray(m, dtype=np.float64).reshape(3, 3).tolist()
    return ((a, b, c), (d, e, f), (g, h, i))


@dataclass(frozen=True, slots=True)
class ArduPilotView:
    """A magnetometer calibration in ArduPilot's terms (what MAG_CAL_REPORT / COMPASS_* carry).

    ``ofs_mG`` is COMPASS_OFS_X/Y/Z (added to raw, milligauss); ``diag`` is
    COMPASS_DIA_X/Y/Z and ``offdiag`` is COMPASS_ODI_X/Y/Z = (xy, xz, yz) of the
    symmetric part divided by ``scale`` (COMPASS_SCALE); ``rotation_rotvec`` is
    what the symmetric form cannot hold (the bridge's own alignment parameter).
    The defaults are ArduPilot's: no soft iron, no scale, no rotation.
    """

    ofs_mG: Vec3
    diag: Vec3 = (1.0, 1.0, 1.0)
    offdiag: Vec3 = (0.0, 0.0, 0.0)
    scale: float = 1.0
    rotation_rotvec: Vec3 = (0.0, 0.0, 0.0)

    @property
    def rotation_deg(self) -> float:
        """The rotation's angle (degrees): how far the magnetometer is turned against the
        accelerometer."""
        return math.degrees(float(np.linalg.norm(self.rotation_rotvec)))

    @classmethod
    def of_device(cls, page: ParamsFrame) -> ArduPilotView:
        """A device flash page's magnetometer half (offsets in counts, gains) in these terms:
        its offsets as COMPASS_OFS, its gains as the diagonal."""
        z, per_g = sensor.ZERO_COUNTS, sensor.MAG_COUNTS_PER_GAUSS
        ofs = [-1000.0 * (o - z) / per_g for o in (page.xoff, page.yoff, page.zoff)]
        return cls(_vec3(ofs), (page.kx, page.ky, page.kz))


@dataclass(frozen=True, slots=True)
class AffineCalibration:
    """``corrected = matrix @ (raw - offset)`` for one three-axis sensor (immutable)."""

    offset: Vec3 = (0.0, 0.0, 0.0)
    matrix: Mat3 = IDENTITY

    @classmethod
    def from_arrays(cls, offset: npt.ArrayLike, matrix: npt.ArrayLike) -> AffineCalibration:
        """Build from numpy arrays; raises ``ValueError`` on non-finite or singular input."""
        # (every fit builds its results here, the hand-held fit dozens of times a fit: the
        # arrays as given, plain floats and ndarray.all() rather than numpy's function layers)
        off = _vec3(offset)
        m = np.asarray(matrix, dtype=np.float64).reshape(3, 3)
        mat = _mat3(m)
        if not (all(map(math.isfinite, off)) and np.isfinite(m).all()):
            raise ValueError("calibration must be finite")
        if abs(float(np.linalg.det(m))) < 1e-9:
            raise ValueError("calibration matrix is singular")
        return cls(off, mat)

    @property
    def offset_array(self) -> FloatArray:
        """``offset`` as a numpy vector."""
        return np.asarray(self.offset, dtype=np.float64)

    @property
    def matrix_array(self) -> FloatArray:
        """``matrix`` as a 3x3 numpy array."""
        return np.asarray(self.matrix, dtype=np.float64)

    def apply(self, raw: npt.ArrayLike) -> FloatArray:
        """Correct one vector (3,) or a batch (N, 3)."""
        r = np.asarray(raw, dtype=np.float64)
        return (r - self.offset_array) @ self.matrix_array.T

    def then_rotate(self, rotation: npt.ArrayLike) -> AffineCalibration:
        """This calibration followed by a rotation (e.g. magnetometer-to-accelerometer alignment)."""
        return AffineCalibration.from_arrays(self.offset, np.asarray(rotation) @ self.matrix_array)

    def ardupilot_view(self) -> ArduPilotView:
        """Polar-decompose ``matrix = R @ S`` and express ``S`` the ArduPilot way.

        ``scale`` is chosen so the mean of the diagonal is 1 (COMPASS_SCALE).
        """
        m = self.matrix_array
        U, s, Vt = np.linalg.svd(m)
        R = U @ Vt
        if np.linalg.det(R) < 0:  # keep a proper rotation
            U[:, -1] = -U[:, -1]
            s[-1] = -s[-1]
            R = U @ Vt
        S = Vt.T @ np.diag(s) @ Vt
        scale = float(np.mean(np.diag(S)))
        Sn = S / scale
        return ArduPilotView(
            ofs_mG=_vec3(-1000.0 * self.offset_array),
            diag=_vec3(np.diag(Sn)),
            offdiag=(float(Sn[0, 1]), float(Sn[0, 2]), float(Sn[1, 2])),
            scale=scale,
            rotation_rotvec=_vec3(dcm_to_rotvec(R)),
        )

    @classmethod
    def from_ardupilot(cls, view: ArduPilotView) -> AffineCalibration:
        """Inverse of :meth:`ardupilot_view`: rebuild ``matrix = scale * R @ S`` and the offset.

        This is how a parameter SET (COMPASS_OFS_X, COMPASS_DIA_Y, ...) turns
        back into the calibration the engine applies.
        """
        d, o = view.diag, view.offdiag
        S = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
        R = rotvec_to_dcm(view.rotation_rotvec)
        return cls.from_arrays(-np.asarray(view.ofs_mG) / 1000.0, view.scale * (R @ S))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"offset": list(self.offset), "matrix": [list(r) for r in self.matrix]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AffineCalibration:
        """Inverse of :meth:`to_dict`; raises ``ValueError``/``KeyError``/``TypeError`` on bad input."""
        return cls.from_arrays(d["offset"], d["matrix"])


def corrects_iron(mag: AffineCalibration, tol: float = 1e-6) -> bool:
    """Whether a magnetometer calibration corrects anything but the axes' orientation.

    False for the identity and for a pure rotation (a level trim or a mounting
    folded in): no hard-iron offset and no soft-iron or gain correction, so the
    heading carries the unit's iron errors in full -- an uncalibrated compass.

    ``M @ M.T`` is the identity, element by element within ``tol`` (and numpy's
    ``allclose`` relative 1e-5 on the diagonal), as plain floats: the status of every
    front end asks this each time it goes out, and numpy's ``allclose`` on a 3x3
    costs some 70 us where this costs 5.
    """
    if any(abs(o) > tol for o in mag.offset):
        return True
    m = mag.matrix
    for i in range(3):
        ri = m[i]
        for j in range(3):
            rj = m[j]
            dot = ri[0] * rj[0] + ri[1] * rj[1] + ri[2] * rj[2]
            want = 1.0 if i == j else 0.0
            if not abs(dot - want) <= tol + 1e-5 * want:
                return True
    return False


@dataclass(frozen=True, slots=True)
class Calibration:
    """The complete sensor calibration the attitude engine applies.

    ``mag`` maps nominal gauss into the accelerometer's (body) axes; ``accel``
    maps nominal g into a unit gravity vector in the same axes. A level trim
    or mounting correction is a rotation folded into *both* matrices, so the
    two sensors always share one frame.
    """

    mag: AffineCalibration = field(default_factory=AffineCalibration)
    accel: AffineCalibration = field(default_factory=AffineCalibration)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"mag": self.mag.to_dict(), "accel": self.accel.to_dict()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Calibration:
        """Inverse of :meth:`to_dict`."""
        return cls(AffineCalibration.from_dict(d["mag"]), AffineCalibration.from_dict(d["accel"]))

    # -- the ArduPilot view ----------------------------------------------------------------

    def ardupilot_view(self) -> ArduPilotView:
        """The magnetometer calibration as ArduPilot's COMPASS_* figures (and the rotation)."""
        return self.mag.ardupilot_view()

    def ardupilot_parameters(self) -> dict[str, float]:
        """The calibration group's parameter values: COMPASS_OFS_*, COMPASS_DIA_*,
        COMPASS_ODI_*, COMPASS_SCALE, COMPASS_ORIENT and BRG_ALIGN_* (the rotation the
        symmetric form cannot hold; beyond 45 deg split as :func:`split_rotation` says)."""
        v = self.ardupilot_view()
        orient, residual = split_rotation(rotvec_to_dcm(v.rotation_rotvec))
        return {
            "COMPASS_OFS_X": v.ofs_mG[0],
            "COMPASS_OFS_Y": v.ofs_mG[1],
            "COMPASS_OFS_Z": v.ofs_mG[2],
            "COMPASS_DIA_X": v.diag[0],
            "COMPASS_DIA_Y": v.diag[1],
            "COMPASS_DIA_Z": v.diag[2],
            "COMPASS_ODI_X": v.offdiag[0],
            "COMPASS_ODI_Y": v.offdiag[1],
            "COMPASS_ODI_Z": v.offdiag[2],
            "COMPASS_SCALE": v.scale,
            "COMPASS_ORIENT": float(int(orient)),
            "BRG_ALIGN_X": float(residual[0]),
            "BRG_ALIGN_Y": float(residual[1]),
            "BRG_ALIGN_Z": float(residual[2]),
        }

    @classmethod
    def from_ardupilot_parameters(
        cls, values: Mapping[str, float], accel: AffineCalibration | None = None
    ) -> Calibration:
        """Inverse of :meth:`ardupilot_parameters`: the calibration the parameters describe,
        with ``accel`` as the accelerometer half (the identity if None). ``ValueError`` if
        the magnetometer half is singular or not finite."""
        g = values.__getitem__
        R = rotation_matrix(int(g("COMPASS_ORIENT"))) @ rotvec_to_dcm(
            [g("BRG_ALIGN_X"), g("BRG_ALIGN_Y"), g("BRG_ALIGN_Z")]
        )
        view = ArduPilotView(
            ofs_mG=(g("COMPASS_OFS_X"), g("COMPASS_OFS_Y"), g("COMPASS_OFS_Z")),
            diag=(g("COMPASS_DIA_X"), g("COMPASS_DIA_Y"), g("COMPASS_DIA_Z")),
            offdiag=(g("COMPASS_ODI_X"), g("COMPASS_ODI_Y"), g("COMPASS_ODI_Z")),
            scale=g("COMPASS_SCALE"),
            rotation_rotvec=_vec3(dcm_to_rotvec(R)),
        )
        mag = AffineCalibration.from_ardupilot(view)
        return cls(mag=mag, accel=AffineCalibration() if accel is None else accel)

    # -- the device view -------------------------------------------------------------------

    def device_page(self, current: ParamsFrame | None = None) -> ParamsFrame:
        """The flash page that holds what the device can of this calibration: its model
        ``H = K * (m - off)`` takes offsets and per-axis gains; the level reference
        (Gxoff .. Gzoff) is the device's own, ``current``'s (the datasheet's factory
        values when None: a page to check or show, not to write).

        Offsets: ``2458 + 2560 * offset`` counts (the nominal transfer inverted).
        Gains: the diagonal of the symmetric soft-iron part relative to x (the
        device's heading is scale-free, and MAGCAL,END itself sets Kx = 1); the
        rotation and the off-diagonal terms have no place in the device's model.
        Values are rounded to the flash's grid (0.1 count, 0.0001). Raises
        ``ValueError`` when an offset leaves 0-4095 counts or a gain leaves the
        0.1-10 that PAR,SET accepts.
        """
        mag = self.mag
        d = mag.ardupilot_view().diag
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
        level = ParamsFrame.factory() if current is None else current
        return ParamsFrame(
            offs[0], offs[1], offs[2], gains[0], gains[1], gains[2],
            level.gxoff, level.gyoff, level.gzoff,
        )  # fmt: skip


_ORIENT_SPLIT_DEG = 45.0  # rotations beyond this are COMPASS_ORIENT + a residual


def split_rotation(R: npt.ArrayLike) -> tuple[Rotation, FloatArray]:
    """(nearest ArduPilot rotation, residual rotation vector) with ``R = M(orient) @ R(residual)``.

    Rotations within 45 deg of identity stay whole (orientation NONE): a real
    alignment error is a few degrees, a wrong mounting is a multiple of 45, as
    ArduPilot's own calibrator reports a new orientation.
    """
    R = np.asarray(R, dtype=np.float64)
    angle = math.degrees(float(np.linalg.norm(dcm_to_rotvec(R))))
    if angle <= _ORIENT_SPLIT_DEG:
        return Rotation.ROTATION_NONE, dcm_to_rotvec(R)
    best, best_angle, best_res = Rotation.ROTATION_NONE, math.inf, dcm_to_rotvec(R)
    for rot in ROTATION_EULER_DEG:
        Mr = rotation_matrix(rot)
        res = dcm_to_rotvec(Mr.T @ R)
        a = float(np.linalg.norm(res))
        if a < best_angle - 1e-9:
            best, best_angle, best_res = rot, a, res
    return best, best_res


@dataclass(frozen=True, slots=True)
class CalibrationReport:
    """How good a fit is, in the figures an integrator reads.

    ``fitness_mG`` is ArduPilot's MAG_CAL_REPORT.fitness: RMS of (|corrected| -
    radius) in milligauss. Field spreads are peak-to-peak / 2 of |B| in nT
    (the seed paper's "+-700 nT -> +-100 nT"). ``status`` is a MAG_CAL_STATUS
    name ("MAG_CAL_SUCCESS", "MAG_CAL_BAD_RADIUS", ...).

    Fits of a frame series (a hand-held tumble, :mod:`bridge.calibration.fits.handheld`)
    also say how good the result is for the heading: ``heading_error_deg`` /
    ``tilt_error_deg`` the predicted RMS error the calibration itself leaves
    (any heading, tilt up to 60 deg), ``motion_g`` the linear acceleration seen
    (RMS per axis), ``window_s`` the averaging window used. Their
    ``fitness_mG`` then counts that error too -- ``sqrt(residual^2 + (H tan
    heading_error)^2)`` with ``H`` the horizontal field -- so a fit the shake
    spoiled cannot show a perfect fitness; ``residual_mG`` keeps the
    magnetometer's own residual.

    Spreads, fitness and ``n_samples`` cover the samples the fit kept;
    ``n_frames`` counts every usable frame and ``field_spread_after_all_nT`` is
    the spread after over all of them. ``reason`` is the cause of a failure
    (empty on success); ``predicted_heading_deg`` / ``heading_limit_deg`` the
    acceptance rule's verdict (:mod:`bridge.calibration.fits.acceptance`).
    """

    method: str
    status: str = "MAG_CAL_SUCCESS"
    n_samples: int = 0
    n_rejected: int = 0
    fitness_mG: float = math.nan
    radius_G: float = math.nan
    scale_factor: float = 1.0
    field_spread_before_nT: float = math.nan
    field_spread_after_nT: float = math.nan
    gravity_spread_before_mg: float = math.nan
    gravity_spread_after_mg: float = math.nan
    coverage_pct: float = math.nan
    iterations: int = 0
    notes: tuple[str, ...] = ()
    # RMS companions of the +-half-peak-to-peak spreads above (|B| - mean, |g| - 1 g).
    field_rms_before_nT: float = math.nan
    field_rms_after_nT: float = math.nan
    gravity_rms_before_mg: float = math.nan
    gravity_rms_after_mg: float = math.nan
    residual_mG: float = math.nan
    heading_error_deg: float = math.nan
    tilt_error_deg: float = math.nan
    motion_g: float = math.nan
    window_s: float = math.nan
    # The acceptance rule's figures (bridge.calibration.fits.acceptance): the cause of a
    # failure, the frames the figures cover, the sensor's noise, the heading error
    # predicted and its limit, the sphere sections the raw samples reach.
    reason: str = ""
    n_frames: int = 0
    noise_mG: float = math.nan
    horizontal_mG: float = math.nan
    sections_covered: int = 0
    predicted_heading_deg: float = math.nan
    heading_floor_deg: float = math.nan
    heading_limit_deg: float = math.nan
    field_spread_after_all_nT: float = math.nan
    field_rms_after_all_nT: float = math.nan

    @property
    def ok(self) -> bool:
        """True when ``status`` is MAG_CAL_SUCCESS."""
        return self.status == "MAG_CAL_SUCCESS"

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (NaN becomes None)."""
        out: dict[str, Any] = {}
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            if isinstance(v, float) and not math.isfinite(v):
                v = None
            elif isinstance(v, tuple):
                v = list(v)
            out[name] = v
        return out


@dataclass(frozen=True, slots=True)
class CalibrationResult:
    """A method's outcome: the parameters and their report."""

    calibration: Calibration
    report: CalibrationReport
