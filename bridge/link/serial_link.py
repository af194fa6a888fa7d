"""CompassLink: the driver that runs the link machine on a real port, on one reader thread.

Everything the link decides -- its states, the handshake, command
transactions, sequence tracking -- is the sans-I/O
:class:`bridge.protocol.link.LinkMachine`. This module only does what the
machine asks: it opens the port when :meth:`~bridge.protocol.link.LinkMachine.open_due`,
reads it (waking no later than the machine's next deadline), hands the bytes
and ``now`` in, writes the :class:`~bridge.protocol.link.Write` events, closes
the port on :class:`~bridge.protocol.link.ClosePort`, logs the notices, and
hands every frame to ``on_frame`` and every state change to ``on_state``.

One reader thread, which never waits on anything but the port: a command
caller's thread submits its transaction to the machine (under the link's
lock, writing its first attempt itself) and waits for the reader to see it
end. The machine is not thread-safe, so every call into it holds the lock;
the callbacks run outside it, in the reader thread.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable

from bridge.link.transport import EndOfRecording, Transport
from bridge.protocol.device import (
    CommandError,
    CommandLate,
    CommandNotSupported,
    CommandRejected,
    CommandTimeout,
    LinkCounters,
    LinkDown,
    LinkState,
    Received,
)
from bridge.protocol.gmr import CommandFrame, GmrFrame, ParamsFrame, VersionFrame
from bridge.protocol.link import (
    DEFAULT_LATE_ANSWER_WINDOW_S,
    ClosePort,
    LinkEvent,
    LinkMachine,
    LinkProtocol,
    Notice,
    StateChanged,
    Write,
)

__all__ = [
    "CommandError",
    "CommandLate",
    "CommandNotSupported",
    "CommandRejected",
    "CommandTimeout",
    "CompassLink",
    "LinkCounters",
    "LinkDown",
    "LinkProtocol",
    "LinkState",
    "Received",
]

log = logging.getLogger(__name__)

#: Longest single read: bounds how late the reader notices close() (the machine's own
#: deadlines wake it on time).
_READ_TIMEOUT_S = 0.05
_READ_CHUNK = 4096
#: Reading in bursts (``due_at``): wake this long before the next output falls due. The
#: frames held meanwhile are all read then, stamped with that read's time: it must come
#: before the due time (or the oldest of them would count as due), whatever the
#: scheduler's lateness in waking a thread on a loaded machine (1-2 ms measured).
BURST_LEAD_S = 0.004
#: ... and never hold the port longer than this: a serial port's kernel buffer (4 KiB)
#: holds about 0.35 s of 115200 baud, and samples older than this would be stale news.
MAX_BURST_S = 0.2
#: A frame the compass's rhythm puts within the lead (it would be read on its own, and
#: not be due yet: a wake-up more): the hold ends this long after it instead (the frames'
#: jitter on a pty: a few tenths of a millisecond).
AFTER_FRAME_S = 0.001
#: With the compass's rhythm known, a hold ends before the due frame is expected (and never
#: before :data:`AFTER_FRAME_S` after the frame before it) by what the held frames take to
#: go through the pipeline (:func:`burst_estimate`) and this much more: the due frame comes
#: right after them, and finds more of the code and data it runs on still in the caches
#: than after the 4-9 ms of sleep a lead of :data:`BURST_LEAD_S` before the due *time*
#: leaves (docs/performance-history.md, "The due frame, read warm"); nor does it wait
#: behind them.
WARM_MARGIN_S = 0.0005
#: ... what a burst is taken to take before one has been timed (nine frames at 100 Hz take
#: about 0.7 ms on a quiet machine).
FIRST_BURST_S = 0.0017
#: The rhythm is the earliest the last frames read on their own put it at, of at most this
#: many of them, none older than a second (:func:`frames_phase`).
RHYTHM_READS = 8
#: A burst read after the due time (the thread woke late): its frames but the newest are
#: stamped this long before the due time, so that none of the held ones passes for due.
HELD_BEFORE_DUE_S = 1e-6


class Wake:
    """A flag for one waiting thread (the reader): :class:`threading.Event`'s ``set`` /
    ``clear`` / ``wait`` on a bare lock, held while the flag is clear.

    The reader waits on it ten times a second at 100 Hz (its hold), and an ``Event``'s
    timed wait goes through a :class:`threading.Condition` -- a lock made, taken and
    dropped, a list of waiters kept -- which cost ~120 us of CPU a 90 ms wait on this VM
    against ~80 us for the lock alone (docs/performance-history.md, "The hold's wait"). Any
    thread may ``set``; only the reader clears and waits.
    """

    __slots__ = ("_lock",)

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lock.acquire()  # held: the flag is clear

    def set(self) -> None:
        """Raise the flag (a waiter returns at once); idempotent, from any thread."""
        with contextlib.suppress(RuntimeError):  # already set: the lock was not held
            self._lock.release()

    def clear(self) -> None:
        """Lower the flag (the waiting thread only)."""
        self._lock.acquire(False)

    def is_set(self) -> bool:
        """Whether the flag is raised."""
        return not self._lock.locked()

    def wait(self, timeout: float) -> bool:
        """Return True as soon as the flag is raised, False after ``timeout`` seconds (at
        once for ``timeout <= 0``, as ``Event.wait``: a lock's -1 would wait for ever)."""
        if self._lock.acquire(True, timeout) if timeout > 0 else self._lock.acquire(False):
            # Put the flag back as it was (raised). A set() racing in between has
            # released the lock already: nothing to put back.
            with contextlib.suppress(RuntimeError):
                self._lock.release()
            return True
        return False


class CompassLink:
    """Reads one compass port, keeps it alive, and runs command transactions on it.

    ``transport`` is a :class:`~bridge.link.transport.Transport` (not yet
    open). Every frame goes to ``on_frame(received)``, called in the reader
    thread, so it must be quick and must never block (the daemon's whole
    per-frame pipeline runs there: decode, attitude, non-blocking output
    hand-offs). ``on_state(old, new)`` is called in the reader thread on each
    state change. The rest (``protocol``, ``rate_hz``, ``stale_after``, the
    backoff, the late-answer window) is the :class:`~bridge.protocol.link.LinkMachine`'s.
    Use as a context manager or call :meth:`start` / :meth:`close`.
    """

    def __init__(
        self,
        transport: Transport,
        *,
        on_frame: Callable[[Received], None],
        protocol: LinkProtocol = "gmr",
        rate_hz: int | None = 10,
        stale_after: float = 2.0,
        on_state: Callable[[LinkState, LinkState], None] | None = None,
        backoff_initial: float = 0.1,
        backoff_max: float = 2.0,
        late_answer_window: float = DEFAULT_LATE_ANSWER_WINDOW_S,
        clock: Callable[[], float] = time.monotonic,
        due_at: Callable[[], float] | None = None,
    ) -> None:
        self._machine = LinkMachine(
            name=transport.name,
            protocol=protocol,
            rate_hz=rate_hz,
            stale_after=stale_after,
            backoff_initial=backoff_initial,
            backoff_max=backoff_max,
            late_answer_window=late_answer_window,
        )
        self._transport = transport
        self._on_frame = on_frame
        self._on_state = on_state
        self._clock = clock
        self._due_at = due_at
        # One lock for the machine and the port's writes/closes; waiters on its condition.
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._wake = Wake()  # a command was queued: the reader's wait is stale
        self._ended = threading.Event()
        self._reader: threading.Thread | None = None
        self._said: list[StateChanged | Notice] = []  # to log (and hand to on_state) unlocked
        self._ended_seen = 0  # the machine's commands_ended when waiters were last woken
        self._bursts = BurstReads()  # when to hold the port, and how to stamp what waited

    # ------------------------------------------------------------------ public API

    @property
    def name(self) -> str:
        """The transport's name (the port)."""
        return self._transport.name

    @property
    def protocol(self) -> LinkProtocol:
        """``"gmr"`` or a heading-only protocol."""
        return self._machine.protocol

    @property
    def rate_hz(self) -> int | None:
        """The output rate the connect handshake asks for."""
        return self._machine.rate_hz

    @property
    def stale_after(self) -> float:
        """Seconds without an attitude frame after which the port is reopened."""
        return self._machine.stale_after

    def set_rate(self, rate_hz: int | None, stale_after: float | None = None) -> None:
        """A new output rate (and silence limit): see :meth:`LinkMachine.set_rate`."""
        with self._lock:
            self._machine.set_rate(rate_hz, stale_after)
        self._wake.set()

    @property
    def state(self) -> LinkState:
        """The current :class:`LinkState`."""
        with self._lock:
            return self._machine.state

    @property
    def counters(self) -> LinkCounters:
        """A consistent snapshot of the counters."""
        with self._lock:
            return self._machine.counters

    @property
    def version(self) -> VersionFrame | None:
        """The last ``$PGMRV`` seen (asked for or not), None before any."""
        return self._machine.version

    @property
    def params(self) -> ParamsFrame | None:
        """The last ``$PGMRP`` seen, None before any."""
        return self._machine.params

    @property
    def ended(self) -> bool:
        """A replay transport has played its whole recording (the link is ABSENT for good)."""
        return self._ended.is_set()

    def wait_ended(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for the end of a replay; True if it ended."""
        return self._ended.wait(timeout)

    def start(self) -> CompassLink:
        """Start the reader thread (once)."""
        if self._reader is not None:
            raise RuntimeError("link already started")
        with self._lock:
            self._machine.start(self._clock())
            self._act()
        self._reader = threading.Thread(target=self._run, name="compass-link-reader", daemon=True)
        self._reader.start()
        return self

    def close(self, timeout: float = 2.0) -> None:
        """Stop the reader (within about ``timeout`` s) and close the port."""
        self._stop.set()
        self._wake.set()
        t = self._reader
        if t is not None and t is not threading.current_thread():
            t.join(timeout)
            if t.is_alive():
                log.error("%s: thread %s did not stop within %.1f s", self.name, t.name, timeout)
        with self._cond:
            # Every command still waiting ends in LinkDown.
            self._machine.close(self._clock())
            self._act()
            self._cond.notify_all()
        if t is None or not t.is_alive():
            self._report()  # the reader is gone: what is left is said here
        self._close_port()

    def __enter__(self) -> CompassLink:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def wait_state(self, state: LinkState, timeout: float) -> bool:
        """Wait up to ``timeout`` s for the link to be in ``state``; True if it is."""
        with self._cond:
            return self._cond.wait_for(
                lambda: self._machine.state is state or self._stop.is_set(), timeout
            ) and (self._machine.state is state)

    def command(
        self, name: str, *args: object, timeout: float | None = None, retries: int = 2
    ) -> GmrFrame:
        """Run one command transaction (``$PGMRQ,<name>,<args>``) and return its answer.

        ``timeout`` is per attempt (default: the datasheet's deadline for the
        command plus the line times). Raises :class:`CommandRejected` on an ERR
        answer, :class:`CommandTimeout` (:class:`CommandLate` when the answer
        came after the deadline), :class:`LinkDown` when the port is not open or
        the link closes, :class:`CommandNotSupported` on a heading-only compass.
        """
        if self._machine.protocol != "gmr":
            raise CommandNotSupported(
                f"protocol {self._machine.protocol!r} is a heading-only compass: "
                "it takes no commands"
            )
        if threading.current_thread() is self._reader:
            raise RuntimeError("command() called from the link's reader thread would deadlock")
        cmd = CommandFrame(name, tuple(str(a) for a in args))  # ValueError if malformed
        per_try = timeout if timeout is not None else self.default_timeout(cmd)
        with self._cond:
            if self._stop.is_set():
                raise LinkDown("link is closed")
            txn = self._machine.submit(cmd, self._clock(), per_try, retries)
            self._act()
            self._wake.set()  # the reader's wait may end later than this command's deadline
            while not txn.done:
                # The reader ends it (answer, deadline) or close() does; the bound only
                # guards against a reader that died.
                if not self._cond.wait(1.0) and (
                    self._reader is None or not self._reader.is_alive()
                ):
                    self._machine.close(self._clock())
                    self._act()
        return txn.result()

    def default_timeout(self, cmd: CommandFrame) -> float:
        """Per-attempt timeout for ``cmd``: datasheet deadline + line times at the port's baud."""
        baud = getattr(self._transport, "baud", None)
        return self._machine.default_timeout(cmd, baud if isinstance(baud, int) else None)

    # ------------------------------------------------------------------ the driver

    def _act(self) -> None:
        """Do what the machine asks (the lock held): writes and closes at once; state changes
        and log lines kept for :meth:`_report` (nothing is logged or called back under the
        lock); command waiters woken when a transaction ended."""
        m = self._machine
        events: list[LinkEvent] = m.take_events() if m.has_events else []
        for ev in events:
            if type(ev) is Write:
                try:
                    self._transport.write(ev.data)
                except OSError as e:
                    # The reader notices a lost port on its next read: fail this command.
                    m.write_failed(ev, str(e), self._clock())
                    events.extend(m.take_events())
            elif type(ev) is ClosePort:
                with contextlib.suppress(OSError):
                    self._transport.close()
            elif isinstance(ev, StateChanged | Notice):
                self._said.append(ev)
        if events or m.commands_ended != self._ended_seen:
            self._ended_seen = m.commands_ended
            self._cond.notify_all()

    def _report(self) -> None:
        """Log what the machine said; state changes to ``on_state`` (reader thread, or close()
        once the reader is gone; the lock not held)."""
        with self._lock:
            said, self._said = self._said, []
        for ev in said:
            if type(ev) is Notice:
                log.log(ev.level, "%s", ev.message)
                continue
            assert type(ev) is StateChanged
            suffix = f" ({ev.reason})" if ev.reason else ""
            bad = ev.new in (LinkState.ABSENT, LinkState.STALE)
            log.log(
                logging.WARNING if bad else logging.INFO,
                "compass %s: %s -> %s%s",
                self.name,
                ev.old.value,
                ev.new.value,
                suffix,
            )
            if self._on_state is not None:
                try:
                    self._on_state(ev.old, ev.new)
                except Exception:
                    log.exception("compass %s: on_state callback failed", self.name)

    def _close_port(self) -> None:
        with self._lock, contextlib.suppress(OSError):
            self._transport.close()

    def _run(self) -> None:
        try:
            self._read_loop()
        except Exception:
            # A bug must not leave a zombie link that looks alive: say so loudly.
            log.exception("compass %s: reader crashed", self.name)
            with self._cond:
                self._machine.lost(self._clock(), "reader crashed")
                self._machine.close(self._clock())
                self._act()
        finally:
            self._report()
            self._close_port()

    def _open(self) -> bool:
        """Open the port for the machine; False when it has ended for good."""
        try:
            self._transport.open()
        except EndOfRecording as e:
            with self._cond:
                self._machine.end(self._clock(), str(e))
                self._act()
            self._ended.set()
            return False
        except OSError as e:
            with self._cond:
                self._machine.open_failed(self._clock(), str(e))
                self._act()
            return True
        baud = getattr(self._transport, "baud", None)
        with self._cond:
            self._machine.opened(
                self._clock(),
                interactive=self._transport.interactive,
                baud=baud if isinstance(baud, int) else None,
            )
            self._act()
        return True

    def _read_loop(self) -> None:
        machine = self._machine
        on_frame = self._on_frame
        clock = self._clock
        bursts = self._bursts
        while not self._stop.is_set():
            self._wake.clear()  # before the deadline is read: a later command sets it again
            with self._cond:
                now = clock()
                deadline = machine.next_deadline()
                if deadline is not None and now >= deadline:
                    machine.tick(now)  # staleness, a command's deadline, a retry
                    deadline = machine.next_deadline()
                self._act()
                is_open = machine.is_open
                open_due = machine.open_due(now)
            if self._said:
                self._report()
            if not is_open:
                if open_due:
                    if not self._open():
                        return
                    continue
                wait = _READ_TIMEOUT_S * 20 if deadline is None else deadline - now
                if wait > 0:
                    self._wake.wait(wait)
                continue
            timeout = _READ_TIMEOUT_S if deadline is None else deadline - now
            timeout = min(max(timeout, 0.0), _READ_TIMEOUT_S)
            if bursts.held_for is not None:
                # The frames that waited through the hold: what is there now, not the due
                # frame coming after it (a hold with none waiting: a slow compass).
                timeout = 0.0
            try:
                data = self._transport.read(_READ_CHUNK, timeout)
            except EndOfRecording as e:
                with self._cond:
                    machine.end(clock(), str(e))
                    self._act()
                self._ended.set()
                return
            except OSError as e:
                with self._cond:
                    machine.lost(clock(), str(e))
                    self._act()
                continue
            if not data:
                bursts.held_for = None  # nothing waited: frames from now on read as they come
                continue
            now = clock()
            with self._lock:
                received = machine.receive(data, now)
                self._act()
                quiet = machine.quiet
            burst = bursts.held_for is not None and len(received) > 1
            received = bursts.read(received, now)
            for item in received:
                try:
                    on_frame(item)
                except Exception:
                    with self._lock:
                        machine.count("callback_errors")
                        first = machine.counters.callback_errors == 1
                    if first:
                        log.exception("compass %s: on_frame callback failed", self.name)
            if burst:  # the held frames' time through the pipeline: the next hold's lead
                bursts.took(clock() - now)
            if quiet and received and self._due_at is not None:
                self._hold(deadline, now)

    def _hold(self, deadline: float | None, read_at: float) -> None:
        """Let the port's bytes gather until shortly before the frame the next output
        falls due on (:meth:`BurstReads.hold`; or the machine's next deadline): the frames
        meanwhile then go through the pipeline together -- one wake-up, warm caches --
        instead of one cold wake-up each; the frames from then on are read as they come,
        so the one the output carries is as prompt as ever, and comes while the burst's
        code is still warm. A command (or close) ends the wait at once."""
        assert self._due_at is not None
        now = self._clock()
        try:
            due = self._due_at()
        except Exception:  # an output's bug must not stop the reader: read as frames come
            log.exception("compass %s: due_at failed; reading every frame as it comes", self.name)
            self._due_at = None
            return
        until = self._bursts.hold(due, self._machine.rate_hz, now, read_at, deadline)
        if until is not None:
            self._wake.wait(until - now)


class BurstReads:
    """When the reader holds the port, and how it stamps what waited (pure: times in,
    times out; :class:`CompassLink`'s reader runs it on the port, ``benchmarks.reads`` on
    a simulated clock).

    After a read, :meth:`read` stamps its frames (:func:`_held` when the read came after
    the due time it held for) and notes the compass's rhythm from the reads of one frame
    each; :meth:`took` times a burst's way through the pipeline; :meth:`hold` says until
    when to let the next frames gather (:func:`hold_end`), and remembers the due time it
    held for (:attr:`held_for`: the next read takes what waited, at once) and how many
    frames the rhythm put before it (:func:`held_count`).
    """

    __slots__ = ("arrived", "burst_s", "held_for", "held_n")

    def __init__(self) -> None:
        #: The last reads of one frame each (read as they came): the frames' rhythm.
        self.arrived: deque[float] = deque(maxlen=RHYTHM_READS)
        self.burst_s = FIRST_BURST_S  #: what a burst of held frames takes (burst_estimate)
        self.held_for: float | None = None  #: the due time the last hold was for
        self.held_n: int | None = None  #: ... and the frames the rhythm put in it (None: unknown)

    def read(self, received: list[Received], now: float) -> list[Received]:
        """The frames of a read at ``now``, stamped for the outputs (the hold is over)."""
        held_for = self.held_for
        if held_for is not None:
            if now >= held_for:
                received = _held(received, held_for, self.held_n)
            self.held_for = None
        elif len(received) == 1:
            self.arrived.append(now)  # read as it came: when the compass's frames come
        return received

    def took(self, seconds: float) -> None:
        """A burst of held frames took ``seconds`` through the pipeline: the next hold's lead."""
        self.burst_s = burst_estimate(self.burst_s, seconds)

    def hold(
        self, due: float, rate_hz: int | None, now: float, read_at: float, deadline: float | None
    ) -> float | None:
        """Until when to hold the port at ``now`` for the output due at ``due`` (never past
        :data:`MAX_BURST_S` nor the link machine's ``deadline``), the last read having come
        at ``read_at``; None: do not wait."""
        phase = frames_phase(self.arrived, rate_hz)
        end = hold_end(due, phase, rate_hz, self.burst_s + WARM_MARGIN_S)
        until = min(end, now + MAX_BURST_S)
        if deadline is not None and deadline < until:
            until = deadline
        if until <= now:
            return None
        # Ended by the rhythm (after the last frame expected before the due time)?
        rhythm = until == end != due - BURST_LEAD_S
        self.held_for = due
        self.held_n = held_count(due, phase, read_at, rate_hz) if rhythm else None
        return until


def hold_end(
    due: float, arrived: float | None, rate_hz: int | None, lead: float = BURST_LEAD_S
) -> float:
    """When a hold for the due time ``due`` ends: with the compass's rhythm known,
    ``lead`` before the due frame (the first after ``due``) is expected (at most
    :data:`BURST_LEAD_S`), but not before :data:`AFTER_FRAME_S` after the frame before
    it; so every frame before the due one comes with the held ones (none costs a wake-up
    of its own, in which it would not be due yet), and the due frame is read as it comes,
    right after them, while the caches are warm. Without a rhythm, :data:`BURST_LEAD_S`
    before ``due``.

    The rhythm: one frame every ``1 / rate_hz`` seconds (the rate asked of the compass),
    in step with ``arrived``, when a frame read on its own came (:func:`frames_phase`;
    one every due time). Without one (no rate, no frame read on its own in the last
    second) the lead alone.
    """
    until = due - BURST_LEAD_S
    if arrived is None or not rate_hz or not 0.0 < due - arrived < 1.0:
        return until
    period = 1.0 / rate_hz
    if period <= 2.0 * AFTER_FRAME_S:
        return until
    last = arrived + (math.ceil((due - arrived) / period) - 1) * period  # the last before due
    return max(last + AFTER_FRAME_S, last + period - min(lead, BURST_LEAD_S))


def burst_estimate(previous: float, took: float) -> float:
    """What the next burst of held frames will take to go through the pipeline, after one
    took ``took`` seconds: a longer one at once (a busy machine: the due frame must not
    come before the burst is through), a shorter one a quarter of the way (one quick burst
    does not shorten the lead that much)."""
    return took if took >= previous else previous + 0.25 * (took - previous)


def frames_phase(arrivals: Iterable[float], rate_hz: int | None) -> float | None:
    """When the compass's frames come, from the reads of one frame each in ``arrivals``
    (oldest first): the newest, moved back to the earliest point of the rhythm (one frame
    every ``1 / rate_hz`` s) any of those within a second of it puts it at. A read only
    ever comes late -- the thread's wake-up, a busy machine -- so the earliest is the
    closest to when the compass sends; one late read does not move the rhythm, which a
    hold ending shortly before the due frame relies on. None without a read;
    the newest without a rate.
    """
    reads = list(arrivals)
    if not reads:
        return None
    newest = reads[-1]
    if not rate_hz:
        return newest
    period = 1.0 / rate_hz
    return min(a + round((newest - a) / period) * period for a in reads if newest - a < 1.0)


def held_count(due: float, phase: float | None, read_at: float, rate_hz: int | None) -> int:
    """How many frames the rhythm (one every ``1 / rate_hz`` s in step with ``phase``, as
    :func:`hold_end` has it) puts after the newest frame read by a read at ``read_at``
    (the last point of the rhythm at or before it) and before ``due``."""
    if phase is None or not rate_hz:
        return 0
    period = 1.0 / rate_hz
    newest = phase + math.floor((read_at - phase) / period) * period
    return max(0, math.ceil((due - newest) / period - 1e-9) - 1)


def _held(received: list[Received], due: float, held: int | None) -> list[Received]:
    """The frames of the read after a hold for ``due`` that came after it (the thread woke
    late): the ``held`` oldest (the frames the rhythm put before ``due``) stamped just
    before it, the rest -- the due frame and any after it, which came while the thread
    was late -- due by the read as frames read as they come are; without a rhythm
    (``held`` None) all but the newest stamped before ``due``.

    Stamped with the read's time, the oldest -- held up to :data:`MAX_BURST_S` -- would
    be the first an output finds due, and go out as if it were new. The newest, when
    kept, is the freshest sample there is. (A frame that came after ``due`` and is
    stamped before it -- a frame not where the rhythm put it -- is stamped a little
    before it came.)
    """
    before = due - HELD_BEFORE_DUE_S
    if held is None:
        held = len(received) - 1
    if held <= 0:
        return received
    return [Received(r.frame, before, r.t) for r in received[:held]] + received[held:]
