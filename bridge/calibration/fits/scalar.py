"""Scalar calibration: 9 parameters per sensor from |B| (or |g|) being constant.

The classic vector-magnetometer model of the scalar-calibration literature
(Merayo et al., the Ørsted/CHAMP scheme; the seed paper's "+-700 nT -> +-100 nT"):
each sensor axis has an offset, a sensitivity and -- because real axes are not
quite orthogonal -- a direction given by three small angles. With the sensor's
x axis defining the frame and y lying in its xy plane, the forward model is::

    raw - o = S @ P @ B          S = diag(s_x, s_y, s_z)
                                 P = [[1,      0,      0                   ],
                                      [sin a,  cos a,  0                   ],
                                      [sin b,  sin c,  sqrt(1-sin²b-sin²c)]]

so the correction ``B = L @ (raw - o)`` has a *lower-triangular* ``L = (S P)^-1``
(6 numbers) and the offset (3): 9 parameters, estimated by Levenberg-Marquardt
on the residuals ``|L (raw_i - o)| - R``. ``R`` is the known local field
(WMM, or a reference magnetometer) when given -- that fixes the absolute
scale -- else the radius of the initial sphere. For the accelerometer ``R`` is
1 g, always known.

What magnitudes cannot see: a common rotation of all three axes. The result
lives in the sensor's own "x-defined" frame, so mag-to-accel alignment is a
separate step (``bridge.calibration.fits.alignment``).

The module also holds small helpers the other fits share: input cleaning and
the field-spread statistics reported as ``+-half peak-to-peak`` and RMS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from bridge.core.calibration import (
    AffineCalibration,
    Calibration,
    CalibrationReport,
    CalibrationResult,
)
from bridge.core.sensor import GAUSS_TO_NT
from bridge.types import FloatArray

MIN_SAMPLES = 30  #: fewer than this and 9 parameters are not credibly determined
MIN_THICKNESS = 0.02  #: smallest / largest spread of the samples: below, they are planar
MAX_OFFSET_SIGMA = 0.01  #: offset 1-sigma, as a fraction of the radius, beyond which the fit fails
_TRI = ((0, 0), (1, 0), (1, 1), (2, 0), (2, 1), (2, 2))  # lower-triangular entries of L


# -- shared helpers --------------------------------------------------------------------


def finite_rows(values: npt.ArrayLike, name: str) -> tuple[FloatArray, int]:
    """``values`` as an (N, 3) float array without non-finite rows, and how many were dropped.

    Raises ``ValueError`` if it is not (N, 3)-shaped.
    """
    a = np.asarray(values, dtype=np.float64)
    if a.ndim == 1 and a.shape == (3,):
        a = a[np.newaxis]
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be an (N, 3) array, got shape {a.shape}")
    ok = np.all(np.isfinite(a), axis=1)
    return a[ok], int(a.shape[0] - int(ok.sum()))


def spread_stats(norms: npt.ArrayLike) -> tuple[float, float]:
    """``(half peak-to-peak, RMS about the mean)`` of a set of magnitudes (NaN if empty)."""
    n = np.asarray(norms, dtype=np.float64)
    if n.size == 0:
        return math.nan, math.nan
    return float(np.ptp(n) / 2.0), float(np.std(n))


def field_spread_nT(mag_G: npt.ArrayLike) -> tuple[float, float]:
    """Total-field spread of (N, 3) vectors in gauss: ``(+-half p-p, RMS)`` in nT."""
    hp, rms = spread_stats(np.linalg.norm(np.asarray(mag_G, dtype=np.float64), axis=-1))
    return hp * GAUSS_TO_NT, rms * GAUSS_TO_NT


def gravity_spread_mg(acc_g: npt.ArrayLike) -> tuple[float, float]:
    """|g| spread of (N, 3) vectors in g: ``(+-half p-p, RMS about 1 g)`` in mg."""
    n = np.linalg.norm(np.asarray(acc_g, dtype=np.float64), axis=-1)
    if n.size == 0:
        return math.nan, math.nan
    return float(np.ptp(n) / 2.0 * 1000.0), float(np.sqrt(np.mean((n - 1.0) ** 2)) * 1000.0)


def failed_result(
    method: str, reason: str, *, n_samples: int = 0, n_rejected: int = 0
) -> CalibrationResult:
    """A failed fit: factory (identity) parameters -- never NaN -- and the reason in the notes."""
    return CalibrationResult(
        Calibration(),
        CalibrationReport(
            method=method,
            status="MAG_CAL_FAILED",
            n_samples=n_samples,
            n_rejected=n_rejected,
            notes=(reason,),
        ),
    )


def field_report(
    method: str,
    x: FloatArray,
    after: FloatArray,
    radius: float,
    *,
    n_samples: int,
    n_rejected: int,
    **more: Any,
) -> CalibrationReport:
    """The report of a field fit that maps the samples ``x`` (gauss) to ``after`` on a sphere
    of ``radius``: its fitness (RMS of |after| - radius, mG) and the field's spread before
    and after (nT); ``more``: the report's other fields."""
    norms = np.linalg.norm(after, axis=1)
    b_hp, b_rms = field_spread_nT(x)
    a_hp, a_rms = field_spread_nT(after)
    return CalibrationReport(
        method=method,
        n_samples=n_samples,
        n_rejected=n_rejected,
        fitness_mG=float(np.sqrt(np.mean((norms - radius) ** 2))) * 1000.0,
        radius_G=radius,
        field_spread_before_nT=b_hp,
        field_spread_after_nT=a_hp,
        field_rms_before_nT=b_rms,
        field_rms_after_nT=a_rms,
        **more,
    )


