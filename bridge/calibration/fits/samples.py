"""Sample acceptance for magnetometer calibration: spread, saturation and outliers.

Three filters, applied in this order by the live calibration flow:

1. **Saturated / non-finite** samples are never used: a channel at an ADC rail
   (0 or 4095 counts) reads the rail, not the field, and would pull the fit.
2. **Near-duplicates** are dropped so a unit held still (or turned slowly)
   does not load the buffer with one direction. This is ArduPilot's
   ``CompassCalibrator::accept_sample``: a new sample must be at least
   ``radius * 2 sin(theta / 2)`` from every sample already kept, with
   ``theta`` the angle between neighbouring vertices of a triangulated
   polyhedron with ``F = 2 V - 4`` faces for ``V`` = buffer size:
   ``A = (4 pi / F + pi) / 3`` and ``theta = 0.5 * acos(cos A / (1 - cos A))``
   (ArduPilot keeps the factor 0.5, i.e. demands half the ideal spacing, so
   the buffer can still fill). The radius starts at 200 mG and is replaced
   by the sphere-fit radius, after which the buffer is thinned again.
3. **Outliers** after a first fit: residual beyond ``k`` robust sigmas
   (1.4826 x median absolute deviation), refit without them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bridge.core.sensor import is_saturated
from bridge.types import BoolArray, FloatArray

COMPASS_CAL_NUM_SAMPLES = 300  #: ArduPilot's sample buffer size
INITIAL_RADIUS_G = 0.2  #: ArduPilot starts acceptance with a 200 mG radius
DEFAULT_OUTLIER_K = 5.0
#: How far below the spacing (squared) a new sample must come to the last kept one for
#: :meth:`SampleAcceptor.offer` to call it a near-duplicate without the buffer-wide check.
#: Python's ``dx*dx + dy*dy + dz*dz`` and numpy's row sum may add the three squares in
#: another order: each is within 3 roundings (2**-53 each) of the exact sum of
#: non-negative terms, so within 7e-16 of each other -- far inside this margin, and
#: the shortcut only ever says what the full check would.
_SURELY_NEAR = 1.0 - 1e-9
#: Floor for the robust sigma: half an ADC count (1 count = 0.39 mG). Residuals
#: smaller than the quantisation step carry no evidence of a bad sample.
MIN_SIGMA_G = 2.0e-4
_MAD_TO_SIGMA = 1.4826  # MAD of a normal distribution -> its standard deviation


def acceptance_angle(n_samples: int = COMPASS_CAL_NUM_SAMPLES) -> float:
    """Angular spacing (radians) demanded between kept samples for a buffer of ``n_samples``."""
    if n_samples < 4:
        raise ValueError(f"need a buffer of at least 4 samples, got {n_samples}")
    faces = 2 * n_samples - 4
    a = 4.0 * math.pi / (3.0 * faces) + math.pi / 3.0
    return 0.5 * math.acos(math.cos(a) / (1.0 - math.cos(a)))


def acceptance_distance(radius_G: float, n_samples: int = COMPASS_CAL_NUM_SAMPLES) -> float:
    """Minimum distance (gauss) between kept samples on a sphere of ``radius_G``."""
    if not (math.isfinite(radius_G) and radius_G > 0.0):
        raise ValueError(f"radius must be positive and finite, got {radius_G!r}")
    return radius_G * 2.0 * math.sin(acceptance_angle(n_samples) / 2.0)


@dataclass(slots=True)
class SampleCounters:
    """Why samples were or were not kept (monotonic until :meth:`SampleAcceptor.reset`)."""

    accepted: int = 0
    near_duplicate: int = 0
    saturated: int = 0
    non_finite: int = 0
    buffer_full: int = 0
    thinned: int = 0

    @property
    def rejected(self) -> int:
        """All samples offered but not (or no longer) kept."""
        return (
            self.near_duplicate + self.saturated + self.non_finite + self.buffer_full + self.thinned
        )


class SampleAcceptor:
    """ArduPilot-style calibration sample buffer (pure: no clock, no I/O).

    ``offer()`` each new raw magnetometer vector (nominal gauss) with its
    saturation flag; the buffer keeps at most ``capacity`` well-spread samples.
    After a sphere fit, :meth:`set_radius` updates the spacing and
    :meth:`thin` drops the samples that no longer meet it.
    """

    def __init__(
        self, capacity: int = COMPASS_CAL_NUM_SAMPLES, radius_G: float = INITIAL_RADIUS_G
    ) -> None:
        if capacity < 4:
            raise ValueError(f"capacity must be at least 4, got {capacity}")
        self._capacity = capacity
        self._buf = np.empty((capacity, 3), dtype=np.float64)
        self._n = 0
        self._radius = INITIAL_RADIUS_G
        self._min_dist = 0.0
        #: the spacing squared times _SURELY_NEAR (set with the spacing)
        self._near2 = 0.0
        #: the last sample kept, and the last one a frame came too close to (the full
        #: check's), as Python floats (None: none since the buffer was emptied or thinned)
        self._last: tuple[float, float, float] | None = None
        self._close: tuple[float, float, float] | None = None
        self.counters = SampleCounters()
        self.set_radius(radius_G)

    @property
    def capacity(self) -> int:
        """Maximum number of samples kept."""
        return self._capacity

    @property
    def radius_G(self) -> float:
        """Sphere radius the spacing is derived from."""
        return self._radius

    @property
    def min_distance_G(self) -> float:
        """Current minimum spacing between kept samples (gauss)."""
        return self._min_dist

    @property
    def full(self) -> bool:
        """True when the buffer holds ``capacity`` samples (time to fit)."""
        return self._n >= self._capacity

    def __len__(self) -> int:
        return self._n

    @property
    def samples(self) -> FloatArray:
        """Copy of the kept samples, (n, 3) gauss, in acceptance order."""
        return self._buf[: self._n].copy()

    def set_radius(self, radius_G: float) -> None:
        """Use a new sphere radius (e.g. from a sphere fit); raises ``ValueError`` if not positive."""
        self._min_dist = acceptance_distance(radius_G, self._capacity)
        self._near2 = self._min_dist**2 * _SURELY_NEAR
        self._radius = float(radius_G)

    def reset(self) -> None:
        """Empty the buffer and the counters (radius kept)."""
        self._n = 0
        self._last = self._close = None
        self.counters = SampleCounters()

    def _close_to(self, v: FloatArray, upto: int, skip: int = -1) -> int:
        """The index of a kept sample (of the first ``upto``, ``skip`` left out) nearer to
        ``v`` than the spacing; -1: none is."""
        if upto == 0:
            return -1
        # (The arrays' own methods: the same sums without np.sum / np.all's dispatch, which
        # cost more than the arithmetic on every frame a collection is offered.)
        d = self._buf[:upto] - v
        d2 = (d * d).sum(axis=1)  # d ** 2: numpy squares by multiplying
        if 0 <= skip < upto:
            d2[skip] = np.inf
        far = d2 >= self._min_dist**2
        return -1 if far.all() else int(far.argmin())

    def offer(self, sample_G: npt.ArrayLike, *, saturated: bool = False) -> bool:
        """Offer one raw sample (3,) in gauss; returns True when it was kept.

        A rejected sample is counted (saturated, non-finite, near-duplicate or
        buffer full) and leaves the buffer untouched.
        """
        v = np.asarray(sample_G, dtype=np.float64).reshape(-1)
        if v.shape != (3,):
            self.counters.non_finite += 1
            return False
        x, y, z = v.tolist()
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            self.counters.non_finite += 1
            return False
        if saturated:
            self.counters.saturated += 1
            return False
        if self._n >= self._capacity:
            self.counters.buffer_full += 1
            return False
        # Most frames of a collection come close to the sample kept last, or to the one the
        # frame before came close to (the field turns a fraction of the spacing a frame): a
        # few float operations say so, where the buffer-wide check costs a dozen numpy
        # calls. Only a sure "too close" is taken from them (_SURELY_NEAR); anything else
        # goes through the full check, which has the last word.
        for kept in (self._last, self._close):
            if kept is not None:
                dx, dy, dz = kept[0] - x, kept[1] - y, kept[2] - z
                if dx * dx + dy * dy + dz * dz < self._near2:
                    self.counters.near_duplicate += 1
                    return False
        close = self._close_to(v, self._n)
        if close >= 0:
            cx, cy, cz = self._buf[close].tolist()
            self._close = (cx, cy, cz)
            self.counters.near_duplicate += 1
            return False
        self._buf[self._n] = v
        self._n += 1
        self._last = (x, y, z)
        self.counters.accepted += 1
        return True

    def offer_counts(self, mag_counts: npt.ArrayLike, sample_G: npt.ArrayLike) -> bool:
        """Offer a sample together with its raw ADC counts (saturation taken from the counts)."""
        return self.offer(sample_G, saturated=bool(is_saturated(np.asarray(mag_counts))))

    def thin(self, order: npt.ArrayLike | None = None) -> int:
        """Drop kept samples closer than the current spacing to another kept one.

        ``order`` (a permutation of ``range(len(self))``) sets the visiting
        order -- ArduPilot shuffles so neighbours are not removed in runs;
        pass ``rng.permutation(len(acceptor))`` for that. Returns how many
        samples were removed.
        """
        n = self._n
        if order is None:
            idx = np.arange(n)
        else:
            idx = np.asarray(order, dtype=np.int64).reshape(-1)
            if idx.shape != (n,) or not np.array_equal(np.sort(idx), np.arange(n)):
                raise ValueError("order must be a permutation of range(len(acceptor))")
        self._buf[:n] = self._buf[idx]
        i = 0
        removed = 0
        while i < self._n:
            if self._close_to(self._buf[i], self._n, skip=i) < 0:
                i += 1
                continue
            # The last sample takes the rejected one's place (as in ArduPilot)
            # and, unlike ArduPilot, is examined next so no close pair survives.
            self._buf[i] = self._buf[self._n - 1]
            self._n -= 1
            removed += 1
        self._last = self._close = None  # their places in the buffer moved, or they are gone
        self.counters.thinned += removed
        return removed


def select_spread(
    samples_G: npt.ArrayLike,
    radius_G: float,
    capacity: int = COMPASS_CAL_NUM_SAMPLES,
    saturated: npt.ArrayLike | None = None,
) -> npt.NDArray[np.int64]:
    """Indices of the samples a :class:`SampleAcceptor` would keep, offered in order (batch helper)."""
    x = np.asarray(samples_G, dtype=np.float64).reshape(-1, 3)
    sat = np.zeros(len(x), dtype=bool) if saturated is None else np.asarray(saturated, dtype=bool)
    if sat.shape != (len(x),):
        raise ValueError("saturated must be one flag per sample")
    acc = SampleAcceptor(capacity, radius_G)
    keep = [i for i in range(len(x)) if acc.offer(x[i], saturated=bool(sat[i]))]
    return np.asarray(keep, dtype=np.int64)


def usable_mask(samples: npt.ArrayLike, saturated: npt.ArrayLike | None = None) -> BoolArray:
    """True for rows that are finite and not flagged saturated; (N, 3) in, (N,) out."""
    x = np.asarray(samples, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"samples must be (N, 3), got shape {x.shape}")
    ok = np.all(np.isfinite(x), axis=1)
    if saturated is not None:
        sat = np.asarray(saturated, dtype=bool).reshape(-1)
        if sat.shape != (x.shape[0],):
            raise ValueError(f"saturated must have {x.shape[0]} flags, got {sat.shape[0]}")
        ok &= ~sat
    return ok


def robust_sigma(residuals: npt.ArrayLike) -> float:
    """1.4826 x median absolute deviation from the median (NaN for no data)."""
    r = np.asarray(residuals, dtype=np.float64).reshape(-1)
    r = r[np.isfinite(r)]
    if r.size == 0:
        return math.nan
    return float(_MAD_TO_SIGMA * np.median(np.abs(r - np.median(r))))


def inlier_mask(
    residuals: npt.ArrayLike, k: float = DEFAULT_OUTLIER_K, min_sigma: float = MIN_SIGMA_G
) -> BoolArray:
    """True where ``|residual - median| <= k * max(robust_sigma, min_sigma)``; non-finite is an outlier."""
    if not (math.isfinite(k) and k > 0.0):
        raise ValueError(f"k must be positive, got {k!r}")
    r = np.asarray(residuals, dtype=np.float64).reshape(-1)
    finite = np.isfinite(r)
    if not np.any(finite):
        return finite
    sigma = max(robust_sigma(r), min_sigma)
    med = float(np.median(r[finite]))
    with np.errstate(invalid="ignore"):
        return finite & (np.abs(r - med) <= k * sigma)
