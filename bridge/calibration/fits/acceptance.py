"""One acceptance rule for every method: the heading error the calibration is predicted to leave.

Every method of :mod:`bridge.calibration.fits.methods` ends here
(:func:`accept`), so no method can say MAG_CAL_SUCCESS -- or be saved -- when
its own figures condemn it. The rule is stated in docs/calibration.md
("When a calibration is accepted"); in short:

* **What the samples allow** (:class:`Evidence`, the same for every method):
  a reference fit -- the general ellipsoid (hard iron + symmetric soft iron,
  robust), the most a magnetometer calibration can explain -- of the very
  samples the method saw. Its residual is the sensor's own *noise* (and
  whatever no calibration removes); the uncertainty of its offsets and soft
  iron, from the residual and the geometry of the samples, is what those
  samples can determine (few samples, or a cap of the sphere, make it large).
* **What the calibration leaves** (:func:`predict`), in milligauss across the
  horizontal field ``H``, then as a heading error ``atan(e / H)``:

  - *systematic*: the calibration's own scatter of ``|B|`` over the kept
    samples beyond the noise, ``sqrt(max(0, s^2 - noise^2))`` -- what its model
    failed to explain (a min/max of a tumble, a wrong model);
  - *uncertainty*: the offset and soft-iron uncertainty of the samples;
  - *hand-held*: for a fitted frame series, the jackknife heading error of the
    accelerometer and alignment (:mod:`bridge.calibration.fits.handheld`);
  - (six faces: the accelerometer's residual tilt seen across ``tan(dip)``.)

* **The limit**: ``max(heading_max_deg, 3 x floor)``, the floor being what a
  perfect calibration fitted from ``N`` samples of that noise on the whole
  sphere would leave, ``atan(noise * sqrt(3 / N) / H)``. A quiet sensor is held
  to the operator's target (:data:`DEFAULT_HEADING_MAX_DEG`, 1 deg:
  ``Acceptance.heading_max_deg``; a live session takes
  ``CalibratorSettings.max_heading_error_deg``); a noisy one with few samples
  to what its noise and count allow -- not to a fixed number of milligauss.
  COMPASS_CAL_FIT bounds the fitness as in ArduPilot (``fitness_max_mG``).

A failure carries its cause in ``reason`` (the largest part, with what to do
about it); the figures say which samples they cover (``n_samples`` kept of
``n_frames``). PURE (numpy).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from bridge.calibration.fits.coverage import N_SECTIONS, sections
from bridge.calibration.fits.ellipsoid import (
    ReferenceField,
    fit_ellipsoid_geometry,
    reference_total_G,
)
from bridge.calibration.fits.samples import usable_mask
from bridge.calibration.fits.sanity import MagCalStatus, SanityLimits, check_mag_calibration
from bridge.calibration.fits.scalar import field_spread_nT
from bridge.core.calibration import CalibrationReport, CalibrationResult
from bridge.core.wmm import EarthField
from bridge.types import BoolArray, FloatArray

#: The operator's heading target (deg RMS) for a sensor quiet enough to reach it. 1 deg:
#: a good calibration of a real hand-held unit is predicted to leave less, while a
#: min/max of a real tumble (1.4-5 deg on the recordings in tests/data) still fails.
DEFAULT_HEADING_MAX_DEG = 1.0
#: How many times the floor (a perfect fit of the same samples) a calibration may leave.
FLOOR_FACTOR = 3.0
#: ArduPilot's COMPASS_CAL_FIT default (mG).
DEFAULT_FITNESS_MAX_MG = 16.0
#: Dip assumed when neither a location nor a turning accelerometer gives one.
ASSUMED_DIP_DEG = 60.0
#: Spread of the accelerometer's direction (RMS of unit-vector deviations) from which
#: it counts as having seen the unit turn: a still (or absent) accelerometer gives no dip.
_TURNING_ACC = 0.1

SUCCESS = MagCalStatus.MAG_CAL_SUCCESS.name


class CalibrationData(Protocol):
    """What the rule reads of :class:`bridge.calibration.fits.methods.CalibrationData`."""

    @property
    def mag_G(self) -> FloatArray: ...
    @property
    def acc_g(self) -> FloatArray | None: ...
    @property
    def saturated(self) -> BoolArray | None: ...
    @property
    def reference(self) -> ReferenceField: ...
    @property
    def reference_ned_G(self) -> FloatArray | None: ...


@dataclass(frozen=True, slots=True)
class Acceptance:
    """The limits of the rule: COMPASS_CAL_FIT and the operator's heading target."""

    fitness_max_mG: float = DEFAULT_FITNESS_MAX_MG
    heading_max_deg: float = DEFAULT_HEADING_MAX_DEG
    floor_factor: float = FLOOR_FACTOR


