"""The compass link as a sans-I/O state machine: bytes and ``now`` in; frames, events out.

The mirror of the simulated firmware (:mod:`bridge.sim.firmware`): the caller
owns the port and the clock. It tells the machine what happened to the port
(:meth:`LinkMachine.opened`, :meth:`~LinkMachine.open_failed`,
:meth:`~LinkMachine.lost`, :meth:`~LinkMachine.end`), hands it the bytes it
read (:meth:`~LinkMachine.receive`, which returns the decoded frames) and
calls :meth:`~LinkMachine.tick` when :meth:`~LinkMachine.next_deadline` comes;
it takes out :meth:`~LinkMachine.take_events` -- :class:`Write` (bytes for the
port), :class:`ClosePort`, :class:`StateChanged` and :class:`Notice` (a log
line) -- and opens the port when :meth:`~LinkMachine.open_due`. The driver on
a real port is :class:`bridge.link.serial_link.CompassLink`; the tests' is
``tests/harness.py`` (the machine and the simulated firmware on one manual clock).

Link states (:class:`~bridge.protocol.device.LinkState`), each change reported once. Only
**attitude frames** count (``$PGMRA``; for a heading-only compass its heading
sentences): a compass that answers commands but streams nothing is not streaming.

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
late or stray answer, not a reset. After every (re)connect and every reset the
machine runs the connect handshake itself: ``VER``, ``RATE,<rate_hz>``,
``PAR,GET``.

Command transactions (GMR protocol only) are serialised; how an answer is matched
to its command, and a late answer kept from passing for a later command's, is
:mod:`bridge.protocol.transactions`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, Protocol, TypeAlias

from bridge.protocol.device import (
    CommandNotSupported,
    LinkCounters,
    LinkDown,
    LinkFrame,
    LinkState,
    Received,
)
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
from bridge.protocol.heading import HeadingDecoder, HeadingFrame
from bridge.protocol.transactions import (
    COMMAND_DEADLINES_S,
    DEFAULT_DEADLINE_S,
    Command,
    Routed,
    Transactions,
)

__all__ = [
    "COMMAND_DEADLINES_S",
    "DEFAULT_DEADLINE_S",
    "DEFAULT_LATE_ANSWER_WINDOW_S",
    "ClosePort",
    "Command",
    "LinkEvent",
    "LinkMachine",
    "LinkProtocol",
    "Notice",
    "StateChanged",
    "Write",
]

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

_LIVE = (LinkState.OPENING, LinkState.STREAMING)


# ---------------------------------------------------------------------------- events


@dataclass(frozen=True, slots=True)
class Write:
    """Bytes for the port. ``command``: the transaction whose attempt they are (the
    driver reports a failed write with :meth:`LinkMachine.write_failed`)."""

    data: bytes
    command: Command | None = None


@dataclass(frozen=True, slots=True)
class ClosePort:
    """Close the port (it went stale, was lost or has ended); reopen when open_due."""

    reason: str


@dataclass(frozen=True, slots=True)
class StateChanged:
    """The link's state changed (each change once)."""

    old: LinkState
    new: LinkState
    reason: str


@dataclass(frozen=True, slots=True)
class Notice:
    """Something worth a log line (``level``: a :mod:`logging` level)."""

    level: int
    message: str


LinkEvent: TypeAlias = Write | ClosePort | StateChanged | Notice


class _Decoder(Protocol):
    def feed(self, data: bytes) -> Sequence[LinkFrame]: ...

    def reset(self) -> None: ...


