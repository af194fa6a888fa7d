"""The application: the running bridge's state and the one owner of each part of it.

:class:`Bridge` holds the attitude engine and its settings' writer, the event
bus, the calibration store and controller, the drift monitor, the parameter
store and the per-frame pipeline, reacts to their changes, and gives every
adapter the same :class:`~bridge.app.services.BridgeServices`. It does no I/O
of its own: :func:`build_bridge` builds its parts, each after what it needs,
on the state directory (:class:`~bridge.documents.DocumentStore`); the compass
(:class:`~bridge.protocol.device.DevicePort`: the serial link, or the in-memory tests'
harness), built after the pipeline it feeds, is connected last
(:meth:`Bridge.connect`). :func:`bridge.daemon.wiring.build_daemon` does both
for the daemon. The functions below are the few hooks between the parts,
named, so that the parts get bound functions (no lambda) of parts already built.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from bridge.app.calibration.controller import CalibrationController, CalibratorSettings
from bridge.app.calibration.drift import DriftMonitor
from bridge.app.calibration.store import CalibrationStore
from bridge.app.params import PARAMETERS, ParamChange, ParamStore
from bridge.app.paramspec import CONFIG_PARAMS, param_from_config
from bridge.app.pipeline import Pipeline
from bridge.app.sample import DaemonStatus
from bridge.app.services import BridgeServices, MessageTap
from bridge.app.settings import EngineSettings, SettingsChange
from bridge.app.tilt import TiltSources, frame_latency_s
from bridge.config import Config
from bridge.core.attitude import AttitudeEngine
from bridge.core.calibration import Calibration
from bridge.core.wmm import EarthField, earth_field
from bridge.documents import DocumentStore
from bridge.events import EventBus, Subscribers
from bridge.protocol.device import DevicePort, LinkState
from bridge.types import LEARN_MODES, Clock, HeadingReference

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
    """A calibration set parameter by parameter (a ground station's COMPASS_* writes): its
    save paced, as params.json's (a storm of sets is a write a second)."""
    out = calibrator.apply_calibration(
        cal, source=PARAMETERS, write_device=False, view=dict(view), paced=True
    )
    return "" if out.ok else out.message


def learning_lowered(params: ParamStore, mode: str) -> None:
    """An undo turned learning down: BRG_CAL_LEARN follows (it persists the choice)."""
    params.set("BRG_CAL_LEARN", float(LEARN_MODES.index(mode)), source="undo")


class Bridge:
    """The running bridge's state (see the module docstring).

    Every part comes in built (:func:`build_bridge` builds them);
    ``calibration_source`` says where the calibration the bridge started with
    came from. Built, it subscribes to the settings and the parameters and
    applies the stored parameters. The compass comes last, through
    :meth:`connect`: it is built after the pipeline it feeds, and
    :attr:`device` and :attr:`services` exist from then on.
    """

    device: DevicePort  #: the compass (set by :meth:`connect`)
    services: BridgeServices  #: what every adapter is built with (set by :meth:`connect`)

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
        self.documents = documents
        self.mavlink_tap = MessageTap()
        #: Told every change of the link's state (:meth:`on_link_state`), in the link's thread.
        self.link_states: Subscribers[LinkState] = Subscribers()
        settings.subscribe(self._on_settings)
        params.subscribe(self._on_params)
        params.start()
        calibrator.onboard = params.get("BRG_CAL_ONBOARD") != 0
        calibrator.fitness_limit_mG = params.get("COMPASS_CAL_FIT")
        drift.set_mode(LEARN_MODES[int(params.get("BRG_CAL_LEARN"))])
        if params.get("BRG_CAL_UNDO") != 0:  # a request left over from a crash
            params.set("BRG_CAL_UNDO", 0, source="start")

    def connect(self, device: DevicePort) -> None:
        """The compass, built after the pipeline (it hands its frames to
        ``pipeline.on_frame``): the calibration controller commands it, the adapters
        get it with :attr:`services`. The graph's one loop -- frames device -> pipeline
        -> controller, commands controller -> device -- is closed here, once."""
        self.device = device
        self.calibrator.use_device(device)
        self.services = BridgeServices(
            status=self.status,
            settings=self.settings,
            params=self.params,
            calibrator=self.calibrator,
            calibrations=self.calibrations,
            events=self.events,
            device=device,
            mavlink_tap=self.mavlink_tap,
            documents=self.documents,
            drift=self.drift,
            tilt=self.tilt,
            link_states=self.link_states,
        )

    def on_link_state(self, old: LinkState, new: LinkState) -> None:
        """The link's state changed (called in its reader thread): the pipeline's link
        events, then whoever follows the state (a status that goes out on a change
        waits on this instead of looking at the state on a clock)."""
        self.pipeline.on_link_state(old, new)
        for fn in self.link_states:
            try:
                fn(new)
            except Exception:  # a follower's bug must not reach the link's reader
                log.exception("link state subscriber failed")

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
            parameters_error=self.params.last_error,
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


def build_bridge(
    options: BridgeOptions,
    *,
    documents: DocumentStore | None = None,
    calibration: Calibration | None = None,
    calibration_source: str = "",
    calibrator_settings: CalibratorSettings | None = None,
    clock: Clock | None = None,
) -> Bridge:
    """The application, each part built after what it needs; connect the compass next
    (:meth:`Bridge.connect`).

    ``calibration`` overrides the stored one (tests, replays, the simulator's true
    calibration), ``calibration_source`` says where it came from. The hooks between
    the parts are bound methods and the functions above, never a lambda to a part
    built later. ``calibrator_settings`` tune the calibration controller; ``clock``
    (a test's simulated clock) times the controller, the drift monitor's samples
    and the pipeline's frame clock (a frame's sampling instant on the simulated
    compass's clock, not the link's); either way the controller's and the drift
    monitor's frames keep the instant they were sampled, not their arrival.
    """
    calibrations = CalibrationStore(documents)
    stored = calibrations.load()
    if calibration is None:
        calibration, source = stored.calibration, stored.description
    else:
        source = calibration_source or "given"
    events = EventBus()
    engine = AttitudeEngine(calibration, heading_reference=options.heading_reference)
    tilt = TiltSources(frame_latency=options.frame_latency_s)
    if options.tilt != "accelerometer":
        engine.set_tilt_policy(tilt)
    field = location_field(options.location)
    settings = EngineSettings(engine, field=field)
    calibrator = CalibrationController(
        settings,
        events,
        store=documents,
        field=field,
        onboard=options.onboard,
        settings=calibrator_settings or CalibratorSettings(timeout_s=options.calibration_timeout_s),
        calibration_source=source,
        clock=clock or time.monotonic,
    )
    params = ParamStore(
        settings,
        documents,
        defaults=options.param_defaults,
        apply_calibration=functools.partial(apply_from_parameters, calibrator),
        stored_view=stored.view if stored.calibration == calibration else None,
        events=events,
    )
    drift = DriftMonitor(
        settings,
        events,
        apply=functools.partial(apply_learned, calibrator),
        calibrating=calibrator.calibrating,
        store=calibrations,
        mode=options.learn,
        on_mode=functools.partial(learning_lowered, params),
    )
    pipeline = Pipeline(
        engine,
        events,
        feed=calibrator.feed,
        calibrating=calibrator.calibrating,
        observe=drift.observe,
        clock=clock,
    )
    return Bridge(
        events=events,
        engine=engine,
        tilt=tilt,
        settings=settings,
        calibrations=calibrations,
        calibration_source=source,
        calibrator=calibrator,
        params=params,
        drift=drift,
        pipeline=pipeline,
        documents=documents,
    )
