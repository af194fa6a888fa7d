"""The run loop: the daemon under a service manager, with SIGHUP reload.

:class:`Service` is what ``compass-bridge run`` runs in its main thread. Around
the :class:`~bridge.daemon.wiring.Daemon` (built by
:func:`~bridge.daemon.wiring.build_daemon`) it adds:

* **sd_notify** (:mod:`bridge.systemd.notify`): ``READY=1`` once the compass streams
  (or after :data:`READY_TIMEOUT_S`, STATUS saying why not), ``STATUS=`` about
  once a second (link state, frame rate, heading, calibration state:
  :class:`bridge.systemd.status.StatusText`), ``STOPPING=1`` on SIGTERM/SIGINT,
  ``RELOADING=1`` ... ``READY=1`` on SIGHUP.
* **The watchdog**: ``WATCHDOG=1`` only while the serial reader (every return
  from a port call is a beat: :class:`bridge.link.observed.ObservedTransport`),
  the pipeline (silent while a frame is stuck in it) and this main loop all make
  progress; any of them silent for :data:`SILENCE_LIMIT_S` stops the pings and
  systemd restarts the service after ``WatchdogSec``.
* **Reload on SIGHUP**: the configuration is read again. Invalid: refused with
  a log line, the running configuration kept. Valid: only the parts whose
  settings changed restart (see :func:`plan_reload`):

  ============================  =================================================
  changed                       what happens
  ============================  =================================================
  ``[device]`` / ``[sim]``      the serial port is reopened with the new settings
                                (a new ``protocol`` restarts the whole bridge)
  ``[location]``                new WMM declination / expected field, in place
  ``[mavlink]``, ``[zenoh]``    that output restarts; the others keep running
  anything else                 the whole bridge restarts in-process
  ============================  =================================================
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import FrameType
from typing import Any

from bridge.app.bridge import location_field
from bridge.app.sample import CompassSample, DaemonStatus, Output
from bridge.app.services import magnetometer_calibrated
from bridge.config import Config
from bridge.console import TerminalGate
from bridge.daemon.wiring import (
    Daemon,
    build_daemon,
    build_outputs,
    make_simulator,
    make_transport,
)
from bridge.events import ChangeRefusedError
from bridge.protocol.device import LinkState
from bridge.systemd.notify import Liveness, Notifier, ServiceNotifier, watchdog_interval_s
from bridge.systemd.status import StatusText, calibration_words
from bridge.types import Clock

log = logging.getLogger(__name__)


#: A watched part silent this long is taken as hung. Above the link's longest pause between
#: two port calls (its reopen backoff, at most 2 s) with margin for a loaded board.
SILENCE_LIMIT_S = 4.0
#: READY=1 is sent after this long even without a streaming compass (STATUS says why).
READY_TIMEOUT_S = 10.0
#: How often the main loop looks at a stop or reload that no signal brought (run in another
#: thread) or the end of a replay. Otherwise it sleeps until a signal (SIGHUP, SIGINT,
#: SIGTERM) wakes it, or the next beat a service manager needs (:data:`MANAGED_BEAT_S`).
MAIN_TICK_S = 0.2
#: How often the main loop beats while a service manager watches (sd_notify's STATUS and
#: pings vouch for the main loop, the pipeline and the worker threads from these beats): a
#: part is silent after SILENCE_LIMIT_S, four of these, so a hang is seen as soon as before.
MANAGED_BEAT_S = SILENCE_LIMIT_S / 4

READER = "serial reader"
PIPELINE = "pipeline"
MAIN = "main loop"
WORKERS = "worker threads"  #: beats while no thread of the daemon has died of an exception

#: Config section -> name of the output it configures (restarted alone on reload).
OUTPUT_SECTIONS: Mapping[str, str] = {"mavlink": "mavlink", "zenoh": "zenoh"}
#: Sections whose change reopens the serial port (the link object keeps running).
LINK_SECTIONS = ("device", "sim")

MakeOutputs = Callable[[Config, Daemon], list[Output]]


# ---------------------------------------------------------------------------
# Reload planning (pure)
# ---------------------------------------------------------------------------


def changed_sections(old: Config, new: Config) -> list[str]:
    """Names of the sections whose values differ between ``old`` and ``new``."""
    return [
        f.name for f in dataclasses.fields(Config) if getattr(old, f.name) != getattr(new, f.name)
    ]


@dataclass(frozen=True, slots=True)
class ReloadPlan:
    """What a reload from one configuration to another has to do."""

    changed: tuple[str, ...]
    reopen_link: bool = False
    location: bool = False
    outputs: tuple[str, ...] = ()  #: output names to restart
    rebuild: tuple[str, ...] = ()  #: sections that force a restart of the whole bridge

    @property
    def unchanged(self) -> bool:
        """Nothing differs."""
        return not self.changed


def plan_reload(old: Config, new: Config) -> ReloadPlan:
    """Which parts restart when ``old`` becomes ``new`` (see the module docstring)."""
    changed = changed_sections(old, new)
    rebuild = [s for s in changed if s not in (*LINK_SECTIONS, "location", *OUTPUT_SECTIONS)]
    if old.device.protocol != new.device.protocol:
        # The link's decoder is chosen at construction: a new protocol is a new bridge.
        rebuild.insert(0, "device")
    reopen = any(s in changed for s in LINK_SECTIONS)
    if "location" in changed and new.device.port == "sim":
        reopen = True  # the simulated unit sits at [location]: it has to be rebuilt too
    return ReloadPlan(
        changed=tuple(changed),
        reopen_link=reopen,
        location="location" in changed,
        outputs=tuple(OUTPUT_SECTIONS[s] for s in changed if s in OUTPUT_SECTIONS),
        rebuild=tuple(rebuild),
    )


# ---------------------------------------------------------------------------
# The service
# ---------------------------------------------------------------------------


class SampleTap:
    """An output that only remembers the latest sample (for STATUS)."""

    name = "status"

    def __init__(self) -> None:
        self.latest: CompassSample | None = None

    def start(self) -> None:
        """Nothing to start."""

    #: It only keeps the latest: no frame needs reading the moment it arrives for it.
    due_at = math.inf

    def publish(self, sample: CompassSample) -> None:
        """Keep ``sample``."""
        self.latest = sample

    def close(self, timeout: float) -> None:
        """Nothing to stop."""


class Service:
    """The daemon plus its service-manager side (see the module docstring).

    ``make_outputs(cfg, daemon)`` builds the outputs for a configuration (called
    again on reload for outputs whose section changed). ``reload_config()``
    reads the configuration again (the same file and overrides as at start);
    None makes SIGHUP a no-op that says so.
    """

    def __init__(
        self,
        cfg: Config,
        make_outputs: MakeOutputs,
        *,
        reload_config: Callable[[], Config] | None = None,
        env: Mapping[str, str] | None = None,
        notifier: Notifier | None = None,
        clock: Clock = time.monotonic,
    ) -> None:
        self.env = os.environ if env is None else env
        self.cfg = cfg
        self._make_outputs = make_outputs
        self._reload_config = reload_config
        self._clock = clock
        self.liveness = Liveness()
        self.tap = SampleTap()
        self.status_text = StatusText()
        self.reload_requested = threading.Event()
        self._wake = threading.Event()  # set by the signal handlers: the main loop looks
        self._signals = False  # those handlers are installed (run in the main thread)
        self._dead: dict[str, int] = {}  # thread name -> deaths (see _on_thread_exception)
        self._dead_lock = threading.Lock()
        self.reloads = 0
        self.reloads_refused = 0
        self.notify = ServiceNotifier(
            notifier if notifier is not None else Notifier.from_env(self.env),
            self.liveness,
            status=self.status_line,
            streaming=self._streaming,
            watchdog_s=watchdog_interval_s(self.env),
            ready_timeout_s=READY_TIMEOUT_S,
            clock=clock,
        )
        self.daemon = self._build(cfg)

    # -- building ------------------------------------------------------------------

    def _reader_beat(self) -> None:
        """Every return from a port call in the reader thread is the reader's beat."""
        self.liveness.beat(READER, self._clock())

    def _build(self, cfg: Config) -> Daemon:
        simulator = make_simulator(cfg)
        transport = make_transport(cfg, simulator)
        daemon = build_daemon(
            cfg, transport=transport, simulator=simulator, on_read=self._reader_beat
        )
        daemon.bridge.pipeline.set_outputs([*self._make_outputs(cfg, daemon), self.tap])
        return daemon

    def _watch(self) -> None:
        now = self._clock()
        for name in (READER, PIPELINE, MAIN, WORKERS):
            self.liveness.watch(name, SILENCE_LIMIT_S, now)

    # -- status --------------------------------------------------------------------

    def _streaming(self) -> bool:
        return self.daemon.link.state is LinkState.STREAMING

    def calibration_state(self, status: DaemonStatus) -> str:
        """Calibration in words (:func:`~bridge.systemd.status.calibration_words`), with
        the parameters' save error ``status`` carries (the one read the line is made of)."""
        bridge = self.daemon.bridge
        try:
            snap = bridge.calibrator.snapshot()
        except Exception:  # the status line must never fail for this
            return status.calibration_source
        return calibration_words(
            snap,
            calibrated=magnetometer_calibrated(bridge.services),
            parameters_error=status.parameters_error,
        )

    def status_line(self) -> str:
        """The current STATUS text."""
        d = self.daemon
        now = self._clock()
        status = d.bridge.status()
        text = self.status_text.render(status, self.tap.latest, self.calibration_state(status), now)
        silent = self.liveness.silent(now)
        if silent:
            # The link state is kept by the reader: when that hangs, the state is stale too.
            hung = ", ".join(f"{name} silent {s:.0f} s" for name, s in silent)
            dead = self.dead_threads()
            if dead:
                hung += f"; thread {', '.join(dead)} died"
            text = f"NOT RESPONDING ({hung}; watchdog pings withheld); {text}"
        return text

    def dead_threads(self) -> list[str]:
        """Threads of the daemon that ended with an exception (names)."""
        with self._dead_lock:
            return sorted(self._dead)

    def _on_thread_exception(self, args: threading.ExceptHookArgs) -> None:
        """``threading.excepthook`` while the service runs: a worker thread died.

        No thread may die silently: the exception is logged once per thread, counted,
        and the watchdog's "worker threads" part stops beating, so the service manager
        restarts a bridge that may no longer answer commands (a MAVLink dispatcher that
        is gone still lets ATTITUDE flow: only this notices it).
        """
        if args.exc_type is SystemExit:
            return
        name = args.thread.name if args.thread is not None else "?"
        with self._dead_lock:
            first = name not in self._dead
            self._dead[name] = self._dead.get(name, 0) + 1
        if first:
            log.error(
                "thread %s died: %s: %s; the watchdog stops pinging",
                name,
                args.exc_type.__name__,
                args.exc_value,
                exc_info=args.exc_value,
            )

    # -- signals -------------------------------------------------------------------

    def _on_hup(self, signum: int, frame: FrameType | None) -> None:
        self.reload_requested.set()
        self._wake.set()

    def _waking(self, handler: Callable[[int, FrameType | None], Any]) -> Any:
        """``handler`` (the caller's SIGINT/SIGTERM handler, which sets ``stop``), then a
        wake-up of the main loop, asleep on its own event rather than on ``stop``."""

        def on_signal(signum: int, frame: FrameType | None) -> Any:
            try:
                return handler(signum, frame)
            finally:
                self._wake.set()

        return on_signal

    def _install_signals(self) -> dict[int, Any]:
        if threading.current_thread() is not threading.main_thread():
            return {}  # embedded in a test thread: the caller drives reloads
        old: dict[int, Any] = {signal.SIGHUP: signal.signal(signal.SIGHUP, self._on_hup)}
        for signum in (signal.SIGINT, signal.SIGTERM):
            handler = signal.getsignal(signum)
            # A Python handler (the CLI's sets ``stop``) is kept and wakes the loop too;
            # the default action ends the process, and an ignored signal does nothing.
            if callable(handler):
                old[signum] = signal.signal(signum, self._waking(handler))
        self._signals = True
        return old

    # -- running -------------------------------------------------------------------

    def _tick_s(self) -> float | None:
        """How long the main loop may sleep (None: until a signal wakes it).

        It ticks only when something needs it: a stop or reload request that no signal
        brings (run outside the main thread), a replay that may end, a service manager
        that is told (the STATUS and watchdog pings read the beats). Under no manager,
        at 100 Hz, five looks a second cost 0.07 % of a core for nothing.
        """
        if not self._signals or self.cfg.device.port.startswith("replay:"):
            return MAIN_TICK_S
        if self.notify.active:
            return MANAGED_BEAT_S
        return None

    def run(self, stop: threading.Event) -> int:
        """Run until ``stop`` is set or a replay ends; returns the exit code (0)."""
        old_handlers = self._install_signals()
        old_hook, threading.excepthook = threading.excepthook, self._on_thread_exception
        self._watch()
        self.daemon.start()
        self.notify.start()
        try:
            while not stop.is_set():
                self._wake.wait(self._tick_s())
                self._wake.clear()
                if stop.is_set():
                    break
                self._beat()
                if self.reload_requested.is_set():
                    self.reload_requested.clear()
                    self.reload()
                    self._beat()
                if self.daemon.link.ended:
                    log.info("replay finished")
                    stop.wait(0.5)  # let the pipeline drain the last frames
                    break
        finally:
            self.notify.stopping("stopping")
            try:
                self.daemon.stop()
                log.info("bridge stopped")
            finally:
                self.notify.close()
                for signum, handler in old_handlers.items():
                    signal.signal(signum, handler)
                self._signals = False
                threading.excepthook = old_hook
        return 0

    def _beat(self) -> None:
        now = self._clock()
        self.liveness.beat(MAIN, now)
        if not self._dead:
            self.liveness.beat(WORKERS, now)
        # The pipeline marks its own progress; a wedged pipeline stops moving this.
        self.liveness.beat(PIPELINE, self.daemon.bridge.pipeline.alive_at)

    # -- reload --------------------------------------------------------------------

    def reload(self) -> bool:
        """Re-read and apply the configuration; False if it was refused (old one kept)."""
        self.notify.reloading()
        note = "reload refused"
        ok = False
        try:
            if self._reload_config is None:
                log.warning("reload: no configuration file to re-read; nothing changed")
                note = "reload: nothing to re-read"
                return False
            try:
                new = self._reload_config()
            except Exception as e:  # ConfigError, an unreadable file, ...
                self.reloads_refused += 1
                log.error("reload refused, keeping the running configuration: %s", e)
                note = f"reload refused ({e})"
                return False
            try:
                note = self._apply(new)
            except Exception as e:
                self.reloads_refused += 1
                log.exception("reload refused, keeping the running configuration: %s", e)
                note = f"reload refused ({e})"
                return False
            self.reloads += 1
            ok = True
            return True
        finally:
            self.notify.reloaded(note)
            if not ok:
                log.info("still running with the previous configuration")

    def _apply(self, new: Config) -> str:
        plan = plan_reload(self.cfg, new)
        if plan.unchanged:
            log.info("reload: configuration unchanged")
            return "reloaded (unchanged)"
        if plan.rebuild:
            return self._rebuild(new, plan)
        d = self.daemon
        # Prepare everything that can fail first; only then touch the running parts.
        simulator = make_simulator(new) if plan.reopen_link else None
        transport = make_transport(new, simulator) if plan.reopen_link else None
        loc = new.location
        location = (loc.latitude, loc.longitude, loc.altitude_m) if loc is not None else None
        field = location_field(location) if plan.location else None
        fresh: list[Output] = self._make_outputs(new, d) if plan.outputs else []
        keep_new = [o for o in fresh if o.name in plan.outputs]
        for o in fresh:
            if o not in keep_new:
                o.close(0.1)  # built but never started
        if plan.location:
            try:
                d.bridge.settings.set_field(field, "reload")
            except ChangeRefusedError as e:
                log.warning("reload: [location] not applied: %s", e)
        if transport is not None:
            log.info("reload: reopening the compass port with the new settings")
            d.reopen(new.device, transport, simulator)
        if plan.outputs:
            self._swap_outputs(plan.outputs, keep_new, [o.name for o in fresh])
        self.cfg = new
        what = ", ".join(f"[{s}]" for s in plan.changed)
        log.info("reload: applied %s; other parts kept running", what)
        return f"reloaded {what}"

    def _swap_outputs(
        self, names: Sequence[str], fresh: Sequence[Output], order: Sequence[str]
    ) -> None:
        """Restart the outputs ``names``: the old ones closed, ``fresh`` started, each in
        its place of ``order`` (the names in :func:`~bridge.daemon.build_outputs`' order;
        the status tap and any other output not in it after them, as at the start)."""
        pipeline = self.daemon.bridge.pipeline
        old = [o for o in pipeline.outputs if o.name in names]
        kept = [o for o in pipeline.outputs if o.name not in names]
        for o in old:
            o.close(1.0)
        for o in fresh:
            o.start()
        # The pipeline publishes in this order: MAVLink's ATTITUDE, the latency-critical
        # output, must not come after Zenoh's documents because [mavlink] was reloaded.
        rank = {name: i for i, name in enumerate(order)}
        outputs = sorted([*kept, *fresh], key=lambda o: rank.get(o.name, len(rank)))
        # One reference store: the pipeline reads the list once per sample.
        pipeline.set_outputs(outputs)
        log.info("reload: restarted output(s) %s", ", ".join(names))

    def _rebuild(self, new: Config, plan: ReloadPlan) -> str:
        what = ", ".join(f"[{s}]" for s in plan.rebuild)
        log.warning("reload: %s changed: restarting the whole bridge", what)
        fresh = self._build(new)  # may raise: the running bridge is untouched then
        self.daemon.stop()
        self.daemon = fresh
        now = self._clock()
        self.liveness.watch(READER, SILENCE_LIMIT_S, now)
        self.liveness.watch(PIPELINE, SILENCE_LIMIT_S, now)
        fresh.start()
        self.cfg = new
        return f"reloaded (restarted: {what} changed)"


def run_daemon(
    cfg: Config,
    stop: threading.Event,
    *,
    console: bool = False,
    reload_config: Callable[[], Config] | None = None,
    gate: TerminalGate | None = None,
) -> int:
    """Run until ``stop`` is set (SIGINT/SIGTERM) or a replay ends; returns the exit code.

    ``gate``: the log stream on the console's terminal, held while in the background.
    """

    def make_outputs(c: Config, daemon: Daemon) -> list[Output]:
        # Called at start and again on reload for an output whose section changed.
        return build_outputs(c, daemon, console=console, gate=gate)

    return Service(cfg, make_outputs, reload_config=reload_config).run(stop)
