"""Accelerometer calibration and mag-to-accel alignment from a hand-held tumble.

A person tumbling the unit also shakes it: linear acceleration ``a`` (a few
hundredths of a g, 0.4-2.5 Hz) rides on gravity, and the accelerometer reads
``g - a``. A frame's gravity *direction* is then degrees off, and the classic
steps take the shake as signal: the scalar fit ``|g| = 1`` sees
``|g - a|^2 = 1 - 2 a_D + |a|^2`` -- whose ``|a|^2`` has slow beats that no
filter separates from a slow tumble -- and the alignment from
``g . m = sin(dip)`` with *unit* vectors inherits the same squares.

This module fits both from the constraint that is *linear* in the shake:
with ``m`` the unit field direction from the (shake-free) magnetometer after
its ellipsoid fit, and ``x`` the raw accelerometer::

    (P (x - o)) . m = sin(dip)        for every frame

``P`` is the accelerometer calibration expressed in the magnetometer's axes
(``P = Q^T L``: ``L`` the lower-triangular accelerometer calibration, ``Q``
the rotation from the magnetometer's into the accelerometer's axes). With
``q = P o`` the model is linear in ``(P, q)`` and in the products ``m (x) x``
and ``m``. The shake enters only as ``-a . B`` (the acceleration along the
field, in the world frame: it does not depend on how the unit is turned), so
the products are averaged over Hann windows (:mod:`bridge.calibration.fits.series`):
the model stays exact for any turn within a window while the shake averages
out. The window (none, or 1 to 6 s) is the one whose result is most
certain; the overall scale comes from ``|g| = 1`` (a common scale does not
tilt anything, so the magnitude's shake terms do no harm there).

With a known accelerometer calibration (six faces, or the one in use) only
``Q`` is fitted, from ``(a . Q m)`` with the calibrated -- *not* normalised --
gravity vector ``a`` (normalising would bring the squares back).

How certain the result is comes from a delete-a-block jackknife over time:
the fit is repeated without each tenth of the session, and the spread of the
heading (and tilt) those fits give on a fixed set of attitudes (tilt up to
60 deg) is the predicted RMS heading error of the calibration
(``heading_sigma_deg``). A fitted accelerometer is only used where it differs
from the one in use by more than twice its own uncertainty: the tilt is never
made worse by noise.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bridge.calibration.fits.handheld_models import (
    Candidate,
    Finisher,
    Solver,
    _gram,
    _joint_features,
    _linear_joint,
    _with_one,
    gram_of,
    solve_joints,
    solve_rotations,
)
from bridge.calibration.fits.scalar import fit_scalar_accel
from bridge.calibration.fits.series import (
    MOTION_WINDOW_S,
    frame_period_s,
    frames_for,
    hann_kernel,
    motion_rms_g,
    runs,
    window_means,
)
from bridge.core.attitude import tilt_compensated_heading
from bridge.core.calibration import AffineCalibration
from bridge.core.geometry import axis_angle_to_dcm, dcm_to_rotvec, euler_to_dcm
from bridge.types import FloatArray

#: Averaging windows tried, seconds (0: single frames).
DEFAULT_WINDOWS_S: tuple[float, ...] = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
JACKKNIFE_BLOCKS = 10
#: Fewest window means a fit is tried on (12 unknowns, and ten jackknife blocks).
MIN_ROWS = 60
#: A fitted accelerometer replaces the one in use only when it differs by this many sigmas.
SIGNIFICANCE = 2.0
#: Linear acceleration (RMS per axis, g; see :func:`series.motion_rms_g`) up to which a
#: tumble counts as still: a smooth 45 deg/s turn reads about 0.016 g, a hand's
#: 0.05 g shake about 0.04 g.
STILL_MOTION_G = 0.025
#: Relative weight of ``|g| = 1`` in a shaken tumble: enough to set the scale only.
SHAKEN_MAGNITUDE_WEIGHT = 0.01
#: Attitudes the predicted errors are averaged over: any heading, tilt up to 60 deg.
EVAL_TILT_DEG = 60.0


def tilted_attitudes(rng: np.random.Generator, n: int, max_tilt_deg: float) -> FloatArray:
    """Random heading; tilt uniform over the spherical cap ``tilt <= max_tilt_deg`` (N, 3, 3)."""
    yaw = rng.uniform(0.0, 2.0 * math.pi, n)
    az = rng.uniform(0.0, 2.0 * math.pi, n)
    cos_t = rng.uniform(math.cos(math.radians(max_tilt_deg)), 1.0, n)
    tilt = np.arccos(np.clip(cos_t, -1.0, 1.0))
    if n == 0:
        return np.empty((0, 3, 3))
    # tilt about a horizontal axis after the heading: body z leaves the vertical by tilt[i]
    tilts = [
        axis_angle_to_dcm((math.cos(a), math.sin(a), 0.0), t)
        for a, t in zip(az.tolist(), tilt.tolist(), strict=True)
    ]
    headings = [euler_to_dcm(0.0, 0.0, y) for y in yaw.tolist()]
    # (a stacked matmul: each product as alone)
    return np.asarray(np.stack(tilts) @ np.stack(headings), dtype=np.float64)


_EVAL_R = tilted_attitudes(np.random.default_rng(0x7417), 120, EVAL_TILT_DEG)


@dataclass(frozen=True, slots=True)
class Spread:
    """Predicted RMS errors of a calibration from its jackknife replicates (degrees)."""

    heading_deg: float
    tilt_deg: float


@dataclass(frozen=True, slots=True)
class HandheldFit:
    """The accelerometer calibration and alignment of a hand-held tumble, and how certain they are.

    ``accel`` maps raw nominal g to the gravity vector (fitted, or the one
    given); ``rotation`` takes the magnetometer's (ellipsoid-calibrated) axes
    into the accelerometer's. ``window_s`` is the averaging window chosen
    (0: single frames); ``heading_sigma_deg`` / ``tilt_sigma_deg`` the
    predicted RMS heading / tilt error of the result (jackknife, tilt up to
    60 deg); ``motion_g`` the linear acceleration seen (RMS per axis, g).
    """

    accel: AffineCalibration
    rotation: FloatArray
    accel_fitted: bool
    window_s: float
    n_windows: int
    dip_deg: float
    heading_sigma_deg: float
    tilt_sigma_deg: float
    motion_g: float
    notes: tuple[str, ...]

    @property
    def rotation_deg(self) -> float:
        """Angle of ``rotation``."""
        return math.degrees(float(np.linalg.norm(dcm_to_rotvec(self.rotation))))


def _unit_rows(v: FloatArray) -> FloatArray:
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return np.asarray(v / np.where(n > 0.0, n, 1.0), dtype=np.float64)


# -- predicted errors ------------------------------------------------------------------


def _headings(
    cals: Sequence[Candidate], x: FloatArray, m_sym: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Headings (B, N) and unit gravity vectors (B, N, 3) of raw ``x`` and ``m_sym`` read
    through each calibration: one call of the (row by row) formulas for all of them."""
    g = np.concatenate([accel.apply(x) for accel, _, _ in cals])
    m = np.concatenate([m_sym @ Q.T for _, Q, _ in cals])
    _, _, h = tilt_compensated_heading(m, g)
    return h.reshape(len(cals), -1), _unit_rows(g).reshape(len(cals), -1, 3)


