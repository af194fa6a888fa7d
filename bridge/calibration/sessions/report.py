"""A finished session's typed report: what was calibrated, how, how well, or why not.

:class:`SessionReport` holds what front ends show and the calibration store
keeps: the method, the verdict (``failure`` None, or a neutral
:class:`Failure` with the reason), the magnetometer result as ArduPilot's
COMPASS_* figures (the calibration's :class:`~bridge.core.calibration.ArduPilotView`,
or a device page's), the host fit's quality including the
hand-held figures (:class:`FitQuality`), an accelerometer or level result, the
device's answer for an on-board routine, and the notes of the fit.

:meth:`SessionReport.to_dict` is its JSON form (events, zenoh, the calibration
file): flat, with the key names the project's tools read (``ofs_x``,
``fitness``, ``heading_error_deg`` ...), NaN as null;
:meth:`SessionReport.from_dict` reads it back. The MAVLink adapter maps a
report to MAG_CAL_REPORT (:mod:`bridge.mavlink.calmap`).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from bridge.calibration.fits.sanity import MagCalStatus
from bridge.calibration.sessions.state import Mode
from bridge.core.calibration import AffineCalibration, ArduPilotView, CalibrationReport
from bridge.protocol.gmr import ParamsFrame
from bridge.types import Vec3

_NAN = math.nan
PARAM_NAMES = ("xoff", "yoff", "zoff", "kx", "ky", "kz", "gxoff", "gyoff", "gzoff")
MAG_PARAM_NAMES = PARAM_NAMES[:6]  #: the flash page's magnetometer half


class Failure(enum.StrEnum):
    """Why a session ended without a result, in the terms of the sanity checks."""

    FAILED = "failed"  #: no usable fit, a time-out, a device refusal, an internal error
    ORIENTATION = "failed_orientation"  #: the magnetometer is rotated against the accelerometer
    RADIUS = "failed_radius"  #: the fitted field strength is implausible (or far from the WMM's)
    OFFSETS = "failed_offsets"  #: hard iron beyond what a compass can be corrected for
    SCALING = "failed_scaling"  #: soft iron (diagonal / off-diagonal) out of bounds
    RESIDUALS = "failed_residuals"  #: fitness over its limit, or the heading error predicted

    @classmethod
    def of_verdict(cls, status: str) -> Failure | None:
        """The fit's verdict (:mod:`bridge.calibration`'s status names) in these terms."""
        try:
            code = MagCalStatus.parse(status)
        except ValueError:
            return cls.FAILED
        return _VERDICTS.get(code, cls.FAILED)


_VERDICTS: dict[MagCalStatus, Failure | None] = {
    MagCalStatus.MAG_CAL_SUCCESS: None,
    MagCalStatus.MAG_CAL_FAILED_ORIENTATION: Failure.ORIENTATION,
    MagCalStatus.MAG_CAL_FAILED_RADIUS: Failure.RADIUS,
    MagCalStatus.MAG_CAL_FAILED_OFFSETS: Failure.OFFSETS,
    MagCalStatus.MAG_CAL_FAILED_DIAG_SCALING: Failure.SCALING,
    MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH: Failure.RESIDUALS,
}


def _f(v: object, default: float = _NAN) -> float:
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else default


def _json(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _vec(v: Any) -> Vec3:
    a = [float(x) for x in v]
    return (a[0], a[1], a[2])


@dataclass(frozen=True, slots=True)
class FitQuality:
    """How good a host magnetometer fit is (NaN: not known for this fit).

    ``fitness_mG`` is ArduPilot's MAG_CAL_REPORT.fitness (RMS residual); for a
    hand-held series it includes the heading error the calibration is
    predicted to leave, ``residual_mG`` being the magnetometer's own residual.
    ``heading_error_deg`` / ``tilt_error_deg`` are those predictions,
    ``motion_g`` the linear acceleration seen, ``window_s`` the averaging
    window; ``orientation_confidence`` ArduPilot's orientation figure of merit.
    """

    fitness_mG: float = _NAN
    residual_mG: float = _NAN
    heading_error_deg: float = _NAN
    tilt_error_deg: float = _NAN
    motion_g: float = _NAN
    window_s: float = _NAN
    radius_mG: float = _NAN
    coverage_pct: float = _NAN
    field_spread_before_nT: float = _NAN
    field_spread_after_nT: float = _NAN
    orientation_confidence: float = _NAN
    predicted_heading_deg: float = _NAN
    heading_limit_deg: float = _NAN
    heading_floor_deg: float = _NAN
    noise_mG: float = _NAN
    field_spread_after_all_nT: float = _NAN
    n_samples: int = 0
    n_rejected: int = 0
    n_frames: int = 0
    sections_covered: int = 0

    @classmethod
    def of(cls, report: CalibrationReport, confidence: float = _NAN) -> FitQuality:
        """The figures of a fit's report."""
        return cls(
            fitness_mG=report.fitness_mG,
            residual_mG=report.residual_mG,
            heading_error_deg=report.heading_error_deg,
            tilt_error_deg=report.tilt_error_deg,
            motion_g=report.motion_g,
            window_s=report.window_s,
            radius_mG=1000.0 * report.radius_G,
            coverage_pct=report.coverage_pct,
            field_spread_before_nT=report.field_spread_before_nT,
            field_spread_after_nT=report.field_spread_after_nT,
            orientation_confidence=confidence,
            predicted_heading_deg=report.predicted_heading_deg,
            heading_limit_deg=report.heading_limit_deg,
            heading_floor_deg=report.heading_floor_deg,
            noise_mG=report.noise_mG,
            field_spread_after_all_nT=report.field_spread_after_all_nT,
            n_samples=report.n_samples,
            n_rejected=report.n_rejected,
            n_frames=report.n_frames,
            sections_covered=report.sections_covered,
        )


