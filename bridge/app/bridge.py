"""The application: the running bridge's state and the one owner of each part of it.

:class:`Bridge` holds the attitude engine and its settings' writer, the event
bus, the calibration store and controller, the drift monitor, the parameter
store and the per-frame pipeline, reacts to their changes, and gives every
adapter the same :class:`~bridge.app.services.BridgeServices`. It does no I/O
of its own and builds none of its parts: :func:`bridge.daemon.wiring.build_daemon`
builds each one after what it needs, the compass link
(:class:`~bridge.device.DevicePort`) and the state directory
(:class:`~bridge.documents.DocumentStore`) among them, and hands them in.
The functions below are the few hooks between the parts, named, so that the
wiring passes bound functions (no lambda) to parts already built.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from bridge.app.calibration.controller import CalibrationController
from bridge.app.calibration.drift import DriftMonitor
from bridge.app.calibration.store import CalibrationStore
from bridge.app.params import PARAMETERS, ParamChange, ParamStore
from bridge.app.paramspec import CONFIG_PARAMS, param_from_config
from bridge.app.pipeline import Pipeline
from bridge.app.sample import DaemonStatus
from bridge.app.services import BridgeServices, MessageTap
from bridge.app.settings import EngineSettings, SettingsChange
from bridge.app.tilt import TiltSources, frame_latency_s
from bridge.calibration.model import Calibration
from bridge.config import Config
from bridge.core.attitude import AttitudeEngine
from bridge.core.wmm import EarthField, earth_field
from bridge.device import DevicePort
from bridge.documents import DocumentStore
from bridge.events import EventBus
from bridge.types import LEARN_MODES, HeadingReference

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class BridgeOptions:
    """What the application takes from the configuration."""

    location: tuple[float, float, float] | None = None  #: latitude, longitude (deg), altitude (m)
    onboard: bool = False  #: BRG_CAL_ONBOARD's default
    calibration_timeout_s: float = 180.0
    heading_reference: HeadingReference = "magnetic"
    learn: str = "detect"  #: BRG_CAL_LEARN's default: "off", "detect" or "learn"
    #: ``[heading] tilt``: "auto" (a tilt source other than the accelerometer while it is
    #: unreliable, :mod:`bridge.app.tilt`) or "accelerometer" (frame by frame, always).
    tilt: str = "auto"
    #: How long before its arrival a compass frame was sampled (its line on the wire).
    frame_latency_s: float = 0.0
    #: Parameter defaults the configuration sets (stream rates, heading feed, ...).
    param_defaults: Mapping[str, float] = field(default_factory=dict)

    @classmethod
    def from_config(cls, cfg: Config) -> BridgeOptions:
        """From a loaded configuration."""
        loc = cfg.location
        heading: HeadingReference = "true" if cfg.heading.reference == "true" else "magnetic"
        learn = cfg.calibration.learn
        if learn not in LEARN_MODES:  # the configuration checks it too; a hand-made Config may not
            raise ValueError(f"calibration.learn must be one of {LEARN_MODES}, got {learn!r}")
        # Every parameter a configuration key gives the default of (paramspec's config_key).
        defaults = {
            spec.name: param_from_config(spec, config_value(cfg, spec.config_key))
            for spec in CONFIG_PARAMS
        }
        return cls(
            location=(loc.latitude, loc.longitude, loc.altitude_m) if loc is not None else None,
            tilt=cfg.heading.tilt,
            frame_latency_s=frame_latency_s(cfg.device.baud),
            onboard=cfg.calibration.onboard,
            calibration_timeout_s=cfg.calibration.timeout_s,
            heading_reference=heading,
            learn=learn,
            param_defaults=defaults,
        )


def config_value(cfg: Config, key: str) -> Any:
    """The value of ``section.key`` in ``cfg``."""
    section, _, name = key.partition(".")
    return getattr(getattr(cfg, section), name)


def location_field(location: tuple[float, float, float] | None) -> EarthField | None:
    """The World Magnetic Model's field at ``location`` (None without one)."""
    if location is None:
        return None
    lat, lon, alt = location
    f = earth_field(lat, lon, alt)
    log.info(
        "location %.4f, %.4f, %.0f m: declination %+.2f deg, field %.0f nT, dip %+.1f deg (WMM)",
        lat,
        lon,
        alt,
        f.declination_deg,
        f.total_G * 1e5,
        f.inclination_deg,
    )
    return f


def apply_learned(
    calibrator: CalibrationController,
    cal: Calibration,
    source: str,
    report: Mapping[str, Any] | None,
    view: Mapping[str, float] | None,
) -> str:
    """The drift monitor's learned (or restored) calibration: engine, store, events.

    Not written to the device: its own heading is only shown beside ours, and
    learning would wear its flash a step at a time. "" when applied, else why not.
    """
    out = calibrator.apply_calibration(
        cal,
        source=source,
        report=dict(report) if report is not None else None,
        write_device=False,
        view=dict(view) if view is not None else None,
    )
    return "" if out.ok else out.message


def apply_from_parameters(
    calibrator: CalibrationController, cal: Calibration, view: Mapping[str, float]
) -> str:
    """A calibration set parameter by parameter (a ground station's COMPASS_* writes)."""
    out = calibrator.apply_calibration(cal, source=PARAMETERS, write_device=False, view=dict(view))
    return "" if out.ok else out.message