@dataclass(frozen=True, slots=True)
class Evidence:
    """What the samples allow, whatever the method: the reference ellipsoid's figures.

    ``frames`` usable (finite, unsaturated) frames; ``kept`` of them the
    reference fit used (``inliers``). Relative figures are fractions of the
    field: ``noise_rel`` the residual RMS, ``offset_sd_rel`` / ``matrix_sd``
    the largest one-sigma uncertainties. ``field_mG`` is the field strength the
    milligauss figures are given in (the reference's total, else the fitted
    radius at the nominal transfer); ``horizontal_mG`` turns them into degrees
    (``horizontal_source`` says where it came from). ``covered`` are the
    sphere sections (of 80) the raw samples reach about the reference centre:
    the same map whatever the method.
    """

    frames: int
    kept: int
    inliers: BoolArray
    noise_rel: float
    offset_sd_rel: float
    matrix_sd: float
    field_mG: float
    horizontal_mG: float
    horizontal_source: str
    covered: frozenset[int]

    @property
    def noise_mG(self) -> float:
        """The sensor's noise as the reference fit sees it (RMS, mG)."""
        return self.noise_rel * self.field_mG

    @property
    def floor_mG(self) -> float:
        """What a perfect fit of ``kept`` samples of this noise on the whole sphere leaves."""
        return self.noise_mG * math.sqrt(3.0 / max(self.kept, 1))


def _deg(mG: float, horizontal_mG: float) -> float:
    return math.degrees(math.atan2(mG, horizontal_mG))


def _unit(v: FloatArray) -> FloatArray:
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return np.asarray(v / np.where(n > 0.0, n, 1.0), dtype=np.float64)


def _horizontal(
    data: CalibrationData, field_mG: float, m_dir: FloatArray, rows: BoolArray
) -> tuple[float, str]:
    ref = data.reference
    if isinstance(ref, EarthField):
        return 1000.0 * float(ref.horizontal_G), "the WMM at the location"
    ned = data.reference_ned_G
    if ned is not None:
        return 1000.0 * float(np.hypot(ned[0], ned[1])), "the reference field"
    if data.acc_g is not None:
        a = np.asarray(data.acc_g, dtype=np.float64)[rows]
        ok = np.all(np.isfinite(a), axis=1) & (np.linalg.norm(a, axis=1) > 0.0)
        if np.count_nonzero(ok) >= 10:
            au = _unit(a[ok])
            spread = float(np.sqrt(np.mean(np.sum((au - au.mean(axis=0)) ** 2, axis=1))))
            if spread >= _TURNING_ACC:
                s = float(np.median(np.sum(au * m_dir[ok], axis=1)))
                dip = math.degrees(math.asin(max(-1.0, min(1.0, s))))
                return field_mG * math.cos(math.radians(dip)), (
                    f"the dip the accelerometer shows ({dip:.1f} deg)"
                )
    return field_mG * math.cos(math.radians(ASSUMED_DIP_DEG)), (
        f"an assumed {ASSUMED_DIP_DEG:.0f} deg dip (no location, no turning accelerometer)"
    )


