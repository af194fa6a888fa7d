"""Hard-iron + symmetric soft-iron ellipsoid fit (what ArduPilot's and PX4's compass calibrations fit).

Model: the raw samples ``x`` (nominal gauss) lie on an ellipsoid
``|S (x - o)| = r`` with ``o`` the hard-iron offset and ``S`` a symmetric
positive-definite soft-iron matrix. A symmetric ``S`` is all COMPASS_DIA_* /
COMPASS_ODI_* can hold; it cannot express the *rotational* part of the sensor
error (axis non-orthogonality, mag-to-accel misalignment) -- that is what
:mod:`bridge.calibration.fits.alignment` adds on top.

Steps:

1. drop non-finite and saturated samples;
2. initial solution: algebraic least-squares quadric fit (data centred and
   scaled for conditioning), falling back to a linear sphere fit when the
   quadric is not an ellipsoid (poor coverage, planar data);
3. Levenberg-Marquardt on the geometric residual ``|S (x - o)| - r`` with the
   radius held (ArduPilot's ellipsoid step: 3 offsets + 6 matrix elements);
4. drop samples whose residual is beyond ``k`` robust sigmas and refine again;
5. normalise ``S`` to unit determinant, so ``r`` is the radius of the sphere
   with the ellipsoid's volume: the field strength the sensor sees at nominal
   gain (ArduPilot's ``_params.radius``);
6. with a reference field (WMM), scale to it: ``scale_factor = |B_wmm| / r``
   (ArduPilot's ``fix_radius``; outside 1/1.5..1.5 it is MAG_CAL_FAILED_RADIUS).

``fitness_mG`` is MAG_CAL_REPORT.fitness: ``sqrt(mean((r - |S (x - o)|)^2))``
in milligauss, before the WMM scale (``CompassCalibrator::update_cal_report``
reports ``sqrtf`` of the mean squared residual).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from bridge.calibration.fits.coverage import coverage
from bridge.calibration.fits.samples import DEFAULT_OUTLIER_K, inlier_mask, usable_mask
from bridge.calibration.fits.sanity import SanityLimits, check_mag_calibration
from bridge.calibration.fits.scalar import failed_result, field_spread_nT
from bridge.core.calibration import (
    AffineCalibration,
    Calibration,
    CalibrationReport,
    CalibrationResult,
)
from bridge.core.wmm import EarthField
from bridge.types import BoolArray, FloatArray

ReferenceField = EarthField | float | npt.ArrayLike | None

MIN_SAMPLES = 12  #: 9 unknowns; a few spare so one bad sample cannot decide the fit
DEFAULT_MAX_ITERATIONS = 40


def reference_total_G(reference: ReferenceField) -> float | None:
    """Total field strength (gauss) of a reference: an EarthField, a number, or an NED vector.

    ``None`` passes through; a non-finite or non-positive value raises ``ValueError``.
    """
    if reference is None:
        return None
    if isinstance(reference, EarthField):
        total = reference.total_G
    else:
        a = np.asarray(reference, dtype=np.float64)
        if a.shape == ():
            total = float(a)
        elif a.shape == (3,):
            total = float(np.linalg.norm(a))
        else:
            raise ValueError(
                f"reference field must be a number or an NED 3-vector, got shape {a.shape}"
            )
    if not (math.isfinite(total) and total > 0.0):
        raise ValueError(f"reference field strength must be positive, got {total!r}")
    return total


def _sym(params: npt.ArrayLike) -> FloatArray:
    """6 parameters (xx, yy, zz, xy, xz, yz) -> symmetric 3x3."""
    s = np.asarray(params, dtype=np.float64)
    return np.array([[s[0], s[3], s[4]], [s[3], s[1], s[5]], [s[4], s[5], s[2]]])


def fit_sphere(x: npt.ArrayLike) -> tuple[FloatArray, float] | None:
    """Linear least-squares sphere: ``|x|^2 = 2 c.x + (r^2 - |c|^2)``; None when degenerate."""
    p = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] < 4:
        return None
    mu = p.mean(axis=0)
    q = p - mu  # centring keeps the normal equations well conditioned
    A = np.column_stack([2.0 * q, np.ones(len(q))])
    b = np.sum(q * q, axis=1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = sol[:3]
    r2 = float(sol[3] + c @ c)
    if not (np.all(np.isfinite(sol)) and r2 > 0.0):
        return None
    return c + mu, math.sqrt(r2)


def fit_quadric(x: npt.ArrayLike) -> tuple[FloatArray, FloatArray] | None:
    """Algebraic ellipsoid: centre ``c`` and positive-definite ``Q`` with ``(x-c)' Q (x-c) = 1``.

    Total least squares on the 10 quadric coefficients (smallest eigenvector of
    the scatter matrix) after centring and scaling the data. Returns None when
    the best quadric is not an ellipsoid.
    """
    p = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] < 10:
        return None
    mu = p.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((p - mu) ** 2, axis=1))))
    if not (math.isfinite(scale) and scale > 0.0):
        return None
    q = (p - mu) / scale
    X, Y, Z = q[:, 0], q[:, 1], q[:, 2]
    D = np.column_stack(
        [X * X, Y * Y, Z * Z, 2 * X * Y, 2 * X * Z, 2 * Y * Z, 2 * X, 2 * Y, 2 * Z, np.ones(len(q))]
    )
    _, V = np.linalg.eigh(D.T @ D)
    v = V[:, 0]
    A = _sym(v[:6])
    b = v[6:9]
    c0 = v[9]
    try:
        centre = -np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return None
    k = float(centre @ A @ centre - c0)
    if not (math.isfinite(k) and k != 0.0):
        return None
    Q = A / k
    if not np.all(np.linalg.eigvalsh(Q) > 0.0):
        return None
    return mu + scale * centre, Q / scale**2


def _sqrtm_spd(Q: FloatArray) -> FloatArray:
    w, V = np.linalg.eigh(Q)
    return (V * np.sqrt(w)) @ V.T


def _row_norms(v: FloatArray) -> FloatArray:
    """``|v_i|`` of an (N, 3) array (einsum: several times faster than ``linalg.norm``)."""
    return np.sqrt(np.einsum("ij,ij->i", v, v))


_Parts = tuple[FloatArray, FloatArray, FloatArray]


def _parts(x: FloatArray, o: FloatArray, S: FloatArray) -> _Parts:
    """``x - o``, its rows through ``S`` and their lengths: what the cost and the Jacobian
    at ``(o, S)`` are made of."""
    d = x - o
    y = d @ S  # S is symmetric: rows are (S d_i)'
    return d, y, _row_norms(y)


def _residual_jacobian(
    x: FloatArray, o: FloatArray, S: FloatArray, radius: float, parts: _Parts | None = None
) -> tuple[FloatArray, FloatArray]:
    """Residuals and Jacobian at ``(o, S)``; ``parts``: its :func:`_parts`, if made already."""
    d, y, n = _parts(x, o, S) if parts is None else parts
    n = np.where(n > 0.0, n, 1e-300)
    u = y / n[:, None]
    J = np.empty((len(x), 9))
    J[:, 0:3] = -(u @ S)  # d|S d|/do = -S u
    J[:, 3:6] = u * d  # diagonal elements
    J[:, 6] = u[:, 0] * d[:, 1] + u[:, 1] * d[:, 0]
    J[:, 7] = u[:, 0] * d[:, 2] + u[:, 2] * d[:, 0]
    J[:, 8] = u[:, 1] * d[:, 2] + u[:, 2] * d[:, 1]
    return n - radius, J


def _cost(parts: _Parts, radius: float) -> float:
    r = parts[2] - radius
    return float(r @ r)


def refine_ellipsoid(
    x: npt.ArrayLike,
    offset: npt.ArrayLike,
    matrix: npt.ArrayLike,
    radius: float,
    *,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
) -> tuple[FloatArray, FloatArray, int]:
    """Levenberg-Marquardt on ``|S (x - o)| - radius`` (radius held); returns (o, S, iterations)."""
    p = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    o = np.asarray(offset, dtype=np.float64).reshape(3).copy()
    S = np.asarray(matrix, dtype=np.float64).reshape(3, 3)
    S = (S + S.T) / 2.0
    # The parts of the last cost taken are the next Jacobian's (the same numbers): kept.
    parts = _parts(p, o, S)
    cost = _cost(parts, radius)
    lam = 1e-3
    it = 0
    rel = math.inf
    for it in range(1, max_iterations + 1):  # noqa: B007 - the count is reported
        r, J = _residual_jacobian(p, o, S, radius, parts)
        JTJ = J.T @ J
        g = J.T @ r
        dJ = np.diag(JTJ).copy()
        dJ[dJ <= 0.0] = 1e-12
        improved = False
        while lam < 1e12:
            try:
                step = np.linalg.solve(JTJ + lam * np.diag(dJ), -g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            o_new = o + step[:3]
            S_new = S + _sym(step[3:])
            new_parts = _parts(p, o_new, S_new)
            new_cost = _cost(new_parts, radius)
            if math.isfinite(new_cost) and new_cost < cost:
                rel = (cost - new_cost) / max(cost, 1e-300)
                o, S, cost, parts = o_new, S_new, new_cost, new_parts
                lam = max(lam / 10.0, 1e-12)
                improved = True
                break
            lam *= 10.0
        # Converged when no step helps or the last one gained nothing measurable.
        if not improved or rel < 1e-12:
            break
    return o, S, it


@dataclass(frozen=True, slots=True)
class EllipsoidFit:
    """Geometric result of the ellipsoid fit, before any WMM scaling.

    ``matrix`` is symmetric with unit determinant and ``|matrix (x - offset)|``
    is close to ``radius_G`` for the inliers; ``inliers`` flags the input rows
    used (False for non-finite, saturated and outlier samples). ``offset_sd_G``
    and ``matrix_sd`` are the largest one-sigma uncertainties of the offsets and
    of the matrix elements implied by the residuals and the sample geometry.
    """

    offset: FloatArray
    matrix: FloatArray
    radius_G: float
    fitness_mG: float
    iterations: int
    inliers: BoolArray
    initial: str
    n_outliers: int
    offset_sd_G: float = math.nan
    matrix_sd: float = math.nan

    def residuals_G(self, x: npt.ArrayLike) -> FloatArray:
        """``|matrix (x - offset)| - radius`` for each row of ``x`` (gauss)."""
        p = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        return _row_norms((p - self.offset) @ self.matrix) - self.radius_G


def fit_ellipsoid_geometry(
    mag_G: npt.ArrayLike,
    *,
    saturated: npt.ArrayLike | None = None,
    outlier_k: float | None = DEFAULT_OUTLIER_K,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
) -> EllipsoidFit | None:
    """The fit itself (steps 1-5 of the module doc); None when the data cannot define an ellipsoid.

    ``outlier_k=None`` disables outlier rejection.
    """
    x_all = np.asarray(mag_G, dtype=np.float64)
    usable = usable_mask(x_all, saturated)
    x = x_all[usable]
    if x.shape[0] < MIN_SAMPLES:
        return None
    initial = "ellipsoid"
    quad = fit_quadric(x)
    if quad is not None:
        o0, Q = quad
        radius = float(np.linalg.det(Q)) ** (-1.0 / 6.0)  # volume-equivalent radius
        S0 = radius * _sqrtm_spd(Q)
    else:
        sph = fit_sphere(x)
        if sph is None:
            return None
        initial = "sphere"
        o0, radius = sph
        S0 = np.eye(3)
    o, S, iters = refine_ellipsoid(x, o0, S0, radius, max_iterations=max_iterations)

    inl = np.ones(x.shape[0], dtype=bool)
    n_out = 0
    if outlier_k is not None:
        res = _row_norms((x - o) @ S) - radius
        inl = inlier_mask(res, outlier_k)
        n_out = int(np.count_nonzero(~inl))
        if n_out and np.count_nonzero(inl) >= MIN_SAMPLES:
            o, S, more = refine_ellipsoid(x[inl], o, S, radius, max_iterations=max_iterations)
            iters += more
        elif n_out:
            return None
    det = float(np.linalg.det(S))
    if not (math.isfinite(det) and det > 0.0):
        return None
    k = det ** (1.0 / 3.0)
    S = S / k
    radius = radius / k
    res, J = _residual_jacobian(x[inl], o, S, radius)
    mse = float(np.mean(res * res))
    fitness = 1000.0 * math.sqrt(mse)
    # Parameter uncertainty from the normal matrix: large when the samples cover
    # too little of the sphere for 9 parameters (the fit then "succeeds" on noise).
    try:
        sd = np.sqrt(np.clip(np.diag(np.linalg.inv(J.T @ J)), 0.0, None) * mse)
    except np.linalg.LinAlgError:
        sd = np.full(9, np.inf)
    inliers = np.zeros(x_all.shape[0], dtype=bool)
    inliers[np.flatnonzero(usable)[inl]] = True
    return EllipsoidFit(
        offset=o,
        matrix=S,
        radius_G=float(radius),
        fitness_mG=fitness,
        iterations=iters,
        inliers=inliers,
        initial=initial,
        n_outliers=n_out,
        offset_sd_G=float(np.max(sd[:3])),
        matrix_sd=float(np.max(sd[3:])),
    )


def fit_ellipsoid(
    mag_G: npt.ArrayLike,
    *,
    reference_field_G: ReferenceField = None,
    saturated: npt.ArrayLike | None = None,
    outlier_k: float | None = DEFAULT_OUTLIER_K,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
    limits: SanityLimits | None = None,
    accel: AffineCalibration | None = None,
) -> CalibrationResult:
    """Hard iron + symmetric soft iron from raw magnetometer samples (N, 3) in nominal gauss.

    ``reference_field_G`` (EarthField, total in gauss, or NED vector) scales the
    result to the WMM field strength; without it the corrected field has the
    fitted radius. ``saturated`` flags samples to ignore. ``accel`` is carried
    into the returned :class:`Calibration` unchanged (identity when None).
    The report's status comes from :func:`bridge.calibration.fits.sanity.check_mag_calibration`.
    Raises ``ValueError`` only for malformed arguments (shape, bad reference);
    data that cannot be fitted gives a MAG_CAL_FAILED result.
    """
    x = np.asarray(mag_G, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"mag_G must be (N, 3), got shape {x.shape}")
    ref = reference_total_G(reference_field_G)
    fit = fit_ellipsoid_geometry(
        x, saturated=saturated, outlier_k=outlier_k, max_iterations=max_iterations
    )
    if fit is None:
        return no_ellipsoid("ellipsoid", x, saturated, "(too few or planar)")
    return ellipsoid_result(fit, x, ref, limits=limits, accel=accel)


def no_ellipsoid(
    method: str, mag_G: FloatArray, saturated: npt.ArrayLike | None, detail: str = ""
) -> CalibrationResult:
    """The failed result of samples that define no ellipsoid (counted, identity parameters)."""
    n_ok = int(np.count_nonzero(usable_mask(mag_G, saturated)))
    reason = "samples do not define an ellipsoid" + (f" {detail}" if detail else "")
    return failed_result(method, reason, n_samples=n_ok, n_rejected=mag_G.shape[0] - n_ok)


def ellipsoid_result(
    fit: EllipsoidFit,
    mag_G: FloatArray,
    reference_total: float | None,
    *,
    limits: SanityLimits | None = None,
    accel: AffineCalibration | None = None,
    method: str = "ellipsoid",
) -> CalibrationResult:
    """Turn an :class:`EllipsoidFit` into a scaled calibration with its report."""
    notes: list[str] = []
    scale = 1.0
    if reference_total is not None:
        scale = reference_total / fit.radius_G
    else:
        notes.append("no reference field: radius not scaled to WMM (MAG_CAL_REPORT.scale_factor 0)")
    if fit.initial == "sphere":
        notes.append("algebraic ellipsoid failed; started from a sphere fit")
    x = mag_G[fit.inliers]
    try:
        mag = AffineCalibration.from_arrays(fit.offset, scale * fit.matrix)
    except ValueError as exc:
        return failed_result(
            method,
            str(exc),
            n_samples=int(x.shape[0]),
            n_rejected=int(np.count_nonzero(~fit.inliers)),
        )
    sanity = check_mag_calibration(
        mag,
        radius_G=fit.radius_G,
        fitness_mG=fit.fitness_mG,
        scale_factor=scale if reference_total is not None else None,
        offset_sd_mG=1000.0 * fit.offset_sd_G,
        matrix_sd=fit.matrix_sd,
        limits=limits,
    )
    notes.extend(sanity.reasons)
    cov = coverage(x, fit.offset, fit.matrix)
    before_hp, before_rms = field_spread_nT(x)
    after_hp, after_rms = field_spread_nT(mag.apply(x))
    report = CalibrationReport(
        method=method,
        status=sanity.status.name,
        n_samples=int(x.shape[0]),
        n_rejected=int(np.count_nonzero(~fit.inliers)),
        fitness_mG=fit.fitness_mG,
        radius_G=fit.radius_G,
        scale_factor=scale,
        field_spread_before_nT=before_hp,
        field_spread_after_nT=after_hp,
        field_rms_before_nT=before_rms,
        field_rms_after_nT=after_rms,
        coverage_pct=cov.percent,
        iterations=fit.iterations,
        notes=tuple(notes),
    )
    return CalibrationResult(Calibration(mag=mag, accel=accel or AffineCalibration()), report)


def with_method(result: CalibrationResult, method: str) -> CalibrationResult:
    """The same result under another method name (registry aliases)."""
    return CalibrationResult(result.calibration, replace(result.report, method=method))
