"""A hard-iron change, seen from the constraints every sample carries (pure: samples in, fits out).

A vehicle's magnetic signature changes in service (a payload, a moved battery,
a bracket): the magnetometer then reads the Earth's field plus a constant
vector ``b`` in body axes, and the heading is off by up to ``asin(|b_xy| / H)``.
Nothing else knows the true heading, but every calibrated sample ``h`` (body
axes, gauss) with its gravity direction ``u = g / |g|`` must satisfy two
constraints if the calibration still holds:

* **field strength** ``|h - b| = F``: every sample counts, turning or not. Turns
  make the horizontal part of ``b`` observable, roll and pitch the vertical
  part. Fitted as the geometric distance (Gauss-Newton), not the algebraic
  sphere fit ``|h|^2 = 2 h.b + c``, whose noisy regressor drags ``b`` towards
  the samples when they cover a narrow arc (a level drive: one circle).
* **dip** ``u . (h - b) = V``, the vertical field ``F sin(dip)``: quasi-static
  samples only -- a turning vehicle's accelerometer sees the centripetal
  acceleration as a tilt of gravity (15 deg in a brisk turn), so a sample
  counts only when the tilt-compensated heading is steady and ``|g|`` is 1 g;
  speed changes still tilt it, so these rows are never trusted better than
  ``dip_sigma_floor_G``.

``F`` and ``V`` are fitted too, with the World Magnetic Model's values
(``reference``) as priors of +-``reference_sigma`` of the field -- when the
calibration reads the model's horizontal field within ``scale_tolerance`` (one
fitted elsewhere, or by a method that does not scale to the model, is judged on
its own data). Samples whose field is off the fit by ``gate_fraction``, the
whole run around them where it stands out of the noise, and ``guard_s`` more
are left out (a magnet going by, tails included); the rest is re-weighted with
Tukey's biweight. A fit says how well it knows each direction (its covariance:
:meth:`DriftEstimate.known`) and whether one offset explains its window
(``consistent``: not across a change, not full of a disturbance).

:class:`DriftEstimator` keeps a window and fits it;
:class:`~bridge.calibration.drift.judge.DriftJudge` turns successive fits into
verdicts (drift detected, cleared, the bounded learning steps). Times are the
samples' own (no clock here).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bridge.core.attitude import tilt_compensated_heading
from bridge.core.calibration import AffineCalibration, Calibration
from bridge.types import FloatArray, Vec3

ZERO: Vec3 = (0.0, 0.0, 0.0)
_TUKEY_C = 4.685  # 95 % efficiency under Gaussian noise
_MAX_MOVE_G = 0.02  # a Gauss-Newton step moves b by at most this
_MAX_OFFSET_G = 0.5  # a fit beyond this is not a drift (nor the learning's business)
_MAD = 1.4826  # median absolute deviation -> sigma


def _median(a: npt.ArrayLike) -> float:
    """``np.median`` of a 1-D array, the same number: the middle order statistic(s) by
    one partition (the last element too, so a NaN anywhere gives NaN as np.median does),
    without np.median's general machinery (several a fit, every estimate)."""
    x = np.asarray(a, dtype=np.float64).reshape(-1)
    n = x.size
    if n < 2:
        return float(np.median(x))
    k = n // 2
    p = np.partition(x, [k, -1] if n % 2 else [k - 1, k, -1])  # np.median's kth
    if math.isnan(p[-1]):
        return math.nan
    # np.median's mean of the middle: a sum from 0.0 (so -0.0 comes out as 0.0), divided
    return (0.0 + float(p[k])) / 1.0 if n % 2 else (0.0 + float(p[k - 1]) + float(p[k])) / 2.0


