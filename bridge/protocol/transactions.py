"""Command transactions on a GMR port: one command at a time, each answer matched to its command.

Pure (no threads, no clock, no port): the link machine
(:class:`bridge.protocol.link.LinkMachine`) hands in ``now``, the answers it
decodes and the port's state, and takes out the lines to write.

The device's answers carry no transaction id, so an answer is matched on its
command word (``$PGMRK,<word>``, ``$PGMRV`` for VER, ``$PGMRP`` for PAR,GET)
and its shape. Every attempt leaves an "expected answer" slot that lives for
the command's deadline plus ``late_window``: the time its answer may still
come from a device slower than its datasheet. Three rules follow:

* **An answer after the deadline is a time-out**, never a success and never
  news of something else (a reset): the command ends with :class:`~bridge.protocol.device.CommandLate`
  (a :class:`~bridge.protocol.device.CommandTimeout` carrying the answer), the link counts
  a time-out and a late answer.
* **No command is sent again while its answer may still come**: a retry goes
  out only once the previous attempt's slot has expired with no answer (the
  line was lost), so a late device never runs a command twice.
* **A late answer never passes for a later command's**: an answer that matches
  no current transaction consumes a slot and is counted as late, and a new
  command waits until no slot of its command word is outstanding.
  The device answers commands in order, so slots are consumed oldest first.
"""

from __future__ import annotations

import enum
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from bridge.protocol.device import (
    CommandError,
    CommandLate,
    CommandRejected,
    CommandTimeout,
    LinkDown,
)
from bridge.protocol.gmr import AckFrame, CommandFrame, GmrFrame, ParamsFrame, VersionFrame

#: Datasheet answer deadlines that differ from the 200 ms default, by command key.
COMMAND_DEADLINES_S: Mapping[str, float] = {"MAGCAL,END": 0.5, "PAR,SET": 0.5, "ACCCAL": 1.5}
DEFAULT_DEADLINE_S = 0.2

#: (message) -> None: what a transaction has to say for the log (the link machine's notes).
Note = Callable[[str], None]


class Routed(enum.Enum):
    """What became of an answer-type frame handed to :meth:`Transactions.route`."""

    ANSWER = "answer"  #: the current command's answer
    LATE = "late"  #: an answer to an attempt that had timed out (absorbed)
    VERSION = "version"  #: a $PGMRV nobody asked for lately (a reboot announces itself so)
    UNSOLICITED = "unsolicited"  #: an ack nobody was waiting for
    DOUBLED = "doubled"  #: a $PGMRV just after our VER (a power-up one racing the answer)
    NONE = "none"  #: not an answer-type frame


@dataclass(slots=True, eq=False)  # compared by identity: each is one attempt
class _Slot:
    word: str  # the answer's command word ("VER" for $PGMRV, "PAR" for $PGMRP)
    expires: float


class _Phase(enum.Enum):
    QUEUED = "queued"  # waiting for its turn (or for a late answer of its word)
    SEND = "send"  # an attempt is to be written
    ANSWER = "answer"  # written; its answer may come on time until ``deadline``
    SLOT = "slot"  # timed out; its answer may still come until the slot expires
    DONE = "done"


class Command:
    """One command transaction: what :meth:`LinkMachine.submit` returns.

    ``done`` turns True once it has ended; :meth:`result` is then the answer
    frame, or raises the :class:`~bridge.protocol.device.CommandError` it ended with.
    """

    __slots__ = (
        "_phase",
        "_slot",
        "answer",
        "answered_at",
        "attempts",
        "cmd",
        "deadline",
        "error",
        "line",
        "per_try",
        "retries",
    )

    def __init__(self, cmd: CommandFrame, line: bytes, per_try: float, retries: int) -> None:
        self.cmd = cmd
        self.line = line
        self.per_try = per_try
        self.retries = retries
        self.attempts = 0  #: attempts written
        self.answer: GmrFrame | None = None
        self.answered_at = 0.0
        self.deadline = float("inf")  #: the current attempt's deadline (clock seconds)
        self.error: CommandError | None = None
        self._phase = _Phase.QUEUED
        self._slot: _Slot | None = None

    @property
    def done(self) -> bool:
        """The transaction has ended (answered, rejected, timed out or failed)."""
        return self._phase is _Phase.DONE

    def result(self) -> GmrFrame:
        """The answer; raises the error the transaction ended with (RuntimeError if running)."""
        if self._phase is not _Phase.DONE:
            raise RuntimeError(f"{self.cmd.key} has not ended yet")
        if self.error is not None:
            raise self.error
        assert self.answer is not None
        return self.answer

    def __repr__(self) -> str:
        return f"Command({self.cmd.key}, {self._phase.value}, attempts={self.attempts})"