_FIT_KEYS = (
    "residual_mG",
    "heading_error_deg",
    "tilt_error_deg",
    "motion_g",
    "window_s",
    "radius_mG",
    "coverage_pct",
    "field_spread_before_nT",
    "field_spread_after_nT",
    "orientation_confidence",
    "predicted_heading_deg",
    "heading_limit_deg",
    "heading_floor_deg",
    "noise_mG",
    "field_spread_after_all_nT",
)


@dataclass(frozen=True, slots=True)
class AccelParams:
    """A six-face accelerometer fit: offsets (g), matrix, |g| spread before/after, face means."""

    offset_g: Vec3
    matrix: tuple[Vec3, Vec3, Vec3]
    gravity_spread_before_mg: float = _NAN
    gravity_spread_after_mg: float = _NAN
    faces: Mapping[str, Vec3] = field(default_factory=dict)  #: PX4 side -> raw mean (g)

    @classmethod
    def of(
        cls, accel: AffineCalibration, report: CalibrationReport, faces: Mapping[str, Any]
    ) -> AccelParams:
        """The figures of a six-face fit and the face means it used."""
        m = accel.matrix
        return cls(
            _vec(accel.offset),
            (_vec(m[0]), _vec(m[1]), _vec(m[2])),
            report.gravity_spread_before_mg,
            report.gravity_spread_after_mg,
            {side: _vec(np.asarray(v).tolist()) for side, v in faces.items()},
        )


@dataclass(frozen=True, slots=True)
class LevelTrim:
    """A host level calibration: the trim found (deg) and how still the unit was (mg)."""

    roll_deg: float
    pitch_deg: float
    spread_mg: float


@dataclass(frozen=True, slots=True)
class DeviceOutcome:
    """What an on-board routine left: the device's answer, its flash page after, the spans.

    ``answer`` is the routine's result as named values (``xoff .. kz`` for
    MAGCAL,END, ``gxoff .. gzoff`` for ACCCAL; empty after a refusal),
    ``params`` the page PAR,GET read back (None: not read), ``spans`` the last
    ``$PGMRC`` spans in counts (MAGCAL), ``error`` the device's refusal code.
    """

    answer: Mapping[str, float] = field(default_factory=dict)
    params: Mapping[str, float] | None = None
    spans: tuple[int, int, int] | None = None
    error: str = ""


def params_dict(page: ParamsFrame | None) -> dict[str, float] | None:
    """A flash page as named values (None stays None)."""
    return None if page is None else dict(zip(PARAM_NAMES, page.values(), strict=True))


