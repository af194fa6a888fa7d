"""Frame time series for the hand-held fits: contiguous runs, window means, motion level.

A person who tumbles a compass also moves it: linear acceleration of a few
hundredths of a g at 0.4-2.5 Hz rides on the gravity the accelerometer
measures, and a single frame's gravity direction is then degrees off. What
saves the calibration is that the shake has no mean -- a hand does not travel
far -- while the unit's attitude changes smoothly. So the hand-held fits
(:mod:`bridge.calibration.fits.handheld`) are written as models that are *linear in
products of the measured vectors* (``m (x) x``, ``x``, ``x x^T`` ...). Averaging
such a product over a short window keeps the model exact however the unit
turns within the window, and averages the shake away. This module makes those
window means.

* :func:`runs` -- the frames as runs of consecutive usable frames (a saturated
  frame or a gap in time ends a run; a window never spans one);
* :func:`hann_kernel` / :func:`window_means` -- Hann-weighted window means of
  per-frame features, every ``step`` frames, within each run;
* :func:`motion_rms_g` -- how hard the unit is being shaken: the RMS per axis
  of the accelerometer about a local quadratic in time (what a smooth turn
  cannot produce); the live motion judge and the fit report use the same one.

Pure: numpy only, no clock, no I/O.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bridge.types import FloatArray, IntArray

#: A gap longer than this many frame periods ends a run (lost frames, a pause in the stream).
MAX_GAP_PERIODS = 2.5
#: Seconds of frames a motion-level window spans: short enough that a turn at human
#: rates is nearly a quadratic in time (45 deg/s leaves ~0.01 g), long enough to hold
#: most of a hand's shake.
MOTION_WINDOW_S = 1.5


def frame_period_s(t_s: npt.ArrayLike) -> float:
    """Median positive time step of ``t_s`` (seconds); NaN with fewer than two distinct times."""
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    d = np.diff(t)
    d = d[np.isfinite(d) & (d > 0.0)]
    return float(np.median(d)) if d.size else math.nan


def runs(
    t_s: npt.ArrayLike, usable: npt.ArrayLike, *, max_gap_periods: float = MAX_GAP_PERIODS
) -> list[tuple[int, int]]:
    """``(start, stop)`` index ranges of consecutive usable frames without a time gap.

    Frames are taken as evenly spaced within a run (the device samples on a
    fixed tick; host arrival jitter does not matter here). A run ends at an
    unusable frame, at a step longer than ``max_gap_periods`` median periods,
    and where time goes backwards.
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    ok = np.asarray(usable, dtype=bool).reshape(-1)
    if t.shape != ok.shape:
        raise ValueError(f"t_s and usable differ in length: {t.shape} vs {ok.shape}")
    ok = ok & np.isfinite(t)
    period = frame_period_s(t)
    d = np.diff(t)
    brk = np.zeros(t.size, dtype=bool)  # brk[i]: frame i cannot follow frame i-1
    if t.size > 1:
        limit = max_gap_periods * period if math.isfinite(period) else math.inf
        brk[1:] = ~(d > 0.0) | (d > limit)
    out: list[tuple[int, int]] = []
    start: int | None = None
    for i in range(t.size):
        if not ok[i] or brk[i]:
            if start is not None:
                out.append((start, i))
            start = i if ok[i] else None
        elif start is None:
            start = i
    if start is not None:
        out.append((start, t.size))
    return out


def hann_kernel(n: int) -> FloatArray:
    """A Hann window of ``n`` taps (zero ends excluded), summing to 1; ``n <= 1`` is ``[1]``.

    Its sidelobes fall off fast, so a shake well above ``2 / window`` Hz is
    averaged away while the window's main lobe keeps the slow turn.
    """
    if n <= 1:
        return np.ones(1)
    w = np.hanning(n + 2)[1:-1]
    return np.asarray(w / w.sum(), dtype=np.float64)


@dataclass(frozen=True, slots=True)
class WindowMeans:
    """Window means of per-frame features: ``rows`` (n, k), ``centre`` (n,) frame index of each."""

    rows: FloatArray
    centre: IntArray

    def __len__(self) -> int:
        return int(self.rows.shape[0])


def window_means(
    features: npt.ArrayLike, spans: list[tuple[int, int]], kernel: npt.ArrayLike, step: int
) -> WindowMeans:
    """Kernel-weighted means of ``features`` (N, k) over each run, every ``step`` frames.

    Only windows that lie wholly inside one run are formed (a window never
    straddles a saturated frame or a gap). ``kernel`` sums to 1, so a feature
    that is constant in time comes out unchanged.
    """
    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2:
        raise ValueError(f"features must be (N, k), got {f.shape}")
    h = np.asarray(kernel, dtype=np.float64).reshape(-1)
    n_k = h.size
    step = max(1, int(step))
    rows: list[FloatArray] = []
    centres: list[IntArray] = []
    for a, b in spans:
        if b - a < n_k:
            continue
        view = np.lib.stride_tricks.sliding_window_view(f[a:b], n_k, axis=0)[::step]
        rows.append(np.asarray(view @ h, dtype=np.float64))
        centres.append(a + n_k // 2 + step * np.arange(view.shape[0], dtype=np.int64))
    if not rows:
        return WindowMeans(np.empty((0, f.shape[1])), np.empty(0, dtype=np.int64))
    return WindowMeans(np.concatenate(rows), np.concatenate(centres))


@functools.lru_cache(maxsize=32)
def _quadratic_basis(n: int) -> FloatArray:
    """``[1, s, s^2]`` at ``n`` evenly spaced ``s`` in [-1, 1] (n, 3): the same for every
    window of ``n`` rows, and building it cost more than the least squares it is for --
    so it is built once (read-only, as it is shared)."""
    s = np.linspace(-1.0, 1.0, n)
    V = np.column_stack([np.ones(n), s, s * s])
    V.flags.writeable = False
    return V


def _quadratic_residual_rms(block: FloatArray) -> FloatArray:
    """Per-column RMS of (n, k) rows about their least-squares quadratic in time."""
    n = block.shape[0]
    V = _quadratic_basis(n)
    coef, *_ = np.linalg.lstsq(V, block, rcond=None)
    r = block - V @ coef
    return np.asarray(np.sqrt(np.sum(r * r, axis=0) / max(1, n - 3)), dtype=np.float64)


def motion_rms_g(acc_g: npt.ArrayLike, frames_per_window: int) -> float:
    """Linear-acceleration level of a stretch of frames: RMS per axis in g.

    The frames are cut into consecutive windows of ``frames_per_window``; in
    each, every accelerometer axis is compared with its best quadratic in
    time (a smooth turn is one; a hand's shake, sensor noise and a jerky turn
    are not). Returns the RMS of those residuals over all windows and axes;
    NaN when no whole window fits. Units are those of ``acc_g`` (nominal g:
    an uncalibrated gain error of a few per cent scales it alike).
    """
    a = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    n = int(frames_per_window)
    if n < 5 or a.shape[0] < n:
        return math.nan
    m = a.shape[0] // n
    sq = [_quadratic_residual_rms(a[i * n : (i + 1) * n]) ** 2 for i in range(m)]
    return float(np.sqrt(np.mean(sq)))


def frames_for(seconds: float, period_s: float, minimum: int = 1) -> int:
    """How many frames of ``period_s`` span ``seconds`` (at least ``minimum``)."""
    if not (math.isfinite(period_s) and period_s > 0.0) or seconds <= 0.0:
        return minimum
    return max(minimum, round(seconds / period_s))
