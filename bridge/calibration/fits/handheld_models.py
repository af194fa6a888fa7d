"""The hand-held fit's two models and their Gauss-Newton solvers (window means in, a candidate out).

:mod:`bridge.calibration.fits.handheld` picks the window and judges the candidates
(jackknife); this module holds what one solve does: the joint model of the
accelerometer calibration and the rotation (``(P (x - o)) . m = sin(dip)`` with
``|g| = 1``), and the rotation-only model for a known accelerometer. See that
module's docstring for the models.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence

import numpy as np

from bridge.calibration.fits.scalar import _lower_factor
from bridge.core.calibration import AffineCalibration
from bridge.core.geometry import rotvec_to_dcm
from bridge.types import BoolArray, FloatArray

#: Smallest per-row eigenvalue of the normal matrix (unit vectors): below, an axis is unobserved.
_MIN_INFORMATION = 1e-4


def _vee(M: FloatArray) -> FloatArray:
    return np.stack([M[..., 2, 1], M[..., 0, 2], M[..., 1, 0]], axis=-1)


# -- the two models --------------------------------------------------------------------

_JOINT_FEATURES = 21  # m (x) x (9), m (3), x (3), x x^T (6 unique)
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _joint_features(m_unit: FloatArray, x: FloatArray) -> FloatArray:
    f = np.empty((x.shape[0], _JOINT_FEATURES))
    f[:, :9] = (m_unit[:, :, None] * x[:, None, :]).reshape(-1, 9)
    f[:, 9:12] = m_unit
    f[:, 12:15] = x
    for k, (i, j) in enumerate(_UPPER):
        f[:, 15 + k] = x[:, i] * x[:, j]
    return f


Candidate = tuple[AffineCalibration, FloatArray, float]  # accel, rotation, sin(dip)
#: Several sets of rows (each with its 1: _with_one) and their _gram in, a candidate
#: (or None) for each out.
Solver = Callable[[Sequence[FloatArray], Sequence[FloatArray]], "list[Candidate | None]"]
Finisher = Callable[[Candidate], Candidate]


def _second_moments(rows: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Window means of ``x`` (n, 3) and of ``x x^T`` (n, 3, 3) from the joint features."""
    mu = rows[:, 12:15]
    S = np.empty((rows.shape[0], 3, 3))
    for k, (i, j) in enumerate(_UPPER):
        S[:, i, j] = S[:, j, i] = rows[:, 15 + k]
    return mu, S


def _magnitude_moment(mu: FloatArray, S: FloatArray, o: FloatArray) -> FloatArray:
    """``M`` with ``tr(L^T L M)`` the window mean of ``|L (x - o)|^2`` (exact for any turn);
    ``o`` (n, 3): each row's own offset."""
    return np.asarray(
        S
        - mu[:, :, None] * o[:, None, :]
        - o[:, :, None] * mu[:, None, :]
        + o[:, :, None] * o[:, None, :],
        dtype=np.float64,
    )


def _with_one(rows: FloatArray) -> FloatArray:
    """The rows with a constant 1 appended (``F``): every model here is linear in ``F``."""
    return np.concatenate([rows, np.ones((rows.shape[0], 1))], axis=1)


def _gram(rows: FloatArray) -> FloatArray:
    """``F^T F`` (:func:`_with_one`): what ``J^T J`` and the linear start need of the rows."""
    return gram_of(_with_one(rows))


def gram_of(F: FloatArray) -> FloatArray:
    """:func:`_gram` of rows given with their 1 (``F``, as :func:`_with_one` makes them)."""
    return np.asarray(F.T @ F, dtype=np.float64)


_DOT_SIGN = np.array([1.0] * 9 + [-1.0] * 3)
_DOT_SIGNS = _DOT_SIGN[:, None] * _DOT_SIGN[None, :]


def _linear_joint(gram: FloatArray) -> Candidate | None:
    """Closed-form start from the rows' :func:`_gram`: (P, q) from the dot constraint, the
    scale from ``|g| = 1``. One problem of :func:`_linear_joints`."""
    return _linear_joints(gram[None])[0]


