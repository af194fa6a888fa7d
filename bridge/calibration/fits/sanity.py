"""Sanity bounds on a fitted calibration, mapped to MAVLink MAG_CAL_STATUS codes.

The limits are ArduPilot's (``CompassCalibrator::fit_acceptable`` and
``fix_radius``; ``AccelCalibrator::accept_result`` for the accelerometer):

==========================  =============================  ===============================
check                       limit                          status when violated
==========================  =============================  ===============================
non-finite / singular       --                             MAG_CAL_FAILED
parameter uncertainty       offsets 1 mG, matrix 0.002     MAG_CAL_FAILED
fitted field radius         150 < r < 950 mG               MAG_CAL_FAILED_RADIUS
WMM scale factor            1/1.5 <= s <= 1.5              MAG_CAL_FAILED_RADIUS
offsets COMPASS_OFS_*       abs < COMPASS_OFFS_MAX 1800 mG MAG_CAL_FAILED_OFFSETS
diagonal COMPASS_DIA_*      0.2 < d < 5.0                  MAG_CAL_FAILED_DIAG_SCALING
off-diagonal COMPASS_ODI_*  abs < 1.0                      MAG_CAL_FAILED_DIAG_SCALING
fitness                     <= COMPASS_CAL_FIT 16 mG       MAG_CAL_FAILED_RESIDUALS_HIGH
mag-to-accel rotation       <= 20 deg                      MAG_CAL_FAILED_ORIENTATION
==========================  =============================  ===============================

Status names follow the MAVLink ``common.xml`` in use (pymavlink >= 2.4.4x):
``MAG_CAL_FAILED_ORIENTATION`` (6) and ``MAG_CAL_FAILED_RADIUS`` (7) were
called ``MAG_CAL_BAD_ORIENTATION`` / ``MAG_CAL_BAD_RADIUS`` before; both
spellings are accepted by :meth:`MagCalStatus.parse`. Codes 8-10 are newer
than many ground stations: :attr:`MagCalStatus.legacy` folds them into
``MAG_CAL_FAILED`` (5), which is what ArduPilot itself sends for them.

The rotation limit is ours: a real mounting misalignment is a few degrees,
while a wrong COMPASS_ORIENT is at least 45 deg, so 20 deg separates them.
So is the uncertainty check: ArduPilot ensures spread samples before it fits,
an offline fit cannot, and samples from a small cap of the sphere fit their
9 parameters to noise with a perfect-looking residual. The engine's methods
(``methods.calibrate``) leave the uncertainty and the fitness out of these
checks and judge them by the acceptance rule instead
(:mod:`bridge.calibration.fits.acceptance`: the heading error predicted, against
a limit that scales with the sensor's noise and sample count); the fixed
defaults here serve direct callers of the fits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import numpy.typing as npt

from bridge.core.calibration import AffineCalibration
from bridge.core.mounting import Rotation, rotation_matrix
from bridge.types import FloatArray


class MagCalStatus(IntEnum):
    """MAVLink MAG_CAL_STATUS (values are the wire codes)."""

    MAG_CAL_NOT_STARTED = 0
    MAG_CAL_WAITING_TO_START = 1
    MAG_CAL_RUNNING_STEP_ONE = 2
    MAG_CAL_RUNNING_STEP_TWO = 3
    MAG_CAL_SUCCESS = 4
    MAG_CAL_FAILED = 5
    MAG_CAL_FAILED_ORIENTATION = 6
    MAG_CAL_FAILED_RADIUS = 7
    MAG_CAL_FAILED_OFFSETS = 8
    MAG_CAL_FAILED_DIAG_SCALING = 9
    MAG_CAL_FAILED_RESIDUALS_HIGH = 10
    # Older spellings of 6 and 7 (enum aliases: same values).
    MAG_CAL_BAD_ORIENTATION = 6
    MAG_CAL_BAD_RADIUS = 7

    @property
    def legacy(self) -> MagCalStatus:
        """The code a ground station that predates 8-10 understands (8-10 -> MAG_CAL_FAILED)."""
        return MagCalStatus.MAG_CAL_FAILED if self.value >= 8 else self

    @property
    def failed(self) -> bool:
        """True for every failure code (5 and above)."""
        return self.value >= MagCalStatus.MAG_CAL_FAILED.value

    @classmethod
    def parse(cls, status: str | int) -> MagCalStatus:
        """From a name (either spelling) or a wire code; raises ``ValueError`` when unknown."""
        if isinstance(status, int):
            return cls(status)
        try:
            return cls[status]
        except KeyError:
            raise ValueError(f"unknown MAG_CAL_STATUS {status!r}") from None


@dataclass(frozen=True, slots=True)
class SanityLimits:
    """Bounds for :func:`check_mag_calibration` (defaults are ArduPilot's)."""

    radius_min_mG: float = 150.0  #: FIELD_RADIUS_MIN
    radius_max_mG: float = 950.0  #: FIELD_RADIUS_MAX
    offset_max_mG: float = 1800.0  #: COMPASS_OFFS_MAX default
    diag_min: float = 0.2
    diag_max: float = 5.0
    offdiag_max: float = 1.0
    fitness_max_mG: float = 16.0  #: COMPASS_CAL_FIT default
    scale_factor_max: float = 1.5  #: COMPASS_MAX_SCALE_FACTOR (min is its inverse)
    rotation_max_deg: float = 20.0
    offset_sd_max_mG: float = 1.0  #: one-sigma offset uncertainty
    matrix_sd_max: float = 0.002  #: one-sigma uncertainty of a soft-iron element


#: The smallest rotation a wrong COMPASS_ORIENT puts between magnetometer and accelerometer.
WRONG_ORIENTATION_MIN_DEG = 45.0


def rotation_determined(sigma_deg: float, limits: SanityLimits | None = None) -> bool:
    """Whether a fitted mag-to-accel rotation known to ``sigma_deg`` (1 sigma; the heading
    error its uncertainty gives) can tell a wrong orientation from a good one: three sigmas
    within the gap between the limit and the smallest wrong orientation (45 - 20 deg). A
    rotation fitted from frames a hand shook too hard to find gravity in (a sigma of tens of
    degrees, or none) is unknown, not wrong: that is motion, not COMPASS_ORIENT."""
    lim = limits or SanityLimits()
    return math.isfinite(sigma_deg) and (
        3.0 * sigma_deg <= WRONG_ORIENTATION_MIN_DEG - lim.rotation_max_deg
    )


@dataclass(frozen=True, slots=True)
class AccelLimits:
    """Bounds for :func:`check_accel_calibration` (ArduPilot's AccelCalibrator)."""

    offset_max_g: float = 1.0
    diag_min: float = 0.8
    diag_max: float = 1.2


@dataclass(frozen=True, slots=True)
class SanityResult:
    """Outcome of a sanity check: the first failing status and every reason found."""

    status: MagCalStatus
    reasons: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        """True when nothing failed."""
        return self.status is MagCalStatus.MAG_CAL_SUCCESS


def _finite(x: float | None) -> bool:
    return x is not None and math.isfinite(x)


def check_mag_calibration(
    mag: AffineCalibration,
    *,
    radius_G: float,
    fitness_mG: float,
    scale_factor: float | None = None,
    offset_sd_mG: float | None = None,
    matrix_sd: float | None = None,
    check_rotation: bool = False,
    limits: SanityLimits | None = None,
) -> SanityResult:
    """Check a magnetometer calibration against ArduPilot-style bounds.

    ``radius_G`` is the fitted field radius before any WMM scaling, as
    ArduPilot's ``_params.radius``; ``scale_factor`` the WMM correction
    (``None`` when no reference field was known). ``offset_sd_mG`` /
    ``matrix_sd`` are the fit's parameter uncertainties, when known.
    ``check_rotation`` enables the
    mag-to-accel rotation bound (only meaningful once an alignment was fitted).
    The status is the first failure in the table's order; all are listed in
    ``reasons``.
    """
    lim = limits or SanityLimits()
    failures: list[tuple[MagCalStatus, str]] = []
    m = mag.matrix_array
    if not (np.all(np.isfinite(m)) and np.all(np.isfinite(mag.offset_array))):
        return SanityResult(MagCalStatus.MAG_CAL_FAILED, ("calibration is not finite",))
    if abs(float(np.linalg.det(m))) < 1e-9:
        return SanityResult(MagCalStatus.MAG_CAL_FAILED, ("calibration matrix is singular",))
    if not _finite(fitness_mG) or not _finite(radius_G):
        return SanityResult(MagCalStatus.MAG_CAL_FAILED, ("fit did not converge (NaN fitness)",))
    view = mag.ardupilot_view()

    if offset_sd_mG is not None and not offset_sd_mG <= lim.offset_sd_max_mG:
        failures.append(
            (
                MagCalStatus.MAG_CAL_FAILED,
                f"offsets undetermined (+-{offset_sd_mG:.1f} mG): samples cover too little "
                "of the sphere, turn the unit through more directions",
            )
        )
    if matrix_sd is not None and not matrix_sd <= lim.matrix_sd_max:
        failures.append(
            (
                MagCalStatus.MAG_CAL_FAILED,
                f"soft-iron matrix undetermined (+-{matrix_sd:.4f}): samples cover too "
                "little of the sphere",
            )
        )
    r_mG = 1000.0 * radius_G
    if not lim.radius_min_mG < r_mG < lim.radius_max_mG:
        failures.append(
            (
                MagCalStatus.MAG_CAL_FAILED_RADIUS,
                f"field radius {r_mG:.0f} mG outside {lim.radius_min_mG:.0f}-{lim.radius_max_mG:.0f} mG",
            )
        )
    if scale_factor is not None:
        lo = 1.0 / lim.scale_factor_max
        if not (_finite(scale_factor) and lo <= scale_factor <= lim.scale_factor_max):
            failures.append(
                (
                    MagCalStatus.MAG_CAL_FAILED_RADIUS,
                    f"scale factor {scale_factor:.3f} to the WMM field outside "
                    f"{lo:.3f}-{lim.scale_factor_max:.3f}",
                )
            )
    for axis, o in zip("XYZ", view.ofs_mG, strict=True):
        if not abs(o) < lim.offset_max_mG:
            failures.append(
                (
                    MagCalStatus.MAG_CAL_FAILED_OFFSETS,
                    f"COMPASS_OFS_{axis} {o:.0f} mG beyond COMPASS_OFFS_MAX {lim.offset_max_mG:.0f}",
                )
            )
    for axis, d in zip("XYZ", view.diag, strict=True):
        if not lim.diag_min < d < lim.diag_max:
            failures.append(
                (
                    MagCalStatus.MAG_CAL_FAILED_DIAG_SCALING,
                    f"COMPASS_DIA_{axis} {d:.3f} outside {lim.diag_min}-{lim.diag_max}",
                )
            )
    for axis, d in zip("XYZ", view.offdiag, strict=True):
        if not abs(d) < lim.offdiag_max:
            failures.append(
                (
                    MagCalStatus.MAG_CAL_FAILED_DIAG_SCALING,
                    f"COMPASS_ODI_{axis} {d:.3f} beyond +-{lim.offdiag_max}",
                )
            )
    if not fitness_mG <= lim.fitness_max_mG:
        failures.append(
            (
                MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH,
                f"fitness {fitness_mG:.2f} mG above COMPASS_CAL_FIT {lim.fitness_max_mG:.1f}",
            )
        )
    if check_rotation:
        angle = math.degrees(float(np.linalg.norm(view.rotation_rotvec)))
        if not angle <= lim.rotation_max_deg:
            failures.append(
                (
                    MagCalStatus.MAG_CAL_FAILED_ORIENTATION,
                    f"mag-to-accel rotation {angle:.1f} deg above {lim.rotation_max_deg:.0f} deg "
                    "(check COMPASS_ORIENT)",
                )
            )
    if not failures:
        return SanityResult(MagCalStatus.MAG_CAL_SUCCESS)
    return SanityResult(failures[0][0], tuple(r for _, r in failures))


def check_accel_calibration(
    accel: AffineCalibration, limits: AccelLimits | None = None
) -> SanityResult:
    """Check an accelerometer calibration (offsets within 1 g, gains 0.8-1.2, as ArduPilot).

    Gains are the diagonal of ``matrix``; there is no accelerometer code in
    MAG_CAL_STATUS, so a failure is ``MAG_CAL_FAILED`` with the reasons.
    """
    lim = limits or AccelLimits()
    m, o = accel.matrix_array, accel.offset_array
    if not (np.all(np.isfinite(m)) and np.all(np.isfinite(o))):
        return SanityResult(
            MagCalStatus.MAG_CAL_FAILED, ("accelerometer calibration is not finite",)
        )
    reasons: list[str] = []
    for axis, v in zip("XYZ", o.tolist(), strict=True):
        if not abs(v) <= lim.offset_max_g:
            reasons.append(f"accel offset {axis} {v:.3f} g beyond {lim.offset_max_g} g")
    for axis, d in zip("XYZ", np.diag(m).tolist(), strict=True):
        if not lim.diag_min <= d <= lim.diag_max:
            reasons.append(f"accel gain {axis} {d:.3f} outside {lim.diag_min}-{lim.diag_max}")
    if reasons:
        return SanityResult(MagCalStatus.MAG_CAL_FAILED, tuple(reasons))
    return SanityResult(MagCalStatus.MAG_CAL_SUCCESS)


# -- ArduPilot's orientation check (calculate_orientation) ----------------------------------

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
