"""The ONE place that wires the parts into the running daemon: :func:`build_daemon`.

::

    Config --make_transport--> Transport --> CompassLink (serial adapter, reader thread)
        --> Pipeline.on_frame, in the reader thread (bridge.app.pipeline)
        --> CompassSample --> every Output.publish(sample): MAVLink, Zenoh, console

:func:`build_daemon` builds the running bridge from the configuration, each
part after what it needs, top to bottom: the port; the application
(:func:`bridge.app.bridge.build_bridge`: engine, settings, calibration
controller, parameters, drift monitor, pipeline, held by a
:class:`~bridge.app.bridge.Bridge`); the compass link that feeds the pipeline,
connected to the application last (:meth:`~bridge.app.bridge.Bridge.connect`).
The adapters (:mod:`bridge.mavlink`, :mod:`bridge.zenoh`, :mod:`bridge.console`,
:mod:`bridge.systemd`) get the bridge's
:class:`~bridge.app.services.BridgeServices` and never see each other;
:func:`build_outputs` builds those the configuration asks for. :class:`Daemon`
is what comes out: the parts by name, and the order they start and stop in.
The service-manager side (sd_notify, watchdog, reload) is
:class:`bridge.daemon.runner.Service`, which runs one.

The graph has one loop, and it is the compass's: frames go link -> pipeline ->
calibration controller, device commands go controller -> link. The
application is built first (the link needs its pipeline) and the link is
connected to it once it exists.

Threads: the link's reader thread (which runs the pipeline: one wake per
frame) and handshake thread, the calibration worker, the drift monitor, and
the outputs' own. :meth:`Daemon.stop` stops them all within a bounded time.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from bridge.app.bridge import Bridge, BridgeOptions, build_bridge
from bridge.app.calibration.store import CalibrationStore
from bridge.app.params import PARAMS_DOCUMENT, ParamChange
from bridge.app.paramspec import CAL_PARAMS
from bridge.app.sample import CompassSample, Output
from bridge.app.services import magnetometer_calibrated
from bridge.app.state import home_relative, state_summary, stored_parameters, value_text
from bridge.calibration.sessions import CalibratorSettings
from bridge.config import Config, DeviceConfig
from bridge.console import ConsoleOutput, TerminalGate
from bridge.core.calibration import Calibration
from bridge.events import Event
from bridge.link.observed import ObservedTransport
from bridge.link.serial_link import CompassLink
from bridge.link.transport import SimTransport, Transport, open_transport
from bridge.storage import StateStore
from bridge.types import Clock

if TYPE_CHECKING:
    from bridge.sim.firmware import Firmware

log = logging.getLogger(__name__)

__all__ = ["Daemon", "build_daemon", "build_outputs", "make_simulator", "make_transport"]


def make_simulator(cfg: Config) -> Firmware | None:
    """The simulated compass ``device.port = "sim"`` stands for (``[sim]``, ``[location]``).

    None for any other port.
    """
    if cfg.device.port != "sim":
        return None
    # Imported here: only the simulated port needs the simulator.
    from bridge.sim.firmware import make_firmware
    from bridge.sim.pty import make_motion

    sim = cfg.sim
    loc = cfg.location
    return make_firmware(
        sim.seed,
        motion=make_motion(sim.motion, sim.seed, sim.shake_g),
        ideal=sim.ideal,
        flash_path=sim.flash_file or None,
        # The simulated unit sits where the configuration says the vehicle is, so
        # the expected field (WMM) and the simulated one agree.
        location=(loc.latitude, loc.longitude, loc.altitude_m) if loc is not None else None,
    )


def make_transport(cfg: Config, simulator: Firmware | None = None) -> Transport:
    """The transport ``cfg.device`` names (not opened yet).

    For ``"sim"`` it talks to ``simulator`` (one made by :func:`make_simulator`
    when None).
    """
    if cfg.device.port != "sim":
        return open_transport(cfg.device.port, cfg.device.baud, realtime=cfg.device.replay_realtime)
    if simulator is None:
        simulator = make_simulator(cfg)
    assert simulator is not None  # the port is "sim"
    return SimTransport(simulator)


#: The one command that gives ``run --simulate`` a fresh start (docs/tools.md, README).
SIM_RESET_COMMAND = "compass-bridge run --simulate --reset"


def _simulator_calibration(
    cfg: Config, simulator: Firmware | None, documents: StateStore, stored: bool
) -> tuple[Calibration | None, str, str]:
    """The simulated compass's calibration and the console's intro lines about it.

    A newcomer's first run shows a heading that turns with the simulated unit: with
    nothing stored, the unit starts with its true calibration (known in simulation,
    what a good calibration gives), unless ``[sim] calibrated = false`` asks for the
    raw unit. A stored calibration (one the user made) is used as for a real compass.
    The second line names the state directory, what it holds and how to empty it.
    ``stored``: the state directory holds a calibration.
    """
    seed = f"seed {cfg.sim.seed}"
    where = home_relative(cfg.storage.dir)
    state = (
        f"State (calibration, parameters set over MAVLink): {where}, holding "
        f"{state_summary(documents)}. A fresh start: {SIM_RESET_COMMAND}"
    )
    if stored:
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
    if simulator is None:  # a caller's own transport on the "sim" port: no unit to ask
        return None, "", ""
    return (
        simulator.sensor.errors.true_calibration(),
        "simulator (the unit's true errors)",
        f"Simulated compass ({seed}), calibrated with its true errors. To see it "
        f"uncalibrated: --set sim.calibrated=false; to {calibrate}.\n" + state,
    )


def _log_start_state(cfg: Config, bridge: Bridge, documents: StateStore) -> None:
    """Say which calibration and which stored parameters the bridge starts with."""
    log.info("calibration: %s (state directory %s)", bridge.calibration_source, cfg.storage.dir)
    if magnetometer_calibrated(bridge.services) is False:
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


@dataclass(eq=False)
class Daemon:
    """The running bridge as :func:`build_daemon` wired it: its parts, by name.

    ``bridge`` is the application (the state and its owners; adapters get its
    ``services``); ``link`` the compass link on ``transport``;
    ``simulator`` the simulated unit behind the ``"sim"`` port (None for a real
    one); ``intro`` the console's lines about the calibration in use ("" for a
    real compass). It starts and stops them in order and reopens the port on a
    reload (:meth:`reopen`); everything else is asked of the part that owns it.
    """

    bridge: Bridge
    link: CompassLink
    transport: ObservedTransport
    simulator: Firmware | None = None
    intro: str = ""

    def start(self) -> Daemon:
        """Start outputs, the application's threads and the link (whose reader runs the pipeline)."""
        outputs = self.bridge.pipeline.outputs
        for out in outputs:
            out.start()
        self.bridge.start()
        self.link.start()
        log.info(
            "bridge started: %s (%s), calibration %s, outputs %s",
            self.link.name,
            self.link.protocol,
            self.bridge.calibration_source,
            ", ".join(o.name for o in outputs) or "none",
        )
        return self

    def stop(self, timeout: float = 3.0) -> None:
        """Stop everything within about ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        # Before the link: a device calibration still running is aborted over it.
        self.bridge.stop(timeout=max(0.1, 0.25 * timeout))
        # Joins the reader, and so the pipeline: no frame reaches an output after this.
        self.link.close(timeout=max(0.1, 0.5 * timeout))
        for out in self.bridge.pipeline.outputs:
            out.close(max(0.1, deadline - time.monotonic()))

    def reopen(
        self, device: DeviceConfig, transport: Transport, simulator: Firmware | None
    ) -> None:
        """Reopen the compass port on ``transport`` with ``device``'s settings (a reload).

        The link keeps running: its reader swaps the transport in at its next call,
        then reconnects with the new rate (:meth:`ObservedTransport.replace
        <bridge.link.observed.ObservedTransport.replace>`).
        """
        self.link.set_rate(device.rate_hz if device.protocol == "gmr" else None, device.stale_after)
        self.simulator = simulator
        self.transport.replace(transport)


def _ignore() -> None:
    """No one watches the reader's progress (a daemon outside a service)."""


