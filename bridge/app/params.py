"""The parameter store: the bridge's one table of parameters, its persistence and effects.

Every front end reads and sets parameters here (MAVLink's parameter protocol,
Zenoh's ``params`` query, the status tools). A value set is validated by the
parameter's own type and range (:mod:`bridge.app.paramspec`), applied (the
calibration group becomes a calibration, COMPASS_DEC / COMPASS_AUTODEC the
declination, AHRS_ORIENTATION the mounting, BRG_*_TOL the quality limits,
BRG_HDG_REF the published heading), saved, and announced to subscribers --
or refused with a reason, changing nothing.

Persistence: ``<storage.dir>/params.json`` holds only the values set by a user
(``{"set": {name: value}}``), so the configuration file's defaults stay in
charge of everything else. The calibration group is not stored there: it is a
view of the calibration, which lives in the calibration store (with the
values as a user set them, so they read back as written).

Writes are **coalesced**: a value set is in force at once and saved by the
store's saver thread at most once per :data:`SAVE_INTERVAL_S` (a storm of
PARAM_SETs is one write a second, not one fsync per SET: an SD card's wear);
an explicit save (PREFLIGHT_STORAGE's, :meth:`ParamStore.save_then`) writes at once
if the last write is older than that, else is told when the saver's paced write is
done -- MAVLink's dispatch never waits for it. A write that fails is tried
again every interval until it succeeds -- said once when it fails
(``params.storage_error``) and once when it works again (``params.saved``) --
and :meth:`ParamStore.close` (the bridge stopping) writes what is pending, so
nothing set is lost.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from bridge.app.paramspec import (
    CAL_PARAMS,
    ParamSpec,
    ParamTable,
    SetOutcome,
    limits_from_values,
    mounting_from_values,
    same_calibration,
)
from bridge.app.settings import EngineSettings, SettingsChange
from bridge.core.calibration import Calibration
from bridge.documents import DocumentStore, StorageError
from bridge.events import ChangeRefusedError, Event, EventBus, Severity, Subscribers

log = logging.getLogger(__name__)

#: Name of the parameter document in the state directory (``<storage.dir>/params.json``).
PARAMS_DOCUMENT = "params"
#: ``source`` of a calibration made from the calibration group's parameters.
PARAMETERS = "parameters"
#: Parameter writes at most this often (seconds): see the module docstring.
SAVE_INTERVAL_S = 1.0

#: Applies a calibration made from parameters: (calibration, the values as set) -> a
#: problem text ("" when applied; it is then saved by the calibration store).
ApplyCalibration = Callable[[Calibration, Mapping[str, float]], str]


@dataclass(frozen=True, slots=True)
class ParamChange:
    """Parameters whose values changed, and who changed them."""

    names: tuple[str, ...]
    source: str


Listener = Callable[[ParamChange], None]


class ParamStore:
    """The bridge's parameters (thread-safe; see the module docstring).

    ``defaults`` are the configuration's values for parameters it sets;
    ``apply_calibration`` applies a calibration built from the calibration
    group (the calibration controller's ``apply_calibration``: engine,
    calibration store, events); ``stored_view`` the calibration group as last
    set by a user, when it still describes the calibration in use; ``events``
    hears of a save that failed and of the one that worked again.
    """

    def __init__(
        self,
        settings: EngineSettings,
        documents: DocumentStore | None,
        *,
        defaults: Mapping[str, float] | None = None,
        apply_calibration: ApplyCalibration | None = None,
        stored_view: Mapping[str, float] | None = None,
        events: EventBus | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._settings = settings
        self._events = events
        self._clock = clock
        self._save_lock = threading.Lock()  # one write at a time (the saver or save())
        self._wake = threading.Condition()
        self._dirty = False  # values in use that params.json does not hold yet
        self._last_write = -math.inf
        self._saver: threading.Thread | None = None
        self._closed = False
        self.writes = 0  #: params.json writes attempted
        self._waiting: list[Callable[[bool], None]] = []  # save_then's, answered by the next write
        self._told: list[tuple[Callable[[bool], None], bool]] = []  # ... answered, to call
        self._documents = documents
        self._defaults = dict(defaults or {})
        self._apply_calibration = apply_calibration
        self._lock = threading.RLock()
        self._listeners: Subscribers[ParamChange] = Subscribers()
        self._table = ParamTable(overrides=self._defaults)
        self._user_set: set[str] = set()
        self._own_calibration: Calibration | None = None  # the last one made from parameters
        #: why the last save failed ("" after a good one)
        self.last_error = "" if documents is not None else "no state directory configured"
        self._load(stored_view)
        settings.subscribe(self._on_settings)

    # -- reading -------------------------------------------------------------------

    @property
    def specs(self) -> tuple[ParamSpec, ...]:
        """Every parameter, in index order."""
        return self._table.specs

    def __len__(self) -> int:
        return len(self._table)

    def spec(self, name: str) -> ParamSpec | None:
        """The spec of ``name`` (None if unknown)."""
        return self._table.spec(name)

    def index(self, name: str) -> int:
        """The index of ``name`` (``KeyError`` if unknown)."""
        return self._table.index(name)

    def get(self, name: str) -> float:
        """The value of ``name`` (``KeyError`` if unknown)."""
        with self._lock:
            return self._table.get(name)

    def values(self) -> dict[str, float]:
        """All values by name (a copy)."""
        with self._lock:
            return self._table.values()

    def by_index(self, index: int) -> tuple[ParamSpec, float]:
        """(spec, value) at ``index`` (``IndexError`` if out of range)."""
        with self._lock:
            return self._table.by_index(index)

    def subscribe(self, fn: Listener) -> Callable[[], None]:
        """Call ``fn(change)`` after values change (in the changing thread); returns the
        unsubscribe function. ``fn`` must be quick and must not raise."""
        return self._listeners.add(fn)

    # -- setting -------------------------------------------------------------------

    def set(self, name: str, value: float, source: str = "PARAM_SET") -> SetOutcome:
        """Validate, apply and save one value; on refusal nothing changes.

        The outcome's ``reason`` says why a value was refused; a value that was
        applied but could not be saved is accepted (it is in force) and the
        problem is in :attr:`last_error` (an event tells the operator).
        """
        with self._lock:
            old = self._table.get(name) if self._table.spec(name) is not None else math.nan
            outcome = self._table.set(name, value)
            if not outcome.accepted or outcome.value == old:
                return outcome
            reason = self._apply(name)
            if reason:
                self._table.restore(name, old)
                assert outcome.spec is not None
                return SetOutcome(False, outcome.spec, outcome.index, old, reason)
            if name not in CAL_PARAMS:
                self._user_set.add(name)
                self._changed()
        self._notify((name,), source)
        return outcome

    def reset(self, source: str = "reset") -> None:
        """Every parameter but the calibration group and the declination back to its default."""
        with self._lock:
            changed = []
            for spec in self._table.specs:
                if spec.group == "cal" or spec.read_only or spec.name == "COMPASS_DEC":
                    continue
                default = self._table.defaults[spec.name]
                if self._table.get(spec.name) != default:
                    self._table.restore(spec.name, default)
                    changed.append(spec.name)
            self._user_set.clear()
            self._apply_all(source)
            self._changed()  # written by the saver, paced; PREFLIGHT_STORAGE asks save_then
        if changed:
            self._notify(tuple(changed), source)

    def reload(self, source: str = "reload") -> None:
        """Back to the stored values (what PREFLIGHT_STORAGE "read" means).

        What was set is what is stored: with a write pending, the saver's next write puts
        the values set in use into params.json, so those are read back as they are (not the
        file's older ones), without waiting for that write."""
        with self._lock:
            before = self._table.values()
            pending = (
                {n: before[n] for n in self._user_set if n not in CAL_PARAMS}
                if self._dirty
                else None
            )
            self._table = ParamTable(overrides=self._defaults)
            self._user_set.clear()
            self._load(None, pending)
            self._apply_all(source)
            after = self._table.values()
        changed = tuple(n for n in after if after[n] != before[n])
        if changed:
            self._notify(changed, source)

    @property
    def saved(self) -> bool:
        """The stored values are the values in use (nothing pending, the last write worked)."""
        return not self._dirty and not self.last_error

    def save_then(self, done: Callable[[bool], None]) -> bool | None:
        """Save without waiting: True or False (:attr:`last_error`) when the values in use
        are now stored -- already, or written at once -- or None when the last write was
        less than :data:`SAVE_INTERVAL_S` ago: the saver's paced write (or any write before
        it) then calls ``done(ok)`` from its thread. PREFLIGHT_STORAGE's, from MAVLink's
        dispatch, which must not be held for the rest of the interval."""
        with self._save_lock:
            if self.writes and self.saved:
                return True
            if self._last_write + SAVE_INTERVAL_S - self._clock() <= 0 or self._closed:
                ok = self._write()
            else:
                self._waiting.append(done)  # dirty: the saver writes when the interval ends
                return None
        self._tell()
        return ok

    def close(self) -> None:
        """Stop the saver; what is pending is written now (the bridge stops)."""
        with self._wake:
            self._closed = True
            self._wake.notify_all()
        saver = self._saver
        if saver is not None and saver is not threading.current_thread():
            saver.join(5.0)
        if self._dirty:
            with self._save_lock:
                self._write()
        self._tell()

    def _changed(self) -> None:
        """A value to store: the saver writes it within :data:`SAVE_INTERVAL_S` (lock held)."""
        self._dirty = True
        if self._documents is None:
            return
        with self._wake:
            if self._saver is None and not self._closed:
                self._saver = threading.Thread(
                    target=self._save_loop, name="params-saver", daemon=True
                )
                self._saver.start()
            self._wake.notify_all()

    def _save_loop(self) -> None:
        while True:
            with self._wake:
                self._wake.wait_for(lambda: self._dirty or self._closed)
                if self._closed:
                    return
                # Coalesce: whatever more is set until the interval is over goes in this write.
                left = self._last_write + SAVE_INTERVAL_S - self._clock()
                if left > 0 and self._wake.wait_for(lambda: self._closed, left):
                    return
            with self._save_lock:  # save_then may have written meanwhile: paced all the same
                if self._dirty and self._clock() - self._last_write >= SAVE_INTERVAL_S:
                    self._write()
            self._tell()

    def _write(self) -> bool:
        """One write of params.json (the save lock held). It holds every value set before it,
        so its result answers the save_then callers waiting (told by :meth:`_tell`, once the
        save lock is let go: they send acks)."""
        waiting, self._waiting = self._waiting, []
        ok = self._write_document()
        self._told.extend((fn, ok) for fn in waiting)
        return ok

    def _tell(self) -> None:
        """Call the save_then callbacks that a write answered (no lock of the store held)."""
        with self._save_lock:
            told, self._told = self._told, []
        for fn, ok in told:
            try:
                fn(ok)
            except Exception:  # a caller's bug must not stop the saver
                log.exception("parameters: a save_then callback failed")

    def _write_document(self) -> bool:
        with self._lock:
            if self._documents is None:
                self.last_error = "no state directory configured"
                return False
            values = self._table.values()
            payload: dict[str, Any] = {
                "set": {n: values[n] for n in sorted(self._user_set) if n not in CAL_PARAMS}
            }
            self._dirty = False
            self._last_write = self._clock()
            self.writes += 1
            failing = bool(self.last_error)
            try:
                self._documents.save(PARAMS_DOCUMENT, payload)
            except StorageError as e:
                self._dirty, self.last_error = True, str(e)  # tried again next interval
                if not failing:
                    log.error(
                        "parameters not saved: %s (tried again every %g s)", e, SAVE_INTERVAL_S
                    )
                    self._emit("params.storage_error", "Parameters NOT saved", Severity.ERROR, e)
                return False
            self.last_error = ""
        if failing:
            log.warning("parameters saved: the state directory takes them again")
            self._emit("params.saved", "Parameters saved (storage is back)", Severity.NOTICE)
        return True

    def _emit(self, kind: str, text: str, severity: Severity, error: object = None) -> None:
        if self._events is not None:
            data = {"error": str(error)} if error is not None else {}
            self._events.emit(Event(kind, text, severity, data))

    # -- effects -------------------------------------------------------------------

    def _apply(self, name: str) -> str:
        """The effect of a changed value; a non-empty reason undoes the change."""
        spec = self._table.spec(name)
        assert spec is not None
        values = self._table.values()
        settings = self._settings
        group = spec.group
        if group == "cal":
            try:
                cal = Calibration.from_ardupilot_parameters(values, settings.calibration.accel)
            except ValueError as e:
                return f"the calibration it gives is unusable ({e})"
            if self._apply_calibration is None:
                return "no calibration controller to apply it"
            view = {n: values[n] for n in CAL_PARAMS}
            self._own_calibration = cal  # the values stay as the user set them
            problem = self._apply_calibration(cal, view)
            if problem:
                self._own_calibration = None
                return problem
        elif group in ("dec", "mount"):
            try:
                if group == "dec":
                    self._apply_declination(PARAMETERS)
                else:
                    settings.set_mounting(mounting_from_values(values), PARAMETERS)
            except ChangeRefusedError as e:  # a heading guard (an armed autopilot fed by us)
                return str(e)
        elif group == "limits":
            try:
                limits = limits_from_values(values, settings.limits)
            except ValueError as e:
                return str(e)
            settings.set_limits(limits, PARAMETERS)
        elif group == "heading":
            settings.set_heading_reference(
                "true" if values["BRG_HDG_REF"] else "magnetic", PARAMETERS
            )
        return ""

    def _apply_declination(self, source: str) -> None:
        """COMPASS_AUTODEC=1: the model's declination (shown in COMPASS_DEC); 0: COMPASS_DEC."""
        if self._table.get("COMPASS_AUTODEC") != 0:
            self._settings.set_declination(None, source)
            self._show_wmm_declination()
        else:
            self._settings.set_declination(math.degrees(self._table.get("COMPASS_DEC")), source)

    def _show_wmm_declination(self) -> bool:
        wmm = self._settings.wmm_declination_deg
        if wmm is None or self._table.get("COMPASS_AUTODEC") == 0:
            return False
        before = self._table.get("COMPASS_DEC")
        self._table.put("COMPASS_DEC", math.radians(wmm))
        return self._table.get("COMPASS_DEC") != before

    def _apply_all(self, source: str) -> None:
        """Bring the engine in line with every parameter (at start, after a reset or reload)."""
        values = self._table.values()
        s = self._settings
        try:
            s.set_mounting(mounting_from_values(values), source)
        except ChangeRefusedError as e:
            log.warning("parameters: mounting not changed: %s", e)
        s.set_limits(limits_from_values(values, s.limits), source)
        s.set_heading_reference("true" if values["BRG_HDG_REF"] else "magnetic", source)
        try:
            self._apply_declination(source)
        except ChangeRefusedError as e:
            log.warning("parameters: declination not changed: %s", e)

    def _on_settings(self, change: SettingsChange) -> None:
        """A change made elsewhere (a fit, a position): show it in the parameters."""
        changed: list[str] = []
        with self._lock:
            if change.aspect == "calibration":
                cal = self._settings.calibration
                if self._own_calibration is not None and cal is self._own_calibration:
                    return  # made from our own values: they stay as set
                self._own_calibration = None
                before = {n: self._table.get(n) for n in CAL_PARAMS}
                for n, v in cal.ardupilot_parameters().items():
                    self._table.put(n, v)
                changed = [n for n in CAL_PARAMS if self._table.get(n) != before[n]]
            elif change.aspect == "reference" and self._show_wmm_declination():
                changed = ["COMPASS_DEC"]
        if changed:
            self._notify(tuple(changed), change.source)

    def _notify(self, names: tuple[str, ...], source: str) -> None:
        change = ParamChange(names, source)
        for fn in self._listeners:
            try:
                fn(change)
            except Exception:
                log.exception("parameter listener failed on %s", names)

    # -- loading -------------------------------------------------------------------

    def _load(
        self, stored_view: Mapping[str, float] | None, stored: Mapping[str, float] | None = None
    ) -> None:
        """Restore persisted values (refusing, with a warning, what no longer validates):
        params.json's, or ``stored`` -- what the pending write will put there."""
        cal = self._settings.calibration
        for name, v in cal.ardupilot_parameters().items():
            self._table.put(name, v)
        if stored_view is not None and set(CAL_PARAMS) <= set(stored_view):
            try:
                same = same_calibration(
                    Calibration.from_ardupilot_parameters(stored_view, cal.accel), cal, tol=1e-5
                )
            except ValueError:
                same = False
            if same:  # the values as the user set them (the calibration is in its own file)
                for n in CAL_PARAMS:
                    self._table.put(n, float(stored_view[n]))
                self._own_calibration = cal
        if stored is None:
            stored = self._stored()
        for name, v in (stored or {}).items():
            spec = self._table.spec(str(name))
            if spec is None or spec.group == "cal":
                log.warning("stored parameter %r unknown, ignored", name)
                continue
            out = self._table.set(spec.name, v)
            if out.accepted:
                self._user_set.add(spec.name)
            else:
                log.warning("stored %s = %r refused (%s)", name, v, out.reason)

    def _stored(self) -> dict[str, Any] | None:
        """params.json's values (None: no file, or one that cannot be read)."""
        if self._documents is None:
            return None
        try:
            loaded = self._documents.load(PARAMS_DOCUMENT)
        except Exception as e:  # an unreadable state dir must not stop the bridge
            log.warning("cannot read stored parameters: %s", e)
            return None
        for p in loaded.problems:
            log.warning("stored parameters: %s", p)
        doc = loaded.payload
        stored = doc.get("set") if isinstance(doc, dict) else None
        return stored if isinstance(stored, dict) else None

    def start(self, source: str = "start") -> None:
        """Apply every parameter to the engine (once, when the bridge starts)."""
        with self._lock:
            self._apply_all(source)
