"""The host's calibration sessions: magnetometer, six faces, level, fixed yaw (pure).

* :class:`MagSession` -- ArduPilot's two-step magnetometer collection
  (:class:`~bridge.calibration.sessions.collect.MagCollector`), step one's sphere and
  the final fit of every frame in the worker, judged by the acceptance rule
  (:mod:`bridge.calibration.fits.acceptance`: the heading error predicted, against
  the session's COMPASS_CAL_FIT and heading limit). A success waits for accept
  unless ``autosave``; ``retry`` starts a failed fit over (ArduPilot's retry);
* :class:`FaceSession` -- PX4's six faces, then the six-face fit (saved at once);
* :class:`LevelSession` -- one still average, then the level trim (saved at once);
* :class:`FixedYawSession` -- ArduPilot's ``mag_cal_fixed_yaw``, done when it is made
  (:func:`fixed_yaw_result` computes it from recent frames).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from bridge.calibration.fits.accel_faces import Face, fit_six_face, level_trim
from bridge.calibration.fits.acceptance import Acceptance
from bridge.calibration.fits.fixed_yaw import attitude_from_gravity, fixed_yaw_calibration
from bridge.calibration.fits.methods import BEST, CalibrationData, calibrate
from bridge.calibration.fits.sanity import (
    SanityResult,
    check_accel_calibration,
    orientation_confidence,
)
from bridge.calibration.sessions.base import (
    Action,
    Apply,
    Compute,
    Emit,
    FitContext,
    Job,
    Progress,
    Session,
)
from bridge.calibration.sessions.collect import (
    FaceCollector,
    MagCollector,
    StillCollector,
    frame_vectors,
    sphere_step,
)
from bridge.calibration.sessions.motion import MotionJudge
from bridge.calibration.sessions.report import (
    AccelParams,
    Failure,
    LevelTrim,
    SessionReport,
    fit_report,
)
from bridge.calibration.sessions.state import (
    CalibratorSettings,
    Mode,
    Outcome,
    Phase,
    Result,
    number,
)
from bridge.core.calibration import (
    AffineCalibration,
    Calibration,
    CalibrationReport,
    CalibrationResult,
)
from bridge.core.wmm import EarthField, earth_field
from bridge.events import Severity
from bridge.protocol.gmr import AttitudeFrame
from bridge.types import FloatArray

#: What a level calibration asks of the operator (host and on-board alike).
LEVEL_TEXT = "Keep the vehicle level and still"
LEVEL_INSTRUCTION = "keep the vehicle level and still"


class MagSession(Session):
    """A host magnetometer calibration (see the module docstring).

    ``fitness_limit_mG`` is COMPASS_CAL_FIT when the session starts (ArduPilot
    fixes its tolerance at the start too); ``seed`` makes the buffer's
    thinning repeatable.
    """

    mode = Mode.MAG

    def __init__(
        self,
        settings: CalibratorSettings,
        now: float,
        *,
        retry: bool = False,
        autosave: bool = False,
        delay_s: float = 0.0,
        fitness_limit_mG: float | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__(settings, now, autosave=autosave)
        self.retry = retry
        self.delay_s = delay_s
        self.start_at = now + delay_s
        limit = settings.fitness_max_mG if fitness_limit_mG is None else fitness_limit_mG
        self.fitness_limit_mG = float(limit)
        self._seed = seed
        self.collector = self._collector()
        self.result: Calibration | None = None  #: the fitted calibration (success only)

    def _collector(self) -> MagCollector:
        st = self.settings
        seed = self._seed if self.attempt == 1 else 1000 * self._seed + self.attempt
        return MagCollector(
            st.capacity, seed=seed, judge=MotionJudge(st.motion_limit_g, st.motion_interval_s)
        )

    @property
    def pending_accept(self) -> bool:
        """The fit succeeded and waits for accept."""
        return self.phase is Phase.SUCCEEDED and not self.accepted

    def _progress(self, hint: bool, percent: float | None) -> Progress:
        if percent is not None:
            return Progress(percent)
        col = self.collector
        direction = col.direction_hint() if hint else (0.0, 0.0, 0.0)
        return Progress(col.percent, col.mask, direction)

    def begin(self, now: float) -> list[Action]:
        """Started; collecting at once unless delayed."""
        out: list[Action] = [
            self.started(
                "Calibration started: mag",
                retry=self.retry,
                autosave=self.autosave,
                delay_s=self.delay_s,
            )
        ]
        if self.delay_s == 0.0:
            out += self.collect(now)
        return out

    def _tick_waiting(self, now: float) -> list[Action]:
        return self.collect(now) if now >= self.start_at else []

    def feed(self, frame: object, now: float) -> list[Action]:
        """Every attitude frame: the collector (and its motion judge); the fits when full."""
        if not isinstance(frame, AttitudeFrame) or not self.running:
            return []
        out: list[Action] = []
        if self.phase is Phase.WAITING:
            if now < self.start_at:
                return []
            out += self.collect(now)
        self.last_frame_at = now
        col = self.collector
        mag, acc, sat = frame_vectors(frame)
        col.offer(mag, acc, sat, now)
        warning = col.pop_motion_warning()
        if warning is not None:
            data = {"mode": self.mode.value, **warning.data()}
            out.append(Emit("calibration.motion", warning.text, Severity.WARNING, data))
        if col.full and not self.busy:
            if col.step == 1:
                self.pending = Compute("sphere", _sphere_job(col.acceptor.samples))
            else:
                self.pending = Compute("fit", self._fit_job())
                self.phase = Phase.FITTING
            out.append(self.pending)
        return out + self.maybe_progress(now)

    def _fit_job(self) -> Any:
        col = self.collector
        mag, acc = col.data()
        t, mag_all, acc_all, sat_all = col.series.arrays()
        limit, max_err = self.fitness_limit_mG, self.settings.max_heading_error_deg

        def fit(ctx: FitContext) -> tuple[CalibrationResult, float]:
            current = ctx.calibration.accel
            # The current accelerometer calibration sets the tilt, hence the heading at high
            # dip; an uncalibrated (identity) one is better replaced by a fit of the tumble.
            accel = None if current == AffineCalibration() else current
            # Every frame of the collection, in order: the hand-held fit averages a shake away.
            data = CalibrationData(
                mag_all, acc_all, sat_all, reference=ctx.field, accel_calibration=accel, t_s=t
            )
            # The one acceptance rule, with COMPASS_CAL_FIT as the session started with it.
            res = calibrate(BEST, data, Acceptance(fitness_max_mG=limit, heading_max_deg=max_err))
            conf = math.nan
            if res.report.ok:
                cal = res.calibration
                conf = orientation_confidence(cal.mag.apply(mag), cal.accel.apply(acc))
            return res, conf

        return fit

    def _resolved(self, job: Job, value: Any, now: float) -> list[Action]:
        assert isinstance(job, Compute)
        if job.what == "sphere":
            if value is None:
                return self.fail("sphere fit failed (field radius)", Failure.RADIUS, now=now)
            self.collector.begin_step_two(value[0], value[1])
            self.step = 2
            return [self.progress_event(now)]
        res, conf = value
        ok = res.report.ok
        autosaved = self.autosave and ok
        report = fit_report(
            self.mode, res.calibration.mag, res.report, autosaved=autosaved, confidence=conf
        )
        if not ok:
            assert report.failure is not None
            return self.fail(report.reason, report.failure, report=report, now=now)
        self.result = res.calibration
        out = self.succeed(report)
        if self.autosave:
            self.accepted = True
            out.append(Apply(res.calibration, "mag", report, write_device=True))
        return out

    def _retry(self, reason: str, now: float) -> list[Action] | None:
        if not self.retry:
            return None
        # ArduPilot's retry: a fresh attempt at once (no start delay after the first).
        self.attempt += 1
        self.step = 1
        self.pending = None
        self.collector = self._collector()
        notice = self.instruction(
            f"Attempt {self.attempt}: keep turning",
            Severity.WARNING,
            instruction="keep turning the unit through every direction",
            attempt=self.attempt,
            reason=reason,
        )
        return [notice, *self.collect(now)]

    def accept(self) -> tuple[Outcome, list[Action]]:
        """A fit waiting for accept is applied, saved and written to the device."""
        if self.pending_accept and self.result is not None:
            self.accepted = True
            return Outcome(Result.ACCEPTED, "accepted"), [
                Apply(self.result, "mag", self.report, write_device=True)
            ]
        return super().accept()


def _sphere_job(samples: FloatArray) -> Any:
    def sphere(ctx: FitContext) -> tuple[FloatArray, float] | None:
        return sphere_step(samples)

    return sphere


# ---------------------------------------------------------------------------
# accelerometer: six faces and level
# ---------------------------------------------------------------------------


class FaceSession(Session):
    """PX4's six-face accelerometer calibration, saved as soon as it is done."""

    mode = Mode.ACCEL

    def __init__(self, settings: CalibratorSettings, now: float) -> None:
        # PX4 saves an accelerometer calibration as soon as it is done.
        super().__init__(settings, now, autosave=True)
        st = settings
        self.faces = FaceCollector(
            st.face_still_s, st.face_collect_s, st.still_tol_g, st.face_norm_tol_g
        )

    def _progress(self, hint: bool, percent: float | None) -> Progress:
        done = tuple(f.px4_side for f in self.faces.means)
        return Progress(self.faces.percent if percent is None else percent, faces_done=done)

    def begin(self, now: float) -> list[Action]:
        """Started, collecting, and what to do."""
        return [
            self.started("Calibration started: accel"),
            *self.collect(now),
            self.instruction(
                "Hold still on each of the six faces",
                instruction="hold the unit still on each of its six faces in turn",
                step=1,
            ),
        ]

    def feed(self, frame: object, now: float) -> list[Action]:
        """Every attitude frame: faces detected, done, already done, moved."""
        if not isinstance(frame, AttitudeFrame) or not self.running:
            return []
        self.last_frame_at = now
        if self.busy:
            return self.maybe_progress(now)
        _, acc, sat = frame_vectors(frame)
        col = self.faces
        out: list[Action] = []
        for n in col.feed(now, acc, sat):
            side, label = n.face.px4_side, n.face.label
            if n.kind == "detected":
                text = f"{side} orientation detected"
                out.append(self._face("calibration.face_detected", text, side=side, label=label))
            elif n.kind == "done":
                text = f"{side} side done, rotate to a different side"
                done = [f.px4_side for f in col.means]
                out.append(
                    self._face(
                        "calibration.face_done", text, side=side, label=label, faces_done=done
                    )
                )
            elif n.kind == "already_done":
                text = f"{side} side already completed"
                out.append(
                    self.instruction(text, instruction="rotate to a different side", side=side)
                )
            elif n.kind == "moved":
                text = f"motion detected on {side}, hold still"
                out.append(self.instruction(text, instruction="hold still", side=side))
        if col.done:
            means = dict(col.means)
            self.pending = Compute("faces", lambda ctx: _fit_faces(means, ctx))
            self.phase = Phase.FITTING
            out.append(self.pending)
        return out + self.maybe_progress(now)

    def _face(self, kind: str, text: str, **data: Any) -> Emit:
        return Emit(kind, text, data={"mode": self.mode.value, **data})

    def _resolved(self, job: Job, value: Any, now: float) -> list[Action]:
        res, check, new, means = value
        report = SessionReport(
            mode=self.mode,
            method=res.report.method,
            accel=AccelParams.of(res.calibration.accel, res.report, means),
            notes=res.report.notes,
        )
        if check is None or not check.ok:
            why = (check.reasons if check is not None else res.report.notes) or ("fit failed",)
            failure = Failure.of_verdict(res.report.status) or Failure.FAILED
            failed = replace(report, failure=failure, reason=why[0])
            return self.fail(why[0], failure, report=failed, now=now)
        report = report.saved()
        self.accepted = True
        return [*self.succeed(report), Apply(new, "accel", report, write_device=False)]