# -- the scalar model -------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ScalarParameters:
    """The physical 9 parameters behind a lower-triangular correction.

    ``sensitivity`` is per axis relative to the nominal transfer (1.0 = nominal);
    ``nonorth_deg`` = (a, b, c): y-axis tilt towards x, z-axis tilts towards x and y.
    """

    offset: tuple[float, float, float]
    sensitivity: tuple[float, float, float]
    nonorth_deg: tuple[float, float, float]

    @classmethod
    def from_calibration(cls, cal: AffineCalibration) -> ScalarParameters:
        """Decompose ``cal`` (its matrix must be lower-triangular up to rounding)."""
        F = np.linalg.inv(cal.matrix_array)  # forward: raw - o = F @ B
        s = np.linalg.norm(F, axis=1)
        P = F / s[:, np.newaxis]
        a = math.degrees(math.asin(float(np.clip(P[1, 0], -1, 1))))
        b = math.degrees(math.asin(float(np.clip(P[2, 0], -1, 1))))
        c = math.degrees(math.asin(float(np.clip(P[2, 1], -1, 1))))
        return cls(cal.offset, (float(s[0]), float(s[1]), float(s[2])), (a, b, c))

    def to_calibration(self) -> AffineCalibration:
        """The correction ``L (raw - o)`` these parameters describe."""
        a, b, c = (math.radians(v) for v in self.nonorth_deg)
        zz = 1.0 - math.sin(b) ** 2 - math.sin(c) ** 2
        if zz <= 0.0:
            raise ValueError("non-orthogonality angles too large")
        P = np.array(
            [
                [1.0, 0.0, 0.0],
                [math.sin(a), math.cos(a), 0.0],
                [math.sin(b), math.sin(c), math.sqrt(zz)],
            ]
        )
        return AffineCalibration.from_arrays(
            self.offset, np.linalg.inv(np.diag(self.sensitivity) @ P)
        )


def _lower_factor(A: FloatArray) -> FloatArray:
    """Lower-triangular ``L`` with ``L.T @ L = A`` (A symmetric positive definite).

    Cholesky gives ``A = C C.T`` with C lower; flipping the index order turns it
    into the "upper-lower" factorisation we need. ``A`` may be a stack (B, 3, 3): each
    matrix factorised as alone (``LinAlgError`` if any is not positive definite).
    """
    J = np.eye(3)[::-1]
    C = np.linalg.cholesky(J @ A @ J)
    U = J @ C @ J  # upper triangular, A = U U.T
    return np.swapaxes(U, -1, -2)


