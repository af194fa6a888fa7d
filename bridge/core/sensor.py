"""Nominal transfer functions of the GMR compass (datasheet, "Axes and signs").

Body axes are x forward, y right, z down (NED body / FRD). Magnetometer counts
rise with the field along each +axis; accelerometer counts rise with the
component of *gravity* along each +axis, so a level unit at rest reads
(0, 0, +1 g).  Every unit differs from these nominal figures -- that is what
calibration is for -- so these constants only turn counts into roughly-right
physical units before the calibration is applied.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from bridge.types import FloatArray

ADC_BITS = 12
ADC_MAX = 4095  #: a channel at 0 or ADC_MAX counts is saturated
ADC_FULL_SCALE_V = 2.5
ZERO_COUNTS = 2458.0  #: 1.5 V reference, both sensors
MAG_COUNTS_PER_GAUSS = 2560.0
ACC_COUNTS_PER_G = 491.5
GAUSS_TO_NT = 1e5
GAUSS_TO_MGAUSS = 1e3
STANDARD_GRAVITY = 9.80665  #: m/s^2 per g


def mag_counts_to_gauss(counts: npt.ArrayLike) -> FloatArray:
    """Raw magnetometer counts (..., 3) to gauss with the nominal transfer."""
    return (np.asarray(counts, dtype=np.float64) - ZERO_COUNTS) / MAG_COUNTS_PER_GAUSS


def acc_counts_to_g(counts: npt.ArrayLike) -> FloatArray:
    """Raw accelerometer counts (..., 3) to g (gravity vector, +z down) with the nominal transfer."""
    return (np.asarray(counts, dtype=np.float64) - ZERO_COUNTS) / ACC_COUNTS_PER_G


def gauss_to_mag_counts(gauss: npt.ArrayLike) -> FloatArray:
    """Inverse of :func:`mag_counts_to_gauss` (unrounded, unclipped)."""
    return np.asarray(gauss, dtype=np.float64) * MAG_COUNTS_PER_GAUSS + ZERO_COUNTS


def g_to_acc_counts(g: npt.ArrayLike) -> FloatArray:
    """Inverse of :func:`acc_counts_to_g` (unrounded, unclipped)."""
    return np.asarray(g, dtype=np.float64) * ACC_COUNTS_PER_G + ZERO_COUNTS


def is_saturated(counts: npt.ArrayLike) -> npt.NDArray[np.bool_]:
    """True where any channel of a (..., 3) count vector sits at a rail (0 or ADC_MAX)."""
    c = np.asarray(counts)
    return np.any((c <= 0) | (c >= ADC_MAX), axis=-1)