def answer_word(frame: object) -> str | None:
    """The command word a frame answers (None for frames that answer nothing)."""
    if isinstance(frame, AckFrame):
        return frame.command
    if isinstance(frame, VersionFrame):
        return "VER"
    if isinstance(frame, ParamsFrame):
        return "PAR"
    return None


def matches(cmd: CommandFrame, frame: GmrFrame) -> bool:
    """Whether ``frame`` can be the answer to ``cmd`` (stricter than the codec's is_answer).

    ERR answers carry only the command word, so any ERR with the right word
    matches; OK answers must also have the shape the datasheet gives the
    sub-command (RATE echoes the rate, MAGCAL,END has six results, START/ABORT
    none, PAR,SET is acked while PAR,GET is answered by $PGMRP).
    """
    if not cmd.is_answer(frame):
        return False
    if not isinstance(frame, AckFrame) or not frame.ok:
        return True
    key = cmd.key
    if key == "RATE":
        return frame.fields == cmd.args
    if key == "MAGCAL,END":
        return len(frame.fields) == 6
    if key in ("MAGCAL,START", "MAGCAL,ABORT"):
        return not frame.fields
    return key != "PAR,GET"  # PAR,GET is answered by $PGMRP, never by an OK ack


class Transactions:
    """Serialised command transactions with late-answer slots (see the module docstring).

    ``count(name, n)`` bumps a link counter; ``debug`` / ``warn`` take what is
    worth a log line. :meth:`submit` queues a command; :meth:`pump` moves the
    queue on at ``now`` and returns the lines to write; :meth:`route` takes an
    answer-type frame.
    """

    def __init__(
        self,
        *,
        name: str,
        late_window: float,
        count: Callable[[str, int], None],
        debug: Note,
        warn: Note,
    ) -> None:
        self._name = name
        self._late_window = late_window
        self._count = count
        self._debug = debug
        self._warn = warn
        self._queue: deque[Command] = deque()
        self._current: Command | None = None
        self._slots: list[_Slot] = []
        self._last_ver_sent = -float("inf")
        self._orphan_wait = float("inf")  # when the queue's head may go (a late answer's slot)

    @property
    def busy(self) -> bool:
        """A command is running or queued."""
        return self._current is not None or bool(self._queue)

    def submit(self, command: Command) -> None:
        """Queue ``command`` (it runs after those queued before it)."""
        self._queue.append(command)

    def fail_all(self, error: CommandError) -> list[Command]:
        """End every running and queued command with ``error``; the commands ended."""
        ended = []
        if self._current is not None:
            ended.append(self._current)
            self._finish(self._current, error)
        while self._queue:
            c = self._queue.popleft()
            self._finish(c, error)
            ended.append(c)
        return ended

    def write_failed(self, command: Command, error: str) -> None:
        """``command``'s last attempt was never written (the port failed): it ends in LinkDown."""
        if command.done:
            return
        if command._slot in self._slots:
            self._slots.remove(command._slot)  # never sent: no answer can come for it
        self._count("commands_sent", -1)
        self._finish(command, LinkDown(error))

    def next_deadline(self) -> float | None:
        """When :meth:`pump` next has something to do on its own (None: nothing pending)."""
        c = self._current
        if c is not None:
            if c._phase is _Phase.ANSWER:
                return c.deadline
            if c._phase is _Phase.SLOT and c._slot is not None:
                return c._slot.expires
            return None
        if self._queue:
            return self._orphan_wait
        return None

    def pump(self, now: float, can_write: bool, done: list[Command]) -> list[Command]:
        """Move the transactions on at ``now``: the commands whose ``line`` is to be written.

        ``can_write`` is False while the port is closed (an attempt due then
        ends in :class:`LinkDown`). Commands that end are appended to ``done``.
        """
        out: list[Command] = []
        while True:
            c = self._current
            if c is None:
                if not self._queue:
                    return out
                head = self._queue[0]
                # A late answer of this word may still come: it must not pass for this
                # command's, so the command waits until no slot of its word is left.
                self._expire_slots(now)
                word = head.cmd.command
                pending = [s.expires for s in self._slots if s.word == word]
                if pending:
                    self._orphan_wait = max(pending)
                    return out
                self._orphan_wait = float("inf")
                self._queue.popleft()
                self._current = c = head
                c._phase = _Phase.SEND
            if c._phase is _Phase.SEND:
                if c.attempts:
                    self._count("command_retries", 1)
                    self._debug(f"no answer to {c.cmd.key}, resending")
                if not can_write:
                    self._finish(c, LinkDown(f"{self._name} is not open"))
                    done.append(c)
                    continue
                word = c.cmd.command
                slot = _Slot(word, now + c.per_try + self._late_window)
                self._slots.append(slot)
                c._slot = slot
                c.deadline = now + c.per_try
                if word == "VER":
                    self._last_ver_sent = now
                c.attempts += 1
                self._count("commands_sent", 1)
                c._phase = _Phase.ANSWER
                out.append(c)
                return out
            if c._phase is _Phase.ANSWER:
                if now < c.deadline:
                    return out
                if c.attempts > c.retries:
                    self._count("command_timeouts", 1)
                    self._finish(
                        c,
                        CommandTimeout(f"no answer to {c.cmd.key} after {c.attempts} attempt(s)"),
                    )
                    done.append(c)
                    continue
                # Timed out. Its answer may still come until the slot expires: wait for that
                # before sending the command again (a late device must not run it twice).
                c._phase = _Phase.SLOT
            if c._phase is _Phase.SLOT:
                self._expire_slots(now)
                if c._slot in self._slots:
                    return out
                c._phase = _Phase.SEND

    def _finish(self, c: Command, error: CommandError | None) -> None:
        c.error = error
        c._phase = _Phase.DONE
        if self._current is c:
            self._current = None

    def _answered(self, c: Command, frame: GmrFrame, now: float) -> None:
        """``c``'s answer came: success, or :class:`CommandLate` / :class:`CommandRejected`."""
        c.answer, c.answered_at = frame, now
        late = now - c.deadline
        if late > 0:
            self._count("command_timeouts", 1)
            self._warn(
                f"{c.cmd.key} answered {late:.2f} s late (deadline {c.per_try:.2f} s): "
                "taken as a time-out"
            )
            self._finish(c, CommandLate(c.cmd.key, frame, late, c.per_try))
        elif isinstance(frame, AckFrame) and not frame.ok:
            self._count("command_rejections", 1)
            reason = frame.fields[0] if frame.fields else "?"
            self._finish(c, CommandRejected(c.cmd.key, reason, frame))
        else:
            self._finish(c, None)

    def _expire_slots(self, now: float) -> None:
        if self._slots:
            self._slots = [s for s in self._slots if s.expires > now]

    def _take_slot(self, word: str) -> bool:
        for i, s in enumerate(self._slots):
            if s.word == word:
                del self._slots[i]
                return True
        return False

    def route(self, frame: GmrFrame, now: float, done: list[Command]) -> Routed:
        """An answer-type frame: the running command's answer, or accounted for.

        A command that ends with it is appended to ``done``.
        """
        word = answer_word(frame)
        if word is None:
            return Routed.NONE
        self._expire_slots(now)
        c = self._current
        if c is not None and c._phase in (_Phase.ANSWER, _Phase.SLOT) and matches(c.cmd, frame):
            self._take_slot(word)
            late = now > c.deadline
            if late:
                self._count("late_answers", 1)
            self._answered(c, frame, now)
            done.append(c)
            return Routed.LATE if late else Routed.ANSWER
        if self._take_slot(word):
            self._count("late_answers", 1)
            self._debug(f"late answer absorbed: {frame}")
            self._orphan_wait = now  # the command waiting for this orphan may go
            return Routed.LATE
        if isinstance(frame, VersionFrame):
            # A VER answer can be doubled by a power-up $PGMRV racing our VER on connect:
            # only a version nobody asked for lately is news (the link judges it).
            ver_recently = now - self._last_ver_sent < (DEFAULT_DEADLINE_S + self._late_window)
            return Routed.DOUBLED if ver_recently else Routed.VERSION
        self._count("unsolicited_answers", 1)
        self._debug(f"unsolicited answer: {frame}")
        return Routed.UNSOLICITED
