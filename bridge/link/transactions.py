"""Command transactions on a GMR port: one command at a time, each answer matched to its command.

The device's answers carry no transaction id, so an answer is matched on its
command word (``$PGMRK,<word>``, ``$PGMRV`` for VER, ``$PGMRP`` for PAR,GET)
and its shape. Every attempt leaves an "expected answer" slot that lives for
the command's deadline plus ``late_window``: the time its answer may still
come from a device slower than its datasheet. Three rules follow:

* **An answer after the deadline is a time-out**, never a success and never
  news of something else (a reset): the caller gets :class:`~bridge.device.CommandLate`
  (a :class:`~bridge.device.CommandTimeout` carrying the answer), the link counts
  a time-out and a late answer.
* **No command is sent again while its answer may still come**: a retry goes
  out only once the previous attempt's slot has expired with no answer (the
  line was lost), so a late device never runs a command twice.
* **A late answer never passes for a later command's**: an answer that matches
  no current transaction consumes a slot and is counted as late, and a new
  command waits (bounded) until no slot of its command word is outstanding.
  The device answers commands in order, so slots are consumed oldest first.

:class:`Transactions` holds that bookkeeping; :class:`~bridge.link.serial_link.CompassLink`
owns the port, writes for it and hands it every answer-type frame its reader sees.
"""

from __future__ import annotations

import enum
import logging
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from bridge.device import CommandLate, CommandTimeout, LinkDown
from bridge.protocol.gmr import AckFrame, CommandFrame, GmrFrame, ParamsFrame, VersionFrame

log = logging.getLogger(__name__)

#: Datasheet answer deadlines that differ from the 200 ms default, by command key.
COMMAND_DEADLINES_S: Mapping[str, float] = {"MAGCAL,END": 0.5, "PAR,SET": 0.5, "ACCCAL": 1.5}
DEFAULT_DEADLINE_S = 0.2


class Routed(enum.Enum):
    """What became of an answer-type frame the reader handed to :meth:`Transactions.route`."""

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


