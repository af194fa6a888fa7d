"""The calibrator's neutral vocabulary: modes, phases, command answers and tunables.

Nothing here knows a wire format. Front ends map these to theirs: the MAVLink
adapter turns a :class:`Phase` (with the session's step and its report's
failure) into MAG_CAL_STATUS (:mod:`bridge.mavlink.calmap`), a :class:`Result`
into MAV_RESULT; zenoh publishes the values as they are.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Any

from bridge.calibration.fits.acceptance import DEFAULT_FITNESS_MAX_MG, DEFAULT_HEADING_MAX_DEG


class Mode(enum.StrEnum):
    """What a session calibrates, and where."""

    MAG = "mag"  #: host magnetometer: two-step collection, ellipsoid + alignment
    ACCEL = "accel"  #: host accelerometer: six faces
    LEVEL = "level"  #: host level trim
    FIXED_YAW = "fixed_yaw"  #: host offsets from one known yaw
    ONBOARD_MAG = "onboard_mag"  #: the device's MAGCAL
    ONBOARD_LEVEL = "onboard_level"  #: the device's ACCCAL

    @property
    def onboard(self) -> bool:
        """Runs in the device (result in its flash)."""
        return self in (Mode.ONBOARD_MAG, Mode.ONBOARD_LEVEL)

    @property
    def sensor(self) -> str:
        """What it calibrates, in PX4's words ("[cal] calibration done: <sensor>"): mag,
        accel or level."""
        if self in (Mode.MAG, Mode.FIXED_YAW, Mode.ONBOARD_MAG):
            return "mag"
        return "accel" if self is Mode.ACCEL else "level"


class Phase(enum.StrEnum):
    """Where a session is. ``step`` (1 or 2) says which half of a two-step routine runs."""

    IDLE = "idle"  #: no session yet
    WAITING = "waiting"  #: a delayed start, or the device not yet in its routine
    COLLECTING = "collecting"  #: taking frames (the operator turns or holds the unit)
    FITTING = "fitting"  #: the result is being computed (a fit, the device's END or ACCCAL)
    SUCCEEDED = "succeeded"  #: done; a host magnetometer fit may still wait for accept
    FAILED = "failed"  #: done without a result (the report says why)
    CANCELLED = "cancelled"  #: stopped by a cancel; nothing was applied

    @property
    def running(self) -> bool:
        """Waiting, collecting or fitting."""
        return self in _RUNNING


# A set, not a tuple of Phase.WAITING, ...: on 3.11 every ``Phase.X`` goes through EnumType's
# __getattr__ hook (about 0.2 us), and ``running`` is asked several times a frame while a
# calibration collects (the controller, the session, its progress, the status snapshot).
_RUNNING = frozenset((Phase.WAITING, Phase.COLLECTING, Phase.FITTING))


class Result(enum.StrEnum):
    """How a command was taken (front ends map it to MAV_RESULT / a zenoh reply)."""

    ACCEPTED = "accepted"  #: done (or nothing to do)
    IN_PROGRESS = "in_progress"  #: started; the outcome follows as events
    DENIED = "denied"  #: not now (another calibration runs, nothing to accept ...)
    FAILED = "failed"  #: could not be done (bad argument, no position, no device ...)


@dataclass(frozen=True, slots=True)
class Outcome:
    """A command's immediate answer."""

    result: Result
    message: str = ""

    @property
    def ok(self) -> bool:
        """ACCEPTED or IN_PROGRESS."""
        return self.result in (Result.ACCEPTED, Result.IN_PROGRESS)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (zenoh replies)."""
        return {"result": self.result.value, "ok": self.ok, "message": self.message}


@dataclass(frozen=True, slots=True)
class CalibratorSettings:
    """Tunables (defaults follow ArduPilot / PX4 where they have one).

    Times are seconds of the controller's clock. ``fitness_max_mG`` is the
    starting value of the host magnetometer fit's fitness limit; the
    application keeps it equal to COMPASS_CAL_FIT
    (:attr:`~bridge.app.calibration.controller.CalibrationController.fitness_limit_mG`).
    """

    capacity: int = 300  #: magnetometer sample buffer (ArduPilot's COMPASS_CAL_NUM_SAMPLES)
    timeout_s: float = 180.0  #: a whole session (collection or device routine) gives up after this
    no_data_timeout_s: float = 2.0  #: running without any frame this long fails (ArduPilot: 1 s)
    progress_interval_s: float = 1.0  #: at most one progress event per interval (on change)
    face_still_s: float = 1.0  #: stillness window that detects a face
    face_collect_s: float = 1.5  #: further still time averaged per face
    still_tol_g: float = 0.02  #: per-axis standard deviation for "still" (PX4: 0.25 m/s^2)
    face_norm_tol_g: float = 0.5  #: |g| tolerance for a face of an uncalibrated unit
    level_collect_s: float = 1.0  #: host level calibration: still time averaged
    fixed_yaw_window_s: float = 1.0  #: fixed yaw: recent frames averaged
    onboard_min_turn_deg: float = 330.0  #: a device turn counts from this much field direction
    onboard_settle_reports: int = 2  #: $PGMRC reports without span growth that end a turn
    motion_limit_g: float = 0.09  #: linear acceleration (g RMS per axis) the operator is told of
    motion_interval_s: float = 5.0  #: at most one "calibration.motion" warning per interval
    #: a fit predicting a larger heading error fails (or 3x the floor, when that is larger)
    max_heading_error_deg: float = DEFAULT_HEADING_MAX_DEG
    #: a fit with a larger fitness fails (COMPASS_CAL_FIT)
    fitness_max_mG: float = DEFAULT_FITNESS_MAX_MG

    def __post_init__(self) -> None:
        if self.capacity < 20:
            raise ValueError(f"capacity must be at least 20, got {self.capacity}")
        for name in (
            "timeout_s",
            "no_data_timeout_s",
            "progress_interval_s",
            "face_still_s",
            "face_collect_s",
            "still_tol_g",
            "face_norm_tol_g",
            "level_collect_s",
            "fixed_yaw_window_s",
            "onboard_min_turn_deg",
            "motion_limit_g",
            "motion_interval_s",
            "max_heading_error_deg",
            "fitness_max_mG",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive and finite, got {v!r}")
        if self.onboard_settle_reports < 1:
            raise ValueError("onboard_settle_reports must be at least 1")


def number(v: object) -> float | None:
    """``v`` as a finite float, or None (bools, strings, NaN and infinities are not numbers
    here, nor an integer too large for a float)."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return None
    try:
        f = float(v)
    except OverflowError:  # an int beyond 1.8e308
        return None
    return f if math.isfinite(f) else None


def mask_refusal(mask: float) -> Outcome | None:
    """FAILED unless ``mask`` selects compass 0: MAVLink carries it as a float param, 0 (all)
    or a byte that includes compass 0. None when it does."""
    m = number(mask)
    if m is not None and m == int(m) and 0 <= m <= 255 and (int(m) == 0 or int(m) & 1):
        return None
    return Outcome(Result.FAILED, f"compass mask {mask} does not include compass 0")