@dataclass(frozen=True, slots=True)
class DriftSettings:
    """How the estimator samples, fits and judges (see the module docstring)."""

    sample_period_s: float = 0.1  #: one sample kept per this long (10 Hz)
    block_s: float = 5.0  #: samples are handed over, and the window refitted, this often
    window_s: float = 60.0  #: the recent fit (detection) uses this much of the past
    long_window_s: float = 240.0  #: the long fit (learning) up to this much
    gate_fraction: float = 0.15  #: |h| off the field by more than this: not the Earth's field
    guard_s: float = 8.0  #: ... nor its tails: the run above the noise around it, and this long
    field_sigma_floor_G: float = 0.0005
    #: The dip rows are never trusted better than this: a vehicle's speed changes tilt
    #: what its accelerometer takes for gravity (0.05 g is 3 deg, 10 mG of vertical field).
    dip_sigma_floor_G: float = 0.01
    reference_sigma: float = 0.01  #: the model's F and V: +- this fraction of |B| ...
    scale_tolerance: float = 0.03  #: ... when the calibration reads the model's H this well
    quasi_static_rate_dps: float = 1.0  #: heading steadier than this ...
    quasi_static_accel_g: float = 0.02  #: ... and |g| this close to 1: gravity alone
    correlation_s: float = 0.5  #: samples closer than this are not independent evidence
    #: A fit whose residual is 2.5 times its usual level and this much more is a window
    #: of two offsets (across a change) or of a disturbance: no verdict on it.
    consistency_mG: float = 2.0
    min_samples: int = 150  #: no fit on fewer field samples
    detect_mG: float = 10.0  #: a change this large ...
    #: ... or, straight up or down, this large: a vertical offset moves the heading only
    #: with the tilt, and it is what a calibration's soft-iron error mimics best
    detect_vertical_mG: float = 15.0
    detect_sigma_mG: float = 3.0  #: ... known this well ...
    detect_evaluations: int = 3  #: ... in this many fits in a row is drift
    clear_mG: float = 5.0  #: below this in as many fits: no drift (any more)
    learn_sigma_mG: float = 1.5  #: learning steps need the offset known this well ...
    learn_stable_mG: float = 1.5  #: ... and the last three fits this close together
    learn_step_mG: float = 25.0  #: the largest step applied at once
    learn_done_mG: float = 1.0  #: learning ends when what is left is below this
    learn_min_mG: float = 3.0  #: a learning starts with at least this left
    learn_interval_s: float = 10.0  #: at most one step per this long
    learn_total_mG: float = 250.0  #: more than this is no drift to learn: recalibrate
    #: No step within this long after a disturbed sample: one whose field is off the
    #: fitted model by ``gate_fraction`` (the pipeline's flag compares with the
    #: calibration in use, which a large drift itself upsets).
    quiet_s: float = 10.0

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        if self.window_s < 2.0 * self.block_s:
            raise ValueError("window_s must hold at least two blocks")


@dataclass(frozen=True, slots=True)
class DriftEstimate:
    """One fit of the window: the offset change ``offset_G`` (body axes, gauss, relative to
    the calibration the samples are given in) and its covariance ``cov_G2`` (3 x 3,
    row-major, gauss^2), the fitted field ``field_G`` and vertical field
    ``vertical_G``, the robust RMS residual of the field strength, the sample counts,
    whether the model's field served as a prior (``referenced``) and the time of the
    newest sample ``t``."""

    t: float
    offset_G: Vec3
    cov_G2: tuple[float, ...]
    field_G: float
    vertical_G: float
    residual_G: float
    n_field: int
    n_dip: int
    span_s: float
    referenced: bool = False
    outlier_t: float = -math.inf  #: the newest sample gated out as not the Earth's field
    #: The residual is at its usual level: one offset explains the window. A window
    #: across a change (two offsets) or full of a disturbance does not fit so well.
    consistent: bool = True

    @property
    def sigma_G(self) -> float:
        """One sigma along the worst-known direction."""
        return math.sqrt(max(float(np.max(np.linalg.eigvalsh(self.cov))), 0.0))

    @property
    def cov(self) -> FloatArray:
        """The covariance as a 3 x 3 array."""
        return np.asarray(self.cov_G2, dtype=np.float64).reshape(3, 3)

    @property
    def horizontal_G(self) -> float:
        """The horizontal field ``sqrt(F^2 - V^2)``."""
        return math.sqrt(max(self.field_G**2 - self.vertical_G**2, 0.0))

    def known(self, v: Vec3, max_sigma_G: float) -> tuple[Vec3, float]:
        """The part of ``v`` along the directions this fit knows to ``max_sigma_G``, and one
        sigma along that part (inf when no direction is known that well).

        Turns make the horizontal offset known, roll and pitch (or the model's field)
        the vertical one: a level drive says nothing reliable about ``z``, and what
        it cannot say is left out rather than guessed.
        """
        return known_part(self.cov, v, max_sigma_G)