def evidence(data: CalibrationData) -> Evidence | None:
    """The reference fit of ``data``'s magnetometer samples; None when they define no ellipsoid."""
    x = np.asarray(data.mag_G, dtype=np.float64)
    usable = usable_mask(x, data.saturated)
    fit = fit_ellipsoid_geometry(x, saturated=data.saturated)
    if fit is None or not (math.isfinite(fit.radius_G) and fit.radius_G > 0.0):
        return None
    total = reference_total_G(data.reference)
    field_mG = 1000.0 * (total if total is not None else fit.radius_G)
    d = (x - fit.offset) @ fit.matrix.T
    m_dir = _unit(np.where(np.isfinite(d), d, 0.0))
    horizontal_mG, source = _horizontal(data, field_mG, m_dir, fit.inliers)
    s = sections(d[usable])
    covered = frozenset(s[s >= 0].tolist())  # as ints, not one numpy scalar at a time
    return Evidence(
        frames=int(np.count_nonzero(usable)),
        kept=int(np.count_nonzero(fit.inliers)),
        inliers=fit.inliers,
        noise_rel=fit.fitness_mG / 1000.0 / fit.radius_G,
        offset_sd_rel=fit.offset_sd_G / fit.radius_G
        if math.isfinite(fit.offset_sd_G)
        else math.inf,
        matrix_sd=fit.matrix_sd if math.isfinite(fit.matrix_sd) else math.inf,
        field_mG=field_mG,
        horizontal_mG=horizontal_mG,
        horizontal_source=source,
        covered=covered,
    )


def raw_sections(data: CalibrationData) -> frozenset[int] | None:
    """Sphere sections the raw samples reach about the reference centre (None: no ellipsoid)."""
    ev = evidence(data)
    return None if ev is None else ev.covered


@dataclass(frozen=True, slots=True)
class Prediction:
    """The heading error a calibration is predicted to leave, its parts (mG) and the limit (deg)."""

    systematic_mG: float
    uncertainty_mG: float
    handheld_mG: float
    heading_deg: float
    floor_deg: float
    limit_deg: float

    @property
    def ok(self) -> bool:
        """Within the limit."""
        return self.heading_deg <= self.limit_deg


def predict(
    result: CalibrationResult, data: CalibrationData, ev: Evidence, acceptance: Acceptance
) -> Prediction:
    """What ``result`` leaves on the samples of ``data`` (see the module docstring)."""
    rep = result.report
    H = ev.horizontal_mG
    x = np.asarray(data.mag_G, dtype=np.float64)[ev.inliers]
    n = np.linalg.norm(result.calibration.mag.apply(x), axis=1)
    scatter_rel = float(np.std(n) / np.mean(n)) if n.size and np.mean(n) > 0 else math.inf
    systematic = ev.field_mG * math.sqrt(max(0.0, scatter_rel**2 - ev.noise_rel**2))
    uncertainty = ev.field_mG * math.hypot(ev.offset_sd_rel, ev.matrix_sd)
    hh = rep.heading_error_deg
    handheld = H * math.tan(math.radians(min(hh, 89.0))) if math.isfinite(hh) else 0.0
    total = math.sqrt(systematic**2 + uncertainty**2 + handheld**2)
    floor = _deg(ev.floor_mG, H)
    limit = max(acceptance.heading_max_deg, acceptance.floor_factor * floor)
    heading = _deg(total, H) if math.isfinite(total) else math.inf
    return Prediction(systematic, uncertainty, handheld, heading, floor, limit)


def _d(deg: float) -> str:
    """Degrees as the reasons print them: two decimals, or two significant digits below 0.1."""
    return f"{deg:.2f}" if abs(deg) >= 0.1 or deg == 0.0 else f"{deg:.2g}"


