"""The calibration method registry: one data bundle in, any method by name, one result out.

=====================  =======================================================  ==========================
name                   what it fits                                             data it needs
=====================  =======================================================  ==========================
``minmax``             the datasheet's on-board MAGCAL (offsets, x-relative     ``mag_G`` (``acc_g`` gates)
                       gains)
``twelve_position``    full 12-parameter affine from known attitudes            ``mag_G`` + ``attitudes`` +
                                                                                 reference NED vector
``scalar``             magnitude-only 9-parameter fit, both sensors             ``mag_G`` + ``acc_g``
``ellipsoid``          ArduPilot/PX4-style hard iron + symmetric soft iron      ``mag_G``
``ellipsoid_aligned``  ellipsoid + mag-to-accel rotation (alias ``best``)       ``mag_G`` + ``acc_g``
``accel_six_face``     accelerometer offsets + full matrix from six face means  ``face_means``
=====================  =======================================================  ==========================

Accelerometer calibration used by the magnetometer methods (the heading is
only as good as the gravity vector): the six-face fit when ``face_means``
are given, else ``accel_calibration`` (e.g. the stored one), else a scalar
fit of the tumble's accelerometer samples, else the nominal transfer. The
result always carries the accelerometer calibration it was computed with.

When the data is a *series* of consecutive frames (``t_s``, what a live
calibration records), ``ellipsoid_aligned`` fits it as a hand-held tumble
(:func:`~bridge.calibration.fits.alignment.fit_ellipsoid_aligned_series`): the
accelerometer (when neither six faces nor a calibration are given) and the
alignment come from window means that average a person's shake away, and the
report predicts the heading error the calibration leaves.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from types import MappingProxyType

import numpy as np
import numpy.typing as npt

from bridge.calibration.fits.accel_faces import Face, fit_six_face
from bridge.calibration.fits.acceptance import Acceptance, accept
from bridge.calibration.fits.alignment import fit_ellipsoid_aligned, fit_ellipsoid_aligned_series
from bridge.calibration.fits.ellipsoid import ReferenceField, fit_ellipsoid, reference_total_G
from bridge.calibration.fits.minmax import fit_minmax
from bridge.calibration.fits.sanity import SanityLimits
from bridge.calibration.fits.scalar import fit_scalar, fit_scalar_accel, fit_scalar_mag
from bridge.calibration.fits.twelve_position import fit_twelve_position
from bridge.core.calibration import AffineCalibration, Calibration, CalibrationResult
from bridge.core.wmm import EarthField
from bridge.types import BoolArray, FloatArray

#: The methods' own checks: structure only (radius, offsets, scaling, rotation). The
#: fitness (COMPASS_CAL_FIT) and how well the samples determine the result are judged
#: for every method alike by :func:`bridge.calibration.fits.acceptance.accept`.
_STRUCTURE_ONLY = SanityLimits(
    fitness_max_mG=float("inf"), offset_sd_max_mG=float("inf"), matrix_sd_max=float("inf")
)


def _frozen(a: npt.ArrayLike, shape_tail: tuple[int, ...], name: str, n: int | None) -> FloatArray:
    arr = np.array(a, dtype=np.float64)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise ValueError(f"{name} must be (N, {', '.join(map(str, shape_tail))}), got {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name} must have {n} rows like mag_G, got {arr.shape[0]}")
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class CalibrationData:
    """Everything one calibration session recorded (arrays are copied read-only).

    ``mag_G`` (N, 3) raw magnetometer in nominal gauss; ``acc_g`` (N, 3) the
    raw accelerometer of the same frames in nominal g; ``saturated`` (N,) flags
    frames with a channel at an ADC rail (never used for a fit); ``attitudes``
    (N, 3, 3) body->NED where the attitudes are known (twelve-position stops);
    ``face_means`` the mean raw accelerometer reading on each of the six faces;
    ``reference`` the local field -- an :class:`EarthField`, an NED vector in
    gauss, or just the total in gauss; ``accel_calibration`` a known
    accelerometer calibration (e.g. the stored one); ``t_s`` (N,) the frame
    times in seconds when the rows are consecutive frames (a recording, a
    live calibration) rather than a bag of samples.
    """

    mag_G: FloatArray
    acc_g: FloatArray | None = None
    saturated: BoolArray | None = None
    attitudes: FloatArray | None = None
    face_means: Mapping[Face, npt.ArrayLike] | None = None
    reference: ReferenceField = None
    accel_calibration: AffineCalibration | None = None
    t_s: FloatArray | None = None

    def __post_init__(self) -> None:
        mag = _frozen(self.mag_G, (3,), "mag_G", None)
        n = mag.shape[0]
        object.__setattr__(self, "mag_G", mag)
        if self.t_s is not None:
            t = np.array(self.t_s, dtype=np.float64).reshape(-1)
            if t.shape != (n,):
                raise ValueError(f"t_s must have {n} times like mag_G, got {t.shape[0]}")
            t.flags.writeable = False
            object.__setattr__(self, "t_s", t)
        if self.acc_g is not None:
            object.__setattr__(self, "acc_g", _frozen(self.acc_g, (3,), "acc_g", n))
        if self.attitudes is not None:
            object.__setattr__(self, "attitudes", _frozen(self.attitudes, (3, 3), "attitudes", n))
        if self.saturated is not None:
            sat = np.array(self.saturated, dtype=bool).reshape(-1)
            if sat.shape != (n,):
                raise ValueError(f"saturated must have {n} flags, got {sat.shape[0]}")
            sat.flags.writeable = False
            object.__setattr__(self, "saturated", sat)
        if self.face_means is not None:
            means: dict[Face, tuple[float, float, float]] = {}
            for face, v in self.face_means.items():
                if not isinstance(face, Face):
                    raise ValueError(f"face_means keys must be Face, got {face!r}")
                a = np.asarray(v, dtype=np.float64).reshape(-1)
                if a.shape != (3,):
                    raise ValueError(f"face mean for {face.px4_side} must be a 3-vector")
                means[face] = (float(a[0]), float(a[1]), float(a[2]))
            object.__setattr__(self, "face_means", MappingProxyType(means))
        ref = self.reference
        if ref is not None and not isinstance(ref, EarthField):
            a = np.array(ref, dtype=np.float64)
            if a.shape not in ((), (3,)):
                raise ValueError(
                    f"reference must be an EarthField, NED 3-vector or total, got {a.shape}"
                )
            a.flags.writeable = False
            object.__setattr__(self, "reference", float(a) if a.shape == () else a)
        reference_total_G(self.reference)  # validates: positive and finite

    @property
    def reference_total_G(self) -> float | None:
        """Total field strength in gauss, if known."""
        return reference_total_G(self.reference)

    @property
    def reference_ned_G(self) -> FloatArray | None:
        """Field vector (N, E, D) in gauss, if known (a bare total gives None)."""
        if isinstance(self.reference, EarthField):
            return self.reference.ned_G
        if isinstance(self.reference, np.ndarray):
            return self.reference.copy()
        return None

    def usable_rows(self) -> BoolArray:
        """Rows not flagged saturated (finiteness is each method's own check)."""
        n = self.mag_G.shape[0]
        return np.ones(n, dtype=bool) if self.saturated is None else ~self.saturated


Method = Callable[[CalibrationData], CalibrationResult]


def accel_calibration_for(data: CalibrationData) -> tuple[AffineCalibration, str]:
    """The accelerometer calibration the magnetometer methods use, and where it came from."""
    if data.face_means is not None:
        six = fit_six_face(data.face_means)
        if six.report.ok:
            return six.calibration.accel, "six-face"
    if data.accel_calibration is not None:
        return data.accel_calibration, "given"
    if data.acc_g is not None:
        acc = data.acc_g[data.usable_rows()]
        sc = fit_scalar_accel(acc)
        if sc.report.ok:
            return sc.calibration.accel, "scalar fit of the tumble"
    return AffineCalibration(), "nominal"


def _with_accel(
    result: CalibrationResult, accel: AffineCalibration, source: str
) -> CalibrationResult:
    rep = replace(result.report, notes=(*result.report.notes, f"accelerometer: {source}"))
    return CalibrationResult(Calibration(mag=result.calibration.mag, accel=accel), rep)


def _need_acc(data: CalibrationData, method: str) -> FloatArray:
    if data.acc_g is None:
        raise ValueError(f"method {method!r} needs accelerometer samples (acc_g)")
    return data.acc_g


def _minmax(data: CalibrationData) -> CalibrationResult:
    """Min/max of the samples a min/max needs: every sample of a tumble (its extremes are
    where an axis meets the field, at any tilt), or -- for the datasheet's own routine, a
    level turn and a turn on the side -- the device's level/side gating, which keeps the
    tilted frames between the turns from inflating x and y. The one that fits better."""
    ok = data.usable_rows()
    plain = fit_minmax(data.mag_G[ok])
    res = plain
    if data.acc_g is not None:
        gated = fit_minmax(data.mag_G[ok], acc_g=data.acc_g[ok])
        if gated.report.ok and not (
            plain.report.ok and plain.report.fitness_mG <= gated.report.fitness_mG
        ):
            res = replace_note(
                gated, "samples gated as the device's MAGCAL (level turn, side turn)"
            )
        elif plain.report.ok:
            res = replace_note(plain, "every sample used (a tumble)")
    return _with_accel(res, *accel_calibration_for(data))


def replace_note(result: CalibrationResult, note: str) -> CalibrationResult:
    """``result`` with ``note`` added to its report."""
    return CalibrationResult(
        result.calibration, replace(result.report, notes=(*result.report.notes, note))
    )


def _twelve_position(data: CalibrationData) -> CalibrationResult:
    if data.attitudes is None:
        raise ValueError("method 'twelve_position' needs the attitudes of the samples")
    ned = data.reference_ned_G
    if ned is None:
        raise ValueError("method 'twelve_position' needs the reference field as an NED vector")
    ok = data.usable_rows()
    acc = None if data.acc_g is None else data.acc_g[ok]
    res = fit_twelve_position(data.mag_G[ok], data.attitudes[ok], ned, acc_g=acc)
    if acc is None and res.report.ok:
        return _with_accel(res, *accel_calibration_for(data))
    return res


def _scalar(data: CalibrationData) -> CalibrationResult:
    """Both sensors from |B| and |g|; when the accelerometer's samples do not determine its
    fit (a shaken or a still unit), the magnetometer's stands on its own, beside the
    accelerometer calibration the other methods would use."""
    ok = data.usable_rows()
    acc = _need_acc(data, "scalar")[ok]
    res = fit_scalar(data.mag_G[ok], acc, data.reference_total_G)
    if res.report.ok:
        return res
    mag = fit_scalar_mag(data.mag_G[ok], data.reference_total_G)
    if not mag.report.ok:
        return res
    why = "; ".join(n.removeprefix("accel: ") for n in res.report.notes if n.startswith("accel:"))
    accel, source = accel_calibration_for(data)
    return _with_accel(replace_note(mag, f"accelerometer scalar fit failed ({why})"), accel, source)


def _ellipsoid(data: CalibrationData) -> CalibrationResult:
    accel, source = accel_calibration_for(data)
    res = fit_ellipsoid(
        data.mag_G,
        reference_field_G=data.reference,
        saturated=data.saturated,
        accel=accel,
        limits=_STRUCTURE_ONLY,
    )
    return CalibrationResult(
        res.calibration,
        replace(res.report, notes=(*res.report.notes, f"accelerometer: {source}")),
    )


def _ellipsoid_aligned(data: CalibrationData) -> CalibrationResult:
    acc = _need_acc(data, "ellipsoid_aligned")
    if data.t_s is not None:
        return _ellipsoid_aligned_series(data, acc)
    accel, source = accel_calibration_for(data)
    res = fit_ellipsoid_aligned(
        data.mag_G, acc, accel, data.reference, saturated=data.saturated, limits=_STRUCTURE_ONLY
    )
    return CalibrationResult(
        res.calibration,
        replace(res.report, notes=(*res.report.notes, f"accelerometer: {source}")),
    )


def _ellipsoid_aligned_series(data: CalibrationData, acc: FloatArray) -> CalibrationResult:
    assert data.t_s is not None
    known: AffineCalibration | None = None
    source = ""
    if data.face_means is not None:
        six = fit_six_face(data.face_means)
        if six.report.ok:
            known, source = six.calibration.accel, "six-face"
    if known is None and data.accel_calibration is not None:
        known, source = data.accel_calibration, "given"
    res = fit_ellipsoid_aligned_series(
        data.mag_G,
        acc,
        data.t_s,
        known,
        data.reference,
        saturated=data.saturated,
        limits=_STRUCTURE_ONLY,
    )
    if not source:
        fitted = res.calibration.accel != AffineCalibration()
        source = "fit of the tumble (hand-held)" if fitted else "nominal"
    return CalibrationResult(
        res.calibration,
        replace(res.report, notes=(*res.report.notes, f"accelerometer: {source}")),
    )


def _accel_six_face(data: CalibrationData) -> CalibrationResult:
    if data.face_means is None:
        raise ValueError("method 'accel_six_face' needs face_means")
    return fit_six_face(data.face_means)


#: Canonical method names, in the order a table should list them.
METHOD_NAMES: tuple[str, ...] = (
    "minmax",
    "twelve_position",
    "scalar",
    "ellipsoid",
    "ellipsoid_aligned",
    "accel_six_face",
)
ALIASES: Mapping[str, str] = MappingProxyType({"best": "ellipsoid_aligned"})
#: Methods whose data only a live unit gives (a recording of frames has neither):
#: what each needs.
LIVE_ONLY: Mapping[str, str] = MappingProxyType(
    {
        "twelve_position": "the attitudes of twelve known stops",
        "accel_six_face": "the unit held still on its six faces",
    }
)
BEST = ALIASES["best"]

_CANONICAL: dict[str, Method] = {
    "minmax": _minmax,
    "twelve_position": _twelve_position,
    "scalar": _scalar,
    "ellipsoid": _ellipsoid,
    "ellipsoid_aligned": _ellipsoid_aligned,
    "accel_six_face": _accel_six_face,
}
#: name (or alias) -> method; every entry takes a :class:`CalibrationData`.
METHODS: Mapping[str, Method] = MappingProxyType(
    {**_CANONICAL, **{alias: _CANONICAL[target] for alias, target in ALIASES.items()}}
)


def canonical_name(name: str) -> str:
    """The registry name for ``name`` (case-insensitive, aliases resolved); ``ValueError`` if unknown."""
    key = name.strip().lower()
    key = ALIASES.get(key, key)
    if key not in _CANONICAL:
        known = ", ".join([*METHOD_NAMES, *ALIASES])
        raise ValueError(f"unknown calibration method {name!r}; choose one of: {known}")
    return key


def fit(name: str, data: CalibrationData) -> CalibrationResult:
    """Run method ``name`` (or an alias such as ``"best"``) on ``data``, not yet judged.

    The first of :func:`calibrate`'s two steps: the result's report carries the fit's own
    figures and status, and ``method`` its canonical name; :func:`judge` applies the
    acceptance rule. A caller that needs the same fit judged against more than one
    :class:`Acceptance` (an operator's tighter target beside the default) fits once and
    judges each: ``judge(fit(name, data), data, acceptance)`` is ``calibrate(name, data,
    acceptance)``. Raises ``ValueError`` as :func:`calibrate` does.
    """
    key = canonical_name(name)
    res = _CANONICAL[key](data)
    if res.report.method != key:
        res = CalibrationResult(res.calibration, replace(res.report, method=key))
    return res


def judge(
    fitted: CalibrationResult, data: CalibrationData, acceptance: Acceptance | None = None
) -> CalibrationResult:
    """A :func:`fit` result of ``data`` judged by the acceptance rule (see :func:`calibrate`).

    ``fitted`` is not changed: judging it again with another ``acceptance`` gives what
    :func:`calibrate` with that acceptance gives.
    """
    return accept(fitted, data, acceptance, check_rotation=fitted.report.method == BEST)


def calibrate(
    name: str, data: CalibrationData, acceptance: Acceptance | None = None
) -> CalibrationResult:
    """Run method ``name`` (or an alias such as ``"best"``) on ``data`` and judge it.

    Every method's result goes through the one acceptance rule
    (:func:`bridge.calibration.fits.acceptance.accept`: the heading error it is
    predicted to leave, against a limit that scales with the sensor's noise and
    the number of samples; COMPASS_CAL_FIT as ``acceptance.fitness_max_mG``).
    The report's ``method`` is the canonical name; a failure's cause is in its
    ``reason``. Raises ``ValueError`` for an unknown name or when the data lack
    what the method needs; a fit that runs but fails comes back with a failure
    status, never an exception. The two steps are :func:`fit` and :func:`judge`.
    """
    return judge(fit(name, data), data, acceptance)