def known_part(cov: FloatArray, v: Vec3, max_sigma_G: float) -> tuple[Vec3, float]:
    """``v`` projected on the eigen-directions of ``cov`` with sigma <= ``max_sigma_G``, and one
    sigma along the projection (inf when no direction qualifies)."""
    lam, vec = np.linalg.eigh(cov)
    ok = lam <= max_sigma_G**2
    if not ok.any():
        return ZERO, math.inf
    good = vec[:, ok]
    p = good @ (good.T @ np.asarray(v, dtype=np.float64))
    n = float(np.linalg.norm(p))
    if n == 0.0:
        return ZERO, math.sqrt(max(float(np.max(lam[ok])), 0.0))
    u = p / n
    return (float(p[0]), float(p[1]), float(p[2])), math.sqrt(max(float(u @ cov @ u), 0.0))


def norm(v: Vec3) -> float:
    """|v|."""
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


def minus(a: Vec3, b: Vec3) -> Vec3:
    """a - b."""
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def plus(a: Vec3, b: Vec3) -> Vec3:
    """a + b."""
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def heading_error_deg(offset_G: Vec3, horizontal_G: float) -> float:
    """The worst heading error an offset ``offset_G`` (body axes) gives a level vehicle.

    A constant vector of length ``m`` added to a horizontal field ``H`` that turns
    with the heading deflects it by at most ``asin(m / H)`` (90 deg when ``m >= H``).
    """
    m = math.hypot(offset_G[0], offset_G[1])
    if not horizontal_G > 0.0:
        return math.nan
    return math.degrees(math.asin(min(1.0, m / horizontal_G)))


def with_offset_change(cal: Calibration, mounting: FloatArray, offset_G: Vec3) -> Calibration:
    """``cal`` corrected for a hard-iron change ``offset_G`` seen in body (vehicle) axes.

    The engine reads ``h = mounting @ matrix @ (raw - offset)``; a change ``d`` of the
    raw hard iron shows as ``b = mounting @ matrix @ d``, so the new offset is
    ``offset + matrix^-1 @ mounting^T @ b`` (the matrix, the soft iron, stays).
    """
    m = cal.mag
    d = np.linalg.solve(m.matrix_array, np.asarray(mounting).T @ np.asarray(offset_G))
    mag = AffineCalibration.from_arrays(m.offset_array + d, m.matrix_array)
    return Calibration(mag=mag, accel=cal.accel)


@dataclass(frozen=True, slots=True)
class Reference:
    """What the field should be here: total ``field_G`` and vertical ``vertical_G`` (None:
    unknown, e.g. no position configured)."""

    field_G: float | None = None
    vertical_G: float | None = None

    @classmethod
    def from_total_dip(cls, total_G: float | None, dip_deg: float | None) -> Reference:
        """From a total field and a dip angle (positive down), either possibly unknown."""
        if total_G is None:
            return cls()
        v = total_G * math.sin(math.radians(dip_deg)) if dip_deg is not None else None
        return cls(total_G, v)