def _linear_joints(grams: FloatArray) -> list[Candidate | None]:
    """:func:`_linear_joint` of a stack of Gram matrices (B, 22, 22): the factorisations
    of all the problems in one numpy call each, every problem's numbers as alone."""
    out: list[Candidate | None] = [None] * len(grams)
    n = grams[:, -1, -1]
    # D = (m (x) x, -m) per row: D^T D and D^T 1 are the Gram's entries with signs.
    DTD = grams[:, :12, :12] * _DOT_SIGNS  # (a sign flip is exact: the same as row, then column)
    ev = np.linalg.eigvalsh(DTD)
    # (singular values 1e-9 apart): turned about one axis only
    k = np.flatnonzero(ev[:, 0] > 1e-18 * ev[:, -1])
    v, singular = _steps(DTD[k], _DOT_SIGN * grams[k, :12, -1])  # (a singular one: no start)
    k, v = k[~singular], v[~singular]
    P = v[:, :9].reshape(-1, 3, 3)
    det_ok = np.linalg.det(P) > 0.0
    k, v, P = k[det_ok], v[det_ok], P[det_ok]
    o = np.linalg.solve(P, v[:, 9:12, None])[:, :, 0]  # (det > 0: none singular)
    # The mean of |P (x - o)|^2 over the rows is linear in their means (_magnitude_moment).
    mu, S = _second_moments(grams[k, -1, :-1] / n[k, None])
    M = _magnitude_moment(mu, S, o)
    for b, start in zip(k.tolist(), _scaled_starts(P, o, M), strict=True):
        out[b] = start
    return out


def _scaled_starts(P: FloatArray, o: FloatArray, M: FloatArray) -> list[Candidate | None]:
    """The linear starts of a stack of problems from their ``P`` (B, 3, 3), ``o`` (B, 3) and
    :func:`_magnitude_moment` (B, 3, 3): each scaled so its rows' mean ``|P (x - o)|^2`` is 1,
    ``P`` split into ``Q^T L``. The stacked products, factorisations and inverses run
    numpy's routine on each matrix as it would alone (the same numbers), in one call."""
    out: list[Candidate | None] = [None] * len(P)
    mean_sq = np.einsum("bij,bij->b", np.swapaxes(P, 1, 2) @ P, M)
    k = np.flatnonzero(np.isfinite(mean_sq) & (mean_sq > 0.0))
    c = 1.0 / np.sqrt(mean_sq[k])
    P = c[:, None, None] * P[k]
    A = np.swapaxes(P, 1, 2) @ P
    try:
        L = _lower_factor(A)
    except np.linalg.LinAlgError:  # one of them is not positive definite: no start for it
        factors = []
        for j in range(len(k)):
            with contextlib.suppress(np.linalg.LinAlgError):
                factors.append((j, _lower_factor(A[j])))
        if not factors:
            return out
        kept = [j for j, _ in factors]
        k, c, P = k[kept], c[kept], P[kept]
        L = np.stack([f for _, f in factors])
    Q = np.swapaxes(P @ np.linalg.inv(L), 1, 2)
    for j, (b, cj) in enumerate(zip(k.tolist(), c.tolist(), strict=True)):
        with contextlib.suppress(ValueError):  # not a calibration: no start
            out[b] = AffineCalibration.from_arrays(o[b], L[j]), Q[j], cj
    return out


_TRI = ((0, 0), (1, 0), (1, 1), (2, 0), (2, 1), (2, 2))  # lower-triangular entries of L
_TRI_A = np.array([a for a, _ in _TRI])
_TRI_B = np.array([b for _, b in _TRI])
#: Which of the six unique window means of ``x x^T`` (the features after ``x``) is ``[i, j]``.
_XX = np.array([[_UPPER.index((min(i, j), max(i, j))) for j in range(3)] for i in range(3)])
_EYE3 = np.eye(3)
#: (L S)'s coefficients (_joint_coefficients): [_XX[j, b], c] takes L[a, j], (a, b) = _TRI[c].
_T_ROW, _T_COL, _T_A, _T_J = np.array(
    [(_XX[j, b], c, a, j) for c, (a, b) in enumerate(_TRI) for j in range(3)]
).T