def build_daemon(
    cfg: Config,
    outputs: Sequence[Output] = (),
    *,
    transport: Transport | None = None,
    simulator: Firmware | None = None,
    calibration: Calibration | None = None,
    calibrator_settings: CalibratorSettings | None = None,
    clock: Clock | None = None,
    on_read: Callable[[], None] = _ignore,
) -> Daemon:
    """The running bridge, built from ``cfg``: each part after what it needs.

    ``transport`` defaults to :func:`make_transport` on ``cfg.device`` (with
    ``simulator``, or one made by :func:`make_simulator`); it is wrapped in an
    :class:`~bridge.link.observed.ObservedTransport` that calls ``on_read`` on
    every return from a reader-side call (the service watchdog's beat) and that
    a reload swaps. ``calibration`` overrides the stored one (tests, replays);
    with none stored, a simulated unit starts with its true calibration unless
    ``[sim] calibrated = false``. ``outputs`` are outputs built before the bridge
    (tests' collectors); those built on its services are added with
    ``daemon.bridge.pipeline.set_outputs``. ``calibrator_settings`` tune the
    calibration controller; ``clock`` (a test's simulated clock) times the
    controller, the drift monitor's samples and the pipeline's frame clock (the
    frames' sampling instants on the simulated compass's clock, not the link's);
    either way the controller's and the drift monitor's frames keep the instant they
    were sampled, not their arrival.
    """
    # -- the port and what the state directory holds
    if transport is None:
        if simulator is None:
            simulator = make_simulator(cfg)
        transport = make_transport(cfg, simulator)
    port = ObservedTransport(transport, on_read)
    documents = StateStore(cfg.storage.dir)
    intro = ""
    source = ""
    if cfg.device.port == "sim" and calibration is None:
        stored = CalibrationStore(documents).load().stored
        calibration, source, intro = _simulator_calibration(cfg, simulator, documents, stored)

    # -- the application: its owners, each after what it needs (bridge.app.bridge)
    bridge = build_bridge(
        BridgeOptions.from_config(cfg),
        documents=documents,
        calibration=calibration,
        calibration_source=source,
        calibrator_settings=calibrator_settings,
        clock=clock,
    )

    # -- the compass link: it feeds the pipeline, and the controller commands over it
    link = CompassLink(
        port,
        protocol=cfg.device.protocol,  # type: ignore[arg-type]  # validated by config
        rate_hz=cfg.device.rate_hz if cfg.device.protocol == "gmr" else None,
        stale_after=cfg.device.stale_after,
        on_state=bridge.on_link_state,
        # The pipeline runs in the link's reader thread: no second thread to wake for
        # every frame (see bridge.app.pipeline).
        on_frame=bridge.pipeline.on_frame,
        due_at=bridge.pipeline.due_at_time if _read_bursts(cfg) else None,
    )
    bridge.connect(link)
    bridge.pipeline.set_outputs(outputs)
    _log_start_state(cfg, bridge, documents)
    return Daemon(bridge, link, port, simulator, intro)


