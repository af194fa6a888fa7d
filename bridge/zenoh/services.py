"""What the Zenoh output needs from the running bridge, as :class:`FleetServices`.

Built from the application's :class:`~bridge.app.services.BridgeServices`, the
same object the MAVLink adapter gets: status, the calibration controller, the
calibration store, the parameter store, events and the MAVLink message tap.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from bridge.app.services import magnetometer_calibrated
from bridge.calibration.sessions.state import number
from bridge.zenoh.commands import quote
from bridge.zenoh.contract import CommandOutcome, FleetServices

if TYPE_CHECKING:
    from bridge.app.calibration.controller import CalibrationController
    from bridge.app.services import BridgeServices, SentMessage
    from bridge.calibration.sessions.snapshot import CalibratorSnapshot

log = logging.getLogger(__name__)

#: ``cmd/calibration/start`` ``what`` values -> what is calibrated.
START_KINDS = ("mag", "accel", "level", "fixed_yaw")


def calibration_state(svc: BridgeServices) -> dict[str, Any]:
    """The small calibration summary ``<prefix>/status`` carries (``phase``: the calibrator's
    neutral phase -- idle, waiting, collecting, fitting, succeeded, failed, cancelled)."""
    snap = svc.calibrator.snapshot()
    state = _state(snap)
    fit = snap.report.fit if snap.report is not None else None
    fitness = fit.fitness_mG if fit is not None and math.isfinite(fit.fitness_mG) else None
    return {
        "state": state,
        "mode": snap.mode,
        "phase": snap.phase.value,
        "percent": round(snap.completion_pct, 1),
        "onboard": snap.onboard,
        "source": _source(svc, snap),
        "age_s": None if snap.calibration_age_s is None else round(snap.calibration_age_s, 1),
        "saved": snap.calibration_saved,
        # Not saved yet only for its pace (a COMPASS_* value set a moment ago): no storage error.
        "saving": snap.calibration_saving,
        # Why storage refused it (retried); null: it did not (saved, saving, or never ours
        # to save, such as the simulator's true calibration).
        "save_error": snap.calibration_save_error or None,
        "fitness_mG": fitness,
        # False: no hard- or soft-iron correction in use (None: a heading-only compass)
        "calibrated": magnetometer_calibrated(svc),
        # the drift monitor (bridge.app.calibration.drift): mode, state, change left, heading error
        "drift": svc.drift.status().to_dict(),
    }


def calibration_key(svc: BridgeServices) -> tuple[str, str]:
    """``(state, source)`` of :func:`calibration_state`, without the rest of the summary.

    The status stream looks for a change when an event or a link state change comes;
    the whole summary (the drift monitor's status, whether the calibration corrects
    iron) costs several times more and is built only when a document goes out.
    """
    snap = svc.calibrator.snapshot()
    return _state(snap), _source(svc, snap)


def _source(svc: BridgeServices, snap: CalibratorSnapshot) -> str:
    """Where the calibration in use came from: the calibrator's word after an accept, else
    the bridge's start-up one."""
    return snap.calibration_source or svc.status().calibration_source


def _state(snap: CalibratorSnapshot) -> str:
    if snap.running:
        return "running"
    if snap.pending_accept:
        return "pending_accept"
    if snap.failure is not None:
        return "failed"
    return "idle"


def calibration_info(svc: BridgeServices) -> dict[str, Any]:
    """The ``<prefix>/calibration`` answer: the parameters in use and their quality report."""
    snap = svc.calibrator.snapshot()
    # queries are rare: the stored report is read on demand
    report: Mapping[str, Any] | None = (
        snap.report.to_dict() if snap.report is not None else svc.calibrations.load().report
    )
    return {
        "calibration": svc.settings.calibration.to_dict(),
        "source": _source(svc, snap),
        "report": dict(report) if report is not None else None,
        "state": snap.to_dict(),
    }


