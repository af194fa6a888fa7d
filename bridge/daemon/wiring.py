"""The ONE place that wires the parts into the running daemon.

::

    Config --make_transport--> Transport --> CompassLink (serial adapter, reader thread)
        --> Bridge.pipeline.on_frame, in the reader thread (bridge.app.pipeline)
        --> CompassSample --> every Output.publish(sample): MAVLink, Zenoh, console

:class:`~bridge.app.bridge.Bridge` (the application layer) owns the state --
engine settings, parameters, calibration store and controller, the pipeline;
the adapters (:mod:`bridge.link`, :mod:`bridge.mavlink`, :mod:`bridge.zenoh`,
:mod:`bridge.console`, :mod:`bridge.systemd`) get its
:class:`~bridge.app.services.BridgeServices` and never each other.
:class:`Daemon` builds them in that order and starts and stops them; the
service-manager side (sd_notify, watchdog, reload) is
:class:`bridge.daemon.runner.Service`, which runs a :class:`Daemon`.

Threads: the link's reader thread (which runs the pipeline: one wake per
frame) and handshake thread, the calibration worker, and the outputs' own.
:meth:`Daemon.stop` stops them all within a bounded time.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from bridge.app.bridge import Bridge, BridgeOptions
from bridge.app.calibration import CalibrationController
from bridge.app.calibration.store import CalibrationStore
from bridge.app.params import PARAMS_DOCUMENT, ParamChange, ParamStore
from bridge.app.paramspec import CAL_PARAMS
from bridge.app.sample import CompassSample, DaemonStatus, Output
from bridge.app.services import BridgeServices, magnetometer_calibrated
from bridge.app.settings import EngineSettings
from bridge.app.state import home_relative, state_summary, stored_parameters, value_text
from bridge.calibration.model import Calibration
from bridge.calibration.sessions import CalibratorSettings
from bridge.config import Config
from bridge.console import ConsoleOutput, TerminalGate
from bridge.core.attitude import AttitudeEngine
from bridge.device import LinkState, Received
from bridge.events import Event, EventBus
from bridge.link.serial_link import CompassLink
from bridge.link.transport import Transport, open_transport
from bridge.storage import StateStore

log = logging.getLogger(__name__)

__all__ = ["Daemon", "build_outputs", "make_transport"]


def make_transport(cfg: Config) -> Transport:
    """The transport ``cfg.device`` names; ``"sim"`` is built from ``[sim]`` and ``[location]``."""
    if cfg.device.port != "sim":
        return open_transport(cfg.device.port, cfg.device.baud, realtime=cfg.device.replay_realtime)
    from bridge.sim.pty import make_motion  # only the simulated port needs the simulator

    sim = cfg.sim
    loc = cfg.location
    return open_transport(
        "sim",
        cfg.device.baud,
        seed=sim.seed,
        motion=make_motion(sim.motion, sim.seed, sim.shake_g),
        ideal=sim.ideal,
        flash_path=sim.flash_file or None,
        # The simulated unit sits where the configuration says the vehicle is, so
        # the expected field (WMM) and the simulated one agree.
        location=(loc.latitude, loc.longitude, loc.altitude_m) if loc is not None else None,
    )


#: The one command that gives ``run --simulate`` a fresh start (docs/tools.md, README).
SIM_RESET_COMMAND = "compass-bridge run --simulate --reset"


def _simulator_calibration(
    cfg: Config, transport: Transport, documents: StateStore
) -> tuple[Calibration | None, str, str]:
    """The simulated compass's calibration and the console's intro lines about it.

    A newcomer's first run shows a heading that turns with the simulated unit: with
    nothing stored, the unit starts with its true calibration (known in simulation,
    what a good calibration gives), unless ``[sim] calibrated = false`` asks for the
    raw unit. A stored calibration (one the user made) is used as for a real compass.
    The second line names the state directory, what it holds and how to empty it.
    """
    seed = f"seed {cfg.sim.seed}"
    where = home_relative(cfg.storage.dir)
    state = (
        f"State (calibration, parameters set over MAVLink): {where}, holding "
        f"{state_summary(documents)}. A fresh start: {SIM_RESET_COMMAND}"
    )
    if CalibrationStore(documents).load().stored:
        return (
            None,
            "",
            f"Simulated compass ({seed}) with the calibration stored in {where}.\n" + state,
        )
    calibrate = "calibrate it yourself: README, 'Calibrate it'"
    if not cfg.sim.calibrated:
        return (
            None,
            "",
            f"Simulated compass ({seed}), UNCALIBRATED: its heading carries the unit's "
            f"hard- and soft-iron errors; {calibrate}.\n" + state,
        )
    firmware = getattr(transport, "firmware", None)
    errors = getattr(getattr(firmware, "sensor", None), "errors", None)
    if errors is None:
        return None, "", ""
    return (
        errors.true_calibration(),
        "simulator (the unit's true errors)",
        f"Simulated compass ({seed}), calibrated with its true errors. To see it "
        f"uncalibrated: --set sim.calibrated=false; to {calibrate}.\n" + state,
    )


class Daemon:
    """The running bridge: the application, the compass link, the outputs.

    ``transport`` defaults to :func:`make_transport` on ``cfg.device``;
    ``calibration`` to the stored one. ``outputs`` are outputs built before the
    daemon (tests' collectors); those that need the bridge's services are
    built from :attr:`services` and added with :meth:`set_outputs`.
    ``calibrator_settings`` and ``clock`` tune the calibration controller.
    """

    def __init__(
        self,
        cfg: Config,
        outputs: Sequence[Output] = (),
        *,
        transport: Transport | None = None,
        calibration: Calibration | None = None,
        calibrator_settings: CalibratorSettings | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.cfg = cfg
        if transport is None:
            transport = make_transport(cfg)
        documents = StateStore(cfg.storage.dir)
        #: One line for the console about the calibration in use ("" for a real compass).
        self.intro = ""
        source = ""
        if cfg.device.port == "sim" and calibration is None:
            calibration, source, self.intro = _simulator_calibration(cfg, transport, documents)

        def make_link(
            on_frame: Callable[[Received], None],
            on_state: Callable[[LinkState, LinkState], None],
        ) -> CompassLink:
            return CompassLink(
                transport,
                protocol=cfg.device.protocol,  # type: ignore[arg-type]  # validated by config
                rate_hz=cfg.device.rate_hz if cfg.device.protocol == "gmr" else None,
                stale_after=cfg.device.stale_after,
                on_state=on_state,
                # The pipeline runs in the link's reader thread: no queue, no second thread
                # to wake for every frame (see bridge.app.pipeline).
                on_frame=on_frame,
            )

        self.bridge = Bridge(
            BridgeOptions.from_config(cfg),
            make_link,
            documents=documents,
            calibration=calibration,
            calibration_source=source,
            calibrator_settings=calibrator_settings,
            clock=clock,
        )
        self.transport = transport
        log.info("calibration: %s (state directory %s)", self.calibration_source, cfg.storage.dir)
        if magnetometer_calibrated(self.services) is False:
            log.warning(
                "calibration: none in %s: the heading carries the compass's hard- and soft-"
                "iron errors (often tens of degrees); calibrate it (docs/calibration.md)",
                cfg.storage.dir,
            )
        try:
            params = stored_parameters(documents)
        except Exception:  # the stores have logged it
            params = {}
        if params:
            log.info(
                "parameters stored in %s override the configuration: %s",
                documents.directory / f"{PARAMS_DOCUMENT}.json",
                ", ".join(f"{k} = {value_text(v)}" for k, v in sorted(params.items())),
            )
        link = self.bridge.device
        assert isinstance(link, CompassLink)
        self.link: CompassLink = link
        self.bridge.set_outputs(outputs)

    # -- the parts, by name --------------------------------------------------------

    @property
    def services(self) -> BridgeServices:
        """What adapters are built with (:class:`~bridge.app.services.BridgeServices`)."""
        return self.bridge.services

    @property
    def engine(self) -> AttitudeEngine:
        """The attitude engine (read it; change it through :attr:`settings`)."""
        return self.bridge.engine

    @property
    def settings(self) -> EngineSettings:
        """The engine settings' one writer."""
        return self.bridge.settings

    @property
    def params(self) -> ParamStore:
        """The parameter store."""
        return self.bridge.params

    @property
    def events(self) -> EventBus:
        """The operator event bus."""
        return self.bridge.events

    @property
    def calibrator(self) -> CalibrationController:
        """The calibration controller."""
        return self.bridge.calibrator

    @property
    def calibration_source(self) -> str:
        """Where the calibration the daemon started with came from."""
        return self.bridge.calibration_source

    @property
    def outputs(self) -> tuple[Output, ...]:
        """The outputs, in publish order."""
        return self.bridge.outputs

    def set_outputs(self, outputs: Sequence[Output]) -> None:
        """Replace the outputs (one reference store; the pipeline reads it once per sample)."""
        self.bridge.set_outputs(outputs)

    @property
    def samples(self) -> int:
        """Samples the pipeline has produced."""
        return self.bridge.pipeline.samples

    @property
    def pipeline_errors(self) -> int:
        """Frames or publishes that failed in the pipeline."""
        return self.bridge.pipeline.errors

    @property
    def pipeline_alive_at(self) -> float:
        """Monotonic time up to which the pipeline is known not to be stuck (the watchdog's)."""
        return self.bridge.pipeline.alive_at

    def process(self, item: Received) -> CompassSample | None:
        """One received frame to a sample, without publishing it (benchmarks)."""
        return self.bridge.pipeline.process(item.frame, item.t)

    def status(self) -> DaemonStatus:
        """A snapshot of link state and counters."""
        return self.bridge.status()

    @property
    def ended(self) -> bool:
        """A replayed recording has been played to its end."""
        return self.link.ended

    # -- lifecycle ---------------------------------------------------------------

    def start(self) -> Daemon:
        """Start outputs, the calibrator and the link (whose reader runs the pipeline)."""
        for out in self.outputs:
            out.start()
        self.bridge.start()
        self.link.start()
        log.info(
            "bridge started: %s (%s), calibration %s, outputs %s",
            self.link.name,
            self.cfg.device.protocol,
            self.bridge.calibration_source,
            ", ".join(o.name for o in self.outputs) or "none",
        )
        return self

    def stop(self, timeout: float = 3.0) -> None:
        """Stop everything within about ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        # Before the link: a device calibration still running is aborted over it.
        self.bridge.stop(timeout=max(0.1, 0.25 * timeout))
        # Joins the reader, and so the pipeline: no frame reaches an output after this.
        self.link.close(timeout=max(0.1, 0.5 * timeout))
        for out in self.outputs:
            out.close(max(0.1, deadline - time.monotonic()))


def _truth(daemon: Daemon) -> Callable[[CompassSample], float | None] | None:
    """The simulated truth of a sample's heading (a simulated compass only)."""
    if daemon.cfg.device.port != "sim":
        return None
    from bridge.sim.truth import truth_heading_deg

    transport = daemon.transport

    def truth(sample: CompassSample) -> float | None:
        # Looked up per sample: a reload may have swapped the simulated unit.
        fw = getattr(transport, "firmware", None)
        return truth_heading_deg(fw, sample.seq, sample.heading_reference)

    return truth


def _console(daemon: Daemon, gate: TerminalGate | None) -> ConsoleOutput:
    """The live line, with notes naming the files a calibration or a parameter goes to."""
    console = ConsoleOutput(daemon.status, intro=daemon.intro, truth=_truth(daemon), gate=gate)
    where = Path(home_relative(daemon.cfg.storage.dir))

    def on_event(event: Event) -> None:
        if event.kind == "calibration.accepted" and event.data.get("saved"):
            console.note(f"{event.text}: {where / 'calibration.json'}")

    def on_params(change: ParamChange) -> None:
        names = [n for n in change.names if n not in CAL_PARAMS]
        # Written within a second (coalesced); a write that fails is said on its own.
        if names and change.source != "start" and not daemon.params.last_error:
            values = ", ".join(f"{n} = {daemon.params.get(n):g}" for n in names)
            console.note(
                f"Parameter {values} stored in {where / 'params.json'}: it overrides the "
                "configuration from now on ('compass-bridge config' shows it)"
            )

    daemon.events.subscribe(on_event)
    daemon.params.subscribe(on_params)
    return console


def build_outputs(
    cfg: Config,
    daemon: Daemon,
    *,
    console: bool,
    gate: TerminalGate | None = None,
) -> list[Output]:
    """The outputs the configuration asks for, built on the daemon's services.

    MAVLink comes first: the pipeline calls ``publish`` in this order, and the
    autopilot's ATTITUDE is the latency-critical output (Zenoh puts its
    documents in ``publish`` too).
    """
    services = daemon.bridge.services
    outputs: list[Output] = []
    if console:
        outputs.append(_console(daemon, gate))
    if cfg.mavlink.endpoints:
        from bridge.mavlink import MavlinkOutput, MavlinkSettings

        outputs.append(MavlinkOutput(MavlinkSettings.from_config(cfg), services))
    if cfg.zenoh.enabled:
        # Imported here: zenoh (a native runtime) loads only when it is asked for.
        from bridge.zenoh.output import ZenohOutput
        from bridge.zenoh.services import fleet_services
        from bridge.zenoh.session import ZenohSettings

        outputs.append(ZenohOutput(ZenohSettings.from_config(cfg.zenoh), fleet_services(services)))
    return outputs