def _fit_faces(
    means: Mapping[Face, Any], ctx: FitContext
) -> tuple[CalibrationResult, SanityResult | None, Calibration, dict[str, Any]]:
    res = fit_six_face(means)
    check = check_accel_calibration(res.calibration.accel) if res.report.ok else None
    new = Calibration(mag=ctx.calibration.mag, accel=res.calibration.accel)
    return res, check, new, {f.px4_side: v for f, v in means.items()}


class LevelSession(Session):
    """A host level calibration: one still average, then the level trim (saved at once)."""

    mode = Mode.LEVEL

    def __init__(self, settings: CalibratorSettings, now: float) -> None:
        super().__init__(settings, now, autosave=True)
        self.still = StillCollector(settings.level_collect_s, settings.still_tol_g)

    def _progress(self, hint: bool, percent: float | None) -> Progress:
        return Progress(self.still.percent if percent is None else percent)

    def begin(self, now: float) -> list[Action]:
        """Started, collecting, and what to do."""
        return [
            self.started("Calibration started: level"),
            *self.collect(now),
            self.instruction(LEVEL_TEXT, instruction=LEVEL_INSTRUCTION, step=1),
        ]

    def feed(self, frame: object, now: float) -> list[Action]:
        """Every attitude frame until the average is complete."""
        if not isinstance(frame, AttitudeFrame) or not self.running:
            return []
        self.last_frame_at = now
        if not self.busy and self.still.feed(now, *frame_vectors(frame)):
            _, acc_mean, spread = self.still.means()
            tol = self.settings.still_tol_g
            self.pending = Compute("level", lambda ctx: _level(acc_mean, spread, tol, ctx))
            self.phase = Phase.FITTING
            return [self.pending, *self.maybe_progress(now)]
        return self.maybe_progress(now)

    def _resolved(self, job: Job, value: Any, now: float) -> list[Action]:
        new, err, trim = value
        if new is None:
            return self.fail(err, now=now)
        report = SessionReport(self.mode, "level_trim", autosaved=True, level=trim)
        self.accepted = True
        return [*self.succeed(report), Apply(new, "level", report, write_device=False)]


