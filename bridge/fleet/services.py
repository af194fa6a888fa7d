"""What the Zenoh output needs from the running daemon, as :class:`FleetServices`.

The daemon is built after its outputs (``build_outputs`` runs first), so every
service looks the daemon up when called, through ``get_daemon``. Parts the
daemon does not have (no calibrator, no MAVLink parameter table) are simply
absent: the matching queryable answers with an error, the status says less.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from bridge.fleet.mirror import SentPacket
from bridge.fleet.output import CommandOutcome, FleetServices

if TYPE_CHECKING:
    from bridge.calibrator.controller import CalibrationController
    from bridge.daemon import Daemon
    from bridge.events import Event, EventBus

log = logging.getLogger(__name__)

#: ``cmd/calibration/start`` ``what`` values -> what is calibrated.
START_KINDS = ("mag", "accel", "level", "fixed_yaw")


def _calibrator(d: Daemon) -> CalibrationController | None:
    return getattr(d, "calibrator", None)


def _bus(d: Daemon) -> EventBus | None:
    return getattr(d, "events", None)


def _mavlink_output(d: Daemon) -> Any:
    """The daemon's MAVLink output (looked up each time: a reload replaces it), or None."""
    return next((o for o in d.outputs if o.name == "mavlink"), None)


def calibration_state(d: Daemon) -> dict[str, Any]:
    """The small calibration summary ``<prefix>/status`` carries."""
    out: dict[str, Any] = {"source": d.calibration_source, "state": "idle"}
    cal = _calibrator(d)
    if cal is None:
        return out
    snap = cal.snapshot()
    if snap.running:
        state = "running"
    elif snap.pending_accept:
        state = "pending_accept"
    elif snap.mode is not None and snap.status.failed:
        state = "failed"
    else:
        state = "idle"
    report = snap.last_report or {}
    fitness = report.get("fitness_mG", report.get("fitness"))
    out.update(
        {
            "state": state,
            "mode": snap.mode,
            "status": snap.status.name,
            "percent": round(snap.completion_pct, 1),
            "onboard": snap.onboard,
            "source": snap.calibration_source or d.calibration_source,
            "age_s": None if snap.calibration_age_s is None else round(snap.calibration_age_s, 1),
            "saved": snap.calibration_saved,
            "fitness_mG": fitness if isinstance(fitness, int | float) else None,
        }
    )
    return out


def calibration_info(d: Daemon) -> dict[str, Any]:
    """The ``<prefix>/calibration`` answer: the parameters in use and their quality report."""
    cal = _calibrator(d)
    snap = cal.snapshot() if cal is not None else None
    report: Mapping[str, Any] | None = None
    source = d.calibration_source
    if snap is not None:
        source = snap.calibration_source or source
        if snap.last_report is not None:
            report = snap.last_report
    if report is None:
        report = _stored_report(d)
    return {
        "calibration": d.engine.calibration.to_dict(),
        "source": source,
        "report": report,
        "state": snap.to_dict() if snap is not None else None,
    }


def _stored_report(d: Daemon) -> Mapping[str, Any] | None:
    """The report saved with the calibration in use (read on demand: queries are rare)."""
    from bridge.daemon import CALIBRATION_DOCUMENT
    from bridge.storage import StateStore

    try:
        loaded = StateStore(d.cfg.storage.dir).load(CALIBRATION_DOCUMENT)
    except Exception:
        return None
    payload = loaded.payload
    if isinstance(payload, dict) and isinstance(payload.get("report"), dict):
        return dict(payload["report"])
    return None


def _flag(args: Mapping[str, Any], name: str, default: bool | None = None) -> bool | None:
    v = args.get(name, default)
    if v is None or isinstance(v, bool):
        return v
    if v in (0, 1):
        return bool(v)
    raise ValueError(f"{name} must be true or false, got {v!r}")


def _number(args: Mapping[str, Any], name: str, default: float | None = None) -> float | None:
    v = args.get(name, default)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError(f"{name} must be a number, got {v!r}")
    return float(v)


def run_calibration_command(
    cal: CalibrationController, command: str, args: Mapping[str, Any]
) -> CommandOutcome:
    """Map ``cmd/calibration/<command>`` with its JSON arguments onto the controller.

    ``start`` takes ``what`` (``mag`` default, ``accel``, ``level``,
    ``fixed_yaw``), ``onboard`` (true/false; default the BRG_CAL_ONBOARD
    route), and for ``mag`` ``autosave``, ``retry``, ``delay_s``; for
    ``fixed_yaw`` ``yaw_deg`` (required), ``latitude_deg``, ``longitude_deg``.
    ``accept`` and ``cancel`` take nothing.
    """
    if command == "accept":
        outcome = cal.accept()
    elif command == "cancel":
        outcome = cal.cancel()
    elif command == "start":
        what = args.get("what", "mag")
        if what not in START_KINDS:
            raise ValueError(f"what must be one of {', '.join(START_KINDS)}, got {what!r}")
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
        raise ValueError(f"unknown command {command!r}")
    detail = {"result": outcome.result.value, "state": cal.snapshot().to_dict()}
    return CommandOutcome(outcome.ok, outcome.message, detail)


def daemon_services(get_daemon: Callable[[], Daemon]) -> FleetServices:
    """:class:`FleetServices` backed by the daemon ``get_daemon`` returns (when called)."""

    def run_command(command: str, args: Mapping[str, Any]) -> CommandOutcome:
        cal = _calibrator(get_daemon())
        if cal is None:
            return CommandOutcome(False, "calibration is not available on this bridge")
        return run_calibration_command(cal, command, args)

    def subscribe_events(fn: Callable[[Event], None]) -> Callable[[], None]:
        bus = _bus(get_daemon())
        if bus is None:
            return lambda: None
        return bus.subscribe(fn)

    def params() -> Mapping[str, float]:
        table = getattr(_mavlink_output(get_daemon()), "params", None)
        if table is None:
            raise LookupError("this bridge has no parameter table (MAVLink output off)")
        return dict(table.values())

    def subscribe_mavlink(fn: Callable[[Any], None]) -> Callable[[], None]:
        out = _mavlink_output(get_daemon())
        add_tap = getattr(out, "add_tap", None)
        if out is None or add_tap is None:
            log.info("zenoh: mavlink_mirror is on but there is no MAVLink output to mirror")
            return lambda: None
        sysid, compid = out.identity.system_id, out.identity.component_id

        def tap(packet: Any) -> None:
            try:  # runs in the MAVLink sender's thread: never raise into it
                fn(SentPacket(sysid, compid, packet.msgid, packet.payload))
            except Exception:
                log.debug("zenoh: mirror tap failed", exc_info=True)

        unsubscribe: Callable[[], None] = add_tap(tap)
        return unsubscribe

    return FleetServices(
        status=lambda: get_daemon().status(),
        calibration_state=lambda: calibration_state(get_daemon()),
        calibration=lambda: calibration_info(get_daemon()),
        params=params,
        run_command=run_command,
        subscribe_events=subscribe_events,
        subscribe_mavlink=subscribe_mavlink,
        mavlink_source=lambda: _mavlink_output(get_daemon()),
    )
