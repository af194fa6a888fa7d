"""CompassLink: the one reader of the compass port, its state machine and command transactions.

Threads (and why there are two):

* the **reader** opens the transport, reads, feeds the decoder, tracks
  sequence numbers, routes command answers and hands every frame to the
  consumer. It never waits on anything but the port: a lagging consumer loses
  its oldest frames (counted) instead of stalling the reader.
* the **handshake worker** runs ``VER``, ``RATE,<rate_hz>``, ``PAR,GET`` after
  every (re)connect and after a detected device reset. It must be a separate
  thread because the answers it waits for arrive through the reader.

Link states (:class:`LinkState`), each change logged once. Only **attitude
frames** count (``$PGMRA``; for a heading-only compass its heading sentences):
a compass that answers commands but streams nothing is not streaming.

* ``OPENING``   -- opening the port, or open and waiting for attitude frames
* ``STREAMING`` -- attitude frames arrive
* ``STALE``     -- the port is open but no attitude frame came for ``stale_after`` s;
  the link closes and reopens it (with backoff) and stays STALE until frames come back
* ``ABSENT``    -- the port cannot be opened or went away; reopened with backoff, quietly

Hysteresis, so the state never flaps: the link becomes STREAMING on the
second attitude frame of a run; but once a STREAMING spell has ended stale
within ``10 * stale_after``, frames must keep coming for ``stale_after / 2``
first, and that while doubles with each further short spell (up to
``4 * stale_after``); a spell that lasts resets it. A compass that streams in
short bursts stays STALE instead of going lost / restored forever.

A device reset is what the datasheet says it looks like: a ``$PGMRV`` nobody
asked for *and* frames starting again at ``seq`` 0 (or ``seq`` 0 alone, when
the ``$PGMRV`` was lost). A ``$PGMRV`` after which the frames carry on is a
late or stray answer, not a reset.

Command transactions (GMR protocol only) are serialised; how an answer is matched
to its command, and a late answer kept from passing for a later command's, is
:mod:`bridge.link.transactions`.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Literal, Protocol, TypeAlias

from bridge.device import (
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
from bridge.link.transactions import (
    COMMAND_DEADLINES_S,
    DEFAULT_DEADLINE_S,
    Routed,
    Transactions,
)
from bridge.link.transport import EndOfRecording, Transport
from bridge.protocol.framing import MAX_LINE_BYTES
from bridge.protocol.gmr import (
    AckFrame,
    AttitudeFrame,
    CommandFrame,
    GmrDecoder,
    GmrFrame,
    ParamsFrame,
    VersionFrame,
    encode,
)

__all__ = [
    "COMMAND_DEADLINES_S",
    "DEFAULT_DEADLINE_S",
    "DEFAULT_LATE_ANSWER_WINDOW_S",
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
from bridge.protocol.heading import HeadingDecoder, HeadingFrame

Frame: TypeAlias = GmrFrame | HeadingFrame

log = logging.getLogger(__name__)

LinkProtocol: TypeAlias = Literal["gmr", "nmea", "os5000"]

SEQ_MODULUS = 65536
#: A forward seq gap this large cannot be frame loss on a link that would have gone stale
#: long before (at 100 Hz it is 5.5 minutes): count it as a discontinuity instead.
_MAX_PLAUSIBLE_GAP = SEQ_MODULUS // 2
#: ``seq`` 0 after a frame at most this many frames before the wrap is frame loss across
#: the wrap (65534, [65535 lost], 0), not a reboot. A reboot restarts at 0 "from far
#: away"; one in the last 64 frames of a 65536-frame cycle (0.1 % of them) whose
#: ``$PGMRV`` was lost as well reads as loss -- its ``$PGMRV`` is what normally tells.
#: 64 frames: 0.64 s at 100 Hz, longer than any loss that keeps a 100 Hz link streaming
#: within the default stale_after.
_WRAP_LOSS_WINDOW = 64

#: How long after its deadline a command's answer may still come (a device slower than
#: its datasheet): no retry meanwhile, and an answer that late is a time-out, not news.
DEFAULT_LATE_ANSWER_WINDOW_S = 2.0
#: After a short spell, STREAMING needs attitude frames for ``stale_after / _CONFIRM_DIVISOR``
_CONFIRM_DIVISOR = 2.0
#: (a spell is short when it ended stale sooner than ``_FLAP_SPELLS * stale_after``),
_FLAP_SPELLS = 10.0
#: doubled for each further short spell, up to this many times.
_CONFIRM_MAX_FACTOR = 8.0

_READ_TIMEOUT_S = 0.05  # bounds how late the reader notices close() and staleness
_READ_CHUNK = 4096


_LIVE = (LinkState.OPENING, LinkState.STREAMING)


class _Decoder(Protocol):
    def feed(self, data: bytes) -> Sequence[Frame]: ...


class CompassLink:
    """Reads one compass port, keeps it alive, and runs command transactions on it.

    ``transport`` is a :class:`~bridge.link.transport.Transport` (not yet
    open). Frames go to a bounded queue read with :meth:`get` and, if given,
    to ``on_frame(received)`` -- called in the reader thread, so it must be
    quick and must never block (the daemon's whole per-frame pipeline runs
    there: decode, attitude, non-blocking output hand-offs). ``queue_size=0``
    keeps no queue (for an ``on_frame`` consumer; :meth:`get` then always
    returns None).
    ``on_state(old, new)`` is called in the reader thread on each state change.
    Use as a context manager or call :meth:`start` / :meth:`close`.
    """

    def __init__(
        self,
        transport: Transport,
        *,
        protocol: LinkProtocol = "gmr",
        rate_hz: int | None = 10,
        stale_after: float = 2.0,
        queue_size: int = 256,
        on_frame: Callable[[Received], None] | None = None,
        on_state: Callable[[LinkState, LinkState], None] | None = None,
        backoff_initial: float = 0.1,
        backoff_max: float = 2.0,
        late_answer_window: float = DEFAULT_LATE_ANSWER_WINDOW_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if protocol not in ("gmr", "nmea", "os5000"):
            raise ValueError(f"protocol must be 'gmr', 'nmea' or 'os5000', got {protocol!r}")
        if rate_hz is not None:
            CommandFrame.rate(rate_hz)  # ValueError for a rate the device does not offer
        if not stale_after > 0:
            raise ValueError(f"stale_after must be positive, got {stale_after}")
        if queue_size < 0:
            raise ValueError(f"queue_size must be at least 0, got {queue_size}")
        if queue_size == 0 and on_frame is None:
            raise ValueError("queue_size=0 needs an on_frame consumer (frames would go nowhere)")
        if not 0 < backoff_initial <= backoff_max:
            raise ValueError("need 0 < backoff_initial <= backoff_max")
        self._transport = transport
        self.protocol: LinkProtocol = protocol
        self.rate_hz = rate_hz
        self.stale_after = stale_after
        self._on_frame = on_frame
        self._on_state = on_state
        self._backoff_initial = backoff_initial
        self._backoff_max = backoff_max
        self._clock = clock

        self._decoder: _Decoder = self._make_decoder()
        self._stop = threading.Event()
        self._ended = threading.Event()
        self._reader: threading.Thread | None = None
        self._worker: threading.Thread | None = None

        # State (written by the reader; read anywhere under the condition).
        self._state_cond = threading.Condition()
        self._state = LinkState.ABSENT

        # Counters: one dict of ints. Each key has one kind of writer: the per-frame ones
        # (bytes_read, frames, attitude_frames) only the reader, which bumps them without
        # the lock (a store to another key cannot lose them; the snapshot copies under the
        # lock); every other key is written under _stats_lock by whoever counts it.
        self._stats_lock = threading.Lock()
        self._c: dict[str, int] = {
            f: 0 for f in LinkCounters.__dataclass_fields__ if f != "bad_lines"
        }

        # Consumer queue: drop-oldest, never blocks the reader.
        self._queue: deque[Received] = deque()
        self._queue_size = queue_size
        self._queue_cond = threading.Condition()

        # Port: writes (command callers) vs close/reopen (reader).
        self._write_lock = threading.Lock()
        self._port_open = False

        # Command transactions (callers' threads; the reader routes the answers).
        self._txns = Transactions(
            name=transport.name,
            write=self._write,
            count=self._count,
            clock=clock,
            late_window=late_answer_window,
            stop=self._stop,
        )

        # Sequence tracking (reader only).
        self._last_seq: int | None = None
        self._restart_expected = False  # an unasked $PGMRV came: the next seq tells
        # Hysteresis (reader only): 0 -- two frames make a stream; else how many times
        # stale_after / _CONFIRM_DIVISOR attitude frames must keep coming (after short spells).
        self._confirm_factor = 0.0

        # Handshake hand-off: the reader bumps the generation, the worker follows it.
        self._gen_cond = threading.Condition()
        self._generation = 0
        self._handshaken_gen = 0  # worker only
        self._version: VersionFrame | None = None
        self._params: ParamsFrame | None = None

    # ------------------------------------------------------------------ public API

    @property
    def name(self) -> str:
        """The transport's name (the port)."""
        return self._transport.name

    @property
    def state(self) -> LinkState:
        """The current :class:`LinkState`."""
        with self._state_cond:
            return self._state

    @property
    def counters(self) -> LinkCounters:
        """A consistent snapshot of the counters."""
        dropped = getattr(getattr(self._decoder, "counters", None), "dropped", None)
        bad = dict(dropped.snapshot()) if dropped is not None else {}
        with self._stats_lock:
            return LinkCounters(bad_lines=bad, **self._c)

    @property
    def version(self) -> VersionFrame | None:
        """The last ``$PGMRV`` seen (asked for or not), None before any."""
        return self._version

    @property
    def params(self) -> ParamsFrame | None:
        """The last ``$PGMRP`` seen, None before any."""
        return self._params

    @property
    def ended(self) -> bool:
        """A replay transport has played its whole recording (the link is ABSENT for good)."""
        return self._ended.is_set()

    def wait_ended(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for the end of a replay; True if it ended."""
        return self._ended.wait(timeout)

    def start(self) -> CompassLink:
        """Start the reader and handshake threads (once)."""
        if self._reader is not None:
            raise RuntimeError("link already started")
        self._set_state(LinkState.OPENING, "starting")
        self._reader = threading.Thread(target=self._run, name="compass-link-reader", daemon=True)
        self._worker = threading.Thread(
            target=self._handshake_loop, name="compass-link-handshake", daemon=True
        )
        self._reader.start()
        self._worker.start()
        return self

    def close(self, timeout: float = 2.0) -> None:
        """Stop the threads (within about ``timeout`` s) and close the port."""
        self._stop.set()
        self._txns.wake()
        for cond in (self._gen_cond, self._queue_cond, self._state_cond):
            with cond:
                cond.notify_all()
        deadline = time.monotonic() + timeout
        for t in (self._reader, self._worker):
            if t is not None and t is not threading.current_thread():
                t.join(max(0.0, deadline - time.monotonic()))
                if t.is_alive():
                    log.error(
                        "%s: thread %s did not stop within %.1f s", self.name, t.name, timeout
                    )
        self._close_port()

    def __enter__(self) -> CompassLink:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def get(self, timeout: float | None = None) -> Received | None:
        """The oldest queued frame, waiting up to ``timeout`` s (None: forever); None if none."""
        if not self._queue_size:
            return None  # no queue (an on_frame consumer takes every frame)
        with self._queue_cond:
            if not self._queue and timeout != 0:
                self._queue_cond.wait_for(lambda: bool(self._queue) or self._stop.is_set(), timeout)
            return self._queue.popleft() if self._queue else None

    def wait_state(self, state: LinkState, timeout: float) -> bool:
        """Wait up to ``timeout`` s for the link to be in ``state``; True if it is."""
        with self._state_cond:
            return self._state_cond.wait_for(
                lambda: self._state is state or self._stop.is_set(), timeout
            ) and (self._state is state)

    def command(
        self, name: str, *args: object, timeout: float | None = None, retries: int = 2
    ) -> GmrFrame:
        """Send ``$PGMRQ,<name>,<args>`` and return the device's answer.

        The answer is the matching ``$PGMRK,<name>,OK...`` (``$PGMRV`` for VER,
        ``$PGMRP`` for PAR,GET). Each attempt waits ``timeout`` s -- by default
        the datasheet's deadline for the command (200 ms; MAGCAL,END and
        PAR,SET 500 ms; ACCCAL 1.5 s) plus the time a command and an answer
        line take on the wire at the port's baud -- and is resent up to
        ``retries`` times, each time only once the previous attempt's answer can
        no longer come (``late_answer_window`` after its deadline). Raises
        :class:`CommandRejected` on ``ERR``, :class:`CommandLate` (a
        :class:`CommandTimeout`) when the answer came after the deadline,
        :class:`CommandTimeout` when nothing matching came, :class:`LinkDown`
        when the port is not open, :class:`CommandNotSupported` for
        heading-only protocols, ValueError for a malformed command. Frames
        keep flowing to the consumer meanwhile. Must not be called from the
        reader thread (that is, from ``on_frame``/``on_state``).
        """
        if self.protocol != "gmr":
            raise CommandNotSupported(
                f"protocol {self.protocol!r} is a heading-only compass: it takes no commands"
            )
        if threading.current_thread() is self._reader:
            raise RuntimeError("command() called from the link's reader thread would deadlock")
        if retries < 0:
            raise ValueError("retries must be >= 0")
        cmd = CommandFrame(name, tuple(str(a) for a in args))  # ValueError if malformed
        line = encode(cmd)
        per_try = timeout if timeout is not None else self.default_timeout(cmd)
        if not per_try > 0:
            raise ValueError(f"timeout must be positive, got {per_try}")
        answer = self._txns.run(cmd, line, per_try, retries)
        if isinstance(answer, AckFrame) and not answer.ok:
            self._count("command_rejections")
            reason = answer.fields[0] if answer.fields else "?"
            raise CommandRejected(cmd.key, reason, answer)
        return answer

    def default_timeout(self, cmd: CommandFrame) -> float:
        """Per-attempt timeout for ``cmd``: datasheet deadline + line times at the port's baud."""
        deadline = COMMAND_DEADLINES_S.get(cmd.key, DEFAULT_DEADLINE_S)
        baud = getattr(self._transport, "baud", None)
        if isinstance(baud, int) and baud > 0:
            # The device's clock starts when the command has arrived, and the answer must
            # still cross the wire: 10 bits per byte (8N1), a full line each way at worst.
            deadline += 2 * MAX_LINE_BYTES * 10 / baud
        return deadline

    # ------------------------------------------------------------------ commands

    def _write(self, data: bytes) -> None:
        with self._write_lock:
            if not self._port_open:
                raise LinkDown(f"{self.name} is not open")
            try:
                self._transport.write(data)
            except OSError as e:
                # The reader will notice the loss on its next read; just fail this command.
                raise LinkDown(f"{self.name}: write failed: {e}") from e

    def _route_answer(self, frame: GmrFrame, now: float) -> None:
        """Reader side: an answer-type frame to the transactions; a reboot's $PGMRV to us."""
        # Only a version nobody asked for lately, from a device already seen streaming on
        # this connection, may be a reset (a power-up announcement is not one we saw); the
        # next attitude frame's seq decides (see _track_seq).
        if self._txns.route(frame, now) is Routed.VERSION and self._last_seq is not None:
            self._restart_expected = True

    # ------------------------------------------------------------------ reader

    def _make_decoder(self) -> _Decoder:
        if self.protocol == "gmr":
            return GmrDecoder(direction="host")
        return HeadingDecoder(self.protocol)

    def _count(self, name: str, n: int = 1) -> None:
        with self._stats_lock:
            self._c[name] += n

    def _set_state(self, new: LinkState, reason: str = "") -> None:
        with self._state_cond:
            old = self._state
            if new is old:
                return
            self._state = new
            self._state_cond.notify_all()
        suffix = f" ({reason})" if reason else ""
        if new in (LinkState.ABSENT, LinkState.STALE):
            log.warning("compass %s: %s -> %s%s", self.name, old.value, new.value, suffix)
        else:
            log.info("compass %s: %s -> %s%s", self.name, old.value, new.value, suffix)
        if self._on_state is not None:
            try:
                self._on_state(old, new)
            except Exception:
                log.exception("compass %s: on_state callback failed", self.name)

    def _close_port(self) -> None:
        with self._write_lock:
            self._port_open = False
            with contextlib.suppress(OSError):
                self._transport.close()

    def _open_port(self) -> None:
        with self._write_lock:
            self._transport.open()
            self._port_open = True

    def _bump_generation(self) -> None:
        with self._gen_cond:
            self._generation += 1
            self._gen_cond.notify_all()

    def _run(self) -> None:
        try:
            self._read_loop()
        except Exception:
            # A bug must not leave a zombie link that looks alive: say so loudly.
            log.exception("compass %s: reader crashed", self.name)
            self._set_state(LinkState.ABSENT, "reader crashed")
        finally:
            self._close_port()

    def _read_loop(self) -> None:
        backoff = self._backoff_initial
        opened_before = False
        is_open = False
        last_attitude = 0.0  # when the last attitude frame came (or the port opened)
        last_frame = -float("inf")  # when the last frame of any kind came
        run_start: float | None = None  # first attitude frame of the current run
        run_frames = 0
        streaming_since = 0.0
        c = self._c
        while not self._stop.is_set():
            if not is_open:
                try:
                    self._open_port()
                except EndOfRecording as e:
                    self._end_of_recording(str(e))
                    return
                except OSError as e:
                    self._count("open_failures")
                    log.debug("compass %s: open failed: %s", self.name, e)
                    self._set_state(LinkState.ABSENT, str(e))
                    self._stop.wait(backoff)
                    backoff = min(2 * backoff, self._backoff_max)
                    continue
                is_open = True
                if opened_before:
                    self._count("reconnects")
                opened_before = True
                reset = getattr(self._decoder, "reset", None)
                if callable(reset):
                    reset()  # a partial line from the old connection is not a bad line
                self._last_seq = None
                self._restart_expected = False
                last_attitude = self._clock()
                run_start = None
                if self.state is LinkState.ABSENT:
                    self._set_state(LinkState.OPENING, "port open")
                self._bump_generation()
            try:
                data = self._transport.read(_READ_CHUNK, _READ_TIMEOUT_S)
            except EndOfRecording as e:
                self._close_port()
                self._end_of_recording(str(e))
                return
            except OSError as e:
                self._close_port()
                is_open = False
                self._set_state(LinkState.ABSENT, f"port lost: {e}")
                self._stop.wait(backoff)
                backoff = min(2 * backoff, self._backoff_max)
                continue
            now = self._clock()
            if data:
                c["bytes_read"] += len(data)  # reader-only key: no lock (see __init__)
                frames = self._decoder.feed(data)
                if frames:
                    last_frame = now
                    before = c["attitude_frames"]
                    self._handle(frames, now)
                    # Only attitude frames make a stream: command answers do not.
                    if c["attitude_frames"] != before:
                        last_attitude = now
                        # Only this thread writes the state: a plain read, not the lock.
                        if self._state is not LinkState.STREAMING:
                            if run_start is None:
                                run_start, run_frames = now, 0
                            run_frames += c["attitude_frames"] - before
                            if run_frames >= 2 and now - run_start >= self._confirm_s():
                                self._set_state(LinkState.STREAMING)
                                streaming_since = now
                                backoff = self._backoff_initial
            if now - last_attitude > self.stale_after:
                self._count("stale_events")
                if self._state is LinkState.STREAMING:
                    # A short spell between two silences: the next one must last longer.
                    short = now - streaming_since < _FLAP_SPELLS * self.stale_after
                    factor = min(2.0 * self._confirm_factor, _CONFIRM_MAX_FACTOR)
                    self._confirm_factor = max(1.0, factor) if short else 0.0
                what = "attitude frame" if self.protocol == "gmr" else "heading sentence"
                why = f"no {what} for {self.stale_after:g} s"
                if now - last_frame <= self.stale_after:
                    why += " (the compass answers, but streams nothing)"
                self._set_state(LinkState.STALE, f"{why}; reopening")
                self._close_port()
                is_open = False
                run_start = None
                self._stop.wait(backoff)
                backoff = min(2 * backoff, self._backoff_max)

    def _confirm_s(self) -> float:
        """How long attitude frames must keep coming before the link says STREAMING."""
        return self.stale_after / _CONFIRM_DIVISOR * self._confirm_factor

    def _end_of_recording(self, why: str) -> None:
        self._ended.set()
        self._set_state(LinkState.ABSENT, why)

    def _handle(self, frames: Sequence[Frame], now: float) -> None:
        c = self._c
        c["frames"] += len(frames)  # reader-only key: no lock (see __init__)
        for frame in frames:
            if type(frame) is AttitudeFrame:
                # _track_seq's common case inline (per frame: a call costs more than this).
                last = self._last_seq
                c["attitude_frames"] += 1  # reader-only key: no lock (see __init__)
                if last is not None and frame.seq == last + 1 and not self._restart_expected:
                    self._last_seq = frame.seq
                else:
                    self._track_seq(frame.seq)
            elif type(frame) is HeadingFrame:
                c["attitude_frames"] += 1  # a heading-only compass's stream
            elif isinstance(frame, VersionFrame | ParamsFrame | AckFrame):
                if isinstance(frame, VersionFrame):
                    self._version = frame
                elif isinstance(frame, ParamsFrame):
                    self._params = frame
                self._route_answer(frame, now)
            item = Received(frame, now)
            if self._queue_size:
                self._enqueue(item)
            if self._on_frame is not None:
                try:
                    self._on_frame(item)
                except Exception:
                    self._count("callback_errors")
                    if self.counters.callback_errors == 1:
                        log.exception("compass %s: on_frame callback failed", self.name)

    def _track_seq(self, seq: int) -> None:
        """A $PGMRA frame's sequence number (counted in attitude_frames by the caller)."""
        last = self._last_seq
        self._last_seq = seq
        if last is None:
            return  # the first frame of a connection: no gap to count
        expected = (last + 1) % SEQ_MODULUS
        if self._restart_expected:
            # An unasked $PGMRV came: a reboot restarts the sequence, anything else does not.
            self._restart_expected = False
            if seq == expected:
                self._count("unsolicited_answers")
                log.debug("compass %s: a $PGMRV nobody asked for; frames went on", self.name)
            else:
                self._device_reset("$PGMRV unasked, seq restarted")
            return
        if seq == expected:
            return
        gap = (seq - expected) % SEQ_MODULUS
        if seq == 0 and gap >= _WRAP_LOSS_WINDOW:
            # The datasheet's RESET restarts the counter at 0 (its $PGMRV, which normally
            # announces it, may have been lost on the line).
            self._device_reset("seq restarted at 0")
            return
        if gap < _MAX_PLAUSIBLE_GAP:
            self._count("lost_frames", gap)
        else:
            self._count("seq_discontinuities")
            log.debug("compass %s: seq jumped from %d to %d", self.name, last, seq)

    def _device_reset(self, why: str) -> None:
        """A reboot seen in the stream: this frame starts its new sequence."""
        self._count("device_resets")
        log.warning("compass %s: device reset detected (%s)", self.name, why)
        # A rebooted device runs at 10 Hz again: the handshake (VER, RATE, PAR,GET) runs
        # again as after a reconnect.
        self._bump_generation()

    def _enqueue(self, item: Received) -> None:
        with self._queue_cond:
            if len(self._queue) >= self._queue_size:
                self._queue.popleft()
                dropped = True
            else:
                dropped = False
            self._queue.append(item)
            self._queue_cond.notify()
        if dropped:
            self._count("consumer_drops")

    # ------------------------------------------------------------------ handshake

    def _handshake_loop(self) -> None:
        while not self._stop.is_set():
            with self._gen_cond:
                self._gen_cond.wait_for(self._handshake_due, timeout=1.0)
                gen = self._generation
            if self._stop.is_set() or gen == self._handshaken_gen:
                continue
            self._handshaken_gen = gen
            if self.protocol != "gmr" or not self._transport.interactive:
                continue
            try:
                self._handshake()
            except CommandError as e:
                with self._gen_cond:
                    superseded = self._generation != gen
                # A port that died mid-handshake is already logged as ABSENT/STALE, and the
                # next connection redoes the handshake: only a live port's failure is news.
                quiet = superseded or self._stop.is_set() or self.state not in _LIVE
                (log.debug if quiet else log.warning)(
                    "compass %s: connect handshake failed: %s", self.name, e
                )
            except Exception:
                log.exception("compass %s: connect handshake crashed", self.name)

    def _handshake_due(self) -> bool:
        return self._generation != self._handshaken_gen or self._stop.is_set()

    def _handshake(self) -> None:
        version = self.command("VER")
        assert isinstance(version, VersionFrame)
        if self.rate_hz is not None:
            self.command("RATE", self.rate_hz)
        self.command("PAR", "GET")
        log.info(
            "compass %s: firmware %s, hardware %s, serial %s, rate %s Hz",
            self.name,
            version.firmware,
            version.hardware,
            version.serial,
            self.rate_hz if self.rate_hz is not None else "unchanged",
        )