_C = np.arange(6)
#: Rows and columns of the coefficient entries set from a list (_joint_coefficients).
_CM_XX = (15 + _T_ROW, 3 + _T_COL)
_CM_MU = (12 + _TRI_B, 3 + _C)
#: vee(K - K^T)'s terms: K[i, l] - K[l, i] for (i, l) = (2, 1), (0, 2), (1, 0).
_VEE_I = np.array([2, 0, 1])
_VEE_L = np.array([1, 2, 0])
#: The identity's entries [m, b] for L's entries' columns b (the Jacobian of Q G' in L).
_EYE_TRI = _EYE3[None, :, _TRI_B]
#: A's entries in the order of the six means of x x^T, and their weight in tr(A M).
_A_UPPER = np.array([3 * i + j for i, j in _UPPER])
_A_TWICE = np.array([1.0 if i == j else 2.0 for i, j in _UPPER])


def _joint_coefficients(
    o: FloatArray, L: FloatArray, Q: FloatArray, s: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Dot and magnitude residuals and their Jacobians in (o 3, L 6, rotation 3, s 1).

    All are linear in a row's features and 1 (``G' = G - m o^T`` is): returned are their
    coefficients on :func:`_with_one`'s ``F``: the residuals' (22, 2) (``F @ c``: the dot
    and the magnitude residual of each row), the dot's and the magnitude's Jacobians
    (22, 13) each (``F @ Cd``). For ``B`` problems at once: ``o`` (B, 3), ``L`` and ``Q``
    (B, 3, 3), ``s`` (B,); the results have a leading axis of ``B``. Every entry is a
    product or a sum of a few, each problem's computed as it would be alone: this runs
    once per Gauss-Newton step of all the jackknife's problems, so it is written for few
    numpy calls.
    """
    B = o.shape[0]
    QT = np.swapaxes(Q, 1, 2)
    P = QT @ L
    # The dot rows: <P, G'>, (Q G')[a, b] for L's entries, and vee(K - K^T) with
    # K = Q G' L^T for the rotation; column by column, G'[j, m]'s coefficient W[3 j + m]:
    # Q[a, j] I[m, b] for L's entry (a, b), Q[i, j] L[l, m] for K[i, l].
    CD = np.zeros((B, _JOINT_FEATURES + 1, 10))
    W = CD[:, :9]
    W[:, :, 0] = P.reshape(B, 9)
    W[:, :, 1:7] = (QT[:, :, None, _TRI_A] * _EYE_TRI).reshape(B, 9, 6)
    W[:, :, 7:10] = (
        np.swapaxes(Q[:, _VEE_I], 1, 2)[:, :, None, :] * np.swapaxes(L[:, _VEE_L], 1, 2)[:, None]
        - np.swapaxes(Q[:, _VEE_L], 1, 2)[:, :, None, :] * np.swapaxes(L[:, _VEE_I], 1, 2)[:, None]
    ).reshape(B, 9, 3)
    W[:, :, 1:10] += 0.0  # a zero product as +0.0: the sign of zero an einsum of these gave
    # G' W = G W - m (o's contraction of W): the m features' coefficients.
    CD[:, 9:12] = -np.einsum("bm,bimc->bic", o, W.reshape(B, 3, 3, 10))
    # Relative to s: a common scale of P and s leaves the dot rows unchanged, so they never
    # pull the scale (towards P = 0, where they would vanish); |g| = 1 alone sets it.
    s3 = s[:, None, None]
    c = np.zeros((B, _JOINT_FEATURES + 1, 2))
    c[:, :, 0] = CD[:, :, 0] / s[:, None]
    c[:, -1, 0] -= 1.0
    Cd = np.zeros((B, _JOINT_FEATURES + 1, 13))
    Cd[:, 9:12, :3] = -P / s3
    Cd[:, :, 3:12] = CD[:, :, 1:10] / s3
    Cd[:, :, 9:12] *= -1.0  # the rotation's: -(CD / s), exactly
    Cd[:, :, 12] = -CD[:, :, 0] / (s * s)[:, None]
    # The magnitude rows: tr(A M) and 2 (L M)[a, b] with M = S - mu o^T - o mu^T + o o^T
    # (_magnitude_moment), from the window means of x (mu, features 12-14) and of
    # x x^T (xx, the six after).
    A = np.swapaxes(L, 1, 2) @ L
    oc = o[:, :, None]  # o as a column, o[:, None] as a row: each product as with one o
    Ao = (A @ oc)[:, :, 0]
    Lo = (L @ oc)[:, :, 0]
    c[:, 12:15, 1] = -2.0 * Ao
    c[:, 15:21, 1] = A.reshape(B, 9)[:, _A_UPPER] * _A_TWICE
    c[:, -1, 1] = (o[:, None] @ Ao[:, :, None])[:, 0, 0] - 1.0
    Cm = np.zeros((B, _JOINT_FEATURES + 1, 13))
    Cm[:, 12:15, :3] = -2.0 * A  # -2 (mu - o) A
    Cm[:, -1, :3] = 2.0 * (o[:, None] @ A)[:, 0]
    # (L S)[a, b] = sum_j L[a, j] S[j, b] from the six means of x x^T
    Cm[:, _CM_XX[0], _CM_XX[1]] = 2.0 * L[:, _T_A, _T_J]
    Cm[:, 12:15, 3:9] = -2.0 * np.swapaxes(L[:, _TRI_A], 1, 2) * o[:, None, _TRI_B]
    Cm[:, _CM_MU[0], _CM_MU[1]] -= 2.0 * Lo[:, _TRI_A]  # -(L o)[a] mu[b]
    Cm[:, -1, 3:9] = 2.0 * Lo[:, _TRI_A] * o[:, _TRI_B]
    return c, Cd, Cm


def _correlation_time(x: FloatArray) -> float:
    """Integrated autocorrelation time of a residual series, in rows (1 for white noise),
    from its deviations from its mean ``x``.

    Summed over the initial positive run of the autocorrelation (up to a tenth
    of the series), so slow beats count fully and noise does not.
    """
    n = x.size
    var = float(x @ x)
    if n < 4 or not var > 0.0:
        return 1.0
    tau = 1.0
    for lag in range(1, max(2, n // 10)):
        # (ndarray.dot: the BLAS dot that @ calls, without the matmul ufunc's dispatch)
        rho = float(x[:-lag].dot(x[lag:])) / var
        if rho <= 0.0:
            break
        tau += 2.0 * rho
    return tau


def _weight(r: FloatArray) -> float:
    """Weight of a residual series in a joint fit: 1 / sqrt(variance x correlation time)."""
    # np.mean(r) and np.var(r) from the deviations made once: numpy's mean is the sum over
    # n, its var the deviations' squares' sum over n (the same reductions, without the
    # layers around them: this runs for every problem of every window of every fit)
    x = r - float(np.add.reduce(r)) / r.size
    var = float(np.add.reduce(x * x)) / x.size
    return 1.0 / max(math.sqrt(var * _correlation_time(x)), 1e-12)


#: Gauss-Newton stops after a step this small (the parameters are of order 1): over the tests'
#: fits the step after one below 1e-10 was below 3e-13, a change that counts for nothing.
_STEP_TOL = 1e-10


def _steps(JTJ: FloatArray, rhs: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Each problem's solution ``JTJ[k] \\ rhs[k]`` (a Gauss-Newton step), and which are
    singular (no solution: zeros)."""
    try:
        step = np.asarray(np.linalg.solve(JTJ, rhs[:, :, None])[:, :, 0], dtype=np.float64)
        return step, np.zeros(len(rhs), dtype=bool)
    except np.linalg.LinAlgError:  # one of them: tell which
        step = np.zeros_like(rhs)
        bad = np.zeros(len(rhs), dtype=bool)
        for k in range(len(rhs)):
            try:
                step[k] = np.linalg.solve(JTJ[k], rhs[k])
            except np.linalg.LinAlgError:
                bad[k] = True
        return step, bad


