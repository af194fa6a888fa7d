"""The in-memory harness: the link machine and a device on one manual clock.

No threads, no sleeps, no port. :class:`LinkHarness` pairs
:class:`bridge.protocol.link.LinkMachine` with a sans-I/O device -- the
simulated firmware (:mod:`bridge.sim.firmware`) or :class:`ScriptedCompass`,
a device whose answers each test scripts -- and moves simulated time from
one event to the next (a frame, an answer, a link deadline), doing what the
real driver (:class:`bridge.link.serial_link.CompassLink`) does on a port:
opening it when due, carrying the machine's writes to the device and the
device's bytes to the machine, closing it on ``ClosePort``. A "port" can be
unplugged and plugged back.

* :class:`ManualClock` -- the one clock (seconds, starts at 1000.0).
* :meth:`LinkHarness.run_until` -- the one wait: simulated time runs until a
  predicate holds (or a simulated time limit passes); :meth:`LinkHarness.run_for`
  lets a given simulated time pass.
* :class:`Collector` -- the one collector: every frame and state change the link
  hands on.
"""

from __future__ import annotations

import heapq
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from bridge.protocol.device import (
    CommandError,
    LinkCounters,
    LinkDown,
    LinkState,
    Received,
)
from bridge.protocol.gmr import (
    AckFrame,
    AttitudeFrame,
    CommandFrame,
    Flags,
    GmrDecoder,
    GmrFrame,
    ParamsFrame,
    VersionFrame,
    encode,
)
from bridge.protocol.link import (
    ClosePort,
    Command,
    LinkMachine,
    LinkProtocol,
    Notice,
    StateChanged,
    Write,
)

if TYPE_CHECKING:  # bridge_on imports them when it runs: the link tests need none of it
    from bridge.app.bridge import Bridge
    from bridge.config import Config

log = logging.getLogger("harness")

#: Where every manual clock starts (any origin works; not 0, so "time 0" bugs show).
T0 = 1000.0