class DriftEstimator:
    """The window of samples and its fit (not thread-safe: one owner).

    :meth:`add` takes a block of samples -- rows of ``(t, hx, hy, hz, gx, gy, gz)``,
    the calibrated field (gauss) and gravity vector (g, level = (0, 0, +1)) in body
    axes, all in one calibration's terms -- and forgets what fell out of the window
    (``window_s``, default the settings' recent window); :meth:`cut` forgets what
    came before a time; :meth:`estimate` fits what is kept.
    """

    def __init__(
        self, settings: DriftSettings | None = None, window_s: float | None = None
    ) -> None:
        self.settings = settings if settings is not None else DriftSettings()
        self.window_s = float(window_s) if window_s is not None else self.settings.window_s
        if not self.window_s >= 2.0 * self.settings.block_s:
            raise ValueError("window_s must hold at least two blocks")
        #: the blocks as added, each row with its tilt-compensated heading as an eighth
        #: column: a sample's heading never changes, and the quasi-static test of every
        #: fit needs it for the whole window (up to 48 blocks), which is why it is kept
        self._blocks: deque[FloatArray] = deque()
        self._last: Vec3 = ZERO
        self._levels: deque[float] = deque(maxlen=12)  # residuals of consistent fits
        self._consistent = True  # the last fit was
        self._on_model_scale = True  # decided after consistent fits only

    def reset(self) -> None:
        """Forget every sample (a new calibration or mounting: other axes, other terms)."""
        self._blocks.clear()
        self._last = ZERO
        self._levels.clear()
        self._consistent = True
        self._on_model_scale = True

    @property
    def samples(self) -> int:
        """Samples in the window."""
        return sum(len(b) for b in self._blocks)

    def add(self, rows: npt.ArrayLike) -> None:
        """One block of samples (N, 7), in time order; older samples than the window drop out."""
        a = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
        a = a[np.all(np.isfinite(a), axis=1)]
        if len(a) == 0:
            return
        _, _, heading = tilt_compensated_heading(a[:, 1:4], a[:, 4:7])
        self._blocks.append(np.column_stack((a, heading)))
        self.cut(float(a[-1, 0]) - self.window_s)

    def cut(self, before_t: float) -> None:
        """Forget the samples older than ``before_t``."""
        while self._blocks and float(self._blocks[0][-1, 0]) < before_t:
            self._blocks.popleft()
        if self._blocks and float(self._blocks[0][0, 0]) < before_t:
            first = self._blocks[0]
            self._blocks[0] = first[first[:, 0] >= before_t]

    def estimate(self, reference: Reference | None = None) -> DriftEstimate | None:
        """Fit the window (None while it holds fewer than ``min_samples`` usable samples)."""
        if not self._blocks:
            return None
        s = self.settings
        a = np.concatenate(self._blocks)
        t, h, g, hdg = a[:, 0], a[:, 1:4], a[:, 4:7], a[:, 7]
        ref = reference if reference is not None else Reference()
        # The gate judges the field as the last fit corrects it, around its median and
        # never tighter than its own spread: a change the fit does not follow yet
        # widens the spread instead of being gated out for good.
        seen = _row_norms((h - np.asarray(self._last)).T)
        mid = _median(seen)
        dev = np.abs(seen - mid)
        spread = _MAD * _median(dev)
        bad = _runs_with(dev > max(3.0 * spread, 3.0 * s.field_sigma_floor_G),
                         dev > max(s.gate_fraction * mid, 5.0 * spread))  # fmt: skip
        outlier_t = float(t[bad][-1]) if bad.any() else -math.inf
        keep = _away_from(t, bad, s.guard_s)
        if int(keep.sum()) < s.min_samples:
            return None
        t, h, g, hdg = t[keep], h[keep], g[keep], hdg[keep]
        gn = _row_norms(g.T)
        u = g / np.where(gn > 1e-9, gn, 1.0)[:, None]
        qs = _quasi_static(t, hdg, gn, s)
        uq, hq = u[qs], h[qs]  # the quasi-static samples, picked out once for both uses
        if self._consistent:  # (after a garbled fit its offset is no base to judge on)
            self._on_model_scale = self._on_scale(hq, uq, ref)
        if not self._on_model_scale:
            ref = Reference()
        # the dip rows, quasi-static samples only: u . b + V = u . h
        xv = np.zeros((len(uq), 5))
        xv[:, :3] = uq
        xv[:, 4] = 1.0
        yv = np.einsum("ij,ij->i", uq, hq)
        use_dip = len(yv) >= 10
        theta = self._fit(h, xv if use_dip else None, yv, ref, mid)
        if theta is None:
            return None
        fit, cov, resid = theta
        self._last = (float(fit[0]), float(fit[1]), float(fit[2]))
        level = _median(self._levels) if self._levels else resid
        consistent = resid <= max(2.5 * level, level + s.consistency_mG / 1000.0)
        if consistent:
            self._levels.append(resid)
        self._consistent = consistent
        return DriftEstimate(
            t=float(t[-1]),
            offset_G=self._last,
            cov_G2=tuple(float(x) for x in cov[:3, :3].reshape(9)),
            field_G=float(fit[3]),
            vertical_G=float(fit[4]),
            residual_G=resid,
            n_field=len(h),
            n_dip=len(yv) if use_dip else 0,
            span_s=float(t[-1] - t[0]),
            referenced=ref.field_G is not None,
            outlier_t=outlier_t,
            consistent=consistent,
        )

    def _on_scale(self, h: FloatArray, u: FloatArray, ref: Reference) -> bool:
        """Does this calibration read the model's field? Judged on the horizontal field.

        A calibration fitted without the position (or by a method that does not scale
        to the model) reads another |B|: the model then says nothing about its terms.
        A vertical offset changes |B| too -- on a level drive just like a scale would --
        but not the horizontal field, so that is what is compared (quasi-static
        samples: a turn tilts what the accelerometer takes for down).
        """
        if ref.field_G is None or ref.vertical_G is None or len(h) < 10:
            return True
        want = math.sqrt(max(ref.field_G**2 - ref.vertical_G**2, 0.0))
        seen = h - np.asarray(self._last)
        across = seen - np.einsum("ij,ij->i", seen, u)[:, None] * u
        got = _median(_row_norms(across.T))
        return want > 0.0 and abs(got / want - 1.0) <= self.settings.scale_tolerance

    # -- the fit ------------------------------------------------------------------------

    def _fit(
        self,
        h: FloatArray,
        xv: FloatArray | None,
        yv: FloatArray,
        ref: Reference,
        f_start: float,
    ) -> tuple[FloatArray, FloatArray, float] | None:
        """Tukey-reweighted Gauss-Newton; (theta = (b, F, V), covariance, field residual RMS).

        The field rows are the geometric distance ``|h - b| - F``, linearised at the
        current ``b`` -- not the algebraic ``|h|^2 = 2 h.b + c`` of a sphere fit, whose
        noisy regressor correlates with its target and, on a narrow arc (a level drive
        sees one circle of directions), drags ``b`` towards the samples.
        """
        s = self.settings
        n = len(h)
        wf = np.full(n, 1.0 / s.field_sigma_floor_G**2)
        wv = np.full(len(yv), 1.0 / s.dip_sigma_floor_G**2) if xv is not None else None
        theta = np.array([*self._last, f_start, ref.vertical_G or 0.0])
        if xv is not None and ref.vertical_G is None:
            theta[4] = _median(yv - xv[:, :3] @ theta[:3])
        cov = np.eye(5)
        scale_f = s.field_sigma_floor_G
        xf = np.zeros((n, 5))
        xf[:, 3] = 1.0
        hc = np.ascontiguousarray(h.T)  # (3, n): each axis of the field contiguous
        px, py, pw = self._priors(theta, ref)
        pxw = px * pw[:, None]  # the priors' rows are the same every iteration
        prior_a, prior_r = pxw.T @ px, pxw.T @ py
        for it in range(10):
            d = hc - theta[:3, None]  # h - b, by axis
            dn = _row_norms(d)
            xf[:, :3] = (d / np.where(dn > 0.0, dn, 1.0)).T  # unit directions
            yf = dn + xf[:, :3] @ theta[:3]  # n . b + F = |h - b0| + n . b0
            if it > 0:
                rf = yf - xf @ theta
                scale_f = max(_MAD * _median(np.abs(rf)), s.field_sigma_floor_G)
                wf = _tukey(rf / scale_f) / scale_f**2
                if xv is not None:
                    rv = yv - xv @ theta
                    scale_v = max(_MAD * _median(np.abs(rv)), s.dip_sigma_floor_G)
                    wv = _tukey(rv / scale_v) / scale_v**2
            xw = (xf * wf[:, None]).T
            A = xw @ xf + prior_a
            r = xw @ yf + prior_r
            if xv is not None and wv is not None:
                vw = (xv * wv[:, None]).T
                A += vw @ xv
                r += vw @ yv
            try:
                cov = np.linalg.inv(A)
            except np.linalg.LinAlgError:
                return None
            new = cov @ r
            if not np.isfinite(new).all():
                return None
            step = new[:3] - theta[:3]
            move = math.sqrt(float(step.dot(step)))  # np.linalg.norm's own sum, without its checks
            if move > _MAX_MOVE_G:  # a trust region: a mixture of two offsets must not fling b
                new = theta + (new - theta) * (_MAX_MOVE_G / move)
            done = it > 1 and float(np.abs(new - theta).max()) < 1e-7
            theta = new
            if done:
                break
        if float(np.linalg.norm(theta[:3])) > _MAX_OFFSET_G:
            return None  # no drift is this large: the window holds something else
        inflation = max(1.0, s.correlation_s / s.sample_period_s)
        return theta, cov * inflation, scale_f

    def _priors(
        self, theta: FloatArray, ref: Reference
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Rows that hold the parameters where the data say little.

        The model's field and vertical field at +-``reference_sigma`` of the field;
        without a model a vague 1 G (and always on ``b``, around zero) so that a
        window without turns or tilt stays solvable -- its covariance then says how
        little is known.
        """
        s = self.settings
        vague = 1.0
        ys = [0.0, 0.0, 0.0, float(theta[3]), float(theta[4])]
        sig = [_MAX_OFFSET_G] * 3 + [vague] * 2
        if ref.field_G is not None:
            ys[3], sig[3] = ref.field_G, s.reference_sigma * ref.field_G
            if ref.vertical_G is not None:
                ys[4], sig[4] = ref.vertical_G, s.reference_sigma * ref.field_G
        return np.eye(5), np.array(ys), 1.0 / np.square(sig)


def _row_norms(c: FloatArray) -> FloatArray:
    """``np.linalg.norm(c.T, axis=1)``, the same bits, from the (3, n) columns ``c``.

    numpy reduces each row of three left to right, ``(x*x + y*y) + z*z``; written out over
    the columns every operation runs along n numbers instead of a reduction of three per
    row -- a third of the time on a fit's windows (600-2400 samples), where several such
    norms a Gauss-Newton iteration were most of the fit. ``c`` may be the transpose of an
    (n, 3) array (the estimate's own norms of the window): the same bits again (checked on
    1.4 million rows, views of wider arrays among them).
    """
    s = c * c
    return np.sqrt((s[0] + s[1]) + s[2])


def _tukey(z: FloatArray) -> FloatArray:
    """Tukey's biweight: (1 - (z/c)^2)^2 inside c, 0 beyond."""
    q = z / _TUKEY_C
    return np.where(np.abs(q) < 1.0, (1.0 - q * q) ** 2, 0.0)


def _runs_with(above: npt.NDArray[np.bool_], hit: npt.NDArray[np.bool_]) -> npt.NDArray[np.bool_]:
    """The runs of consecutive ``above`` samples that hold a ``hit``: a magnet's whole
    pass, from where its field first stands out of the noise to where it sinks back."""
    if not hit.any():
        return hit
    run = np.cumsum(np.concatenate(([True], above[1:] != above[:-1])))  # run number
    hit_runs = np.unique(run[hit & above])
    return np.asarray(above & np.isin(run, hit_runs) | hit)


def _away_from(t: FloatArray, bad: npt.NDArray[np.bool_], guard_s: float) -> npt.NDArray[np.bool_]:
    """Samples farther than ``guard_s`` from every ``bad`` one (times ascending)."""
    if not bad.any():
        return np.ones(len(t), dtype=bool)
    tb = t[bad]
    i = np.searchsorted(tb, t)
    before = np.abs(t - tb[np.clip(i - 1, 0, len(tb) - 1)])
    after = np.abs(tb[np.clip(i, 0, len(tb) - 1)] - t)
    return np.asarray(np.minimum(before, after) > guard_s)


def _quasi_static(
    t: FloatArray, hdg: FloatArray, gn: FloatArray, s: DriftSettings
) -> npt.NDArray[np.bool_]:
    """Samples where the accelerometer sees gravity alone: |g| = 1 g and a steady heading.

    The heading rate is the tilt-compensated heading's, over +-0.5 s (a turn's
    centripetal acceleration is speed x that rate); across a gap in the samples
    the rate is unknown and the sample does not count. ``hdg`` is each sample's
    tilt-compensated heading (degrees), ``gn`` its ``|g|``.
    """
    n = len(t)
    ok = np.abs(gn - 1.0) < s.quasi_static_accel_g
    k = max(1, round(0.5 / s.sample_period_s))
    if n <= 2 * k:
        return np.zeros(n, dtype=bool)
    psi = np.unwrap(np.radians(hdg))
    dt = t[2 * k :] - t[: -2 * k]
    rate = np.full(n, np.inf)
    steady = dt < 2.0 * k * s.sample_period_s * 1.5
    rate[k:-k] = np.where(
        steady, np.abs(psi[2 * k :] - psi[: -2 * k]) / np.maximum(dt, 1e-9), np.inf
    )
    return np.asarray(ok & (np.degrees(rate) < s.quasi_static_rate_dps))