@dataclass(frozen=True, slots=True)
class SessionReport:
    """A session's result (see the module docstring)."""

    mode: Mode
    method: str
    failure: Failure | None = None
    reason: str = ""
    autosaved: bool = False
    mag: ArduPilotView | None = None
    fit: FitQuality | None = None
    accel: AccelParams | None = None
    level: LevelTrim | None = None
    device: DeviceOutcome | None = None
    yaw_deg: float | None = None
    notes: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        """A result (no failure)."""
        return self.failure is None

    def saved(self) -> SessionReport:
        """This report, marked as applied and saved without an accept."""
        return replace(self, autosaved=True)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (flat; NaN as null)."""
        out: dict[str, Any] = {
            "mode": self.mode.value,
            "method": self.method,
            "status": "success" if self.failure is None else self.failure.value,
            "failure": None if self.failure is None else self.failure.value,
            "autosaved": self.autosaved,
        }
        if self.reason:
            out["reason"] = self.reason
        if self.mag is not None:
            m = self.mag
            for i, a in enumerate("xyz"):
                out[f"ofs_{a}"] = m.ofs_mG[i]
                out[f"diag_{a}"] = m.diag[i]
                out[f"offdiag_{a}"] = m.offdiag[i]
            out["scale_factor"] = m.scale
            out["rotation_deg"] = m.rotation_deg
        if self.fit is not None:
            q = self.fit
            out["fitness"] = _json(q.fitness_mG)
            out.update({k: _json(getattr(q, k)) for k in _FIT_KEYS})
            out["n_samples"], out["n_rejected"] = q.n_samples, q.n_rejected
            out["n_frames"], out["sections_covered"] = q.n_frames, q.sections_covered
        if self.accel is not None:
            c = self.accel
            out["offset_g"] = list(c.offset_g)
            out["matrix"] = [list(r) for r in c.matrix]
            out["gravity_spread_before_mg"] = _json(c.gravity_spread_before_mg)
            out["gravity_spread_after_mg"] = _json(c.gravity_spread_after_mg)
            out["faces"] = {side: list(v) for side, v in c.faces.items()}
        if self.level is not None:
            lv = self.level
            out["trim_roll_deg"], out["trim_pitch_deg"] = lv.roll_deg, lv.pitch_deg
            out["accel_spread_mg"] = lv.spread_mg
        if self.device is not None:
            d = self.device
            out["device"] = dict(d.answer)
            out["device_params"] = None if d.params is None else dict(d.params)
            out["spans"] = None if d.spans is None else list(d.spans)
            if d.error:
                out["device_error"] = d.error
        if self.yaw_deg is not None:
            out["yaw_deg"] = self.yaw_deg
        out["notes"] = list(self.notes)
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SessionReport:
        """A report from its JSON form; raises ``ValueError`` when ``mode`` is not one.

        The JSON form keeps the magnetometer's rotation as its angle (``rotation_deg``,
        what front ends show), not its axis: read back, the rotation is that angle about z.
        """
        failure = d.get("failure")
        mag = fit = accel = level = device = None
        if "ofs_x" in d:
            mag = ArduPilotView(
                (_f(d["ofs_x"], 0.0), _f(d.get("ofs_y"), 0.0), _f(d.get("ofs_z"), 0.0)),
                _vec(_f(d.get(f"diag_{a}"), 1.0) for a in "xyz"),
                _vec(_f(d.get(f"offdiag_{a}"), 0.0) for a in "xyz"),
                _f(d.get("scale_factor"), 1.0),
                (0.0, 0.0, math.radians(_f(d.get("rotation_deg"), 0.0))),
            )
        if "fitness" in d:
            fit = FitQuality(
                _f(d.get("fitness")),
                **{k: _f(d.get(k)) for k in _FIT_KEYS},
                n_samples=int(_f(d.get("n_samples"), 0.0)),
                n_rejected=int(_f(d.get("n_rejected"), 0.0)),
                n_frames=int(_f(d.get("n_frames"), 0.0)),
                sections_covered=int(_f(d.get("sections_covered"), 0.0)),
            )
        if "offset_g" in d:
            rows = d.get("matrix") or [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]
            accel = AccelParams(
                _vec(d["offset_g"]),
                (_vec(rows[0]), _vec(rows[1]), _vec(rows[2])),
                _f(d.get("gravity_spread_before_mg")),
                _f(d.get("gravity_spread_after_mg")),
                {str(k): _vec(v) for k, v in (d.get("faces") or {}).items()},
            )
        if "trim_roll_deg" in d:
            level = LevelTrim(
                _f(d["trim_roll_deg"]), _f(d.get("trim_pitch_deg")), _f(d.get("accel_spread_mg"))
            )
        if "device" in d:
            spans = d.get("spans")
            device = DeviceOutcome(
                {str(k): float(v) for k, v in (d.get("device") or {}).items()},
                d.get("device_params"),
                None if spans is None else (int(spans[0]), int(spans[1]), int(spans[2])),
                str(d.get("device_error") or ""),
            )
        yaw = d.get("yaw_deg")
        return cls(
            mode=Mode(str(d.get("mode"))),
            method=str(d.get("method", "")),
            failure=None if failure is None else Failure(failure),
            reason=str(d.get("reason", "")),
            autosaved=bool(d.get("autosaved", False)),
            mag=mag,
            fit=fit,
            accel=accel,
            level=level,
            device=device,
            yaw_deg=None if yaw is None else float(yaw),
            notes=tuple(str(n) for n in d.get("notes") or ()),
        )


def fit_report(
    mode: Mode,
    mag: AffineCalibration,
    report: CalibrationReport,
    *,
    autosaved: bool = False,
    confidence: float = _NAN,
) -> SessionReport:
    """A magnetometer fit's report (its verdict, figures and notes); a failure's reason is
    the fit's ``reason`` -- the cause, with what to do -- (else its first own note)."""
    failure = Failure.of_verdict(report.status)
    reason = ""
    if failure is not None:
        reasons = [
            n for n in report.notes if not n.startswith(("accelerometer:", "no reference field"))
        ]
        reason = report.reason or (reasons[0] if reasons else failure.value)
    return SessionReport(
        mode=mode,
        method=report.method,
        failure=failure,
        reason=reason,
        autosaved=autosaved,
        mag=mag.ardupilot_view(),
        fit=FitQuality.of(report, confidence),
        notes=report.notes,
    )


def failure_report(
    mode: Mode, reason: str, failure: Failure = Failure.FAILED, **extra: Any
) -> SessionReport:
    """A session that ended without a result (``extra``: more fields, e.g. ``device``)."""
    return SessionReport(mode=mode, method=mode.value, failure=failure, reason=reason, **extra)