def _cause(p: Prediction, ev: Evidence, rep: CalibrationReport, method: str) -> tuple[str, str]:
    """The status and the reason of a calibration over the limit: its largest part, and what to do."""
    head = f"heading error ~{_d(p.heading_deg)} deg > {_d(p.limit_deg)}"
    parts = {
        "systematic": p.systematic_mG,
        "uncertainty": p.uncertainty_mG,
        "handheld": p.handheld_mG,
    }
    worst = max(parts, key=lambda k: parts[k])
    residuals = MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH.name
    if worst == "handheld":
        # Mostly the accelerometer and the alignment a hand's shake left uncertain (the
        # notes say from how many frames and how much shake).
        return residuals, f"{head}: turn slower / steadier"
    if worst == "systematic":
        return residuals, (
            f"{head}: {method} leaves |B| scattered {p.systematic_mG:.1f} mG beyond the sensor's "
            f"{ev.noise_mG:.1f} mG noise: use the best method, or keep iron away while turning"
        )
    return MagCalStatus.MAG_CAL_FAILED.name, (
        f"{head}: offsets known to only +-{ev.offset_sd_rel * ev.field_mG:.1f} mG "
        f"({len(ev.covered)}/{N_SECTIONS} sections, {ev.kept} samples): "
        "turn the unit through more directions"
    )


def _judged(
    rep: CalibrationReport, ev: Evidence | None, p: Prediction | None, mag_all: FloatArray | None
) -> CalibrationReport:
    extra: dict[str, object] = {}
    if ev is not None:
        extra.update(
            n_frames=ev.frames,
            noise_mG=ev.noise_mG,
            horizontal_mG=ev.horizontal_mG,
            sections_covered=len(ev.covered),
        )
    if p is not None:
        extra.update(
            predicted_heading_deg=p.heading_deg,
            heading_floor_deg=p.floor_deg,
            heading_limit_deg=p.limit_deg,
        )
    if mag_all is not None and mag_all.shape[0] >= 2:
        hp, rms = field_spread_nT(mag_all)
        extra.update(field_spread_after_all_nT=hp, field_rms_after_all_nT=rms)
    return replace(rep, **extra)  # type: ignore[arg-type]


def fail(result: CalibrationResult, status: str, reason: str) -> CalibrationResult:
    """``result`` failed with ``reason`` (first among the notes too)."""
    rep = result.report
    notes = rep.notes if reason in rep.notes else (reason, *rep.notes)
    return CalibrationResult(
        result.calibration, replace(rep, status=status, reason=reason, notes=notes)
    )


def _first_reason(rep: CalibrationReport) -> str:
    if rep.reason:
        return rep.reason
    own = [n for n in rep.notes if not n.startswith(("accelerometer:", "no reference field"))]
    return own[0] if own else rep.status


def _accel_only(
    result: CalibrationResult, data: CalibrationData, acceptance: Acceptance
) -> CalibrationResult:
    """Six faces: the residual tilt (|g| scatter after the fit) seen across tan(dip)."""
    rep = result.report
    if not rep.ok:
        return replace_reason(result)
    ref = data.reference
    dip = float(ref.inclination_deg) if isinstance(ref, EarthField) else ASSUMED_DIP_DEG
    tilt = rep.gravity_rms_after_mg / 1000.0 if math.isfinite(rep.gravity_rms_after_mg) else 0.0
    heading = math.degrees(math.atan(math.tan(tilt) * math.tan(math.radians(abs(dip)))))
    judged = replace(
        rep, predicted_heading_deg=heading, heading_limit_deg=acceptance.heading_max_deg
    )
    res = CalibrationResult(result.calibration, judged)
    if heading <= acceptance.heading_max_deg:
        return res
    return fail(
        res,
        MagCalStatus.MAG_CAL_FAILED.name,
        f"heading error ~{heading:.2f} deg > {acceptance.heading_max_deg:.2f} from the faces' residual "
        "tilt: hold each face still and square",
    )


def replace_reason(result: CalibrationResult) -> CalibrationResult:
    """A failed result with its cause in ``reason``."""
    rep = result.report
    return CalibrationResult(result.calibration, replace(rep, reason=_first_reason(rep)))