def _solve_joint(
    rows: FloatArray,
    gram: FloatArray | None = None,
    magnitude_weight: float = 1.0,
    iterations: int = 8,
) -> Candidate | None:
    """Accelerometer calibration and rotation from window means (see the module docstring).

    Gauss-Newton on both constraints at once: the dot product with the field
    (linear in the shake) and ``|g| = 1`` (which pins the accelerometer's own
    shape and scale, but carries the shake's squares): each weighted by the
    inverse scatter of its residuals, so a shaken tumble leans on the first
    and a still one uses both. The scatter counts its correlation time: the
    slow beats a shake leaves in ``|g|`` weigh as the few samples they are.

    ``gram``: the rows' :func:`_gram`, if known. ``J^T J = C^T gram C`` with the
    coefficients ``C`` (:func:`_joint_coefficients`); only the residuals are formed
    per row (for ``J^T r``, which the Gram matrix would give with cancellation).
    One problem of :func:`solve_joints`.
    """
    G = _gram(rows) if gram is None else gram
    return solve_joints([_with_one(rows)], [G], magnitude_weight, iterations)[0]


def solve_joints(
    rows_1: Sequence[FloatArray],
    grams: Sequence[FloatArray],
    magnitude_weight: float = 1.0,
    iterations: int = 8,
) -> list[Candidate | None]:
    """:func:`_solve_joint` of several sets of rows (each with its 1, :func:`_with_one`;
    and their :func:`_gram`) at once.

    The jackknife's problems (the whole series and each one without a block) step
    together: the small matrices of all of them go through each numpy call at once
    (one call instead of one per problem: they cost their call, not their size), the
    rows of each through its own products. Each problem's numbers are what it would
    give alone, and it stops when its own step is small.
    """
    B = len(rows_1)
    out: list[Candidate | None] = [None] * B
    begun = [(b, st) for b, st in enumerate(_linear_joints(np.stack(grams))) if st is not None]
    if not begun:
        return out
    act = [b for b, _ in begun]
    G = np.stack([grams[b] for b in act])
    o = np.stack([st[0].offset_array for _, st in begun])
    L = np.stack([st[0].matrix_array for _, st in begun])
    Q = np.stack([st[1] for _, st in begun])
    s = np.array([st[2] for _, st in begun])
    F = [rows_1[b] for b in act]
    wd = np.ones(len(act))
    wm = np.ones(len(act))
    live = np.arange(len(act))  # of act: still stepping
    failed = np.zeros(len(act), dtype=bool)
    # Windows that do not pin the model can send it off to infinity: judged below (not
    # finite: no candidate); numpy's overflow warnings would only be noise in the log.
    with np.errstate(over="ignore", invalid="ignore"):
        for it in range(iterations):
            c, Cd, Cm = _joint_coefficients(o[live], L[live], Q[live], s[live])
            # J^T J and J^T r of the weighted rows stacked, without stacking them: the
            # residuals row by row (each problem's own rows), J^T J from the Gram matrices
            JTr = np.empty((live.size, 13))
            for k, b in enumerate(live):
                r = F[b] @ c[k]
                if it == 0:
                    wd[b] = _weight(r[:, 0])
                    wm[b] = _weight(r[:, 1]) * magnitude_weight
                Fr = F[b].T @ r
                JTr[k] = (wd[b] * wd[b]) * (Cd[k].T @ Fr[:, 0]) + (wm[b] * wm[b]) * (
                    Cm[k].T @ Fr[:, 1]
                )
            Gl = G[live]
            w2d = (wd[live] * wd[live])[:, None, None]
            w2m = (wm[live] * wm[live])[:, None, None]
            JTJ = w2d * (np.swapaxes(Cd, 1, 2) @ Gl @ Cd) + w2m * (np.swapaxes(Cm, 1, 2) @ Gl @ Cm)
            step, bad = _steps(JTJ, -JTr)
            failed[live[bad]] = True
            o[live] = o[live] + step[:, :3]
            Ll = L[live]
            Ll[:, _TRI_A, _TRI_B] += step[:, 3:9]
            L[live] = Ll
            # (a stacked matmul: each product as alone)
            Q[live] = np.stack([rotvec_to_dcm(st) for st in step[:, 9:12]]) @ Q[live]
            s[live] = s[live] + step[:, 12]
            live = live[~bad & ~(np.max(np.abs(step), axis=1) < _STEP_TOL)]
            if live.size == 0:
                break
    usable = (
        ~failed
        & np.isfinite(L).all(axis=(1, 2))
        & (np.diagonal(L, axis1=1, axis2=2) > 0.0).all(axis=1)
    )
    for k, i in enumerate(act):
        if not usable[k]:
            continue
        with contextlib.suppress(ValueError):  # not a calibration: no candidate
            out[i] = AffineCalibration.from_arrays(o[k], L[k]), Q[k].copy(), float(s[k])
    return out


