"""The application: the running bridge's state and the one owner of each part of it.

:class:`Bridge` builds and holds the attitude engine and its settings' writer,
the event bus, the calibration store and controller, the parameter store and
the per-frame pipeline, and gives every adapter the same
:class:`~bridge.app.services.BridgeServices`. It does no I/O of its own: the
compass link and the state directory come in as protocols
(:class:`~bridge.device.DevicePort` -- made by a factory, since the link calls
the pipeline back -- and :class:`~bridge.documents.DocumentStore`), and
:mod:`bridge.daemon` wires it to the adapters.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from bridge.app.calibration.controller import CalibrationController, CalibratorSettings
from bridge.app.calibration.drift import DriftMonitor
from bridge.app.calibration.store import CalibrationStore
from bridge.app.params import PARAMETERS, ParamChange, ParamStore
from bridge.app.paramspec import CONFIG_PARAMS, param_from_config
from bridge.app.pipeline import Pipeline
from bridge.app.sample import DaemonStatus, Output
from bridge.app.services import BridgeServices, MessageTap
from bridge.app.settings import EngineSettings, SettingsChange
from bridge.app.tilt import TiltSources, frame_latency_s
from bridge.calibration.model import Calibration
from bridge.config import Config
from bridge.core.attitude import AttitudeEngine, AttitudeSolution
from bridge.core.wmm import EarthField, earth_field
from bridge.device import DevicePort, LinkState, Received
from bridge.documents import DocumentStore
from bridge.events import EventBus
from bridge.types import LEARN_MODES, HeadingReference

log = logging.getLogger(__name__)

#: Makes the compass link, given the pipeline's frame and state callbacks.
DeviceFactory = Callable[
    [Callable[[Received], None], Callable[[LinkState, LinkState], None]], DevicePort
]


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
        heading: HeadingReference = "true" if _heading_reference(cfg) == "true" else "magnetic"
        # [calibration] learn (the configuration's owner adds the key; "detect" until then)
        learn = str(getattr(cfg.calibration, "learn", "detect"))
        if learn not in LEARN_MODES:
            raise ValueError(f"calibration.learn must be one of {LEARN_MODES}, got {learn!r}")
        # Every parameter a configuration key gives the default of (paramspec's config_key).
        defaults = {
            spec.name: param_from_config(spec, config_value(cfg, spec.config_key))
            for spec in CONFIG_PARAMS
        }
        heading_section = getattr(cfg, "heading", None)
        return cls(
            location=(loc.latitude, loc.longitude, loc.altitude_m) if loc is not None else None,
            tilt=str(getattr(heading_section, "tilt", "auto")),
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


def _heading_reference(cfg: Config) -> str:
    """The configured published heading (``[heading] reference``; magnetic by default)."""
    section = getattr(cfg, "heading", None)
    return str(getattr(section, "reference", "magnetic"))


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


class Bridge:
    """The running bridge's state (see the module docstring).

    ``calibration`` overrides the stored calibration (tests, replays, the simulator's
    true calibration), ``calibration_source`` says where it came from;
    ``calibrator_settings`` and ``clock`` tune the calibration controller, and
    ``clock`` times the drift monitor's samples too (tests run both on a
    simulated clock; by default a sample keeps its frame's arrival time).
    """

    def __init__(
        self,
        options: BridgeOptions,
        device: DeviceFactory,
        *,
        documents: DocumentStore | None = None,
        calibration: Calibration | None = None,
        calibration_source: str = "",
        calibrator_settings: CalibratorSettings | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.options = options
        self.events = EventBus()
        self.calibrations = CalibrationStore(documents)
        stored = self.calibrations.load()
        if calibration is None:
            calibration = stored.calibration
            self.calibration_source = stored.description
        else:
            self.calibration_source = calibration_source or "given"
        self.engine = AttitudeEngine(calibration, heading_reference=options.heading_reference)
        #: Where each frame's tilt comes from (the engine's tilt policy, unless "accelerometer").
        self.tilt = TiltSources(frame_latency=options.frame_latency_s)
        if options.tilt != "accelerometer":
            self.engine.set_tilt_policy(self.tilt)
        field = location_field(options.location)
        self.settings = EngineSettings(self.engine, field=field)
        self.drift = DriftMonitor(
            self.settings,
            self.events,
            apply=self._apply_learned,
            calibrating=lambda: self.calibrator.calibrating,
            store=self.calibrations,
            mode=options.learn,
            on_mode=self._drift_mode_lowered,
        )
        observe: Callable[[AttitudeSolution, float, bool], None] = self.drift.observe
        if clock is not time.monotonic:  # a simulated clock: the drive's time, not the host's

            def on_clock(a: AttitudeSolution, t: float, saturated: bool) -> None:
                self.drift.observe(a, clock(), saturated)

            observe = on_clock

        self.pipeline = Pipeline(
            self.engine,
            self.events,
            feed=lambda frame: self.calibrator.feed(frame),
            calibrating=lambda: self.calibrator.calibrating,
            observe=observe,
        )
        self.device = device(self.pipeline.on_frame, self.pipeline.on_link_state)
        self.calibrator = CalibrationController(
            self.settings,
            self.events,
            link=self.device,
            store=documents,
            field=field,
            onboard=options.onboard,
            settings=calibrator_settings
            or CalibratorSettings(timeout_s=options.calibration_timeout_s),
            calibration_source=self.calibration_source,
            clock=clock,
        )
        self.params = ParamStore(
            self.settings,
            documents,
            defaults=options.param_defaults,
            apply_calibration=self._calibration_from_params,
            stored_view=stored.view if stored.calibration == calibration else None,
            events=self.events,
        )
        self.mavlink_tap = MessageTap()
        self.services = BridgeServices(
            status=self.status,
            settings=self.settings,
            params=self.params,
            calibrator=self.calibrator,
            calibrations=self.calibrations,
            events=self.events,
            device=self.device,
            mavlink_tap=self.mavlink_tap,
            documents=documents,
            drift=self.drift,
            tilt=self.tilt,
        )
        self.settings.subscribe(self._on_settings)
        self.params.subscribe(self._on_params)
        self.params.start()
        self.calibrator.onboard = self.params.get("BRG_CAL_ONBOARD") != 0
        self.calibrator.fitness_limit_mG = self.params.get("COMPASS_CAL_FIT")
        self.drift.set_mode(LEARN_MODES[int(self.params.get("BRG_CAL_LEARN"))])
        if self.params.get("BRG_CAL_UNDO") != 0:  # a request left over from a crash
            self.params.set("BRG_CAL_UNDO", 0, source="start")

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

    def set_outputs(self, outputs: Sequence[Output]) -> None:
        """The outputs every sample goes to, in order."""
        self.pipeline.set_outputs(outputs)

    @property
    def outputs(self) -> tuple[Output, ...]:
        """The outputs every sample goes to."""
        return self.pipeline.outputs

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

    # -- wiring between the owners -----------------------------------------------------

    def _calibration_from_params(self, cal: Calibration, view: Mapping[str, float]) -> str:
        out = self.calibrator.apply_calibration(
            cal, source=PARAMETERS, write_device=False, view=dict(view)
        )
        return "" if out.ok else out.message

    def _on_settings(self, change: SettingsChange) -> None:
        if change.aspect in ("mounting", "calibration"):
            # The compass's axes or its accelerometer's level moved: what the tilt estimate
            # held, and the residual to the autopilot's axes it learnt, no longer hold.
            self.tilt.reset(f"{change.aspect} changed by {change.source}")
        if change.aspect == "reference":
            # A new position (reload, autopilot): fits are scaled to the field there.
            self.calibrator.set_field(self.settings.field)

    def _apply_learned(
        self,
        cal: Calibration,
        source: str,
        report: Mapping[str, Any] | None,
        view: Mapping[str, float] | None,
    ) -> str:
        """The drift monitor's learned (or restored) calibration: engine, store, events.

        Not written to the device: its own heading is only shown beside ours, and
        learning would wear its flash a step at a time.
        """
        out = self.calibrator.apply_calibration(
            cal,
            source=source,
            report=dict(report) if report is not None else None,
            write_device=False,
            view=dict(view) if view is not None else None,
        )
        return "" if out.ok else out.message

    def _drift_mode_lowered(self, mode: str) -> None:
        """An undo turned learning down: the parameter follows (it persists the choice)."""
        self.params.set("BRG_CAL_LEARN", float(LEARN_MODES.index(mode)), source="undo")

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