@dataclass(slots=True)
class _Txn:
    cmd: CommandFrame
    answer: GmrFrame | None = None
    answered_at: float = 0.0
    deadline: float = float("inf")  #: the current attempt's deadline (clock seconds)


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

    ``write(line)`` sends on the port (raises :class:`LinkDown`), ``count(name)``
    bumps a link counter, ``stop`` is the link's closing flag. Commands run in the
    caller's thread; :meth:`route` runs in the link's reader thread.
    """

    def __init__(
        self,
        *,
        name: str,
        write: Callable[[bytes], None],
        count: Callable[[str], None],
        clock: Callable[[], float],
        late_window: float,
        stop: threading.Event,
    ) -> None:
        self._name = name
        self._write = write
        self._count = count
        self._clock = clock
        self._late_window = late_window
        self._stop = stop
        self._cmd_lock = threading.Lock()
        self._cond = threading.Condition()
        self._current: _Txn | None = None
        self._slots: list[_Slot] = []
        self._last_ver_sent = -float("inf")

    def wake(self) -> None:
        """Wake every waiting command (the link is closing)."""
        with self._cond:
            self._cond.notify_all()

    def run(self, cmd: CommandFrame, line: bytes, per_try: float, retries: int) -> GmrFrame:
        """Send ``line`` (``cmd`` encoded) until a matching answer comes; that answer.

        Raises :class:`CommandTimeout` after ``retries + 1`` unanswered attempts,
        :class:`CommandLate` when the answer came after the deadline (not resent), and
        :class:`LinkDown` when the port is not open or the link closes meanwhile.
        """
        with self._cmd_lock:
            self._wait_for_orphans(cmd.command)
            txn = _Txn(cmd)
            with self._cond:
                self._current = txn
            try:
                return self._transact(txn, line, per_try, retries)
            finally:
                with self._cond:
                    self._current = None

    def _wait_for_orphans(self, word: str) -> None:
        with self._cond:
            while True:
                if self._stop.is_set():
                    raise LinkDown("link is closed")
                now = self._clock()
                self._expire_slots(now)
                pending = [s.expires for s in self._slots if s.word == word]
                if not pending:
                    return
                self._cond.wait(max(0.0, max(pending) - now) + 0.001)

    def _transact(self, txn: _Txn, line: bytes, per_try: float, retries: int) -> GmrFrame:
        word = txn.cmd.command
        for attempt in range(retries + 1):
            if attempt:
                self._count("command_retries")
                log.debug("%s: no answer to %s, resending", self._name, txn.cmd.key)
            sent = self._clock()
            slot = _Slot(word, sent + per_try + self._late_window)
            with self._cond:
                # Registered before writing: the answer may beat the return of write().
                self._slots.append(slot)
                txn.deadline = sent + per_try
                if word == "VER":
                    self._last_ver_sent = sent
            try:
                self._write(line)
            except LinkDown:
                with self._cond:  # never sent: no answer can come for it
                    if slot in self._slots:
                        self._slots.remove(slot)
                raise
            self._count("commands_sent")
            # On time: an answer by the deadline.
            if self._wait(txn, txn.deadline):
                return self._answered(txn, per_try)
            if attempt == retries:
                break
            # Timed out. Its answer may still come until the slot expires: wait for that
            # before sending the command again (a late device must not run it twice).
            if self._wait(txn, slot.expires, until_gone=slot):
                return self._answered(txn, per_try)
        self._count("command_timeouts")
        raise CommandTimeout(f"no answer to {txn.cmd.key} after {retries + 1} attempt(s)")

    def _wait(self, txn: _Txn, end: float, until_gone: _Slot | None = None) -> bool:
        """Wait for ``txn``'s answer until ``end`` (or ``until_gone`` leaves the slots);
        True if it came. :class:`LinkDown` if the link closes meanwhile."""
        with self._cond:
            while txn.answer is None:
                if self._stop.is_set():
                    raise LinkDown("link closed while waiting for an answer")
                now = self._clock()
                if until_gone is not None:
                    self._expire_slots(now)
                    if until_gone not in self._slots:
                        break
                left = end - now
                if left <= 0:
                    break
                self._cond.wait(left)
            return txn.answer is not None

    def _answered(self, txn: _Txn, per_try: float) -> GmrFrame:
        """``txn``'s answer if it came by the deadline; :class:`CommandLate` otherwise."""
        assert txn.answer is not None
        late = txn.answered_at - txn.deadline
        if late <= 0:
            return txn.answer
        self._count("command_timeouts")
        log.warning(
            "%s: %s answered %.2f s late (deadline %.2f s): taken as a time-out",
            self._name,
            txn.cmd.key,
            late,
            per_try,
        )
        raise CommandLate(txn.cmd.key, txn.answer, late, per_try)

    def _expire_slots(self, now: float) -> None:
        if self._slots:
            self._slots = [s for s in self._slots if s.expires > now]

    def _take_slot(self, word: str) -> bool:
        for i, s in enumerate(self._slots):
            if s.word == word:
                del self._slots[i]
                return True
        return False

    def route(self, frame: GmrFrame, now: float) -> Routed:
        """Reader side: give an answer-type frame to the waiting command, or account for it."""
        word = answer_word(frame)
        if word is None:
            return Routed.NONE
        with self._cond:
            self._expire_slots(now)
            txn = self._current
            if txn is not None and txn.answer is None and matches(txn.cmd, frame):
                txn.answer, txn.answered_at = frame, now
                self._take_slot(word)
                self._cond.notify_all()
                if now > txn.deadline:
                    self._count("late_answers")
                    return Routed.LATE
                return Routed.ANSWER
            if self._take_slot(word):
                self._count("late_answers")
                log.debug("%s: late answer absorbed: %s", self._name, frame)
                self._cond.notify_all()  # a command may be waiting for this orphan
                return Routed.LATE
            ver_recently = now - self._last_ver_sent < (DEFAULT_DEADLINE_S + self._late_window)
        if isinstance(frame, VersionFrame):
            # A VER answer can be doubled by a power-up $PGMRV racing our VER on connect:
            # only a version nobody asked for lately is news (the link judges it).
            return Routed.DOUBLED if ver_recently else Routed.VERSION
        self._count("unsolicited_answers")
        log.debug("%s: unsolicited answer: %s", self._name, frame)
        return Routed.UNSOLICITED
