"""The ONE place that wires the parts into the running daemon.

::

    Config --open_transport--> Transport --> CompassLink (reader thread)
        --> the pipeline, in the reader thread (on_frame), per frame:
              $PGMRA  : AttitudeEngine.solve_counts (nominal transfer -> stored
                        calibration -> tilt-compensated heading, + declination)
              heading-only sentence (nmea / os5000): forwarded, + declination
        --> CompassSample --> every Output.publish(sample)

Outputs are pluggable (:class:`Output`); today there is the console line
(:class:`ConsoleOutput`); MAVLink and Zenoh outputs plug in the same way in
:func:`build_outputs`. ``publish`` must never block the pipeline: an output
either keeps the latest sample and does its I/O in its own thread
(:class:`LatestSampleWorker`: console, Zenoh), or does only bounded,
non-blocking work (MAVLink encodes the streams that are due and hands the
packets to non-blocking UDP sends or per-peer bounded queues).

Threads: the link's reader thread (which runs the pipeline: one wake per
frame) and handshake thread, the calibration worker, and the outputs' own.
:meth:`Daemon.stop` stops them all within a bounded time.
"""

from __future__ import annotations

import logging
import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol, TextIO

from bridge.calibration.model import Calibration
from bridge.calibrator import CalibrationController, CalibratorSettings
from bridge.config import Config
from bridge.core.attitude import (
    AttitudeEngine,
    AttitudeSolution,
    FieldReference,
    field_reference_at,
)
from bridge.core.wmm import earth_field
from bridge.events import Event, EventBus, Severity
from bridge.link.serial_link import CompassLink, LinkCounters, LinkState, Received
from bridge.link.transport import Transport, open_transport
from bridge.protocol.gmr import AttitudeFrame, Flags
from bridge.protocol.heading import HeadingFrame
from bridge.storage import StateStore

log = logging.getLogger(__name__)

_SAT = int(Flags.SAT)

#: Disturbance start/end events: at most one per this many seconds (no flapping on the links).
DISTURBANCE_EVENT_MIN_S = 5.0

#: Name of the calibration document in the state directory (``<storage.dir>/calibration.json``).
CALIBRATION_DOCUMENT = "calibration"

HeadingReference = Literal["magnetic", "true"]


# ---------------------------------------------------------------------------
# What outputs receive
# ---------------------------------------------------------------------------


# Not frozen, on purpose (as AttitudeSolution): built for every frame, and a frozen
# dataclass's __init__ costs 2-3x plain slot stores when run cold at 100 Hz. Read-only by
# contract: the same instance goes to every output, in several threads.
@dataclass(slots=True)
class CompassSample:
    """One frame's result, as every output receives it (read-only by contract).

    ``source`` says who computed the heading: ``"host"`` (the attitude engine
    on the raw GMR vectors, calibrated on the host) or ``"device"`` (a
    heading-only compass's own heading, forwarded). ``heading_deg`` is the
    published heading, [0, 360) clockwise from the north ``heading_reference``
    names; the magnetic and true headings are given separately where known
    (true needs a declination). Angles in degrees; ``attitude`` carries the
    full host solution (radians, quaternion, calibrated vectors, quality
    flags) when ``source == "host"``. ``t`` is the monotonic time the frame
    arrived.
    """

    t: float
    source: Literal["host", "device"]
    heading_deg: float
    heading_reference: HeadingReference
    heading_magnetic_deg: float | None
    heading_true_deg: float | None
    declination_deg: float | None
    pitch_deg: float | None
    roll_deg: float | None
    seq: int | None = None
    device_heading_deg: float | None = None  #: the GMR's on-board heading, for comparison
    saturated: bool = False  #: a raw channel sat at an ADC rail: the vectors are clipped
    attitude: AttitudeSolution | None = None
    #: The frame's raw ADC counts (mx, my, mz, ax, ay, az), for MAVLink RAW_IMU; GMR frames only.
    raw_counts: tuple[int, int, int, int, int, int] | None = None


class Output(Protocol):
    """A consumer of samples (console, MAVLink, Zenoh ...).

    ``publish`` is called from the pipeline -- the link's reader thread -- for every
    sample and MUST NOT block or raise: do the I/O elsewhere (see :class:`LatestSampleWorker`).
    """

    @property
    def name(self) -> str:
        """Short name for logs."""
        ...

    def start(self) -> None:
        """Start the output's own thread(s)."""
        ...

    def publish(self, sample: CompassSample) -> None:
        """Hand over one sample; never blocks."""
        ...

    def close(self, timeout: float) -> None:
        """Stop within about ``timeout`` seconds."""
        ...