def _algebraic_ellipsoid(x: FloatArray) -> tuple[FloatArray, FloatArray] | None:
    """Least-squares quadric through the points: ``(centre, A)`` with (x-c).T A (x-c) = 1.

    Returns ``None`` when the quadric is not an ellipsoid (too little rotation in the data).
    """
    mu = x.mean(axis=0)
    sc = float(np.max(np.abs(x - mu))) or 1.0
    y = (x - mu) / sc  # condition the design matrix
    X, Y, Z = y[:, 0], y[:, 1], y[:, 2]
    D = np.column_stack(
        [X * X, Y * Y, Z * Z, 2 * X * Y, 2 * X * Z, 2 * Y * Z, 2 * X, 2 * Y, 2 * Z, np.ones_like(X)]
    )
    try:
        _, sv, Vt = np.linalg.svd(D, full_matrices=False)
    except np.linalg.LinAlgError:
        return None
    if sv[-2] <= 1e-12 * sv[0]:
        return None  # more than one quadric fits: degenerate data
    v = Vt[-1]
    Q = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
    q = v[6:9]
    k = v[9]
    if np.linalg.det(Q) == 0.0:
        return None
    if np.trace(Q) < 0:  # the null vector's sign is arbitrary
        Q, q, k = -Q, -q, -k
    try:
        c = -np.linalg.solve(Q, q)
    except np.linalg.LinAlgError:
        return None
    f = float(c @ Q @ c - k)
    if not np.all(np.linalg.eigvalsh(Q) > 0) or f <= 0:
        return None
    A = Q / f / (sc * sc)
    return mu + c * sc, A


@dataclass(frozen=True, slots=True)
class _ScalarFit:
    cal: AffineCalibration
    radius: float
    iterations: int
    ok: bool
    reason: str