class LinkMachine:
    """The compass link's state, sequence tracking, handshake and command transactions.

    No I/O and no clock: see the module docstring for the calls and events.
    ``name`` is the port's name (for what it says); ``rate_hz`` the output
    rate the handshake asks for (None: leave the device's); ``stale_after``
    the silence after which the port is reopened.
    """

    def __init__(
        self,
        *,
        name: str = "compass",
        protocol: LinkProtocol = "gmr",
        rate_hz: int | None = 10,
        stale_after: float = 2.0,
        backoff_initial: float = 0.1,
        backoff_max: float = 2.0,
        late_answer_window: float = DEFAULT_LATE_ANSWER_WINDOW_S,
    ) -> None:
        if protocol not in ("gmr", "nmea", "os5000"):
            raise ValueError(f"protocol must be 'gmr', 'nmea' or 'os5000', got {protocol!r}")
        self._check_rate(rate_hz, stale_after)
        if not 0 < backoff_initial <= backoff_max:
            raise ValueError("need 0 < backoff_initial <= backoff_max")
        self.name = name
        self.protocol: LinkProtocol = protocol
        self._rate_hz = rate_hz
        self._stale_after = stale_after
        self._backoff_initial = backoff_initial
        self._backoff_max = backoff_max
        self._decoder: _Decoder = (
            GmrDecoder(direction="host") if protocol == "gmr" else HeadingDecoder(protocol)
        )
        self._events: list[LinkEvent] = []
        self._c: dict[str, int] = {
            f: 0 for f in LinkCounters.__dataclass_fields__ if f != "bad_lines"
        }
        self._state = LinkState.ABSENT
        # The port, as the driver reports it.
        self._started = False
        self._closed = False
        self._ended = False
        self._open = False
        self._opened_before = False
        self._interactive = True
        self._baud: int | None = None
        self._open_at = 0.0
        self._backoff = backoff_initial
        # The stream.
        self._last_attitude = 0.0  # when the last attitude frame came (or the port opened)
        self._last_frame = -float("inf")  # when the last frame of any kind came
        self._run_start: float | None = None  # first attitude frame of the current run
        self._run_frames = 0
        self._streaming_since = 0.0
        # Hysteresis: 0 -- two frames make a stream; else how many times
        # stale_after / _CONFIRM_DIVISOR attitude frames must keep coming (after short spells).
        self._confirm_factor = 0.0
        # Sequence tracking.
        self._last_seq: int | None = None
        self._restart_expected = False  # an unasked $PGMRV came: the next seq tells
        # Commands and the connect handshake.
        self._txns = Transactions(
            name=name,
            late_window=late_answer_window,
            count=self.count,
            debug=self._debug,
            warn=self._warn,
        )
        self._done: list[Command] = []
        #: Transactions ended so far (a driver wakes its command waiters when it moves).
        self.commands_ended = 0
        self._generation = 0
        self._handshake: Command | None = None  # the handshake's command in flight
        self._handshake_gen = 0  # the generation it serves
        self._handshaken_gen = 0  # the last generation a handshake was started for
        self._version: VersionFrame | None = None
        self._params: ParamsFrame | None = None

    @staticmethod
    def _check_rate(rate_hz: int | None, stale_after: float) -> None:
        if rate_hz is not None:
            CommandFrame.rate(rate_hz)  # ValueError for a rate the device does not offer
        if not stale_after > 0:
            raise ValueError(f"stale_after must be positive, got {stale_after}")

    # ------------------------------------------------------------------ what it knows

    @property
    def state(self) -> LinkState:
        """The current :class:`~bridge.protocol.device.LinkState`."""
        return self._state

    @property
    def counters(self) -> LinkCounters:
        """A snapshot of the counters."""
        dropped = getattr(getattr(self._decoder, "counters", None), "dropped", None)
        bad = dict(dropped.snapshot()) if dropped is not None else {}
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
    def rate_hz(self) -> int | None:
        """The output rate the handshake asks for (None: the device's own)."""
        return self._rate_hz

    @property
    def stale_after(self) -> float:
        """Seconds without an attitude frame after which the port is reopened."""
        return self._stale_after

    @property
    def is_open(self) -> bool:
        """The port is open (as the driver last reported)."""
        return self._open

    @property
    def quiet(self) -> bool:
        """Streaming, no command in flight or queued, nothing for the driver to do: the
        bytes may wait in the port's buffer a while (a driver reading in bursts)."""
        return (
            self._state is LinkState.STREAMING
            and not self._txns.busy
            and self._handshake is None
            and not self._events
        )

    @property
    def ended(self) -> bool:
        """The port has ended for good (a replay played to its end)."""
        return self._ended

    def count(self, name: str, n: int = 1) -> None:
        """Bump counter ``name`` (a :class:`~bridge.protocol.device.LinkCounters` field) by ``n``."""
        self._c[name] += n

    def take_events(self) -> list[LinkEvent]:
        """Everything the machine asks of its driver since the last call, in order."""
        events, self._events = self._events, []
        return events

    @property
    def has_events(self) -> bool:
        """Events are waiting for :meth:`take_events`."""
        return bool(self._events)

    def open_due(self, now: float) -> bool:
        """The driver should open the port now."""
        return (
            self._started
            and not (self._open or self._closed or self._ended)
            and now >= self._open_at
        )

    def next_deadline(self) -> float | None:
        """When the machine next needs :meth:`tick` (or the port opened); None: only on input."""
        if not self._started or self._closed or self._ended:
            return None
        due = self._last_attitude + self._stale_after if self._open else self._open_at
        txn = self._txns.next_deadline()
        return due if txn is None else min(due, txn)

    def default_timeout(self, cmd: CommandFrame, baud: int | None = None) -> float:
        """Per-attempt timeout for ``cmd``: datasheet deadline + line times at ``baud``."""
        deadline = COMMAND_DEADLINES_S.get(cmd.key, DEFAULT_DEADLINE_S)
        if baud is not None and baud > 0:
            # The device's clock starts when the command has arrived, and the answer must
            # still cross the wire: 10 bits per byte (8N1), a full line each way at worst.
            deadline += 2 * MAX_LINE_BYTES * 10 / baud
        return deadline

    # ------------------------------------------------------------------ inputs: the port

    def start(self, now: float) -> None:
        """The link starts: OPENING, and the port is due to be opened."""
        if self._started:
            raise RuntimeError("link already started")
        self._started = True
        self._open_at = now
        self._set_state(LinkState.OPENING, "starting")

    def opened(self, now: float, *, interactive: bool = True, baud: int | None = None) -> None:
        """The driver opened the port (``interactive``: bytes written reach a device;
        ``baud``: the line's speed, for the commands' deadlines)."""
        self._open = True
        self._interactive = interactive
        self._baud = baud
        if self._opened_before:
            self._c["reconnects"] += 1
        self._opened_before = True
        self._decoder.reset()  # a partial line from the old connection is not a bad line
        self._last_seq = None
        self._restart_expected = False
        self._last_attitude = now
        self._run_start = None
        if self._state is LinkState.ABSENT:
            self._set_state(LinkState.OPENING, "port open")
        self._new_generation(now)

    def open_failed(self, now: float, error: str) -> None:
        """The port could not be opened: ABSENT, retried after the backoff."""
        self._c["open_failures"] += 1
        self._debug(f"open failed: {error}")
        self._set_state(LinkState.ABSENT, error)
        self._retry_later(now)

    def lost(self, now: float, error: str) -> None:
        """A read failed: the port is gone (closed, ABSENT, retried after the backoff)."""
        self._close_port(f"port lost: {error}")
        self._set_state(LinkState.ABSENT, f"port lost: {error}")
        self._retry_later(now)
        self._pump(now)

    def end(self, now: float, why: str) -> None:
        """The port has ended for good (a replay's recording is played): ABSENT for good."""
        self._close_port(why)
        self._ended = True
        self._set_state(LinkState.ABSENT, why)
        self._pump(now)

    def close(self, now: float) -> None:
        """The link is closing: every command ends in LinkDown; no more opens."""
        self._closed = True
        self._close_port("link closed")
        self._txns.fail_all(LinkDown("link is closed"))
        self._handshake = None

    def write_failed(self, write: Write, error: str, now: float) -> None:
        """A :class:`Write` could not be written: its command ends in LinkDown."""
        if write.command is not None:
            self._txns.write_failed(write.command, f"{self.name}: write failed: {error}")
            self._done.append(write.command)
            self._pump(now)

    # ------------------------------------------------------------------ inputs: bytes, time

    def receive(self, data: bytes, now: float) -> list[Received]:
        """Bytes read at ``now``: the frames they complete (in order)."""
        c = self._c
        c["bytes_read"] += len(data)
        frames = self._decoder.feed(data)
        out: list[Received] = []
        if frames:
            self._last_frame = now
            before = c["attitude_frames"]
            answers = self._handle(frames, now, out)
            # Only attitude frames make a stream: command answers do not.
            n = c["attitude_frames"] - before
            if n:
                self._last_attitude = now
                if self._state is not LinkState.STREAMING:
                    if self._run_start is None:
                        self._run_start, self._run_frames = now, 0
                    self._run_frames += n
                    if self._run_frames >= 2 and now - self._run_start >= self._confirm_s():
                        self._set_state(LinkState.STREAMING)
                        self._streaming_since = now
                        self._backoff = self._backoff_initial
            if answers or self._generation != self._handshaken_gen:
                self._pump(now)  # an answer may end a command; a reset redoes the handshake
        if now >= self._last_attitude + self._stale_after and self._open:
            self._go_stale(now)
        return out

    def tick(self, now: float) -> None:
        """Time passes: staleness, command deadlines, retries and the handshake."""
        if self._open and now >= self._last_attitude + self._stale_after:
            self._go_stale(now)
        self._pump(now)

    # ------------------------------------------------------------------ inputs: commands

    def submit(self, cmd: CommandFrame, now: float, timeout: float, retries: int = 2) -> Command:
        """Queue a command transaction (``timeout``: per attempt); its :class:`Command`.

        Raises :class:`~bridge.protocol.device.CommandNotSupported` on a heading-only compass.
        """
        if self.protocol != "gmr":
            raise CommandNotSupported(
                f"protocol {self.protocol!r} is a heading-only compass: it takes no commands"
            )
        if retries < 0:
            raise ValueError("retries must be >= 0")
        if not timeout > 0:
            raise ValueError(f"timeout must be positive, got {timeout}")
        command = Command(cmd, encode(cmd), timeout, retries)
        self._txns.submit(command)
        self._pump(now)
        return command

    def set_rate(self, rate_hz: int | None, stale_after: float | None = None) -> None:
        """A new output rate (and silence limit) for the link, e.g. from a reload.

        The rate is asked of the device by the next connect handshake (a reload
        that changes it reopens the port); ``stale_after`` applies at once.
        """
        stale = self._stale_after if stale_after is None else stale_after
        self._check_rate(rate_hz, stale)
        self._rate_hz = rate_hz
        self._stale_after = stale

    # ------------------------------------------------------------------ internals

    def _debug(self, message: str) -> None:
        self._events.append(Notice(logging.DEBUG, f"compass {self.name}: {message}"))

    def _warn(self, message: str) -> None:
        self._events.append(Notice(logging.WARNING, f"compass {self.name}: {message}"))

    def _set_state(self, new: LinkState, reason: str = "") -> None:
        old = self._state
        if new is old:
            return
        self._state = new
        self._events.append(StateChanged(old, new, reason))

    def _close_port(self, reason: str) -> None:
        if self._open:
            self._open = False
            self._events.append(ClosePort(reason))
        self._run_start = None

    def _retry_later(self, now: float) -> None:
        self._open_at = now + self._backoff
        self._backoff = min(2 * self._backoff, self._backoff_max)

    def _confirm_s(self) -> float:
        """How long attitude frames must keep coming before the link says STREAMING."""
        return self._stale_after / _CONFIRM_DIVISOR * self._confirm_factor

    def _go_stale(self, now: float) -> None:
        self._c["stale_events"] += 1
        if self._state is LinkState.STREAMING:
            # A short spell between two silences: the next one must last longer.
            short = now - self._streaming_since < _FLAP_SPELLS * self._stale_after
            factor = min(2.0 * self._confirm_factor, _CONFIRM_MAX_FACTOR)
            self._confirm_factor = max(1.0, factor) if short else 0.0
        what = "attitude frame" if self.protocol == "gmr" else "heading sentence"
        why = f"no {what} for {self._stale_after:g} s"
        if now - self._last_frame <= self._stale_after:
            why += " (the compass answers, but streams nothing)"
        self._set_state(LinkState.STALE, f"{why}; reopening")
        self._close_port(why)
        self._retry_later(now)

    def _handle(self, frames: Sequence[LinkFrame], now: float, out: list[Received]) -> bool:
        """Count and track ``frames`` into ``out``; True if any was an answer-type frame."""
        c = self._c
        c["frames"] += len(frames)
        answers = False
        for frame in frames:
            if type(frame) is AttitudeFrame:
                # _track_seq's common case inline (per frame: a call costs more than this).
                last = self._last_seq
                c["attitude_frames"] += 1
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
                answers = True
            out.append(Received(frame, now))
        return answers

    def _route_answer(self, frame: GmrFrame, now: float) -> None:
        """An answer-type frame to the transactions; a reboot's $PGMRV to the seq tracking."""
        # Only a version nobody asked for lately, from a device already seen streaming on
        # this connection, may be a reset (a power-up announcement is not one we saw); the
        # next attitude frame's seq decides (see _track_seq).
        if self._txns.route(frame, now, self._done) is Routed.VERSION and (
            self._last_seq is not None
        ):
            self._restart_expected = True

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
                self._c["unsolicited_answers"] += 1
                self._debug("a $PGMRV nobody asked for; frames went on")
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
            self._c["lost_frames"] += gap
        else:
            self._c["seq_discontinuities"] += 1
            self._debug(f"seq jumped from {last} to {seq}")

    def _device_reset(self, why: str) -> None:
        """A reboot seen in the stream: this frame starts its new sequence."""
        self._c["device_resets"] += 1
        self._warn(f"device reset detected ({why})")
        # A rebooted device runs at 10 Hz again: the handshake (VER, RATE, PAR,GET) runs
        # again as after a reconnect. (The caller pumps after the frames.)
        self._generation += 1

    # -- commands and the handshake

    def _new_generation(self, now: float) -> None:
        self._generation += 1
        self._pump(now)

    def _handshake_pending(self) -> bool:
        return (
            self._generation != self._handshaken_gen
            and self.protocol == "gmr"
            and self._interactive
            and self._open
        )

    def _pump(self, now: float) -> None:
        """Move the transactions and the handshake on at ``now``."""
        for _ in range(8):  # each round ends a handshake step at most: bounded
            done = self._done
            if self._handshake is None and self._generation != self._handshaken_gen:
                if self._handshake_pending():
                    self._handshaken_gen = self._handshake_gen = self._generation
                    self._handshake = self._submit_internal("VER")
                elif not (self.protocol == "gmr" and self._interactive):
                    self._handshaken_gen = self._generation  # nothing to ask a replay
            for command in self._txns.pump(now, self._open, done):
                self._events.append(Write(command.line, command))
            if not done:
                return
            self._after_commands()

    def _submit_internal(self, name: str, *args: object) -> Command:
        cmd = CommandFrame(name, tuple(str(a) for a in args))
        command = Command(cmd, encode(cmd), self.default_timeout(cmd, self._baud), 2)
        self._txns.submit(command)
        return command

    def _after_commands(self) -> None:
        """Commands that ended: the handshake's next step (or its end)."""
        done, self._done = self._done, []
        self.commands_ended += len(done)
        hs = self._handshake
        if hs is None or hs not in done:
            return
        self._handshake = None
        superseded = self._generation != self._handshake_gen
        if hs.error is not None:
            # A port that died mid-handshake is already reported ABSENT/STALE, and the
            # next connection redoes the handshake: only a live port's failure is news.
            quiet = superseded or self._closed or self._state not in _LIVE
            (self._debug if quiet else self._warn)(f"connect handshake failed: {hs.error}")
            return
        if superseded:
            return  # the next round of _pump starts the new generation's handshake
        key = hs.cmd.key
        if key == "VER":
            if self._rate_hz is not None:
                self._handshake = self._submit_internal("RATE", self._rate_hz)
            else:
                self._handshake = self._submit_internal("PAR", "GET")
        elif key == "RATE":
            self._handshake = self._submit_internal("PAR", "GET")
        else:
            v = self._version
            rate = self._rate_hz if self._rate_hz is not None else "unchanged"
            if v is not None:
                self._events.append(
                    Notice(
                        logging.INFO,
                        f"compass {self.name}: firmware {v.firmware}, hardware {v.hardware}, "
                        f"serial {v.serial}, rate {rate} Hz",
                    )
                )
