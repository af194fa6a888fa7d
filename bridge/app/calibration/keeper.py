"""The calibration in use, kept: saved at once, saved again as soon as storage takes it.

:class:`CalibrationKeeper` holds what the controller knows of the calibration in
use -- where it came from, when it was accepted, whether it is on disk -- and
saves it through the :class:`~bridge.app.calibration.store.CalibrationStore`. A save
that fails (a full, read-only or missing state directory) leaves the
calibration in force and *pending*: :meth:`CalibrationKeeper.retry` (the
controller's worker, every :data:`RETRY_S`) saves the newest pending one as
soon as the directory takes it again, so an accepted or learned calibration is
not lost on the next restart once space returns. Until then every status says
"NOT saved".

A calibration set value by value (the COMPASS_* parameters, one PARAM_SET each) is
*paced* as ``params.json`` is (:mod:`bridge.app.params`): saved at once, or -- within
:data:`PACE_S` of the last save -- kept pending and saved by the worker when that
second is over, so a storm of sets is a write a second, not one fsync each (they made
one write a set: 200 sets, 200 writes in 0.65 s). :meth:`CalibrationKeeper.flush`
saves a pending one at once (the bridge stopping).

:class:`StrayCalibration` notices a compass left in its own calibration mode
(the ``CAL`` flag on every frame) with no session of ours running it: an
on-board MAGCAL interrupted by an unplug, a lost link, a crash or an error.
The controller then sends ``MAGCAL,ABORT`` -- as soon as the device can hear
it (frames with the flag are coming, so it can) -- and at shutdown.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from bridge.app.calibration.store import CalibrationStore
from bridge.core.calibration import Calibration
from bridge.documents import StorageError
from bridge.events import Event, Severity
from bridge.protocol.device import CommandError

log = logging.getLogger(__name__)

#: A calibration not saved is tried again this often (seconds).
RETRY_S = 5.0
#: A paced calibration (set value by value) is saved at most this often (seconds).
PACE_S = 1.0
#: The CAL flag seen this long with no session of ours: the device was left calibrating.
STRAY_HOLD_S = 1.0
#: ``MAGCAL,ABORT`` for a stray calibration mode at most this often.
STRAY_RETRY_S = 5.0


@dataclass(frozen=True, slots=True)
class _Unsaved:
    calibration: Calibration
    source: str
    accepted_unix: float
    report: Mapping[str, Any] | None
    view: Mapping[str, float] | None


class CalibrationKeeper:
    """The calibration in use, its origin and whether it is saved (thread-safe).

    ``store`` None keeps nothing (no state directory): every save "fails" with
    that reason and is never retried.
    """

    def __init__(self, store: CalibrationStore | None, source: str = "") -> None:
        self._store = store
        self._lock = threading.Lock()
        self.source = source  #: where the calibration in use came from
        self.accepted_unix: float | None = None  #: when it was accepted (None: unknown)
        self.saved = False  #: it is on disk
        self.error = ""  #: why the last save failed
        self._unsaved: _Unsaved | None = None
        self._retry_at = math.inf
        self._saved_at = -math.inf  # the last save that worked (the clock of ``now``)
        self.paced = False  #: the pending one waits for its pace, not for storage
        if store is not None:
            stored = store.load()  # never raises
            if stored.stored:
                self.accepted_unix = stored.accepted_unix
                self.saved = True

    @property
    def pending(self) -> bool:
        """A calibration in use waits to be saved."""
        return self._unsaved is not None

    def retry_due(self, now: float) -> float:
        """When :meth:`retry` next has something to do (``inf``: nothing pending)."""
        return self._retry_at

    def keep(
        self,
        calibration: Calibration,
        *,
        source: str,
        accepted_unix: float,
        report: Mapping[str, Any] | None,
        view: Mapping[str, float] | None,
        now: float,
        paced: bool = False,
    ) -> str:
        """``calibration`` is the one in use from now on: save it; the error ("" if saved,
        or -- ``paced``, the last save less than :data:`PACE_S` ago -- if it waits for its
        pace: :attr:`paced` then)."""
        item = _Unsaved(calibration, source, accepted_unix, report, view)
        with self._lock:
            self.source, self.accepted_unix = source, accepted_unix
            if paced and now < self._saved_at + PACE_S and (self._unsaved is None or self.paced):
                self._unsaved, self._retry_at = item, self._saved_at + PACE_S
                # paced first: a status read between the two stores (no lock there) sees
                # "saving" or the saved one, never a storage error that did not happen
                self.paced, self.saved = True, False
                return ""
            return self._save(item, now)

    def retry(self, now: float) -> bool:
        """Save the pending one if it is due; True when storage took one it had refused."""
        with self._lock:
            item, failing = self._unsaved, not self.paced
            if item is None or now < self._retry_at:
                return False
            return not self._save(item, now) and failing

    def flush(self, now: float) -> None:
        """Save a calibration waiting for its pace now (the bridge stopping)."""
        with self._lock:
            if self._unsaved is not None and self.paced:
                self._save(self._unsaved, now)

    def _save(self, item: _Unsaved, now: float) -> str:
        if self._store is None:
            self.saved, self.error = False, "no state directory configured"
            self._unsaved, self._retry_at = None, math.inf  # nowhere to save it, ever
            return self.error
        try:
            self._store.save(
                item.calibration,
                source=item.source,
                accepted_unix=item.accepted_unix,
                report=item.report,
                view=item.view,
            )
        except StorageError as e:
            first = self._unsaved is None or self.paced
            self.saved, self.error, self.paced = False, str(e), False
            self._unsaved, self._retry_at = item, now + RETRY_S
            if first:
                log.error("calibration NOT saved (%s): retried every %.0f s", e, RETRY_S)
            return self.error
        self.saved, self.error, self.paced = True, "", False
        self._unsaved, self._retry_at, self._saved_at = None, math.inf, now
        return ""


def applied(source: str, error: str, paced: bool, *, stored: bool) -> tuple[list[Event], str]:
    """What a calibration applied says: its events and its outcome's words. ``error``: why
    it was not saved ("" if it was, or if ``paced``: its save waits for its pace);
    ``stored``: there is a state directory to save in (else no storage error to tell)."""
    data: dict[str, Any] = {"source": source, "saved": not error and not paced, "paced": paced}
    if paced:
        text, said = "Calibration accepted, saved within a second", " (saved within a second)"
        severity = Severity.INFO
    elif not error:
        text, severity, said = "Calibration accepted and saved", Severity.INFO, " and saved"
    else:
        text, said = "Calibration applied, NOT saved", f" but not saved: {error}"
        severity = Severity.WARNING
        data["error"] = error
    events = [Event("calibration.accepted", text, severity, data)]
    if error and stored:
        events.append(storage_error(error))
    return events, f"calibration applied{said}"


def storage_error(error: str) -> Event:
    """The event of a calibration storage refused (``error``: why)."""
    return Event(
        "calibration.storage_error", f"Calibration not saved: {error}", Severity.ERROR,
        {"error": error},
    )  # fmt: skip


class StrayCalibration:
    """Says when to abort a device calibration mode no session of ours runs (PURE: times in).

    :meth:`frame` takes every attitude frame's CAL flag and whether one of our
    sessions runs the device's MAGCAL now; it answers True when ``MAGCAL,ABORT``
    should go out: the flag has stayed on for :data:`STRAY_HOLD_S` with no
    session of ours (the frames of a session that just ended do not count),
    at most once per :data:`STRAY_RETRY_S` while it stays on.
    """

    def __init__(self) -> None:
        self._since: float | None = None
        self._sent_at = -math.inf
        self.last_cal_at = -math.inf  #: the last frame that carried the flag
        self.aborts = 0  #: aborts asked for

    def frame(self, cal: bool, ours: bool, now: float) -> bool:
        """One attitude frame; True: send ``MAGCAL,ABORT`` now."""
        if cal:
            self.last_cal_at = now
        if not cal or ours:
            self._since = None
            return False
        if self._since is None:
            self._since = now
        if now - self._since < STRAY_HOLD_S or now - self._sent_at < STRAY_RETRY_S:
            return False
        self._sent_at = now
        self.aborts += 1
        return True

    def abort(self, command: Callable[..., Any]) -> None:
        """``MAGCAL,ABORT`` through ``command`` (the controller's worker); a failure is
        retried by the next :meth:`frame` that asks for it."""
        log.warning(
            "compass is in its calibration mode (CAL flag) and no calibration runs: "
            "an interrupted on-board MAGCAL; aborting it (MAGCAL,ABORT)"
        )
        try:
            command("MAGCAL", "ABORT", retries=0)
        except CommandError as e:
            log.info("MAGCAL,ABORT of the left-over calibration mode: %s (tried again)", e)

    def calibrating(self, now: float) -> bool:
        """The device's frames carried the CAL flag a moment ago (at shutdown: abort it)."""
        return now - self.last_cal_at < STRAY_HOLD_S