def _fit_magnitude(x: FloatArray, radius: float | None, max_iter: int = 100) -> _ScalarFit:
    """LM fit of ``|L (x - o)| = R`` with L lower-triangular (see module docstring)."""
    # Samples from rotations about one axis only lie in a plane: the offset and
    # scale along its normal are then unobservable, whatever the noise says.
    sv = np.linalg.svd(x - x.mean(axis=0), compute_uv=False)
    if not sv[-1] > MIN_THICKNESS * sv[0]:
        return _ScalarFit(
            AffineCalibration(),
            math.nan,
            0,
            False,
            "samples lie in a plane: rotate about more axes",
        )
    init = _algebraic_ellipsoid(x)
    if init is None:
        # A sphere start still lets LM work when the data is merely thin.
        c = (x.max(axis=0) + x.min(axis=0)) / 2.0
        half = (x.max(axis=0) - x.min(axis=0)) / 2.0
        if np.any(half <= 0):
            return _ScalarFit(AffineCalibration(), math.nan, 0, False, "no variation on an axis")
        A = np.diag(1.0 / half**2)
    else:
        c, A = init
    L = _lower_factor(A)  # |L (x - c)| ~ 1
    r0 = float(np.mean(np.linalg.norm((x - c) @ L.T, axis=1)))
    R = float(radius) if radius is not None else float(np.mean(np.linalg.norm(x - c, axis=1)))
    L = L * (R / r0)
    p = np.concatenate([c, [L[i, j] for i, j in _TRI]])

    def unpack(p: FloatArray) -> tuple[FloatArray, FloatArray]:
        M = np.zeros((3, 3))
        for k, (i, j) in enumerate(_TRI):
            M[i, j] = p[3 + k]
        return p[:3], M

    def residuals(p: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        o, M = unpack(p)
        v = x - o
        u = v @ M.T
        n = np.linalg.norm(u, axis=1)
        return n - R, v, u, n

    res, v, u, n = residuals(p)
    cost = float(res @ res)
    lam = 1e-3
    it = 0
    JtJ = np.eye(9)
    for it in range(1, max_iter + 1):  # noqa: B007 - "it" is reported
        _, M = unpack(p)
        un = u / np.where(n > 0, n, 1.0)[:, np.newaxis]
        J = np.empty((x.shape[0], 9))
        J[:, :3] = -(un @ M)
        for k, (i, j) in enumerate(_TRI):
            J[:, 3 + k] = un[:, i] * v[:, j]
        JtJ = J.T @ J
        g = J.T @ res
        improved = False
        for _ in range(20):  # bounded damping search
            H = JtJ + lam * np.diag(np.diag(JtJ) + 1e-30)
            try:
                step = np.linalg.solve(H, -g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            p_new = p + step
            r_new, v_new, u_new, n_new = residuals(p_new)
            c_new = float(r_new @ r_new)
            if math.isfinite(c_new) and c_new <= cost:
                rel = (cost - c_new) / max(cost, 1e-300)
                p, res, v, u, n, cost = p_new, r_new, v_new, u_new, n_new, c_new
                lam = max(lam / 10.0, 1e-12)
                improved = True
                break
            lam *= 10.0
        if not improved or rel < 1e-12 or float(np.max(np.abs(step))) < 1e-12 * max(1.0, R):
            break
    o, M = unpack(p)
    # |L v| does not change if a row of L flips sign: keep the diagonal positive.
    M = M * np.sign(np.where(np.diag(M) == 0, 1.0, np.diag(M)))[:, np.newaxis]
    ev = np.linalg.eigvalsh(JtJ)
    if not np.all(np.isfinite(p)) or ev[0] <= 1e-10 * ev[-1]:
        return _ScalarFit(
            AffineCalibration(), R, it, False, "parameters not observable: too little rotation"
        )
    # 1-sigma uncertainty of the offsets from the fit's own covariance
    dof = max(x.shape[0] - 9, 1)
    sigma_o = np.sqrt(np.diag(np.linalg.inv(JtJ))[:3] * cost / dof)
    if not float(sigma_o.max()) < MAX_OFFSET_SIGMA * R:
        return _ScalarFit(
            AffineCalibration(), R, it, False, "offsets not determined: too little rotation"
        )
    try:
        cal = AffineCalibration.from_arrays(o, M)
    except ValueError as e:
        return _ScalarFit(AffineCalibration(), R, it, False, str(e))
    return _ScalarFit(cal, R, it, True, "")


def _magnitude_report(
    method: str, x: FloatArray, fit: _ScalarFit, n_rejected: int, *, gravity: bool
) -> CalibrationReport:
    after = fit.cal.apply(x)
    if gravity:
        norms = np.linalg.norm(after, axis=1)
        fitness = float(np.sqrt(np.mean((norms - fit.radius) ** 2)))
        b_hp, b_rms = gravity_spread_mg(x)
        a_hp, a_rms = gravity_spread_mg(after)
        return CalibrationReport(
            method=method,
            n_samples=int(x.shape[0]),
            n_rejected=n_rejected,
            radius_G=math.nan,
            gravity_spread_before_mg=b_hp,
            gravity_spread_after_mg=a_hp,
            gravity_rms_before_mg=b_rms,
            gravity_rms_after_mg=a_rms,
            iterations=fit.iterations,
            notes=(f"|g| residual RMS {fitness * 1000.0:.2f} mg",),
        )
    return field_report(
        method,
        x,
        after,
        fit.radius,
        n_samples=int(x.shape[0]),
        n_rejected=n_rejected,
        iterations=fit.iterations,
    )


def _describe(cal: AffineCalibration, unit: str) -> str:
    sp = ScalarParameters.from_calibration(cal)
    return (
        f"offset {unit} ({sp.offset[0]:+.4f}, {sp.offset[1]:+.4f}, {sp.offset[2]:+.4f}); "
        f"sensitivity ({sp.sensitivity[0]:.4f}, {sp.sensitivity[1]:.4f}, {sp.sensitivity[2]:.4f}); "
        f"non-orthogonality deg ({sp.nonorth_deg[0]:+.3f}, {sp.nonorth_deg[1]:+.3f}, {sp.nonorth_deg[2]:+.3f})"
    )


def fit_scalar_mag(mag_G: npt.ArrayLike, reference_G: float | None = None) -> CalibrationResult:
    """Scalar calibration of the magnetometer from (N, 3) nominal-gauss samples.

    ``reference_G`` is the known local total field (WMM); without it the scale
    is that of the data's own sphere. The accelerometer part of the result is
    the identity. Non-finite rows are dropped and counted; too few samples or
    too little rotation give status MAG_CAL_FAILED with identity parameters.
    """
    x, dropped = finite_rows(mag_G, "mag_G")
    if reference_G is not None and not (math.isfinite(reference_G) and reference_G > 0):
        raise ValueError(f"reference_G must be a positive field strength, got {reference_G!r}")
    if x.shape[0] < MIN_SAMPLES:
        return failed_result(
            "scalar",
            f"too few samples: {x.shape[0]} < {MIN_SAMPLES}",
            n_samples=x.shape[0],
            n_rejected=dropped,
        )
    fit = _fit_magnitude(x, reference_G)
    if not fit.ok:
        return failed_result("scalar", fit.reason, n_samples=x.shape[0], n_rejected=dropped)
    report = _magnitude_report("scalar", x, fit, dropped, gravity=False)
    report = replace(report, notes=(*report.notes, "mag " + _describe(fit.cal, "G")))
    return CalibrationResult(Calibration(mag=fit.cal), report)


def fit_scalar_accel(acc_g: npt.ArrayLike) -> CalibrationResult:
    """Scalar calibration of the accelerometer from (N, 3) still samples (|g| = 1).

    The samples must be taken at rest in many orientations; moving samples
    violate |g| = 1 and bias the fit. The magnetometer part is the identity.
    """
    x, dropped = finite_rows(acc_g, "acc_g")
    if x.shape[0] < MIN_SAMPLES:
        return failed_result(
            "scalar",
            f"too few samples: {x.shape[0]} < {MIN_SAMPLES}",
            n_samples=x.shape[0],
            n_rejected=dropped,
        )
    fit = _fit_magnitude(x, 1.0)
    if not fit.ok:
        return failed_result("scalar", fit.reason, n_samples=x.shape[0], n_rejected=dropped)
    report = _magnitude_report("scalar", x, fit, dropped, gravity=True)
    report = replace(report, notes=(*report.notes, "accel " + _describe(fit.cal, "g")))
    return CalibrationResult(Calibration(accel=fit.cal), report)


def fit_scalar(
    mag_G: npt.ArrayLike, acc_g: npt.ArrayLike, reference_G: float | None = None
) -> CalibrationResult:
    """Scalar calibration of both sensors; one report with field and gravity spreads.

    The two sensors come out each in its own frame (x axis = the sensor's x);
    align them afterwards if heading accuracy matters (``alignment.py``). If
    either fit fails the result is failed (identity parameters), naming which.
    """
    m = fit_scalar_mag(mag_G, reference_G)
    a = fit_scalar_accel(acc_g)
    if not m.report.ok or not a.report.ok:
        reasons = [f"mag: {n}" for n in m.report.notes] if not m.report.ok else []
        reasons += [f"accel: {n}" for n in a.report.notes] if not a.report.ok else []
        return CalibrationResult(
            Calibration(),
            replace(m.report, status="MAG_CAL_FAILED", notes=tuple(reasons)),
        )
    r = replace(
        m.report,
        gravity_spread_before_mg=a.report.gravity_spread_before_mg,
        gravity_spread_after_mg=a.report.gravity_spread_after_mg,
        gravity_rms_before_mg=a.report.gravity_rms_before_mg,
        gravity_rms_after_mg=a.report.gravity_rms_after_mg,
        iterations=m.report.iterations + a.report.iterations,
        notes=m.report.notes + a.report.notes,
    )
    return CalibrationResult(Calibration(mag=m.calibration.mag, accel=a.calibration.accel), r)