@dataclass(frozen=True, slots=True)
class DaemonStatus:
    """A snapshot for status displays."""

    port: str
    state: LinkState
    counters: LinkCounters
    samples: int
    pipeline_errors: int
    calibration_source: str


# ---------------------------------------------------------------------------
# Output helpers
# ---------------------------------------------------------------------------


class LatestSampleWorker:
    """Base for outputs: ``publish`` stores the latest sample; a thread emits it.

    Two pacings:

    * ``wake_on_publish=True`` (network outputs): :meth:`emit` runs for each
      new sample, at most once per ``interval`` seconds (a rate limit);
    * ``wake_on_publish=False`` (the console): :meth:`emit` runs every
      ``interval`` seconds with the latest sample, new or not (``None``
      before the first).

    Either way a slow consumer sees the newest data and skips the rest
    (counted, approximately, in ``skipped``) instead of stalling the pipeline.
    Errors in ``emit`` are counted and logged once, never fatal.
    """

    def __init__(self, name: str, interval: float, *, wake_on_publish: bool = True) -> None:
        if not interval > 0:
            raise ValueError(f"interval must be positive, got {interval}")
        self._name = name
        self.interval = interval
        self._wake_on_publish = wake_on_publish
        self._latest: CompassSample | None = None
        self._fresh = False
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.skipped = 0
        self.errors = 0

    @property
    def name(self) -> str:
        """Short name for logs."""
        return self._name

    def start(self) -> None:
        """Start the worker thread."""
        if self._thread is not None:
            raise RuntimeError(f"{self._name} already started")
        self._thread = threading.Thread(target=self._run, name=f"output-{self._name}", daemon=True)
        self._thread.start()

    def publish(self, sample: CompassSample) -> None:
        """Keep ``sample`` as the latest; O(1), no lock (one reference store, then a flag)."""
        if self._fresh:
            self.skipped += 1
        self._latest = sample
        self._fresh = True
        if self._wake_on_publish:
            self._wake.set()

    def _next(self, due: float) -> bool:
        """Wait for the next emit; False when stopping."""
        if self._wake_on_publish:
            while not self._fresh:
                self._wake.wait(0.5)  # bounded, so a stop is seen even without samples
                self._wake.clear()
                if self._stop.is_set():
                    return False
        return not self._stop.wait(max(0.0, due - time.monotonic()))

    def _run(self) -> None:
        # A clock-paced output waits one interval first: at start there is nothing to show yet.
        due = time.monotonic() + (0.0 if self._wake_on_publish else self.interval)
        while self._next(due):
            due = time.monotonic() + self.interval
            sample, self._fresh = self._latest, False
            try:
                self.emit(sample)
            except Exception:
                self.errors += 1
                if self.errors == 1:
                    log.exception("output %s failed (further failures are only counted)", self.name)
        try:
            self.finish()
        except Exception:
            log.exception("output %s failed to finish", self.name)

    def emit(self, sample: CompassSample | None) -> None:
        """Do the output's I/O for the latest sample (in the worker thread)."""
        raise NotImplementedError

    def finish(self) -> None:
        """Called once in the worker thread after the stop (flush, close)."""

    def close(self, timeout: float) -> None:
        """Stop the worker within ``timeout`` seconds."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("output %s did not stop within %.1f s", self.name, timeout)


def format_line(sample: CompassSample | None, status: DaemonStatus) -> str:
    """The console line: heading, pitch, roll, where the heading comes from, link health."""
    c = status.counters
    health = f"{status.state.value}  frames {c.attitude_frames or c.frames}"
    health += f"  lost {c.lost_frames}  bad {c.bad_lines_total}"
    if sample is None or status.state is not LinkState.STREAMING:
        what = "waiting for the compass" if sample is None else "no fresh data"
        return f"{what} on {status.port}  [{health}]"
    ref = "mag" if sample.heading_reference == "magnetic" else "true"
    parts = [f"hdg {sample.heading_deg:5.1f} {ref}"]
    if sample.heading_reference == "magnetic" and sample.heading_true_deg is not None:
        parts.append(f"(true {sample.heading_true_deg:5.1f})")
    parts.append(f"pitch {_deg(sample.pitch_deg)}")
    parts.append(f"roll {_deg(sample.roll_deg)}")
    src: str = sample.source
    if sample.device_heading_deg is not None:
        src += f", device hdg {sample.device_heading_deg:5.1f}"
    parts.append(f"[{src}]")
    flags = []
    if sample.saturated:
        flags.append("SATURATED")
    if sample.attitude is not None:
        a = sample.attitude
        flags += [n for n, on in (("degraded", a.degraded), ("disturbed", a.disturbed)) if on]
        if a.accelerating:
            flags.append("accelerating")
    if flags:
        parts.append(" ".join(flags).upper())
    return "  ".join(parts) + f"  [{health}]"


def _deg(v: float | None) -> str:
    return "  n/a" if v is None else f"{v:+6.1f}"


class ConsoleOutput(LatestSampleWorker):
    """A live line of heading/pitch/roll on a text stream (``run --simulate``).

    On a terminal the line is rewritten in place with ``\\r`` ten times a
    second; otherwise (a pipe, a log) one full line per second, so the output
    stays readable and testable.
    """

    def __init__(
        self,
        status: Callable[[], DaemonStatus],
        stream: TextIO | None = None,
        *,
        tty: bool | None = None,
        interval: float | None = None,
    ) -> None:
        self._stream = stream if stream is not None else sys.stdout
        self.tty = self._stream.isatty() if tty is None else tty
        super().__init__(
            "console",
            interval if interval is not None else (0.1 if self.tty else 1.0),
            wake_on_publish=False,  # paced by the clock, not by the frame rate
        )
        self._status = status
        self._width = 0

    def emit(self, sample: CompassSample | None) -> None:
        """Write the line for the latest sample."""
        line = format_line(sample, self._status())
        if self.tty:
            pad = max(0, self._width - len(line))
            self._width = len(line)
            self._stream.write("\r" + line + " " * pad)
        else:
            self._stream.write(line + "\n")
        self._stream.flush()

    def finish(self) -> None:
        """End the in-place line so the shell prompt starts on a fresh one."""
        if self.tty and self._width:
            self._stream.write("\n")
            self._stream.flush()


# ---------------------------------------------------------------------------
# The daemon
# ---------------------------------------------------------------------------


def load_calibration(directory: str) -> tuple[Calibration, str]:
    """The stored calibration, or identity; never raises (a bad file is logged and ignored).

    Returns ``(calibration, source)`` where source is ``"stored"``,
    ``"stored (previous copy)"`` or ``"none (identity)"``.
    """
    try:
        result = StateStore(directory).load(CALIBRATION_DOCUMENT)
    except Exception as e:  # an unreadable directory must not stop the bridge
        log.warning("calibration: cannot read %s (%s); using identity", directory, e)
        return Calibration(), "none (identity)"
    for problem in result.problems:
        log.warning("calibration: %s", problem)
    if result.payload is None:
        log.info(
            "calibration: none stored in %s; using identity (nominal transfer only)", directory
        )
        return Calibration(), "none (identity)"
    payload: Any = result.payload
    # Accept the bare Calibration.to_dict() or a document that wraps it with a report.
    if isinstance(payload, dict) and isinstance(payload.get("calibration"), dict):
        payload = payload["calibration"]
    try:
        cal = Calibration.from_dict(payload)
    except (KeyError, TypeError, ValueError) as e:
        log.warning("calibration: stored document is unusable (%s); using identity", e)
        return Calibration(), "none (identity)"
    source = "stored" if result.source == "current" else "stored (previous copy)"
    log.info("calibration: loaded from %s (%s)", directory, source)
    return cal, source


def field_reference(cfg: Config) -> FieldReference | None:
    """Declination and expected field from the WMM at ``[location]``, if set."""
    loc = cfg.location
    if loc is None:
        return None
    # Computed once at start: the field drifts ~0.1 deg/year, far below compass error.
    ref = field_reference_at(loc.latitude, loc.longitude, loc.altitude_m)
    log.info(
        "location %.4f, %.4f, %.0f m: declination %+.2f deg, field %.0f nT, dip %+.1f deg (WMM)",
        loc.latitude,
        loc.longitude,
        loc.altitude_m,
        ref.declination_deg,
        (ref.total_G or 0.0) * 1e5,
        ref.dip_deg,
    )
    return ref


def make_transport(cfg: Config) -> Transport:
    """The transport ``cfg.device`` names; ``"sim"`` is built from ``[sim]`` and ``[location]``."""
    if cfg.device.port != "sim":
        return open_transport(cfg.device.port, cfg.device.baud, realtime=cfg.device.replay_realtime)
    from bridge.sim.pty import MOTIONS  # only the simulated port needs the simulator

    sim = cfg.sim
    loc = cfg.location
    return open_transport(
        "sim",
        cfg.device.baud,
        seed=sim.seed,
        motion=MOTIONS[sim.motion](sim.seed),
        ideal=sim.ideal,
        flash_path=sim.flash_file or None,
        # The simulated unit sits where the configuration says the vehicle is, so
        # the expected field (WMM) and the simulated one agree.
        location=(loc.latitude, loc.longitude, loc.altitude_m) if loc is not None else None,
    )


def _fold(a: float) -> float:
    a = math.fmod(a, 360.0)
    return a + 360.0 if a < 0.0 else (0.0 if a >= 360.0 else a)


class Daemon:
    """The running bridge: link -> pipeline -> outputs.

    ``transport`` defaults to :func:`open_transport` on ``cfg.device``;
    ``calibration`` defaults to the stored one (see :func:`load_calibration`).
    """

    #: Heading published until a configuration key chooses (a later issue): magnetic,
    #: as the device and ArduPilot's compass report it; true is given alongside.
    HEADING_REFERENCE: HeadingReference = "magnetic"

    def __init__(
        self,
        cfg: Config,
        outputs: Sequence[Output] = (),
        *,
        transport: Transport | None = None,
        calibration: Calibration | None = None,
    ) -> None:
        self.cfg = cfg
        self.outputs = list(outputs)
        if calibration is None:
            calibration, self.calibration_source = load_calibration(cfg.storage.dir)
        else:
            self.calibration_source = "given"
        self.reference = field_reference(cfg)
        self.engine = AttitudeEngine(
            calibration, reference=self.reference, heading_reference=self.HEADING_REFERENCE
        )
        if transport is None:
            transport = make_transport(cfg)
        self.link = CompassLink(
            transport,
            protocol=cfg.device.protocol,  # type: ignore[arg-type]  # validated by config
            rate_hz=cfg.device.rate_hz if cfg.device.protocol == "gmr" else None,
            stale_after=cfg.device.stale_after,
            on_state=self._on_link_state,
            # The pipeline runs in the link's reader thread: no queue, no second thread to
            # wake for every frame (a thread hand-off costs more CPU at 100 Hz than the
            # whole attitude solution). Everything it calls is non-blocking by contract.
            queue_size=0,
            on_frame=self._on_frame,
        )
        #: Operator-visible events (calibration, ...) for every front end.
        self.events = EventBus()
        loc = cfg.location
        #: The calibration state machine every front end drives (fed by the pipeline).
        self.calibrator = CalibrationController(
            self.engine,
            self.events,
            link=self.link,
            store=StateStore(cfg.storage.dir),
            field=earth_field(loc.latitude, loc.longitude, loc.altitude_m) if loc else None,
            onboard=cfg.calibration.onboard,
            settings=CalibratorSettings(timeout_s=cfg.calibration.timeout_s),
            calibration_source=self.calibration_source,
        )
        self.samples = 0
        self.pipeline_errors = 0
        self._frame_started_at: float | None = None  # set while a frame is in the pipeline
        self._disturbed = False  # disturbance state last reported as an event (pipeline)
        self._disturbed_at = -math.inf  # when it was reported
        self._disturbed_seen_while_calibrating = False  # muted disturbance (diagnostics, tests)
        self._link_lost = False  # link.lost emitted, link.restored not yet (reader thread)

    # -- lifecycle ---------------------------------------------------------------

    def start(self) -> Daemon:
        """Start outputs, the calibrator and the link (whose reader runs the pipeline)."""
        for out in self.outputs:
            out.start()
        self.calibrator.start()
        self.link.start()
        log.info(
            "bridge started: %s (%s), calibration %s, outputs %s",
            self.link.name,
            self.cfg.device.protocol,
            self.calibration_source,
            ", ".join(o.name for o in self.outputs) or "none",
        )
        return self

    def stop(self, timeout: float = 3.0) -> None:
        """Stop everything within about ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        # Before the link: a device calibration still running is aborted over it.
        self.calibrator.close(timeout=max(0.1, 0.25 * timeout))
        # Joins the reader, and so the pipeline: no frame reaches an output after this.
        self.link.close(timeout=max(0.1, 0.5 * timeout))
        for out in self.outputs:
            out.close(max(0.1, deadline - time.monotonic()))

    @property
    def ended(self) -> bool:
        """A replayed recording has been played to its end."""
        return self.link.ended

    def status(self) -> DaemonStatus:
        """A snapshot of link state and counters."""
        return DaemonStatus(
            port=self.link.name,
            state=self.link.state,
            counters=self.link.counters,
            samples=self.samples,
            pipeline_errors=self.pipeline_errors,
            # After an accept the calibrator knows better than the start-up value.
            calibration_source=self.calibrator.snapshot().calibration_source
            or self.calibration_source,
        )

    # -- the per-frame path --------------------------------------------------------

    @property
    def pipeline_alive_at(self) -> float:
        """Monotonic time up to which the pipeline is known not to be stuck (the watchdog's).

        Now while it waits for a frame; the time the current frame went in while
        one is being processed, so a frame that never comes out stops the clock.
        """
        started = self._frame_started_at
        return time.monotonic() if started is None else started

    def _on_frame(self, item: Received) -> None:
        """The per-frame path, run in the link's reader thread for every frame."""
        self._frame_started_at = item.t  # when the reader got it: the same monotonic clock
        try:
            sample = self.process(item)
            if sample is not None:
                self.samples += 1
                for out in self.outputs:
                    try:
                        out.publish(sample)
                    except Exception:
                        self.pipeline_errors += 1
                        log.exception("output %s: publish raised", out.name)
        except Exception:
            # A bad frame must not stop the bridge: count it, say so once.
            self.pipeline_errors += 1
            if self.pipeline_errors == 1:
                log.exception("pipeline: frame %r failed (further failures counted)", item)
        finally:
            self._frame_started_at = None

    def process(self, item: Received) -> CompassSample | None:
        """One received frame to a sample (None for frames that carry no heading)."""
        frame = item.frame
        self.calibrator.feed(frame)  # never raises; cheap when no calibration runs
        if isinstance(frame, AttitudeFrame):
            return self._from_gmr(frame, item.t)
        if isinstance(frame, HeadingFrame):
            return self._from_heading(frame, item.t)
        return None  # $PGMRV/P/K/C: handled by the link

    def _on_link_state(self, old: LinkState, new: LinkState) -> None:
        """Link lost / restored as operator events (called in the link's reader thread)."""
        down = (LinkState.STALE, LinkState.ABSENT)
        if old is LinkState.STREAMING and new in down:
            self._link_lost = True
            why = "stale" if new is LinkState.STALE else "port gone"
            self.events.emit(
                Event(
                    "link.lost", f"Compass link lost ({why})", Severity.ERROR, {"state": new.value}
                )
            )
        elif new is LinkState.STREAMING and self._link_lost:  # via OPENING after a reopen
            self._link_lost = False
            self.events.emit(Event("link.restored", "Compass link restored", Severity.NOTICE))

    def _disturbance_changed(self, disturbed: bool, a: AttitudeSolution, t: float) -> None:
        """Disturbance start / end as operator events (pipeline, on transitions only).

        At most one event per :data:`DISTURBANCE_EVENT_MIN_S`: a badly calibrated unit
        turning near the threshold would flap; a change inside the hold-off is reported
        when it ends, if it still holds then.
        """
        if t - self._disturbed_at < DISTURBANCE_EVENT_MIN_S:
            return
        if self.calibrator.calibrating:
            # An uncalibrated unit tumbling for its calibration is "disturbed" half the
            # time: that is expected, not news. The state is re-judged once it ends.
            self._disturbed_seen_while_calibrating |= disturbed
            return
        self._disturbed, self._disturbed_at = disturbed, t
        data = {"field_mG": round(1000.0 * a.field_strength_G, 1), "dip_deg": round(a.dip_deg, 1)}
        if disturbed:
            text, sev = "Magnetic disturbance: heading unreliable", Severity.WARNING
        else:
            text, sev = "Magnetic disturbance cleared", Severity.NOTICE
        kind = "disturbance.start" if disturbed else "disturbance.end"
        self.events.emit(Event(kind, text, sev, data))

    def _from_gmr(self, f: AttitudeFrame, t: float) -> CompassSample:
        a = self.engine.solve_counts(f.mx, f.my, f.mz, f.ax, f.ay, f.az)
        if a.disturbed is not self._disturbed:
            self._disturbance_changed(a.disturbed, a, t)
        return CompassSample(
            t=t,
            source="host",
            heading_deg=a.heading_deg,
            heading_reference=a.heading_reference,
            heading_magnetic_deg=a.heading_magnetic_deg,
            heading_true_deg=a.heading_true_deg,
            declination_deg=a.declination_deg,
            pitch_deg=math.degrees(a.pitch),
            roll_deg=math.degrees(a.roll),
            seq=f.seq,
            device_heading_deg=f.heading,
            # int & int: Flags' own "&" is Python code in the enum module (per frame).
            saturated=(int(f.flags) & _SAT) != 0,
            attitude=a,
            raw_counts=(f.mx, f.my, f.mz, f.ax, f.ay, f.az),
        )

    def _from_heading(self, f: HeadingFrame, t: float) -> CompassSample | None:
        if f.heading_deg is None:
            return None  # $PTNTHPR in alarm: the device itself has no heading
        # Declination: the WMM at [location] when set, else the sentence's own
        # variation (HDG); a heading-only compass is never re-calibrated here.
        decl = self.reference.declination_deg if self.reference is not None else None
        if decl is None:
            decl = f.variation_deg
        mag: float | None
        true: float | None
        if f.reference == "magnetic":
            mag = f.heading_deg
            true = _fold(f.heading_deg + decl) if decl is not None else None
        else:
            true = f.heading_deg
            mag = _fold(f.heading_deg - decl) if decl is not None else None
        # Publish the configured reference when it is known, else the one the sentence gave.
        ref: HeadingReference = "magnetic"
        published = mag
        if (self.HEADING_REFERENCE == "true" and true is not None) or mag is None:
            ref, published = "true", true
        assert published is not None  # one of the two is the sentence's own heading
        return CompassSample(
            t=t,
            source="device",
            heading_deg=published,
            heading_reference=ref,
            heading_magnetic_deg=mag,
            heading_true_deg=true,
            declination_deg=decl,
            pitch_deg=f.pitch_deg,
            roll_deg=f.roll_deg,
        )


