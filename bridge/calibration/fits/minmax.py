"""Method 1: min/max hard-iron offsets and per-axis gains, as the compass's own MAGCAL does.

Datasheet, ``MAGCAL,END``::

    X/Y/Zoff = (max + min) / 2
    Kx = 1, Ky = (Xmax - Xmin) / (Ymax - Ymin), Kz = (Xmax - Xmin) / (Zmax - Zmin)

and it fails with ``RANGE`` if any axis spanned under 400 counts. With
accelerometer samples the device's gating is reproduced: x/y extremes only
while level (tilt under 20 deg), the z extreme only while on its side
(|gz| under 0.35 g). Without them every sample counts for every axis (a host
that collected a tumble).

Gains are normalised to x, so the corrected field keeps the x axis's own
sensitivity error (radius = x sensitivity * |B|): heading does not care,
field-strength checks should use the report's ``radius_G``. Min/max sees no cross-axis terms (soft
iron, non-orthogonality, misalignment); the matrix is diagonal.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from bridge.calibration.fits.scalar import failed_result, field_report
from bridge.core.calibration import (
    AffineCalibration,
    Calibration,
    CalibrationResult,
)
from bridge.core.sensor import MAG_COUNTS_PER_GAUSS, ZERO_COUNTS

#: Datasheet: MAGCAL fails with RANGE if an axis spanned under 400 counts.
MIN_SPAN_COUNTS = 400.0
MIN_SPAN_G = MIN_SPAN_COUNTS / MAG_COUNTS_PER_GAUSS
LEVEL_TILT_DEG = 20.0  #: x/y extremes are tracked only below this tilt
SIDE_MAX_GZ_G = 0.35  #: the z extreme is tracked only while |gz| is under this


def fit_minmax(mag_G: npt.ArrayLike, *, acc_g: npt.ArrayLike | None = None) -> CalibrationResult:
    """Min/max offsets and x-normalised gains from (N, 3) nominal-gauss samples.

    ``acc_g`` (N, 3), if given, gates the samples the way the device does.
    Returns status MAG_CAL_FAILED (identity parameters, reason in the notes) on
    too few samples or an axis span under 400 counts -- the datasheet's RANGE.
    """
    raw = np.asarray(mag_G, dtype=np.float64)
    if raw.ndim != 2 or raw.shape[1:] != (3,):
        raise ValueError(f"mag_G must be an (N, 3) array, got shape {raw.shape}")
    ok = np.all(np.isfinite(raw), axis=1)
    if acc_g is not None:
        acc = np.asarray(acc_g, dtype=np.float64)
        if acc.shape != raw.shape:
            raise ValueError(f"acc_g must match mag_G's shape {raw.shape}, got {acc.shape}")
        ok &= np.all(np.isfinite(acc), axis=1)
        acc = acc[ok]
    x = raw[ok]
    dropped = int(raw.shape[0] - x.shape[0])
    if x.shape[0] < 2:
        return failed_result(
            "minmax", f"too few samples: {x.shape[0]}", n_samples=x.shape[0], n_rejected=dropped
        )

    if acc_g is None:
        xy_rows = z_rows = np.ones(x.shape[0], dtype=bool)
    else:
        gn = np.linalg.norm(acc, axis=1)
        safe = np.where(gn > 0, gn, 1.0)
        tilt_deg = np.degrees(np.arccos(np.clip(acc[:, 2] / safe, -1.0, 1.0)))
        xy_rows = (gn > 0) & (tilt_deg < LEVEL_TILT_DEG)
        z_rows = np.abs(acc[:, 2]) < SIDE_MAX_GZ_G

    lo = np.zeros(3)
    hi = np.zeros(3)
    for axis, rows in ((0, xy_rows), (1, xy_rows), (2, z_rows)):
        if not np.any(rows):
            where = "level" if axis < 2 else "on its side"
            return failed_result(
                "minmax",
                f"RANGE: no samples {where} for the {'xyz'[axis]} axis",
                n_samples=x.shape[0],
                n_rejected=dropped,
            )
        lo[axis] = float(np.min(x[rows, axis]))
        hi[axis] = float(np.max(x[rows, axis]))
    span = hi - lo
    short = [
        f"{'xyz'[i]} {span[i] * MAG_COUNTS_PER_GAUSS:.0f}" for i in range(3) if span[i] < MIN_SPAN_G
    ]
    if short:
        return failed_result(
            "minmax",
            f"RANGE: axis span under {MIN_SPAN_COUNTS:.0f} counts ({', '.join(short)} counts)",
            n_samples=x.shape[0],
            n_rejected=dropped,
        )
    offset = (hi + lo) / 2.0
    gains = np.array([1.0, span[0] / span[1], span[0] / span[2]])
    cal = AffineCalibration.from_arrays(offset, np.diag(gains))
    after = cal.apply(x)
    radius = float(np.mean(np.linalg.norm(after, axis=1)))
    used = int(np.count_nonzero(xy_rows | z_rows))
    report = field_report(
        "minmax",
        x,
        after,
        radius,
        n_samples=used,
        n_rejected=dropped + (x.shape[0] - used),
        notes=(
            "device MAGCAL equivalent: off counts "
            + ", ".join(f"{ZERO_COUNTS + MAG_COUNTS_PER_GAUSS * o:.1f}" for o in offset)
            + "; K "
            + ", ".join(f"{k:.4f}" for k in gains),
        ),
    )
    return CalibrationResult(Calibration(mag=cal), report)