def _level(
    acc_mean: FloatArray, spread: float, tol: float, ctx: FitContext
) -> tuple[Calibration | None, str, LevelTrim | None]:
    current = ctx.calibration
    if spread >= tol:
        return None, f"the unit moved ({1000.0 * spread:.0f} mg): hold it still", None
    try:
        new = level_trim(acc_mean, current)
    except ValueError as e:
        return None, str(e), None
    roll, pitch = attitude_from_gravity(current.accel.apply(acc_mean))
    return new, "", LevelTrim(math.degrees(roll), math.degrees(pitch), 1000.0 * spread)


# ---------------------------------------------------------------------------
# fixed yaw
# ---------------------------------------------------------------------------


#: A fixed-yaw position whose WMM field differs from the one this bridge knows by more than
#: this fraction of it (as a vector: 0.15 is about 9 deg of direction or 15 % of strength,
#: some hundreds of km) is refused: one wrong query must not move the heading by 100 deg.
FIXED_YAW_MAX_FIELD_CHANGE = 0.15
#: Offsets a fixed-yaw calibration may produce, mG: ArduPilot's COMPASS_OFFS_MAX default.
FIXED_YAW_MAX_OFFSET_MG = 1800.0


def fixed_yaw_inputs(
    yaw_deg: object,
    field: EarthField | None,
    latitude_deg: object | None,
    longitude_deg: object | None,
) -> tuple[float, EarthField] | str:
    """The yaw and the field a fixed-yaw calibration uses, or why they are refused.

    The field is the WMM's at the position given (0, 0 = unset, as the MAVLink
    command says), else ``field`` (the configured or the autopilot's position).
    Refused: a yaw that is not a finite number within +-360 deg, a latitude or
    longitude out of range, and -- when the bridge knows where it is -- a
    position whose field differs from the known one by more than
    :data:`FIXED_YAW_MAX_FIELD_CHANGE` (ArduPilot's ``mag_cal_fixed_yaw`` checks
    none of this; one wrong value would store offsets of a whole gauss).
    """
    yaw = number(yaw_deg)
    if yaw is None or not -360.0 <= yaw <= 360.0:
        return f"bad yaw {_short(yaw_deg)}: degrees, -360 to 360"
    if latitude_deg is None and longitude_deg is None:
        return (yaw, field) if field is not None else "no position: set [location] or give one"
    lat, lon = number(latitude_deg), number(longitude_deg)
    if lat is None or lon is None or not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        return (
            f"bad position {_short(latitude_deg)}, {_short(longitude_deg)}: latitude -90 to 90, "
            "longitude -180 to 180, in degrees"
        )
    if not (lat or lon):
        return (yaw, field) if field is not None else "no position: set [location] or give one"
    given = earth_field(lat, lon)
    if field is not None:
        change = float(np.linalg.norm(given.ned_G - field.ned_G)) / max(field.total_G, 1e-9)
        if change > FIXED_YAW_MAX_FIELD_CHANGE:
            return (
                f"position {lat:.4f}, {lon:.4f} is implausible: its field differs by "
                f"{100 * change:.0f} % from the field where this bridge is (configured "
                "[location] or the autopilot's); send 0, 0 to use that one, or correct [location]"
            )
    return yaw, given


