"""Magnetometer-to-accelerometer alignment from the constant dot product, and the full best fit.

After an ellipsoid fit the magnetometer reads a sphere, but in axes that are
still *rotated* against the accelerometer's: the symmetric soft-iron matrix
cannot hold the rotational part of the axis non-orthogonality nor the
mounting misalignment of the two sensor chips. On a realistic unit that is
2-3 deg of heading error while the ellipsoid residual looks perfect.

Wherever the unit points, the angle between gravity and the Earth's field is
the same (90 deg + dip), so with unit vectors ``a_i`` (gravity) and
``m_i`` (field) and the sought rotation ``R``::

    a_i . (R m_i) = sin(dip)        for every sample i

Any rotation other than the true one makes this vary with attitude, so a
tumble determines ``R`` (and the dip) completely:

1. linear initial solution: ``a' X m - s = 0`` is linear in the 9 elements of
   ``X`` and ``s``; the smallest eigenvector of the 10x10 scatter matrix gives
   ``X = alpha R``, projected onto the nearest rotation (SVD);
2. Gauss-Newton on the rotation (a rotation-vector increment ``delta``:
   ``d/d delta [a . exp(delta^) R m] = (R m x a) . delta``) and ``s``;
3. samples with a residual beyond ``k`` robust sigmas are dropped, then 2 again.

That is :func:`fit_ellipsoid_aligned`, for a bag of samples (unit vectors, so
a sample taken while the unit accelerates is skipped). A *series* of
consecutive frames -- what a live calibration records -- goes through
:func:`fit_ellipsoid_aligned_series` instead: the same ellipsoid, then
:mod:`bridge.calibration.fits.handheld`, which keeps every frame of a shaken,
hand-held tumble and averages the shake away.

A level-only turn leaves the rotation about the vertical undetermined; that is
detected from the normal matrix and reported (``observable=False``, identity).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from bridge.calibration.fits.ellipsoid import (
    DEFAULT_MAX_ITERATIONS,
    ReferenceField,
    ellipsoid_result,
    fit_ellipsoid_geometry,
    no_ellipsoid,
    reference_total_G,
)
from bridge.calibration.fits.handheld import fit_handheld
from bridge.calibration.fits.samples import DEFAULT_OUTLIER_K, inlier_mask, usable_mask
from bridge.calibration.fits.sanity import (
    MagCalStatus,
    SanityLimits,
    SanityResult,
    check_mag_calibration,
    rotation_determined,
)
from bridge.calibration.fits.scalar import gravity_spread_mg
from bridge.core.calibration import AffineCalibration, Calibration, CalibrationResult
from bridge.core.geometry import dcm_to_rotvec, rotvec_to_dcm
from bridge.core.sensor import GAUSS_TO_MGAUSS
from bridge.core.wmm import EarthField
from bridge.types import BoolArray, FloatArray

MIN_SAMPLES = 20
DEFAULT_MAX_ACCEL_DEVIATION_G = 0.05  #: |g| further than this from 1 g: the unit was accelerating
#: Smallest per-sample eigenvalue of the normal matrix below which a rotation axis
#: counts as unobserved: a level-only turn gives exactly 0 about the vertical, a
#: real tumble about 0.05 at 63 deg dip.
_MIN_INFORMATION = 1e-3
#: Residuals are sines (dimensionless); 1e-4 is 0.006 deg, below any sensor noise.
_MIN_SIGMA = 1e-4


@dataclass(frozen=True, slots=True)
class AlignmentResult:
    """Rotation from the calibrated magnetometer axes into the accelerometer axes.

    ``rotation`` (3x3) is applied after the magnetometer calibration
    (``AffineCalibration.then_rotate``). ``dot_mean`` is the mean of
    ``a . (R m)`` with unit ``a`` and ``m`` in gauss: the vertical field
    component. ``dot_spread_before``/``_after`` are the standard deviations of
    that dot product (gauss) without and with the rotation. ``dip_deg`` is the
    inclination the aligned data imply (positive down). ``inliers`` flags the
    input rows used.
    """

    rotation: FloatArray
    angle_deg: float
    dot_mean: float
    dot_spread_before: float
    dot_spread_after: float
    dip_deg: float
    n_samples: int
    n_rejected: int
    iterations: int
    observable: bool
    inliers: BoolArray

    @property
    def rotvec(self) -> FloatArray:
        """The rotation as a rotation vector (axis * angle, radians)."""
        return dcm_to_rotvec(self.rotation)


def _unit(v: FloatArray) -> FloatArray:
    n = np.sqrt(np.einsum("ij,ij->i", v, v))[:, None]
    return np.asarray(v / np.where(n > 0.0, n, 1.0), dtype=np.float64)


def _nearest_rotation(X: FloatArray) -> FloatArray:
    U, _, Vt = np.linalg.svd(X)
    R = U @ Vt
    if np.linalg.det(R) < 0.0:
        U[:, -1] = -U[:, -1]
        R = U @ Vt
    return np.asarray(R, dtype=np.float64)


def linear_alignment(a_unit: FloatArray, m_unit: FloatArray) -> tuple[FloatArray, float]:
    """Closed-form initial rotation and sin(dip) from unit gravity/field rows (N, 3)."""
    D = np.empty((a_unit.shape[0], 10))
    D[:, :9] = (a_unit[:, :, None] * m_unit[:, None, :]).reshape(-1, 9)
    D[:, 9] = -1.0
    _, V = np.linalg.eigh(D.T @ D)
    v = V[:, 0]
    X = v[:9].reshape(3, 3)
    if np.linalg.det(X) < 0.0:  # the eigenvector's sign is arbitrary; X must be +alpha R
        v = -v
        X = -X
    R = _nearest_rotation(X)
    alpha = float(np.trace(R.T @ X)) / 3.0
    s = float(v[9] / alpha) if alpha != 0.0 else 0.0
    return R, max(-1.0, min(1.0, s))


def _gauss_newton(
    a: FloatArray, m: FloatArray, R: FloatArray, s: float, max_iterations: int
) -> tuple[FloatArray, float, int, float]:
    """Refine (R, s); returns them, the iterations and the smallest normal-matrix eigenvalue per sample."""
    n = a.shape[0]
    min_info = 0.0
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 - the count is reported
        Rm = m @ R.T
        e = np.einsum("ij,ij->i", a, Rm) - s
        J = np.empty((n, 4))
        J[:, :3] = np.cross(Rm, a)
        J[:, 3] = -1.0
        JTJ = J.T @ J
        min_info = float(np.linalg.eigvalsh(JTJ)[0]) / n
        if min_info < _MIN_INFORMATION:
            break
        step = np.linalg.solve(JTJ, -(J.T @ e))
        R = rotvec_to_dcm(step[:3]) @ R
        s += float(step[3])
        if float(np.linalg.norm(step)) < 1e-12:
            break
    return R, s, it, min_info


def fit_alignment(
    mag_cal_G: npt.ArrayLike,
    acc_cal_g: npt.ArrayLike,
    *,
    max_accel_deviation_g: float = DEFAULT_MAX_ACCEL_DEVIATION_G,
    outlier_k: float | None = DEFAULT_OUTLIER_K,
    max_iterations: int = 10,
) -> AlignmentResult:
    """Rotation taking calibrated magnetometer vectors into the accelerometer's axes.

    ``mag_cal_G`` (N, 3) is the magnetometer after its ellipsoid calibration,
    ``acc_cal_g`` (N, 3) the calibrated gravity vector of the *same* frames.
    Rows that are non-finite, zero, or whose |g| is more than
    ``max_accel_deviation_g`` from 1 g (the unit was accelerating) are skipped.
    Raises ``ValueError`` on mismatched shapes or fewer than 20 usable rows.
    """
    m_all = np.asarray(mag_cal_G, dtype=np.float64)
    a_all = np.asarray(acc_cal_g, dtype=np.float64)
    if m_all.ndim != 2 or m_all.shape[1] != 3 or m_all.shape != a_all.shape:
        raise ValueError(f"mag and acc must both be (N, 3), got {m_all.shape} and {a_all.shape}")
    ok = usable_mask(m_all) & usable_mask(a_all)
    a0 = np.where(ok[:, None], a_all, 0.0)
    m0 = np.where(ok[:, None], m_all, 0.0)
    an = np.sqrt(np.einsum("ij,ij->i", a0, a0))
    mn = np.sqrt(np.einsum("ij,ij->i", m0, m0))
    ok &= (np.abs(an - 1.0) <= max_accel_deviation_g) & (mn > 0.0)
    idx = np.flatnonzero(ok)
    if idx.size < MIN_SAMPLES:
        raise ValueError(f"alignment needs at least {MIN_SAMPLES} still samples, got {idx.size}")
    m, a = m_all[idx], a_all[idx]
    mu, au = _unit(m), _unit(a)

    R, s = linear_alignment(au, mu)
    R, s, iters, info = _gauss_newton(au, mu, R, s, max_iterations)
    keep = np.ones(idx.size, dtype=bool)
    if outlier_k is not None and info >= _MIN_INFORMATION:
        e = np.einsum("ij,ij->i", au, mu @ R.T) - s
        keep = inlier_mask(e, outlier_k, _MIN_SIGMA)
        if not np.all(keep) and np.count_nonzero(keep) >= MIN_SAMPLES:
            R, s, more, info = _gauss_newton(au[keep], mu[keep], R, s, max_iterations)
            iters += more
        else:
            keep[:] = True
    observable = info >= _MIN_INFORMATION
    if not observable:
        R = np.eye(3)
    dots_before = np.einsum("ij,ij->i", au[keep], m[keep])
    dots_after = np.einsum("ij,ij->i", au[keep], m[keep] @ R.T)
    sin_dip = float(np.mean(np.einsum("ij,ij->i", au[keep], mu[keep] @ R.T)))
    inliers = np.zeros(m_all.shape[0], dtype=bool)
    inliers[idx[keep]] = True
    return AlignmentResult(
        rotation=R,
        angle_deg=math.degrees(float(np.linalg.norm(dcm_to_rotvec(R)))),
        dot_mean=float(np.mean(dots_after)),
        dot_spread_before=float(np.std(dots_before)),
        dot_spread_after=float(np.std(dots_after)),
        dip_deg=math.degrees(math.asin(max(-1.0, min(1.0, sin_dip)))),
        n_samples=int(np.count_nonzero(keep)),
        n_rejected=int(m_all.shape[0] - np.count_nonzero(keep)),
        iterations=iters,
        observable=observable,
        inliers=inliers,
    )


def fit_ellipsoid_aligned(
    mag_G: npt.ArrayLike,
    acc_g: npt.ArrayLike,
    accel_calibration: AffineCalibration | None = None,
    reference_field_G: ReferenceField = None,
    *,
    saturated: npt.ArrayLike | None = None,
    outlier_k: float | None = DEFAULT_OUTLIER_K,
    max_accel_deviation_g: float = DEFAULT_MAX_ACCEL_DEVIATION_G,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
    limits: SanityLimits | None = None,
) -> CalibrationResult:
    """The engine's best magnetometer calibration: ellipsoid fit, then mag-to-accel alignment.

    ``mag_G``/``acc_g`` are the raw (nominal-transfer) vectors of the same
    frames, (N, 3) each; ``accel_calibration`` maps ``acc_g`` into a unit
    gravity vector (use the 6-face calibration: its quality sets the heading
    accuracy at high dip) and is returned unchanged as the result's ``accel``.
    The result's magnetometer matrix is ``R @ S``: symmetric soft iron, then
    the rotation into the accelerometer's axes (COMPASS_DIA/ODI hold ``S``;
    ``ardupilot_view().rotation_rotvec`` returns ``R``).
    """
    x = np.asarray(mag_G, dtype=np.float64)
    g = np.asarray(acc_g, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape != g.shape:
        raise ValueError(f"mag_G and acc_g must both be (N, 3), got {x.shape} and {g.shape}")
    method = "ellipsoid_aligned"
    acc_cal = accel_calibration or AffineCalibration()
    ref = reference_total_G(reference_field_G)
    fit = fit_ellipsoid_geometry(
        x, saturated=saturated, outlier_k=outlier_k, max_iterations=max_iterations
    )
    if fit is None:
        return no_ellipsoid(method, x, saturated)
    ell = ellipsoid_result(fit, x, ref, limits=limits, accel=acc_cal, method=method)
    notes = list(ell.report.notes)
    if accel_calibration is None:
        notes.append("no accelerometer calibration given: nominal accelerometer used for alignment")
    mag_sym = ell.calibration.mag
    use = fit.inliers & usable_mask(g)
    try:
        al = fit_alignment(
            mag_sym.apply(x[use]),
            acc_cal.apply(g[use]),
            max_accel_deviation_g=max_accel_deviation_g,
            outlier_k=outlier_k,
        )
    except ValueError as exc:
        notes.append(f"alignment skipped: {exc}")
        return CalibrationResult(ell.calibration, replace(ell.report, notes=tuple(notes)))
    if not al.observable:
        notes.append(
            "alignment not observable from these attitudes (turn the unit over): not applied"
        )
    mag = mag_sym.then_rotate(al.rotation)
    sanity = check_mag_calibration(
        mag,
        radius_G=fit.radius_G,
        fitness_mG=fit.fitness_mG,
        scale_factor=ell.report.scale_factor if ref is not None else None,
        offset_sd_mG=1000.0 * fit.offset_sd_G,
        matrix_sd=fit.matrix_sd,
        check_rotation=True,
        limits=limits,
    )
    # The ellipsoid's own reasons are already in notes; add only what the rotation changed.
    notes.extend(r for r in sanity.reasons if r not in notes)
    notes.append(
        f"mag-to-accel rotation {al.angle_deg:.2f} deg, dip {al.dip_deg:.2f} deg, "
        f"dot spread {GAUSS_TO_MGAUSS * al.dot_spread_before:.2f} -> "
        f"{GAUSS_TO_MGAUSS * al.dot_spread_after:.2f} mG ({al.n_samples} samples)"
    )
    g_before = gravity_spread_mg(g[use])
    g_after = gravity_spread_mg(acc_cal.apply(g[use]))
    report = replace(
        ell.report,
        status=sanity.status.name,
        iterations=ell.report.iterations + al.iterations,
        gravity_spread_before_mg=g_before[0],
        gravity_spread_after_mg=g_after[0],
        gravity_rms_before_mg=g_before[1],
        gravity_rms_after_mg=g_after[1],
        notes=tuple(notes),
    )
    return CalibrationResult(Calibration(mag=mag, accel=acc_cal), report)


def motion_failure_reason(heading_error_deg: float, limit_deg: float | None = None) -> str:
    """Why a hand-held fit is not good enough, in the operator's terms (a STATUSTEXT's worth)."""
    if not heading_error_deg < 89.0:  # (none, or the fit's "unknown": 89 deg and beyond)
        return "gravity not determined: turn slower / steadier"
    limit = f" > {limit_deg:g}" if limit_deg is not None else ""
    return f"heading error ~{heading_error_deg:.2f} deg{limit}: turn slower / steadier"


def horizontal_field_G(reference: ReferenceField, radius_G: float, dip_deg: float) -> float:
    """Horizontal intensity for turning a heading error into milligauss.

    From the reference when it has a direction (an :class:`EarthField` or an
    NED vector); else its total (or the fitted radius) with the fitted dip.
    """
    if isinstance(reference, EarthField):
        return float(reference.horizontal_G)
    if reference is not None:
        a = np.asarray(reference, dtype=np.float64)
        if a.shape == (3,):
            return float(np.hypot(a[0], a[1]))
    total = reference_total_G(reference) or radius_G
    return float(total * math.cos(math.radians(dip_deg)))


def fit_ellipsoid_aligned_series(
    mag_G: npt.ArrayLike,
    acc_g: npt.ArrayLike,
    t_s: npt.ArrayLike,
    accel_calibration: AffineCalibration | None = None,
    reference_field_G: ReferenceField = None,
    *,
    saturated: npt.ArrayLike | None = None,
    outlier_k: float | None = DEFAULT_OUTLIER_K,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
    limits: SanityLimits | None = None,
) -> CalibrationResult:
    """The best fit from a frame *series* (a hand-held tumble), with its predicted heading error.

    ``mag_G``/``acc_g`` (N, 3) are the raw vectors of consecutive frames and
    ``t_s`` (N,) their times in seconds. The ellipsoid is fitted to every
    usable frame (a shake does not reach the magnetometer); the accelerometer
    calibration -- unless ``accel_calibration`` is given -- and the
    magnetometer-to-accelerometer rotation come from
    :func:`bridge.calibration.fits.handheld.fit_handheld`, which averages the shake
    away. The report carries ``heading_error_deg`` and a ``fitness_mG`` that
    includes it (see :class:`CalibrationReport`). Falls back to
    :func:`fit_ellipsoid_aligned` on the same frames when the series does not
    determine the hand-held fit (too few frames, or turns about one axis).
    """
    x = np.asarray(mag_G, dtype=np.float64)
    g = np.asarray(acc_g, dtype=np.float64)
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape != g.shape or t.shape != (x.shape[0],):
        raise ValueError(
            f"mag_G, acc_g and t_s must be (N, 3), (N, 3), (N,); got {x.shape}, {g.shape}, {t.shape}"
        )
    method = "ellipsoid_aligned"
    ref = reference_total_G(reference_field_G)
    fit = fit_ellipsoid_geometry(
        x, saturated=saturated, outlier_k=outlier_k, max_iterations=max_iterations
    )
    if fit is None:
        return no_ellipsoid(method, x, saturated)
    ell = ellipsoid_result(fit, x, ref, limits=limits, method=method)
    if ell.report.status == "MAG_CAL_FAILED" and ell.calibration == Calibration():
        return ell  # not even a matrix to align
    sym = ell.calibration.mag
    use = fit.inliers & usable_mask(g)
    ned = None
    if isinstance(reference_field_G, EarthField):
        ned = reference_field_G.ned_G
    elif reference_field_G is not None and np.asarray(reference_field_G).shape == (3,):
        ned = np.asarray(reference_field_G, dtype=np.float64)
    hh = fit_handheld(sym.apply(x), g, t, use, accel=accel_calibration, field_ned_G=ned)
    if hh is None:
        res = fit_ellipsoid_aligned(
            x,
            g,
            accel_calibration,
            reference_field_G,
            saturated=saturated,
            outlier_k=outlier_k,
            max_iterations=max_iterations,
            limits=limits,
        )
        note = "frame series too short or too uniform for the hand-held fit: single samples used"
        return CalibrationResult(
            res.calibration, replace(res.report, notes=(*res.report.notes, note))
        )
    mag = sym.then_rotate(hh.rotation)
    h_G = horizontal_field_G(reference_field_G, fit.radius_G * ell.report.scale_factor, hh.dip_deg)
    # The calibration's own predicted error seen as a residual (an unknown one: 89 deg).
    sigma = hh.heading_sigma_deg if math.isfinite(hh.heading_sigma_deg) else 89.0
    error_mG = 1000.0 * h_G * math.tan(math.radians(min(89.0, sigma)))
    fitness = math.hypot(fit.fitness_mG, error_mG)
    sanity = check_mag_calibration(
        mag,
        radius_G=fit.radius_G,
        fitness_mG=fitness,
        scale_factor=ell.report.scale_factor if ref is not None else None,
        offset_sd_mG=1000.0 * fit.offset_sd_G,
        matrix_sd=fit.matrix_sd,
        check_rotation=True,
        limits=limits,
    )
    if sanity.status is MagCalStatus.MAG_CAL_FAILED_ORIENTATION and not rotation_determined(
        hh.heading_sigma_deg, limits
    ):
        # (Its only failure: the rotation is checked last.) A hand that shook gravity out of
        # reach leaves a rotation of tens of degrees of noise: unknown, not wrong. The
        # operator is told to turn steadier, not to change COMPASS_ORIENT.
        sanity = SanityResult(MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH)
    notes = list(ell.report.notes)
    if sanity.status is MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH and fitness > fit.fitness_mG:
        # The magnetometer fits; what is off is the gravity the hand disturbed: say so first.
        notes.insert(0, motion_failure_reason(hh.heading_sigma_deg))
    notes.extend(r for r in sanity.reasons if r not in notes)
    notes.extend(hh.notes)
    notes.append(
        f"mag-to-accel rotation {hh.rotation_deg:.2f} deg, dip {hh.dip_deg:.2f} deg, "
        f"linear acceleration {hh.motion_g:.3f} g RMS"
    )
    g_before = gravity_spread_mg(g[use])
    g_after = gravity_spread_mg(hh.accel.apply(g[use]))
    report = replace(
        ell.report,
        status=sanity.status.name,
        fitness_mG=fitness,
        residual_mG=fit.fitness_mG,
        heading_error_deg=hh.heading_sigma_deg,
        tilt_error_deg=hh.tilt_sigma_deg,
        motion_g=hh.motion_g,
        window_s=hh.window_s,
        gravity_spread_before_mg=g_before[0],
        gravity_spread_after_mg=g_after[0],
        gravity_rms_before_mg=g_before[1],
        gravity_rms_after_mg=g_after[1],
        notes=tuple(notes),
    )
    return CalibrationResult(Calibration(mag=mag, accel=hh.accel), report)