class ManualClock:
    """A clock that moves only when told (callable like ``time.monotonic``)."""

    def __init__(self, t: float = T0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t

    @classmethod
    def of(cls, clock: object) -> ManualClock:
        """``clock`` (e.g. an output's): the manual clock the test built it on."""
        assert isinstance(clock, cls), clock
        return clock

    def advance(self, dt: float) -> None:
        """Move ``dt`` seconds on."""
        if dt < 0:
            raise ValueError("time does not go back")
        self.t += dt


class Device(Protocol):
    """A sans-I/O compass (what :class:`bridge.sim.firmware.Firmware` is)."""

    def receive(self, data: bytes, now: float) -> None: ...

    def poll(self, now: float) -> bytes: ...

    def next_event_at(self) -> float | None: ...


@dataclass
class Collector:
    """Everything the link hands on: frames (``items``) and state changes (``states``)."""

    items: list[Received] = field(default_factory=list)
    states: list[tuple[LinkState, LinkState]] = field(default_factory=list)

    def on_frame(self, item: Received) -> None:
        self.items.append(item)

    def on_state(self, old: LinkState, new: LinkState) -> None:
        self.states.append((old, new))

    def seqs(self) -> list[int]:
        """The ``seq`` of every attitude frame, in order."""
        return [i.frame.seq for i in self.items if isinstance(i.frame, AttitudeFrame)]

    def new_states(self) -> list[LinkState]:
        """The states the link went to, in order."""
        return [new for _, new in self.states]


# ---------------------------------------------------------------------------- a scripted device

VERSION = VersionFrame("2.1.0", "B3", "GMR-000417")
PARAMS = ParamsFrame(2460.5, 2455.0, 2470.0, 1.0, 1.0213, 0.9876, 2458.0, 2458.0, 2949.5)

Reply = list[tuple[float, bytes]]  # (delay after the command arrived, bytes to send)
Handler = Callable[[CommandFrame, int], Reply | None]  # (command, how many times seen) -> reply


def attitude_line(seq: int) -> bytes:
    """A valid ``$PGMRA`` line carrying ``seq``."""
    return encode(AttitudeFrame(seq, 87.3, -1.2, 0.4, 3101, 2470, 3311, 2470, 2452, 2950, Flags(6)))


def default_reply(cmd: CommandFrame) -> Reply:
    """What :class:`ScriptedCompass` answers when no handler is set for a command."""
    if cmd.command == "VER":
        return [(0.0, encode(VERSION))]
    if cmd.command == "RATE":
        return [(0.0, encode(AckFrame.rate_ok(int(cmd.args[0]))))]
    if cmd.key == "PAR,GET":
        return [(0.0, encode(PARAMS))]
    return [(0.0, encode(AckFrame.failure(cmd.command, "UNKNOWN")))]


class ScriptedCompass:
    """A GMR device whose stream and answers the test scripts (sans-I/O, like the firmware).

    It streams ``$PGMRA`` at ``rate_hz`` from ``seq`` 0 while :attr:`streaming`,
    answers each command with ``handlers[key](cmd, n)`` (n: how many times that
    key was seen) or :func:`default_reply`, loses the seqs in :attr:`lose`, and
    sends whatever :meth:`send` schedules.
    """

    def __init__(self, rate_hz: float = 50.0) -> None:
        self.period = 1.0 / rate_hz
        self.streaming = True
        self.seq = 0
        self.handlers: dict[str, Handler] = {}
        self.commands: list[tuple[float, CommandFrame]] = []
        self.sent_seqs: list[int] = []
        self.lose: set[int] = set()  #: seqs never sent (lost on the line)
        self._seen: dict[str, int] = {}
        self._decoder = GmrDecoder(direction="device")
        self._sched: list[tuple[float, int, bytes]] = []
        self._n = 0
        self._now = -float("inf")
        self._next_frame: float | None = None
        self._reboot_at: float | None = None
        self._out = bytearray()

    # -- scripting
    def send(self, data: bytes, delay: float = 0.0) -> None:
        """``data`` goes out ``delay`` s from now."""
        self._n += 1
        heapq.heappush(self._sched, (self._now + delay, self._n, data))

    def set_seq(self, seq: int) -> None:
        """The next frame carries ``seq`` (frames in between are "lost")."""
        self.seq = seq % 65536

    def skip(self, n: int) -> None:
        """Lose the next ``n`` frames."""
        self.seq = (self.seq + n) % 65536

    def reboot(self, silence: float = 0.3) -> None:
        """RESET as the datasheet has it: silence, then $PGMRV and frames from seq 0."""
        self._reboot_at = self._now + silence

    def received(self, key: str | None = None) -> list[CommandFrame]:
        """The commands that arrived (those with ``key``)."""
        return [c for _, c in self.commands if key is None or c.key == key]

    # -- the device
    def receive(self, data: bytes, now: float) -> None:
        self._advance(now)
        for cmd in self._decoder.feed(data):
            if not isinstance(cmd, CommandFrame):
                continue
            self.commands.append((now, cmd))
            n = self._seen[cmd.key] = self._seen.get(cmd.key, 0) + 1
            handler = self.handlers.get(cmd.key)
            reply = handler(cmd, n) if handler is not None else default_reply(cmd)
            for delay, line in reply or []:
                self.send(line, delay)

    def poll(self, now: float) -> bytes:
        self._advance(now)
        out = bytes(self._out)
        self._out.clear()
        return out

    def next_event_at(self) -> float | None:
        due = [] if self._reboot_at is None else [self._reboot_at]
        if self._sched:
            due.append(self._sched[0][0])
        frame = self._frame_due(self._now)
        if frame is not None:
            due.append(frame)
        return min(due) if due else None

    def _frame_due(self, now: float) -> float | None:
        if not self.streaming or self._reboot_at is not None or now == -float("inf"):
            self._next_frame = None
            return None
        if self._next_frame is None:  # (re)starting: the first frame at once
            self._next_frame = now
        return self._next_frame

    def _advance(self, now: float) -> None:
        """Send everything due up to ``now``, in time order."""
        if self._now == -float("inf"):
            self._now = now  # powered up by the first look at it
        while True:
            due: list[tuple[float, int]] = []
            if self._reboot_at is not None:
                due.append((self._reboot_at, 0))
            frame = self._frame_due(self._now)
            if frame is not None:
                due.append((frame, 1))
            if self._sched:
                due.append((self._sched[0][0], 2))
            if not due:
                break
            t, kind = min(due)
            if t > now:
                break
            self._now = max(self._now, t)
            if kind == 0:
                self._reboot_at = None
                self._out += encode(VERSION)
                self.seq = 0
                self._next_frame = t
            elif kind == 1:
                if self.seq in self.lose:
                    self.seq = (self.seq + 1) % 65536
                self.sent_seqs.append(self.seq)
                self._out += attitude_line(self.seq)
                self.seq = (self.seq + 1) % 65536
                self._next_frame = t + self.period
            else:
                self._out += heapq.heappop(self._sched)[2]
        self._now = max(self._now, now)


class LinePlayer:
    """A device that plays ``lines`` one every ``period`` s, round and round (sans-I/O).

    What the host writes is kept in :attr:`host_bytes`; :meth:`inject` sends
    extra bytes once, before the next line.
    """

    def __init__(self, lines: list[bytes], period: float = 0.02) -> None:
        self.lines = list(lines)
        self.period = period
        self.host_bytes = bytearray()
        self.sent = 0
        self.silent = False  #: True: the device sends nothing (its lines are not sent later)
        self._extra: list[bytes] = []
        self._next: float | None = None
        self._out = bytearray()

    def inject(self, data: bytes) -> None:
        self._extra.append(data)

    def receive(self, data: bytes, now: float) -> None:
        self.host_bytes += data

    def poll(self, now: float) -> bytes:
        if self._next is None:
            self._next = now
        while self._next <= now:
            if self.silent:
                self._next += self.period
                continue
            if self._extra:
                self._out += self._extra.pop(0)
            self._out += self.lines[self.sent % len(self.lines)]
            self.sent += 1
            self._next += self.period
        out = bytes(self._out)
        self._out.clear()
        return out

    def next_event_at(self) -> float | None:
        return self._next


# ---------------------------------------------------------------------------- the harness


class LinkHarness:
    """The link machine and ``device`` on one :class:`ManualClock` (see the module docstring).

    ``machine`` options (``protocol``, ``rate_hz``, ``stale_after``, ...) are
    passed through; ``baud`` is the line's (it lengthens the commands' default
    deadlines as on a real port). ``on_frame`` gets every frame after the
    :attr:`collector` (a pipeline, say).
    """

    #: Steps at one instant before the harness calls it a livelock.
    MAX_STEPS_AT_ONE_TIME = 10_000

    def __init__(
        self,
        device: Device,
        *,
        clock: ManualClock | None = None,
        baud: int | None = 115200,
        interactive: bool = True,
        on_frame: Callable[[Received], None] | None = None,
        start: bool = True,
        **machine: Any,
    ) -> None:
        self.device = device
        self.clock = clock if clock is not None else ManualClock()
        self.baud = baud
        self.interactive = interactive
        machine.setdefault("name", "harness")
        self.machine = LinkMachine(**machine)
        self.collector = Collector()
        self.on_frame = on_frame
        self.on_state: Callable[[LinkState, LinkState], None] | None = None
        self.plugged = True
        self.open_count = 0
        self.notices: list[Notice] = []
        self.reasons: list[str] = []  #: why each state change happened, in order
        self._attached_before = False
        self._timers: list[tuple[float, int, Callable[[], None]]] = []
        self._n = 0
        if start:
            self.start()

    # -- what the link knows
    @property
    def state(self) -> LinkState:
        return self.machine.state

    @property
    def counters(self) -> LinkCounters:
        return self.machine.counters

    @property
    def now(self) -> float:
        return self.clock.t

    def start(self) -> None:
        """Start the link (the port is opened at once)."""
        self.machine.start(self.clock.t)
        self._settle()

    # -- the world
    def at(self, delay: float, action: Callable[[], None]) -> None:
        """Run ``action`` ``delay`` simulated seconds from now (a scripted fault)."""
        self._n += 1
        heapq.heappush(self._timers, (self.clock.t + delay, self._n, action))

    def every(self, period: float, action: Callable[[], None]) -> None:
        """Run ``action`` every ``period`` simulated seconds from now on (a worker's tick).

        Not re-entered: an action that runs the harness itself (a blocking device command)
        skips the ticks that fall inside it.
        """
        busy = False

        def tick() -> None:
            nonlocal busy
            self.at(period, tick)
            if busy:
                return
            busy = True
            try:
                action()
            finally:
                busy = False

        self.at(period, tick)

    def clear_timers(self) -> None:
        """Forget every scripted action still to come (:meth:`at`, :meth:`every`)."""
        self._timers.clear()

    def unplug(self) -> None:
        """The adapter vanishes: the open port fails, opens fail until :meth:`replug`."""
        self.plugged = False
        if self.machine.is_open:
            self.machine.lost(self.clock.t, "read failed: [Errno 5] Input/output error")
        self._settle()

    def end(self, why: str = "end of recording") -> None:
        """The port ends for good (a replay played to its end)."""
        self.machine.end(self.clock.t, why)
        self._settle()

    def replug(self) -> None:
        """The adapter is back (the link opens it at its next try)."""
        self.plugged = True

    # -- time
    def step(self, limit: float) -> bool:
        """Move to the next event (no later than ``limit``) and handle it; False at ``limit``."""
        due = [limit]
        for t in (self.machine.next_deadline(), self.device.next_event_at()):
            if t is not None:
                due.append(t)
        if self._timers:
            due.append(self._timers[0][0])
        t = max(min(due), self.clock.t)
        self.clock.t = t
        while self._timers and self._timers[0][0] <= t:
            heapq.heappop(self._timers)[2]()
        self._settle()
        return t < limit

    def run_until(self, pred: Callable[[], bool], within: float = 30.0) -> bool:
        """Run simulated time until ``pred()`` holds or ``within`` simulated s pass.

        The one wait: True if it holds (checked after every event).
        """
        limit = self.clock.t + within
        same, last = 0, self.clock.t
        while not pred():
            if not self.step(limit):
                return pred()
            same = same + 1 if self.clock.t == last else 0
            last = self.clock.t
            if same > self.MAX_STEPS_AT_ONE_TIME:
                raise RuntimeError(f"the harness livelocks at t={self.clock.t}")
        return True

    def run_for(self, seconds: float) -> None:
        """Let ``seconds`` of simulated time pass."""
        self.run_until(lambda: False, seconds)

    # -- commands
    def submit(
        self, name: str, *args: object, timeout: float | None = None, retries: int = 2
    ) -> Command:
        """Queue a command (returns at once; see :meth:`command`)."""
        cmd = CommandFrame(name, tuple(str(a) for a in args))
        per_try = timeout if timeout is not None else self.machine.default_timeout(cmd, self.baud)
        command = self.machine.submit(cmd, self.clock.t, per_try, retries)
        self._settle()
        return command

    def command(
        self, name: str, *args: object, timeout: float | None = None, retries: int = 2
    ) -> GmrFrame:
        """One command transaction, run to its end in simulated time: its answer (or error)."""
        command = self.submit(name, *args, timeout=timeout, retries=retries)
        if not self.run_until(lambda: command.done, 60.0):
            raise AssertionError(f"{command} did not end in 60 simulated s")
        return command.result()

    # -- the driver's part
    def _settle(self) -> None:
        """Do what the machine asks at this instant until it asks nothing more."""
        m, t = self.machine, self.clock.t
        for _ in range(self.MAX_STEPS_AT_ONE_TIME):
            if m.open_due(t):
                self._open(t)
            m.tick(t)
            data = self.device.poll(t)
            if data and m.is_open:
                for item in m.receive(data, t):
                    self.collector.on_frame(item)
                    if self.on_frame is not None:
                        self.on_frame(item)
            if not m.has_events:
                return
            for ev in m.take_events():
                if type(ev) is Write:
                    if m.is_open and self.plugged:
                        self.device.receive(ev.data, t)
                    else:
                        m.write_failed(ev, "port not open", t)
                elif type(ev) is StateChanged:
                    self.collector.on_state(ev.old, ev.new)
                    self.reasons.append(ev.reason)
                    if self.on_state is not None:
                        self.on_state(ev.old, ev.new)
                elif type(ev) is Notice:
                    self.notices.append(ev)
                    log.log(ev.level, "%s", ev.message)
                else:
                    assert type(ev) is ClosePort
        raise RuntimeError(f"the link machine livelocks at t={t}")

    def _open(self, t: float) -> None:
        if not self.plugged:
            self.machine.open_failed(t, f"cannot open {self.machine.name}: no such file")
            return
        if self._attached_before:
            self.device.poll(t)  # what it sent while the port was closed is lost, as on a line
        # else: the first poll powers the device up, and its $PGMRV is for the link to see.
        self._attached_before = True
        self.open_count += 1
        self.machine.opened(t, interactive=self.interactive, baud=self.baud)


class HarnessPort:
    """The harness as a :class:`bridge.protocol.device.DevicePort` (what the application uses).

    :meth:`command` runs the transaction to its end in simulated time (the
    caller's thread steps the harness), so an application that commands the
    compass works on the harness unchanged.
    """

    def __init__(self, harness: LinkHarness) -> None:
        self.h = harness

    @property
    def name(self) -> str:
        return self.h.machine.name

    @property
    def protocol(self) -> str:
        return self.h.machine.protocol

    @property
    def state(self) -> LinkState:
        return self.h.machine.state

    @property
    def counters(self) -> LinkCounters:
        return self.h.machine.counters

    @property
    def version(self) -> VersionFrame | None:
        return self.h.machine.version

    @property
    def params(self) -> ParamsFrame | None:
        return self.h.machine.params

    def command(
        self, name: str, *args: object, timeout: float | None = None, retries: int = 2
    ) -> Any:
        if not self.h.machine.is_open:
            raise LinkDown(f"{self.name} is not open")
        return self.h.command(name, *args, timeout=timeout, retries=retries)

    def close(self) -> None:
        """The link closes (the compass goes silent for the application)."""
        self.h.machine.close(self.h.clock.t)
        self.h._settle()


def bridge_on(harness: LinkHarness, cfg: Config, **kw: Any) -> Bridge:
    """The application (:class:`bridge.app.bridge.Bridge`) built from ``cfg`` with the
    harness as its compass (:class:`HarnessPort`) and the harness's clock: every frame goes
    through its pipeline as the link hands it on. ``kw`` goes to Bridge (``calibration``,
    ``calibrator_settings``, ...). Start the harness afterwards (``start=False``)."""
    from bridge.app.bridge import BridgeOptions, build_bridge
    from bridge.storage import StateStore

    kw.setdefault("documents", StateStore(cfg.storage.dir))
    app = build_bridge(BridgeOptions.from_config(cfg), clock=harness.clock, **kw)
    harness.on_frame, harness.on_state = app.pipeline.on_frame, app.on_link_state
    app.connect(HarnessPort(harness))
    return app


__all__ = [
    "PARAMS",
    "T0",
    "VERSION",
    "Collector",
    "CommandError",
    "Device",
    "HarnessPort",
    "LinePlayer",
    "LinkHarness",
    "LinkProtocol",
    "LinkState",
    "ManualClock",
    "ScriptedCompass",
    "attitude_line",
    "bridge_on",
    "default_reply",
]
