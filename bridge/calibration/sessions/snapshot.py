"""What front ends read of the calibrator (:class:`CalibratorSnapshot`) and where it writes
(:class:`CalibrationTarget`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

from bridge.calibration.sessions.base import Session
from bridge.calibration.sessions.report import Failure, SessionReport
from bridge.calibration.sessions.state import Phase
from bridge.core.calibration import Calibration
from bridge.core.mounting import Mounting


@dataclass(frozen=True, slots=True)
class CalibratorSnapshot:
    """The controller's state for status queries (MAVLink HEARTBEAT, zenoh status, CLI).

    ``phase`` and ``step`` are those of the current (or last) session
    (:attr:`Phase.IDLE`, step 0, before the first); ``report`` its result once
    it has one; ``pending_accept`` a successful host magnetometer fit waiting
    for accept; ``calibration_age_s`` how long ago the calibration in use was
    accepted (None: never, or unknown); ``calibration_saved`` whether it is on disk, and
    ``calibration_saving`` whether it waits only for its pace (a COMPASS_* value set
    within a second of the last save: written within that second, no storage error), and
    ``calibration_save_error`` why storage refused it ("": it did not; a calibration that
    was never ours to save, such as the simulator's true one, is neither saved nor refused).
    """

    mode: str | None
    phase: Phase
    step: int
    running: bool
    attempt: int
    completion_pct: float
    completion_mask: bytes
    direction: tuple[float, float, float]
    onboard: bool
    faces_done: tuple[str, ...]
    report: SessionReport | None
    pending_accept: bool
    calibration_source: str
    calibration_age_s: float | None
    calibration_saved: bool
    calibration_saving: bool = False
    calibration_save_error: str = ""

    @property
    def failure(self) -> Failure | None:
        """Why the last session failed (None: it did not)."""
        if self.phase is not Phase.FAILED:
            return None
        return self.report.failure if self.report is not None else Failure.FAILED

    @classmethod
    def of(
        cls,
        session: Session | None,
        *,
        onboard: bool,
        calibration_source: str,
        calibration_age_s: float | None,
        calibration_saved: bool,
        calibration_saving: bool = False,
        calibration_save_error: str = "",
    ) -> CalibratorSnapshot:
        """The state of ``session`` (None: none yet) and of the calibration in use."""
        # The fields in their order, not by keyword: a status query may come every frame,
        # and the frozen class's __init__ took twice as long given keywords.
        if session is None:
            return cls(
                None,  # mode
                Phase.IDLE,
                0,  # step
                False,  # running
                0,  # attempt
                0.0,  # completion_pct
                bytes(10),  # completion_mask
                (0.0, 0.0, 0.0),  # direction
                onboard,
                (),  # faces_done
                None,  # report
                False,  # pending_accept
                calibration_source,
                calibration_age_s,
                calibration_saved,
                calibration_saving,
                calibration_save_error,
            )
        p = session.progress()
        return cls(
            session.mode.value,
            session.phase,
            session.step,
            session.running,
            session.attempt,
            p.percent,  # completion_pct
            p.mask,  # completion_mask
            p.direction,
            onboard,
            p.faces_done or (),
            session.report,
            session.pending_accept,
            calibration_source,
            calibration_age_s,
            calibration_saved,
            calibration_saving,
            calibration_save_error,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "mode": self.mode,
            "phase": self.phase.value,
            "step": self.step,
            "running": self.running,
            "attempt": self.attempt,
            "completion_pct": self.completion_pct,
            "completion_mask": list(self.completion_mask),
            "direction": list(self.direction),
            "onboard": self.onboard,
            "faces_done": list(self.faces_done),
            "report": None if self.report is None else self.report.to_dict(),
            "pending_accept": self.pending_accept,
            "calibration_source": self.calibration_source,
            "calibration_age_s": self.calibration_age_s,
            "calibration_saved": self.calibration_saved,
            "calibration_saving": self.calibration_saving,
            "calibration_save_error": self.calibration_save_error,
        }


class CalibrationTarget(Protocol):
    """Where an accepted calibration goes: the attitude engine, or the application's
    :class:`~bridge.app.settings.EngineSettings` (its one writer, which tells the others)."""

    @property
    def calibration(self) -> Calibration:
        """The calibration in use."""
        ...

    @property
    def mounting(self) -> Mounting:
        """The mounting in use."""
        ...

    def update_calibration(self, calibration: Calibration) -> None:
        """Use ``calibration`` from now on."""
        ...