def spread(base: Candidate, replicates: Sequence[Candidate], field_dir_ned: FloatArray) -> Spread:
    """Jackknife RMS heading and tilt error of ``base`` from its delete-a-block ``replicates``.

    Raw readings are synthesised from ``base`` at a fixed set of attitudes
    (any heading, tilt up to 60 deg) and read back through every replicate;
    the jackknife variance ``(B-1)/B sum (h_b - mean h)^2`` of each attitude's
    heading (and gravity direction), averaged over the attitudes, is the
    predicted mean square error.
    """
    accel0, Q0, _ = base
    g_b = _EVAL_R[:, 2, :]  # R^T (0, 0, 1)
    m_b = np.einsum("nji,j->ni", _EVAL_R, field_dir_ned)
    L0 = accel0.matrix_array
    x = np.linalg.solve(L0, g_b.T).T + accel0.offset_array
    m_sym = m_b @ Q0  # Q0^T m_b per row
    B = len(replicates)
    if B < 2:
        return Spread(math.nan, math.nan)
    h, u = _headings([base, *replicates], x, m_sym)
    dh = (h[1:] - h[0] + 180.0) % 360.0 - 180.0
    du = u[1:] - u[0]
    k = (B - 1) / B
    var_h = k * np.sum((dh - dh.mean(axis=0)) ** 2, axis=0)
    var_u = k * np.sum((du - du.mean(axis=0)) ** 2, axis=(0, 2))
    return Spread(float(np.sqrt(np.mean(var_h))), math.degrees(float(np.sqrt(np.mean(var_u)))))


