"""The pure report pieces of ``compass-bridge calibrate`` (no I/O): maps, estimates, lines.

* :func:`coverage_map` / :func:`coverage_text` -- the 80 sphere sections on a
  latitude/longitude grid, covered or still missing;
* :func:`heading_error_estimate_deg` -- the fitness seen as a heading error;
* :func:`report_lines` -- the calibration report for a person;
* :func:`progress_note` / :func:`is_motion_warning` -- the live bar's note,
  with the bridge's "slower / steadier" warning while it is fresh;
* :class:`StatusTextChunks` -- a long STATUSTEXT (a failure's reason) put back together;
* :func:`frame_times` -- a recording's frames evenly in time (the device counter).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np
import numpy.typing as npt

from bridge.calibration.fits.coverage import N_SECTIONS, sections
from bridge.types import FloatArray

#: Rows x columns of the terminal coverage map (latitude bands x longitude sectors).
MAP_ROWS, MAP_COLS = 9, 36


# ---------------------------------------------------------------------------
# Pure helpers
# ---------------------------------------------------------------------------


def _grid_sections(rows: int = MAP_ROWS, cols: int = MAP_COLS) -> npt.NDArray[np.int64]:
    lat = np.radians(90.0 - (np.arange(rows) + 0.5) * 180.0 / rows)
    lon = np.radians((np.arange(cols) + 0.5) * 360.0 / cols)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    v = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), -np.sin(la)], axis=-1)
    return sections(v.reshape(-1, 3)).reshape(rows, cols)


_GRID = _grid_sections()


def coverage_map(missing: Iterable[int]) -> str:
    """The sphere as a latitude/longitude map: ``#`` sections covered, ``.`` still missing.

    Rows go from straight up (field pointing to -z in the sensor frame, top)
    to straight down; columns go round the horizon. PURE.
    """
    miss = set(missing)
    lines = ["".join("." if int(s) in miss else "#" for s in row) for row in _GRID]
    return "\n".join(f"  |{line}|" for line in lines)


def horizontal_field_G(total_G: float, dip_deg: float) -> float:
    """Horizontal intensity of a field of ``total_G`` and inclination ``dip_deg``."""
    return total_G * math.cos(math.radians(dip_deg))


def heading_error_estimate_deg(fitness_mG: float, horizontal_G: float) -> float:
    """Expected RMS heading error of a fit, frame by frame: the fitness seen as a sideways error.

    A residual of ``fitness`` milligauss across the horizontal field ``H``
    turns the heading by ``atan(fitness / H)``. The fit's residual is radial
    (|B| error), the heading error is tangential; for a fit without a
    systematic shape error the two are of the same size, which is what makes
    this a fair *estimate*, not a measurement. The bridge's fitness of a live
    (or recorded) tumble also holds the error the calibration itself is
    predicted to leave (accelerometer and alignment, see
    :class:`~bridge.core.calibration.CalibrationReport`), so a shaken tumble
    cannot look excellent here. NaN when either is unknown.
    """
    if not (math.isfinite(fitness_mG) and math.isfinite(horizontal_G) and horizontal_G > 0):
        return math.nan
    return math.degrees(math.atan2(fitness_mG / 1000.0, horizontal_G))


def _fmt(v: Any, spec: str = ".2f") -> str:
    if isinstance(v, int | float) and math.isfinite(v):
        return format(v, spec)
    return "n/a"


def _params_lines(report: dict[str, Any]) -> list[str]:
    return [
        "offsets       COMPASS_OFS_X/Y/Z  "
        + "  ".join(_fmt(report.get(f"ofs_{a}"), "+.1f") for a in "xyz")
        + " mG",
        "diagonal      COMPASS_DIA_X/Y/Z  "
        + "  ".join(_fmt(report.get(f"diag_{a}"), ".4f") for a in "xyz"),
        "off-diagonal  COMPASS_ODI_X/Y/Z  "
        + "  ".join(_fmt(report.get(f"offdiag_{a}"), "+.4f") for a in "xyz"),
        f"scale         COMPASS_SCALE  {_fmt(report.get('scale_factor'), '.4f')}",
    ]


def _succeeded(report: dict[str, Any]) -> bool:
    return report.get("cal_status") == "MAG_CAL_SUCCESS"


def _status_line(report: dict[str, Any]) -> str:
    return f"status        {report.get('cal_status', '?')}" + (
        f"  (method {report['method']})" if report.get("method") else ""
    )


def _share_lines(report: dict[str, Any], source: str) -> list[str]:
    """The part of the heading error ``source`` accounts for (the hand-held fits report
    it), with the tilt and the motion behind it; none where the report has no share."""
    cal_err = report.get("heading_error_deg")
    if not (isinstance(cal_err, int | float) and math.isfinite(cal_err)):
        return []
    motion = report.get("motion_g")
    return [
        f"  of which   ~{_fmt(cal_err, '.3f')} deg from {source}"
        f" (tilt ~{_fmt(report.get('tilt_error_deg'), '.3f')} deg)"
        + (f"; linear acceleration {motion:.3f} g RMS" if isinstance(motion, float) else "")
    ]


def report_lines(report: dict[str, Any], heading_error_deg: float) -> list[str]:
    """The calibration report for a person (``report`` is a MAG_CAL_REPORT-shaped dict).

    A failed fit shows no parameters (they belong to nothing): its status, its
    cause when the report carries one, and the figures that condemned it.
    """
    out = [_status_line(report)]
    if report.get("reason") and not _succeeded(report):
        out.append(f"cause         {report['reason']}")
    out.append(
        f"fitness       {_fmt(report.get('fitness'))} mG RMS"
        + (f", {report['n_samples']} samples" if report.get("n_samples") else "")
    )
    if not _succeeded(report):
        out.append("parameters    none: the fit failed")
        return out
    out += _params_lines(report)
    b, a = report.get("field_spread_before_nT"), report.get("field_spread_after_nT")
    if isinstance(b, int | float) or isinstance(a, int | float):
        # in mG, as the fitness and the offsets (the report's nT / 100): one unit system
        b, a = (v / 100.0 if isinstance(v, int | float) else v for v in (b, a))
        out.append(f"field spread  ±{_fmt(b, '.1f')} mG before  ->  ±{_fmt(a, '.1f')} mG after")
    else:
        out.append("field spread  not reported over this path (see the fitness)")
    out.append(f"heading error ~{_fmt(heading_error_deg)} deg RMS (estimated from the fitness)")
    out += _share_lines(report, "the calibration itself")
    return out


def offline_lines(report: dict[str, Any]) -> list[str]:
    """The report of a fit of a recording: verdict and cause, then -- on success -- the
    parameters; every figure says which samples it covers (kept by the fit, or all frames)."""
    ok = _succeeded(report)
    kept, frames = report.get("n_samples") or 0, report.get("n_frames") or 0
    over = f"the {kept} samples the fit kept" + (f" (of {frames} frames)" if frames else "")
    out = [_status_line(report)]
    if not ok:
        out.append(f"cause         {report.get('reason') or report.get('failure') or '?'}")
    out.append(f"fitness       {_fmt(report.get('fitness'))} mG RMS over {over}")
    pred, lim = report.get("predicted_heading_deg"), report.get("heading_limit_deg")
    if isinstance(pred, int | float):
        floor, noise = report.get("heading_floor_deg"), report.get("noise_mG")
        out.append(
            f"heading error ~{_fmt(pred)} deg RMS predicted, limit {_fmt(lim)} deg"
            + (
                f" (a perfect fit of these samples: ~{_fmt(floor, '.3f')} deg;"
                f" sensor noise {_fmt(noise, '.1f')} mG)"
                if isinstance(floor, int | float)
                else ""
            )
        )
    out += _share_lines(report, "the accelerometer and alignment")
    if not ok:
        out.append("parameters    none: the fit failed")
        return out
    out += _params_lines(report)
    b, a = report.get("field_spread_before_nT"), report.get("field_spread_after_nT")
    every = report.get("field_spread_after_all_nT")
    out.append(
        f"field spread  +-{_fmt(b, '.0f')} nT before -> +-{_fmt(a, '.0f')} nT after over {over}"
        + (f"; +-{_fmt(every, '.0f')} nT after over all {frames} frames" if frames else "")
    )
    return out


def coverage_text(missing: frozenset[int]) -> str:
    """Legend line and map of the sections still ``missing``. PURE."""
    return (
        f"sphere coverage: {N_SECTIONS - len(missing)}/{N_SECTIONS} sections "
        "(# covered, . still missing)\n" + coverage_map(missing)
    )


#: How long a motion warning from the bridge stays on the progress line (it repeats
#: the warning every few seconds while the motion lasts).
MOTION_NOTE_S = 5.0


def is_motion_warning(text: str) -> bool:
    """A STATUSTEXT telling the operator to move slower / steadier (``calibration.motion``)."""
    t = text.lower()
    return "slower" in t or "steadier" in t


def progress_note(missing: int, warning: str | None = None) -> str:
    """The note after the live bar: sections still missing, and a recent motion warning. PURE."""
    note = f"{missing} section{'' if missing == 1 else 's'} missing"
    return f"{note}  {warning}" if warning else note


def frame_times(seq: npt.ArrayLike, arrival_s: npt.ArrayLike) -> FloatArray:
    """Even frame times (s) from the device's frame counter, scaled by the arrival times.

    The device samples on a fixed tick and numbers its frames (``seq`` mod
    65536); lines arrive in bursts, so the counter spaces the frames and the
    arrival times only give the period. A counter that stands still or jumps
    back (a reset) leaves a gap of ten periods: the hand-held fit never
    averages across it. PURE.
    """
    q = np.asarray(seq, dtype=np.int64).reshape(-1)
    a = np.asarray(arrival_s, dtype=np.float64).reshape(-1)
    if q.size == 0:
        return np.empty(0)
    d = np.diff(q) % 65536
    broken = (d == 0) | (d >= 32768)
    steps = np.where(broken, 10, d).astype(np.float64)
    ticks = np.concatenate([[0.0], np.cumsum(steps)])
    counted = float(np.sum(d[~broken]))
    span = float(a[-1] - a[0]) if a.size > 1 else 0.0
    period = span / counted if counted > 0 and span > 0 else 0.1
    return np.asarray(ticks * period, dtype=np.float64)


#: Characters of one STATUSTEXT.
STATUSTEXT_CHARS = 50


class StatusTextChunks:
    """Joins MAVLink 2 STATUSTEXT chunks (same ``id``, in ``chunk_seq`` order) into whole texts.

    A text of more than 50 characters comes as chunks sharing a non-zero
    ``id``; the last is shorter than 50 characters. ``id`` 0 is a text on its
    own. PURE (takes any object with ``text``, ``id``, ``chunk_seq``).
    """

    def __init__(self) -> None:
        self._parts: dict[int, dict[int, str]] = {}

    def add(self, msg: Any) -> str | None:
        """One STATUSTEXT; the whole text once it is complete, else None."""
        text = str(msg.text)
        key = int(msg.id or 0)
        if key == 0:
            return text
        parts = self._parts.setdefault(key, {})
        parts[int(msg.chunk_seq or 0)] = text
        if len(text) >= STATUSTEXT_CHARS:
            return None
        del self._parts[key]
        return "".join(parts[k] for k in sorted(parts))