def _flag(args: Mapping[str, Any], name: str, default: bool | None = None) -> bool | None:
    v = args.get(name, default)
    if v is None or isinstance(v, bool):
        return v
    if v in (0, 1):
        return bool(v)
    raise ValueError(f"{name} must be true or false, got {quote(v)}")


def _number(args: Mapping[str, Any], name: str, default: float | None = None) -> float | None:
    v = args.get(name, default)
    if v is None:
        return None
    f = number(v)  # no bool, no NaN or infinity, no integer beyond a float
    if f is None:
        raise ValueError(f"{name} must be a number, got {quote(v)}")
    return f


def run_calibration_command(
    cal: CalibrationController,
    command: str,
    args: Mapping[str, Any],
    *,
    undo: Callable[[], tuple[bool, str]] | None = None,
) -> CommandOutcome:
    """Map ``cmd/calibration/<command>`` with its JSON arguments onto the controller.

    ``start`` takes ``what`` (``mag`` default, ``accel``, ``level``,
    ``fixed_yaw``), ``onboard`` (true/false; default the BRG_CAL_ONBOARD
    route), and for ``mag`` ``autosave``, ``retry``, ``delay_s``; for
    ``fixed_yaw`` ``yaw_deg`` (required), ``latitude_deg``, ``longitude_deg``.
    ``accept`` and ``cancel`` take nothing, nor does ``undo``: back to the
    calibration learning started from (``undo``, the drift monitor's).
    """
    if command == "undo":
        if undo is None:
            return CommandOutcome(False, "no learned calibration to undo on this bridge")
        ok, message = undo()
        return CommandOutcome(ok, message, {"state": cal.snapshot().to_dict()})
    if command == "accept":
        outcome = cal.accept()
    elif command == "cancel":
        outcome = cal.cancel()
    elif command == "start":
        what = args.get("what", "mag")
        if what not in START_KINDS:
            raise ValueError(f"what must be one of {', '.join(START_KINDS)}, got {quote(what)}")
        onboard = _flag(args, "onboard")
        if what == "mag":
            outcome = cal.start_mag(
                autosave=bool(_flag(args, "autosave", False)),
                retry=bool(_flag(args, "retry", False)),
                delay_s=_number(args, "delay_s", 0.0) or 0.0,
                onboard=onboard,
            )
        elif what == "accel":
            outcome = cal.start_accel()
        elif what == "level":
            outcome = cal.start_level(onboard=onboard)
        else:
            yaw = _number(args, "yaw_deg")
            if yaw is None:
                raise ValueError("fixed_yaw needs yaw_deg")
            outcome = cal.fixed_yaw(
                yaw,
                latitude_deg=_number(args, "latitude_deg"),
                longitude_deg=_number(args, "longitude_deg"),
            )
    else:
        raise ValueError(f"unknown command {quote(command)}")
    detail = {"result": outcome.result.value, "state": cal.snapshot().to_dict()}
    return CommandOutcome(outcome.ok, outcome.message, detail)


def fleet_services(svc: BridgeServices) -> FleetServices:
    """:class:`FleetServices` backed by the bridge's services."""

    def run_command(command: str, args: Mapping[str, Any]) -> CommandOutcome:
        return run_calibration_command(svc.calibrator, command, args, undo=svc.drift.undo)

    def subscribe_mavlink(fn: Callable[[SentMessage], None]) -> Callable[[], None]:
        return svc.mavlink_tap.subscribe(fn)

    return FleetServices(
        status=svc.status,
        calibration_state=lambda: calibration_state(svc),
        calibration_key=lambda: calibration_key(svc),
        calibration=lambda: calibration_info(svc),
        params=lambda: svc.params.values(),
        run_command=run_command,
        subscribe_events=svc.events.subscribe,
        subscribe_mavlink=subscribe_mavlink,
        emit_event=svc.events.emit,
        tilt_state=svc.tilt.status,
        subscribe_link_state=svc.link_states.add,
    )