def change(a: Candidate, b: Candidate, base: Candidate, field_dir_ned: FloatArray) -> Spread:
    """RMS heading and tilt differences between calibrations ``a`` and ``b`` (same attitudes as :func:`spread`)."""
    accel0, Q0, _ = base
    g_b = _EVAL_R[:, 2, :]
    m_b = np.einsum("nji,j->ni", _EVAL_R, field_dir_ned)
    x = np.linalg.solve(accel0.matrix_array, g_b.T).T + accel0.offset_array
    m_sym = m_b @ Q0
    (ha, hb), (ua, ub) = _headings([a, b], x, m_sym)
    dh = (ha - hb + 180.0) % 360.0 - 180.0
    cos = np.clip(np.sum(ua * ub, axis=1), -1.0, 1.0)
    return Spread(
        float(np.sqrt(np.mean(dh * dh))), math.degrees(float(np.sqrt(np.mean(np.arccos(cos) ** 2))))
    )


# -- the fit ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Trial:
    window_s: float
    n_rows: int
    full: Candidate
    spread: Spread


def _trial(
    features: FloatArray,
    spans: list[tuple[int, int]],
    period_s: float,
    window_s: float,
    solve: Solver,
    finish: Finisher,
    field_dir: FloatArray,
    blocks: int,
) -> _Trial | None:
    n_k = frames_for(window_s, period_s) if window_s > 0.0 else 1
    step = max(1, n_k // 8)
    wm = window_means(features, spans, hann_kernel(n_k), step)
    if len(wm) < MIN_ROWS:
        return None
    edges = np.linspace(0, len(wm), blocks + 1).astype(int)
    # Each replicate's Gram matrix is the sum of the other blocks': one pass over the rows.
    F = _with_one(wm.rows)
    grams = np.stack([gram_of(F[edges[b] : edges[b + 1]]) for b in range(blocks)])
    # The whole series first, then each replicate: solved together (solve_joints). (The
    # sums over the stack's first axis add the blocks' matrices in order, as they did
    # from a list of them.)
    rows = [F]
    gram_sums = [np.sum(grams, axis=0)]
    others = ~np.eye(blocks, dtype=bool)
    for b in range(blocks):
        rows.append(np.concatenate((F[: edges[b]], F[edges[b + 1] :])))
        gram_sums.append(np.sum(grams[others[b]], axis=0))
    solved = solve(rows, gram_sums)
    if any(r is None for r in solved):
        return None
    full, *reps = (finish(r) for r in solved if r is not None)
    return _Trial(window_s, len(wm), full, spread(full, reps, field_dir))


def _best(
    features: FloatArray,
    spans: list[tuple[int, int]],
    period_s: float,
    windows_s: Sequence[float],
    solve: Solver,
    finish: Finisher,
    field_dir: FloatArray,
    blocks: int,
) -> _Trial | None:
    best: _Trial | None = None
    for w in windows_s:
        tr = _trial(features, spans, period_s, w, solve, finish, field_dir, blocks)
        if (
            tr is not None
            and math.isfinite(tr.spread.heading_deg)
            and (best is None or tr.spread.heading_deg < best.spread.heading_deg)
        ):
            best = tr
    return best


def _field_direction(field_ned_G: npt.ArrayLike | None, sin_dip: Callable[[], float]) -> FloatArray:
    """The field's unit vector (NED): the given field's, else from the dip the frames show.

    ``sin_dip`` is only called without a usable field: working it out takes a pass over
    every frame (a fit, a median), which a live calibration -- it has the WMM field --
    does not need."""
    if field_ned_G is not None:
        f = np.asarray(field_ned_G, dtype=np.float64).reshape(3)
        n = float(np.linalg.norm(f))
        if math.isfinite(n) and n > 0.0:
            return f / n
    s = max(-1.0, min(1.0, sin_dip()))
    return np.array([math.sqrt(1.0 - s * s), 0.0, s])


def fit_handheld(
    mag_sym_G: npt.ArrayLike,
    acc_g: npt.ArrayLike,
    t_s: npt.ArrayLike,
    usable: npt.ArrayLike,
    *,
    accel: AffineCalibration | None = None,
    field_ned_G: npt.ArrayLike | None = None,
    windows_s: Sequence[float] | None = None,
    blocks: int = JACKKNIFE_BLOCKS,
) -> HandheldFit | None:
    """Accelerometer calibration (unless ``accel`` is given) and alignment from a frame series.

    ``mag_sym_G`` (N, 3): the magnetometer after its ellipsoid (symmetric)
    calibration; ``acc_g`` (N, 3): the raw accelerometer in nominal g; ``t_s``
    (N,): frame times in seconds; ``usable`` (N,): frames to use (not
    saturated, not rejected). ``accel``: a known accelerometer calibration
    (only the rotation is fitted then). ``field_ned_G``: the local field, for
    the predicted errors (else the fitted dip is used). None when the frames
    do not determine the fit (too few, or turned about one axis only).
    """
    windows_s = DEFAULT_WINDOWS_S if windows_s is None else windows_s
    m = np.asarray(mag_sym_G, dtype=np.float64)
    x = np.asarray(acc_g, dtype=np.float64)
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    ok = np.asarray(usable, dtype=bool).reshape(-1)
    if m.shape != x.shape or m.ndim != 2 or m.shape[1] != 3 or t.shape != (m.shape[0],):
        raise ValueError(
            f"mag, acc and t must be (N, 3), (N, 3), (N,); got {m.shape}, {x.shape}, {t.shape}"
        )
    ok = ok & np.all(np.isfinite(m), axis=1) & np.all(np.isfinite(x), axis=1)
    ok &= np.linalg.norm(np.where(ok[:, None], m, 1.0), axis=1) > 0.0
    spans = runs(t, ok)
    period = frame_period_s(t)
    mu = _unit_rows(np.where(ok[:, None], m, 1.0))
    motion = _motion(x, spans, period)
    notes: list[str] = []

    def rotation_only(given: AffineCalibration) -> _Trial | None:
        a = given.apply(x)
        feats = (a[:, :, None] * mu[:, None, :]).reshape(-1, 9)

        def sin_dip() -> float:
            if not np.any(ok):
                return 0.0
            return float(np.median(np.sum(_unit_rows(a[ok]) * mu[ok], axis=1)))

        fdir = _field_direction(field_ned_G, sin_dip)

        def finish(c: Candidate) -> Candidate:
            return given, c[1], c[2]

        return _best(feats, spans, period, windows_s, solve_rotations, finish, fdir, blocks)

    if accel is not None:
        tr = rotation_only(accel)
        fitted = False
    else:
        feats = _joint_features(mu, x)

        def sin_dip() -> float:
            # the linear start's on every frame
            first = _linear_joint(_gram(feats[ok])) if np.count_nonzero(ok) >= MIN_ROWS else None
            return first[2] if first is not None else 0.0

        fdir = _field_direction(field_ned_G, sin_dip)
        # Still: |g| = 1 holds to the sensor noise and adds to what the dot product says.
        # Shaken: its squares of the shake beat slowly, so it only sets the scale.
        weight = 1.0 if motion <= STILL_MOTION_G else SHAKEN_MAGNITUDE_WEIGHT

        def joint(
            rows: Sequence[FloatArray], grams: Sequence[FloatArray]
        ) -> list[Candidate | None]:
            return solve_joints(rows, grams, weight)

        tr = _best(feats, spans, period, windows_s, joint, lambda c: c, fdir, blocks)
        fitted = tr is not None
        if tr is not None:
            nominal_accel: Candidate = (AffineCalibration(), tr.full[1], tr.full[2])
            tilt = change(tr.full, nominal_accel, tr.full, fdir).tilt_deg
            nominal = None
            if not tilt > SIGNIFICANCE * tr.spread.tilt_deg:
                nominal = rotation_only(AffineCalibration())
            if nominal is not None:
                notes.append(
                    f"accelerometer fit ({tilt:.3f} deg from nominal, "
                    f"+-{tr.spread.tilt_deg:.3f}) not significant: nominal kept"
                )
                # The nominal transfer may be off by as much as the fit says: count it.
                diff = change(tr.full, nominal.full, tr.full, fdir)
                err = Spread(
                    math.hypot(nominal.spread.heading_deg, diff.heading_deg),
                    math.hypot(nominal.spread.tilt_deg, diff.tilt_deg),
                )
                tr = _Trial(nominal.window_s, nominal.n_rows, nominal.full, err)
                fitted = False
        if tr is None:
            tr = _undetermined_accel(rotation_only(AffineCalibration()), x[ok], fdir)
            fitted = False
            notes.append("accelerometer not determined by these frames: nominal kept")
    if tr is None:
        return None
    acc_cal, Q, s = tr.full
    notes.append(
        f"{'accelerometer and ' if fitted else ''}alignment from {tr.n_rows} "
        f"{'frames' if tr.window_s == 0.0 else f'{tr.window_s:g} s window means'}; "
        f"predicted heading error {tr.spread.heading_deg:.3f} deg, tilt {tr.spread.tilt_deg:.3f} deg"
    )
    return HandheldFit(
        accel=acc_cal,
        rotation=Q,
        accel_fitted=fitted,
        window_s=tr.window_s,
        n_windows=tr.n_rows,
        dip_deg=math.degrees(math.asin(max(-1.0, min(1.0, s)))),
        heading_sigma_deg=tr.spread.heading_deg,
        tilt_sigma_deg=tr.spread.tilt_deg,
        motion_g=motion,
        notes=tuple(notes),
    )


def _undetermined_accel(nominal: _Trial | None, acc: FloatArray, fdir: FloatArray) -> _Trial | None:
    """The nominal-accelerometer fit when the frames cannot tell the accelerometer's calibration.

    Its predicted error must count how far off the nominal transfer may be:
    as far as a plain ``|g| = 1`` fit of the same frames puts it (shake and
    all); infinitely far when even that fails.
    """
    if nominal is None:
        return None
    rough = fit_scalar_accel(acc)
    if not rough.report.ok:
        return _Trial(nominal.window_s, nominal.n_rows, nominal.full, Spread(math.inf, math.inf))
    guess: Candidate = (rough.calibration.accel, nominal.full[1], nominal.full[2])
    d = change(guess, nominal.full, nominal.full, fdir)
    err = Spread(
        math.hypot(nominal.spread.heading_deg, d.heading_deg),
        math.hypot(nominal.spread.tilt_deg, d.tilt_deg),
    )
    return _Trial(nominal.window_s, nominal.n_rows, nominal.full, err)


def _motion(x: FloatArray, spans: list[tuple[int, int]], period_s: float) -> float:
    """Linear-acceleration level over the runs (RMS per axis, g): see :func:`series.motion_rms_g`."""
    n = frames_for(MOTION_WINDOW_S, period_s, minimum=5)
    acc = 0.0
    count = 0
    for a, b in spans:
        k = (b - a) // n
        if k == 0:
            continue
        v = motion_rms_g(x[a:b], n)
        acc += k * v * v
        count += k
    return math.sqrt(acc / count) if count else math.nan