def build_outputs(
    cfg: Config,
    status: Callable[[], DaemonStatus],
    *,
    console: bool,
    daemon: Daemon | None = None,
) -> list[Output]:
    """The outputs the configuration asks for (MAVLink and Zenoh plug in here).

    ``daemon`` gives outputs the bridge's services (events, calibrator); the
    Zenoh output needs it and is left out without one.
    """
    outputs: list[Output] = []
    if console:
        outputs.append(ConsoleOutput(status))
    # MAVLink first: the pipeline calls publish() in this order, and the autopilot's
    # ATTITUDE is the latency-critical output (zenoh puts its documents in publish too).
    if cfg.mavlink.endpoints and daemon is not None:
        # Imported here: bridge.mavlink builds on this module.
        from bridge.mavlink import MavlinkOutput, MavlinkSettings

        services = daemon  # the output resolves the daemon's services when it starts
        outputs.append(MavlinkOutput(MavlinkSettings.from_config(cfg), lambda: services))
    if cfg.zenoh.enabled and daemon is not None:
        # Imported here: zenoh (a native runtime) loads only when it is asked for.
        from bridge.fleet.output import ZenohOutput
        from bridge.fleet.services import daemon_services
        from bridge.fleet.session import ZenohSettings

        outputs.append(
            ZenohOutput(ZenohSettings.from_config(cfg.zenoh), daemon_services(lambda: daemon))
        )
    return outputs


def run_daemon(
    cfg: Config,
    stop: threading.Event,
    *,
    console: bool = False,
    reload_config: Callable[[], Config] | None = None,
) -> int:
    """Run until ``stop`` is set (SIGINT/SIGTERM) or a replay ends; returns the exit code.

    The service side -- sd_notify READY/STATUS/WATCHDOG/STOPPING, SIGHUP reload
    through ``reload_config`` -- is :class:`bridge.service.Service`.
    """
    from bridge.service import Service  # it builds on this module

    def make_outputs(c: Config, daemon: Daemon) -> list[Output]:
        # Called at start and again on reload for an output whose section changed.
        return build_outputs(c, daemon.status, console=console, daemon=daemon)

    return Service(cfg, make_outputs, reload_config=reload_config).run(stop)