def _short(v: object) -> str:
    """``repr(v)`` cut to a few characters (an argument may be anything)."""
    text = repr(v)
    return text if len(text) <= 24 else text[:21] + "..."


def fixed_yaw_result(
    frames: Sequence[AttitudeFrame],
    yaw_deg: float,
    field_ned_G: FloatArray,
    calibration: Calibration,
    mounting: FloatArray,
    still_tol_g: float,
) -> tuple[Calibration, SessionReport] | str:
    """ArduPilot's fixed-yaw calibration from recent still ``frames``; a str says why not."""
    still = StillCollector(0.0, still_tol_g, min_rows=2)
    for i, f in enumerate(frames):
        still.feed(float(i), *frame_vectors(f))
    if not still.complete:
        return "no recent frames from the compass"
    if not still.still:
        return "the unit is moving: hold it still"
    mag_mean, acc_mean, _ = still.means()
    try:
        cal = fixed_yaw_calibration(
            mag_mean, acc_mean, yaw_deg, field_ned_G, calibration, np.asarray(mounting)
        )
    except ValueError as e:
        return f"fixed-yaw calibration failed: {e}"
    offset_mG = 1000.0 * float(np.linalg.norm(cal.mag.offset_array))
    if offset_mG > FIXED_YAW_MAX_OFFSET_MG:
        return (
            f"implausible: the offsets would be {offset_mG:.0f} mG (more than "
            f"{FIXED_YAW_MAX_OFFSET_MG:.0f}); check the yaw and the position"
        )
    fit = CalibrationReport(method="fixed_yaw", n_samples=len(frames))
    report = fit_report(Mode.FIXED_YAW, cal.mag, fit, autosaved=True)
    return cal, replace(report, yaw_deg=float(yaw_deg))


class FixedYawSession(Session):
    """A fixed-yaw calibration: done when made; :meth:`begin` reports and applies it."""

    mode = Mode.FIXED_YAW

    def __init__(
        self,
        settings: CalibratorSettings,
        now: float,
        calibration: Calibration,
        report: SessionReport,
    ) -> None:
        super().__init__(settings, now, autosave=True)
        self._calibration = calibration
        self._report = report

    def begin(self, now: float) -> list[Action]:
        """Done: the report, and the new offsets applied, saved and written to the device."""
        self.accepted = True
        done = self.succeed(self._report, "Calibration done: mag (fixed yaw)")
        return [*done, Apply(self._calibration, "fixed_yaw", self._report, write_device=True)]