def _read_bursts(cfg: Config) -> bool:
    """Whether the link reads in bursts: as configured, except for a replay played as fast
    as it decodes (its frames come from no clock the outputs' due times could follow)."""
    dev = cfg.device
    return dev.read_bursts and (dev.replay_realtime or not dev.port.startswith("replay:"))


def _truth(daemon: Daemon) -> Callable[[CompassSample], float | None] | None:
    """The simulated truth of a sample's heading (a simulated compass only)."""
    if daemon.simulator is None:
        return None
    from bridge.sim.truth import truth_heading_deg

    def truth(sample: CompassSample) -> float | None:
        # Looked up per sample: a reload may have swapped the simulated unit.
        unit = daemon.simulator
        return (
            None if unit is None else truth_heading_deg(unit, sample.seq, sample.heading_reference)
        )

    return truth


def _console(cfg: Config, daemon: Daemon, gate: TerminalGate | None) -> ConsoleOutput:
    """The live line, with notes naming the files a calibration or a parameter goes to."""
    bridge = daemon.bridge
    console = ConsoleOutput(bridge.status, intro=daemon.intro, truth=_truth(daemon), gate=gate)
    where = Path(home_relative(cfg.storage.dir))

    def on_event(event: Event) -> None:
        if event.kind == "calibration.accepted" and event.data.get("saved"):
            console.note(f"{event.text}: {where / 'calibration.json'}")

    def on_params(change: ParamChange) -> None:
        names = [n for n in change.names if n not in CAL_PARAMS]
        # Written within a second (coalesced); a write that fails is said on its own.
        if names and change.source != "start" and not bridge.params.last_error:
            values = ", ".join(f"{n} = {bridge.params.get(n):g}" for n in names)
            console.note(
                f"Parameter {values} stored in {where / 'params.json'}: it overrides the "
                "configuration from now on ('compass-bridge config' shows it)"
            )

    bridge.events.subscribe(on_event)
    bridge.params.subscribe(on_params)
    return console


def build_outputs(
    cfg: Config,
    daemon: Daemon,
    *,
    console: bool,
    gate: TerminalGate | None = None,
) -> list[Output]:
    """The outputs the configuration asks for, built on the bridge's services.

    MAVLink comes first: the pipeline calls ``publish`` in this order, and the
    autopilot's ATTITUDE is the latency-critical output (Zenoh puts its
    documents in ``publish`` too).
    """
    services = daemon.bridge.services
    outputs: list[Output] = []
    if console:
        outputs.append(_console(cfg, daemon, gate))
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