def accept(
    result: CalibrationResult,
    data: CalibrationData,
    acceptance: Acceptance | None = None,
    *,
    check_rotation: bool = False,
) -> CalibrationResult:
    """``result`` judged by the rule (status, ``reason`` and the figures in its report)."""
    acc = acceptance or Acceptance()
    rep = result.report
    if rep.method == "accel_six_face":
        return _accel_only(result, data, acc)
    if rep.method == "twelve_position":
        return _known_attitudes(result, data, acc)
    ev = evidence(data)
    mag = result.calibration.mag
    usable = usable_mask(np.asarray(data.mag_G), data.saturated)
    mag_all = mag.apply(np.asarray(data.mag_G)[usable]) if rep.ok else None
    if not rep.ok:
        return replace_reason(CalibrationResult(result.calibration, _judged(rep, ev, None, None)))
    # The bounds every method answers to (ArduPilot's: radius, offsets, scaling, COMPASS_CAL_FIT).
    sanity = check_mag_calibration(
        mag,
        radius_G=rep.radius_G
        if math.isfinite(rep.radius_G)
        else 1e-3 * (ev.field_mG if ev else 0.0),
        fitness_mG=rep.fitness_mG,
        check_rotation=check_rotation,
        limits=_limits(acc),
    )
    if ev is None:
        judged = CalibrationResult(result.calibration, _judged(rep, None, None, mag_all))
        if not sanity.ok:
            why = _sanity_reason(sanity.reasons[0], sanity.status, rep)
            return fail(judged, sanity.status.name, why)
        return fail(
            judged,
            MagCalStatus.MAG_CAL_FAILED.name,
            "samples do not define an ellipsoid: turn the unit through more directions",
        )
    p = predict(result, data, ev, acc)
    judged = CalibrationResult(result.calibration, _judged(rep, ev, p, mag_all))
    if not sanity.ok:
        return fail(
            judged, sanity.status.name, _sanity_reason(sanity.reasons[0], sanity.status, rep)
        )
    if not p.ok:
        return fail(judged, *_cause(p, ev, rep, rep.method))
    return judged


def _sanity_reason(why: str, status: MagCalStatus, rep: CalibrationReport) -> str:
    """A bound's reason with what to do: over COMPASS_CAL_FIT because a hand shook the
    accelerometer (a hand-held fit's fitness counts it), or because the field itself
    scatters; the other bounds say what is out of range."""
    if status is not MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH:
        return f"{why}: check the mounting and the field around the unit, then recalibrate"
    if math.isfinite(rep.residual_mG) and rep.fitness_mG > math.sqrt(2.0) * rep.residual_mG:
        return f"{why} (heading error ~{_d(rep.heading_error_deg)} deg): turn slower / steadier"
    return f"{why}: keep iron away while turning, or raise COMPASS_CAL_FIT"


def _limits(acc: Acceptance) -> SanityLimits:
    return SanityLimits(fitness_max_mG=acc.fitness_max_mG)


def _known_attitudes(
    result: CalibrationResult, data: CalibrationData, acc: Acceptance
) -> CalibrationResult:
    """Twelve known attitudes: the fit's residual against the reference vectors across ``H``.

    Its samples are averaged stops, not a cloud an ellipsoid could be fitted to;
    the residual (vector, mG) is what the calibration leaves at those attitudes.
    """
    rep = result.report
    if not rep.ok:
        return replace_reason(result)
    ned = data.reference_ned_G
    H = 1000.0 * float(np.hypot(ned[0], ned[1])) if ned is not None else math.nan
    heading = _deg(rep.fitness_mG, H) if math.isfinite(H) and H > 0 else math.inf
    res = CalibrationResult(
        result.calibration,
        replace(
            rep,
            n_frames=int(np.count_nonzero(usable_mask(np.asarray(data.mag_G), data.saturated))),
            horizontal_mG=H,
            predicted_heading_deg=heading,
            heading_limit_deg=acc.heading_max_deg,
        ),
    )
    if heading <= acc.heading_max_deg:
        return res
    return fail(
        res,
        MagCalStatus.MAG_CAL_FAILED_RESIDUALS_HIGH.name,
        f"heading error ~{heading:.2f} deg > {acc.heading_max_deg:.2f} at the known attitudes: "
        "set each attitude squarely and hold it still",
    )
