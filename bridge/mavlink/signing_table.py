"""The signing replay table kept in the state directory, so a replay stays a replay across
a restart.

:class:`~bridge.mavlink.signing.Signing` keeps, per signed stream, the newest timestamp it
has accepted; a packet captured on the wire and sent again later is refused because its
timestamp is not newer. That table lives in memory. :class:`SigningTable` keeps it in the
state directory (the document :data:`SIGNING_DOCUMENT`, ``<storage.dir>/signing.json``):

* **restored** when the MAVLink output starts;
* **written ahead** of every signed command or parameter set that is obeyed
  (:meth:`SigningTable.save` before the command runs), so a copy of it replayed after a
  restart is refused too;
* **saved at most every** :data:`SAVE_EVERY_S` for the other valid signed traffic (the
  autopilot's position and attitude), by the output's telemetry thread
  (:attr:`SigningTable.save_due`), and once more when the output closes.

A save that fails is logged once (until one succeeds again) and tried again a period later,
not at once: a full or read-only disk must not cost a write per packet.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

from bridge.documents import DocumentStore, StorageError
from bridge.mavlink.signing import Signing

log = logging.getLogger(__name__)

#: Name of the signing replay table in the state directory (``<storage.dir>/signing.json``).
SIGNING_DOCUMENT = "signing"
#: Other valid signed traffic (positions, attitude) is saved at most this often, seconds.
SAVE_EVERY_S = 10.0


class SigningTable:
    """When and how the replay table of ``signing`` goes to ``documents`` (see the module
    docstring). Without a key (``signing`` None) or a state directory (``documents`` None)
    there is nothing to keep, and every method does nothing. Not thread-safe by itself:
    the output's dispatch thread marks and writes ahead, its telemetry thread saves on the
    period, as before; a save is one whole document write."""

    def __init__(
        self,
        signing: Signing | None,
        documents: DocumentStore | None,
        clock: Callable[[], float],
    ) -> None:
        self.signing = signing
        self.documents = documents
        self.clock = clock
        self.dirty = False  #: valid signed packets since the table was last saved
        self._saved_at = -math.inf  # or last tried, when that failed
        self._failed = False

    def restore(self) -> None:
        """Load the table saved by the last run (a damaged document is logged and skipped:
        the table then starts empty, as on a first run)."""
        if self.signing is None or self.documents is None:
            return
        loaded = self.documents.load(SIGNING_DOCUMENT)
        for p in loaded.problems:
            log.warning("mavlink: stored signing state: %s", p)
        n = self.signing.restore(loaded.payload)
        if n:
            log.info("mavlink: %d signed streams restored: replays stay refused", n)

    def mark(self) -> bool:
        """A valid signed packet changed the table. True when it was clean until now: the
        caller then wakes the thread that saves it (:attr:`save_due` moved)."""
        if self.dirty:
            return False
        self.dirty = True
        return True

    @property
    def save_due(self) -> float:
        """When the table is saved next (clock seconds; +inf: nothing new to save)."""
        return self._saved_at + SAVE_EVERY_S if self.dirty else math.inf

    def save(self) -> None:
        """Write the table now (before an obeyed command; when :attr:`save_due` comes; on
        close)."""
        if self.signing is None or self.documents is None:
            self.dirty = False  # nowhere to keep it: nothing to come back for
            return
        try:
            self.documents.save(SIGNING_DOCUMENT, self.signing.snapshot())
        except StorageError as e:
            if not self._failed:
                log.error(
                    "mavlink: signing replay table not saved (%s): a packet captured now "
                    "could be replayed after a restart",
                    e,
                )
            self._failed = True
            self._saved_at = self.clock()  # tried: again a period later, not at once
            return
        self.dirty = False
        self._failed = False
        self._saved_at = self.clock()