#: ``a m^T`` one feature at a time: the rotation's Jacobian on them is its coefficients.
_ROTATION_BASIS = np.eye(9).reshape(9, 3, 3)


def solve_rotations(
    rows_1: Sequence[FloatArray], grams: Sequence[FloatArray], iterations: int = 12
) -> list[Candidate | None]:
    """Rotation ``R`` and ``s`` with ``<R, mean(a m^T)> = s`` (Gauss-Newton from the identity)
    for several sets of rows (each with its 1, and their :func:`_gram`) at once, as :func:`solve_joints`
    does: each problem's numbers as alone."""
    B = len(rows_1)
    out: list[Candidate | None] = [None] * B
    G = np.stack(grams)
    n = G[:, -1, -1]
    F = list(rows_1)
    R = np.repeat(np.eye(3)[None], B, axis=0)
    s = np.array([float(np.sum(g[-1, [0, 4, 8]]) / g[-1, -1]) for g in grams])
    C = np.zeros((B, 10, 4))  # J = F C
    C[:, -1, 3] = -1.0
    live = np.arange(B)
    unobserved = np.zeros(B, dtype=bool)
    for _ in range(iterations):
        RE = np.einsum("bij,klj->bkil", R[live], _ROTATION_BASIS)  # (R m) a^T per row
        Cl = C[live]
        Cl[:, :-1, :3] = _vee(np.swapaxes(RE, 2, 3) - RE)
        C[live] = Cl
        JTJ = np.swapaxes(Cl, 1, 2) @ G[live] @ Cl
        informed = np.linalg.eigvalsh(JTJ)[:, 0] / n[live] >= _MIN_INFORMATION
        unobserved[live[~informed]] = True
        live, JTJ, Cl = live[informed], JTJ[informed], Cl[informed]
        if live.size == 0:
            break
        rhs = np.empty((live.size, 4))
        coef = np.concatenate([R[live].reshape(-1, 9), -s[live, None]], axis=1)
        for k, b in enumerate(live.tolist()):
            e = F[b] @ coef[k]
            rhs[k] = -(Cl[k].T @ (F[b].T @ e))
        step = np.linalg.solve(JTJ, rhs[:, :, None])[:, :, 0]
        # (a stacked matmul: each product as alone)
        R[live] = np.stack([rotvec_to_dcm(st) for st in step[:, :3]]) @ R[live]
        # |step| as np.linalg.norm gives it: the square root of its dot with itself
        small = np.array([math.sqrt(st @ st) < _STEP_TOL for st in step])
        s[live] = s[live] + step[:, 3]
        live = live[~small]
        if live.size == 0:
            break
    for b in np.flatnonzero(~unobserved).tolist():
        out[b] = AffineCalibration(), R[b].copy(), float(s[b])
    return out