def learning_lowered(params: ParamStore, mode: str) -> None:
    """An undo turned learning down: BRG_CAL_LEARN follows (it persists the choice)."""
    params.set("BRG_CAL_LEARN", float(LEARN_MODES.index(mode)), source="undo")


class Bridge:
    """The running bridge's state (see the module docstring).

    Every part comes in built; ``calibration_source`` says where the calibration
    the bridge started with came from. Built, it subscribes to the settings and
    the parameters and applies the stored parameters (so an adapter built on
    :attr:`services` sees them in force).
    """

    def __init__(
        self,
        *,
        events: EventBus,
        engine: AttitudeEngine,
        tilt: TiltSources,
        settings: EngineSettings,
        calibrations: CalibrationStore,
        calibration_source: str,
        calibrator: CalibrationController,
        params: ParamStore,
        drift: DriftMonitor,
        pipeline: Pipeline,
        device: DevicePort,
        documents: DocumentStore | None = None,
    ) -> None:
        self.events = events
        self.engine = engine
        #: Where each frame's tilt comes from (the engine's tilt policy, unless "accelerometer").
        self.tilt = tilt
        self.settings = settings
        self.calibrations = calibrations
        self.calibration_source = calibration_source
        self.calibrator = calibrator
        self.params = params
        self.drift = drift
        self.pipeline = pipeline
        self.device = device
        self.mavlink_tap = MessageTap()
        self.services = BridgeServices(
            status=self.status,
            settings=settings,
            params=params,
            calibrator=calibrator,
            calibrations=calibrations,
            events=events,
            device=device,
            mavlink_tap=self.mavlink_tap,
            documents=documents,
            drift=drift,
            tilt=tilt,
        )
        settings.subscribe(self._on_settings)
        params.subscribe(self._on_params)
        params.start()
        calibrator.onboard = params.get("BRG_CAL_ONBOARD") != 0
        calibrator.fitness_limit_mG = params.get("COMPASS_CAL_FIT")
        drift.set_mode(LEARN_MODES[int(params.get("BRG_CAL_LEARN"))])
        if params.get("BRG_CAL_UNDO") != 0:  # a request left over from a crash
            params.set("BRG_CAL_UNDO", 0, source="start")

    # -- lifecycle -----------------------------------------------------------------

    def start(self) -> None:
        """Start the application's own threads (the calibration worker, the drift monitor)."""
        self.calibrator.start()
        self.drift.start()

    def stop(self, timeout: float) -> None:
        """Stop them (a device calibration still running is aborted)."""
        deadline = time.monotonic() + timeout
        # The drift monitor's thread ends after the block at hand (milliseconds): the
        # calibration worker, which may be waiting on the device, keeps the rest.
        self.drift.close(timeout=0.25 * timeout)
        self.calibrator.close(timeout=max(0.1, deadline - time.monotonic()))
        self.params.close()  # a parameter set a moment ago is written now

    # -- status --------------------------------------------------------------------

    def status(self) -> DaemonStatus:
        """A snapshot of link state and counters."""
        d = self.device
        return DaemonStatus(
            port=d.name,
            state=d.state,
            counters=d.counters,
            samples=self.pipeline.samples,
            pipeline_errors=self.pipeline.errors,
            # After an accept the calibrator knows better than the start-up value.
            calibration_source=self.calibrator.snapshot().calibration_source
            or self.calibration_source,
        )

    # -- reactions between the owners ------------------------------------------------

    def _on_settings(self, change: SettingsChange) -> None:
        if change.aspect in ("mounting", "calibration"):
            # The compass's axes or its accelerometer's level moved: what the tilt estimate
            # held, and the residual to the autopilot's axes it learnt, no longer hold.
            self.tilt.reset(f"{change.aspect} changed by {change.source}")
        if change.aspect == "reference":
            # A new position (reload, autopilot): fits are scaled to the field there.
            self.calibrator.set_field(self.settings.field)

    def undo_learned(self) -> tuple[bool, str]:
        """Back to the calibration learning started from (Zenoh ``cmd/calibration/undo``,
        ``BRG_CAL_UNDO``); see :meth:`~bridge.app.calibration.drift.DriftMonitor.undo`."""
        return self.drift.undo()

    def _on_params(self, change: ParamChange) -> None:
        if "BRG_CAL_ONBOARD" in change.names:
            self.calibrator.onboard = self.params.get("BRG_CAL_ONBOARD") != 0
        if "COMPASS_CAL_FIT" in change.names:  # the host fit's fitness limit (ArduPilot's)
            self.calibrator.fitness_limit_mG = self.params.get("COMPASS_CAL_FIT")
        if "BRG_CAL_LEARN" in change.names:
            self.drift.set_mode(LEARN_MODES[int(self.params.get("BRG_CAL_LEARN"))])
        if "BRG_CAL_UNDO" in change.names and self.params.get("BRG_CAL_UNDO") != 0:
            # An action on the change 0 -> 1 (a SET of the value already in force changes
            # nothing): it reads back 1, as every ground station checks a SET's echo, until
            # set to 0 (or a restart); a repeated request finds nothing learned to undo.
            self.undo_learned()
